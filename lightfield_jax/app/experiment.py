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
runner checks the whole config against it
(:func:`~lightfield_jax.app.experiment_config.typed_config`), and the grid's memory,
before any work, so that a bad config is one line naming the file and the key. The
outputs go to a staging folder, published into ``out`` only when the run succeeds.

Long experiments resume: ``ctx.cached(key, compute)`` stores each finished unit of work
as ``out/cache/KEY.json`` (kept when a run fails) and returns it on a rerun instead of
recomputing; ``ctx.sweep(axes, key, compute)`` runs a Cartesian sweep that way. The
other pieces the scripts share (CSV tables, figures, the run's provenance) are
:mod:`lightfield_jax.app.experiment_records`.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import datetime
import hashlib
import itertools
import json
import os
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

from lightfield_jax.app.distributed import Task, check_count, cluster, run_tasks
from lightfield_jax.app.experiment_config import (
    MAX_CELLS,
    check_cells,
    typed_config,
)
from lightfield_jax.app.experiment_records import (
    machine,
    versions,
)
from lightfield_jax.app.experiment_scripts import CONFIGS_DIR as CONFIGS_DIR
from lightfield_jax.app.experiment_scripts import EXPERIMENTS_DIR as EXPERIMENTS_DIR
from lightfield_jax.app.experiment_scripts import load_helper as load_helper
from lightfield_jax.app.experiment_scripts import load_script
from lightfield_jax.files import atomic_directory, atomic_write_json
from lightfield_jax.runtime.memory import check_memory, render_bytes
from lightfield_jax.schema import load_yaml


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


def child_env() -> dict[str, str]:
    """The environment of an experiment's child process: the parent's, with JAX's GPU
    memory preallocation off unless set (parent and children share one accelerator;
    each would otherwise take 75 % of its memory at its first array, and a child ran
    out of memory on an H200)."""
    return {"XLA_PYTHON_CLIENT_PREALLOCATE": "false", **os.environ}


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
        module = load_script(config["experiment"])
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
