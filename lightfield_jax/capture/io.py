"""Image and file I/O: captures in, renders and reports out.

Reading: :func:`read_image` loads OpenEXR, TIFF (8/16-bit, float), PNG (8/16-bit) and
``.npy`` files into an ``(height, width, channels)`` float array in the image frame of
docs/model.md section 1 (row 0 at the top). Integer samples are scaled to [0, 1] by their
type's maximum (255 or 65535); float samples are kept as they are. Other integer samples
(signed, or 32-bit: some scientific cameras' TIFFs) are refused alike in a TIFF and a
``.npy``, naming the type: save them as uint16 or float32. The source sample
type is reported, so a caller can tell a saturated 8-bit pixel from a bright HDR one.

Writing: every writer is atomic. It writes a temporary file in the target's directory
and renames it over the target with :func:`os.replace`, so a reader (or a crash) never
sees a half-written file. :func:`atomic_directory` does the same for a command that
writes several files into one folder: nothing appears in the folder unless the whole
command succeeds.

OpenImageIO is imported inside the functions that need it, so ``import lightfield_jax``
does not load it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import math
import os
import re
import secrets
import shutil
import stat
import sys
import tempfile
import threading
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lightfield_jax.app.memory import IMAGE_COPIES, check_memory, image_bytes

IMAGE_EXTENSIONS: tuple[str, ...] = (".exr", ".tif", ".tiff", ".png", ".npy")
# The attribute in which write_exr records the channel order: OpenEXR stores channels
# sorted by name (I1, I10, I2, ...), and OpenImageIO moves R, G, B, A to the front.
_CHANNEL_ORDER_ATTR = "lightfield_jax:channels"
# Default channel names by channel count, as OpenImageIO names them.
_DEFAULT_NAMES = ("R", "G", "B", "A")
# The most channels a camera image holds (RGBA): a (height, width, channels) .npy with
# more is a stack of images.
_MAX_CHANNELS = 4


class CaptureError(ValueError):
    """An input image or file that cannot be used; the message names the file."""


class CaptureFileNotFoundError(CaptureError, FileNotFoundError):
    """An input file that does not exist."""


@dataclasses.dataclass(frozen=True, eq=False)
class ImageData:
    """An image read by :func:`read_image`.

    Attributes:
        pixels: float array (height, width, channels); float32, or float64 when the
            source holds doubles. Integer sources are scaled to [0, 1].
        channel_names: one name per channel (e.g. ``("R", "G", "B")``, ``("I1", "I2")``).
        bit_depth: bits per sample in the source (8, 16, 32, 64; 12 for a 12-bit file).
        path: the file read.
        sample_type: the source's sample type: ``"uint8"``, ``"uint16"``, ``"half"``,
            ``"float"`` or ``"double"`` (others as OpenImageIO or numpy name them).
    """

    pixels: np.ndarray
    channel_names: tuple[str, ...]
    bit_depth: int
    path: Path
    sample_type: str = "float"

    def __repr__(self) -> str:
        return (
            f"ImageData(shape={self.pixels.shape}, dtype={self.pixels.dtype}, "
            f"channel_names={self.channel_names}, bit_depth={self.bit_depth}, "
            f"sample_type={self.sample_type!r}, path={str(self.path)!r})"
        )

    @property
    def is_integer(self) -> bool:
        """True when the source stored integer samples (scaled here to [0, 1])."""
        return self.sample_type.startswith(("uint", "int"))

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.pixels.shape

    def channel(self, name: str) -> np.ndarray:
        """The (height, width) plane of the channel called ``name``."""
        return self.pixels[..., _channel_index(self.channel_names, name, self.path)]


# --------------------------------------------------------------------------- reading


def read_image(
    path: str | os.PathLike,
    channel: str | int | Sequence[str | int] | None = None,
    *,
    n_channels: int | None = None,
) -> ImageData:
    """Read an image as (height, width, channels) floats.

    Args:
        path: an ``.exr``, ``.tif``/``.tiff``, ``.png`` or ``.npy`` file. A ``.npy``
            array is (height, width) or (height, width, 1-4 channels); uint8/uint16
            arrays are scaled like image files, float arrays kept.
        channel: keep only this channel (a name or an index) or these channels, in the
            order given; ``None`` keeps all.
        n_channels: when given, the number of channels the caller expects (after the
            selection); anything else is an error.

    Raises:
        CaptureFileNotFoundError: the file does not exist.
        CaptureError: unsupported extension, unreadable file, unknown channel, or an
            unexpected channel count. Every message names the file.
    """
    path = Path(path)
    ext = path.suffix.lower()
    require_regular_file(path, "an image file")
    if ext not in IMAGE_EXTENSIONS:
        why = (
            " (JPEG's lossy 8x8-block compression distorts the faint scattered light the "
            "fit measures: save the camera's raw files as 16-bit TIFF or PNG)"
            if ext in (".jpg", ".jpeg", ".jfif")
            else ""
        )
        raise CaptureError(
            f"{path}: unsupported image extension {path.suffix!r}; "
            f"supported: {', '.join(IMAGE_EXTENSIONS)}{why}"
        )
    image = _read_npy(path, channel is None) if ext == ".npy" else _read_oiio(path)
    if channel is not None:
        wanted = [channel] if isinstance(channel, (str, int, np.integer)) else list(channel)
        index = [_channel_index(image.channel_names, c, path) for c in wanted]
        image = dataclasses.replace(
            image,
            pixels=np.ascontiguousarray(image.pixels[..., index]),
            channel_names=tuple(image.channel_names[i] for i in index),
        )
    if n_channels is not None and image.pixels.shape[-1] != n_channels:
        raise CaptureError(
            f"{path}: expected {n_channels} channel(s), found {image.pixels.shape[-1]} "
            f"({', '.join(image.channel_names)})"
        )
    return image


def require_regular_file(path: Path, what: str, error: type[ValueError] = CaptureError) -> None:
    """Refuse, before opening it, a ``path`` that is missing or not a regular file (a
    folder, a FIFO that would block the read forever, a device)."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        if error is CaptureError:
            raise CaptureFileNotFoundError(f"{path}: file not found") from None
        raise error(f"{path}: file not found") from None
    except OSError as e:
        raise error(f"{path}: cannot read ({e.strerror})") from None
    if stat.S_ISDIR(mode):
        raise error(f"{path}: is a directory, not {what}")
    if not stat.S_ISREG(mode):
        raise error(f"{path}: is not a regular file (a FIFO, device or socket), not {what}")


