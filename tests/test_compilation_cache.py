"""The persistent compilation cache: unreadable entries are replaced, not warned about
on every run."""

import os
import re
import subprocess
import sys
import warnings

import pytest

from lightfield_jax.inverse import programs
from lightfield_jax.inverse.programs import CompilationCacheWarning, repairing_compilation_cache

READ_ERROR = "Error reading persistent compilation cache entry for '{}': error: Error -3"


def test_an_unreadable_entry_is_deleted_and_said_once(tmp_path, monkeypatch):
    monkeypatch.setattr(programs, "_cache_folder", lambda: str(tmp_path))
    for name in ("jit__solve-1f6c-cache", "jit__solve-1f6c-atime", "jit__solve_x-9-cache"):
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "jit__scan-77-cache").write_bytes(b"x")
    with pytest.warns(UserWarning) as seen:
        with repairing_compilation_cache():
            warnings.warn(READ_ERROR.format("jit__solve"), stacklevel=1)
            warnings.warn(READ_ERROR.format("jit__scan-77"), stacklevel=1)  # an entry's key
            warnings.warn("something else", stacklevel=1)
    # The program's entries and that one key's are gone; another program's stay.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["jit__solve_x-9-cache"]
    shown = [(w.category, str(w.message)) for w in seen]
    assert shown == [
        (UserWarning, "something else"),
        (
            CompilationCacheWarning,
            f"the compilation cache {tmp_path} held 2 unreadable entries (jit__scan-77, "
            "jit__solve): deleted, and their programs compiled anew and stored again",
        ),
    ]


def test_a_read_while_another_process_holds_the_lock_deletes_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(programs, "_cache_folder", lambda: str(tmp_path))
    stopped = []
    monkeypatch.setattr(programs, "_stop_cache", lambda: stopped.append(True))
    (tmp_path / "jit__solve-1f6c-cache").write_bytes(b"x")
    locked = READ_ERROR.format("jit__solve").replace(
        "error: Error -3", f"The file lock '{tmp_path}/.lockfile' could not be acquired."
    )
    with pytest.warns(CompilationCacheWarning) as seen:
        with repairing_compilation_cache():
            warnings.warn(locked, stacklevel=1)
    assert [p.name for p in tmp_path.iterdir()] == ["jit__solve-1f6c-cache"]
    assert stopped == [True]
    assert [str(w.message) for w in seen] == [
        f"the compilation cache {tmp_path} stayed locked by another process for 10 s: turned "
        "off for the rest of this process (1 program(s) compiled instead of loaded)"
    ]


_LOCKED_RUN = r"""
import sys, warnings
import jax, jax.numpy as jnp
import lightfield_jax as lfj
from lightfield_jax.inverse.programs import repairing_compilation_cache
lfj.enable_compilation_cache(sys.argv[1])
with warnings.catch_warnings(record=True) as seen:
    warnings.simplefilter("always")
    with repairing_compilation_cache():
        for k in range(3):
            float(jax.jit(lambda x: jnp.sin(x) * k)(jnp.float32(1.0)))
print("enabled", jax.config.jax_enable_compilation_cache)
for w in seen:
    print("WARNING", w.category.__name__, str(w.message).splitlines()[0])
"""


def test_a_cache_another_process_keeps_locked_is_turned_off_after_one_wait(tmp_path):
    """Before: each program waited 10 s for the lock to read and 10 s to store (a fit's
    48 programs: minutes idle) while another process held it (stopped with Ctrl-Z)."""
    import filelock

    cache = tmp_path / "cache"
    cache.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_MAX_SIZE"}
    with filelock.FileLock(cache / ".lockfile"):
        done = subprocess.run(
            [sys.executable, "-c", _LOCKED_RUN, str(cache)],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        )
    said = done.stdout.splitlines()
    assert "enabled False" in said, said
    warned = [s for s in said if s.startswith("WARNING")]
    assert warned == [
        f"WARNING CompilationCacheWarning the compilation cache {cache} stayed locked by "
        "another process for 10 s: turned off for the rest of this process (1 program(s) "
        "compiled instead of loaded)"
    ], said
    assert not list(cache.glob("*-cache"))


