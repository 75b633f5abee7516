"""The capture format: shifted stripe images of a medium, and how they were taken.

A capture is a YAML file next to its images (``lightfield-jax simulate`` writes one for
stripe illumination; the inverse pipeline reads it)::

    images: [shift_00.exr, shift_01.exr, shift_02.exr, shift_03.exr, shift_04.exr, shift_05.exr]
    pattern: {period: 6, lit: 3, phases: [0, 1, 2, 3, 4, 5], direction_deg: 0.0, entry: left}
    dark_frame: dark.exr         # optional
    black_level: 0.0             # optional
    medium_roi: [x0, y0, x1, y1] # optional
    pixel_size_mm: 0.05          # optional
    saturation: 0.98             # optional
    channel: all                 # optional
    geometry: {kind: plane}      # optional
    truth: {sigma_t: 0.2051, sigma_s: 0.0366, g: 0.4, gain: 1.0, phase: paper}  # optional

Keys:

- ``images``: a list of image files (paths relative to the capture file; OpenEXR,
  TIFF, PNG or ``.npy``, all the same size and channel count), one per phase; or one
  ``.npy`` stack of shape [P, H, W] or [P, H, W, C]. Integer samples are scaled to
  [0, 1] by their type's maximum (see :func:`~lightfield_jax._io.read_image`).
- ``pattern``: the projected stripes (MODEL.md section 3): ``period`` (default 6),
  ``lit`` (default 3), ``phases`` (one per image, default 0..P−1), ``direction_deg``
  (default: the entry wall's inward normal), ``entry`` (left, right, top, bottom;
  default left). Image row r (column, for the top and bottom walls) is lit in an image
  of phase φ iff (r + φ) mod period < lit, counted in the full image frame; with a
  ``medium_roi`` the loaded pattern's phases are shifted to count from the ROI's edge.
- ``dark_frame``: an image taken with the projector off, subtracted from every image
  first. Same size as the images; one channel or as many as the images.
- ``black_level``: b in [0, 1): a dark stripe emits b times a lit one (MODEL.md
  section 5). Absent: unknown (a joint fit may estimate it).
- ``medium_roi``: [x0, y0, x1, y1] in pixels, x1 and y1 exclusive: the medium's
  rectangle. Images are cropped to it and its edges are the medium's walls.
- ``pixel_size_mm``: pixel pitch in mm (> 0), to report coefficients in mm⁻¹.
- ``saturation``: image value (after integer scaling) at or above which a raw pixel
  is saturated and masked. Absent: integer frames mask pixels at their top code (255
  or 65535, i.e. 1.0), float frames mask nothing.
- ``channel``: which channel to use: a name (R, G, B, Y, ...), an index, or ``all``
  (default: every channel, fitted separately).
- ``geometry``: ``{kind: plane}``, the paper's 2-D model (default). Other kinds (the
  slab of MODEL.md section 7) are not supported yet.
- ``truth``: the true parameters of a simulated capture (``sigma_t``, ``sigma_s``,
  ``g``, ``gain``, ``phase``, ``black_level``), for reports.

:func:`load_capture` validates all of it: every error is a
:class:`~lightfield_jax._io.CaptureError` whose message starts with the capture file and
names the key and value (or the image file). Pixels that cannot be used (NaN or Inf in
an image or the dark frame, saturated or clipped) are masked, with a
:class:`CaptureWarning` that counts them.
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ._config import _as_int, _Section, load_yaml
from ._illumination import WALLS, Stripes
from ._io import (
    CaptureError,
    CaptureFileNotFoundError,
    ImageData,
    _channel_index,
    atomic_write_text,
    read_image,
    read_npy_stack,
)
from ._medium import PHASE_CONVENTIONS

CAPTURE_KEYS: tuple[str, ...] = (
    "images",
    "pattern",
    "dark_frame",
    "black_level",
    "medium_roi",
    "pixel_size_mm",
    "saturation",
    "channel",
    "geometry",
    "truth",
)
GEOMETRY_KINDS: tuple[str, ...] = ("plane",)
_PATTERN_KEYS = ("period", "lit", "phases", "direction_deg", "entry")
_TRUTH_FLOATS = ("sigma_t", "sigma_s", "g", "gain", "black_level")
_TRUTH_KEYS = (*_TRUTH_FLOATS, "phase")


class CaptureWarning(UserWarning):
    """Pixels of a capture were masked (non-finite, saturated or clipped)."""


@dataclasses.dataclass(frozen=True, eq=False)
class Capture:
    """A loaded, validated capture (see the module docstring).

    Attributes:
        images: float array [P, H, W, C]: the images after dark-frame subtraction and
            the ROI crop, in image units. Masked non-finite values are set to 0.
        channel_names: one name per channel.
        pattern: the stripes of each image, phases counted in the cropped frame.
        mask: bool [H, W, C], True where a pixel is valid in every image (finite in the
            images and the dark frame, and not saturated).
        black_level: b, or ``None`` when unknown.
        roi: (x0, y0, x1, y1) of the medium in the full frame, or ``None``.
        pixel_size_mm: pixel pitch, or ``None``.
        saturation: the saturation threshold used, or ``None``.
        source: the capture file.
        image_paths: the image files (one ``.npy`` stack repeated for a stack).
        dark_frame: the dark frame's file, or ``None``.
        n_masked: masked [H, W, C] entries: ``nonfinite``, ``saturated`` (finite but
            saturated or clipped) and ``total``.
        geometry: the geometry mapping (``{"kind": "plane"}``).
        truth: the true parameters of a simulated capture, or ``None``.
        warnings: the messages of the :class:`CaptureWarning` s issued while loading.
    """

    images: np.ndarray
    channel_names: tuple[str, ...]
    pattern: Stripes
    mask: np.ndarray
    black_level: float | None
    roi: tuple[int, int, int, int] | None
    pixel_size_mm: float | None
    saturation: float | None
    source: Path
    image_paths: tuple[Path, ...]
    dark_frame: Path | None
    n_masked: dict[str, int]
    geometry: dict[str, Any]
    truth: dict[str, Any] | None
    warnings: tuple[str, ...]

    @property
    def n_images(self) -> int:
        return self.images.shape[0]

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the (cropped) images."""
        return self.images.shape[1:3]


