"""Compiled fit programs: module-level jitted functions, keyed by their static settings.

Every fit program is a plain function of arrays and of static settings (frozen,
hashable records: the renderer's static fields, a settings dataclass, the optimistix
solver). It is jitted once per process (:func:`jitted`); jit's own cache then keys each
compiled program by those settings and by the shapes and dtypes of its arrays, so a
second capture of the same shape, another channel of an RGB capture or another stage
of a fit that lands in the same shape bucket runs without tracing or compiling.

:func:`enable_compilation_cache` turns on JAX's persistent compilation cache from the
Python API (the command line does it by default), so a new process loads the programs
instead of compiling them.
"""

from __future__ import annotations

import builtins
import contextlib
import functools
import glob
import os
import warnings
from pathlib import Path

import jax

from lightfield_jax.checks import shown


def _compiler_options() -> dict | None:
    """XLA options of the fit programs: on the CPU, LLVM's optimisation level 1 instead
    of the default 2. A fit program runs for well under a second and compiles for
    several: level 1 compiles it about 15-25 % faster and it runs as fast (measured on
    the demo capture: the same answers to float32 rounding)."""
    if jax.default_backend() != "cpu":
        return None
    return {"xla_backend_optimization_level": 1}


@functools.cache
def jitted(fn, static_argnames: tuple[str, ...]):
    """``fn`` jitted with ``static_argnames`` static, built on first use (the XLA options
    depend on the backend, which importing the package must not start)."""
    return jax.jit(fn, static_argnames=static_argnames, compiler_options=_compiler_options())


def clear_compiled() -> None:
    """Forget the programs compiled in this process (the next fit compiles again, or
    loads from the persistent compilation cache where that is on): for cold timings."""
    jax.clear_caches()


# Every compiled XLA program maps its code into the process's memory, and the kernel
# limits the number of maps (vm.max_map_count, 65530 by default on Linux): past it the
# next compilation crashes the process (a segmentation fault or an abort inside XLA's
# compiler; measured: the test suite in one process, about 650 tests in, with 4 GB in
# use). A fit starts by forgetting the compiled programs where more than this share of
# the limit is in use (a long session of fits of many sizes).
CROWDED_SHARE = 0.5


def memory_maps() -> tuple[int, int]:
    """The process's memory maps and the kernel's limit on them (``(0, 0)`` where the
    system does not say: not Linux)."""
    try:
        with open("/proc/self/maps", "rb") as f:
            used = sum(1 for _ in f)
        with open("/proc/sys/vm/max_map_count") as f:
            return used, int(f.read())
    except (OSError, ValueError):
        return 0, 0


def forget_if_crowded(say=None) -> bool:
    """Forget the compiled programs (:func:`clear_compiled`) where the process holds
    more than ``CROWDED_SHARE`` of the kernel's memory-map limit; whether it did.
    ``say`` is told why."""
    used, limit = memory_maps()
    if not limit or used <= CROWDED_SHARE * limit:
        return False
    clear_compiled()
    if say is not None:
        say(
            f"compiled programs forgotten (they held {used} of the system's {limit} memory "
            "maps): this fit compiles its own again"
        )
    return True


def enable_compilation_cache(path: str | os.PathLike) -> Path:
    """Keep compiled XLA programs in ``path`` (created if missing) across processes.

    Every program is cached however quick it was to compile (a fit's programs compile
    in seconds each on a CPU and run in a fraction of that). The folder is locked for
    each read and write, so processes sharing it (a batch's workers) never read each
    other's half-written entry, and it keeps at most :data:`CACHE_MAX_BYTES` (or
    ``$JAX_COMPILATION_CACHE_MAX_SIZE``), dropping the programs used least recently.
    Call it before the first fit of the process; returns the folder. Raises
    ``OSError`` naming the folder when it cannot be created."""
    # Checked here: unchecked, "" caches into the current folder silently, None or bytes
    # raise Python's bare TypeError, a NUL "embedded null byte", none naming the argument.
    text = os.fspath(path) if isinstance(path, (str, os.PathLike)) else None
    if not isinstance(text, str) or not text.strip() or "\0" in text:
        raise ValueError(
            f"enable_compilation_cache: path: must be a folder's path (a non-empty str or "
            f"os.PathLike without NUL), got {shown(path)}"
        )
    global _stopped
    _stopped = None  # asked for again: a folder an earlier lock timeout turned off too
    return use_compilation_cache(Path(text).expanduser())


