"""How does a sweep of fits scale with Dask workers (issue 48)?

A sweep of ``len(sigma_t) × len(g)`` cells (simulated stripe captures of a small grid,
each fitted with the joint method) runs once per entry of ``workers`` on a fresh local
Dask cluster of that many worker processes (one thread each), through the runner's
task engine (:func:`lightfield_jax.app.distributed.run_tasks`: nothing stored, every
cell computed). Measured: the sweep's wall time (from the first submission to the last
result; the cluster's start is apart), each fit's own seconds, and whether every
cell's answer is the same bit for bit across worker counts and against the serial run
(``serial``: every cell fitted in this process first, one after the other).

Each worker compiles the fit's programs once (all cells have one shape) and reuses
them for its later cells, as a serial run does: the first cell of each worker is the
slow one.

Outputs: ``dask_scaling.json`` (the rows, the machine, the versions, the date),
``dask_scaling.png`` (wall time and speed-up against the worker count).
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import Annotated

from lightfield_jax.app.experiment import load_helper
from lightfield_jax.app.experiment_config import (
    Count,
    Dtype,
    Pixels,
    Positive,
    Range,
    Seed,
    typed_config,
)
from lightfield_jax.app.experiment_records import provenance, pyplot, save_figure

inv = load_helper("_inverse")

# What differs between two runs of the same fit: its timings and the load it ran under.
UNSTABLE = ("seconds", "load_avg")


@dataclasses.dataclass(frozen=True)
class Config:
    """configs/dask_scaling.yaml: the cells (σt × g at one albedo, a small grid, noise),
    the fit's step limit, the worker counts to time, and whether to fit serially too."""

    dtype: Dtype
    width: Pixels
    height: Pixels
    sigma_t: tuple[Positive, ...]
    g: tuple[Annotated[float, Range(-0.9, 0.9)], ...]
    albedo: Annotated[float, Range(0, 0.95, open_low=True)]
    photons: Positive
    read: Annotated[float, Range(0)]
    seed: Seed
    max_steps: Count
    workers: tuple[Annotated[int, Range(1, 64)], ...]
    xla_cache: tuple[bool, ...] = (False,)
    serial: bool = True


def _cell(config: Config, sigma_t: float, g: float, xla_dir: str | None = None) -> dict:
    """One cell: its capture (seeded) and the joint fit's record (with the persistent
    compilation cache ``xla_dir``, when given)."""
    medium = {"sigma_t": sigma_t, "sigma_s": sigma_t * config.albedo, "g": g}
    sim = inv.simulate(inv.capture_config(medium, config.width, config.height))
    images = inv.camera(sim.images, (config.photons, config.read), config.seed)
    with inv.xla_cache(xla_dir):
        rec = inv.fit_record(
            images,
            sim.config.illumination,
            inv.truth_of(medium),
            method="joint",
            black_level=0.0,
            max_steps=config.max_steps,
        )
    return inv.jsonable({"sigma_t": sigma_t, "g": g, **rec})


def _stable(rec):
    """``rec`` without its timings and load, at every depth."""
    if isinstance(rec, dict):
        return {k: _stable(v) for k, v in rec.items() if k not in UNSTABLE}
    if isinstance(rec, list):
        return [_stable(v) for v in rec]
    return rec


