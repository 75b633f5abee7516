"""The checks of an exposure bracket before its merge (:mod:`lightfield_jax.capture.hdr`).

Before the merge, :func:`exposure_ratio_problem` compares the exposures of
each bracket pairwise where both hold signal: their median linear ratio, over samples
chosen on the brighter exposure's value (never on the dimmer one's noise near its
floor), must be the ratio of their stated times within
:data:`EXPOSURE_RATIO_TOLERANCE` (files listed out of order, or wrong
``exposure_times``, are refused); then
:func:`exposure_mismatch_problem` compares them sample by sample: at most
:data:`EXPOSURE_MISMATCH_SHARE` of the samples compared may be off their median ratio
by more than :data:`EXPOSURE_MISMATCH_FACTOR` (an exposure of another shift, or a scene
that moved, is refused).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from lightfield_jax.capture.response import (
    AUTO_CLIP,
    CLIP,
    Response,
)

# Two exposures of a bracket whose median ratio (below) differs from the ratio of their
# stated times by more than this factor (either way) are refused: their files are
# listed out of order, or exposure_times are wrong. Real brackets stay well inside it:
# a shutter's timing error (a few %, ~10-20 % at 1/4000 s), a response curve's error
# (auto: 1-2 %; a 2 % black pedestal under γ 2.2: 10-30 % over part of the codes),
# quantisation and noise, which a median over the pixels mostly removes. The slips it is
# there for are far outside: two exposures swapped invert the ratio (a third of a stop
# apart: 1.26² = 1.59; one stop: 4), and times one stop off are 2.
#
# The median (exposure_ratios), per pair: first a rough ratio r, the median over the
# samples well exposed and at least _AGREEMENT_FLOOR of full scale after the dark frame
# in both (the pixel-by-pixel check's choice; fewer than _MIN_RATIO_SAMPLES: the pair is
# not judged); r says which exposure is the brighter. Then the median of dimmer/brighter
# over samples chosen on the brighter one's value alone: at least _AGREEMENT_FLOOR,
# unclipped, and predicting (÷ r) at least the well-exposed floor's signal in the dimmer
# one (at most _AGREEMENT_FLOOR), the dimmer one unclipped whatever it reads. Samples
# chosen on the dimmer one's own value near its floor are those its noise lifted, and
# their median is low: on a pair 16-64x apart that shares little light (the long one
# clips where the short one holds signal), with a pedestal and read noise, 10-27 for a
# stated 16-64, though noise is small (2000 photo-electrons at full scale).
# Measured on brackets from simulated six-shift stripe captures (128x96: the paper's
# milk, sigma_t 0.2051, sigma_s 0.0366, g 0.4 per px, and the milk two and four times
# as dense), 1/8/64 ms, 1/4/16 ms, four exposures 2x apart and 10/40 ms, the shortest
# exposure's peak at 0.5 and 1.5 of full scale, Poisson noise of 300, 1000, 2000 and
# 20000 photo-electrons at full scale with read noise 0.0005, 8- and 16-bit linear,
# without a pedestal and with a 2 % one and its dark level, two noise draws: 4608
# brackets.
#   Brackets as taken: none refused; the worst pair 1.11x off its times at 300
#     photo-electrons, 1.06x at 1000, 1.04x at 2000, 1.01x at 20000. Chosen on each
#     exposure's own value (well exposed in both), 1097 of them are refused (1089 of
#     the 1152 16-bit ones with a pedestal; 525 of their 576 at 2000 photo-electrons
#     or more).
#   Two neighbouring files swapped, or one time 2x, 0.5x or 4x off (36864): every one
#     with a pair judged that holds the changed exposure is refused (35116); the other
#     1748, all in the denser milks, are not judged (the changed exposure shares under
#     _MIN_RATIO_SAMPLES samples of signal with every other).
EXPOSURE_RATIO_TOLERANCE = 1.5


# The fewest well-exposed samples (pixels x channels) a pair of exposures is judged on.
_MIN_RATIO_SAMPLES = 50


# Well exposed: a sample at least this far above 0 (and above the response's near-black
# code, module docstring), below the clip, with signal left after the dark frame.
_WELL_EXPOSED = 0.02


def exposure_ratio_problem(
    samples: np.ndarray,
    times: Sequence[float],
    response: Response,
    *,
    levels: int | None,
    dark: np.ndarray | None = None,
    clip: float = CLIP,
) -> tuple[int, int, float, float] | None:
    """Whether a bracket's exposures (J, H, W, C; samples in [0, 1]) scale as their
    ``times`` say: for each pair of exposures (j < k, nearest first) with at least
    ``_MIN_RATIO_SAMPLES`` samples that hold signal in both, the median ratio of their
    linear, dark-subtracted values (over samples chosen on the brighter exposure's
    value: the comment above :data:`EXPOSURE_RATIO_TOLERANCE`) against t_k / t_j.
    Returns the first pair off by more than :data:`EXPOSURE_RATIO_TOLERANCE`,
    ``(j, k, measured, stated)``, else ``None``."""
    return ratio_problem_of(
        pair_statistics(samples, times, response, levels=levels, dark=dark, clip=clip)
    )


def ratio_within(measured: float, stated: float) -> bool:
    """Whether a pair's median ratio is its times' within :data:`EXPOSURE_RATIO_TOLERANCE`."""
    return 1.0 / EXPOSURE_RATIO_TOLERANCE <= measured / stated <= EXPOSURE_RATIO_TOLERANCE


def ratio_problem_of(stats) -> tuple[int, int, float, float] | None:
    """:func:`exposure_ratio_problem` of a bracket's :func:`pair_statistics`."""
    return next(
        ((j, k, m, s) for j, k, m, s, _, _ in stats if m is not None and not ratio_within(m, s)),
        None,
    )


