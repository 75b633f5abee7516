"""Reading a capture's images and calibration frames (dark, black, white, flat): their
files, memory, sizes and channels, and the checks that they show what the file says
(light in every image, projector frames where they belong)."""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import math
import os
from collections.abc import Iterable, Sequence
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
from lightfield_jax.capture.paths import is_file_name
from lightfield_jax.capture.pixels import (
    CLIPPED_MIN,
    CLIPPED_SHARE,
    float_clip,
    one_value,
)
from lightfield_jax.capture.response import RESPONSES
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
    if not is_file_name(value):
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


def images_listed_twice(
    top: Section, base: Path, frames: Sequence[ImageData] = (), names: Sequence[str] = ()
) -> str | None:
    """What to say of stripe images listed again under ``images`` (refused by the
    phases' checks where the phases are given and differ; measured or the default, a
    warning: one image counted as two shifts, its noise twice), or of ``frames`` (named
    ``names``) that hold the same pixels (a copied file, a stack's repeated frame: no
    two exposures of a camera are alike), or ``None``."""
    images = top.get("images", None)
    if not isinstance(images, list):
        return _same_pixels(frames, names)

    def identity(value) -> Any:
        # A bracket (a list of exposures) is one shift too: its files, in order.
        files = value if isinstance(value, list) else [value]
        if not all(map(is_file_name, files)):
            return None
        return tuple(_file_identity(base, v) for v in files)

    again = _repeats(identity(value) for value in images)
    if not again:
        return _same_pixels(frames, names)
    (i, j), more = again[0], _and_more(again)
    bracket = isinstance(images[i], list)
    shown = ", ".join(images[i]) if bracket else images[i]
    return (
        f"images[{i}] ({shown}) is the {'bracket' if bracket else 'file'} of images[{j}] "
        f"listed again{more}: one image counted as two shifts (a slip in the list?)"
    )


def _repeats(keys: Iterable[Any]) -> list[tuple[int, int]]:
    """``(i, j)`` for each key equal to an earlier one's, j the first with it (``None``
    keys skipped)."""
    seen: dict[Any, int] = {}
    again = []
    for i, key in enumerate(keys):
        if key is None:
            continue
        if key in seen:
            again.append((i, seen[key]))
        seen.setdefault(key, i)
    return again


def _and_more(again: list) -> str:
    return f" (and {len(again) - 1} more)" if len(again) > 1 else ""