def test_a_size_limit_below_every_program_is_said_once(tmp_path):
    """Before: JAX_COMPILATION_CACHE_MAX_SIZE=0 (or 1, or -5) gave one warning per
    program (48 lines for a fit)."""
    env = {**os.environ, "JAX_COMPILATION_CACHE_MAX_SIZE": "0"}
    done = subprocess.run(
        [sys.executable, "-c", _LOCKED_RUN, str(tmp_path / "cache")],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    warned = [s for s in done.stdout.splitlines() if s.startswith("WARNING")]
    assert len(warned) == 1, warned
    said = r"could not store \d+ compiled program\(s\) \(larger than the cache's size limit of 0"
    assert re.search(said, warned[0]), warned


_RUN = r"""
import sys, warnings
import jax, jax.numpy as jnp
import lightfield_jax as lfj
from lightfield_jax.inverse.programs import repairing_compilation_cache
lfj.enable_compilation_cache(sys.argv[1])
with warnings.catch_warnings(record=True) as seen:
    warnings.simplefilter("always")
    with repairing_compilation_cache():
        print(float(jax.jit(lambda x: jnp.sin(x) * 2)(jnp.float32(1.0))))
for w in seen:
    print("WARNING", w.category.__name__, str(w.message).splitlines()[0])
"""


def test_a_damaged_cache_is_repaired_by_the_next_run(tmp_path):
    """Before: JAX warned about each damaged entry (31 lines for a fit) in every run and
    never replaced it. Now the run that meets it says so once and stores the program
    again; the run after it reads the cache without a word."""
    cache = tmp_path / "cache"

    def run():
        done = subprocess.run(
            [sys.executable, "-c", _RUN, str(cache)], capture_output=True, text=True, check=True
        )
        return [line for line in done.stdout.splitlines() if line.startswith("WARNING")]

    assert run() == []
    entries = sorted(cache.glob("*-cache"))
    assert entries
    for path in entries:  # damaged: cut short, as by a crash or a full disk
        path.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    said = run()
    assert len(said) == 1 and said[0].startswith("WARNING CompilationCacheWarning"), said
    assert "unreadable entries" in said[0]
    assert run() == []


_OLD_WRITER = r"""
import sys
import jax, jax.numpy as jnp
jax.config.update("jax_compilation_cache_dir", sys.argv[1])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
print(float(jax.jit(lambda x: jnp.cos(x) + 3)(jnp.float32(1.0))))
"""


def test_the_cache_is_locked_and_bounded_and_takes_entries_written_without_a_limit(tmp_path):
    """Processes sharing the folder (a batch's workers) lock each read and write: JAX
    does only with a size limit, which also keeps the folder from growing without end.
    Such a limit reads every entry's last-use file when it stores a program: a folder
    filled without one (an earlier version of this package) made every store fail."""
    cache = tmp_path / "cache"
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_MAX_SIZE"}
    subprocess.run([sys.executable, "-c", _OLD_WRITER, str(cache)], env=env, check=True)
    old = sorted(cache.glob("*-cache"))
    assert old and not list(cache.glob("*-atime"))  # (written without a limit)

    done = subprocess.run(
        [sys.executable, "-c", _RUN + _LIMIT, str(cache)],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    assert "WARNING" not in done.stdout, done.stdout
    assert f"limit {programs.CACHE_MAX_BYTES}" in done.stdout
    entries = sorted(p.name.removesuffix("-cache") for p in cache.glob("*-cache"))
    assert len(entries) > len(old) and all(p.exists() for p in old)  # new ones beside
    assert sorted(p.name.removesuffix("-atime") for p in cache.glob("*-atime")) == entries
    assert (cache / ".lockfile").exists()


_LIMIT = r"""
print("limit", jax.config.jax_compilation_cache_max_size)
"""


def test_an_entry_unread_for_the_file_systems_error_is_kept(tmp_path, monkeypatch):
    """A read that failed on the folder (a full disk writing the last-use file, another
    user's file) is no damaged entry: nothing is deleted."""
    monkeypatch.setattr(programs, "_cache_folder", lambda: str(tmp_path))
    (tmp_path / "jit__solve-1f6c-cache").write_bytes(b"x")
    failed = READ_ERROR.format("jit__solve").replace(
        "error: Error -3", "PermissionError: [Errno 13] Permission denied: 'x-atime'"
    )
    with pytest.warns(CompilationCacheWarning) as seen:
        with repairing_compilation_cache():
            warnings.warn(failed, stacklevel=1)
    assert [p.name for p in tmp_path.iterdir()] == ["jit__solve-1f6c-cache"]
    assert [str(w.message) for w in seen] == [
        f"the compilation cache {tmp_path} could not read 1 compiled program(s) "
        "(PermissionError: [Errno 13] Permission denied: 'x-atime'): compiled instead of "
        "loaded, their entries kept"
    ]


def test_entries_another_writer_left_undated_are_dated_when_a_store_fails(tmp_path, monkeypatch):
    monkeypatch.setattr(programs, "_cache_folder", lambda: str(tmp_path))
    (tmp_path / "jit_other-12-cache").write_bytes(b"x")
    failed = (
        "Error writing persistent compilation cache entry for 'jit_f': FileNotFoundError: "
        f"[Errno 2] No such file or directory: '{tmp_path}/jit_other-12-atime'"
    )
    with pytest.warns(CompilationCacheWarning, match="could not store 1 compiled"):
        with repairing_compilation_cache():
            warnings.warn(failed, stacklevel=1)
    assert (tmp_path / "jit_other-12-atime").exists()  # the next store succeeds


_SET_UP = r"""
import sys
import jax
from lightfield_jax.inverse import programs
a, b = sys.argv[1:]
jax.config.update("jax_compilation_cache_dir", a)  # the user's own, before the package's
programs.use_compilation_cache(programs.Path(a))
print("min", jax.config.jax_persistent_cache_min_compile_time_secs)
print("limit", jax.config.jax_compilation_cache_max_size)
programs._stop_cache()  # (a lock another process kept)
programs.use_compilation_cache(programs.Path(a))  # a batch worker's next fit
print("stopped", jax.config.jax_enable_compilation_cache)
programs.use_compilation_cache(programs.Path(b))
print("other folder", jax.config.jax_enable_compilation_cache)
programs._stop_cache()
programs.enable_compilation_cache(a)  # asked for again by the API
print("asked again", jax.config.jax_enable_compilation_cache)
"""


def test_the_set_up_is_its_own_and_a_stopped_cache_stays_off_until_asked_for(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_MAX_SIZE"}
    done = subprocess.run(
        [sys.executable, "-c", _SET_UP, str(tmp_path / "a"), str(tmp_path / "b")],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    assert done.stdout.splitlines() == [
        "min 0.0",
        f"limit {programs.CACHE_MAX_BYTES}",
        "stopped False",
        "other folder True",
        "asked again True",
    ], done.stderr