# The persistent cache's size limit: a fit's programs take tens of MB; thousands of
# programs (fits of many capture sizes and models) stay below it.
CACHE_MAX_BYTES = 2 * 2**30
_LIMIT_ENV = "JAX_COMPILATION_CACHE_MAX_SIZE"
# The folder this module set up, and the one a lock timeout turned off (for the rest of
# the process: a batch's worker sets the cache up again before each fit).
_configured: str | None = None
_stopped: str | None = None


def use_compilation_cache(folder: Path) -> Path:
    """JAX's persistent compilation cache in ``folder``, created if missing (``OSError``
    naming it where it cannot be), for every program; locked and bounded where the
    folder is writable (:func:`enable_compilation_cache`). The one set-up of the API,
    the commands and a batch's workers; nothing is done where this function already set
    it up there, or where a lock another process kept turned it off."""
    from jax.experimental.compilation_cache import compilation_cache

    global _configured
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OSError(f"compilation cache: cannot create {folder} ({e.strerror})") from e
    same = jax.config.jax_compilation_cache_dir == str(folder)
    if str(folder) == _stopped or (same and _configured == str(folder)):
        return folder
    jax.config.update("jax_compilation_cache_dir", str(folder))
    if "JAX_ENABLE_COMPILATION_CACHE" not in os.environ:  # (the user's off is kept)
        jax.config.update("jax_enable_compilation_cache", True)  # (after a lock's stop)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    # JAX locks the folder (filelock) only with a size limit; a read-only folder, which
    # it never writes, could not be locked: every read would fail. A limit the user set
    # (the environment, or jax.config to another value) is kept.
    writable = os.access(folder, os.W_OK)
    if _LIMIT_ENV not in os.environ and jax.config.jax_compilation_cache_max_size in (
        -1,
        CACHE_MAX_BYTES,
    ):
        jax.config.update("jax_compilation_cache_max_size", CACHE_MAX_BYTES if writable else -1)
    if writable:
        _date_unlimited_entries(folder)
    compilation_cache.reset_cache()  # set up once per process, at the first compilation
    _configured = str(folder)
    return folder


def _date_unlimited_entries(folder: Path) -> None:
    """Entries written without a size limit (an earlier version, or a process sharing
    the folder without one) have no last-use file, and JAX's limit reads one for every
    entry each time it stores a program: without them every store would fail. Each gets
    its own modification time."""
    for entry in folder.glob("*-cache"):
        used = entry.with_name(entry.name.removesuffix("-cache") + "-atime")
        if not used.exists():
            with contextlib.suppress(OSError):
                used.write_bytes(entry.stat().st_mtime_ns.to_bytes(8, "little"))


class CompilationCacheWarning(UserWarning):
    """What the persistent compilation cache could not do in a fit, said once
    (:func:`repairing_compilation_cache`): entries it could not read (deleted, their
    programs compiled anew), programs it could not store, a lock another process kept."""


# JAX's warning for an entry of the persistent cache it cannot read (a file cut short
# by a crash or a full disk, or written by another version); it names the program and
# the exception's type.
_UNREADABLE = "Error reading persistent compilation cache entry for '"
# JAX's warning for a program it could not store (a full disk, a read-only folder): one
# per program, tens per fit, all of one cause.
_UNWRITABLE = "Error writing persistent compilation cache entry for '"
# filelock's timeout (JAX waits 10 s for the folder's lock: use_compilation_cache).
_LOCKED = "could not be acquired"
# JAX's warning for a program larger than the cache's size limit (one per program).
_TOO_LARGE = "Cache value for key '"


def _stop_cache() -> None:
    """The persistent cache off for the rest of the process (the folder kept)."""
    from jax.experimental.compilation_cache import compilation_cache

    global _stopped
    _stopped = _cache_folder()
    jax.config.update("jax_enable_compilation_cache", False)
    compilation_cache.reset_cache()


def _cache_folder() -> str | None:
    return jax.config.jax_compilation_cache_dir


def _delete_entries(name: str) -> bool:
    """Delete the persistent cache's files of the program ``name`` (a module name such
    as ``jit__solve``, or one entry's key); whether any entry was deleted."""
    folder = _cache_folder()
    if not folder:
        return False
    deleted = False
    for path in Path(folder).glob(glob.escape(name) + "-*"):
        with contextlib.suppress(OSError):
            path.unlink()
            deleted = deleted or path.name.endswith("-cache")
    return deleted


