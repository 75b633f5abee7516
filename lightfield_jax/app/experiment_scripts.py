"""Where the experiment scripts and configs live, and how they are loaded: the source
tree's ``experiments/`` and ``configs/`` in a checkout, else the wheel's copies
(``lightfield_jax/_experiments``, ``lightfield_jax/_configs``); a script or a helper
module of the scripts (names starting with ``_``) is executed by path as the module
``lightfield_jax_experiments.NAME``.

Below both the runner (:mod:`lightfield_jax.app.experiment`) and the Dask workers
(:mod:`lightfield_jax.app.distributed`, which load a task's script while unpickling it),
so that neither imports the other for it.
"""

from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path

# The package folder: the source tree's folders lie beside it, the wheel's inside it.
PACKAGE_DIR = Path(__file__).resolve().parent.parent

# The scripts' package, as a module of its own: pickle finds a script's functions by
# importing their module's name (Dask sends them to its workers so).
SCRIPTS_PACKAGE = "lightfield_jax_experiments"


def tree_or_packaged(tree: str, packaged: str, package: Path = PACKAGE_DIR) -> Path:
    """The source tree's folder ``tree`` when running from a checkout (beside
    ``package``), else the wheel's copy ``package/packaged``."""
    source = package.parent / tree
    return source if source.is_dir() else package / packaged


EXPERIMENTS_DIR = tree_or_packaged("experiments", "_experiments")


CONFIGS_DIR = tree_or_packaged("configs", "_configs")


def _exec_module(name: str, path: Path):
    """Execute ``path`` as the module ``lightfield_jax_experiments.NAME``, registered in
    ``sys.modules`` first (dataclasses in a script look their module up)."""
    sys.modules.setdefault(SCRIPTS_PACKAGE, types.ModuleType(SCRIPTS_PACKAGE))
    spec = importlib.util.spec_from_file_location(f"{SCRIPTS_PACKAGE}.{name}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[spec.name]
        raise
    return module


def load_helper(name: str):
    """A helper module shared by the experiment scripts, ``experiments/NAME.py`` (e.g.
    ``_inverse``, ``_batch``): loaded once per process, then the same module object.
    The scripts are loaded by path, not from a package, so they import helpers this way:
    ``inv = load_helper("_inverse")``."""
    full = f"{SCRIPTS_PACKAGE}.{name}"
    if full in sys.modules:
        return sys.modules[full]
    path = EXPERIMENTS_DIR / f"{name}.py"
    if not path.is_file():
        raise ValueError(f"experiment: no helper module {path}")
    return _exec_module(name, path)


def load_script(name):
    """The experiment script ``experiments/NAME.py`` (it defines ``run(config, out,
    ctx)``), executed afresh; ``ValueError`` for a name that is not a shipped script."""
    # Only the shipped experiments: a config is data and never names a file to run.
    known = sorted(p.stem for p in EXPERIMENTS_DIR.glob("*.py") if not p.stem.startswith("_"))
    if not isinstance(name, str) or name not in known:
        raise ValueError(f"experiment: unknown experiment {name!r} (known: {', '.join(known)})")
    script = EXPERIMENTS_DIR / f"{name}.py"
    module = _exec_module(name, script)
    if not hasattr(module, "run"):
        raise ValueError(f"experiment: {script} defines no run(config, out, ctx)")
    return module


__all__ = [
    "CONFIGS_DIR",
    "EXPERIMENTS_DIR",
    "PACKAGE_DIR",
    "SCRIPTS_PACKAGE",
    "load_helper",
    "load_script",
    "tree_or_packaged",
]
