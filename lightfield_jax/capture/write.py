"""Writing a capture file (the format: :mod:`lightfield_jax.capture.capture`)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lightfield_jax.capture.keys import check_pixel_size
from lightfield_jax.capture.paths import same_file
from lightfield_jax.checks import check_number, shown
from lightfield_jax.files import atomic_write_text
from lightfield_jax.scene.geometry import Plane, Slab
from lightfield_jax.scene.illumination import Stripes


def write_capture_yaml(
    path: str | os.PathLike,
    *,
    images: Sequence[str | os.PathLike] | str | os.PathLike,
    pattern: Stripes,
    dark_frame: str | os.PathLike | None = None,
    black_level: float | str | None = None,
    medium_roi: Sequence[int] | str | None = None,
    pixel_size_mm: float | None = None,
    saturation: float | None = None,
    channel: str | int | None = None,
    geometry: dict[str, Any] | None = None,
    truth: dict[str, Any] | None = None,
    fit: dict[str, Any] | None = None,
    black_frame: str | os.PathLike | None = None,
    white_frame: str | os.PathLike | None = None,
    flat_field: str | os.PathLike | None = None,
) -> Path:
    """Write a capture file (atomically); keys left ``None`` are omitted.

    ``images`` is a list of image files or one ``.npy`` stack, and ``dark_frame``,
    ``black_frame``, ``white_frame`` and ``flat_field`` files, all given relative to the
    capture file's folder. ``medium_roi`` and ``black_level`` may be ``"auto"``.
    """

    # Checked here: unchecked, pattern=None raises an AttributeError, images=5 "'int'
    # object is not iterable", an array or a Slab yaml's RepresenterError, and a NaN
    # saturation or pixel pitch is written into a file load_capture then refuses.
    if not isinstance(pattern, Stripes):
        raise ValueError(
            f"write_capture_yaml: pattern: must be a Stripes, got {type(pattern).__name__}"
        )
    if isinstance(images, bytes) or not isinstance(images, (str, os.PathLike, Sequence)):
        raise ValueError(
            "write_capture_yaml: images: must be a list of image files or one .npy stack, "
            f"got {shown(images)}"
        )
    frames = {
        "dark_frame": dark_frame,
        "black_frame": black_frame,
        "white_frame": white_frame,
        "flat_field": flat_field,
    }
    _check_files(path, images, pattern, frames)
    check_pixel_size(pixel_size_mm, "write_capture_yaml: pixel_size_mm")
    if saturation is not None:
        check_number(saturation, "write_capture_yaml: saturation", low=0.0, low_open=True)
    if black_level is not None and black_level != "auto":
        check_number(
            black_level, "write_capture_yaml: black_level", low=0.0, high=1.0, high_open=True
        )

    def plain(value):
        if isinstance(value, (np.generic, np.ndarray)):
            return value.tolist()
        if isinstance(value, (Plane, Slab)):
            return value.as_dict()
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        if isinstance(value, os.PathLike):
            return os.fspath(value)
        return value

    data = {
        "images": images if isinstance(images, (str, os.PathLike)) else list(images),
        "pattern": pattern.as_dict(),
        "dark_frame": dark_frame,
        "black_level": black_level,
        "medium_roi": medium_roi,
        "pixel_size_mm": pixel_size_mm,
        "saturation": saturation,
        "channel": channel,
        "geometry": geometry,
        "fit": fit,
        "truth": truth,
        "black_frame": black_frame,
        "white_frame": white_frame,
        "flat_field": flat_field,
    }
    data = plain({k: v for k, v in data.items() if v is not None})
    for key, value in data.items():
        try:
            yaml.safe_dump(value)
        except yaml.YAMLError:
            raise ValueError(
                f"write_capture_yaml: {key}: cannot be written to a capture file, got "
                f"{shown(value)}"
            ) from None
    text = yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=100)
    header = "# lightfield_jax capture file (format: lightfield_jax.capture.capture)\n"
    return atomic_write_text(path, header + text)


def _check_files(path, images, pattern: Stripes, frames: dict[str, Any]) -> None:
    """Refuse an image list that load_capture refuses (empty, not one image or bracket
    per phase, entries that are not file names), calibration frames that are not file
    names, and a capture file that would replace a file it lists: unchecked, the file
    was written and the loading said what was wrong, an image was replaced by the YAML,
    or a frame of 5 a TypeError of the path check below."""

    def name(value) -> bool:
        text = os.fspath(value) if isinstance(value, (str, os.PathLike)) else None
        return isinstance(text, str) and text not in ("", ".") and "\0" not in text

    def names(value) -> bool:  # a file, or a bracketed capture's one per exposure
        return name(value) or (isinstance(value, list) and bool(value) and all(map(name, value)))

    for key, value in frames.items():
        if value is not None and not names(value):
            raise ValueError(
                f"write_capture_yaml: {key}: must be an image file name (with brackets, a "
                f"list of one per exposure time), got {shown(value)}"
            )
    if isinstance(images, (str, os.PathLike)) and not name(images):
        raise ValueError(
            f"write_capture_yaml: images: must be image file names or one .npy stack, got "
            f"{shown(images)}"
        )
    if not isinstance(images, (str, os.PathLike)):
        shifts = list(images)
        if not all(names(v) for v in shifts):
            raise ValueError(
                "write_capture_yaml: images: must be image file names (or a list of "
                f"exposures' files per shift), got {shown(shifts)}"
            )
        if len(shifts) != pattern.n_patterns:
            raise ValueError(
                f"write_capture_yaml: images: {len(shifts)} listed for the pattern's "
                f"{pattern.n_patterns} phases {list(pattern.phases)}: give one per phase"
            )
    else:
        shifts = [images]
    listed = [v for item in [*shifts, *frames.values()] if item is not None for v in _files(item)]
    folder = Path(path).parent
    for value in listed:
        target = folder / value
        if os.path.abspath(target) == os.path.abspath(path) or same_file(target, path):
            raise ValueError(
                f"write_capture_yaml: {path}: is the listed file {os.fspath(value)}, which "
                "the capture file would replace; write it under another name"
            )


def _files(item) -> list:
    return list(item) if isinstance(item, list) else [item]
