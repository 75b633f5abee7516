"""The stripes seen in a capture's images, through their Fourier coefficient across the
light at the projector's frequency: the transverse axis, the phase line along the light
(its slope is the light's direction), the stripes' measured period and lit width. The
method is :mod:`lightfield_jax.capture.detect`'s "Orientation", "Direction", "Period"
and "Lit width"."""

from __future__ import annotations

import math

import numpy as np

from lightfield_jax.capture.detect_roi import (
    mad_sigma,
)
from lightfield_jax.scene.illumination import check_direction

ACROSS = {"left": "rows", "right": "rows", "top": "columns", "bottom": "columns"}


def across_first(a: np.ndarray, entry: str) -> np.ndarray:
    """(..., H, W) → (..., across, along): the axis along the entry wall first."""
    return a if ACROSS[entry] == "rows" else np.swapaxes(a, -1, -2)


def stripe_coefficients(a: np.ndarray, u0: int, frequency: float) -> np.ndarray:
    """Hann-windowed Fourier coefficient at ``frequency`` across axis −2 of a
    (P, across, along) stack whose first across pixel is u0: (P, along)."""
    return _spectrum(a, u0, np.array([frequency]), lambda c: c)[0]


# Frequencies per matrix product in _spectrum: bounds its (F, P, along) block.
_SPECTRUM_CHUNK = 32


def _spectrum(a: np.ndarray, u0: int, frequencies: np.ndarray, reduce) -> np.ndarray:
    """``reduce`` of the Hann-windowed Fourier coefficients (F, P, along) at each of
    ``frequencies`` across axis −2 of a (P, across, along) stack whose first across
    pixel is u0, stacked over the frequencies: one matrix product per block of
    frequencies, not a pass over the stack per frequency."""
    n = a.shape[-2]
    w = np.hanning(n + 2)[1:-1]
    u = u0 + np.arange(n) + 0.5
    mean = np.einsum("u,puj->pj", w, a) / w.sum()
    p, _, along = a.shape
    # (across, P·along), windowed: real matrix products with the cosines and sines.
    centred = (w[:, None] * np.moveaxis(a - mean[:, None, :], 1, 0).reshape(n, -1)).astype(float)
    out = []
    for i in range(0, len(frequencies), _SPECTRUM_CHUNK):
        f = np.asarray(frequencies[i : i + _SPECTRUM_CHUNK], float)
        phase = 2 * np.pi * f[:, None] * u  # (F, across)
        c = (np.cos(phase) @ centred) - 1j * (np.sin(phase) @ centred)
        out.append(reduce(c.reshape(len(f), p, along)))
    return np.concatenate(out)


# Stripe contrast of an image: its Fourier amplitude across the stripes at the period
# against that at 1.5 times it (not a harmonic of the stripes: noise alone gives about
# 1, a 24-row crop of rendered stripes about 4, the window's leakage included). Images
# whose median contrast reaches STRIPED have stripes.
STRIPED = 2.5


# A given period contradicts the images where their stripes' strongest period differs
# from it by more than PERIOD_OFF and the given one's stripe amplitude is below
# PERIOD_WEAK of that one's (a stripe pattern's harmonics are weaker than its
# fundamental: a half or a double period has little amplitude; a small capture cannot
# tell 6 from 8 px apart better than 0.47, measured on 24 rows).
PERIOD_OFF, PERIOD_WEAK = 0.1, 0.6


def other_period(stack: np.ndarray, u0: int, period: float) -> float | None:
    """The period (px) of the clear stripes of a (P, across, along) stack
    (:func:`across_first`, first across pixel u0) where it contradicts the given
    ``period`` (see PERIOD_OFF), searched between 2 px and a third of the wall;
    ``None`` where it does not, or where no stripes are clear."""
    n = stack.shape[-2]
    longest = n / 3.0
    if longest <= 2.0:
        return None

    def amplitude(p):
        return np.abs(stripe_coefficients(stack, u0, 1.0 / p)).sum(axis=-1)

    frequencies = np.linspace(1.0 / longest, 0.5, 400)
    periods = 1.0 / frequencies
    power = np.median(_spectrum(stack, u0, frequencies, lambda c: np.abs(c).sum(axis=-1)), 1)
    best = float(periods[int(np.argmax(power))])
    with np.errstate(divide="ignore", invalid="ignore"):
        seen = np.median(amplitude(best) / amplitude(1.5 * best)) >= STRIPED
        weak = np.median(amplitude(period)) < PERIOD_WEAK * np.max(power)
    return best if seen and weak and abs(best / period - 1.0) > PERIOD_OFF else None


def period_contradiction(stack: np.ndarray, u0: int, period: int, entry: str) -> str | None:
    """What to say of a given stripe ``period`` the stack's clear stripes contradict
    (:func:`other_period`), after its key (``pattern.period``); ``None`` where they do
    not. The capture file's check and ``fit_images``' say it alike."""
    best = other_period(stack, u0, period)
    if best is None:
        return None
    return (
        f"{period} contradicts the images, whose stripes repeat every {best:.2f} px across "
        f"the {entry} wall (measured); correct it"
    )


