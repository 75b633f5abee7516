import os
from pathlib import Path

import jax
import pytest

# The commands' stderr is compared line by line: their stage lines (on by default where
# stderr is not a terminal) are tested on their own, with --progress.
os.environ["LIGHTFIELD_JAX_PROGRESS"] = "none"

# Tests check convergence and gradients: float64 unless a test asks for float32.
jax.config.update("jax_enable_x64", True)

# A persistent compilation cache for the tests, shared by the run's processes and kept
# across runs beside the commands' own cache and never in it: most of a cold run is
# compiling, and a program compiled again (another renderer of the same model, a fit
# after its programs were forgotten, the next run) loads instead. With a size limit JAX
# locks each read and write (filelock), so no process reads another's half-written
# entry, and past it drops the entries least recently used. The commands run here,
# in-process and as subprocesses, use the same folder rather than turning the user's
# cache on. The set-up is the package's own (programs.use_compilation_cache: every
# program, locked, at most 2 GiB). LIGHTFIELD_JAX_TEST_XLA_CACHE=off: a cold run; =DIR:
# another folder.


def _test_xla_cache() -> Path | None:
    chosen = os.environ.get("LIGHTFIELD_JAX_TEST_XLA_CACHE", "")
    if chosen.strip().lower() in ("off", "0", "no", "false"):
        return None
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "lightfield_jax"
    folder = Path(chosen) if chosen else base / "tests-xla"
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    return folder


_XLA_CACHE = _test_xla_cache()
if _XLA_CACHE is not None:
    from lightfield_jax.inverse.programs import use_compilation_cache

    use_compilation_cache(_XLA_CACHE)
    # (the commands run as subprocesses lock it too: JAX reads this at import)
    limit = jax.config.jax_compilation_cache_max_size
    os.environ["JAX_COMPILATION_CACHE_MAX_SIZE"] = str(limit)
# (XLA_CACHE_ENV; tests of it set it themselves)
os.environ["LIGHTFIELD_JAX_XLA_CACHE"] = "off" if _XLA_CACHE is None else str(_XLA_CACHE)


def pytest_collection_modifyitems(config, items):
    """Tests marked ``forgets_compiled`` clear every compiled program of the process
    (``clear_compiled``: cold timings, a fresh compile to compare with): they run last,
    so the tests after them in file order do not compile their programs again."""
    last = [item for item in items if item.get_closest_marker("forgets_compiled")]
    items[:] = [item for item in items if not item.get_closest_marker("forgets_compiled")] + last


@pytest.fixture(autouse=True)
def _bounded_compiled_programs():
    """The whole suite in one process compiles thousands of XLA programs, each with
    memory maps of its own code: past the kernel's limit on maps the next compilation
    crashes the process (measured: at about 70 % of the suite). They are forgotten
    after a test that leaves more than half the limit in use, as a fit does before it
    starts (``forget_if_crowded``)."""
    yield
    from lightfield_jax.inverse.programs import forget_if_crowded  # after x64 is set

    forget_if_crowded()