# --------------------------------------------------------------------------- loading


def load_capture(path: str | os.PathLike) -> Capture:
    """Read and validate a capture file (see the module docstring).

    Raises:
        CaptureFileNotFoundError: the capture file or an image does not exist.
        CaptureError: anything else that makes the capture unusable; the message
            starts with the capture file and names the key, value or image.
    """
    path = Path(path)
    if not path.exists():
        raise CaptureFileNotFoundError(f"{path}: file not found")
    top = _Section(str(path), "", load_yaml(path, CaptureError), CAPTURE_KEYS, error=CaptureError)
    base = path.parent
    channel = _channel(top)
    frames = _frames(top, base, channel)
    height, width, n_channels = frames[0].pixels.shape
    pattern = _pattern(top, len(frames))
    dark = _dark_frame(top, base, channel, frames[0])
    roi = _roi(top, width, height)
    black_level = top.float("black_level", None)
    if black_level is not None and not 0.0 <= black_level < 1.0:
        top.fail("black_level", f"must lie in [0, 1), got {black_level!r}")
    pixel_size = _positive(top, "pixel_size_mm")
    saturation = _positive(top, "saturation")
    geometry = _geometry(top)
    truth = _truth(top)

    raw = np.stack([f.pixels for f in frames])
    dark_pixels = None if dark is None else dark.pixels
    if roi is not None:
        x0, y0, x1, y1 = roi
        raw = raw[:, y0:y1, x0:x1]
        dark_pixels = None if dark_pixels is None else dark_pixels[y0:y1, x0:x1]
        pattern = _crop_pattern(pattern, x0, y0)
    names = [f.path.name for f in frames]
    if len(set(f.path for f in frames)) == 1 and len(frames) > 1:
        names = [f"{frames[0].path.name}[{i}]" for i in range(len(frames))]
    notes: list[str] = []
    nonfinite = _nonfinite(raw, dark_pixels, names, dark, notes)
    saturated = _saturated(raw, frames, names, saturation, notes) & ~nonfinite
    mask = ~(nonfinite | saturated)
    for note in notes:
        warnings.warn(f"{path}: {note}", CaptureWarning, stacklevel=2)
    if not mask.any():
        top.fail("images", "no usable pixel: every pixel is non-finite or saturated in some image")
    images = raw if dark_pixels is None else raw - dark_pixels
    images = np.where(np.isfinite(images), images, 0).astype(raw.dtype)
    return Capture(
        images=images,
        channel_names=frames[0].channel_names,
        pattern=pattern,
        mask=mask,
        black_level=black_level,
        roi=roi,
        pixel_size_mm=pixel_size,
        saturation=saturation,
        source=path,
        image_paths=tuple(f.path for f in frames),
        dark_frame=None if dark is None else dark.path,
        n_masked={
            "nonfinite": int(nonfinite.sum()),
            "saturated": int(saturated.sum()),
            "total": int((~mask).sum()),
        },
        geometry=geometry,
        truth=truth,
        warnings=tuple(notes),
    )