def exposure_ratios(
    samples: np.ndarray,
    times: Sequence[float],
    response: Response,
    *,
    levels: int | None,
    dark: np.ndarray | None = None,
    clip: float = CLIP,
):
    """``(j, k, measured, stated)`` for each pair of a bracket's exposures (nearest
    first) with enough samples that hold signal in both (:func:`exposure_ratio_problem`)."""
    stats = pair_statistics(samples, times, response, levels=levels, dark=dark, clip=clip)
    return [(j, k, m, s) for j, k, m, s, _, _ in stats if m is not None]


def pair_statistics(
    samples: np.ndarray,
    times: Sequence[float],
    response: Response,
    *,
    levels: int | None,
    dark: np.ndarray | None = None,
    clip: float = CLIP,
    pairs: Sequence[tuple[int, int]] | None = None,
    offset: float = 0.0,
) -> list[tuple[int, int, float | None, float, float | None, int]]:
    """Both checks' figures of a bracket's pairs of exposures (``pairs``, default every
    pair, nearest first), from one linearisation and one median ratio per pair:
    ``(j, k, measured, stated, share, compared)``, ``measured`` the median ratio x_k/x_j
    (:func:`_pair_ratio`; ``None`` where too few samples hold signal in both),
    ``stated`` t_k/t_j, ``share`` of the ``compared`` samples off that ratio (or the
    stated one, where none was measured) by more than :data:`EXPOSURE_MISMATCH_FACTOR`
    (``None`` where fewer than ``_MIN_RATIO_SAMPLES`` are compared: the comment above
    :data:`EXPOSURE_MISMATCH_SHARE`); ``offset``: a constant taken from every linear
    value first (:func:`bracket_offset`)."""
    signal = _signal_samples(samples, response, levels, dark, clip, offset)
    x, good, top, finite, full = signal
    low = _AGREEMENT_FLOOR * full
    tiny = 1e-6 * full  # a sample at or below its dark value: far off any prediction
    stats = []
    for j, k in _pairs(len(times)) if pairs is None else pairs:
        stated = float(times[k]) / float(times[j])
        measured = _pair_ratio(signal, response, levels, j, k)
        valid = measured is not None and math.isfinite(measured) and measured > 0
        ratio = measured if valid else stated
        to_k, to_j = x[j] * ratio, x[k] / ratio
        compared = (good[j] & finite[k] & (to_k >= low) & (to_k <= top[k])) | (
            good[k] & finite[j] & (to_j >= low) & (to_j <= top[j])
        )
        count = int(compared.sum())
        share = None
        if count >= _MIN_RATIO_SAMPLES:
            xj = np.maximum(x[j], tiny)[compared]
            xk = np.maximum(x[k], tiny)[compared]
            off = np.abs(np.log(xk / (ratio * xj))) > math.log(EXPOSURE_MISMATCH_FACTOR)
            share = float(off.mean())
        stats.append((j, k, measured, stated, share, count))
    return stats


