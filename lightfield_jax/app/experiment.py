"""Config-driven experiments: ``lightfield-jax experiment configs/NAME.yaml [--out DIR]``.

An experiment is a short script ``experiments/NAME.py`` (one question each) defining

    def run(config: dict, out: pathlib.Path, ctx: Context) -> dict

which writes its data (JSON/CSV) and figures (PNG) into ``out`` through ``ctx`` and
returns a summary (JSON-ready) that the runner stores in ``out/summary.json`` together
with the config, software versions, machine and date. Its config ``configs/NAME.yaml``
holds ``experiment: NAME`` (the script's name), the parameters, and an optional
``reduced:`` mapping whose keys replace the top-level ones for ``--reduced`` (the small
size the test suite runs, so experiments cannot rot).

Scripts share helper modules in ``experiments/`` (names starting with ``_``) through
:func:`load_helper`.

The scripts and configs ship inside the wheel (``lightfield_jax/_experiments``,
``lightfield_jax/_configs``), so an installed package runs them too: a config is a
path, or the name of a shipped one (``lightfield-jax experiment forward_accuracy``).
In a source checkout the tree's ``experiments/`` and ``configs/`` are used.

Long experiments resume: ``ctx.cached(key, compute)`` stores each finished unit of work
as ``out/cache/KEY.json`` and returns it on a rerun instead of recomputing;
``ctx.sweep(axes, key, compute)`` runs a Cartesian sweep that way. The other pieces
the scripts share are written here once: typed, frozen configs (:func:`typed_config`),
CSV tables (:func:`write_csv`) and figures (:func:`pyplot`, :func:`save_figure`).
"""

from __future__ import annotations

import csv
import dataclasses
import datetime
import hashlib
import importlib.util
import itertools
import json
import os
import platform
import sys
import time
import types
import typing
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

from lightfield_jax.app.config import load_yaml
from lightfield_jax.capture.io import atomic_path, atomic_write_json

_HERE = Path(__file__).resolve().parent.parent  # the package folder


def _tree_or_packaged(tree: str, packaged: str) -> Path:
    """The source tree's folder when running from a checkout, else the wheel's copy."""
    source = _HERE.parent / tree
    return source if source.is_dir() else _HERE / packaged


EXPERIMENTS_DIR = _tree_or_packaged("experiments", "_experiments")
CONFIGS_DIR = _tree_or_packaged("configs", "_configs")


def versions() -> dict[str, str]:
    """Versions of the software an experiment ran with."""
    import equinox
    import jax
    import numpy
    import optimistix

    from lightfield_jax import __version__

    return {
        "lightfield_jax": __version__,
        "python": sys.version.split()[0],
        "jax": jax.__version__,
        "equinox": equinox.__version__,
        "optimistix": optimistix.__version__,
        "numpy": numpy.__version__,
    }


def machine() -> dict[str, Any]:
    import os

    import jax

    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "devices": [str(d) for d in jax.devices()],
    }