def _differences(a, b, path: str = "") -> list[str]:
    """The paths (``[3].sigma_t``) where two records (lists of) differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        keys = sorted(set(a) | set(b))
        return [d for k in keys for d in _differences(a.get(k), b.get(k), f"{path}.{k}")]
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        pairs = enumerate(zip(a, b, strict=True))
        return [d for i, (x, y) in pairs for d in _differences(x, y, f"{path}[{i}]")]
    return [] if a == b else [path]


def _sweep(config: Config, workers: int, xla_dir: str | None) -> dict:
    """The sweep on a fresh local cluster of ``workers`` processes: its records and
    times."""
    from lightfield_jax.app.distributed import Task, cluster, run_tasks

    tasks = [
        Task(f"st{st}|g{g}", f"sigma_t {st}, g {g}", _cell, (config, st, g, xla_dir))
        for st in config.sigma_t
        for g in config.g
    ]
    t0 = time.perf_counter()
    with cluster(workers=workers) as client:
        client.wait_for_workers(workers, timeout=120)
        started = time.perf_counter()
        report = run_tasks(tasks, load=lambda _t: None, save=lambda _t, _v: None, client=client)
        wall = time.perf_counter() - started
    if report.failures:
        raise RuntimeError(f"dask_scaling: {next(iter(report.failures.values()))}")
    records = [report.results[t.key] for t in tasks]
    return {
        "workers": workers,
        "xla_cache": xla_dir is not None,
        "cells": len(tasks),
        "wall_seconds": wall,
        "cluster_start_seconds": started - t0,
        "fit_seconds": [r["seconds"]["total"] for r in records],
        "records": records,
    }


def run(raw: dict, out: Path, ctx) -> dict:
    import tempfile

    config = typed_config(Config, raw)
    runs = []
    with inv.precision(config.dtype), tempfile.TemporaryDirectory() as tmp:
        # The persistent compilation cache of the runs that use it: filled by the first
        # fit that compiles (the serial run's, else a worker's), read by every worker.
        xla = str(Path(tmp) / "xla")
        serial, serial_seconds = None, None
        if config.serial:
            ctx.progress("serial")
            t0 = time.perf_counter()
            serial = [
                _cell(config, st, g, xla if any(config.xla_cache) else None)
                for st in config.sigma_t
                for g in config.g
            ]
            serial_seconds = time.perf_counter() - t0
        for cached in config.xla_cache:
            for n in config.workers:
                ctx.progress(f"{n} worker(s){', XLA cache' if cached else ''}")
                runs.append(_sweep(config, n, xla if cached else None))
    reference = [_stable(r) for r in runs[0]["records"]]
    for r in runs:
        mine = [_stable(x) for x in r["records"]]
        r["differs_from_first"] = _differences(reference, mine)
        r["same_as_first"] = not r["differs_from_first"]
        if serial is not None:
            r["differs_from_serial"] = _differences([_stable(x) for x in serial], mine)
        r["same_as_serial"] = None if serial is None else not r["differs_from_serial"]
    first = {c: next(r for r in runs if r["xla_cache"] == c) for c in config.xla_cache}
    table = [
        {
            "workers": r["workers"],
            "xla_cache": r["xla_cache"],
            "wall_seconds": r["wall_seconds"],
            "speedup": first[r["xla_cache"]]["wall_seconds"] / r["wall_seconds"],
            "median_fit_seconds": inv.median(r["fit_seconds"]),
            "first_fit_seconds": max(r["fit_seconds"]),
            "cluster_start_seconds": r["cluster_start_seconds"],
            "same_as_first": r["same_as_first"],
            "same_as_serial": r["same_as_serial"],
        }
        for r in runs
    ]
    data = {
        "config": raw,
        "table": table,
        "serial_seconds": serial_seconds,
        "serial_records": serial,
        "runs": runs,
        "load_avg_end": os.getloadavg(),
        **provenance(),
    }
    ctx.write_json("dask_scaling.json", inv.jsonable(data))
    title = (
        f"{runs[0]['cells']} joint fits ({config.width}x{config.height} px), one sweep per "
        "worker count"
    )
    figure = _plot(table, title, ctx.figure_path("dask_scaling.png"))
    return inv.jsonable(
        {
            "figures": [figure],
            "data": ["dask_scaling.json"],
            "table": table,
            "serial_seconds": data["serial_seconds"],
        }
    )


def _plot(table: list[dict], title: str, path: Path) -> str:
    plt = pyplot()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 3.6))
    for cached in sorted({r["xla_cache"] for r in table}):
        rows = [r for r in table if r["xla_cache"] == cached]
        n = [r["workers"] for r in rows]
        label = "warm XLA cache" if cached else "each worker compiles"
        ax1.plot(n, [r["wall_seconds"] for r in rows], "o-", label=label)
        ax2.plot(n, [r["speedup"] for r in rows], "o-", label=label)
    n = sorted({r["workers"] for r in table})
    ax2.plot(n, [k / n[0] for k in n], "k:", label="ideal")
    ax1.set_xlabel("Dask workers")
    ax1.set_ylabel("sweep wall time (s)")
    ax1.set_ylim(bottom=0)
    ax2.set_xlabel("Dask workers")
    ax2.set_ylabel(f"speed-up over {n[0]} worker(s)")
    for ax in (ax1, ax2):
        ax.set_xticks(n)
        ax.legend(fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)
    return path.name
