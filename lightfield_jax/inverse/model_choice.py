"""Plane or slab? ``geometry: {kind: auto, thickness: h, ...}`` (issue 7).

The plane model (the paper's) is cheap; the slab model is the tank. ``auto`` fits the
plane model first and keeps it only where its misfit to the capture is below the
capture's own noise, i.e. where no measurement could tell the two apart; otherwise it
fits the slab. The crossover, charted by ``experiments/plane_vs_slab.py`` over the
thickness in mean free paths σt·h, albedo and g, is what this rule reproduces per
capture.

The noise is measured from the images, independently of any model: the fourth
difference along the light's direction removes the smooth decay (the signal's
fourth derivative is ~σt⁴ times the signal) and leaves white noise with variance
70 σ² (1, −4, 6, −4, 1). Both the noise and the misfit are relative L2 norms over the
same pixels, ‖·‖/‖capture‖, so a plane fit that only misses the noise has a misfit
equal to the noise: the plane model's own error is e = √(misfit² − noise²), and the
plane is kept where e ≤ threshold × noise.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from lightfield_jax.inverse.noise import MIN_ALONG, five_point, stencil_centre
from lightfield_jax.scene.illumination import Stripes


@dataclasses.dataclass(frozen=True)
class GeometryChoice:
    """What ``geometry: auto`` decided, and on what evidence.

    Attributes:
        chosen: ``"plane"`` or ``"slab"``.
        plane_misfit: ‖plane fit − capture‖₂ / ‖capture‖₂ over the fitted region.
        noise: the capture's relative noise ‖noise‖₂ / ‖capture‖₂.
        plane_error: the plane model's own error √(max(misfit² − noise², 0)).
        threshold: the plane is kept when ``plane_error`` ≤ ``threshold`` · ``noise``.
    """

    chosen: str
    plane_misfit: float
    noise: float
    plane_error: float
    threshold: float = 1.0

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def relative_noise(images, pattern: Stripes, mask=None) -> float:
    """The capture's relative noise ‖noise‖₂ / ‖capture‖₂ (a float; ~1e-3 on
    noiseless renders of period-6 stripes: the signal's own fourth difference).

    ``images``: [P, H, W]; ``mask`` (H, W): the pixels to use (default: finite ones).
    """
    a = np.asarray(images, np.float64)
    if a.ndim != 3:
        raise ValueError(f"images: expected [P, H, W], got shape {a.shape}")
    axis = 2 if pattern.along_x else 1
    if a.shape[axis] < MIN_ALONG:
        raise ValueError(
            f"images: need at least {MIN_ALONG} pixels along the light to measure the noise, "
            f"got {a.shape[axis]}"
        )
    if mask is not None:
        a = np.where(np.asarray(mask, bool)[None], a, np.nan)
    finite = np.isfinite(a)
    d4, ok = five_point(np.where(finite, a, 0.0), finite, axis)
    centre = stencil_centre(a, axis)
    if ok.sum() < 16:
        raise ValueError("images: too few valid pixels to measure the noise")
    signal = np.sum(centre[ok] ** 2)
    if signal <= 0:
        raise ValueError("images: no signal to measure the noise against")
    return float(np.sqrt(np.sum(d4[ok] ** 2) / signal))


def choose(plane_misfit: float, noise: float, threshold: float = 1.0) -> GeometryChoice:
    """Keep the plane model iff its own error √(misfit² − noise²) is at most
    ``threshold`` × the noise."""
    error = math.sqrt(max(plane_misfit**2 - noise**2, 0.0))
    chosen = "plane" if error <= threshold * noise else "slab"
    return GeometryChoice(chosen, float(plane_misfit), float(noise), error, threshold)


def misfit(model, observed, mask=None) -> float:
    """‖model − observed‖₂ / ‖observed‖₂ over ``mask`` (finite pixels by default)."""
    m = np.asarray(model, np.float64)
    o = np.asarray(observed, np.float64)
    keep = np.isfinite(m) & np.isfinite(o)
    if mask is not None:
        keep &= np.broadcast_to(np.asarray(mask, bool), keep.shape)
    return float(np.sqrt(np.sum((m - o)[keep] ** 2) / np.sum(o[keep] ** 2)))


__all__ = ["GeometryChoice", "choose", "misfit", "relative_noise"]
