"""Photometric calibration of a capture: what the camera's files are, and the projector's
black level.

Raw files (:func:`check_raw_frames`). Cameras write linear data as 16-bit TIFF or PNG
(from a raw converter) and HDR merges as float EXR; the checks here turn the ways such
files go wrong into clear errors or notes:

- Frames of one capture must share a sample format: a 16-bit image among 8-bit ones
  (or an integer among float ones) is scaled differently (by its type's maximum), so
  the images would not be in the same units.
- A 16-bit file often holds 10-, 12- or 14-bit data (codes up to 1023, 4095, 16383).
  When the largest code of the images is exactly such a top code, reached by several
  pixels, the sensor clipped there: those pixels are saturated although they are far
  below 65535.
- A 4-channel image is RGBA (an alpha channel that is constant is dropped) or a split
  raw Bayer mosaic (R, G, G, B planes): a varying fourth channel is refused. A
  constant alpha (the channel named A) is dropped from any image of two or more
  channels, and a varying one refused, wherever it stands (a 5-channel EXR: R, G, B,
  A, Z).
- A 1-channel image can be an undemosaiced Bayer mosaic: its four 2×2 pixel classes
  (even/odd row × even/odd column) carry different colour filters. The test compares
  each pixel with its 3×3 neighbourhood mean in log space, class by class, on the
  mean of the frames (where the stripes average out); smooth light gives the same
  value in every class. The mosaic's signature is a class interaction (the two
  diagonal pairs differ) or a difference within a diagonal pair, which stripes along
  rows or columns, and smooth gradients, never produce.

Black level (:func:`estimate_black_level`), b in docs/model.md section 5, from:

- the all-black frame K (the projector showing black) with the all-white frame W: the
  slope of K against W over the medium's pixels (K = δ + b·R_full, W = δ + R_full; a
  regression is immune to a dark offset δ that no dark frame removed);
- or the all-black frame against the mean of the shifts, when the phases tile the
  period (mean = δ + (a + b(1 − a))·R_full, a = lit/period): slope q, b = a·q/(1 − q(1 − a));
- without a black frame, Imin/Imax at the entry wall, extrapolated to the wall from the
  first three pixels along the light. There Imin/Imax = (b + c·M/D)/(1 + c·M/D) with
  c = a + b(1 − a): multiple scatter M is smallest but not zero, so this is an upper
  bound. Measured on renders (48×36 px, period 6, b from 0.005 to 0.05, 54 captures):
  biased by +0.002 to +0.003 for the paper's milk, +0.016 to +0.022 at albedo 0.5 to
  0.8, where the black-frame estimates above are within 0.0007. Take a black frame, or
  leave ``black_level`` out so that the joint fit estimates it with the full model.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from lightfield_jax.capture.io import CaptureError, ImageData
from lightfield_jax.inverse.decay import entry_coordinates

# Sensor depths that 16-bit files commonly carry.
_SENSOR_BITS = (10, 12, 14)
# A 1-channel image whose 2×2 pixel classes differ by more than this (log ratio) is a mosaic.
_MOSAIC_LOG_RATIO = math.log(1.1)


# --------------------------------------------------------------------------- raw files


def check_sample_formats(frames: Sequence[tuple[str, ImageData]], aux) -> None:
    """Every image has the first image's sample format (or, a float one, any float
    format: half, float and double hold one unit alike); an integer calibration frame
    (dark, black, white) has it too (a float one is taken as given; a flat field's
    units do not matter).

    ``frames`` and ``aux`` are (key, image) pairs; raises :class:`CaptureError` whose
    message names the keys, files and formats (without the capture file)."""
    key0, first = frames[0]

    def fmt(image: ImageData) -> str:
        kind = "integer" if image.is_integer else "float"
        return f"{image.bit_depth}-bit {kind} ({image.sample_type})"

    for key, image in frames[1:]:
        # Float samples (half, float, double) are taken as they are: one unit in any.
        integer = image.is_integer or first.is_integer
        if integer and (image.sample_type, image.bit_depth) != (first.sample_type, first.bit_depth):
            raise CaptureError(
                f"{key}: {image.path.name} is {fmt(image)} but {key0} ({first.path.name}) is "
                f"{fmt(first)}; integer samples are scaled by their type's maximum, so the "
                "images would not share units: write every image in one format"
            )
    for key, image in aux:
        # A flat field is divided by its own median: its units never matter.
        other = not first.is_integer or image.bit_depth != first.bit_depth
        if image.is_integer and other and key != "flat_field":
            raise CaptureError(
                f"{key}: {image.path.name} is {fmt(image)} but the images are {fmt(first)}; "
                "a calibration frame must share the images' format (or be float, in the "
                "images' units after scaling to [0, 1]): integer samples are scaled by "
                "their type's maximum, float ones are taken as they are"
            )


def sensor_top_code(raw: np.ndarray, frames: Sequence[ImageData]) -> tuple[float, int] | None:
    """For 16-bit integer frames holding 10-, 12- or 14-bit data clipped at their top
    code: (the top code as a [0, 1] value, the sensor's bits); else ``None``."""
    if not all(f.is_integer and f.bit_depth == 16 for f in frames):
        return None
    codes = np.rint(np.where(np.isfinite(raw), raw, 0.0) * 65535.0)
    top = int(codes.max())
    for bits in _SENSOR_BITS:
        if top == (1 << bits) - 1 and int(np.sum(codes == top)) >= 2:
            return top / 65535.0, bits
    return None


def alpha_index(names: Sequence[str]) -> int | None:
    """The alpha channel's index among ``names`` (the channel named A: the last one if
    several are), ``None`` without one or with a single channel."""
    if len(names) < 2 or "A" not in names:
        return None
    return len(names) - 1 if names[-1] == "A" else list(names).index("A")


def drop_constant_alpha(frames: list[ImageData], notes: list[str]) -> list[ImageData]:
    """Frames without a constant alpha channel (the channel named A, of two or more;
    noted); a varying alpha, or four channels that are not RGBA, is a
    :class:`CaptureError`. The alpha may stand anywhere (a 5-channel EXR: R, G, B, A,
    Z)."""
    names = frames[0].channel_names
    n = len(names)
    if (a := alpha_index(names)) is not None:
        alpha = np.stack([f.pixels[..., a] for f in frames])
        finite = alpha[np.isfinite(alpha)]
        if finite.size and np.all(finite == finite[0]):
            notes.append(
                f"dropped the constant alpha channel A of the {n}-channel images "
                f"({', '.join(names)})"
            )
            keep = [i for i in range(n) if i != a]
            return [
                dataclasses.replace(
                    f,
                    pixels=np.ascontiguousarray(f.pixels[..., keep]),
                    channel_names=tuple(names[i] for i in keep),
                )
                for f in frames
            ]
        raise CaptureError(
            f"{frames[0].path.name} has a varying alpha channel ({', '.join(names)}): "
            "not a camera image of the medium; save the images without alpha, or choose "
            "a channel with the channel key"
        )
    if n == 4:
        raise CaptureError(
            f"{frames[0].path.name} has 4 channels ({', '.join(names)}): a split raw "
            "Bayer mosaic (R, G, G, B planes) is not a demosaiced image; convert the raw "
            "files to RGB (e.g. dcraw -4 -T, or rawpy with gamma (1, 1) and "
            "output_bps 16), or choose a channel with the channel key"
        )
    return frames


def mosaic_score(image: np.ndarray) -> tuple[float, float]:
    """(score, its standard error) of a 1-channel image being a 2×2 colour mosaic: the
    larger of the class interaction and the within-diagonal difference of the classes'
    median log ratio to the 3×3 neighbourhood mean (see the module docstring)."""
    a = np.asarray(image, np.float64)
    h, w = a.shape
    if h < 8 or w < 8:
        return 0.0, math.inf
    pad = np.pad(a, 1, mode="edge")
    with np.errstate(invalid="ignore", over="ignore"):  # +Inf beside -Inf: NaN, not good
        box = sum(pad[i : i + h, j : j + w] for i in range(3) for j in range(3)) / 9.0
    lo = np.minimum.reduce([pad[i : i + h, j : j + w] for i in range(3) for j in range(3)])
    finite = a[np.isfinite(a)]  # NaN and Inf are masked later, not measured here
    if finite.size < 20:
        return 0.0, math.inf
    top = float(np.percentile(finite, 99))
    # Pixels whose whole neighbourhood is well lit: away from edges and the noise floor.
    good = (lo > 0.05 * top) & np.isfinite(box)
    good[0], good[-1], good[:, 0], good[:, -1] = False, False, False, False
    ratio = np.log(np.where(good, a, 1.0) / np.where(good, box, 1.0))
    medians, errors = {}, []
    for i in (0, 1):
        for j in (0, 1):
            sel = good[i::2, j::2]
            values = ratio[i::2, j::2][sel]
            if values.size < 20:
                return 0.0, math.inf
            medians[i, j] = float(np.median(values))
            spread = 1.4826 * float(np.median(np.abs(values - medians[i, j])))
            errors.append(1.25 * spread / math.sqrt(values.size))
    c = medians
    interaction = 0.5 * abs(c[0, 0] + c[1, 1] - c[0, 1] - c[1, 0])
    diagonal = 0.5 * abs(abs(c[0, 0] - c[1, 1]) - abs(c[0, 1] - c[1, 0]))
    return max(interaction, diagonal), 2.0 * max(errors)


def check_not_mosaic(frames: Sequence[ImageData]) -> None:
    """Refuse 1-channel frames that look like an undemosaiced Bayer mosaic."""
    if frames[0].pixels.shape[-1] != 1:
        return
    with np.errstate(invalid="ignore", over="ignore"):  # +Inf and -Inf: NaN, left out
        mean = np.mean(np.stack([f.pixels[..., 0] for f in frames]), axis=0)
    score, err = mosaic_score(mean)
    if score > max(_MOSAIC_LOG_RATIO, 6.0 * err):
        raise CaptureError(
            f"{frames[0].path.name}: the 1-channel images look like an undemosaiced Bayer "
            f"mosaic (their 2x2 pixel classes differ by {100 * math.expm1(score):.0f}%); "
            "demosaic the raw files to linear RGB (e.g. dcraw -4 -T, or rawpy with gamma "
            "(1, 1) and output_bps 16) and choose a channel, or fit each colour plane as "
            "its own capture"
        )


# --------------------------------------------------------------------------- black level


@dataclasses.dataclass(frozen=True)
class BlackLevel:
    """An estimate of the projector's black level b.

    Attributes:
        value: b, clipped to [0, 0.99).
        stderr: its standard error (NaN where not estimated).
        method: how it was measured, in words.
        per_channel: the estimate of each channel (``value`` combines them).
        upper_bound: True when the method can only overestimate b.
    """

    value: float
    stderr: float
    method: str
    per_channel: tuple[float, ...]
    upper_bound: bool = False


def _slope(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least-squares slope of y = δ + q·x and its standard error."""
    n = x.size
    xm, ym = x.mean(), y.mean()
    sxx = float(np.sum((x - xm) ** 2))
    q = float(np.sum((x - xm) * (y - ym))) / sxx
    r = y - ym - q * (x - xm)
    return q, math.sqrt(float(np.sum(r**2)) / max(n - 2, 1) / sxx)


def _combine(values: list[float], errors: list[float]) -> tuple[float, float]:
    w = np.array([1.0 / e**2 if e > 0 and math.isfinite(e) else 0.0 for e in errors])
    if w.sum() == 0:
        return float(np.mean(values)), math.nan
    return float(np.sum(w * values) / w.sum()), float(1.0 / math.sqrt(w.sum()))


def estimate_black_level(
    images: np.ndarray,
    lit_fraction: float,
    *,
    tiles_period: bool,
    mask: np.ndarray,
    entry: str,
    direction_deg: float,
    black: np.ndarray | None = None,
    white: np.ndarray | None = None,
) -> BlackLevel:
    """Estimate b from a capture cropped to the medium (see the module docstring).

    Args:
        images: (P, H, W, C), dark frame subtracted (if any).
        lit_fraction: a = lit/period.
        tiles_period: whether the phases are 0..period−1 (each row lit ``lit`` times).
        mask: (H, W, C), valid pixels.
        entry, direction_deg: the light's entry wall and heading.
        black, white: the all-black and all-white frames (H, W, C), treated like the
            images, or ``None``.

    Raises:
        ValueError: too few usable pixels.
    """
    a = lit_fraction
    n_channels = images.shape[-1]
    if black is not None and (white is not None or tiles_period):
        ref = white if white is not None else images.mean(axis=0)
        values, errors = [], []
        for ch in range(n_channels):
            x, y = ref[..., ch], black[..., ch]
            use = mask[..., ch] & np.isfinite(x) & np.isfinite(y)
            if use.sum() < 10:
                raise ValueError("black_level: auto: fewer than 10 usable pixels")
            use &= x > 0.05 * np.percentile(x[use], 99)
            if use.sum() < 10 or not np.ptp(x[use]) > 1e-6 * np.max(np.abs(x[use])):
                which = "white_frame does" if white is not None else "images do"
                raise ValueError(
                    f"black_level: auto: the {which} not vary over the medium, so the "
                    "black frame's slope against them is undetermined; give black_level"
                )
            q, dq = _slope(x[use], y[use])
            if white is None:  # slope against the mean of the shifts
                den = 1.0 - q * (1.0 - a)
                q, dq = a * q / den, a * dq / den**2
            values.append(q)
            errors.append(dq)
        b, db = _combine(values, errors)
        against = "the all-white frame" if white is not None else "the mean of the shifts"
        margin = 3.0 * (db if math.isfinite(db) else 0.0) + 0.01
        if not -margin < b < 1.0:  # a projector's black is a fraction of its white
            raise ValueError(
                f"black_frame: the all-black frame against {against} gives a black level "
                f"of {b:.3g}, outside [0, 1): not the projector's black frame (check "
                "black_frame and white_frame)"
            )
        return BlackLevel(
            value=min(max(b, 0.0), 0.99),
            stderr=db,
            method=f"slope of the all-black frame against {against}",
            per_channel=tuple(values),
        )
    h, w = images.shape[1:3]
    s, _ = entry_coordinates(h, w, entry, direction_deg)
    imax, imin = images.max(axis=0), images.min(axis=0)
    values = []
    for ch in range(n_channels):
        hi, lo = imax[..., ch], imin[..., ch]
        use = mask[..., ch] & (s < 3.0) & np.isfinite(hi) & np.isfinite(lo)
        if use.sum() < 3:
            raise ValueError("black_level: auto: no usable pixel at the entry wall")
        use &= hi > 0.2 * hi[use].max()
        # Median Imin/Imax per pixel-wide step of s, extrapolated linearly to s = 0.
        steps = np.floor(s[use]).astype(int)
        ratio = lo[use] / hi[use]
        xs = [float(np.mean(s[use][steps == k])) for k in range(3) if (steps == k).sum() >= 2]
        ys = [float(np.median(ratio[steps == k])) for k in range(3) if (steps == k).sum() >= 2]
        values.append(float(np.polyfit(xs, ys, 1)[1]) if len(xs) >= 2 else float(np.median(ratio)))
    b = float(np.mean(values))
    return BlackLevel(
        value=min(max(b, 0.0), 0.99),
        stderr=math.nan,
        method="Imin/Imax at the entry wall (an upper bound: multiple scatter adds to Imin)",
        per_channel=tuple(values),
        upper_bound=True,
    )


__all__ = [
    "BlackLevel",
    "check_not_mosaic",
    "check_sample_formats",
    "drop_constant_alpha",
    "estimate_black_level",
    "mosaic_score",
    "sensor_top_code",
]