def _channel(top: _Section) -> str | int | None:
    """The channel selection for read_image: a name, an index, or None for all."""
    value = top.get("channel", "all")
    if isinstance(value, bool) or not isinstance(value, (str, int)) or value == "":
        top.fail("channel", f"must be a channel name, an index or 'all', got {value!r}")
    if isinstance(value, int) and value < 0:
        top.fail("channel", f"must be a non-negative index, got {value!r}")
    return None if value == "all" else value


def _read(top: _Section, key: str, file: Path, channel) -> ImageData:
    try:
        return read_image(file, channel)
    except CaptureFileNotFoundError as e:
        raise CaptureFileNotFoundError(f"{top.source}: {key}: {e}") from None
    except CaptureError as e:
        raise CaptureError(f"{top.source}: {key}: {e}") from None


def _file(top: _Section, key: str, value: Any, base: Path) -> Path:
    if not isinstance(value, str) or not value:
        top.fail(key, f"must be a file path, got {value!r}")
    return base / value


def _frames(top: _Section, base: Path, channel) -> list[ImageData]:
    value = top.get("images")
    if isinstance(value, str):
        file = _file(top, "images", value, base)
        if file.suffix.lower() != ".npy":
            top.fail(
                "images",
                f"a single file must be a .npy stack [P, H, W(, C)], got {value!r}; "
                "list the image files otherwise",
            )
        try:
            frames = read_npy_stack(file)
            if channel is not None:
                index = _channel_index(frames[0].channel_names, channel, file)
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
        return frames
    if not isinstance(value, list):
        top.fail("images", f"must be a list of image files or one .npy stack, got {value!r}")
    if not value:
        top.fail("images", "the list is empty: give one image per phase")
    frames = [
        _read(top, f"images[{i}]", _file(top, f"images[{i}]", v, base), channel)
        for i, v in enumerate(value)
    ]
    first = frames[0]
    for i, f in enumerate(frames[1:], start=1):
        if f.pixels.shape != first.pixels.shape:
            top.fail(
                f"images[{i}]",
                f"{f.path.name} is {_size(f)}, but images[0] ({first.path.name}) is "
                f"{_size(first)}; every image must have the same size and channels",
            )
    return frames


def _size(image: ImageData) -> str:
    h, w, c = image.pixels.shape
    return f"{w}x{h} pixels with {c} channel(s)"


