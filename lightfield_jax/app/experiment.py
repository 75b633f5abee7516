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

Every script defines its config as a frozen dataclass ``Config`` (field types with
:class:`Range` bounds, ``Literal`` choices, nested mappings as dataclass schemas); the
runner checks the whole config against it (:func:`typed_config`), and the grid's memory,
before any work, so that a bad config is one line naming the file and the key. The
outputs go to a staging folder, published into ``out`` only when the run succeeds.

Long experiments resume: ``ctx.cached(key, compute)`` stores each finished unit of work
as ``out/cache/KEY.json`` (kept when a run fails) and returns it on a rerun instead of
recomputing; ``ctx.sweep(axes, key, compute)`` runs a Cartesian sweep that way. The
other pieces the scripts share are written here once: CSV tables (:func:`write_csv`)
and figures (:func:`pyplot`, :func:`save_figure`).
"""

from __future__ import annotations

import contextlib
import contextvars
import csv
import dataclasses
import datetime
import hashlib
import importlib.util
import itertools
import json
import math
import os
import platform
import sys
import time
import types
import typing
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

from lightfield_jax.files import atomic_directory, atomic_path, atomic_write_json
from lightfield_jax.schema import load_yaml

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
    """What an experiment gets besides its config: where to write, progress, resume.

    ``out`` is where this run's outputs go (under :func:`run_experiment`, a staging
    folder published into the results folder only when the run succeeds); ``keep`` is
    the results folder itself, for what outlives a failed run (:meth:`kept`): the
    cache of finished units, a persistent XLA cache (default: ``out``)."""

    out: Path
    progress: Callable[[str], None]
    reduced: bool
    keep: Path | None = None
    # Where parallel sweeps run (see parallel_sweep): the Dask scheduler's address
    # (None: $LIGHTFIELD_JAX_SCHEDULER, else an embedded local cluster of ``workers``).
    scheduler: str | None = None
    workers: int | None = None
    allow_large: bool = False
    say: Callable[[str], None] = lambda _m: None
    _resources: contextlib.ExitStack = dataclasses.field(default_factory=contextlib.ExitStack)
    _client: Any = None

    def kept(self, name: str) -> Path:
        """``keep/NAME``: a folder that a failed run leaves for the next one to reuse."""
        return (self.keep or self.out) / name

    def _entry(self, key: str) -> Path:
        return self.kept("cache") / f"{hashlib.sha1(key.encode()).hexdigest()[:16]}.json"

    def stored(self, key: str) -> Any:
        """The value stored under ``key`` (see :meth:`cached`), or ``None``."""
        try:  # an entry that cannot be read (truncated, edited) is computed again
            stored = json.loads(self._entry(key).read_text())
        except (OSError, ValueError):
            return None
        if isinstance(stored, dict) and stored.get("key") == key and "value" in stored:
            return stored["value"]
        return None

    def store(self, key: str, value: Any) -> None:
        atomic_write_json(self._entry(key), {"key": key, "value": value})

    def cached(self, key: str, compute: Callable[[], Any]) -> Any:
        """``compute()``'s JSON-ready result, stored once under ``keep/cache``."""
        stored = self.stored(key)
        if stored is not None:
            return stored
        value = compute()
        self.store(key, value)
        return value

    def rows_per_medium(self, config: dict, case: Callable[[dict], list]) -> list:
        """The rows of ``case(spec)`` for each medium of ``config["media"]``, each
        medium's stored under its spec and the rest of the config (a rerun with the same
        settings reuses them)."""
        shared = {k: v for k, v in config.items() if k not in ("media", "experiment")}
        rows = []
        for spec in config["media"]:
            key = f"{sorted(spec.items())}|{sorted(shared.items())}"
            rows += self.cached(key, lambda s=spec: case(s))
        return rows

    def sweep(
        self,
        axes: Sequence[tuple[str, Iterable]],
        key: Callable[..., str],
        compute: Callable[..., Any],
    ) -> list:
        """``compute(**point)`` for every point of the Cartesian product of ``axes``
        (``(name, values)`` pairs, the first outermost), each reported through
        ``progress`` and :meth:`cached` under ``key(**point)``: a rerun resumes."""
        from lightfield_jax.app.distributed import check_count

        points = _points(axes)
        check_count(len(points), self.allow_large, "sweep points")
        rows = []
        for point in points:
            self.progress(", ".join(f"{n} {v}" for n, v in point.items()))
            rows.append(self.cached(key(**point), lambda p=point: compute(**p)))
        return rows

    def client(self):
        """The run's Dask client, started at the first use and closed with the run."""
        if self._client is None:
            from lightfield_jax.app.distributed import cluster

            self._client = self._resources.enter_context(
                cluster(self.scheduler, workers=self.workers)
            )
        return self._client

    def close(self) -> None:
        self._resources.close()
        self._client = None

    def parallel_sweep(
        self,
        axes: Sequence[tuple[str, Iterable]],
        key: Callable[..., str],
        compute: Callable[..., Any],
        *,
        timeout: float | None = None,
        on_timeout: Callable[[dict, float], Any] | None = None,
        seconds_per_point: float = 30.0,
    ) -> list:
        """:meth:`sweep` with the points computed in parallel on Dask (:meth:`client`),
        each stored as it completes (the same cache as :meth:`sweep`'s: a rerun, serial
        or parallel, resumes). ``compute`` must be picklable (a function of the script,
        or a lambda of its ``run``) and runs in the caller's precision (x64 or not).

        ``timeout`` (s) bounds each point: its row is then ``on_timeout(point,
        timeout)`` (stored), or without ``on_timeout`` a failure. Points that failed (a
        worker dead twice, an exception, a timeout) are not stored: the run then raises
        :class:`ExperimentError` naming them, after every other point is stored."""
        from lightfield_jax.app.distributed import Task, check_count, run_tasks

        points = _points(axes)
        check_count(len(points), self.allow_large, "sweep points")  # before a cluster starts
        tasks = [
            Task(
                key(**point),
                ", ".join(f"{n} {v}" for n, v in point.items()),
                _call_with,
                (compute, point),
            )
            for point in points
        ]
        report = run_tasks(
            tasks,
            load=lambda t: self.stored(t.key),
            save=lambda t, v: self.store(t.key, v),
            client=self.client(),
            timeout=timeout,
            on_timeout=None if on_timeout is None else lambda t, s: on_timeout(t.args[1], s),
            seconds_per_task=seconds_per_point,
            allow_large=self.allow_large,
            what="sweep points",
            say=self.say,
            desc="sweep",
        )
        if report.failures:
            first = next(iter(report.failures.values()))
            raise ExperimentError(
                f"{len(report.failures)} of {len(tasks)} sweep points failed (first: {first}); "
                "the others are stored, a rerun computes only the failed ones"
            )
        return [report.results[t.key] for t in tasks]

    def write_json(self, name: str, data: Any) -> Path:
        path = self.out / name
        atomic_write_json(path, data)
        return path

    def figure_path(self, name: str) -> Path:
        return self.out / name


