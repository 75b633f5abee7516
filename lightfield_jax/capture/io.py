"""Image reading: captures in.

Reading: :func:`read_image` loads OpenEXR, TIFF (8/16-bit, float), PNG (8/16-bit) and
``.npy`` files into an ``(height, width, channels)`` float array in the image frame of
docs/model.md section 1 (row 0 at the top). Integer samples are scaled to [0, 1] by their
type's maximum (255 or 65535); float samples are kept as they are. Other integer samples
(signed, or 32-bit: some scientific cameras' TIFFs) are refused alike in a TIFF and a
``.npy``, naming the type: save them as uint16 or float32. The source sample
type is reported, so a caller can tell a saturated 8-bit pixel from a bright HDR one.

Writing is :mod:`lightfield_jax.capture.image_write` (images) and
:mod:`lightfield_jax.files` (atomic files and folders).

OpenImageIO is imported inside the functions that need it, so ``import lightfield_jax``
does not load it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import sys
import tempfile
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from lightfield_jax.files import require_regular_file
from lightfield_jax.runtime.memory import IMAGE_COPIES, check_memory, image_bytes

IMAGE_EXTENSIONS: tuple[str, ...] = (".exr", ".tif", ".tiff", ".png", ".npy")
# The attribute in which write_exr records the channel order: OpenEXR stores channels
# sorted by name (I1, I10, I2, ...), and OpenImageIO moves R, G, B, A to the front.
CHANNEL_ORDER_ATTR = "lightfield_jax:channels"
# Default channel names by channel count, as OpenImageIO names them.
_DEFAULT_NAMES = ("R", "G", "B", "A")
# The most channels a camera image holds (RGBA): a (height, width, channels) .npy with
# more is a stack of images.
_MAX_CHANNELS = 4


class CaptureError(ValueError):
    """An input image or file that cannot be used; the message names the file."""


class CaptureFileNotFoundError(CaptureError, FileNotFoundError):
    """An input file that does not exist."""


def require_capture_file(path: Path, what: str) -> None:
    """:func:`lightfield_jax.files.require_regular_file` for a capture's input: a
    :class:`CaptureError` (:class:`CaptureFileNotFoundError` where it is missing)."""
    require_regular_file(path, what, CaptureError, CaptureFileNotFoundError)


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
        return self.pixels[..., channel_index(self.channel_names, name, self.path)]


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
    require_capture_file(path, "an image file")
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
        index = [channel_index(image.channel_names, c, path) for c in wanted]
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
    require_capture_file(path, "an image file")
    if path.suffix.lower() == ".npy":
        return tuple(npy_header(path)[0])
    inp = _open_oiio(path)
    try:
        spec = inp.spec()
        return (spec.height, spec.width, spec.nchannels)
    finally:
        inp.close()


def channel_index(names: Sequence[str], channel: str | int, path: Path) -> int:
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
        raise CaptureError(f"{path}: not a readable .npy array ({error_line(e)})") from None
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


def load_npy(path: Path) -> np.ndarray:
    shape, dtype = npy_header(path)
    check_memory(
        IMAGE_COPIES * math.prod(shape) * max(dtype.itemsize, 4),
        f"{path} (shape {shape}, {dtype})",
    )
    try:
        a = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise CaptureError(f"{path}: not a readable .npy array ({error_line(e)})") from None
    if not a.dtype.isnative:  # big-endian data from another machine: native order
        a = a.astype(a.dtype.newbyteorder("="))
    return a


def error_line(error: BaseException) -> str:
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
    a = load_npy(path)
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
    require_capture_file(path, "a .npy stack")
    if path.suffix.lower() != ".npy":
        raise CaptureError(f"{path}: an image stack must be a .npy file")
    a = load_npy(path)
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


def _said_once(message: str, path: Path) -> str:
    """The library's ``message``, each line once, without "EXR Error (PATH): " (said 3 times)."""
    lines = [x.strip().removeprefix(f"EXR Error ({path}):").strip() for x in message.splitlines()]
    return "; ".join(dict.fromkeys(x for x in lines if x)) or "unknown error"


def _open_oiio(path: Path):
    """An open OpenImageIO reader of ``path`` at its first subimage, from its header
    alone. A file that holds several subimages (the pages of a multi-page TIFF, the parts
    of a multi-part EXR) is refused: only one would be read. MIP levels of one image are
    not subimages, and are not refused."""
    import OpenImageIO as oiio

    with _library_stderr():
        inp = oiio.ImageInput.open(oiio_name(path))
    if inp is None:
        raise CaptureError(f"{path}: cannot read image ({_said_once(oiio.geterror(), path)})")
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
            why = _said_once(inp.geterror() or oiio.geterror(), path)
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
            why = _said_once(inp.geterror() or oiio.geterror(), path)
            raise CaptureError(f"{path}: cannot read pixels ({why})")
        bits = spec.get_int_attribute("oiio:BitsPerSample", 0) or spec.format.size() * 8
        sample_type = str(spec.format)
        names = tuple(spec.channelnames)
        order = spec.get_string_attribute(CHANNEL_ORDER_ATTR, "")
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


__all__ = [
    "IMAGE_EXTENSIONS",
    "CaptureError",
    "CaptureFileNotFoundError",
    "ImageData",
    "read_image",
    "read_npy_stack",
    "require_capture_file",
]
