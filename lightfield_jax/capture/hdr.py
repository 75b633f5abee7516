"""Exposure brackets to linear radiance: the camera's response and the HDR merge.

The light in a tank spans three to four decades (the direct light at the entry wall to
the multiple-scattered tail), more than one 8- or 16-bit exposure holds. A capture may
therefore give each shift (and each calibration frame) as a bracket of exposures with
times t_j (seconds); :func:`merge_bracket` turns a bracket into one linear image.

**Response.** A sample value z ∈ [0, 1] (integer codes scaled by their type's maximum)
is mapped to a linear exposure x = f⁻¹(z) (relative units) by the camera's inverse
response, per channel (:class:`Response`): ``linear`` (x = z, a raw converter's
linear output), ``srgb`` (the sRGB curve of most 8-bit camera files,
:func:`srgb_response`), a table from a file (:func:`load_response`), or ``auto``, recovered
from the brackets themselves (:func:`calibrate_response`) with OpenCV's Debevec–Malik
calibration (``cv2.createCalibrateDebevec``: the smooth g = ln f⁻¹ that makes
g(z_ij) − ln t_j agree between the exposures of every sample pixel, a linear least-
squares problem over 256 codes). OpenCV's calibration takes 8-bit images only: for
16-bit brackets the samples are rounded to 8 bits for the calibration and the curve is
interpolated at their full resolution. OpenCV picks its sample pixels at random (or on
a grid) from the frame, which in a mostly dark tank image lands mostly on black
pixels; here 256 pixels are chosen with their summed codes evenly spread over the range
they cover and handed to it as a 16×16 image on its grid, with a smoothness weight
λ = 50 (measured on 8-bit γ 2.2 brackets of such scenes: the curve is within 1-2 % of
the truth over codes 16-232 with λ = 50, within 10 % with OpenCV's default 10). The
curve is not supported near the top code (few samples, and the calibration's hat weight
vanishes there: 4-17 % off above code 240), so with an ``auto`` response samples above
``AUTO_CLIP`` = 0.9 count as clipped. An ``auto`` curve is normalised to x(0.5) = 1 and
x(0) = 0 (Debevec's log curve leaves the black code undetermined). The calibration
assumes z = f(E·t): light that scales with the exposure (ambient light is fine), no
black pedestal under the non-linear curve (cameras that write gamma-encoded files
subtract their black level before encoding). Measured with a pedestal of 2 % of full
scale under γ 2.2, the recovered curve is 10-30 % low over z 0.25-0.4 and the fit's g
0.025 low.

**Check.** Before the merge, :func:`exposure_ratio_problem` compares the exposures of
each bracket pairwise where both hold signal: their median linear ratio, over samples
chosen on the brighter exposure's value (never on the dimmer one's noise near its
floor), must be the ratio of their stated times within
:data:`EXPOSURE_RATIO_TOLERANCE` (files listed out of order, or wrong
``exposure_times``, are refused); then
:func:`exposure_mismatch_problem` compares them sample by sample: at most
:data:`EXPOSURE_MISMATCH_SHARE` of the samples compared may be off their median ratio
by more than :data:`EXPOSURE_MISMATCH_FACTOR` (an exposure of another shift, or a scene
that moved, is refused).

**Merge.** OpenCV's ``mergeDebevec``/``mergeRobertson`` weight samples by a hat
function of the code and take 8-bit input; neither drops a sample by how much light
it holds nor returns the merged noise. The merge here is the maximum-likelihood
estimate under shot noise, where x_j is Poisson in E·t_j: over the samples that are
valid (neither clipped nor near black),

    E = Σ_j (x_j − d_j) / Σ_j t_j,    Var E ∝ E / T,   T = Σ_j t_j (the effective exposure),

with d_j the dark frame's sample at the same exposure (a camera's black pedestal does
not scale with t, so it is subtracted before merging, never after). A sample is
**clipped** when z ≥ ``clip`` (default 0.98: sensors knee below their top code). Every
pixel merges its longest unclipped exposure (none: its shortest, flagged ``clipped``;
the capture masks it), and each shorter unclipped one unless it is **near black**:
judged on the signal that longest exposure predicts for it, s_j = (x_J − d_J)·t_j/t_J,
never on the sample itself (keeping the dim samples that read noise happened to lift
would bias a tank's far end and its black surround up, measured 17-1500× on a 16-bit
bracket): one code exceeds 5 % of that signal, f⁻¹(z + Δz) − f⁻¹(z) > 0.05·s_j at its
code z = f(s_j + d_j) (without a dark frame, for 8-bit γ 2.2 that is z < 0.17), or z <
0.005 (read noise). A pixel whose longest unclipped exposure is itself near black is
merged from that one sample (it is dark: the best there is). T goes to the joint fit's
weights (w ∝ √(T / (E + floor)) instead of 1/√(E + floor)).

OpenCV is imported inside :func:`calibrate_response`, so ``import lightfield_jax``
does not load it.
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lightfield_jax.capture.io import CaptureError, error_line, load_npy, require_capture_file
from lightfield_jax.files import atomic_write_text

RESPONSES = ("linear", "srgb", "auto")
CLIP = 0.98
AUTO_CLIP = 0.9
_SMOOTHNESS = 50.0
_NEAR_BLACK = 0.005
_MAX_QUANTISATION = 0.05
_CALIBRATION_PIXELS = 256


@dataclasses.dataclass(frozen=True, eq=False)
class Response:
    """The camera's inverse response x = f⁻¹(z), per channel.

    Attributes:
        kind: ``linear``, ``srgb``, ``auto`` (recovered from the brackets) or ``file``.
        codes: z at the table's nodes, increasing over [0, 1], shape (N,).
        curve: x at the nodes, shape (N, C) (C = 1: every channel alike), increasing.
        source: the file a ``file`` curve came from, else ``None``.
    """

    kind: str
    codes: np.ndarray
    curve: np.ndarray
    source: Path | None = None

    def linearize(self, z: np.ndarray) -> np.ndarray:
        """x = f⁻¹(z) for samples z (…, C) in [0, 1]."""
        z = np.asarray(z, np.float64)
        if self.kind == "linear":
            return z
        if self.kind == "srgb":
            return _srgb_decode(z)
        out = np.empty_like(z)
        for c in range(z.shape[-1]):
            column = self.curve[:, min(c, self.curve.shape[1] - 1)]
            out[..., c] = np.interp(z[..., c], self.codes, column)
        return out

    def encode(self, x: np.ndarray) -> np.ndarray:
        """z = f(x), the code of linear exposures x (…, C) (the inverse of
        :meth:`linearize`, clipped to [0, 1])."""
        x = np.asarray(x, np.float64)
        if self.kind == "linear":
            return np.clip(x, 0.0, 1.0)
        if self.kind == "srgb":
            return _srgb_encode(np.clip(x, 0.0, 1.0))
        out = np.empty_like(x)
        for c in range(x.shape[-1]):
            column = self.curve[:, min(c, self.curve.shape[1] - 1)]
            out[..., c] = np.interp(x[..., c], column, self.codes)
        return out

    def step(self, z: np.ndarray, levels: int | None) -> np.ndarray:
        """f⁻¹(z + Δz) − f⁻¹(z): the linear size of one code at z (0 for float samples,
        ``levels`` None)."""
        if levels is None:
            return np.zeros(np.shape(z))
        return self.linearize(np.minimum(z + 1.0 / (levels - 1), 1.0)) - self.linearize(z)

    def near_black(self, levels: int | None) -> np.ndarray:
        """Per channel, the code z below which a sample without a dark frame is near
        black (module docstring); ``levels``: the samples' number of codes (None: float)."""
        n = self.curve.shape[1]
        z = np.repeat(np.linspace(0.0, 1.0, 1025)[:, None], n, axis=1)
        with np.errstate(invalid="ignore"):
            coarse = ~(self.step(z, levels) <= _MAX_QUANTISATION * self.linearize(z))
        z = z[:, 0]
        out = np.empty(n)
        for c in range(n):
            bad = np.flatnonzero(coarse[: int(CLIP * 1024), c])
            out[c] = max(_NEAR_BLACK, z[bad[-1] + 1] if bad.size else 0.0)
        return out

    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "source": None if self.source is None else str(self.source),
            "codes": self.codes.tolist(),
            "curve": self.curve.T.tolist(),
        }