def _points(axes: Sequence[tuple[str, Iterable]]) -> list[dict]:
    """The points of the Cartesian product of ``axes`` (the first outermost)."""
    names = [name for name, _ in axes]
    return [
        dict(zip(names, values, strict=True))
        for values in itertools.product(*(list(v) for _, v in axes))
    ]


def _call_with(compute: Callable[..., Any], point: dict) -> Any:
    return compute(**point)


def check_choices(name: str, key: str, values, known) -> None:
    """Refuse a value of the list ``values`` (config key ``key``) outside ``known``."""
    for value in values:
        if value not in known:
            raise ValueError(
                f"{name}: {key}: unknown {value!r} (known: {', '.join(map(str, known))})"
            )


@dataclasses.dataclass(frozen=True)
class Range:
    """The interval a config number must lie in, written into its field's annotation:
    ``width: Annotated[int, Range(8, 2048)]``; ``open_low`` and ``open_high`` exclude
    the ends themselves."""

    low: float = -math.inf
    high: float = math.inf
    open_low: bool = False
    open_high: bool = False

    def __contains__(self, x) -> bool:
        above = self.low < x if self.open_low else self.low <= x
        below = x < self.high if self.open_high else x <= self.high
        return above and below

    def __str__(self) -> str:
        low, high = _number(self.low), _number(self.high)
        if self.high == math.inf:
            return f"{'>' if self.open_low else '>='} {low}"
        return f"in {'(' if self.open_low else '['}{low}, {high}{')' if self.open_high else ']'}"