def _pattern(top: _Section, n_images: int) -> Stripes:
    s = top.section("pattern", _PATTERN_KEYS)
    period, lit = s.int("period", 6), s.int("lit", 3)
    phases = s.get("phases", None)
    if phases is None:
        phases = list(range(n_images))
    elif not isinstance(phases, list) or not phases:
        s.fail(s.key("phases"), f"must be a non-empty list of integers, got {phases!r}")
    else:
        phases = [_as_int(s, f"{s.key('phases')}[{i}]", p) for i, p in enumerate(phases)]
    if len(phases) != n_images:
        s.fail(
            s.key("phases"),
            f"lists {len(phases)} phase(s) for {n_images} image(s); give one phase per image",
        )
    direction = s.float("direction_deg", None)
    entry = s.choice("entry", WALLS, "left")
    try:
        return Stripes(period, lit, tuple(phases), direction_deg=direction, entry=entry)
    except ValueError as e:
        message = str(e).replace("illumination.", "pattern.").replace("illumination:", "pattern:")
        raise CaptureError(f"{top.source}: {message}") from None


def _crop_pattern(pattern: Stripes, x0: int, y0: int) -> Stripes:
    """The pattern with wall cells counted from the ROI's edge instead of the frame's."""
    offset = y0 if pattern.entry in ("left", "right") else x0
    phases = tuple((p + offset) % pattern.period for p in pattern.phases)
    return dataclasses.replace(pattern, phases=phases)


def _dark_frame(top: _Section, base: Path, channel, first: ImageData) -> ImageData | None:
    value = top.get("dark_frame", None)
    if value is None:
        return None
    dark = _read(top, "dark_frame", _file(top, "dark_frame", value, base), channel)
    h, w, c = first.pixels.shape
    dh, dw, dc = dark.pixels.shape
    if (dh, dw) != (h, w) or dc not in (1, c):
        top.fail(
            "dark_frame",
            f"{value} is {_size(dark)}, but the images are {_size(first)} (a dark frame has "
            "the images' size and one channel or as many as they have)",
        )
    return dark


def _roi(top: _Section, width: int, height: int) -> tuple[int, int, int, int] | None:
    value = top.get("medium_roi", None)
    if value is None:
        return None
    if (
        not isinstance(value, list)
        or len(value) != 4
        or any(isinstance(v, bool) or not isinstance(v, int) for v in value)
    ):
        top.fail("medium_roi", f"must be a list of 4 integers [x0, y0, x1, y1], got {value!r}")
    x0, y0, x1, y1 = value
    if not (0 <= x0 and x0 + 2 <= x1 <= width and 0 <= y0 and y0 + 2 <= y1 <= height):
        top.fail(
            "medium_roi",
            f"{value} does not fit the {width}x{height} image: need 0 <= x0, x0 + 2 <= x1 <= "
            f"{width}, 0 <= y0, y0 + 2 <= y1 <= {height} (x1, y1 exclusive)",
        )
    return (x0, y0, x1, y1)


def _positive(top: _Section, key: str) -> float | None:
    value = top.float(key, None)
    if value is not None and value <= 0:
        top.fail(key, f"must be > 0, got {value!r}")
    return value


def _geometry(top: _Section) -> dict[str, Any]:
    if "geometry" not in top.data:
        return {"kind": "plane"}
    kind = top.section("geometry", None).get("kind")
    if kind not in GEOMETRY_KINDS:
        top.fail(
            "geometry.kind",
            f"{kind!r} is not supported; this version fits the paper's 2-D model only "
            f"(kind: {', '.join(GEOMETRY_KINDS)})",
        )
    top.section("geometry", ("kind",), f" for kind {kind}")
    return {"kind": kind}


def _truth(top: _Section) -> dict[str, Any] | None:
    if "truth" not in top.data:
        return None
    s = top.section("truth", _TRUTH_KEYS)
    truth: dict[str, Any] = {k: s.float(k) for k in _TRUTH_FLOATS if k in s.data}
    if "phase" in s.data:
        truth["phase"] = s.choice("phase", PHASE_CONVENTIONS)
    return truth


