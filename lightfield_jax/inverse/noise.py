"""The capture's noise, measured from the 4th differences of its images along the light
(of a fit's residual where one is given), not from a model of the medium.

- The fourth difference along the light's direction removes the smooth decay and
  leaves white noise of variance 70 σ² (:func:`five_point`, :func:`stencil_centre`;
  :mod:`lightfield_jax.inverse.model_choice` uses them too). Divided by the fit's
  shot-noise scale √(I + floor), its mean square is the variance α of one weighted
  residual that noise alone would give (:func:`noise_scale`); the χ²/dof of
  :mod:`lightfield_jax.inverse.budget` is measured against it.
- The read-noise floor of the shot-noise weights, b/a of var(I) = a·I + b, is fitted
  to the same differences binned by intensity (:func:`noise_floor`).
"""

from __future__ import annotations

import math

import numpy as np

from lightfield_jax.inverse.lstsq import gram_inverse, scaled_lstsq
from lightfield_jax.scene.illumination import Stripes

# The fewest pixels along the light the noise's 4th differences are measured over (a
# fit needs them: inverse/data.py).
MIN_ALONG = 8


def stencil_centre(x: np.ndarray, axis: int) -> np.ndarray:
    """``x`` without two pixels at each end along ``axis``: the centres of the five-pixel
    stencils of :func:`five_point`."""
    sl = [slice(None)] * x.ndim
    sl[axis] = slice(2, x.shape[axis] - 2)
    return x[tuple(sl)]


