"""Where a capture file's relative paths lead: the folder of the file itself, after
symbolic links (:func:`capture_folder`); the files it lists (:func:`listed_files`,
:func:`capture_files`); and the refusal of a linked capture file whose link's folder
holds other files of the names it lists (:func:`check_link_folder`)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from lightfield_jax.capture.io import CaptureError, CaptureFileNotFoundError
from lightfield_jax.capture.keys import AUX_FRAMES
from lightfield_jax.capture.response import RESPONSES
from lightfield_jax.schema import load_yaml


def capture_folder(path: str | os.PathLike) -> Path:
    """The folder the relative paths of the capture file ``path`` (images, calibration
    frames, a response table) are read from: the folder of the file it is, after
    symbolic links. A capture file is written beside its images; a link to it from
    elsewhere (a working folder, a shorter name) names those images, as a link to a
    script or a Makefile keeps its meaning."""
    path = Path(path)
    if path.is_symlink():
        # realpath: the link's target, relative to the link's own folder; a loop is
        # left to the read, which names it.
        return Path(os.path.realpath(path)).parent
    return path.parent


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether ``a`` and ``b`` name one existing file (False where either is missing)."""
    with contextlib.suppress(OSError):
        return os.path.samefile(a, b)
    return False


def is_file_name(value: Any) -> bool:
    """Whether a capture file's ``value`` can name a file: a non-empty string without a
    NUL byte (what is not is refused where its key is read)."""
    return isinstance(value, str) and bool(value) and "\0" not in value


def check_link_folder(path: Path, names: Iterable[str], error: type[Exception]) -> None:
    """Refuse a linked capture file ``path`` where its link's folder holds another file
    under one of the ``names`` it lists: a template linked into several captures'
    folders would otherwise read the images beside the template, and a link from a
    folder of another capture would read the others; which are meant cannot be told."""
    base = capture_folder(path)
    here = path.parent
    if base == here or same_file(base, here):
        return
    for name in names:
        beside, linked = here / name, base / name
        if os.path.lexists(beside) and not same_file(beside, linked):
            raise error(
                f"{path}: a link to {os.path.realpath(path)}, whose listed files are read "
                f"beside it in {base}, but the link's folder {here} holds another {name}: "
                "which file is meant cannot be told; give the capture file's own path, or "
                "copy it instead of linking"
            )


def capture_files(path: str | os.PathLike) -> list[Path]:
    """The capture file and every file it lists (images, calibration frames), from the
    YAML alone: the inputs an output must not replace. Values that are not file names
    are skipped (:func:`~lightfield_jax.capture.loading.load_capture` reports them)."""
    path = Path(path)
    data = load_yaml(path, CaptureError, CaptureFileNotFoundError)
    return [path] + [capture_folder(path) / v for v in listed_files(data)]


def listed_files(data: Any) -> list[str]:
    """The file names a capture file's YAML ``data`` lists (images, calibration frames, a
    response table), relative to :func:`capture_folder`."""

    def names(value) -> list:  # a file, a list of files, or brackets (lists of lists)
        if isinstance(value, list):
            return [name for v in value for name in names(v)]
        return [value]

    if not isinstance(data, dict):
        return []
    listed = names(data.get("images")) + names([data.get(key) for key in AUX_FRAMES])
    if data.get("response") not in RESPONSES:
        listed.append(data.get("response"))
    return [v for v in listed if is_file_name(v)]
