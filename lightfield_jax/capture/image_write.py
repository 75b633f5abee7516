"""Image writers: OpenEXR with named channels, PNG and TIFF (8/16-bit), each atomic
(:func:`lightfield_jax.files.atomic_path`).

OpenImageIO is imported inside the functions that need it, so ``import lightfield_jax``
does not load it.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from lightfield_jax.capture.io import CHANNEL_ORDER_ATTR, oiio_name
from lightfield_jax.files import atomic_path


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
    attrs = {"compression": "zip", **(metadata or {}), CHANNEL_ORDER_ATTR: ",".join(names)}
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


__all__ = ["write_exr", "write_png", "write_tiff"]
