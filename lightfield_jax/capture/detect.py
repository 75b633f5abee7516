"""Geometry of a stripe capture, measured from its images: where the medium is, which
wall the light enters, where it heads, and where the stripes fall on the camera's rows.

A real capture comes without these numbers, and measuring them by hand (a ruler on the
tank, a protractor on the projector) is the error-prone step. :func:`detect_geometry`
finds them in the images themselves, in the image frame of docs/model.md section 1:

- **Medium (ROI).** The signal S is the mean over the shifts (every row is lit in some
  shift, so S has no stripes) or the all-white frame. Its noise floor is read from the
  frame's dimmest border band (or given, e.g. 0 after a dark frame); pixels above the
  floor by eight times its scatter (and by 2·10⁻³ of the peak) are "lit". After a 3×3
  opening (isolated noise pixels), the largest connected lit region's bounding box is
  the ROI ``(x0, y0, x1, y1)``, x1 and y1 exclusive. Each edge is classified: ``wall``
  (a sharp step: the band just inside is well above the threshold, the band just
  outside below it), ``frame`` (the ROI reaches the image's edge), or ``faded`` (the
  light fades out before a wall: typically the far wall of a dense medium).
- **A faded far edge is not a wall.** Where the light fades before the wall opposite
  the entry, the tank goes on: light that scatters past the fade and back is part of
  the signal there, and the model's walls are black. The ROI is therefore extended
  across the light's direction beyond the fade, through the frame as long as it stays
  dark (below the lit threshold), to the frame's edge or to where something lit begins
  again (``Geometry.faded``: where the light faded and how far the ROI now reaches). The
  fit then crops its model where each channel's light falls into its noise
  (:func:`~lightfield_jax.inverse.model_size.size_model`): the black wall a finite model needs
  somewhere stands where the light is at the noise floor, not at the detection's
  threshold (2·10⁻³ of the peak). Faded side edges (light that does not reach the
  side walls) are reported, not extended: the projector does not light beyond them,
  which the model's illumination could not represent.
- **Orientation and stripe phase.** Along the wall (the transverse axis) each shifted
  image is a square wave of period T = ``period`` camera pixels. Its Fourier
  coefficient at frequency 1/T, per line along the light (a Hann-windowed sum across
  the ROI), c_p(x) = Σ_u w(u)·I_p(u, x)·exp(−2πi u/T), has a phase that drifts
  linearly along the light, arg c_p(x) = α_p − 2π·x·tan(θ')/T, where tan(θ') is the
  ridges' slope (dy/dx for the left and right walls, dx/dy for the top and bottom
  walls). The axis with the stronger 1/T component is the transverse one (stripes
  crossing the wrong axis repeat every T/tan θ' pixels, not T).
- **Entry wall.** Of the two walls across the light, the one where the signal is
  brighter (light decays away from the wall it enters).
- **Direction.** The common slope of the phases of every shift, by weighted least
  squares (weights |c|², the inverse variance of a phase) on the phases detrended by a
  first slope from the mean phase increment between neighbouring lines (no phase
  unwrapping), refined twice, with lines whose residual exceeds four robust standard
  deviations dropped (a robust line fit). θ0 = atan(tan θ') from the left wall, 180° +
  atan from the right wall, 90° − atan from the top and 270° − atan from the bottom
  wall. Its standard error comes from the fit's residual.
- **Phases.** The stripe centre on the entry wall, u_c = −T·arg c_p(x_wall)/(2π), gives
  the phase of each image: rows r with (r + φ) mod T < lit are lit, whose centre is
  −φ + lit/2, so φ = lit/2 − u_c (mod T), rounded to an integer. The fractional part
  left over (``phase_offset``, in pixels) says how far the projector's stripes are from
  the camera's rows, which the capture format cannot express (docs/model.md section 3).
- **Period.** The transverse frequency whose Fourier power is largest near 1/T (a dense
  search between 1/(1.5T) and 1.5/T) gives the stripes' period in camera pixels: it
  must be T for the capture format to describe them.
- **Lit width.** On the lines along the light next to the entry wall (the direct light
  keeps the projector's sharp stripes there), the fraction of pixels above the midpoint
  of their one-period neighbourhood's extremes, times T (``Geometry.lit_px``): it must
  be ``lit`` (within 0.15 row on renders, oblique ones included).

Measured on renders (48×36 px media embedded in a dark frame with shot and read noise,
θ0 from −20° to 25°, three media, 54 captures): lit walls within 0 px, θ0 within 0.09°
(rms 0.04°; the reported standard error, 0.005-0.02°, is the statistical part only: the
window and the oblique shadow edge add a bias of a few hundredths of a degree), every
phase right. The far wall of a dense medium is not seen: for the paper's milk (σt 0.2)
the ROI ends 26 px short of a 48 px tank, where the light has fallen to about 1 % of its
peak, an edge reported as ``faded``.

Stripes not aligned with the pixel grid are thus described by an oblique
``direction_deg``, which the renderer models (docs/model.md section 3). Confidence is a
number in [0, 1], the smallest of the parts' confidences (``Geometry.parts``): ``roi``
(1 when the entry wall and both side walls are sharp steps or the frame's edge, minus
0.25 for each that is not), ``entry`` (1 − the far side's signal / the entry side's),
``orientation`` (1 − the weaker axis's stripe power / the stronger's), ``direction``
(1/(1 + (stderr/0.5°)²)), ``phases`` (1 − 2·|phase_offset|) and ``period``
(1 − |measured/T − 1|/0.1, clipped). A detection with a confidence below 0.5 deserves
a look (``lightfield-jax inspect``).

scikit-image is imported inside the functions that use it, so ``import lightfield_jax``
does not load it.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from lightfield_jax.capture.detect_roi import (
    detect_roi,
    extend_faded,
    noise_floor,
    stripe_free_signal,
)
from lightfield_jax.capture.stripe_phase import (
    ACROSS,
    across_first,
    direction_from_slope,
    measured_lit,
    measured_period,
    phase_line,
    points_in,
    slope_from_direction,
    stripe_coefficients,
    stripe_power,
)
from lightfield_jax.checks import check_int, check_number, number_problem, real_array, shown
from lightfield_jax.scene.illumination import WALLS, along_x, check_direction

_OPPOSITE = {"left": "right", "right": "left", "top": "bottom", "bottom": "top"}


LOW_CONFIDENCE = 0.5


@dataclasses.dataclass(frozen=True)
class Geometry:
    """What :func:`detect_geometry` found (image frame of docs/model.md section 1).

    Attributes:
        roi: the medium's rectangle ``(x0, y0, x1, y1)`` in pixels, x1, y1 exclusive.
        entry: the wall the light enters through (left, right, top, bottom).
        direction_deg: the light's heading θ0 (degrees from +x toward +y).
        direction_stderr_deg: its standard error (0 when it was given, not measured).
        phases: one stripe phase per image, counted in the full frame (a row r, or a
            column for the top and bottom walls, is lit iff (r + φ) mod period < lit).
        phase_offset: the largest distance (pixels) between a measured stripe position
            and the nearest whole row; 0 means the stripes fall on the camera's rows.
        period_px: the stripes' measured period along the wall (camera pixels).
        confidence: the smallest of ``parts`` (see the module docstring).
        parts: confidence of each measured part, in [0, 1].
        edges: how each ROI edge was found: ``wall``, ``frame``, ``faded`` or ``given``.
        given: the parts that were given rather than measured.
        faded: for a faded far edge, ``{"side", "at", "extended_to", "until"}``: the
            side, the coordinate (x or y, px) where the light faded, the ROI's edge after
            extending it, and why it stops there (``frame`` or ``lit``); else ``None``.
        floor: the signal's noise floor (image units) and ``noise`` its scatter;
            ``threshold`` the level above which a pixel counted as lit.
        lit_px: the stripes' measured lit width along the wall (camera pixels per
            period) next to the entry wall; NaN where the wall is too short to measure.
    """

    roi: tuple[int, int, int, int]
    entry: str
    direction_deg: float
    direction_stderr_deg: float
    phases: tuple[int, ...]
    phase_offset: float
    period_px: float
    confidence: float
    parts: dict[str, float]
    edges: dict[str, str]
    given: tuple[str, ...]
    floor: float
    noise: float
    threshold: float
    faded: dict[str, Any] | None = None
    lit_px: float = math.nan

    def summary(self) -> str:
        """One line per finding, for a report or the command line."""
        x0, y0, x1, y1 = self.roi
        edges = ", ".join(f"{k} {v}" for k, v in self.edges.items())
        parts = ", ".join(f"{k} {v:.2f}" for k, v in self.parts.items())
        return "\n".join(
            [
                f"medium_roi [{x0}, {y0}, {x1}, {y1}] ({x1 - x0}x{y1 - y0} px; edges: {edges})",
                *([self.fade_note()] if self.faded else []),
                f"entry {self.entry}, direction_deg {self.direction_deg:.3f}"
                f" ± {self.direction_stderr_deg:.3f}",
                f"phases {list(self.phases)} (stripes {self.phase_offset:.2f} px off the "
                f"camera's rows; period measured {self.period_px:.3f} px)",
                f"confidence {self.confidence:.2f} ({parts})"
                + (f"; given: {', '.join(self.given)}" if self.given else ""),
            ]
        )

    def fade_note(self) -> str:
        """What was done about a faded far edge, in words."""
        f = self.faded
        axis = "x" if along_x(f["side"]) else "y"
        until = "the frame's edge" if f["until"] == "frame" else "where the frame is lit again"
        return (
            f"the light fades before the {f['side']} wall at {axis} = {f['at']}: not a wall "
            f"(the tank goes on), so the ROI extends to {axis} = {f['extended_to']} "
            f"({until}); the fit crops its model where each channel's light meets its noise"
        )

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["roi"] = list(self.roi)
        d["phases"] = list(self.phases)
        d["given"] = list(self.given)
        for key in ("threshold", "floor", "noise"):
            d[key] = d[key] if math.isfinite(d[key]) else None
        return d


def _clip01(v: float) -> float:
    return float(min(max(v, 0.0), 1.0))


def _checked(images, period, lit, reference, floor, roi, entry, direction_deg, valid):
    """``(images, reference)`` as float64 arrays, every argument of
    :func:`detect_geometry` checked (ValueError naming it). Unchecked, period 0 would
    raise a ZeroDivisionError, 6.0 a TypeError, an unknown entry a KeyError, a NaN
    direction "cannot convert float NaN to integer", a roi of three values an unpacking
    error; complex or bool images, lit 0 or 10 and a floor of "0" would be taken; a
    reference of another shape would end in "no lit medium found"."""
    key = "detect_geometry"
    a = real_array(images, f"{key}: images", (3, 4), "(P, H, W) or (P, H, W, C)", finite="any")
    check_int(period, f"{key}: period", low=2)
    check_int(lit, f"{key}: lit", low=1, high=period - 1)
    if floor is not None:
        check_number(floor, f"{key}: floor")
    if reference is not None:
        reference = real_array(reference, f"{key}: reference", (2, 3), "(H, W[, C])", finite="any")
        if reference.shape not in (a.shape[1:3], a.shape[1:]):
            raise ValueError(
                f"{key}: reference: must have the images' (H, W[, C]) {a.shape[1:]}, got "
                f"shape {reference.shape}"
            )
    height, width = a.shape[1:3]
    if roi is not None:
        box = () if isinstance(roi, (str, bytes)) or not np.iterable(roi) else tuple(roi)
        if not (
            len(box) == 4
            and all(number_problem(v, integer=True) is None for v in box)
            and 0 <= box[0] < box[2] <= width
            and 0 <= box[1] < box[3] <= height
        ):
            raise ValueError(
                f"{key}: roi: must be (x0, y0, x1, y1), integers with 0 <= x0 < x1 <= "
                f"{width} and 0 <= y0 < y1 <= {height}, got {shown(roi)}"
            )
    if entry is not None and entry not in WALLS:
        raise ValueError(f"{key}: entry: must be one of {', '.join(WALLS)}, got {shown(entry)}")
    if direction_deg is not None:
        check_number(direction_deg, f"{key}: direction_deg", low=-360.0, high=360.0)
    if valid is not None:
        v = np.asarray(valid)
        if v.dtype != bool:
            raise ValueError(f"{key}: valid: must be an array of booleans, got dtype {v.dtype}")
        try:
            valid = np.broadcast_to(v, a.shape[:3])
        except ValueError:
            raise ValueError(
                f"{key}: valid: must have the images' (P, H, W) {a.shape[:3]} or (H, W) "
                f"shape, got {v.shape}"
            ) from None
    return a, reference, valid


def detect_geometry(
    images,
    *,
    period: int = 6,
    lit: int = 3,
    reference=None,
    floor: float | None = None,
    roi: tuple[int, int, int, int] | None = None,
    entry: str | None = None,
    direction_deg: float | None = None,
    valid=None,
) -> Geometry:
    """Find the medium's ROI, the entry wall, the light's direction and the stripes'
    phases in a stripe capture (see the module docstring for how).

    Args:
        images: the shifted stripe images over the whole camera frame, ``(P, H, W)`` or
            ``(P, H, W, C)`` (channels are summed), dark frame subtracted if there is
            one. Non-finite pixels count as 0; saturated pixels are used as they are
            (clipping keeps a stripe's centre where it is).
        period, lit: the projected stripes (docs/model.md section 3), in camera pixels.
        reference: an all-white frame ``(H, W[, C])`` to find the ROI in (default: the
            mean of the shifts).
        floor: the signal level of an unlit pixel (0 after a dark frame); default: the
            median of the image's dimmest border band.
        roi, entry, direction_deg: known values, used instead of measured ones.
        valid: booleans ``(P, H, W)`` or ``(H, W)``, false where a value is not to be
            trusted (masked, clipped, or zeroed by a mask): each image's lines along the
            light that hold one are left out of the heading's and the phases' fit (a
            mask's zeros in the stripes of one shift and not another, counted, measure a
            0 deg heading at -11.7 deg). An image with no line left has no phase measured
            (the ``phases`` part's confidence 0).

    Returns:
        A :class:`Geometry`.

    Raises:
        ValueError: no lit medium, no visible stripes, or given values that contradict
            each other; the message says which.
    """
    a, reference, valid = _checked(
        images, period, lit, reference, floor, roi, entry, direction_deg, valid
    )
    if a.ndim == 4:
        a = np.where(np.isfinite(a), a, 0.0).sum(axis=-1)
    a = np.where(np.isfinite(a), a, 0.0)
    s = stripe_free_signal(a, reference)
    given = []
    if roi is None:
        roi, edges, (level, noise, threshold) = detect_roi(s, floor)
    else:
        given.append("roi")
        roi = tuple(int(v) for v in roi)
        edges = dict.fromkeys(WALLS, "given")
        level, noise = noise_floor(s, floor)
        threshold = math.nan
    x0, y0, x1, y1 = roi
    crop = a[:, y0:y1, x0:x1]
    parts: dict[str, float] = {}

    if direction_deg is not None and entry is not None:
        check_direction(entry, direction_deg, "pattern")
    candidates = [entry] if entry is not None else list(WALLS)
    if direction_deg is not None:
        candidates = [e for e in candidates if points_in(e, direction_deg)]
    axes = sorted({ACROSS[e] for e in candidates})
    power = {}
    for ax in axes:
        stack = crop if ax == "rows" else np.swapaxes(crop, 1, 2)
        power[ax] = stripe_power(stack, y0 if ax == "rows" else x0, period)
    across = max(power, key=power.get)
    if len(power) == 2:
        weaker = min(power.values()) / max(max(power.values()), np.finfo(float).tiny)
        parts["orientation"] = _clip01(1.0 - weaker)
    if power[across] <= 0:
        raise ValueError(
            f"detect_geometry: no stripes of period {period} px are visible in the ROI "
            f"{list(roi)}; check pattern.period and the images"
        )
    pair = [e for e in candidates if ACROSS[e] == across]
    profile = np.mean(stripe_free_signal(across_first(crop, pair[0]), None), axis=0)
    ends = {
        "left": profile[0],
        "top": profile[0],
        "right": profile[-1],
        "bottom": profile[-1],
    }
    if entry is None:
        entry = max(pair, key=lambda e: ends[e])
        parts["entry"] = _clip01(
            1.0 - ends[_OPPOSITE[entry]] / max(ends[entry], np.finfo(float).tiny)
        )
    else:
        given.append("entry")
    if "roi" not in given:
        near = [edges[e] for e in WALLS if e != _OPPOSITE[entry]]
        parts["roi"] = _clip01(1.0 - 0.25 * sum(e not in ("wall", "frame") for e in near))
    if direction_deg is not None:
        check_direction(entry, direction_deg, "pattern")

    stack = across_first(crop, entry)
    u0, along0 = (y0, x0) if across == "rows" else (x0, y0)
    c = stripe_coefficients(stack, u0, 1.0 / period)
    lines = None
    if valid is not None:
        lines = across_first(valid[:, y0:y1, x0:x1], entry).all(axis=1)  # (P, along)
        c = np.where(lines, c, 0.0)
    x = along0 + np.arange(stack.shape[-1]) + 0.5
    fixed = None
    if direction_deg is not None:
        fixed = -2.0 * math.pi * slope_from_direction(entry, direction_deg) / period
        given.append("direction")
    slope, slope_err, alpha, kept = phase_line(c, x, fixed)
    t = -slope * period / (2.0 * math.pi)
    if direction_deg is None:
        direction_deg = direction_from_slope(entry, t)
        # d(angle)/d(t) = 1/(1 + t²), in degrees.
        stderr = math.degrees(slope_err * period / (2.0 * math.pi) / (1.0 + t * t))
        parts["direction"] = 1.0 / (1.0 + (stderr / 0.5) ** 2) * _clip01(kept / 0.8)
    else:
        stderr = 0.0
    wall = along0 if entry in ("left", "top") else along0 + stack.shape[-1]
    centre = (-(alpha + slope * wall) * period / (2.0 * math.pi)) % period
    raw = (lit / 2.0 - centre) % period
    whole = np.round(raw)
    offset = float(np.max(np.abs(raw - whole))) if raw.size else 0.0
    phases = tuple(int(v) % period for v in whole)
    parts["phases"] = _clip01(1.0 - 2.0 * offset)
    if lines is not None and not lines.any(axis=1).all():
        parts["phases"] = 0.0
    period_px = measured_period(stack, u0, period)
    parts["period"] = _clip01(1.0 - abs(period_px / period - 1.0) / 0.1)
    lit_px = measured_lit(stack, entry, period)
    faded = None
    if "roi" not in given and edges[_OPPOSITE[entry]] == "faded":
        roi, faded = extend_faded(s, roi, _OPPOSITE[entry], threshold)
    return Geometry(
        roi=roi,
        entry=entry,
        direction_deg=float(direction_deg),
        direction_stderr_deg=float(stderr),
        phases=phases,
        phase_offset=offset,
        period_px=period_px,
        confidence=float(min(parts.values())) if parts else 1.0,
        parts=parts,
        edges=edges,
        given=tuple(given),
        floor=float(level),
        noise=float(noise),
        threshold=float(threshold),
        faded=faded,
        lit_px=lit_px,
    )


__all__ = [
    "LOW_CONFIDENCE",
    "Geometry",
    "detect_geometry",
]