def _same_pixels(frames: Sequence[ImageData], names: Sequence[str]) -> str | None:
    def key(frame: ImageData) -> bytes:
        pixels = np.ascontiguousarray(frame.pixels)  # (hashed in place: no copy)
        return hashlib.sha256(memoryview(pixels).cast("B")).digest() + str(pixels.shape).encode()

    again = _repeats(key(frame) for frame in frames)
    if not again:
        return None
    (i, j), more = again[0], _and_more(again)
    return (
        f"images[{i}] ({names[i]}) holds the same pixels as images[{j}] ({names[j]}){more}: "
        "one image counted as two shifts (a copied file?)"
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
        if not is_file_name(value):
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
    by_index = isinstance(channel, int)
    return [first] + [
        matched_channels(top, f"images[{i}]", f, first, by_index)
        for i, f in enumerate(frames[1:], 1)
    ]


def matched_channels(
    top: Section, key: str, frame: ImageData, first: ImageData, by_index: bool = False
) -> ImageData:
    """``frame``'s channels in the order of ``first``'s (images[0]'s), matched by name
    (a layer's prefix, ``rgb.R``, aside): one file saved B, G, R among R, G, B ones had
    its blue fitted as the others' red. Channels of other names are refused (which is
    which cannot be told); one channel is one, whatever its name, unless ``by_index``
    (``channel:`` an index) chose it from a file of several."""
    names, order = frame.channel_names, first.channel_names
    if len(names) < (1 if by_index else 2) or len(names) != len(order):
        return frame
    bare, wanted = [n.rsplit(".", 1)[-1] for n in names], [n.rsplit(".", 1)[-1] for n in order]
    if bare == wanted:
        return frame
    if sorted(bare) != sorted(wanted) or len(set(bare)) != len(bare):
        top.fail(
            key,
            f"{frame.path.name} has the channels {', '.join(names)}, but images[0] "
            f"({first.path.name}) has {', '.join(order)}: channels are matched by name; save "
            "every file with the same channels, or choose one by name with the channel key",
        )
    index = [bare.index(n) for n in wanted]
    return dataclasses.replace(
        frame,
        pixels=np.ascontiguousarray(frame.pixels[..., index]),
        channel_names=tuple(names[i] for i in index),
    )


def size_text(image: ImageData) -> str:
    h, w, c = image.pixels.shape
    return f"{w}x{h} pixels with {c} channel(s)"


def read_aux_frame(top: Section, key: str, base: Path, channel, first: ImageData, value=None):
    """A calibration frame (dark, black, white, flat; ``value``: its file, default the
    key's): the images' size, and one channel or as many as they have."""
    value = top.get(key, None) if value is None else value
    if value is None:
        return None
    frame = read_frame(top, key, resolve_file(top, key, value, base), None)
    if channel is not None:
        frame = _chosen_channel(top, key, frame, channel, first)
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
    frame = matched_channels(top, key, frame, first)
    if not np.isfinite(frame.pixels).any():  # said here, not as "images: no usable pixel"
        top.fail(key, f"{value}: every pixel value is NaN or Inf (a corrupt file?)")
    return frame


def _chosen_channel(top: Section, key: str, frame: ImageData, channel, first: ImageData):
    """The channel of a calibration frame (all of its channels read) that the images'
    ``channel`` key chose: one grey channel (Y) applies to every channel; else the
    channel of the name the images' chosen one has, wherever it is in the frame
    (``channel: 0`` chose the images' R, and the R of a frame saved B, G, R is its
    third: before, its B was subtracted), a layer's prefix aside where one layer has
    it; else the key's name or index as in the images."""
    names, chosen = frame.channel_names, first.channel_names[0]
    bare, colour = [n.rsplit(".", 1)[-1] for n in names], chosen.rsplit(".", 1)[-1]
    colours = [n for i, n in enumerate(bare) if i != alpha_index(names)]
    if colours in (["Y"], [colour]):  # grey, or the chosen one alone
        return frame
    matches = [i for i, n in enumerate(bare) if n == colour]
    try:
        if chosen in names:  # the same name, a layer's prefix included
            index = names.index(chosen)
        elif len(matches) == 1:  # the same colour of another layer's name
            index = matches[0]
        elif matches:
            top.fail(
                key,
                f"{frame.path.name} has {', '.join(names[i] for i in matches)}, none of them "
                f"the images' {chosen}: which one is theirs cannot be told (save the frame "
                "with the images' channel names)",
            )
        else:  # none of that name: the key's own name or index, as in the images
            index = channel_index(names, channel, frame.path)
    except CaptureError as e:
        top.fail(key, str(e))
    return dataclasses.replace(
        frame,
        pixels=np.ascontiguousarray(frame.pixels[..., [index]]),
        channel_names=(names[index],),
    )


def check_not_blank(top: Section, frames: list[tuple[str, str, np.ndarray]]) -> None:
    """Refuse a stripe image (``(key, name, pixels)`` each: a single exposure or one
    exposure of a bracket) that holds no image: NaN and Inf only (checked first in every
    frame: an image of nothing else is no image), one value ≤ 0 among frames that vary
    (a dropped frame: before, fitted as a shift, not converged without a word of it), or
    no value above 0 among frames with light (a float frame with an offset subtracted
    twice, which a fit takes for a minute to a gain of -387). Every frame alike is said
    later, with its cause."""
    for key, name, pixels in frames:
        if not np.isfinite(pixels).any():
            top.fail(key, f"{name}: every pixel value is NaN or Inf (a corrupt file?)")
    flat = [one_value(pixels) for _, _, pixels in frames]
    for (key, name, _), level in zip(frames, flat, strict=True):
        if level is not None and level <= 0 and None in flat:
            top.fail(
                key,
                f"{name}: every pixel value is {level:.6g}, unlike the other images (a "
                "dropped frame, or the projector or camera off?)",
            )
    largest = [
        float(np.max(pixels, initial=-np.inf, where=np.isfinite(pixels))) for *_, pixels in frames
    ]
    if max(largest) > 0:
        for (key, name, _), top_value in zip(frames, largest, strict=True):
            if top_value <= 0:
                top.fail(
                    key,
                    f"{name}: no pixel value is above 0 (the largest is {top_value:.6g}), "
                    "unlike the other images: images of light are not negative (an offset "
                    "subtracted from this one twice, or the projector or camera off?)",
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
                clip = float_clip(pixels)
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
        level = one_value(pixels) if key == "white_frame" else None
        if level is not None:
            top.fail(
                key,
                f"{name}: every pixel value is {level:.6g}: not a camera image of the "
                "projector showing all white (that varies over the medium)",
            )


# The name of a grey image's one channel (OpenEXR's, and simulate's).
GREY = "Y"


def read_calibration_frames(
    top: Section, base: Path, channel, frames: list[ImageData], notes: list[str]
) -> tuple[list[ImageData], dict[str, ImageData | None]]:
    """The calibration frames of single exposures (``None`` for a key not given), and
    the stripe images; where no ``channel`` is chosen and every channel of every image
    and calibration frame holds the same values (a grey image saved as colour), the
    images and frames reduced to one channel :data:`GREY` (noted): each channel would be
    fitted alike, three times the work for one answer listed three times. A file that
    gives values per channel (``dark_level`` by channel, a ``truth`` list, a response
    table) keeps the channels, with a note."""
    aux = {key: read_aux_frame(top, key, base, channel, frames[0]) for key in AUX_FRAMES}
    names = frames[0].channel_names
    given = [f for f in aux.values() if f is not None]
    if channel is not None or len(names) < 2:
        return frames, aux
    if not all(_one_value_per_pixel(f.pixels) for f in [*frames, *given]):
        return frames, aux
    where = "every image" + (" and calibration frame" if given else "")
    same = f"images: the channels {', '.join(names)} hold the same values in {where}"
    truth = top.data.get("truth")
    if (
        isinstance(top.data.get("dark_level"), dict)
        or isinstance(truth, list)
        or (isinstance(truth, dict) and any(isinstance(v, list) for v in truth.values()))
        or top.data.get("response", "linear") not in RESPONSES
    ):
        notes.append(
            f"{same}, but the file gives values per channel: each is fitted (channel: "
            f"{names[0]} fits one)"
        )
        return frames, aux
    notes.append(f"{same} (a grey image saved as colour): loaded as one channel {GREY}")

    def grey(frame: ImageData | None) -> ImageData | None:
        if frame is None or frame.pixels.shape[-1] == 1:
            return frame
        return dataclasses.replace(
            frame, pixels=np.ascontiguousarray(frame.pixels[..., :1]), channel_names=(GREY,)
        )

    return [grey(f) for f in frames], {k: grey(f) for k, f in aux.items()}


def _one_value_per_pixel(pixels: np.ndarray) -> bool:
    """Every channel of (height, width, channels) ``pixels`` holds the first's values
    (NaN where it has NaN)."""
    first = pixels[..., :1]
    return bool(np.all((pixels == first) | (np.isnan(pixels) & np.isnan(first))))