def oiio_name(path: str | os.PathLike, error: type[Exception] = CaptureError) -> str:
    """``path`` as the image library takes it: a name that is valid UTF-8. A file or
    folder named in another encoding (bytes Python holds as surrogates) is ``error``,
    naming it, not the library's "incompatible function arguments" traceback."""
    name = os.fspath(path)
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        raise error(
            f"{name}: the path is not valid UTF-8 (a file or folder named in another "
            "encoding), which the image library cannot open; rename it"
        ) from None
    return name


def image_values(path: str | os.PathLike) -> int:
    """The number of samples (height × width × channels, × images for a ``.npy``
    stack) a file decodes to, from its header alone (no pixels read)."""
    return math.prod(image_shape(path))


def image_shape(path: str | os.PathLike) -> tuple[int, ...]:
    """The shape a file decodes to, from its header alone (no pixels read): (height,
    width, channels) for an image file, the array's shape for a ``.npy``."""
    path = Path(path)
    require_regular_file(path, "an image file")
    if path.suffix.lower() == ".npy":
        return tuple(npy_header(path)[0])
    inp = _open_oiio(path)
    try:
        spec = inp.spec()
        return (spec.height, spec.width, spec.nchannels)
    finally:
        inp.close()


def _channel_index(names: Sequence[str], channel: str | int, path: Path) -> int:
    if isinstance(channel, (int, np.integer)) and not isinstance(channel, bool):
        if not 0 <= channel < len(names):
            raise CaptureError(
                f"{path}: channel index {channel} out of range for {len(names)} channel(s)"
            )
        return int(channel)
    if channel not in names:
        raise CaptureError(f"{path}: no channel named {channel!r}; channels: {', '.join(names)}")
    return list(names).index(channel)


def _default_names(n: int) -> tuple[str, ...]:
    if n == 1:
        return ("Y",)
    return tuple(_DEFAULT_NAMES[i] if i < 4 else f"channel{i}" for i in range(n))


def npy_header(path: Path) -> tuple[tuple[int, ...], np.dtype]:
    """The shape and dtype a ``.npy`` file declares, checked against the file's size
    (a header claiming more data than the file holds is refused before any read)."""
    try:
        with open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(f)
            else:
                shape, _, dtype = np.lib.format.read_array_header_2_0(f)
            offset = f.tell()
    except (OSError, ValueError, EOFError) as e:
        raise CaptureError(f"{path}: not a readable .npy array ({_one_line(e)})") from None
    if dtype.hasobject:
        raise CaptureError(f"{path}: holds Python objects, not numbers")
    count = math.prod(shape)
    declared = count * dtype.itemsize
    held = os.path.getsize(path) - offset
    if declared > held:
        raise CaptureError(
            f"{path}: the header declares shape {shape} of {dtype} ({declared} bytes), but "
            f"the file holds {held} bytes of data (truncated or corrupt)"
        )
    return shape, dtype