def _pair_ratio(signal, response: Response, levels, j: int, k: int) -> float | None:
    """The median ratio x_k/x_j of two exposures (``signal``: :func:`_signal_samples`),
    unbiased by noise: a rough ratio over the samples with signal in both, then the
    median of dimmer/brighter over samples chosen on the brighter exposure's value
    alone, so that the dimmer one's noise near its floor does not choose them (the
    brighter one is never near 0, the dimmer one may read 0 or less); ``None`` where
    fewer than ``_MIN_RATIO_SAMPLES`` samples serve either step."""
    x, good, top, finite, full = signal
    rough = _median_ratio(x, good, j, k)
    if rough is None:
        return None
    floor = response.linearize(np.maximum(response.near_black(levels), _WELL_EXPOSED)[None])[0]
    floor = np.minimum(floor, _AGREEMENT_FLOOR * full)
    a, b, r = (k, j, rough) if rough >= 1 else (j, k, 1 / rough)
    chosen = good[a] & finite[b] & (x[b] < top[b]) & (x[a] >= floor * r)
    if chosen.sum() < _MIN_RATIO_SAMPLES:
        return None
    q = float(np.median(x[b][chosen] / x[a][chosen]))
    if a == j:
        return q
    return 1 / q if q > 0 else math.inf


def _pairs(n: int) -> list[tuple[int, int]]:
    """Every pair (j < k) of n exposures, nearest first."""
    return sorted(((j, k) for j in range(n) for k in range(j + 1, n)), key=lambda p: p[1] - p[0])


def _well_exposed(samples, response: Response, levels, dark, clip):
    """A bracket's linear, dark-subtracted values and where they are well exposed
    (:func:`exposure_ratio_problem`)."""
    x, well, _, _ = _linear_samples(samples, response, levels, dark, clip)
    return x, well


def _linear_samples(samples, response: Response, levels, dark, clip, offset=0.0):
    """``(x, well, top, finite)``: a bracket's linear, dark-subtracted values (less
    ``offset``, in linear units), where they are well exposed, the value a clipped
    sample reads as (the clip's, less the dark frame's and ``offset``), and where the
    sample and its dark value are finite."""
    z = np.asarray(samples, np.float64)
    if response.kind == "auto":
        clip = min(clip, AUTO_CLIP)
    finite = np.isfinite(z)
    z = np.where(finite, z, np.nan)
    top = response.linearize(np.full((1, z.shape[-1]), clip))[0]
    with np.errstate(invalid="ignore"):
        x = response.linearize(np.where(finite, z, 0.0))
        if dark is not None:
            dz = np.broadcast_to(np.asarray(dark, np.float64), z.shape)
            finite = finite & np.isfinite(dz)
            d = response.linearize(np.where(np.isfinite(dz), dz, 0.0))
            x = x - d
            top = top - d
        x, top = x - offset, top - offset
        floor = np.maximum(response.near_black(levels), _WELL_EXPOSED)
        well = (z >= floor) & (z < clip) & (x > 0)
    return x, well, np.broadcast_to(top, z.shape), finite