def provenance() -> dict[str, Any]:
    """What a measurement's JSON records besides its numbers: the software's versions,
    the machine and the date (UTC)."""
    return {
        "versions": versions(),
        "machine": machine(),
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


@dataclasses.dataclass
class Context:
    """What an experiment gets besides its config: where to write, progress, resume."""

    out: Path
    progress: Callable[[str], None]
    reduced: bool

    def cached(self, key: str, compute: Callable[[], Any]) -> Any:
        """``compute()``'s JSON-ready result, stored once under ``out/cache``."""
        safe = hashlib.sha1(key.encode()).hexdigest()[:16]
        path = self.out / "cache" / f"{safe}.json"
        if path.exists():
            stored = json.loads(path.read_text())
            if stored.get("key") == key:
                return stored["value"]
        value = compute()
        atomic_write_json(path, {"key": key, "value": value})
        return value

    def sweep(
        self,
        axes: Sequence[tuple[str, Iterable]],
        key: Callable[..., str],
        compute: Callable[..., Any],
    ) -> list:
        """``compute(**point)`` for every point of the Cartesian product of ``axes``
        (``(name, values)`` pairs, the first outermost), each reported through
        ``progress`` and :meth:`cached` under ``key(**point)``: a rerun resumes."""
        names = [name for name, _ in axes]
        rows = []
        for values in itertools.product(*(list(v) for _, v in axes)):
            point = dict(zip(names, values, strict=True))
            self.progress(", ".join(f"{n} {v}" for n, v in point.items()))
            rows.append(self.cached(key(**point), lambda p=point: compute(**p)))
        return rows

    def write_json(self, name: str, data: Any) -> Path:
        path = self.out / name
        atomic_write_json(path, data)
        return path

    def figure_path(self, name: str) -> Path:
        return self.out / name


def check_config(name: str, config: dict, allowed, choices: dict | None = None) -> None:
    """Refuse an experiment config's unknown keys, and list values outside the known
    ones: ``choices`` maps a key (whose value is a list) to its allowed values."""
    unknown = sorted(set(config) - set(allowed))
    if unknown:
        raise ValueError(f"{name}: unknown config keys {unknown}")
    for key, known in (choices or {}).items():
        check_choices(name, key, config[key], known)


def check_choices(name: str, key: str, values, known) -> None:
    """Refuse a value of the list ``values`` (config key ``key``) outside ``known``."""
    for value in values:
        if value not in known:
            raise ValueError(
                f"{name}: {key}: unknown {value!r} (known: {', '.join(map(str, known))})"
            )


def _type_ok(value, annotation) -> bool:
    """Whether a YAML value fits a config field's annotation (int for float allowed;
    lists for tuples; bool is not an int)."""
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        return any(_type_ok(value, a) for a in typing.get_args(annotation))
    if annotation is type(None):
        return value is None
    if annotation is Any:
        return True
    if origin in (tuple, list):
        args = typing.get_args(annotation)
        inner = args[0] if args else Any
        return isinstance(value, (list, tuple)) and all(_type_ok(v, inner) for v in value)
    if origin is dict or annotation is dict:
        return isinstance(value, dict)
    if annotation is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if annotation is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, annotation)


def typed_config(cls, config: dict):
    """The frozen dataclass ``cls`` built from an experiment config (its ``experiment``
    key aside): an unknown key, a missing one or a value of the wrong type is a
    one-line ``ValueError`` naming the experiment and the key. Lists become tuples."""
    name = config.get("experiment", cls.__name__)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(config) - set(fields) - {"experiment"})
    if unknown:
        raise ValueError(f"{name}: unknown config keys {unknown}")
    hints = typing.get_type_hints(cls)
    values = {}
    for key, field in fields.items():
        if key not in config:
            no_default = field.default is dataclasses.MISSING
            if no_default and field.default_factory is dataclasses.MISSING:
                raise ValueError(f"{name}: missing config key {key!r}")
            continue
        value = config[key]
        if not _type_ok(value, hints[key]):
            raise ValueError(f"{name}: {key}: expected {_type_name(hints[key])}, got {value!r}")
        values[key] = tuple(value) if isinstance(value, list) else value
    return cls(**values)


def _type_name(annotation) -> str:
    return getattr(annotation, "__name__", None) or str(annotation).replace("typing.", "")


def write_csv(path: Path, header: Sequence[str], rows: Iterable[Sequence]) -> Path:
    """A CSV table (``header``, then one line per row), written atomically."""
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)
    return Path(path)


def pyplot():
    """matplotlib's pyplot on the non-interactive Agg backend (imported on first use:
    the package does not import matplotlib)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path, dpi: int = 110) -> Path:
    """Write ``fig`` to ``path`` atomically at ``dpi`` and close it; returns the path."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi)
    pyplot().close(fig)
    return Path(path)