def _load_npy(path: Path) -> np.ndarray:
    shape, dtype = npy_header(path)
    check_memory(
        IMAGE_COPIES * math.prod(shape) * max(dtype.itemsize, 4),
        f"{path} (shape {shape}, {dtype})",
    )
    try:
        a = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise CaptureError(f"{path}: not a readable .npy array ({_one_line(e)})") from None
    if not a.dtype.isnative:  # big-endian data from another machine: native order
        a = a.astype(a.dtype.newbyteorder("="))
    return a


def _one_line(error: BaseException) -> str:
    return " ".join(str(error).split())[:200]


def _npy_image(a: np.ndarray, path: Path) -> ImageData:
    """An (..., height, width, channels) array as image data (integers scaled to [0, 1])."""
    if a.dtype in (np.uint8, np.uint16):
        pixels = a.astype(np.float32) / np.float32(np.iinfo(a.dtype).max)
    elif a.dtype in (np.float16, np.float32):
        pixels = a.astype(np.float32)
    elif a.dtype == np.float64:
        pixels = a
    elif a.dtype.kind in "iu":
        raise _integer_samples(path, "array dtype", a.dtype.name)
    else:
        raise CaptureError(
            f"{path}: unsupported array dtype {a.dtype}; expected uint8, uint16, "
            "float16, float32 or float64"
        )
    sample_type = {"float16": "half", "float32": "float", "float64": "double"}.get(
        a.dtype.name, a.dtype.name
    )
    return ImageData(
        pixels=np.ascontiguousarray(pixels),
        channel_names=_default_names(a.shape[-1]),
        bit_depth=a.dtype.itemsize * 8,
        path=path,
        sample_type=sample_type,
    )


def _integer_samples(path: Path, what: str, name: str) -> CaptureError:
    """The refusal of integer samples other than uint8 and uint16 (``name``: numpy's
    name, e.g. ``int16``, ``uint32``), alike for a TIFF and a ``.npy``. Their scale is
    not a camera's: a signed 16-bit TIFF would be scaled by 32767 (counts up to 65535
    from some scientific cameras wrapped to negative values), a 32-bit one by 2^32 - 1, and
    the top code of a clipped sensor, the response table and dark_level in codes /
    65535 all count in 8 or 16 unsigned bits."""
    bits = np.dtype(name).itemsize * 8
    kind = "unsigned" if name.startswith("u") else "signed"
    return CaptureError(
        f"{path}: unsupported {what} {name} ({kind} {bits}-bit integers): integer samples "
        "are read as unsigned 8- or 16-bit (scaled by 255 or 65535); save the counts as "
        "uint16 (0..65535) or as float32"
    )


def _read_npy(path: Path, whole: bool = True) -> ImageData:
    """A ``.npy`` image; ``whole``: every channel is kept (none chosen), so that one
    with more than :data:`_MAX_CHANNELS` is taken for a stack saved as one image."""
    a = _load_npy(path)
    shape = a.shape
    if a.ndim == 2:
        a = a[..., None]
    # An empty one (a height of 0) is named as such, not as 'every pixel value is NaN or
    # Inf' (an image) or a size mismatch of '0x24 pixels' (a dark frame).
    if a.ndim != 3 or 0 in a.shape:
        raise CaptureError(
            f"{path}: expected a (height, width) or (height, width, channels) array, "
            f"got shape {shape}{' (no pixels)' if a.ndim == 3 else ''}"
        )
    if whole and a.shape[-1] > _MAX_CHANNELS:
        # A stack of images saved as one image file, not a 24x32 image with 32 channels
        # (which would be refused as having 'a varying alpha channel').
        n, height, width = a.shape
        raise CaptureError(
            f"{path}: shape {a.shape} looks like a stack of {n} images ({height} x {width}, "
            f"height x width), not one image with {width} channels (a camera image has at "
            f"most {_MAX_CHANNELS}): give a stack alone as the capture file's images "
            f"(images: {path.name}), or save one file per image and list them"
        )
    return _npy_image(a, path)