def _nonfinite(
    raw: np.ndarray,
    dark: np.ndarray | None,
    names: Sequence[str],
    dark_image: ImageData | None,
    notes: list[str],
) -> np.ndarray:
    """[H, W, C] True where an image or the dark frame is NaN or Inf; notes the counts."""
    bad = ~np.isfinite(raw)
    counts = {n: int(c) for n, c in zip(names, bad.sum(axis=(1, 2, 3)), strict=True) if c}
    out = bad.any(axis=0)
    if dark is not None:
        dark_bad = ~np.isfinite(dark)
        if dark_bad.any():
            counts[dark_image.path.name] = int(dark_bad.sum())
        out = out | np.broadcast_to(dark_bad, out.shape)
    if counts:
        listed = ", ".join(f"{n}: {c}" for n, c in counts.items())
        notes.append(
            f"{sum(counts.values())} pixel value(s) are NaN or Inf ({listed}); "
            f"{int(out.sum())} pixel(s) masked"
        )
    return out


def _saturated(
    raw: np.ndarray,
    frames: Sequence[ImageData],
    names: Sequence[str],
    saturation: float | None,
    notes: list[str],
) -> np.ndarray:
    """[H, W, C] True where a raw image is saturated (>= saturation) or clipped (at the
    top code of an integer frame, when no saturation is given); notes what was found."""
    with np.errstate(invalid="ignore"):
        if saturation is not None:
            hit = raw >= saturation
        else:
            integer = np.array([f.is_integer for f in frames])[:, None, None, None]
            hit = integer & (raw >= 1.0)
    per_frame = hit.sum(axis=(1, 2, 3))
    finite = np.isfinite(raw).sum(axis=(1, 2, 3))
    full = [n for n, h, f in zip(names, per_frame, finite, strict=True) if f and h == f]
    if full:
        notes.append(f"every pixel is saturated in {', '.join(full)}")
    listed = ", ".join(f"{n}: {int(h)}" for n, h in zip(names, per_frame, strict=True) if h)
    out = hit.any(axis=0)
    if listed and saturation is not None:
        notes.append(
            f"pixel values at or above saturation {saturation:g} ({listed}); "
            f"{int(out.sum())} pixel(s) masked"
        )
    elif listed:
        bits = sorted({f.bit_depth for f, h in zip(frames, per_frame, strict=True) if h})
        codes = ", ".join(f"{(1 << b) - 1} ({b}-bit)" for b in bits)
        notes.append(
            f"integer frames clipped at their top code {codes} ({listed}); "
            f"{int(out.sum())} pixel(s) masked (set saturation: to change the threshold)"
        )
    return out


# --------------------------------------------------------------------------- writing


def write_capture_yaml(
    path: str | os.PathLike,
    *,
    images: Sequence[str | os.PathLike] | str | os.PathLike,
    pattern: Stripes,
    dark_frame: str | os.PathLike | None = None,
    black_level: float | None = None,
    medium_roi: Sequence[int] | None = None,
    pixel_size_mm: float | None = None,
    saturation: float | None = None,
    channel: str | int | None = None,
    geometry: dict[str, Any] | None = None,
    truth: dict[str, Any] | None = None,
) -> Path:
    """Write a capture file (atomically); keys left ``None`` are omitted.

    ``images`` is a list of image files or one ``.npy`` stack, and ``dark_frame`` a
    file, all given relative to the capture file's folder.
    """

    def plain(value):
        if isinstance(value, np.generic):
            return value.item()
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        if isinstance(value, os.PathLike):
            return os.fspath(value)
        return value

    data = {
        "images": images if isinstance(images, (str, os.PathLike)) else list(images),
        "pattern": {
            "period": pattern.period,
            "lit": pattern.lit,
            "phases": list(pattern.phases),
            "direction_deg": pattern.direction_deg,
            "entry": pattern.entry,
        },
        "dark_frame": dark_frame,
        "black_level": black_level,
        "medium_roi": medium_roi,
        "pixel_size_mm": pixel_size_mm,
        "saturation": saturation,
        "channel": channel,
        "geometry": geometry,
        "truth": truth,
    }
    data = plain({k: v for k, v in data.items() if v is not None})
    text = yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=100)
    header = "# lightfield_jax capture file (format: lightfield_jax._capture)\n"
    return atomic_write_text(path, header + text)


__all__ = ["CAPTURE_KEYS", "Capture", "CaptureWarning", "load_capture", "write_capture_yaml"]