def _failed_on_the_folder(text: str) -> bool:
    """Whether JAX's warning ``text`` names an error of the file system (``OSError`` and
    its kinds: a full disk, a file of another user), not of the entry's content."""
    kind = text.split("': ", 1)[-1].split(":", 1)[0].strip()
    error = getattr(builtins, kind, None)
    return isinstance(error, type) and issubclass(error, OSError)


@contextlib.contextmanager
def repairing_compilation_cache():
    """JAX warns about each unreadable entry of the persistent compilation cache and
    compiles the program, but never replaces the entry: every later process warned
    again (measured: 31 lines per fit from a cache whose files were damaged). Inside
    this context such an entry is deleted when JAX warns about it (the program it then
    compiles is stored in its place), and one :class:`CompilationCacheWarning` at the
    end says so. Said in one warning each too, nothing deleted: the programs JAX could
    not store (a full disk, a size limit below them) or read for an error of the file
    system, and a lock another process kept (the cache is then off for the rest of the
    process: every program would wait 10 s for it). Other warnings are shown as before.
    Usable as a decorator."""
    previous = warnings.showwarning
    deleted: list[str] = []
    unstored: list[str] = []  # the reason of each program JAX could not store
    unread: list[str] = []  # ... could not read (its entry kept)
    locked: list[str] = []  # programs not read: the folder's lock was not acquired

    def show(message, category, filename, lineno, file=None, line=None):
        text = str(message)
        if text.startswith((_UNREADABLE, _UNWRITABLE)) and _LOCKED in text:
            # Another process holds the folder's lock (stopped, or on a hung network
            # file system): the entry is fine, but every program would wait 10 s to
            # read and 10 s to store. The cache is off for the rest of the process.
            locked.append(text.split("'", 2)[1])
            _stop_cache()
            return
        if text.startswith(_UNREADABLE) and _failed_on_the_folder(text):
            unread.append(text.split("': ", 1)[-1])
            return
        if text.startswith(_UNWRITABLE):
            unstored.append(text.split("': ", 1)[-1])
            if "-atime" in text and "FileNotFoundError" in text and _cache_folder():
                _date_unlimited_entries(Path(_cache_folder()))  # (a writer without a limit)
            return
        if text.startswith(_TOO_LARGE):  # a size limit below the program (0: none)
            limit = text.rsplit(" of ", 1)[-1]
            unstored.append(f"larger than the cache's size limit of {limit}")
            return
        if not text.startswith(_UNREADABLE):
            previous(message, category, filename, lineno, file, line)
            return
        name = text[len(_UNREADABLE) :].split("'", 1)[0]
        if _delete_entries(name):
            deleted.append(name)
        else:  # (nothing there to delete, or a file the process cannot delete)
            unread.append(text.split("': ", 1)[-1])

    with warnings.catch_warnings():
        warnings.showwarning = show
        yield
    if unstored:
        warnings.warn(
            CompilationCacheWarning(
                f"the compilation cache {_cache_folder()} could not store "
                f"{len(unstored)} compiled program(s) ({unstored[0]}): they are compiled "
                "again by the next run"
            ),
            stacklevel=3,
        )
    if unread:
        warnings.warn(
            CompilationCacheWarning(
                f"the compilation cache {_cache_folder()} could not read {len(unread)} "
                f"compiled program(s) ({unread[0]}): compiled instead of loaded, their "
                "entries kept"
            ),
            stacklevel=3,
        )
    if locked:
        warnings.warn(
            CompilationCacheWarning(
                f"the compilation cache {_cache_folder()} stayed locked by another process "
                f"for 10 s: turned off for the rest of this process ({len(locked)} program(s) "
                "compiled instead of loaded)"
            ),
            stacklevel=3,
        )
    if deleted:
        names = ", ".join(sorted(set(deleted))[:4]) + (", ..." if len(set(deleted)) > 4 else "")
        warnings.warn(
            CompilationCacheWarning(
                f"the compilation cache {_cache_folder()} held "
                f"{len(deleted)} unreadable entries ({names}): deleted, and their programs "
                "compiled anew and stored again"
            ),
            stacklevel=3,
        )


__all__ = [
    "CACHE_MAX_BYTES",
    "CompilationCacheWarning",
    "clear_compiled",
    "enable_compilation_cache",
    "forget_if_crowded",
    "jitted",
    "memory_maps",
    "repairing_compilation_cache",
    "use_compilation_cache",
]