def read_npy_stack(path: str | os.PathLike) -> list[ImageData]:
    """Read a ``.npy`` stack of images, (images, height, width) or (images, height,
    width, channels), as one :class:`ImageData` per image (scaled like
    :func:`read_image`)."""
    path = Path(path)
    require_regular_file(path, "a .npy stack")
    if path.suffix.lower() != ".npy":
        raise CaptureError(f"{path}: an image stack must be a .npy file")
    a = _load_npy(path)
    if a.ndim == 3:
        a = a[..., None]
    if a.ndim != 4 or 0 in a.shape:
        raise CaptureError(
            f"{path}: expected an (images, height, width) or (images, height, width, "
            f"channels) stack, got shape {a.shape}"
        )
    stack = _npy_image(a, path)
    return [dataclasses.replace(stack, pixels=frame) for frame in stack.pixels]


# Subimages counted at most: a hostile file with a million pages is refused as "more
# than 100" without seeking through them all.
_MAX_SUBIMAGES = 100
# What one subimage is called in the formats that hold several.
_SUBIMAGE_WORDS = {"tiff": ("page", "a multi-page TIFF"), "openexr": ("part", "a multi-part EXR")}


# Lines an image library prints on the process's stderr itself, besides the error
# OpenImageIO reports (which the message quotes): libpng's "libpng error: ...".
_LIBRARY_LINES = (b"libpng error:", b"libpng warning:")
_STDERR_LOCK = threading.Lock()


