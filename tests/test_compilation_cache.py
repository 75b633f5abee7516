"""The persistent compilation cache: unreadable entries are replaced, not warned about
on every run."""

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