def _signal_samples(samples, response: Response, levels, dark, clip, offset=0.0):
    """``(x, good, top, finite, full)`` as :func:`_linear_samples`, with ``good`` where a
    sample is well exposed and at least ``_AGREEMENT_FLOOR`` of full scale (``full``, the
    linear value of the top code, per channel) after the dark frame, where shot noise
    stays small."""
    x, well, top, finite = _linear_samples(samples, response, levels, dark, clip, offset)
    full = response.linearize(np.ones((1, x.shape[-1])))[0]
    return x, well & (x >= _AGREEMENT_FLOOR * full), top, finite, full


def _median_ratio(x, good, j, k) -> float | None:
    """The median of x_k/x_j over the samples ``good`` in both exposures; ``None`` where
    fewer than ``_MIN_RATIO_SAMPLES`` are."""
    both = good[j] & good[k]
    if both.sum() < _MIN_RATIO_SAMPLES:
        return None
    return float(np.median(x[k][both] / x[j][both]))


# Two exposures of one bracket must also agree pixel by pixel: an exposure of another
# shift (its stripes elsewhere, its brightness right for its time) can pass the median
# check above, and the merge mixes two stripe patterns into one image. Compared: every
# sample whose value in one exposure is well exposed and at least _AGREEMENT_FLOOR of
# full scale after the dark frame (where shot noise stays small), where it predicts the
# other exposure's value (times their measured ratio, _pair_ratio) between that floor
# and the clip; a
# sample the other exposure clipped, or left at or below its dark value, counts as its
# value reads. At most EXPOSURE_MISMATCH_SHARE of them may differ from the median ratio
# by more than EXPOSURE_MISMATCH_FACTOR. Measured, the share in the worst pair of each
# bracket, on brackets written from simulated six-shift stripe captures (64x48: the
# paper's milk, sigma_t 0.2051, sigma_s 0.0366, g 0.4 per px, also at 128x96; the milk
# two and four times as dense; sigma_t 0.1, sigma_s 0.05, g 0.3; sigma_t 0.03; sigma_t
# 0.6, sigma_s 0.5, g 0.7), 1/8/64 ms, 1/4/16 ms, four exposures 2x apart and 10/40 ms,
# Poisson noise of 300, 1000, 2000 and 20000 photo-electrons at full scale with read
# noise, 8-bit linear with a 2 % pedestal and dark frames, 16-bit linear with and
# without, 8-bit srgb and auto (gamma 2.2), a gamma 2.2 table for 16 bits, the shortest
# exposure's peak at 0.5 and 1.5 of full scale, two noise draws each:
#   brackets of one scene: 0 with 2000 photo-electrons or more, at most 0.020 with
#     1000, at most 0.10 with 300 (these with the ratio over samples with signal in
#     both, or the stated one; by _pair_ratio's ratio, the one used, two 8-bit RGB exposures
#     16x apart at 300 of a scene over three decades: at most 0.023, where the ratio
#     over both's samples gives 0.18-0.20); the test suite's brackets (tests/test_hdr.py,
#     tests/test_hostile.py): 0. Above the threshold only the brackets of one auto curve
#     recovered from two 8-bit exposures of sigma_t 0.03, most samples clipped (1.3-1.8x
#     off over the top codes, so their merge is off too): 0.27-0.34;
#   one exposure from the next shift, where it moves more than 5 % of the merged pixels
#     by 10 %: at least 0.32 for the milk (0.33 at 128x96), 0.31 for sigma_t 0.1, 0.24
#     for sigma_t 0.03; the milk twice as dense: 530 of 551 refused, 17 with under
#     _MIN_RATIO_SAMPLES to compare (not judged), 4 passed (auto, the 1 ms exposure of
#     1/8/64 ms, whose pair with the 8 ms one is not judged). Four times as dense, at
#     64x48, 73 of 539 are not judged and 23 pass (16 of them refused by the median
#     check); at sigma_t 0.6, sigma_s 0.5, g 0.7 the stripes are under 2x apart but at
#     the entry wall, and every swap passes (0-0.13; up to 68 % of its merged pixels
#     10 % off).
EXPOSURE_MISMATCH_FACTOR = 2.0


