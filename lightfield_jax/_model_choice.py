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
70 σ² (1, −4, 6, −4, 1); divided by the local signal it gives the relative noise.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ._illumination import Stripes


@dataclasses.dataclass(frozen=True)
class GeometryChoice:
    """What ``geometry: auto`` decided, and on what evidence.

    Attributes:
        chosen: ``"plane"`` or ``"slab"``.
        plane_misfit: ‖plane fit − capture‖₂ / ‖capture‖₂ over the fitted region.
        noise: the capture's relative per-pixel noise ε (std / signal).
        threshold: the plane is kept when ``plane_misfit`` ≤ ``threshold`` · ``noise``.
    """

    chosen: str
    plane_misfit: float
    noise: float
    threshold: float = 1.0

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def relative_noise(images, pattern: Stripes, floor_fraction: float = 0.1) -> float:
    """The capture's relative per-pixel noise ε = std/signal, a robust median over the
    pixels brighter than ``floor_fraction`` of the brightest (float; ~1e-5 and below
    on noiseless renders).

    ``images``: [P, H, W] (NaN where masked).
    """
    a = np.asarray(images, np.float64)
    if a.ndim != 3:
        raise ValueError(f"images: expected [P, H, W], got shape {a.shape}")
    axis = 2 if pattern.entry in ("left", "right") else 1
    if a.shape[axis] < 8:
        raise ValueError(
            f"images: need at least 8 pixels along the light to measure the noise, "
            f"got {a.shape[axis]}"
        )
    d4 = np.diff(a, n=4, axis=axis) / np.sqrt(70.0)
    sl = [slice(None)] * 3
    sl[axis] = slice(2, a.shape[axis] - 2)
    centre = a[tuple(sl)]
    peak = np.nanmax(a)
    ok = np.isfinite(d4) & np.isfinite(centre) & (centre > floor_fraction * peak)
    if ok.sum() < 16:
        raise ValueError("images: too few bright pixels to measure the noise")
    ratio = np.abs(d4[ok]) / centre[ok]
    return float(1.4826 * np.median(ratio))


def choose(plane_misfit: float, noise: float, threshold: float = 1.0) -> GeometryChoice:
    """Keep the plane model iff its misfit is at most ``threshold`` × the noise."""
    chosen = "plane" if plane_misfit <= threshold * noise else "slab"
    return GeometryChoice(chosen, float(plane_misfit), float(noise), threshold)


def misfit(model, observed, mask=None) -> float:
    """‖model − observed‖₂ / ‖observed‖₂ over ``mask`` (finite pixels by default)."""
    m = np.asarray(model, np.float64)
    o = np.asarray(observed, np.float64)
    keep = np.isfinite(m) & np.isfinite(o)
    if mask is not None:
        keep &= np.broadcast_to(np.asarray(mask, bool), keep.shape)
    return float(np.sqrt(np.sum((m - o)[keep] ** 2) / np.sum(o[keep] ** 2)))


__all__ = ["GeometryChoice", "choose", "misfit", "relative_noise"]