@contextlib.contextmanager
def _library_stderr() -> Iterator[None]:
    """Within the block, the lines the image libraries print on stderr (file descriptor
    2) are held and dropped where they are :data:`_LIBRARY_LINES` (the error they
    report is in the one-line message); any other output is passed on after it."""
    try:
        held = tempfile.TemporaryFile()
    except OSError:  # no temporary folder: the lines are shown as printed
        yield
        return
    try:
        saved = os.dup(2)
    except OSError:  # no stderr to keep clean
        held.close()
        yield
        return
    with _STDERR_LOCK, held:
        with contextlib.suppress(Exception):
            sys.stderr.flush()
        os.dup2(held.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            held.seek(0)
            kept = [
                line
                for line in held.read().splitlines(keepends=True)
                if not line.startswith(_LIBRARY_LINES)
            ]
            if kept:
                with contextlib.suppress(OSError):
                    os.write(2, b"".join(kept))


def _open_oiio(path: Path):
    """An open OpenImageIO reader of ``path`` at its first subimage, from its header
    alone. A file that holds several subimages (the pages of a multi-page TIFF, the parts
    of a multi-part EXR) is refused: only one would be read. MIP levels of one image are
    not subimages, and are not refused."""
    import OpenImageIO as oiio

    with _library_stderr():
        inp = oiio.ImageInput.open(oiio_name(path))
    if inp is None:
        raise CaptureError(f"{path}: cannot read image ({oiio.geterror() or 'unknown error'})")
    try:
        count = 1
        while count <= _MAX_SUBIMAGES and inp.seek_subimage(count, 0):
            count += 1
        inp.geterror()  # the failed seek's message (TIFF), not an error of the file
        if count > 1:
            word, kind = _SUBIMAGE_WORDS.get(inp.format_name(), ("subimage", "a multi-image file"))
            many = f"more than {_MAX_SUBIMAGES}" if count > _MAX_SUBIMAGES else str(count)
            raise CaptureError(
                f"{path}: holds {many} {word}s ({kind}), but only one image per file is "
                f"read: save each {word} as a file of its own and list each file"
            )
        if not inp.seek_subimage(0, 0):
            why = inp.geterror() or oiio.geterror() or "unknown error"
            raise CaptureError(f"{path}: cannot read image ({why})")
    except BaseException:
        inp.close()
        raise
    return inp


def _read_oiio(path: Path) -> ImageData:
    import OpenImageIO as oiio

    inp = _open_oiio(path)
    try:
        spec = inp.spec()
        check_memory(
            image_bytes(spec.height, spec.width, spec.nchannels, spec.format.size()),
            f"{path} ({spec.width}x{spec.height}, {spec.nchannels} channel(s))",
        )
        if spec.deep or spec.depth > 1:
            raise CaptureError(f"{path}: deep and volume images are not supported")
        if (spec.x, spec.y, spec.width, spec.height) != (
            spec.full_x,
            spec.full_y,
            spec.full_width,
            spec.full_height,
        ):
            raise CaptureError(
                f"{path}: the data window ({spec.x}, {spec.y}, {spec.width}x{spec.height}) "
                f"differs from the display window ({spec.full_x}, {spec.full_y}, "
                f"{spec.full_width}x{spec.full_height}); crop or pad the image first"
            )
        base = spec.format.basetype
        if base not in (oiio.UINT8, oiio.UINT16, oiio.HALF, oiio.FLOAT, oiio.DOUBLE):
            # Not read scaled by the type's range (int16 by 32767, uint32 by 2^32 - 1).
            signed = base in (oiio.INT8, oiio.INT16, oiio.INT32, oiio.INT64)
            name = f"{'' if signed else 'u'}int{spec.format.size() * 8}"
            raise _integer_samples(path, "sample type", name)
        # Reading with an explicit type; OpenImageIO scales integers to [0, 1].
        fmt = oiio.DOUBLE if base == oiio.DOUBLE else oiio.FLOAT
        with _library_stderr():
            pixels = inp.read_image(0, 0, 0, spec.nchannels, fmt)
        if pixels is None:
            raise CaptureError(f"{path}: cannot read pixels ({inp.geterror() or oiio.geterror()})")
        bits = spec.get_int_attribute("oiio:BitsPerSample", 0) or spec.format.size() * 8
        sample_type = str(spec.format)
        names = tuple(spec.channelnames)
        order = spec.get_string_attribute(_CHANNEL_ORDER_ATTR, "")
    finally:
        inp.close()
    pixels = np.asarray(pixels).reshape(spec.height, spec.width, spec.nchannels)
    stored = tuple(order.split(",")) if order else ()
    if sorted(stored) == sorted(names):
        pixels = pixels[..., [names.index(n) for n in stored]]
        names = stored
    return ImageData(
        pixels=np.ascontiguousarray(pixels),
        channel_names=names,
        bit_depth=int(bits),
        path=path,
        sample_type=sample_type,
    )


# --------------------------------------------------------------------------- writing


def write_exr(
    path: str | os.PathLike,
    channels: Mapping[str, np.ndarray],
    *,
    metadata: Mapping[str, str | int | float] | None = None,
) -> Path:
    """Write a float32 OpenEXR file with named channels (atomically).

    Args:
        path: the ``.exr`` file.
        channels: channel name → (height, width) array, e.g. ``{"I1": i1, "I2": i2}``.
            The order is recorded, and :func:`read_image` returns channels in it.
        metadata: extra header attributes (string, int or float values).
    """
    path = Path(path)
    if not isinstance(channels, Mapping):  # an array has no names (nor one truth value)
        shape = f" of shape {np.shape(channels)}" if hasattr(channels, "shape") else ""
        raise TypeError(
            f"{path}: write_exr: channels must map each channel's name to a (height, width) "
            f"array (e.g. {{'Y': image}}), got {type(channels).__name__}{shape}"
        )
    if not channels:
        raise ValueError(f"{path}: write_exr needs at least one channel")
    names = list(channels)
    for name in names:
        if not isinstance(name, str) or not name or "," in name:
            raise ValueError(f"{path}: channel names must be non-empty strings without ','")
    planes = [np.asarray(channels[n]) for n in names]
    shape = planes[0].shape
    for name, plane in zip(names, planes, strict=True):
        if plane.ndim != 2 or plane.shape != shape:
            raise ValueError(
                f"{path}: channel {name!r} has shape {plane.shape}; every channel must be "
                f"a 2-D array of the same shape (first is {shape})"
            )
    pixels = np.stack(planes, axis=-1).astype(np.float32)
    attrs = {"compression": "zip", **(metadata or {}), _CHANNEL_ORDER_ATTR: ",".join(names)}
    _write_oiio(path, pixels, "float", names, attrs)
    return path


def write_png(path: str | os.PathLike, array: np.ndarray, bits: int = 8) -> Path:
    """Write an 8- or 16-bit PNG (atomically).

    ``array`` is (height, width) or (height, width, 1–4 channels). Float arrays must lie
    in [0, 1] and are scaled to the integer range (rounded); integer arrays are written
    as codes and must fit in ``bits``; boolean arrays map to 0 and the maximum.
    """
    if bits not in (8, 16):
        raise ValueError(f"write_png: bits must be 8 or 16, got {bits!r}")
    pixels = _to_hwc(path, array)
    if not 1 <= pixels.shape[-1] <= 4:
        raise ValueError(f"{path}: a PNG holds 1 to 4 channels, got {pixels.shape[-1]}")
    return _write_oiio(Path(path), _quantize(path, pixels, bits), f"uint{bits}", None, {})


def write_tiff(path: str | os.PathLike, array: np.ndarray, bits: int = 16) -> Path:
    """Write a 16-bit integer or 32-bit float TIFF (atomically).

    ``bits=16`` quantises like :func:`write_png`; ``bits=32`` writes float32 values as
    they are. ``array`` is (height, width) or (height, width, channels).
    """
    if bits not in (16, 32):
        raise ValueError(f"write_tiff: bits must be 16 or 32, got {bits!r}")
    pixels = _to_hwc(path, array)
    if bits == 16:
        data, fmt = _quantize(path, pixels, 16), "uint16"
    else:
        data, fmt = pixels.astype(np.float32), "float"
    return _write_oiio(Path(path), data, fmt, None, {"compression": "zip"})


def _to_hwc(path, array) -> np.ndarray:
    a = np.asarray(array)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or 0 in a.shape:
        raise ValueError(
            f"{path}: expected a (height, width) or (height, width, channels) array, "
            f"got shape {np.shape(array)}"
        )
    return a


def _quantize(path, a: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    dtype = np.uint8 if bits == 8 else np.uint16
    if a.dtype == bool:
        return np.where(a, top, 0).astype(dtype)
    if np.issubdtype(a.dtype, np.integer):
        if a.min() < 0 or a.max() > top:
            raise ValueError(
                f"{path}: integer codes must lie in [0, {top}] for {bits}-bit output, "
                f"got [{a.min()}, {a.max()}]"
            )
        return a.astype(dtype)
    if not np.all(np.isfinite(a)) or a.min() < 0.0 or a.max() > 1.0:
        raise ValueError(
            f"{path}: float values must be finite and lie in [0, 1] for {bits}-bit output, "
            f"got [{a.min()}, {a.max()}]"
        )
    return np.rint(a * top).astype(dtype)


def _write_oiio(
    path: Path,
    pixels: np.ndarray,
    fmt: str,
    names: Sequence[str] | None,
    attrs: Mapping[str, str | int | float],
) -> Path:
    import OpenImageIO as oiio

    pixels = np.ascontiguousarray(pixels)  # (H, W, C): a 2-D array is written wrongly
    height, width, n = pixels.shape
    spec = oiio.ImageSpec(width, height, n, getattr(oiio, fmt.upper()))
    if names is not None:
        spec.channelnames = tuple(names)
    for key, value in attrs.items():
        spec.attribute(key, value)
    oiio_name(path, ValueError)  # its temporary beside it is named alike
    with atomic_path(path) as tmp:
        name = str(tmp)
        out = oiio.ImageOutput.create(name)
        if out is None:
            raise OSError(f"{path}: cannot create an image writer ({oiio.geterror()})")
        try:
            if not out.open(name, spec):
                raise OSError(f"{path}: cannot open for writing ({out.geterror()})")
            if not out.write_image(pixels):
                raise OSError(f"{path}: write failed ({out.geterror()})")
        finally:
            out.close()
    return path


# --------------------------------------------------------------------------- atomic files


# Temporaries not yet published or removed: removed by remove_temporaries() when the
# command is stopped by a signal (see _signals).
_TEMPORARIES: set[Path] = set()


# The name of a temporary: ``.NAME.tmp-PID-HEX.EXT``, PID the process writing it. One
# whose process is gone (killed by SIGKILL, a power cut) is stale: the next command
# writing beside it removes it (:func:`_sweep_stale`).
_TEMPORARY_NAME = re.compile(r"\..*\.tmp-(\d+)-[0-9a-f]{8}(\.[^.]*)?", re.DOTALL)
# The longest file name most file systems take (bytes); a temporary's name is kept
# within it whatever the target's length (a 250-byte name, or a long extension).
_NAME_MAX = 255
# An extension longer than this is left off a temporary's name: the writers that pick
# a format by the extension (images, figures) take short ones only.
_MAX_SUFFIX = 16
# Folders already swept of stale temporaries by this process.
_SWEPT: set[str] = set()


def _temporary_name(path: Path) -> str:
    """A fresh temporary name for ``path``: hidden, its extension kept (the writers
    pick a format by it), at most :data:`_NAME_MAX` bytes (the target's name cut)."""
    suffix = path.suffix if len(os.fsencode(path.suffix)) <= _MAX_SUFFIX else ""
    tail = f".tmp-{os.getpid()}-{secrets.token_hex(4)}{suffix}"
    room = _NAME_MAX - 1 - len(os.fsencode(tail))
    stem = os.fsencode(path.name)[:room].decode(errors="ignore")  # whole characters
    return f".{stem}{tail}"


def _sweep_stale(folder: Path) -> None:
    """Remove, once per folder and process, the temporaries there (files and staging
    folders of :data:`_TEMPORARY_NAME`) whose process no longer runs on this machine:
    what a killed command left."""
    key = os.path.abspath(folder)
    if key in _SWEPT:
        return
    _SWEPT.add(key)
    try:
        with os.scandir(folder) as entries:
            names = [e.name for e in entries if e.name.startswith(".")]
    except OSError:
        return
    for name in names:
        match = _TEMPORARY_NAME.fullmatch(name)
        if match is None or _running(int(match.group(1))):
            continue
        stale = folder / name
        if stale.is_dir() and not stale.is_symlink():
            shutil.rmtree(stale, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                stale.unlink()


def _running(pid: int) -> bool:
    """Whether process ``pid`` runs on this machine (ours included)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):  # none (or no process id at all)
        return False
    except OSError:  # another user's: running
        return True
    return True


def _reserve(path: Path, make) -> Path:
    """Create a uniquely named sibling of ``path`` (hidden, same extension) with ``make``;
    it is registered as a temporary until :func:`forget_temporary`. Stale temporaries
    beside it (of a killed command) are removed first."""
    _sweep_stale(path.parent)
    for _ in range(100):
        candidate = path.with_name(_temporary_name(path))
        try:
            make(candidate)
        except FileExistsError:
            continue
        _TEMPORARIES.add(candidate)
        return candidate
    raise FileExistsError(f"{path}: could not create a temporary name beside it")


def forget_temporary(path: Path) -> None:
    """``path`` was published or removed: no longer a temporary to clean up."""
    _TEMPORARIES.discard(path)


# Folders made to hold outputs not yet published, outermost first: removed (where still
# empty) when the command fails or is stopped by a signal, so that a failed command
# leaves no empty folders of its output's path (render bad.json --out new/a/view: new/a).
_MADE_FOLDERS: list[Path] = []


def make_folders(folder: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; the ones made, outermost first, are
    registered for :func:`remove_made_folders` until :func:`keep_made_folders`."""
    missing = []
    for f in (folder, *folder.parents):
        if os.path.lexists(f):
            break
        missing.append(f)
    made = []
    for f in reversed(missing):
        try:
            os.mkdir(f)
        except FileExistsError:  # made meanwhile (a folder or not: said by the next step)
            continue
        made.append(f)
        _MADE_FOLDERS.append(f)
    return made


def keep_made_folders(made: Sequence[Path]) -> None:
    """The folders ``made`` hold published outputs: no longer to remove."""
    for f in made:
        with contextlib.suppress(ValueError):
            _MADE_FOLDERS.remove(f)


def remove_made_folders(made: Sequence[Path] | None = None) -> None:
    """Remove the folders ``made`` (default: every one registered), innermost first,
    where they are still empty."""
    for f in reversed(list(_MADE_FOLDERS if made is None else made)):
        with contextlib.suppress(OSError):
            os.rmdir(f)
    keep_made_folders(list(_MADE_FOLDERS if made is None else made))


def remove_temporaries() -> None:
    """Remove every temporary file and staging folder not yet published (on a signal),
    and the folders made for them where they are left empty."""
    for path in list(_TEMPORARIES):
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                path.unlink()
        _TEMPORARIES.discard(path)
    remove_made_folders()


def _make_file(p: Path) -> None:
    # Mode 0o666 lets the umask decide permissions, as for any new file.
    os.close(os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))


def _fsync(p: Path) -> None:
    fd = os.open(p, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_failure(error: OSError, target: Path) -> OSError | None:
    """The error of a writer that failed for want of space (or an I/O error), naming
    ``target`` (the output the user named, not its temporary); ``None`` for any other
    error. Writers that report no errno (numpy's "N requested and M written", an EXR
    library's "write failed") are named too, as "no space left on device" when the
    target's file system has no free space."""
    if error.errno in _WRITE_ERRNOS:
        return OSError(error.errno, error.strerror or os.strerror(error.errno), str(target))
    if error.errno is not None or type(error) is not OSError:
        return None
    if error.filename is not None and error.strerror:
        # Already named by an inner output (a file in a staged folder): keep its words,
        # not its temporary's name (not "write failed ([Errno None] write failed ...").
        return OSError(None, error.strerror, str(target))
    message = " ".join(str(error).split()) or "write failed"
    with contextlib.suppress(OSError):
        folder = next(p for p in (target, *target.parents) if p.exists())
        if os.statvfs(folder).f_bavail == 0:
            return OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)} ({message})", str(target))
    return OSError(None, f"write failed ({message})", str(target))


_WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO}


