import jax

# Tests check convergence and gradients: float64 unless a test asks for float32.
jax.config.update("jax_enable_x64", True)


def pytest_collection_modifyitems(config, items):
    """Tests marked ``forgets_compiled`` clear every compiled program of the process
    (``clear_compiled``: cold timings, a fresh compile to compare with): they run last,
    so the tests after them in file order do not compile their programs again."""
    last = [item for item in items if item.get_closest_marker("forgets_compiled")]
    items[:] = [item for item in items if not item.get_closest_marker("forgets_compiled")] + last