EXPOSURE_MISMATCH_SHARE = 0.2


_AGREEMENT_FLOOR = 0.05


def exposure_mismatch_problem(
    samples: np.ndarray,
    times: Sequence[float],
    response: Response,
    *,
    levels: int | None,
    dark: np.ndarray | None = None,
    clip: float = CLIP,
) -> tuple[int, int, float, int] | None:
    """Whether a bracket's exposures (J, H, W, C; samples in [0, 1]) agree pixel by
    pixel (the comment above :data:`EXPOSURE_MISMATCH_SHARE`): for each pair of
    exposures (j < k, nearest first) with at least ``_MIN_RATIO_SAMPLES`` samples to
    compare, the share that differ from their median ratio by more than
    :data:`EXPOSURE_MISMATCH_FACTOR`. Returns the first pair whose share exceeds
    :data:`EXPOSURE_MISMATCH_SHARE`, ``(j, k, share, compared)``, else ``None``."""
    return mismatch_problem_of(
        pair_statistics(samples, times, response, levels=levels, dark=dark, clip=clip)
    )


def mismatch_problem_of(stats) -> tuple[int, int, float, int] | None:
    """:func:`exposure_mismatch_problem` of a bracket's :func:`pair_statistics`."""
    return next(
        (
            (j, k, share, n)
            for j, k, _, _, share, n in stats
            if share is not None and share > EXPOSURE_MISMATCH_SHARE
        ),
        None,
    )


def exposure_mismatches(
    samples: np.ndarray,
    times: Sequence[float],
    response: Response,
    *,
    levels: int | None,
    dark: np.ndarray | None = None,
    clip: float = CLIP,
    pairs: Sequence[tuple[int, int]] | None = None,
    offset: float = 0.0,
):
    """``(j, k, share, compared)`` for each pair of a bracket's exposures (``pairs``,
    default every pair, nearest first) that has enough samples to compare
    (:func:`exposure_mismatch_problem`, :func:`pair_statistics`)."""
    stats = pair_statistics(
        samples, times, response, levels=levels, dark=dark, clip=clip, pairs=pairs, offset=offset
    )
    return [(j, k, share, n) for j, k, _, _, share, n in stats if share is not None]


def bracket_offset(
    samples: np.ndarray,
    times: Sequence[float],
    response: Response,
    pair: tuple[int, int],
    *,
    levels: int | None,
    dark: np.ndarray | None = None,
    clip: float = CLIP,
) -> float:
    """The constant p in every linear sample (x_j = t_j·L + p: a camera pedestal left
    in, p > 0, or a dark level that subtracts too much, p < 0) with which the two
    exposures of ``pair`` that :func:`exposure_ratio_problem` found off do scale as
    their times say: the straight line x_k = a·x_j + p·(1 − a) through their
    well-exposed samples has its slope a within 15 % of t_k/t_j. NaN where no such
    constant explains them (a wrong order or wrong times)."""
    x, well = _well_exposed(samples, response, levels, dark, clip)
    j, k = pair
    both = well[j] & well[k]
    if both.sum() < _MIN_RATIO_SAMPLES:
        return math.nan
    xj, xk = x[j][both], x[k][both]
    if not np.ptp(xj) > 0:
        return math.nan
    a, b = np.polyfit(xj, xk, 1)
    stated = float(times[k]) / float(times[j])
    if not (abs(a / stated - 1) <= 0.15 and abs(1 - a) > 1e-6):
        return math.nan
    return float(b / (1 - a))


__all__ = [
    "EXPOSURE_MISMATCH_FACTOR",
    "EXPOSURE_MISMATCH_SHARE",
    "EXPOSURE_RATIO_TOLERANCE",
    "exposure_mismatch_problem",
    "exposure_ratio_problem",
]