@contextlib.contextmanager
def naming_output(target: str | os.PathLike) -> Iterator[None]:
    """Re-raise a writer's failure for want of space as an ``OSError`` naming ``target``
    (see :func:`_write_failure`); other errors, and one that already names ``target``
    or a file in it (an inner output's own name), pass unchanged."""
    try:
        yield
    except OSError as e:
        named = e.filename
        if isinstance(named, (str, bytes)) and Path(os.fsdecode(named)).is_relative_to(target):
            raise
        failure = _write_failure(e, Path(target))
        if failure is None:
            raise
        raise failure from e


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it replaces ``path``.

    Write the file's content to the yielded path (any writer: numpy, OpenImageIO,
    matplotlib; the temporary keeps the extension). When the block raises, the
    temporary is removed and ``path`` is left as it was. Parent folders are created.
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path}: is a directory")
    if path in _TEMPORARIES:
        # Already a temporary (staged_files'): written in place, published by its owner,
        # not staged again under a temporary of the temporary's name.
        with naming_output(path):
            yield path
        return
    made = make_folders(path.parent)
    try:
        tmp = _reserve(path, _make_file)
    except BaseException:
        remove_made_folders(made)
        raise
    try:
        with naming_output(path):
            yield tmp
            _fsync(tmp)
            os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        remove_made_folders(made)
        raise
    finally:
        forget_temporary(tmp)
    keep_made_folders(made)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode(encoding))