def _number(x: float) -> str:
    """``x`` as a config would write it: integers in full, else ``%g``."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


# The ranges the experiments share: an image side, a count of things, a seed (numpy's
# generators take 0 .. 2**32 - 1 as 32-bit seeds), a positive number, a precision.
Pixels = Annotated[int, Range(8, 2048)]
Count = Annotated[int, Range(1, 100_000)]
Seed = Annotated[int, Range(0, 2**32 - 1)]
Positive = Annotated[float, Range(0, open_low=True)]
Dtype = Literal["float32", "float64"]


class _Invalid(ValueError):
    """A config value that does not fit its field: ``key``, the reason."""


class _WrongType(_Invalid):
    """A value of the wrong kind at ``key`` itself (not inside it)."""

    def __init__(self, key: str, annotation, value):
        super().__init__(f"{key}: expected {_type_name(annotation)}, got {value!r}")
        self.key = key


def _check_value(value, annotation, key: str):
    """``value`` (YAML) checked against a field's annotation, returned as the config
    holds it (lists become tuples); a misfit raises :class:`_Invalid`. int is accepted
    for float, bool is not a number, floats are finite; ``Annotated[dict, Schema]``
    checks a mapping against the dataclass ``Schema`` (kept as the mapping)."""
    origin = typing.get_origin(annotation)
    if origin is Annotated:
        base, *extras = typing.get_args(annotation)
        schemas = [e for e in extras if isinstance(e, type) and dataclasses.is_dataclass(e)]
        if schemas:
            if not isinstance(value, dict):
                raise _WrongType(key, dict, value)
            _build(schemas[0], value, f"{key}.")
            return value
        value = _check_value(value, base, key)
        for r in (e for e in extras if isinstance(e, Range)):
            if value not in r:
                raise _Invalid(f"{key}: must be {r}, got {value!r}")
        return value
    if origin is Literal:
        known = typing.get_args(annotation)
        if isinstance(value, bool) or value not in known:
            raise _Invalid(f"{key}: must be one of {', '.join(map(str, known))}, got {value!r}")
        return value
    if origin in (typing.Union, types.UnionType):
        errors = []
        for option in typing.get_args(annotation):
            try:
                return _check_value(value, option, key)
            except _Invalid as e:
                errors.append(e)
        # An option of the value's kind: its reason (a range, a key inside); else the
        # types expected.
        fitting = [e for e in errors if not (isinstance(e, _WrongType) and e.key == key)]
        raise fitting[0] if fitting else _WrongType(key, annotation, value)
    if annotation is Any:
        return value
    if origin in (tuple, list):
        args = typing.get_args(annotation)
        inner = args[0] if args else Any
        if not isinstance(value, (list, tuple)):
            raise _WrongType(key, annotation, value)
        items = tuple(_check_value(v, inner, f"{key}[{i}]") for i, v in enumerate(value))
        _check_names(items, key)
        return items
    if annotation is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        if ok and not math.isfinite(value):
            raise _Invalid(f"{key}: must be a finite number, got {value!r}")
    elif annotation is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif annotation is type(None):
        ok = value is None
    else:
        ok = isinstance(value, origin or annotation)
    if not ok:
        raise _WrongType(key, annotation, value)
    return value


def _check_names(items: tuple, key: str) -> None:
    """A list of named mappings (media, scenes): the names key the tables, the figures
    and some figures' file names, so they must differ and hold no path separator
    (two scenes of one name would both run, then one be kept in the results or their
    rows mixed in one figure; a name with '/' would name a file in another folder)."""
    names = [v["name"] for v in items if isinstance(v, dict) and isinstance(v.get("name"), str)]
    if len(names) != len(items):
        return
    for i, name in enumerate(names):
        if not name or "/" in name or "\\" in name or "\0" in name:
            raise _Invalid(f"{key}[{i}].name: must be a non-empty name without '/', got {name!r}")
    if len(set(names)) < len(names):
        raise _Invalid(f"{key}: names must differ, got {names}")


def _build(cls, config: dict, prefix: str = ""):
    """``cls(**config)`` with every key checked (see :func:`typed_config`); the keys
    named with ``prefix`` (``"oblique."``, ``"media[0]."``)."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(config) - set(fields) - ({"experiment"} if not prefix else set())
    if unknown:  # (YAML keys may be numbers or booleans too)
        raise _Invalid(f"unknown config keys {sorted(f'{prefix}{k}' for k in unknown)}")
    hints = typing.get_type_hints(cls, include_extras=True)
    values = {}
    for key, field in fields.items():
        if key in config:
            values[key] = _check_value(config[key], hints[key], prefix + key)
        elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            raise _Invalid(f"missing config key {prefix + key!r}")
    return cls(**values)


def typed_config(cls, config: dict):
    """The frozen dataclass ``cls`` built from an experiment config (its ``experiment``
    key aside). An unknown key (a typo), a missing one, a value of the wrong type (a
    string or a bool for a number), a number outside its field's :class:`Range`, or a
    mapping (``Annotated[dict, Schema]``) that does not fit its schema is a one-line
    ``ValueError`` naming the experiment and the key's path (``oblique.y``,
    ``media[1].g``), as are the checks of ``cls.__post_init__``. Lists become tuples."""
    name = config.get("experiment", cls.__name__)
    try:
        return _build(cls, config)
    except _Invalid as e:
        raise ValueError(f"{name}: {e}") from None


