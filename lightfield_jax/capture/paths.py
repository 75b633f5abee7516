"""Where a capture file's relative paths start: the folder of the file itself, after
symbolic links (:func:`capture_folder`), and the refusal of a linked capture file whose
link's folder holds other files of the names it lists (:func:`check_link_folder`)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterable
from pathlib import Path


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


def _same_file(a: Path, b: Path) -> bool:
    with contextlib.suppress(OSError):
        return os.path.samefile(a, b)
    return False


def check_link_folder(path: Path, names: Iterable[str], error: type[Exception]) -> None:
    """Refuse a linked capture file ``path`` where its link's folder holds another file
    under one of the ``names`` it lists: a template linked into several captures'
    folders would otherwise read the images beside the template, and a link from a
    folder of another capture would read the others; which are meant cannot be told."""
    base = capture_folder(path)
    here = path.parent
    if base == here or _same_file(base, here):
        return
    for name in names:
        beside, linked = here / name, base / name
        if os.path.lexists(beside) and not _same_file(beside, linked):
            raise error(
                f"{path}: a link to {os.path.realpath(path)}, whose listed files are read "
                f"beside it in {base}, but the link's folder {here} holds another {name}: "
                "which file is meant cannot be told; give the capture file's own path, or "
                "copy it instead of linking"
            )
