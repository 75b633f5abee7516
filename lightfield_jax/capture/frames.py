"""Reading a capture's images and calibration frames (dark, black, white, flat), the
calibration, and the masks of non-finite and saturated pixels."""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lightfield_jax.capture.calibration import alpha_index, sensor_top_code
from lightfield_jax.capture.io import (
    CaptureError,
    CaptureFileNotFoundError,
    ImageData,
    channel_index,
    image_shape,
    read_image,
    read_npy_stack,
)
from lightfield_jax.capture.keys import AUX_FRAMES
from lightfield_jax.inverse.data import floor_is_cut, floor_pileup
from lightfield_jax.runtime.memory import capture_bytes, check_memory
from lightfield_jax.schema import Section, brief


def _check_capture_memory(top: Section, files: Sequence[Path]) -> None:
    """Refuse, from the files' headers, before any is decoded, an image whose size
    differs from the first's (a header claiming 20000x20000 pixels) and a capture too
    large to load (a file that cannot be read is left to the read, which names its
    key)."""
    shapes: list[tuple[int, ...]] = []
    first: tuple[int, ...] | None = None
    for i, file in enumerate(files):
        try:
            shape = image_shape(file)
        except CaptureError:
            if first is None:
                return
            shape = first  # its read says what is wrong
        if first is None:
            first = shape
        elif _image_like(shape) and _image_like(first) and shape[:2] != first[:2]:
            top.fail(
                f"images[{i}]",
                f"{file.name} is {shape[1]}x{shape[0]} pixels (its header), but images[0] "
                f"({files[0].name}) is {first[1]}x{first[0]}; every image must have the "
                "same size and channels",
            )
        shapes.append(shape)
    samples = sum(math.prod(shape) for shape in shapes)
    check_memory(
        capture_bytes(samples), f"{top.source}: images ({len(files)} file(s), {samples} samples)"
    )


def _image_like(shape: tuple[int, ...]) -> bool:
    """A header's shape that is one image's, (height, width[, channels]) with pixels;
    others (an empty array, a stack) are named by the read."""
    return len(shape) in (2, 3) and 0 not in shape


def read_frame(top: Section, key: str, file: Path, channel) -> ImageData:
    try:
        image = read_image(file, channel)
    except CaptureFileNotFoundError as e:
        raise CaptureFileNotFoundError(f"{top.source}: {key}: {e}") from None
    except CaptureError as e:
        raise CaptureError(f"{top.source}: {key}: {e}") from None
    _check_float32_range(top, key, image)
    return image


_FLOAT32_MAX = float(np.finfo(np.float32).max)


def _check_float32_range(top: Section, key: str, image: ImageData) -> None:
    """Refuse double-precision samples beyond float32's range (1e300 in a .npy: before,
    numpy's overflow warnings and 'no pixel is finite ... nothing to separate')."""
    pixels = image.pixels
    if pixels.dtype != np.float64:
        return
    with np.errstate(invalid="ignore"):
        big = np.abs(pixels) > _FLOAT32_MAX
    if big.any():
        top.fail(
            key,
            f"{image.path.name}: {int(big.sum())} value(s) beyond float32's range (up to "
            f"{float(np.max(np.abs(pixels[big]))):.3g}; float32 holds {_FLOAT32_MAX:.3g}), "
            "which the pipeline computes in: scale the images by a constant",
        )


def resolve_file(top: Section, key: str, value: Any, base: Path) -> Path:
    if not isinstance(value, str) or not value or "\0" in value:
        top.fail(key, f"must be a file path, got {brief(value)}")
    return base / value


def _file_identity(base: Path, value: str) -> Any:
    """A listed file's identity: its device and inode (one file under two names, a hard
    link), else its resolved path."""
    path = base / value
    with contextlib.suppress(OSError, RuntimeError):  # RuntimeError: a symlink loop
        path = path.resolve()
    with contextlib.suppress(OSError):
        st = os.stat(path)
        return (st.st_dev, st.st_ino)
    return path


