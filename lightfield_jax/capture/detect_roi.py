"""Where the medium is in a stripe capture's frame: the signal without stripes, its noise
floor, the lit region's bounding box (the ROI) with each edge classified (``wall``,
``frame``, ``faded``), and a faded far edge extended across the dark beyond it. The
method is :mod:`lightfield_jax.capture.detect`'s "Medium (ROI)"."""

from __future__ import annotations

import math

import numpy as np

from lightfield_jax.scene.illumination import WALLS, along_x


def mad_sigma(values: np.ndarray) -> float:
    v = values[np.isfinite(values)]
    if v.size == 0:
        return 0.0
    return 1.4826 * float(np.median(np.abs(v - np.median(v))))


def stripe_free_signal(images: np.ndarray, reference: np.ndarray | None) -> np.ndarray:
    """The unstriped signal S (H, W): the all-white frame, or the mean over the shifts,
    summed over the channels; non-finite pixels count as 0."""
    s = np.mean(images, axis=0) if reference is None else reference
    s = np.where(np.isfinite(s), s, 0.0)
    return s.sum(axis=-1) if s.ndim == 3 else s


def noise_floor(s: np.ndarray, floor: float | None) -> tuple[float, float]:
    """(floor, noise) of the signal: the dimmest border band's median (or the given
    floor) and the noise of that band, from differences between neighbouring pixels
    along it (so a slow variation, the medium's own light, does not count as noise)."""
    h, w = s.shape
    k = max(1, min(2, h // 8, w // 8))
    bands = [s[:k], s[-k:], s[:, :k].T, s[:, -k:].T]  # each (k, length)
    dim = min(bands, key=lambda b: float(np.median(b)))
    level = float(np.median(dim)) if floor is None else float(floor)
    return level, mad_sigma(np.diff(dim, axis=1).ravel()) / math.sqrt(2.0)


def _edge_kind(s: np.ndarray, region: np.ndarray, roi, side: str, level: float, threshold: float):
    x0, y0, x1, y1 = roi
    h, w = s.shape
    if side == "left":
        at_frame, inside = x0 == 0, (s[y0:y1, x0], region[y0:y1, x0])
        outside = None if at_frame else s[y0:y1, x0 - 1]
    elif side == "right":
        at_frame, inside = x1 == w, (s[y0:y1, x1 - 1], region[y0:y1, x1 - 1])
        outside = None if at_frame else s[y0:y1, x1]
    elif side == "top":
        at_frame, inside = y0 == 0, (s[y0, x0:x1], region[y0, x0:x1])
        outside = None if at_frame else s[y0 - 1, x0:x1]
    else:
        at_frame, inside = y1 == h, (s[y1 - 1, x0:x1], region[y1 - 1, x0:x1])
        outside = None if at_frame else s[y1, x0:x1]
    if at_frame:
        return "frame"
    values, lit = inside
    # The lit part of the band (light may reach only part of a side wall).
    step = float(np.percentile(values[lit], 90)) if lit.any() else level
    dark = float(np.percentile(outside[lit], 50)) if lit.any() else math.inf
    return "wall" if step - level > 4.0 * (threshold - level) and dark <= threshold else "faded"


def detect_roi(s: np.ndarray, floor: float | None):
    from skimage.measure import label
    from skimage.morphology import opening

    level, noise = noise_floor(s, floor)
    peak = float(np.percentile(s, 99.5))
    threshold = level + max(8.0 * noise, 2e-3 * (peak - level), np.finfo(float).tiny)
    lit = s > threshold
    cleaned = opening(lit, np.ones((3, 3), bool))
    labels = label(cleaned if cleaned.any() else lit, connectivity=2)
    if labels.max() == 0:
        raise ValueError(
            "detect_geometry: no lit medium found: no pixel stands above the noise floor "
            f"{level:.4g} (scatter {noise:.3g}) of the images' dimmest border"
        )
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    region = labels == int(np.argmax(sizes))
    rows, cols = np.flatnonzero(region.any(axis=1)), np.flatnonzero(region.any(axis=0))
    roi = (int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1)
    if roi[2] - roi[0] < 4 or roi[3] - roi[1] < 4:
        raise ValueError(
            f"detect_geometry: the lit region {list(roi)} is smaller than 4x4 pixels; "
            "give medium_roi"
        )
    edges = {side: _edge_kind(s, region, roi, side, level, threshold) for side in WALLS}
    return roi, edges, (level, noise, threshold)


def extend_faded(s: np.ndarray, roi, side: str, threshold: float):
    """The ROI extended beyond a faded ``side`` through the frame while the signal S,
    averaged across the light over the ROI, stays below the lit threshold."""
    x0, y0, x1, y1 = roi
    h, w = s.shape
    if along_x(side):
        profile = s[y0:y1].mean(axis=0)
        start, stop, step = (x1, w, 1) if side == "right" else (x0 - 1, -1, -1)
    else:
        profile = s[:, x0:x1].mean(axis=1)
        start, stop, step = (y1, h, 1) if side == "bottom" else (y0 - 1, -1, -1)
    end, until = stop, "frame"
    for i in range(start, stop, step):
        if profile[i] > threshold:
            end, until = i, "lit"
            break
    edge = end if step > 0 else end + 1  # exclusive on the far side, inclusive on the near
    at = {"left": x0, "right": x1, "top": y0, "bottom": y1}[side]
    extended = {
        "left": (edge, y0, x1, y1),
        "right": (x0, y0, edge, y1),
        "top": (x0, edge, x1, y1),
        "bottom": (x0, y0, x1, edge),
    }[side]
    return extended, {"side": side, "at": at, "extended_to": edge, "until": until}


__all__ = [
    "detect_roi",
    "extend_faded",
    "mad_sigma",
    "noise_floor",
    "stripe_free_signal",
]
