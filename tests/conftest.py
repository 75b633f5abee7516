import os

import jax
import pytest

# The commands' stderr is compared line by line: their stage lines (on by default where
# stderr is not a terminal) are tested on their own, with --progress.
os.environ["LIGHTFIELD_JAX_PROGRESS"] = "none"

# Tests check convergence and gradients: float64 unless a test asks for float32.
jax.config.update("jax_enable_x64", True)


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