def images_listed_twice(top: Section, base: Path) -> str | None:
    """What to say of stripe images listed again under ``images`` (refused by the
    phases' checks where the phases are given and differ; with ``phases: auto``, a
    warning: one image counted as two shifts, its noise twice), or ``None``."""
    images = top.get("images", None)
    if not isinstance(images, list):
        return None
    seen: dict[Any, int] = {}
    again = []
    for i, value in enumerate(images):
        # A bracket (a list of exposures) is one shift too: its files, in order.
        files = value if isinstance(value, list) else [value]
        if not all(isinstance(v, str) and v and "\0" not in v for v in files):
            continue
        ident = tuple(_file_identity(base, v) for v in files)
        if ident in seen:
            again.append((i, seen[ident]))
        seen.setdefault(ident, i)
    if not again:
        return None
    i, j = again[0]
    more = f" (and {len(again) - 1} more)" if len(again) > 1 else ""
    bracket = isinstance(images[i], list)
    shown = ", ".join(images[i]) if bracket else images[i]
    return (
        f"images[{i}] ({shown}) is the {'bracket' if bracket else 'file'} of images[{j}] "
        f"listed again{more}: one image counted as two shifts (a slip in the list?)"
    )


def check_distinct_files(top: Section, base: Path) -> None:
    """Refuse one file given in two roles (a stripe image and a calibration frame, or
    two calibration frames): a user's slip that would otherwise
    run a whole fit on a wrong capture (the paths as given, resolved; a missing file is
    left to the reader's error)."""
    roles: list[tuple[str, Any]] = []
    images = top.get("images", None)
    if isinstance(images, list):
        roles += [(f"images[{i}]", v) for i, v in enumerate(images)]
    else:  # a .npy stack (its file may also be a calibration frame's)
        roles.append(("images", images))
    roles += [(key, top.get(key, None)) for key in AUX_FRAMES]
    # Exposure brackets: each exposure's file (images[i][j], dark_frame[j]).
    roles = [
        item
        for key, value in roles
        for item in (
            [(f"{key}[{j}]", v) for j, v in enumerate(value)]
            if isinstance(value, list)
            else [(key, value)]
        )
    ]
    seen: dict[Any, str] = {}
    for key, value in roles:
        if not isinstance(value, str) or not value or "\0" in value:
            continue  # not a path: resolve_file names its key
        ident = _file_identity(base, value)
        # A stripe image listed twice is left to the phases' checks (and, within a
        # bracket, to its exposure ratios); a calibration frame repeated in its own
        # bracket keeps its role.
        role, other = key.split("[")[0], seen.get(ident, "").split("[")[0]
        if ident in seen and role != other:
            top.fail(key, f"{value} is also {seen[ident]}: one file cannot be both")
        seen.setdefault(ident, key)


def read_frames(top: Section, base: Path, channel) -> list[ImageData]:
    check_distinct_files(top, base)
    value = top.get("images")
    if isinstance(value, str):
        file = resolve_file(top, "images", value, base)
        if file.suffix.lower() != ".npy":
            top.fail(
                "images",
                f"a single file must be a .npy stack [P, H, W(, C)], got {brief(value)}; "
                "list the image files otherwise",
            )
        _check_capture_memory(top, [file])
        try:
            frames = read_npy_stack(file)
            if channel is not None:
                index = channel_index(frames[0].channel_names, channel, file)
                frames = [
                    dataclasses.replace(
                        f, pixels=f.pixels[..., [index]], channel_names=(f.channel_names[index],)
                    )
                    for f in frames
                ]
        except CaptureFileNotFoundError as e:
            raise CaptureFileNotFoundError(f"{top.source}: images: {e}") from None
        except CaptureError as e:
            raise CaptureError(f"{top.source}: images: {e}") from None
        for frame in frames:
            _check_float32_range(top, "images", frame)
        return frames
    if not isinstance(value, list):
        top.fail("images", f"must be a list of image files or one .npy stack, got {brief(value)}")
    if not value:
        top.fail("images", "the list is empty: give one image per phase")
    files = [resolve_file(top, f"images[{i}]", v, base) for i, v in enumerate(value)]
    _check_capture_memory(top, files)
    frames = [read_frame(top, f"images[{i}]", file, channel) for i, file in enumerate(files)]
    first = frames[0]
    for i, f in enumerate(frames[1:], start=1):
        if f.pixels.shape != first.pixels.shape:
            top.fail(
                f"images[{i}]",
                f"{f.path.name} is {size_text(f)}, but images[0] ({first.path.name}) is "
                f"{size_text(first)}; every image must have the same size and channels",
            )
    return frames


def size_text(image: ImageData) -> str:
    h, w, c = image.pixels.shape
    return f"{w}x{h} pixels with {c} channel(s)"


