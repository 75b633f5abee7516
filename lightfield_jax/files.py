"""Files written whole or not at all, and regular-file checks before a read.

Every writer is atomic. It writes a temporary file in the target's directory and renames
it over the target with :func:`os.replace`, so a reader (or a crash) never sees a
half-written file. :func:`atomic_directory` does the same for a command that writes
several files into one folder: nothing appears in the folder unless the whole command
succeeds. Temporaries of a command stopped by a signal are removed by
:func:`remove_temporaries`.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import secrets
import shutil
import stat
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np


def require_regular_file(
    path: Path, what: str, error: type[ValueError], missing: type[ValueError] | None = None
) -> None:
    """Refuse, before opening it, a ``path`` that is missing (``missing``, default
    ``error``) or not a regular file (a folder, a FIFO that would block the read forever,
    a device): ``error``."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise (missing or error)(f"{path}: file not found") from None
    except OSError as e:
        raise error(f"{path}: cannot read ({e.strerror})") from None
    if stat.S_ISDIR(mode):
        raise error(f"{path}: is a directory, not {what}")
    if not stat.S_ISREG(mode):
        raise error(f"{path}: is not a regular file (a FIFO, device or socket), not {what}")


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


def reserve_temporary(path: Path, make) -> Path:
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


def make_file(p: Path) -> None:
    # Mode 0o666 lets the umask decide permissions, as for any new file.
    os.close(os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))


def fsync_path(p: Path) -> None:
    fd = os.open(p, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_failure(error: OSError, target: Path) -> OSError | None:
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
    (see :func:`write_failure`); other errors, and one that already names ``target``
    or a file in it (an inner output's own name), pass unchanged."""
    try:
        yield
    except OSError as e:
        named = e.filename
        if isinstance(named, (str, bytes)) and Path(os.fsdecode(named)).is_relative_to(target):
            raise
        failure = write_failure(e, Path(target))
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
        tmp = reserve_temporary(path, make_file)
    except BaseException:
        remove_made_folders(made)
        raise
    try:
        with naming_output(path):
            yield tmp
            fsync_path(tmp)
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
            raise ValueError(f"{given}: the root folder cannot be an output folder")
    made = make_folders(path.parent)
    published = False
    try:
        stage = reserve_temporary(path, lambda p: os.mkdir(p, 0o777))
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
    "atomic_directory",
    "atomic_path",
    "atomic_write_bytes",
    "atomic_write_json",
    "atomic_write_npy",
    "atomic_write_text",
    "fsync_path",
    "forget_temporary",
    "keep_made_folders",
    "make_file",
    "make_folders",
    "naming_output",
    "remove_made_folders",
    "remove_temporaries",
    "require_regular_file",
    "reserve_temporary",
    "write_failure",
]