def stripe_power(a: np.ndarray, u0: int, period: float) -> float:
    return float(np.sum(np.abs(stripe_coefficients(a, u0, 1.0 / period)) ** 2))


def measured_period(a: np.ndarray, u0: int, period: int) -> float:
    freqs = np.linspace(1.0 / (1.5 * period), 1.5 / period, 301)
    power = _spectrum(a, u0, freqs, lambda c: np.sum(np.abs(c) ** 2, axis=(1, 2)))
    return float(1.0 / freqs[int(np.argmax(power))])


def phase_line(c: np.ndarray, x: np.ndarray, slope: float | None):
    """Common slope k and per-image intercepts α_p of arg c_p(x) ≈ α_p + k·x, weights
    |c|²; returns (k, stderr of k, α_p, fraction of lines kept)."""
    weight = np.abs(c) ** 2
    keep = weight > 1e-6 * weight.max()
    fixed = slope is not None
    if not fixed:
        z = np.sum(c[:, 1:] * np.conj(c[:, :-1]))
        slope = float(np.angle(z))
    stderr = 0.0
    for _ in range(3):
        detrended = c * np.exp(-1j * slope * x)[None]
        alpha = np.angle(np.sum(np.where(keep, detrended, 0.0), axis=1))
        resid = np.angle(detrended * np.exp(-1j * alpha)[:, None])
        if fixed:
            break
        w = np.where(keep, weight, 0.0)
        sw = w.sum(axis=1, keepdims=True)
        xm = (w * x).sum(axis=1, keepdims=True) / np.where(sw > 0, sw, 1.0)
        dx = x[None] - xm
        den = float(np.sum(w * dx**2))
        if den <= 0:
            raise ValueError("detect_geometry: the stripes are not visible along the light")
        delta = float(np.sum(w * dx * resid)) / den
        slope += delta
        e = (resid - delta * dx) * np.sqrt(w)
        n, p = int(keep.sum()), c.shape[0] + 1
        s2 = float(np.sum(np.where(keep, e, 0.0) ** 2)) / max(n - p, 1)
        stderr = math.sqrt(s2 / den)
        scatter = mad_sigma(e[keep])
        if scatter > 0:
            keep = keep & (np.abs(e) <= 4.0 * scatter)
    detrended = c * np.exp(-1j * slope * x)[None]
    alpha = np.angle(np.sum(np.where(keep, detrended, 0.0), axis=1))
    total = (weight > 1e-6 * weight.max()).sum()
    return slope, stderr, alpha, float(keep.sum()) / max(int(total), 1)


def direction_from_slope(entry: str, t: float) -> float:
    a = math.degrees(math.atan(t))
    return {"left": a, "right": 180.0 + a, "top": 90.0 - a, "bottom": 270.0 - a}[entry]


def slope_from_direction(entry: str, direction_deg: float) -> float:
    t = math.radians(direction_deg)
    if ACROSS[entry] == "rows":
        return math.tan(t)
    return math.cos(t) / math.sin(t)


def measured_lit(stack: np.ndarray, entry: str, period: int) -> float:
    """Lit width of the stripes along the wall (pixels per period), measured on the
    lines along the light next to the entry wall, where the direct light keeps the
    projector's sharp stripes: the fraction of pixels above the midpoint of the local
    extremes over one period (a sliding window, so a slow variation along the wall
    does not count), times the period. The line at the wall itself is skipped where
    there are enough (it may be cut by the wall's edge)."""
    if entry in ("right", "bottom"):
        stack = stack[..., ::-1]
    n = stack.shape[-1]
    lines = stack[..., 1:4] if n >= 8 else stack[..., : max(1, n // 2)]
    lines = np.moveaxis(lines, -2, -1)  # (P, lines, across)
    if lines.shape[-1] < 2 * period + 1:
        return math.nan
    window = np.lib.stride_tricks.sliding_window_view(lines, period + 1, axis=-1)
    middle = 0.5 * (window.max(axis=-1) + window.min(axis=-1))
    h = period // 2
    centre = lines[..., h : h + middle.shape[-1]]
    spread = window.max(axis=-1) - window.min(axis=-1)
    counted = spread > 0
    if not counted.any():
        return math.nan
    return float(np.mean((centre > middle)[counted]) * period)


def points_in(entry: str, direction_deg: float) -> bool:
    try:
        check_direction(entry, direction_deg, "pattern")
    except ValueError:
        return False
    return True


__all__ = [
    "ACROSS",
    "STRIPED",
    "across_first",
    "direction_from_slope",
    "measured_lit",
    "measured_period",
    "other_period",
    "period_contradiction",
    "phase_line",
    "points_in",
    "slope_from_direction",
    "stripe_coefficients",
    "stripe_power",
]