def linear_response() -> Response:
    return Response("linear", np.array([0.0, 1.0]), np.array([[0.0], [1.0]]))


def _srgb_decode(z: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.where(z <= 0.04045, z / 12.92, ((np.maximum(z, 0.04045) + 0.055) / 1.055) ** 2.4)


def _srgb_encode(x: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.where(
            x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 0.0031308) ** (1 / 2.4) - 0.055
        )


def srgb_response() -> Response:
    """The sRGB transfer curve (IEC 61966-2-1), which cameras, phones and image editors
    write into 8-bit files: x = z/12.92 for z ≤ 0.04045, else ((z + 0.055)/1.055)^2.4
    (evaluated exactly; the table, 1025 nodes, is what ``to_dict`` records)."""
    z = np.linspace(0.0, 1.0, 1025)
    return Response("srgb", z, _srgb_decode(z)[:, None])


def _header_names(text: str) -> list[str]:
    """The channel names of a table's ``# z, x_R, x_G, x_B`` header (:func:`write_response`)."""
    for line in text.splitlines():
        if line.lstrip().startswith("#"):
            words = line.lstrip("# \t").replace(",", " ").split()
            if words[:1] == ["z"] and all(w.startswith("x_") for w in words[1:]):
                return [w[2:] for w in words[1:]]
    return []


# A response table has at most one row per code of a 16-bit camera (65536 rows of a
# code and four columns: about 5 MB of text).
MAX_RESPONSE_BYTES = 1 << 24


def load_response(
    path: str | os.PathLike, n_channels: int, names: Sequence[str] | None = None
) -> Response:
    """A response table: a text file (CSV or whitespace, ``#`` comments) or ``.npy``
    array whose first column is z in [0, 1] (increasing, from 0 to 1) and whose other
    columns are x = f⁻¹(z), one column for every channel or one per channel,
    increasing (as :func:`write_response` writes them). Columns named in a header
    (``# z, x_R, x_G, x_B``) are taken by name: those of ``names``, the capture's
    channels (also one chosen with ``channel:``), in their order."""
    path = Path(path)
    # A FIFO would block the read forever, a folder or device is no table.
    require_capture_file(path, "a response table")
    size = os.path.getsize(path)
    if size > MAX_RESPONSE_BYTES:  # parsed as text, it would take ten times its size
        raise CaptureError(
            f"{path}: {size} bytes is too large for a response table (at most "
            f"{MAX_RESPONSE_BYTES}: one row per code of a 16-bit camera is about 5 MB)"
        )
    header: list[str] = []
    try:
        if path.suffix.lower() == ".npy":
            table = load_npy(path)  # its header checked against the memory first
            if table.dtype.kind not in "iuf":
                raise CaptureError(
                    f"{path}: a response table holds numbers, got an array of dtype {table.dtype}"
                )
        else:
            text = path.read_text()
            header = _header_names(text)
            with warnings.catch_warnings():  # "input contained no data": the shape says it
                warnings.simplefilter("ignore", UserWarning)
                table = np.loadtxt(text.replace(",", " ").splitlines(), ndmin=2)
    except (OSError, ValueError) as e:
        if isinstance(e, CaptureError):
            raise
        raise CaptureError(f"{path}: cannot read a response table ({error_line(e)})") from None
    table = np.asarray(table, np.float64)
    wanted = list(names or ())
    if wanted and table.ndim == 2 and len(header) == table.shape[1] - 1 > 1:
        # Columns named in the header are taken by name, in the capture's order.
        if not set(wanted) <= set(header):
            raise CaptureError(
                f"{path}: its header names the channels {', '.join(header)}, but the "
                f"capture's are {', '.join(wanted)}"
            )
        table = table[:, [0] + [1 + header.index(n) for n in wanted]]
    if table.ndim != 2 or table.shape[1] not in (2, n_channels + 1) or table.shape[0] < 2:
        raise CaptureError(
            f"{path}: a response table has rows (z, x) or (z, x per channel: {n_channels}), "
            f"got shape {table.shape}"
        )
    codes, curve = table[:, 0], table[:, 1:]
    if not np.all(np.isfinite(table)) or codes[0] != 0.0 or codes[-1] != 1.0:
        raise CaptureError(f"{path}: the first column (z) must run from 0 to 1, finite")
    if np.any(np.diff(codes) <= 0) or np.any(np.diff(curve, axis=0) < 0):
        raise CaptureError(f"{path}: z must increase and x must not decrease down the table")
    if np.any(curve[-1] <= curve[0]):
        raise CaptureError(f"{path}: x is constant down the table: not a response (x(1) > x(0))")
    return Response("file", codes, curve, path)


def write_response(path: str | os.PathLike, response: Response, names: Sequence[str]) -> Path:
    """Write a response table (CSV, header comment) that ``response: FILE`` reads."""
    curve = response.curve
    header = "# z, " + ", ".join(f"x_{n}" for n in names[: curve.shape[1]])
    rows = [
        ", ".join(f"{v:.8g}" for v in (z, *x)) for z, x in zip(response.codes, curve, strict=True)
    ]
    return atomic_write_text(path, "\n".join([header, *rows]) + "\n")


# ---------------------------------------------------------------------- calibration


def _calibration_pixels(samples: np.ndarray, clip: float) -> np.ndarray:
    """Indices of up to 256 pixels of a (J, N) channel whose summed codes spread evenly
    over their range, among the pixels neither black nor clipped in every exposure."""
    score = samples.sum(axis=0)
    usable = np.flatnonzero((samples.max(axis=0) > 0) & (samples.min(axis=0) < clip))
    if usable.size < 16:
        raise CaptureError(
            "auto: fewer than 16 pixels are lit and unclipped in some exposure; "
            "give response: linear or a response file"
        )
    order = usable[np.argsort(score[usable])]
    targets = np.linspace(score[order[0]], score[order[-1]], _CALIBRATION_PIXELS)
    picks = np.clip(np.searchsorted(score[order], targets), 0, order.size - 1)
    return order[np.unique(picks)]


def calibrate_response(
    brackets: np.ndarray, times: Sequence[float], clip: float = CLIP
) -> Response:
    """Recover the inverse response from brackets (J exposures of a scene, pooled over
    the shifts: (J, N, C) samples in [0, 1]) with OpenCV's Debevec calibration (module
    docstring); times in seconds."""
    import cv2

    j, _, n_channels = brackets.shape
    times32 = np.asarray(times, np.float32)
    codes = np.arange(256) / 255.0
    curve = np.empty((256, n_channels))
    calibrate = cv2.createCalibrateDebevec(_CALIBRATION_PIXELS, _SMOOTHNESS, False)
    side = int(math.isqrt(_CALIBRATION_PIXELS))
    for c in range(n_channels):
        z8 = np.rint(np.clip(brackets[..., c], 0.0, 1.0) * 255.0).astype(np.uint8)
        pick = _calibration_pixels(z8 / 255.0, clip)
        grid = np.resize(pick, side * side)  # the grid OpenCV samples, every cell a pick
        images = [np.repeat(z8[i, grid].reshape(side, side, 1), 3, axis=2) for i in range(j)]
        g = np.asarray(calibrate.process(images, times32), np.float64)[:, 0, 0]
        g = np.maximum.accumulate(g)  # a response never decreases
        g[0] = 0.0
        curve[:, c] = g / g[128]
    return Response("auto", codes, curve)


# ---------------------------------------------------------------------------- merge


@dataclasses.dataclass(frozen=True, eq=False)
class Merged:
    """One merged bracket (module docstring).

    Attributes:
        radiance: E (H, W, C), linear, in response units per second.
        exposure: T = Σ t_j over the valid samples (H, W, C), seconds (the longest
            unclipped exposure's time where no sample is valid).
        clipped: (H, W, C) True where every exposure is clipped.
        dark: (H, W, C) True where no sample is valid and E comes from one dark sample.
        clipped_samples, near_black_samples: (J, H, W, C) True where a sample was
            dropped as clipped, or as near black (and not clipped).
    """

    radiance: np.ndarray
    exposure: np.ndarray
    clipped: np.ndarray
    dark: np.ndarray
    clipped_samples: np.ndarray
    near_black_samples: np.ndarray


def merge_bracket(
    samples: np.ndarray,
    times: Sequence[float],
    response: Response,
    *,
    levels: int | None,
    dark: np.ndarray | None = None,
    clip: float = CLIP,
) -> Merged:
    """Merge a bracket (J, H, W, C) of samples in [0, 1], exposure times in seconds,
    into linear radiance (module docstring). ``dark``: the dark frame's bracket at the
    same times, (J, H, W, C) or (J, H, W, 1); ``levels``: the samples' code count
    (256, 65536) or ``None`` for float samples."""
    z = np.asarray(samples, np.float64)
    if response.kind == "auto":
        clip = min(clip, AUTO_CLIP)
    t = np.asarray(times, np.float64).reshape(-1, 1, 1, 1)
    # A NaN or Inf sample (or dark value) is no sample: read as 0, it would become the
    # pixel's reference where the longer exposures clipped, and the merge near 0.
    finite = np.isfinite(z)
    z = np.where(finite, z, 0.0)
    x = response.linearize(z)
    d = np.zeros_like(x)
    if dark is not None:
        dz = np.broadcast_to(np.asarray(dark, np.float64), z.shape)
        dark_finite = np.isfinite(dz)
        finite = finite & dark_finite
        d = response.linearize(np.where(dark_finite, dz, 0.0))
        x = x - d
    clipped = ~(z < clip) & finite
    unclipped = (z < clip) & finite
    # The reference of each pixel: its longest unclipped exposure (none: the shortest,
    # flagged clipped). It is always merged; the light it measured predicts each other
    # sample's signal, and a sample joins where that prediction resolves it.
    by_time = np.broadcast_to(t, z.shape)
    ref = np.argmax(np.where(unclipped, by_time, -np.inf), axis=0)
    none_ok = ~unclipped.any(axis=0)
    ref = np.where(none_ok, np.argmin(t[:, 0, 0, 0]), ref)
    ref_x = np.take_along_axis(x, ref[None], axis=0)[0]
    ref_t = t[:, 0, 0, 0][ref]
    # Near black, judged on the prediction (the sample's own value would select on its
    # noise: keeping only the dim samples that noise lifted biases the merge up): one
    # code more than 5 % of the predicted signal left after the dark frame, or a
    # predicted code below the read-noise floor.
    predicted = np.maximum(ref_x, 0.0)[None] * (t / ref_t[None])
    z_pred = response.encode(predicted + d)
    black = unclipped & (
        (z_pred < _NEAR_BLACK) | ~(response.step(z_pred, levels) <= _MAX_QUANTISATION * predicted)
    )
    is_ref = np.arange(len(t)).reshape(-1, 1, 1, 1) == ref[None]
    valid = (unclipped & ~black) | (is_ref & unclipped)
    total = np.sum(np.where(valid, t, 0.0), axis=0)
    merged = np.sum(np.where(valid, x, 0.0), axis=0)
    empty = total == 0  # every exposure clipped: the shortest one's value
    radiance = np.where(empty, ref_x / ref_t, merged / np.where(empty, 1.0, total))
    radiance = np.where(finite.any(axis=0), radiance, np.nan)  # no sample: masked as NaN
    ref_black = np.take_along_axis(black, ref[None], axis=0)[0]
    return Merged(
        radiance=radiance,
        exposure=np.where(empty, ref_t, total),
        clipped=none_ok & finite.any(axis=0),
        dark=ref_black & (total == ref_t) & ~none_ok,
        clipped_samples=clipped,
        near_black_samples=black,
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


@dataclasses.dataclass(frozen=True, eq=False)
class Brackets:
    """What merging a capture's exposure brackets did (``Capture.brackets``).

    Attributes:
        times: the exposure times t_j (seconds), shortest first as given.
        response: the inverse response used.
        clip: the sample value at or above which a sample counted as clipped.
        near_black: per channel, the value below which a sample counted as near black
            without a dark frame (with one: where one code exceeds 5 % of the signal).
        exposure: T (P, H, W, C) of every merged shift (seconds), whole frame.
        clipped: (H, W, C) True where every exposure of some shift is clipped.
        clipped_shifts: (P, H, W, C) the same per shift.
        clipped_fraction, near_black_fraction: (J, H, W): per exposure, the fraction of a
            pixel's samples (over shifts and channels) that were dropped as clipped or
            near black.
        dark_pixels: pixel values (shifts × pixels × channels) merged from one dark sample.
        files: the image files, one list per shift.
        dark_frame: whether a dark frame was subtracted (near black is then judged
            against the signal, not ``near_black``).
    """

    times: tuple[float, ...]
    response: Response
    clip: float
    near_black: tuple[float, ...]
    exposure: np.ndarray
    clipped: np.ndarray
    clipped_shifts: np.ndarray
    clipped_fraction: np.ndarray
    near_black_fraction: np.ndarray
    dark_pixels: int
    files: tuple[tuple[Path, ...], ...]
    dark_frame: bool = False

    def summary(self) -> str:
        j = len(self.times)
        threshold = (
            ""
            if self.dark_frame
            else f"; without a dark frame z < {', '.join(f'{v:.3g}' for v in self.near_black)}"
        )
        clipped = ", ".join(
            f"{t * 1e3:g} ms {100 * float(c.mean()):.1f}%/{100 * float(b.mean()):.1f}%"
            for t, c, b in zip(
                self.times, self.clipped_fraction, self.near_black_fraction, strict=True
            )
        )
        return (
            f"HDR: {len(self.files)} brackets of {j} exposures merged, "
            f"{self.response.kind} response; samples dropped as clipped (>= {self.clip:g}) / "
            "near black (one code over 5 % of the signal the longest unclipped exposure "
            f"predicts{threshold}), of the whole frame's samples (pixels outside the medium "
            f"are near black at every exposure): {clipped}; "
            f"{int(self.clipped_shifts.sum())} value(s) clipped in every exposure (masked; "
            f"{int(self.clipped.sum())} pixel(s)), "
            f"{self.dark_pixels} merged from one dark sample"
        )

    def to_dict(self) -> dict:
        return {
            "exposure_times": list(self.times),
            "response": self.response.to_dict(),
            "clip": self.clip,
            "near_black": list(self.near_black),
            "clipped_fraction": [float(c.mean()) for c in self.clipped_fraction],
            "near_black_fraction": [float(b.mean()) for b in self.near_black_fraction],
            "clipped_pixels": int(self.clipped.sum()),
            "clipped_values": int(self.clipped_shifts.sum()),
            "dark_pixels": self.dark_pixels,
            "dark_frame": self.dark_frame,
        }


def merge_capture(
    images: np.ndarray,
    times: Sequence[float],
    response: Response,
    *,
    levels: int | None,
    dark: np.ndarray | None = None,
    clip: float = CLIP,
    files: Sequence[Sequence[Path]] = (),
) -> tuple[np.ndarray, Brackets]:
    """Merge every shift's bracket: ``images`` (P, J, H, W, C) in [0, 1] → radiance
    (P, H, W, C) and the :class:`Brackets` record; ``dark`` (J, H, W, C or 1)."""
    merged = [
        merge_bracket(b, times, response, levels=levels, dark=dark, clip=clip) for b in images
    ]
    record = Brackets(
        times=tuple(float(t) for t in times),
        response=response,
        clip=min(clip, AUTO_CLIP) if response.kind == "auto" else clip,
        near_black=tuple(float(v) for v in response.near_black(levels)),
        exposure=np.stack([m.exposure for m in merged]).astype(np.float32),
        clipped=np.any([m.clipped for m in merged], axis=0),
        clipped_shifts=np.stack([m.clipped for m in merged]),
        clipped_fraction=np.mean([m.clipped_samples for m in merged], axis=(0, 4)),
        near_black_fraction=np.mean([m.near_black_samples for m in merged], axis=(0, 4)),
        dark_pixels=int(sum(m.dark.sum() for m in merged)),
        files=tuple(tuple(row) for row in files),
        dark_frame=dark is not None,
    )
    return np.stack([m.radiance for m in merged]), record


__all__ = [
    "AUTO_CLIP",
    "EXPOSURE_MISMATCH_FACTOR",
    "EXPOSURE_MISMATCH_SHARE",
    "EXPOSURE_RATIO_TOLERANCE",
    "Brackets",
    "CLIP",
    "RESPONSES",
    "Merged",
    "Response",
    "calibrate_response",
    "exposure_mismatch_problem",
    "exposure_ratio_problem",
    "linear_response",
    "srgb_response",
    "load_response",
    "merge_bracket",
    "merge_capture",
    "write_response",
]