def fit_keywords(where: str, key: str, value) -> dict:
    """``value``, extra :func:`~lightfield_jax.fit_images` keywords of a config's ``key``,
    checked as a capture file's ``fit:`` section is (the FitOptions fields, their types,
    then FitOptions' own checks): one-line errors naming ``where`` and ``key.FIELD``."""
    from lightfield_jax.capture.keys import read_fit_options
    from lightfield_jax.schema import Section

    return read_fit_options(Section(where, "", {key: value}, None), key)


def _type_name(annotation) -> str:
    origin = typing.get_origin(annotation)
    if origin is Annotated:
        return _type_name(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(annotation))
    if annotation is type(None):
        return "null"
    if origin in (tuple, list):
        return "a list"
    if annotation is dict:
        return "a mapping"
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
    name, path = str(path), Path(path)
    known = sorted(p.stem for p in CONFIGS_DIR.glob("*.yaml"))
    if not name.strip():  # Path("") is "."
        raise FileNotFoundError(
            f"an empty experiment name: give NAME or a config file (shipped: {', '.join(known)})"
        )
    shipped = CONFIGS_DIR / f"{path.stem}.yaml"
    if not path.is_file() and path.parent == Path(".") and shipped.is_file():
        path = shipped  # a shipped config, by name
    if not path.is_file() and not (path.exists() or path.is_symlink()):
        raise FileNotFoundError(f"{path}: no such experiment config (shipped: {', '.join(known)})")
    # Else a folder, FIFO or symlink loop: load_yaml names it (before the read).
    # The configs' own loader: duplicate keys, alias bombs and oversized files refused.
    data = load_yaml(path, ValueError)
    if "experiment" not in data:
        raise ValueError(f"{path}: an experiment config needs the key 'experiment: NAME'")
    small = data.pop("reduced", None) or {}
    if not isinstance(small, dict):
        raise ValueError(f"{path}: reduced: must be a mapping of overrides")
    if reduced and not small:  # else a full run would be recorded as a reduced one
        raise ValueError(f"{path}: --reduced: this config has no reduced: section to apply")
    # Checked in a full run too (a typo there would surface only in the test suite);
    # not the experiment: the reduced run is the same experiment.
    unknown = sorted(map(str, set(small) - set(data) | ({"experiment"} & set(small))))
    if unknown:
        raise ValueError(f"{path}: reduced: overrides unknown keys {unknown}")
    if reduced:
        data.update(small)
    return data


# A sweep larger than this is refused unless allowed (run_experiment's max_cells,
# ``experiment --max-cells``): a config of 10**6 cells would start days of work
# without a word. The shipped full configs count at most a few thousand.
MAX_CELLS = 10_000
# Integer keys that count repetitions of the whole experiment (one cell each).
_COUNT_KEYS = ("seeds",)


def count_cells(config: dict) -> int:
    """An upper estimate of the units of work (cells) an experiment config sweeps,
    from its shape alone (no script loaded): in each mapping, the product of the
    lengths of its lists (each a sweep axis) and of its ``seeds`` count, times the sum
    of the cells of its sub-mappings that sweep something (each a sweep of its own).
    ``experiment`` and ``reduced`` are not counted. Any runner can call it before the
    work starts."""
    return _cells(config, top=True)[0]


def _cells(value: dict, top: bool = False) -> tuple[int, bool]:
    """(cells, whether ``value`` sweeps anything) of one mapping of a config."""
    product, sections, sweeps = 1, 0, False
    for key, item in value.items():
        if top and key in ("experiment", "reduced"):
            continue
        if isinstance(item, list):
            product *= max(1, len(item))
            sweeps = True
        elif key in _COUNT_KEYS and isinstance(item, int) and not isinstance(item, bool):
            product *= max(1, item)
            sweeps = True
        elif isinstance(item, dict):
            cells, inner = _cells(item)
            if inner:
                sections += cells
                sweeps = True
    return product * max(1, sections), sweeps


def check_cells(config: dict, source: str | Path, limit: int | None = MAX_CELLS) -> int:
    """The cells of ``config`` (:func:`count_cells`), refused (a ``ValueError`` naming
    ``source`` and the count) above ``limit`` (``None``: no limit)."""
    cells = count_cells(config)
    if limit is not None and cells > limit:
        raise ValueError(
            f"{source}: sweeps about {cells} cells (the product of its lists' lengths), "
            f"more than the limit of {limit}; a run of that size is meant: give "
            f"--max-cells {cells} (run_experiment(..., max_cells={cells}))"
        )
    return cells


