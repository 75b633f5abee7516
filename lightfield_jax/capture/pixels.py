"""A capture's pixel values made usable: calibrated to linear units ((a − dark) / flat,
the flat field normalised), and the masks of what cannot be used (NaN or Inf, outliers,
saturated or clipped, floored at a clamp), each noted in words."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from lightfield_jax.capture.io import (
    ImageData,
)
from lightfield_jax.inverse.data import floor_is_cut, floor_pileup
from lightfield_jax.schema import Section


def normalized_flat(
    top: Section,
    flat: ImageData | None,
    dark: np.ndarray | None,
    issues: list[str],
    values: np.ndarray | None,
):
    """The flat field, dark frame subtracted, divided by its median: NaN where it is
    not positive or where it was clipped (its top code, or many float values equal to
    its largest: the vignetting there is not measured; those pixels are masked).
    ``values``: its linear values (its pixels, or its codes mapped by a response);
    ``dark`` is linear too. The clip is judged on its pixels."""
    if flat is None:
        return None
    raw = flat.pixels
    if flat.is_integer:
        clipped = raw >= 1.0  # its top code
    else:
        clipped = float_clip(raw)
        clipped = np.zeros(raw.shape, bool) if clipped is None else clipped
    if clipped.any():
        issues.append(
            f"flat_field: {int(clipped.sum())} pixel value(s) of {flat.path.name} sit at its "
            f"{'top code' if flat.is_integer else 'largest value'} (clipped: the vignetting "
            "there is not measured); those pixels are masked"
        )
    f = calibrate(values, dark, None)
    f = np.where(clipped, np.nan, f)
    good = np.isfinite(f) & (f > 0)
    if good.mean() < 0.5:
        # A clipped pixel is said as such: an overexposed flat (its top code) is not one
        # that is "not positive".
        top_name = "top code" if flat.is_integer else "largest value"
        parts = [
            f"{what} in {int(k.sum())}"
            for k, what in (
                (clipped, f"clipped at its {top_name}"),
                (~good & ~clipped, "not positive (after the dark frame) or not finite"),
            )
            if k.any()
        ]
        top.fail(
            "flat_field",
            f"{flat.path.name} is {' and '.join(parts)} of its {good.size} pixel values: "
            "not a flat field",
        )
    bad = np.isfinite(f) & (f <= 0)
    if bad.any():  # said as such: before, counted among the NaN or Inf values
        zero, negative = bad & (values == 0), bad & (values < 0)
        kinds = [
            f"{int(k.sum())} {what}"
            for k, what in (
                (zero, "zero"),
                (negative, "negative"),
                (bad & ~zero & ~negative, "at or below the dark frame"),
            )
            if k.any()
        ]
        issues.append(
            f"flat_field: {int(bad.sum())} pixel value(s) of {flat.path.name} are not "
            f"positive ({', '.join(kinds)}): no vignetting is measured there; those pixels "
            "are masked"
        )
    median = np.median(f[good])
    dim = good & (f < _FLAT_DIM * median)
    if dim.any():  # a dead pixel (1e-30) multiplied its image values by 1e30, unsaid
        issues.append(
            f"flat_field: {int(dim.sum())} pixel value(s) of {flat.path.name} are below "
            f"{_FLAT_DIM:g} of its median (the smallest {float(np.min(f[dim]) / median):.3g}): "
            "dividing by them would multiply those image values more than "
            f"{1 / _FLAT_DIM:g}-fold (dead pixels, not vignetting); those pixels are masked"
        )
        good &= ~dim
    return np.where(good, f / median, np.nan)


# A flat field's pixels below this fraction of its median are masked: no lens vignettes
# a thousandfold; such a pixel is dead or dust, and dividing by it blows the image up.
_FLAT_DIM = 1e-3


def calibrate(
    a: np.ndarray,
    dark: np.ndarray | None,
    flat: np.ndarray | None,
    linear: Callable[[np.ndarray], np.ndarray] | None = None,
) -> np.ndarray:
    """(a − dark) / flat: the images (or a calibration frame) in linear units; ``a``'s
    codes first mapped by ``linear`` (a single exposure's ``response``) where given
    (``dark`` and ``flat`` are linear already)."""
    if linear is not None:
        a = linear(a)
    if dark is not None:
        a = a - dark
    return a if flat is None else a / flat


# A pixel value beyond this many times the images' 99th percentile of |value| is taken
# for corrupt and masked as a NaN is (the brightest light of a tank, at its entry wall,
# is within a few tens of times that percentile).
OUTLIER = 1e4


def corrupt_to_nan(raw: np.ndarray, names: Sequence[str], notes: list[str]) -> np.ndarray:
    """``raw`` (P, H, W, C) with values beyond :data:`OUTLIER` times the images' 99th
    percentile of |value| set to NaN (then masked as such); notes where."""
    finite = np.abs(raw[np.isfinite(raw)])
    if not finite.size:
        return raw
    limit = OUTLIER * float(np.percentile(finite, 99))
    if np.issubdtype(raw.dtype, np.floating) and limit > float(np.finfo(raw.dtype).max):
        return raw  # nothing of its type lies beyond (compared, the limit overflowed a cast)
    with np.errstate(invalid="ignore"):
        wild = np.isfinite(raw) & (np.abs(raw) > limit)
    if limit <= 0 or not wild.any():
        return raw
    where = [n for n, w in zip(names, wild.any(axis=(1, 2, 3)), strict=True) if w]
    notes.append(
        f"{int(wild.sum())} pixel value(s) beyond {OUTLIER:g} times the images' 99th "
        f"percentile, in {', '.join(where)} (corrupt?): taken as NaN"
    )
    return np.where(wild, np.nan, raw).astype(raw.dtype)


def inf_to_nan(values: np.ndarray | None) -> np.ndarray | None:
    """``values`` with every Inf a NaN. Both are masked alike (:func:`nonfinite_mask` counts
    them from the values as read); a NaN goes through the calibration's arithmetic and
    statistics quietly, where +Inf beside -Inf (or an Inf dark frame under an Inf image)
    made numpy warn "invalid value encountered" on the terminal."""
    if values is None or not np.isinf(values).any():
        return values
    return np.where(np.isinf(values), np.nan, values).astype(values.dtype)


def nonfinite_mask(
    raw: np.ndarray,
    frames: Sequence[tuple[ImageData, np.ndarray, np.ndarray]],
    names: Sequence[str],
    notes: list[str],
) -> np.ndarray:
    """[P, H, W, C] True where an image's value, or a calibration frame's (dark, flat:
    each with its cropped pixels as used, unusable values NaN: the pixel in every
    image, and its cropped values as read), is NaN or Inf; notes the counts of the
    values that were NaN or Inf as read (a flat field's non-positive or clipped values
    are masked too, and said by :func:`normalized_flat`, not counted here as NaN or Inf)."""
    out = ~np.isfinite(raw)
    counts = {n: int(c) for n, c in zip(names, out.sum(axis=(1, 2, 3)), strict=True) if c}
    for image, pixels, values in frames:
        frame_bad = ~np.isfinite(pixels)
        read_bad = ~np.isfinite(values)
        if read_bad.any():
            counts[image.path.name] = int(read_bad.sum())
        out = out | np.broadcast_to(frame_bad, out.shape)
    if counts:
        listed = ", ".join(f"{n}: {c}" for n, c in counts.items())
        notes.append(
            f"{sum(counts.values())} pixel value(s) are NaN or Inf ({listed}); {_masked(out)}"
        )
    return out


def _channel_name(frames: Sequence[ImageData], c: int) -> str:
    """Channel ``c``'s name in the frames (its index where they have none)."""
    names = frames[0].channel_names
    return names[c] if c < len(names) else str(c)


def _masked(values: np.ndarray) -> str:
    """How much a [P, H, W, C] mask of bad values masks, for a note."""
    pixels = int(values.any(axis=0).sum())
    return f"{int(values.sum())} value(s) masked in {pixels} pixel(s)"


# Float frames of measured (mostly distinct) values are taken for clipped where at
# least this share of their values, and at least CLIPPED_MIN of them, equal their
# largest exactly (a noiseless render ties a few pixels at its peak, far fewer).
CLIPPED_SHARE = 0.01


CLIPPED_MIN = 16


def float_clip(values: np.ndarray) -> np.ndarray | None:
    """Where float ``values`` equal their largest, positive value, where that is a clip:
    at least ``CLIPPED_MIN`` and ``CLIPPED_SHARE`` of them equal it exactly, among
    measured (noisy, nearly all distinct) values; ``None`` where it is not (a synthetic
    image of a few levels, or a perfectly flat frame, is not clipped at its top)."""
    finite = values[np.isfinite(values)]
    top = float(np.max(finite)) if finite.size else 0.0
    if top <= 0:
        return None
    here = values == top
    measured = np.unique(finite).size > 0.5 * finite.size
    if measured and here.sum() >= max(CLIPPED_MIN, CLIPPED_SHARE * finite.size):
        return here
    return None


def one_value(image: np.ndarray) -> float | None:
    """The one value of an image whose finite pixel values are all equal, else ``None``."""
    values = image[np.isfinite(image)]
    return float(values[0]) if values.size and np.all(values == values[0]) else None


def saturated_mask(
    raw: np.ndarray,
    frames: Sequence[ImageData],
    names: Sequence[str],
    saturation: float | None,
    sensor: tuple[float, int] | None,
    notes: list[str],
    find_plateau: bool = True,
) -> np.ndarray:
    """[P, H, W, C] True where a raw image's value is saturated (>= saturation) or
    clipped (at the top code of an integer frame, or of the sensor's bits in a 16-bit
    file, when no saturation is given; with ``find_plateau``, a float frame's many values
    equal to its largest); notes what was found. Merged exposure brackets flag their
    own clipped samples (no plateau: their merged values are radiances)."""
    with np.errstate(invalid="ignore"):
        if saturation is not None:
            hit = raw >= saturation
        else:
            integer = np.array([f.is_integer for f in frames])[:, None, None, None]
            hit = integer & (raw >= (1.0 if sensor is None else sensor[0]))
    plateau = None
    if saturation is None and find_plateau:  # float frames: a clip shows as many values at the top
        floating = np.array([not f.is_integer for f in frames])
        tops, at_top = {}, np.zeros(raw.shape, bool)
        for c in range(raw.shape[-1]):  # per channel: a white balance scales each clip
            values = raw[floating][..., c]
            here = float_clip(values)
            if here is not None:
                tops[_channel_name(frames, c)] = float(values[here][0])
                at_top[floating, :, :, c] = here
        if tops:
            plateau = (tops, at_top)
            hit = hit | at_top
    per_frame = hit.sum(axis=(1, 2, 3))
    finite = np.isfinite(raw).sum(axis=(1, 2, 3))
    full = [n for n, h, f in zip(names, per_frame, finite, strict=True) if f and h == f]
    if full:
        notes.append(f"every pixel is saturated in {', '.join(full)}")
    listed = ", ".join(f"{n}: {int(h)}" for n, h in zip(names, per_frame, strict=True) if h)
    if listed and saturation is not None:
        notes.append(
            f"pixel values at or above saturation {saturation:g} ({listed}); {_masked(hit)}"
        )
    elif listed and plateau is not None:
        tops = plateau[0]
        largest = (
            f"the images' largest, {next(iter(tops.values())):g}"
            if len(tops) == 1 and raw.shape[-1] == 1
            else "their channel's largest ("
            + ", ".join(f"{c} {t:g}" for c, t in tops.items())
            + ")"
        )
        notes.append(
            f"{int(plateau[1].sum())} float pixel values equal {largest} ({listed}): clipped; "
            f"{_masked(hit)} (set saturation: to give the threshold)"
        )
    elif listed:
        bits = sorted({f.bit_depth for f, h in zip(frames, per_frame, strict=True) if h})
        codes = ", ".join(f"{(1 << b) - 1} ({b}-bit)" for b in bits)
        if sensor is not None:
            codes = f"{(1 << sensor[1]) - 1} ({sensor[1]}-bit data in 16-bit files)"
        notes.append(
            f"integer frames clipped at their top code {codes} ({listed}); "
            f"{_masked(hit)} (set saturation: to change the threshold)"
        )
    return hit


def floored_mask(
    raw: np.ndarray,
    usable: np.ndarray,
    frames: Sequence[ImageData],
    names: Sequence[str],
    notes: list[str],
    images: np.ndarray,
    pattern,
) -> np.ndarray:
    """[P, H, W, C] True where a raw value (among the ``usable`` ones) sits at a floor it
    was clamped at (:func:`~lightfield_jax.inverse.data.floor_pileup`, per channel: a
    16-bit file or a camera's black subtraction cut the dark values' noise at 0);
    notes what was found. Integer codes were cut there by the file or the camera (their
    lowest code holds every value the noise or the quantisation put below it); float
    frames only where the calibrated ``images`` show an additive noise that could have
    taken values below it (:func:`~lightfield_jax.inverse.data.floor_is_cut`)."""
    out = np.zeros(raw.shape, bool)
    integer = all(f.is_integer for f in frames)
    for c in range(raw.shape[-1]):
        here = floor_pileup(raw[..., c], usable[..., c])
        if here.any() and (
            integer or floor_is_cut(images[..., c], usable[..., c] & ~here, usable[..., c], pattern)
        ):
            out[..., c] = here
    levels = {
        _channel_name(frames, c): float(raw[..., c][out[..., c]][0])
        for c in range(raw.shape[-1])
        if out[..., c].any()
    }
    if levels:
        per = out.sum(axis=(1, 2, 3))
        listed = ", ".join(f"{n}: {int(k)}" for n, k in zip(names, per, strict=True) if k)
        at = ", ".join(f"{c} {v:g}" for c, v in levels.items())
        notes.append(
            f"{int(out.sum())} pixel value(s) sit at their channel's lowest ({at}; {listed}): "
            "a floor they were clamped at (the fit masks them, and the values its answer "
            "puts within 3 sigma of it)"
        )
    return out
