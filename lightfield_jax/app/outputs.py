"""The files a command writes: checked before any work, published together at the end.

A command names its outputs (``--out``, ``--plot``, ``--json``, results folders) and
its inputs (the config or capture file and every file a capture lists) to
:func:`check_outputs` before it starts. An output is refused, with an
:class:`OutputError` naming the path as the user gave it, when it

- is one of the run's inputs (the same file, whatever the path that names it),
- names the same file as another output,
- exists and is not what the command writes (a device, a FIFO or a folder where a
  file is expected; a file where a folder is expected),
- is in a folder that cannot be written (read-only, ``/proc``; a probe file is created
  and removed there, as permission bits do not bind the superuser), or under a path
  one of whose existing parents is not a folder,
- is a figure in a format the plotting library cannot write,
- is a folder another command wrote (it holds that command's marker file, one of
  :data:`FOLDER_MARKERS`) holding a file this command would replace (``render --out``
  into ``simulate``'s folder replaced its ``bounces.npy``). A folder holding the
  command's own marker is its own: a rerun replaces its files, as before. A command
  writing a simulated capture (:data:`CAPTURE_MARKER`) or a pattern's template
  (``capture.yaml``) also refuses a folder without its marker holding a file it would
  replace (the user's own capture or a camera's frames); so do ``render`` and
  ``experiment`` (their own markers): a folder of figures or arrays of the user's own
  (``docs/figures``) is never written over. Every folder a
  command writes into is named, each checked alike: ``render`` of several channels
  names each channel's subfolder too.

:func:`staged_files` then writes the files of one command: each output is written to a
temporary beside it, and all of them replace their targets only when the whole command
has succeeded, so a failure leaves every existing file as it was.
"""

from __future__ import annotations

import contextlib
import fnmatch
import os
import shutil
import stat
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

from lightfield_jax.capture.io import IMAGE_EXTENSIONS, oiio_name
from lightfield_jax.files import (
    forget_temporary,
    fsync_path,
    keep_made_folders,
    make_file,
    make_folders,
    naming_output,
    remove_made_folders,
    reserve_temporary,
    write_failure,
)


class OutputError(ValueError):
    """An output path that the command must not or cannot write; names the path."""


# The file each folder-writing command leaves in its output folder, and the command:
# a folder holding one is that command's (demo's folder is a simulated capture: its
# marker is simulate's).
FOLDER_MARKERS = {
    "metadata.json": "simulate",
    "render.json": "render",
    "summary.json": "experiment",
}
# The marker of a folder that holds a simulated capture (simulate's and demo's): these
# commands (``writer``) refuse to replace any file in a folder without it (a capture of
# the user's own: capture.yaml, shift_*.exr, a pattern's template), not only another
# command's.
CAPTURE_MARKER = "metadata.json"


def plot_formats() -> tuple[str, ...]:
    """The figure file extensions matplotlib writes (``png``, ``pdf``, ``svg``, ...)."""
    from matplotlib.backend_bases import FigureCanvasBase

    return tuple(sorted(FigureCanvasBase.get_supported_filetypes()))


def _tex_system() -> str | None:
    """The TeX program matplotlib's pgf backend runs, where it is missing."""

    import matplotlib

    tex = str(matplotlib.rcParams["pgf.texsystem"])
    return None if shutil.which(tex) else tex


def check_plot_format(given: str) -> None:
    """Refuse a figure name whose extension matplotlib cannot write (a .pgf one too
    where its TeX program is missing)."""
    suffix = Path(given).suffix.lower().lstrip(".")
    formats = plot_formats()
    tex = _tex_system() if "pgf" in formats else None
    if tex is not None:
        formats = tuple(f for f in formats if f != "pgf")
        if suffix == "pgf":  # else a traceback after the work ("'xelatex' not found")
            raise OutputError(
                f"{given}: matplotlib writes .pgf figures through {tex}, which is not "
                f"installed; choose another format: {', '.join(formats)}"
            )
    if suffix not in formats:
        shown = f"extension {'.' + suffix!r}" if suffix else "no extension"
        raise OutputError(
            f"{given}: a figure needs a file extension matplotlib writes ({shown}); "
            f"supported: {', '.join(formats)}"
        )


