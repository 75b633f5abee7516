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

from lightfield_jax.checks import check_int, check_number, number_problem, real_array, shown
from lightfield_jax.scene.illumination import WALLS, along_x, check_direction

_OPPOSITE = {"left": "right", "right": "left", "top": "bottom", "bottom": "top"}
_ACROSS = {"left": "rows", "right": "rows", "top": "columns", "bottom": "columns"}
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


# --------------------------------------------------------------------------- helpers


def _mad_sigma(values: np.ndarray) -> float:
    v = values[np.isfinite(values)]
    if v.size == 0:
        return 0.0
    return 1.4826 * float(np.median(np.abs(v - np.median(v))))


def _signal(images: np.ndarray, reference: np.ndarray | None) -> np.ndarray:
    """The unstriped signal S (H, W): the all-white frame, or the mean over the shifts,
    summed over the channels; non-finite pixels count as 0."""
    s = np.mean(images, axis=0) if reference is None else reference
    s = np.where(np.isfinite(s), s, 0.0)
    return s.sum(axis=-1) if s.ndim == 3 else s


def _floor(s: np.ndarray, floor: float | None) -> tuple[float, float]:
    """(floor, noise) of the signal: the dimmest border band's median (or the given
    floor) and the noise of that band, from differences between neighbouring pixels
    along it (so a slow variation, the medium's own light, does not count as noise)."""
    h, w = s.shape
    k = max(1, min(2, h // 8, w // 8))
    bands = [s[:k], s[-k:], s[:, :k].T, s[:, -k:].T]  # each (k, length)
    dim = min(bands, key=lambda b: float(np.median(b)))
    level = float(np.median(dim)) if floor is None else float(floor)
    return level, _mad_sigma(np.diff(dim, axis=1).ravel()) / math.sqrt(2.0)


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


def _detect_roi(s: np.ndarray, floor: float | None):
    from skimage.measure import label
    from skimage.morphology import opening

    level, noise = _floor(s, floor)
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


def across_first(a: np.ndarray, entry: str) -> np.ndarray:
    """(..., H, W) → (..., across, along): the axis along the entry wall first."""
    return a if _ACROSS[entry] == "rows" else np.swapaxes(a, -1, -2)


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


def _stripe_power(a: np.ndarray, u0: int, period: float) -> float:
    return float(np.sum(np.abs(stripe_coefficients(a, u0, 1.0 / period)) ** 2))


def _measured_period(a: np.ndarray, u0: int, period: int) -> float:
    freqs = np.linspace(1.0 / (1.5 * period), 1.5 / period, 301)
    power = _spectrum(a, u0, freqs, lambda c: np.sum(np.abs(c) ** 2, axis=(1, 2)))
    return float(1.0 / freqs[int(np.argmax(power))])


def _phase_line(c: np.ndarray, x: np.ndarray, slope: float | None):
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
        scatter = _mad_sigma(e[keep])
        if scatter > 0:
            keep = keep & (np.abs(e) <= 4.0 * scatter)
    detrended = c * np.exp(-1j * slope * x)[None]
    alpha = np.angle(np.sum(np.where(keep, detrended, 0.0), axis=1))
    total = (weight > 1e-6 * weight.max()).sum()
    return slope, stderr, alpha, float(keep.sum()) / max(int(total), 1)


def _direction_from_slope(entry: str, t: float) -> float:
    a = math.degrees(math.atan(t))
    return {"left": a, "right": 180.0 + a, "top": 90.0 - a, "bottom": 270.0 - a}[entry]


def _slope_from_direction(entry: str, direction_deg: float) -> float:
    t = math.radians(direction_deg)
    if _ACROSS[entry] == "rows":
        return math.tan(t)
    return math.cos(t) / math.sin(t)


def _clip01(v: float) -> float:
    return float(min(max(v, 0.0), 1.0))


# --------------------------------------------------------------------------- detection


def _checked(images, period, lit, reference, floor, roi, entry, direction_deg):
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
    return a, reference


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

    Returns:
        A :class:`Geometry`.

    Raises:
        ValueError: no lit medium, no visible stripes, or given values that contradict
            each other; the message says which.
    """
    a, reference = _checked(images, period, lit, reference, floor, roi, entry, direction_deg)
    if a.ndim == 4:
        a = np.where(np.isfinite(a), a, 0.0).sum(axis=-1)
    a = np.where(np.isfinite(a), a, 0.0)
    s = _signal(a, reference)
    given = []
    if roi is None:
        roi, edges, (level, noise, threshold) = _detect_roi(s, floor)
    else:
        given.append("roi")
        roi = tuple(int(v) for v in roi)
        edges = dict.fromkeys(WALLS, "given")
        level, noise = _floor(s, floor)
        threshold = math.nan
    x0, y0, x1, y1 = roi
    crop = a[:, y0:y1, x0:x1]
    parts: dict[str, float] = {}

    if direction_deg is not None and entry is not None:
        check_direction(entry, direction_deg, "pattern")
    candidates = [entry] if entry is not None else list(WALLS)
    if direction_deg is not None:
        candidates = [e for e in candidates if _points_in(e, direction_deg)]
    axes = sorted({_ACROSS[e] for e in candidates})
    power = {}
    for ax in axes:
        stack = crop if ax == "rows" else np.swapaxes(crop, 1, 2)
        power[ax] = _stripe_power(stack, y0 if ax == "rows" else x0, period)
    across = max(power, key=power.get)
    if len(power) == 2:
        weaker = min(power.values()) / max(max(power.values()), np.finfo(float).tiny)
        parts["orientation"] = _clip01(1.0 - weaker)
    if power[across] <= 0:
        raise ValueError(
            f"detect_geometry: no stripes of period {period} px are visible in the ROI "
            f"{list(roi)}; check pattern.period and the images"
        )
    pair = [e for e in candidates if _ACROSS[e] == across]
    profile = np.mean(_signal(across_first(crop, pair[0]), None), axis=0)
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
    x = along0 + np.arange(stack.shape[-1]) + 0.5
    fixed = None
    if direction_deg is not None:
        fixed = -2.0 * math.pi * _slope_from_direction(entry, direction_deg) / period
        given.append("direction")
    slope, slope_err, alpha, kept = _phase_line(c, x, fixed)
    t = -slope * period / (2.0 * math.pi)
    if direction_deg is None:
        direction_deg = _direction_from_slope(entry, t)
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
    period_px = _measured_period(stack, u0, period)
    parts["period"] = _clip01(1.0 - abs(period_px / period - 1.0) / 0.1)
    lit_px = _measured_lit(stack, entry, period)
    faded = None
    if "roi" not in given and edges[_OPPOSITE[entry]] == "faded":
        roi, faded = _extend_faded(s, roi, _OPPOSITE[entry], threshold)
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


def _measured_lit(stack: np.ndarray, entry: str, period: int) -> float:
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


def _extend_faded(s: np.ndarray, roi, side: str, threshold: float):
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


def _points_in(entry: str, direction_deg: float) -> bool:
    try:
        check_direction(entry, direction_deg, "pattern")
    except ValueError:
        return False
    return True


__all__ = [
    "Geometry",
    "LOW_CONFIDENCE",
    "STRIPED",
    "detect_geometry",
    "other_period",
    "period_contradiction",
]