SCRIPTS_PACKAGE = "lightfield_jax_experiments"


def _exec_module(name: str, path: Path):
    """Execute ``path`` as the module ``lightfield_jax_experiments.NAME``, registered in
    ``sys.modules`` first (dataclasses in a script look their module up)."""
    # The scripts' package, as a module of its own: pickle finds a script's functions
    # by importing their module's name (Dask sends them to its workers so).
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


class ExperimentError(RuntimeError):
    """An experiment that failed while it ran (e.g. a child process's fit): one line."""


def child_failed(what: str, returncode: int, stderr: str) -> ExperimentError:
    """The error of a child process that failed: ``what`` and its last line of stderr
    (its exception), or its exit status (a child killed by a signal says nothing)."""
    lines = [line.strip() for line in (stderr or "").splitlines() if line.strip()]
    reason = lines[-1][:300] if lines else f"exit status {returncode}"
    return ExperimentError(f"{what} failed: {reason}")


def check_experiment_config(module, config: dict) -> Any:
    """The script's typed ``Config`` of ``config`` (every experiment script defines one),
    and the memory its smallest render of ``width`` × ``height`` needs (checked against
    the machine's, see :mod:`lightfield_jax.runtime.memory`): a bad config is refused in a
    second, before any work."""
    from lightfield_jax.runtime.memory import check_memory, render_bytes

    typed = typed_config(module.Config, config)
    w, h = getattr(typed, "width", None), getattr(typed, "height", None)
    if isinstance(w, int) and isinstance(h, int):
        # A lower bound: one image at 16 direction bins (the experiments render more).
        check_memory(render_bytes(1, h, w, 16), f"{config['experiment']}: {w}x{h} pixels")
    return typed


_CURRENT: contextvars.ContextVar[Context | None] = contextvars.ContextVar(
    "lightfield_jax_experiment", default=None
)


def current_client():
    """The Dask client of the experiment now running (started at the first call), or
    ``None`` outside :func:`run_experiment`: the experiments' helpers run their fits
    on it."""
    ctx = _CURRENT.get()
    return None if ctx is None else ctx.client()


def run_experiment(
    config_path: str | Path,
    out: str | Path | None = None,
    *,
    reduced: bool = False,
    progress: Callable[[str], None] = lambda _m: None,
    max_cells: int | None = MAX_CELLS,
    scheduler: str | None = None,
    workers: int | None = None,
    allow_large: bool = False,
    say: Callable[[str], None] = lambda _m: None,
) -> dict:
    """Run one experiment; returns its summary (also written to ``out/summary.json``).

    The config is checked whole before any work (:func:`check_experiment_config`). The
    outputs are written into a staging folder beside ``out`` and published into ``out``
    (with ``summary.json``) only when the run succeeds: a failed run leaves no partial
    result, only ``out/cache`` (the finished units a rerun resumes from). A config
    sweeping more than ``max_cells`` cells (:func:`count_cells`) is refused before it
    starts (``None``: no limit).

    ``scheduler``, ``workers``: where the script's parallel sweeps run (a Dask cluster,
    see :meth:`Context.parallel_sweep`); ``allow_large``: sweeps of more than 10^4
    points are refused without it; ``say``: the messages said before a sweep."""
    config = load_experiment_config(config_path, reduced)
    check_cells(config, config_path, max_cells)
    try:
        module = _load_script(config["experiment"])
        check_experiment_config(module, config)
        if reduced:  # the values reduced: replaces too: a trial run vouches for the config
            typed_config(module.Config, load_experiment_config(config_path))
    except ValueError as e:  # a config the script refuses: named with its file
        e.args = (f"{config_path}: {e}",)  # (its kind kept: a MemoryLimitError)
        raise
    name = config["experiment"]
    out = Path(out) if out is not None else Path("results") / name
    existed = out.exists()
    started = datetime.datetime.now(datetime.UTC)
    try:
        with atomic_directory(out) as staging:
            ctx = Context(
                out=staging,
                progress=progress,
                reduced=reduced,
                keep=out,
                scheduler=scheduler,
                workers=workers,
                allow_large=allow_large,
                say=say,
            )
            current = _CURRENT.set(ctx)
            try:
                summary = module.run(config, staging, ctx)
            except ValueError as e:  # a config the script refuses late
                e.args = (f"{config_path}: {e}",)
                raise
            finally:
                _CURRENT.reset(current)
                ctx.close()
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
            atomic_write_json(staging / "summary.json", record)
    except BaseException:
        if not existed and out.is_dir() and not any(out.iterdir()):
            out.rmdir()  # no empty output folder left behind
        raise
    return record
