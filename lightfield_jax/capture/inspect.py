"""What the pipeline sees in a capture, before any fit (``lightfield-jax inspect``).

:func:`inspect_capture` separates the loaded capture (docs/model.md section 5, with the
capture's black level, or 0 when unknown) and measures, per channel, the signal-to-noise
ratio of the direct image D and the multiple image M along the light: in bins of the
distance s from the entry wall (2 px), SNR = mean of the image / its noise. Across the
light (along the entry wall) D and M are nearly constant, so the second difference
across it, I(u) − (I(u−1) + I(u+1))/2, is noise with variance 1.5σ²: σ is its robust
scatter (1.4826 × MAD)/√1.5 within the bin. Structure that the separation leaves across
the light (stripe residue at oblique incidence, the shadow edge) counts as noise, so
this is a lower bound on the SNR. ``Inspection.summary`` says it in
words and :func:`lightfield_jax.viz.plot_inspect` draws it with the ROI, entry wall,
direction and saturation mask.
"""

from __future__ import annotations

import dataclasses
import math
import os

import numpy as np

from lightfield_jax.capture.capture import Capture
from lightfield_jax.capture.loading import load_capture
from lightfield_jax.inverse.decay import entry_coordinates
from lightfield_jax.inverse.separate import separate
from lightfield_jax.scene.illumination import unseparated_rows

SNR_USABLE = 10.0
_BIN_PX = 2.0