def read_aux_frame(top: Section, key: str, base: Path, channel, first: ImageData, value=None):
    """A calibration frame (dark, black, white, flat; ``value``: its file, default the
    key's): the images' size, and one channel or as many as they have."""
    value = top.get(key, None) if value is None else value
    if value is None:
        return None
    frame = read_frame(top, key, resolve_file(top, key, value, base), channel)
    h, w, c = first.pixels.shape
    fh, fw, fc = frame.pixels.shape
    names = frame.channel_names
    # Its alpha: the last channel, or one elsewhere without which the channels are the
    # images' (R, G, B, A, Z for R, G, B, Z images whose alpha was dropped).
    a = alpha_index(names)
    if (
        fc == c + 1
        and a is not None
        and (a == fc - 1 or names[:a] + names[a + 1 :] == first.channel_names)
    ):
        keep = [i for i in range(fc) if i != a]
        frame = dataclasses.replace(
            frame,
            pixels=np.ascontiguousarray(frame.pixels[..., keep]),
            channel_names=tuple(frame.channel_names[i] for i in keep),
        )
        fc = c
    if (fh, fw) != (h, w) or fc not in (1, c):
        top.fail(
            key,
            f"{value} is {size_text(frame)}, but the images are {size_text(first)} (a "
            f"{key.replace('_', ' ')} has the images' size and one channel or as many as "
            "they have)",
        )
    if not np.isfinite(frame.pixels).any():  # said here, not as "images: no usable pixel"
        top.fail(key, f"{value}: every pixel value is NaN or Inf (a corrupt file?)")
    return frame


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
        clipped = _float_clip(raw)
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


def _float_clip(values: np.ndarray) -> np.ndarray | None:
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


def _one_value(image: np.ndarray) -> float | None:
    """The one value of an image whose finite pixel values are all equal, else ``None``."""
    values = image[np.isfinite(image)]
    return float(values[0]) if values.size and np.all(values == values[0]) else None


def check_not_blank(top: Section, frames: list[tuple[str, str, np.ndarray]]) -> None:
    """Refuse a stripe image (``(key, name, pixels)`` each: a single exposure or one
    exposure of a bracket) that holds no image: NaN and Inf only (checked first in every
    frame: an image of nothing else is no image), or one value ≤ 0 among frames that vary
    (a dropped frame: before, fitted as a shift, not converged without a word of it).
    Every frame alike is said later, with its cause."""
    for key, name, pixels in frames:
        if not np.isfinite(pixels).any():
            top.fail(key, f"{name}: every pixel value is NaN or Inf (a corrupt file?)")
    flat = [_one_value(pixels) for _, _, pixels in frames]
    for (key, name, _), level in zip(frames, flat, strict=True):
        if level is not None and level <= 0 and None in flat:
            top.fail(
                key,
                f"{name}: every pixel value is {level:.6g}, unlike the other images (a "
                "dropped frame, or the projector or camera off?)",
            )


def check_projector_frames(top: Section, aux: dict, merged: bool) -> None:
    """Refuse a ``black_frame`` or ``white_frame`` that is no camera image of the
    projector's black or white: a black frame clipped at its top code or, a float file,
    at its largest value (its slope against the white gives a black level near 0, which
    would be accepted), or a white frame of one value (one of zeros would be blamed on
    the images by the geometry's detection; a constant white is no measurement). Merged brackets'
    frames are radiances: only the one-value check applies to them."""
    for key in ("white_frame", "black_frame"):
        frame = aux.get(key)
        if frame is None:
            continue
        name, pixels = frame.path.name, frame.pixels
        if key == "black_frame" and not merged:
            if frame.is_integer:
                sensor = sensor_top_code(pixels[None], [frame]) if frame.bit_depth == 16 else None
                at_top, where = pixels >= (1.0 if sensor is None else sensor[0]), "top code"
            else:
                clip = _float_clip(pixels)
                at_top = np.zeros(pixels.shape, bool) if clip is None else clip
                where = "largest value"
            n = int(at_top.sum())
            if n >= max(CLIPPED_MIN, CLIPPED_SHARE * at_top.size):
                top.fail(
                    key,
                    f"{name}: {n} of {at_top.size} pixel values sit at its {where} (saturated: "
                    "a clipped black frame gives a wrong black level); take it with a "
                    "shorter exposure",
                )
        if not np.isfinite(pixels).any():
            top.fail(key, f"{name}: every pixel value is NaN or Inf (a corrupt file?)")
        # A black frame of one value is a measurement (a camera clamping its black at
        # 0, a projector's black below one code): a black level of 0, as before.
        level = _one_value(pixels) if key == "white_frame" else None
        if level is not None:
            top.fail(
                key,
                f"{name}: every pixel value is {level:.6g}: not a camera image of the "
                "projector showing all white (that varies over the medium)",
            )


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
            here = _float_clip(values)
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