def five_point(a: np.ndarray, w: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """The 4th differences of ``a`` along ``axis`` over √70 (the noise's standard
    deviation where the signal is smooth and the noise white) and where all five pixels
    of each have weight ``w > 0``."""
    d4 = np.diff(a, n=4, axis=axis) / math.sqrt(70.0)
    valid = np.ones(d4.shape, bool)
    sl = [slice(None)] * a.ndim
    for s in range(5):  # every one of the five pixels must be valid
        sl[axis] = slice(s, a.shape[axis] - 4 + s)
        valid &= w[tuple(sl)] > 0
    return d4, valid


def _fourth_differences(a: np.ndarray, w: np.ndarray, axis: int) -> np.ndarray | None:
    """The weighted 4th differences along ``axis`` squared, z² (each a χ²₁ times the
    noise's weighted variance where the signal is smooth), where all five pixels are
    valid; ``None`` where fewer than 16."""
    d4, valid = five_point(a, w, axis)
    z2 = (d4 * stencil_centre(w, axis))[valid] ** 2
    return z2 if z2.size >= 16 else None


# The fewest samples per intensity bin of :func:`noise_floor`, and the most bins.
FLOOR_SAMPLES = 64
FLOOR_BINS = 12
# Floors beyond this multiple of the peak make the weights uniform to 0.05 %: read
# noise alone (no growth of the variance with the signal seen).
FLOOR_UNIFORM = 1e3


def _clipped_mean(z2: np.ndarray) -> float:
    """The mean of χ²₁-like samples less outliers: a first scale from the median or,
    where most samples are (near) zero, the 90th percentile; then the mean of those
    below 1000×, then 50× the scale (χ²₁ exceeds 50 with chance 2e-12)."""
    scale = max(float(np.median(z2) / 0.45494), float(np.quantile(z2, 0.9) / 2.7055))
    for limit in (1000.0, 50.0):
        kept = z2[z2 <= limit * scale]
        if kept.size < 16:
            break
        scale = float(np.mean(kept))
    return scale


def noise_floor(images: np.ndarray, mask: np.ndarray, pattern: Stripes) -> float | None:
    """The capture's read-noise floor in image units: b/a of the variance model
    var(I) = a·I + b (shot noise ∝ I, read noise constant), fitted to the squared 4th
    differences along the light (each a χ²₁ times the variance where the signal is
    smooth: the noise dominates them at any photon count a camera gives) binned by the
    stencil's centre intensity (least squares over the bins; each term's error from the
    bins' scatter about the line or their own noise, √(2/n) of a mean of n χ²₁, the
    larger), each bin's mean less outliers (the entry wall's kink;
    :func:`_clipped_mean`; a mean, not a median: dark pixels counting 0 or 1 photon
    are not Gaussian). ``FLOOR_UNIFORM`` × the
    peak where the variance does not grow with the signal (read noise alone); ``None``
    where no read noise is seen (the intercept within 2σ of 0) or where it cannot be
    measured (fewer than two bins of :data:`FLOOR_SAMPLES`, fewer than
    :data:`MIN_ALONG` pixels along the light, or a degenerate fit)."""
    a = np.asarray(images, np.float64)
    axis = 2 if pattern.along_x else 1
    if a.shape[axis] < MIN_ALONG:
        return None
    valid_px = np.broadcast_to(np.asarray(mask, bool)[None], a.shape) & np.isfinite(a)
    d4, valid = five_point(np.where(valid_px, a, 0.0), valid_px.astype(float), axis)
    centre = stencil_centre(a, axis)[valid]
    z2 = d4[valid] ** 2
    n_bins = min(FLOOR_BINS, centre.size // FLOOR_SAMPLES)
    if n_bins < 2:
        return None
    order = np.argsort(centre)
    level, var, sd = [], [], []
    for part in np.array_split(order, n_bins):
        level.append(float(np.mean(centre[part])))
        var.append(_clipped_mean(z2[part]))
        sd.append(var[-1] * math.sqrt(2.0 / part.size))  # a mean of n χ²₁
    level, var, sd = np.array(level), np.array(var), np.array(sd)
    peak = float(np.max(np.where(valid_px, a, -np.inf)))
    design = np.stack([level, np.ones_like(level)], axis=1)
    slope, intercept = scaled_lstsq(design, var)  # the level's column: image units
    # Errors from the bins' scatter about the line or from their own noise, the larger.
    scatter = np.sum((var - design @ np.array([slope, intercept])) ** 2) / max(n_bins - 2, 1)
    noise = np.mean(sd**2)
    cov = gram_inverse(design, pseudo=True) * max(scatter, noise)
    err_slope, err_intercept = np.sqrt(np.diag(cov))
    # Each term only where the data show it (2σ): no read noise seen, the shot-noise
    # weights' own floor (None); no growth with the signal, uniform weights.
    if not (np.isfinite(slope) and np.isfinite(intercept) and err_intercept > 0):
        return None
    if not intercept > 2 * err_intercept:
        return None
    if not slope > 2 * err_slope:
        return FLOOR_UNIFORM * peak
    return float(min(intercept / slope, FLOOR_UNIFORM * peak))


def noise_scale(
    images: np.ndarray, weights: np.ndarray, pattern: Stripes, model: np.ndarray | None = None
) -> float:
    """α: the variance of one weighted residual w·(model − I) that the capture's noise
    gives, measured from 4th differences along the light (NaN where it cannot be
    measured: fewer than 16 pixels along the light).

    χ² compares the mean of (w·r)² with α, so α is a mean. Without ``model``: the
    median of the images' squared differences (that of χ²₁ is 0.4549 of its mean),
    robust to the signal's kinks (the entry wall) but low where pixels differ in
    weighted variance: shot noise is ∝ I while the weights floor at 1e-3 of the peak,
    so where dark pixels are many the median is theirs (a backward medium's capture:
    11× below the mean). With ``model`` (the fitted images, like ``images``): the
    differences of the residual I − model (the signal's curvature and kinks cancel),
    their mean less outliers (a median scale, the mean below 1000× it, the mean below
    50× that: χ²₁ exceeds 50 with chance 2e-12; the first scale is the 90th
    percentile's where that is larger, so that pixels counting no photon do not set
    it to 0); never below the images' median scale,
    which on a noiseless capture (float rounding only) keeps the signal's own 4th
    differences as the floor of what this probe can tell from noise."""
    a = np.asarray(images, np.float64)
    w = np.asarray(weights, np.float64)
    axis = 2 if pattern.along_x else 1
    if a.shape[axis] < MIN_ALONG:
        return math.nan
    z2 = _fourth_differences(a, w, axis)
    if z2 is None:
        return math.nan
    floor = float(np.median(z2) / 0.45494)
    if model is None:
        return floor
    z2 = _fourth_differences(a - np.asarray(model, np.float64), w, axis)
    if z2 is None:
        return floor
    # The first scale: the median's, or the 90th percentile's where more than half of the
    # differences are (near) zero, as in a photon-starved capture whose dark pixels
    # count 0 (their median alone put χ²/dof at 4e8 on a fit within 2 % of the truth).
    return max(_clipped_mean(z2), floor)


__all__ = [
    "FLOOR_BINS",
    "FLOOR_SAMPLES",
    "FLOOR_UNIFORM",
    "MIN_ALONG",
    "five_point",
    "noise_floor",
    "noise_scale",
    "stencil_centre",
]