def load_experiment_config(path: str | Path, reduced: bool = False) -> dict:
    """Read an experiment config; ``reduced`` applies its ``reduced:`` overrides."""
    path = Path(path)
    shipped = CONFIGS_DIR / f"{path.stem}.yaml"
    if not path.is_file() and path.parent == Path(".") and shipped.is_file():
        path = shipped  # a shipped config, by name
    if not path.is_file():
        known = sorted(p.stem for p in CONFIGS_DIR.glob("*.yaml"))
        raise FileNotFoundError(f"{path}: no such experiment config (shipped: {', '.join(known)})")
    # The configs' own loader: duplicate keys, alias bombs and oversized files refused.
    data = load_yaml(path, ValueError)
    if "experiment" not in data:
        raise ValueError(f"{path}: an experiment config needs the key 'experiment: NAME'")
    small = data.pop("reduced", None) or {}
    if not isinstance(small, dict):
        raise ValueError(f"{path}: reduced: must be a mapping of overrides")
    if reduced and not small:  # else a full run would be recorded as a reduced one
        raise ValueError(f"{path}: --reduced: this config has no reduced: section to apply")
    if reduced:
        unknown = sorted(set(small) - set(data))
        if unknown:
            raise ValueError(f"{path}: reduced: overrides unknown keys {unknown}")
        data.update(small)
    return data


def _exec_module(name: str, path: Path):
    """Execute ``path`` as the module ``lightfield_jax_experiments.NAME``, registered in
    ``sys.modules`` first (dataclasses in a script look their module up)."""
    spec = importlib.util.spec_from_file_location(f"lightfield_jax_experiments.{name}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[spec.name]
        raise
    return module


def child_env() -> dict[str, str]:
    """The environment of an experiment's child process: the parent's, with JAX's GPU
    memory preallocation off unless set (parent and children share one accelerator;
    each would otherwise take 75 % of its memory at its first array, and a child ran
    out of memory on an H200)."""
    return {"XLA_PYTHON_CLIENT_PREALLOCATE": "false", **os.environ}


def load_helper(name: str):
    """A helper module shared by the experiment scripts, ``experiments/NAME.py`` (e.g.
    ``_inverse``, ``_batch``): loaded once per process, then the same module object.
    The scripts are loaded by path, not from a package, so they import helpers this way:
    ``inv = load_helper("_inverse")``."""
    full = f"lightfield_jax_experiments.{name}"
    if full in sys.modules:
        return sys.modules[full]
    path = EXPERIMENTS_DIR / f"{name}.py"
    if not path.is_file():
        raise ValueError(f"experiment: no helper module {path}")
    return _exec_module(name, path)


def _load_script(name):
    # Only the shipped experiments: a config is data and never names a file to run.
    known = sorted(p.stem for p in EXPERIMENTS_DIR.glob("*.py") if not p.stem.startswith("_"))
    if not isinstance(name, str) or name not in known:
        raise ValueError(f"experiment: unknown experiment {name!r} (known: {', '.join(known)})")
    script = EXPERIMENTS_DIR / f"{name}.py"
    module = _exec_module(name, script)
    if not hasattr(module, "run"):
        raise ValueError(f"experiment: {script} defines no run(config, out, ctx)")
    return module


def run_experiment(
    config_path: str | Path,
    out: str | Path | None = None,
    *,
    reduced: bool = False,
    progress: Callable[[str], None] = lambda _m: None,
) -> dict:
    """Run one experiment; returns its summary (also written to ``out/summary.json``)."""
    config = load_experiment_config(config_path, reduced)
    try:
        module = _load_script(config["experiment"])
    except ValueError as e:
        raise ValueError(f"{config_path}: {e}") from None
    name = config["experiment"]
    out = Path(out) if out is not None else Path("results") / name
    existed = out.exists()
    out.mkdir(parents=True, exist_ok=True)
    started = datetime.datetime.now(datetime.UTC)
    ctx = Context(out=out, progress=progress, reduced=reduced)
    try:
        summary = module.run(config, out, ctx)
    except ValueError as e:  # a config the script refuses: named with its file
        if not existed and not any(out.iterdir()):
            out.rmdir()  # no empty output folder left behind
        raise ValueError(f"{config_path}: {e}") from None
    record = {
        "experiment": name,
        "config_file": str(config_path),
        "config": config,
        "reduced": reduced,
        "started_utc": started.isoformat(timespec="seconds"),
        "seconds": (datetime.datetime.now(datetime.UTC) - started).total_seconds(),
        "versions": versions(),
        "machine": machine(),
        "summary": summary,
    }
    atomic_write_json(out / "summary.json", record)
    return record