def check_json_name(given: str, option: str, hint: str = "") -> None:
    """Refuse a JSON output (``option``, e.g. ``--out``) named like an image, an array
    or a figure (``results.png``: the figure was meant, or the file would be misread as
    an image), or like a capture or config file (``.yaml``: ``fit --out sim.yaml``
    replaced the user's config); ``hint`` is added to the message (where the figure
    goes)."""

    suffix = Path(given).suffix.lower()
    if suffix in IMAGE_EXTENSIONS or suffix.lstrip(".") in plot_formats():
        raise OutputError(
            f"{option} {given}: the results are written as JSON, which a {suffix} name "
            f"would hide; name it .json{hint}"
        )
    if suffix in (".yaml", ".yml"):  # a slip for the capture or config beside it
        raise OutputError(
            f"{option} {given}: a {suffix} name is a capture file's or a config's, which "
            f"the JSON results would replace or be taken for; name it .json{hint}"
        )


def check_outputs(
    files: Sequence[str | os.PathLike] = (),
    folders: Sequence[str | os.PathLike] = (),
    inputs: Iterable[str | os.PathLike] = (),
    folder_names: Sequence[str] = (),
    marker: str | None = None,
    writer: str | None = None,
) -> None:
    """Check, before any work, that a command may write ``files`` (single files) and
    ``folders`` (output folders) without touching ``inputs`` (see the module docstring).
    ``folder_names``: the names (glob patterns) the command writes into its folders;
    an input there with such a name would be replaced, and so would the outputs of
    another command (a folder holding a marker of :data:`FOLDER_MARKERS` other than
    ``marker``, the command's own). ``writer``: the command (named in the message) whose
    folders are its own only where they hold ``marker``: a file it would replace in a
    folder without it is the user's (a capture of their own), refused too.

    Raises:
        OutputError: the first output that cannot be written; the message names it.
    """
    inputs = [Path(p) for p in inputs]
    seen: dict[str, str] = {}
    for given, folder in [(f, False) for f in files] + [(d, True) for d in folders]:
        path = Path(given)
        if not folder and os.fspath(given).endswith(("/", os.sep)):
            # Path() drops the separator: "--out new/" wrote the results as a file "new".
            raise OutputError(f"{given}: ends in {os.sep!r}, a folder; expected a file name")
        _check_kind(path, folder)
        for source in inputs:
            inside = folder and _same(path, source.parent)
            if _same(path, source) or (
                inside and any(fnmatch.fnmatch(source.name, n) for n in folder_names)
            ):
                what = "holds" if inside else "is"
                raise OutputError(
                    f"{given}: {what} an input of this command ({source}), which it would "
                    "replace; choose another output"
                )
        if folder:  # a folder's outputs are images (simulate, render, pattern, demo)
            oiio_name(path, OutputError)
            _check_owner(path, os.fspath(given), folder_names, marker, writer)
        key = os.path.realpath(path)
        if key in seen:
            raise OutputError(f"{given}: names the same file as the output {seen[key]}")
        seen[key] = os.fspath(given)
        _check_writable(path, os.fspath(given))


def _check_owner(
    path: Path, given: str, folder_names: Sequence[str], marker: str | None, writer: str | None
) -> None:
    """Refuse a folder another command wrote (and this one did not), or, with a
    ``writer``, any folder without ``marker``, when this command would replace a file
    in it."""
    if not path.is_dir() or (marker is not None and (path / marker).is_file()):
        return  # a rerun into the command's own folder
    others = [m for m in FOLDER_MARKERS if m != marker and (path / m).is_file()]
    users = writer is not None and not others
    if not others and not users:
        return
    try:
        with os.scandir(path) as entries:
            names = sorted(e.name for e in entries)
    except OSError:
        return  # an unreadable folder: _check_writable says what is wrong
    replaced = [n for n in names if any(fnmatch.fnmatch(n, p) for p in folder_names)]
    if "capture.yaml" in replaced:  # named first: the file the user cares most about
        replaced.insert(0, replaced.pop(replaced.index("capture.yaml")))
    more = f" (and {len(replaced) - 1} more)" if len(replaced) > 1 else ""
    if replaced and users:
        whose = "a capture" if marker == CAPTURE_MARKER else "a file"
        raise OutputError(
            f"{given}: holds {replaced[0]}{more} that lightfield-jax {writer} did not write "
            f"(no {marker}; {whose} of your own?), which this command would replace; "
            "choose another output folder"
        )
    if replaced:
        raise OutputError(
            f"{given}: holds the outputs of lightfield-jax {FOLDER_MARKERS[others[0]]} "
            f"({others[0]}), whose {replaced[0]}{more} this command would replace; choose "
            "another output folder"
        )