def _json_default(obj: Any):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"Object of type {type(obj).__name__} is not JSON serializable")


def atomic_write_json(path: str | os.PathLike, obj: Any, *, indent: int = 2) -> Path:
    """Write ``obj`` as JSON atomically (numpy scalars and arrays, paths allowed).

    Strict JSON: NaN and infinity are refused (``ValueError``); write ``None`` for a
    missing value.
    """
    text = json.dumps(obj, indent=indent, allow_nan=False, default=_json_default)
    return atomic_write_text(path, text + "\n")


def atomic_write_npy(path: str | os.PathLike, array: np.ndarray) -> Path:
    """Save ``array`` as ``.npy`` atomically (no pickled objects)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, np.asarray(array), allow_pickle=False)
    return Path(path)


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike) -> Iterator[Path]:
    """Stage a folder's output; publish it into ``path`` only when the block succeeds.

    Yields a hidden staging folder beside ``path``: write every output file there.
    On success, a ``path`` that did not exist (or was empty) becomes the staging folder
    in one rename; an existing ``path`` receives the staged files one ``os.replace``
    each, so files it held that the block did not write are kept. On an exception the
    staging folder is deleted and ``path`` is untouched.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise NotADirectoryError(f"{path}: exists and is not a directory")
    keep_folder = path.name in ("", "..")
    if keep_folder:
        # ".", "..", "/": the staging folder is named after the folder
        # (not "PosixPath('.') has an empty name"), and the files are moved into it: a rename
        # over an empty "." would leave the caller's shell in a deleted folder.
        given, path = path, Path(os.path.abspath(path))
        if not path.name:
            raise CaptureError(f"{given}: the root folder cannot be an output folder")
    made = make_folders(path.parent)
    published = False
    try:
        stage = _reserve(path, lambda p: os.mkdir(p, 0o777))
        try:
            with naming_output(path):
                yield stage
                _publish(stage, path, keep_folder)
                published = True
        finally:
            shutil.rmtree(stage, ignore_errors=True)
            forget_temporary(stage)
    finally:
        if published:
            keep_made_folders(made)
        else:  # nothing written: nor the folders made to hold it
            remove_made_folders(made)