@dataclasses.dataclass(frozen=True, eq=False)
class Inspection:
    """The separated capture and its signal-to-noise ratio along the light.

    Attributes:
        capture: the capture inspected.
        direct, multiple: D and M, [H, W, C] (cropped frame, image units).
        distance: s, the path length from the entry wall of each pixel [H, W] (px).
        bins: centres of the distance bins (px).
        snr_direct, snr_multiple: [C, bins], NaN where a bin has no valid pixel.
        reach: per channel, the largest distance at which D's SNR is at least 10.
    """

    capture: Capture
    direct: np.ndarray
    multiple: np.ndarray
    distance: np.ndarray
    bins: np.ndarray
    snr_direct: np.ndarray
    snr_multiple: np.ndarray
    reach: tuple[float, ...]

    def to_dict(self) -> dict:
        """The findings as JSON-ready values (NaN as ``None``)."""
        c = self.capture

        def clean(a):
            return [None if not math.isfinite(v) else float(v) for v in np.ravel(a)]

        return {
            "capture": str(c.source),
            "channels": list(c.channel_names),
            "medium_roi": None if c.roi is None else list(c.roi),
            "entry": c.pattern.entry,
            "direction_deg": c.pattern.direction_deg,
            "phases": list(c.pattern.phases),
            "black_level": c.black_level,
            "black_level_method": c.black_level_estimate and c.black_level_estimate.method,
            "detected": None if c.detected is None else c.detected.to_dict(),
            "n_masked": c.n_masked,
            "distance_px": clean(self.bins),
            "snr_direct": dict(zip(c.channel_names, map(clean, self.snr_direct), strict=True)),
            "snr_multiple": dict(zip(c.channel_names, map(clean, self.snr_multiple), strict=True)),
            "reach_px": dict(zip(c.channel_names, self.reach, strict=True)),
            "notes": list(c.notes),
            "warnings": [*c.warnings, *self.problems()],
            "brackets": None if c.brackets is None else c.brackets.to_dict(),
            "response": c.response_record(),
        }

    def summary(self) -> str:
        """A report of what the pipeline sees, one fact per line."""
        c = self.capture
        p, h, w, n = c.images.shape
        det = c.detected
        source = "auto" if det is not None and "roi" not in det.given else "given"
        roi = "whole frame" if c.roi is None else f"{list(c.roi)} ({source})"
        lines = [
            f"capture: {c.source}",
            f"images: {p} of {w}x{h} px after the crop, channels {', '.join(c.channel_names)}",
            f"medium_roi: {roi}",
            f"entry: {c.pattern.entry}, direction_deg {c.pattern.direction_deg:.3f}, "
            f"phases {list(c.pattern.phases)} (counted from the ROI's edge), period "
            f"{c.pattern.period}, lit {c.pattern.lit}",
        ]
        if det is not None:
            lines.append("detected: " + det.summary().replace("\n", "\n  "))
        b = c.black_level
        lines.append(
            "black_level: "
            + (
                "unknown (the joint fit estimates it; separation here assumes 0)"
                if b is None
                else f"{b:.4f}"
            )
            + (f" ({c.black_level_estimate.method})" if c.black_level_estimate else "")
        )
        lines.append(
            f"masked: {c.n_masked['values']} of {p * h * w * n} values (pixels "
            f"saturated in some image: {c.n_masked['saturated']}, non-finite: "
            f"{c.n_masked['nonfinite']}, of {h * w * n})"
        )
        for i, name in enumerate(c.channel_names):
            peak, ratio, snr0, start = self._wall(i)
            wall = "at the entry wall"
            if start >= _MASKED_WALL_PX:
                wall = f"from s = {start:.0f} px (the wall's pixels are masked: clipped?)"
            if not peak > 0:  # nothing to measure (problems() says why)
                lines.append(f"[{name}] no direct light (D peak {peak:.4g})")
                continue
            lines.append(
                f"[{name}] D peak {peak:.4g}, M/D {wall} {ratio:.3f}; SNR of D "
                f"{snr0:.0f} nearest the wall, >= {SNR_USABLE:g} up to s = {self.reach[i]:.0f} px "
                f"of {float(self.distance.max()):.0f}"
            )
        for note in c.notes:
            lines.append(f"note: {note}")
        for warning in [*c.warnings, *self.problems()]:
            lines.append(f"warning: {warning}")
        return "\n".join(lines)

    def _wall(self, i: int) -> tuple[float, float, float, float]:
        """Channel i's direct peak, M/D and SNR of D at the entry wall (NaN: undefined),
        and the distance s (px) from which they are measured: the wall's, or where its
        pixels are masked (a capture clipped near the wall) the nearest valid ones'."""
        c = self.capture
        d, m, valid = self.direct[..., i], self.multiple[..., i], c.mask[..., i]
        start = float(self.distance[valid].min()) if valid.any() else math.nan
        near = valid & (self.distance < start + 3.0) & (d > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = float(np.median(m[near] / d[near])) if near.any() else math.nan
        peak = float(np.max(d[valid])) if valid.any() else math.nan
        snr = self.snr_direct[i][np.isfinite(self.snr_direct[i])]
        return peak, ratio, float(snr[0]) if snr.size else math.nan, start

    def problems(self) -> list[str]:
        """What makes a channel unusable for a fit (its statistics undefined), one line
        each; empty for a usable capture."""
        found, p = [], self.capture.pattern  # rows left unseparated: a note of the capture
        for i, name in enumerate(self.capture.channel_names):
            peak, ratio, snr0, _ = self._wall(i)
            if not peak > 0 or math.isnan(ratio):
                found.append(
                    f"[{name}] no direct light at the entry wall (the separated direct "
                    "image is not positive on the valid pixels nearest it): check the "
                    "pattern and medium_roi"
                )
            elif self.reach[i] <= 0 and not unseparated_rows(p.period, p.lit, p.phases):
                found.append(
                    f"[{name}] the direct light's SNR never reaches {SNR_USABLE:g} "
                    f"(at the wall: {snr0:.3g}): too dark or too noisy to fit"
                )
        return found


# The wall counts as masked where its nearest valid pixel is this far (px) from it.
_MASKED_WALL_PX = 2.0


def _snr(
    image: np.ndarray, valid: np.ndarray, index: np.ndarray, n_bins: int, across_rows: bool
) -> np.ndarray:
    """Mean / noise per distance bin; the noise from second differences across the light
    (where the image is constant up to noise), σ = 1.4826·MAD/√1.5."""
    a = image if across_rows else image.T
    ok = valid if across_rows else valid.T
    second = np.full(a.shape, np.nan)
    second[1:-1] = a[1:-1] - 0.5 * (a[:-2] + a[2:])
    both = np.zeros(a.shape, bool)
    both[1:-1] = ok[1:-1] & ok[:-2] & ok[2:]
    if not across_rows:
        second, both = second.T, both.T
    out = np.full(n_bins, np.nan)
    for k in range(n_bins):
        sel = both & (index == k)
        if sel.sum() < 4:
            continue
        r = second[sel]
        noise = 1.4826 * float(np.median(np.abs(r - np.median(r)))) / math.sqrt(1.5)
        mean = float(np.mean(image[valid & (index == k)]))
        out[k] = mean / noise if noise > 0 else math.inf
    return out


def inspect_capture(capture: Capture | str | os.PathLike) -> Inspection:
    """Separate a loaded capture (or its capture file's path, loaded with
    :func:`~lightfield_jax.load_capture`) and measure its SNR along the light (module
    docs)."""
    if isinstance(capture, (str, os.PathLike)):  # as fit_capture takes it
        capture = load_capture(capture)
    elif not isinstance(capture, Capture):
        raise TypeError(
            f"inspect_capture: expected a capture (lightfield_jax.load_capture) or a capture "
            f"file's path, got {type(capture).__name__}"
        )
    images = np.asarray(capture.images, np.float64)
    p, h, w, n = images.shape
    if p < 2:  # in the capture file's words, not separate's
        raise ValueError(
            f"images: inspecting needs at least 2 shifted images (the separation of the "
            f"direct light compares them), got {p}"
        )
    pattern = capture.pattern
    b = min(max(capture.black_level or 0.0, 0.0), 0.99)
    sep = separate(images, lit_fraction=pattern.lit_fraction, black_level=b)
    direct, multiple = np.asarray(sep.direct), np.asarray(sep.multiple)
    s, u = entry_coordinates(h, w, pattern.entry, pattern.direction_deg)
    n_bins = int(math.ceil(float(s.max()) / _BIN_PX)) + 1
    index = np.floor(s / _BIN_PX).astype(int)
    centres = (np.arange(n_bins) + 0.5) * _BIN_PX
    across = h if pattern.along_x else w
    on_wall = (u >= 0) & (u < across)
    snr_d, snr_m, reach = [], [], []
    for i in range(n):
        valid = capture.mask[..., i] & on_wall
        rows = pattern.along_x
        snr_d.append(_snr(direct[..., i], valid, index, n_bins, rows))
        snr_m.append(_snr(multiple[..., i], valid, index, n_bins, rows))
        good = np.flatnonzero(np.nan_to_num(snr_d[-1], nan=0.0) >= SNR_USABLE)
        reach.append(min(float(centres[good[-1]]), float(s.max())) if good.size else 0.0)
    return Inspection(
        capture=capture,
        direct=direct,
        multiple=multiple,
        distance=s,
        bins=centres,
        snr_direct=np.array(snr_d),
        snr_multiple=np.array(snr_m),
        reach=tuple(reach),
    )


__all__ = ["Inspection", "inspect_capture"]