def _same(a: Path, b: Path) -> bool:
    if "\0" in os.fspath(a) or "\0" in os.fspath(b):
        return False  # not a path: the reader names the key that gave it
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist
        return os.path.realpath(a) == os.path.realpath(b)


def _check_kind(path: Path, folder: bool) -> None:
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return
    except OSError as e:
        raise OutputError(f"{path}: cannot be written ({e.strerror})") from None
    if folder and not stat.S_ISDIR(mode):
        raise OutputError(f"{path}: exists and is not a directory")
    if not folder and stat.S_ISDIR(mode):
        raise OutputError(f"{path}: is a directory, expected a file name")
    if not folder and not stat.S_ISREG(mode):
        raise OutputError(
            f"{path}: exists and is not a regular file (a device, FIFO or socket); "
            "choose a new file name or a regular file to replace"
        )
    if not folder and not mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH):
        # Replacing it would go through its folder's permissions, not its own.
        raise OutputError(
            f"{path}: exists and is read-only (mode {stat.S_IMODE(mode):04o}); make it "
            "writable to replace it, or choose another output"
        )


def _check_writable(path: Path, given: str) -> None:
    """The nearest existing parent of ``path`` is a folder where a file can be created."""
    parent = path.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise OutputError(f"{given}: {parent} is not a directory")
    try:
        probe = reserve_temporary(parent / ".lightfield-jax-probe", make_file)
    except OSError as e:
        raise OutputError(f"{given}: cannot write in {parent} ({e.strerror or e})") from None
    forget_temporary(probe)
    probe.unlink()


@contextlib.contextmanager
def staged_files() -> Iterator[Callable[[str | os.PathLike], Path]]:
    """Stage the files of one command; publish them only when the block succeeds.

    Yields ``stage(target)``, which returns a temporary path beside ``target`` (same
    extension) for a writer to fill. When the block ends normally, every temporary
    replaces its target (``os.replace``); when it raises, the temporaries are removed
    and every target is left as it was.
    """
    pending: list[tuple[Path, Path]] = []
    made: list[Path] = []  # the folders made for the outputs: removed unless published
    published = False

    def stage(target: str | os.PathLike) -> Path:
        target = Path(target)
        made.extend(make_folders(target.parent))
        tmp = reserve_temporary(target, make_file)
        pending.append((tmp, target))
        return tmp

    def writing() -> Path:  # the output being written: the last one staged
        return pending[-1][1] if pending else Path(".")

    try:
        try:
            yield stage
        except OSError as e:  # a writer's failure names its output, not the temporary
            failure = write_failure(e, writing())
            if failure is None:
                raise
            raise failure from e
        for tmp, target in pending:
            with naming_output(target):
                fsync_path(tmp)
        for tmp, target in pending:
            os.replace(tmp, target)
            forget_temporary(tmp)
        published = True
    finally:
        for tmp, _ in pending:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            forget_temporary(tmp)
        if published:
            keep_made_folders(made)
        else:  # nothing written: nor the folders made to hold it
            remove_made_folders(made)


def check_command_outputs(
    files=(),
    folders=(),
    inputs=(),
    plots=(),
    folder_names=(),
    marker=None,
    writer=None,
    json=(),
) -> None:
    """Check every output of a command before its work (see
    :func:`~lightfield_jax.app.outputs.check_outputs`); ``plots`` are figures among
    ``files``, whose format is checked too; ``json``: (option, file, hint) of the JSON
    files among them, whose names must not be an image's or a figure's;
    ``folder_names``: the names written into ``folders``; ``marker``: the command's own
    file (its folders are its own); ``writer``: the command's name where a folder
    without ``marker`` is the user's."""
    for plot in plots:
        check_plot_format(plot)
    files, folders = [f for f in files if f], [d for d in folders if d]
    check_outputs(files, folders, inputs, folder_names, marker, writer)
    for option, given, hint in json:
        if given:
            check_json_name(given, option, hint)


__all__ = [
    "check_command_outputs",
    "CAPTURE_MARKER",
    "FOLDER_MARKERS",
    "OutputError",
    "check_outputs",
    "check_plot_format",
    "plot_formats",
    "staged_files",
]