def _publish(stage: Path, path: Path, keep_folder: bool = False) -> None:
    if not path.is_symlink() and not (keep_folder and path.is_dir()):
        try:
            os.rename(stage, path)  # replaces a missing or empty folder atomically
            return
        except OSError as e:
            if e.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                raise
    moves = []
    for root, _dirs, files in os.walk(stage):
        rel = Path(root).relative_to(stage)
        target_dir = path / rel
        if target_dir.exists() and not target_dir.is_dir():
            raise NotADirectoryError(f"{target_dir}: exists and is not a directory")
        for name in files:
            if (target_dir / name).is_dir():
                raise IsADirectoryError(f"{target_dir / name}: is a directory")
            moves.append((Path(root) / name, target_dir / name))
    for src, dst in moves:
        dst.parent.mkdir(parents=True, exist_ok=True)
        os.replace(src, dst)


__all__ = [
    "IMAGE_EXTENSIONS",
    "CaptureError",
    "CaptureFileNotFoundError",
    "ImageData",
    "atomic_directory",
    "atomic_path",
    "atomic_write_bytes",
    "atomic_write_json",
    "atomic_write_npy",
    "atomic_write_text",
    "read_image",
    "read_npy_stack",
    "require_regular_file",
    "write_exr",
    "write_png",
    "write_tiff",
]
