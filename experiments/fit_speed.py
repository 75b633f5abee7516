"""How long does the joint fit take, and does its cost grow with the albedo?

Each medium of ``media`` is rendered as a noiseless six-shift stripe capture
(:func:`~lightfield_jax.simulate_capture`, period 6, gain 1, black level 0; the plain
series marched to ``bounces``, or a medium's ``tail`` solve past 4 of them) and fitted
by the default joint fit (``fit`` holds extra :func:`~lightfield_jax.fit_images`
keywords, e.g. ``tail``) in a fresh Python process, twice:

- ``cold``: the first fit of the process, nothing compiled (no persistent XLA cache):
  what ``lightfield-jax fit`` costs a user, split into XLA compile and run seconds
  (the fit's own split; the process start and imports are apart, ``process``);
- ``warm``: the same fit again in that process, on the programs already compiled;
- ``cached``: the same fit in a second fresh process that shares the first one's
  persistent compilation cache (:func:`~lightfield_jax.enable_compilation_cache`, in a
  temporary folder; the command line turns it on by default): what the next capture's
  fit costs a user in a new session, compiled programs loaded instead of compiled.

Per fit: errors of σt, σs (relative) and g (absolute), iterations, the model (bounces,
or K0 and the tail's method and Krylov steps), the verdict and its reasons. The dense
forward medium's and the refractive slab's cold times are also given as multiples of
the milk's in the same run (the issue's target: at most 3×). The machine may be shared:
compare rows of one run, and read each record's 1-minute load average.

Each medium's record is one cached unit (a stopped run resumes). A child process that
fails (its fit raises) fails the experiment with the child's last line; a fit past
``timeout`` is recorded as a timeout.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Annotated, Literal

import numpy as np

import lightfield_jax as lfj
from lightfield_jax.app.experiment import ExperimentError, child_env, child_failed, load_helper
from lightfield_jax.app.experiment_config import Pixels, Range, fit_keywords, typed_config
from lightfield_jax.app.experiment_records import provenance, pyplot, save_figure
from lightfield_jax.scene.geometry_spec import parse_geometry


@dataclasses.dataclass(frozen=True)
class MediumSpec:
    """One medium: its name, σt, σs (per pixel), g; optional phase, geometry (a slab),
    the truth's bounces (default: auto), its own fit keywords (over the config's
    ``fit``: the same medium fitted two ways in one run) and the truth's tail solve
    (``simulate``'s ``tail``: a slab near albedo 1, whose march takes most of an hour at
    128×96)."""

    name: str
    sigma_t: float
    sigma_s: float
    g: float
    phase: str = "paper"
    geometry: dict | None = None
    bounces: int | str | None = None
    fit: dict | None = None
    tail: Literal["gmres", "bicgstab"] | None = None


@dataclasses.dataclass(frozen=True)
class Config:
    """configs/fit_speed.yaml: the captures' size (pixels), the media (each: name,
    sigma_t, sigma_s, g; optional phase, geometry, the truth's bounces), extra
    :func:`~lightfield_jax.fit_images` keywords (a capture file's ``fit:`` keys) and the
    time limit (s) of each medium's child process."""

    width: Pixels
    height: Pixels
    media: tuple[Annotated[dict, MediumSpec], ...]
    fit: dict = dataclasses.field(default_factory=dict)
    timeout: Annotated[float, Range(0, 86_400, open_low=True)] = 1800.0
    heights: tuple[Pixels, ...] = ()
    height_media: tuple[str, ...] = ()

    def __post_init__(self):
        if not self.media:
            raise ValueError("fit_speed: media: must list at least one medium")
        names = [m["name"] for m in self.media]
        if len(set(names)) < len(names):
            raise ValueError(f"fit_speed: media: names must differ, got {names}")
        inv = load_helper("_inverse")
        for i, m in enumerate(self.media):  # each capture's config, as simulate checks it
            inv.check_simulation_config(_capture_config(self, m), f"fit_speed: media[{i}]")
        # The fit's keywords, as a capture file's fit: section (FitOptions' own checks).
        fit_keywords("fit_speed", "fit", self.fit)
        for i, m in enumerate(self.media):
            if m.get("fit") is not None:
                fit_keywords("fit_speed", f"media[{i}].fit", {**self.fit, **m["fit"]})
        for name in self.height_media:
            if name not in names:
                raise ValueError(f"fit_speed: height_media: {name!r} is not a medium of media")


def _capture_config(cfg: Config, medium: dict, height: int | None = None) -> dict:
    inv = load_helper("_inverse")
    sim_cfg = inv.capture_config(
        {"phase": "paper", **medium},
        cfg.width,
        cfg.height if height is None else height,
        black_level=0.0,
        bounces="auto" if medium.get("bounces") is None else medium["bounces"],
    )
    if medium.get("geometry"):
        sim_cfg["geometry"] = dict(medium["geometry"])
    if medium.get("tail"):
        sim_cfg["tail"] = medium["tail"]
    return sim_cfg


def _capture(cfg: Config, medium: dict, height: int) -> np.ndarray:
    config = _capture_config(cfg, medium, height)
    return np.asarray(load_helper("_inverse").simulate(config).images)


def _fit_kwargs(cfg: Config, medium: dict) -> dict:
    kwargs = {
        "black_level": 0.0,
        "phase": medium.get("phase", "paper"),
        **load_helper("_inverse").OWN_MODEL,  # the captures are the model's own renders
        **cfg.fit,
        **(medium.get("fit") or {}),
    }
    if medium.get("geometry"):
        kwargs["geometry"] = medium["geometry"]
    return kwargs


def _in_fresh_process(images: np.ndarray, truth: dict, kwargs: dict, timeout: float) -> dict:
    """The cold and warm fits in a child process, then the cached fit in a second one
    (each killed after ``timeout`` seconds)."""
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        np.save(tmp / "images.npy", images)
        request = {
            "images": str(tmp / "images.npy"),
            "truth": truth,
            "kwargs": kwargs,
            "cache": str(tmp / "xla_cache"),
        }
        rec = _child_run(tmp / "request.json", {**request, "labels": ["cold", "warm"]}, timeout)
        if "cold" in rec and "warm_timeout" not in rec:
            again = _child_run(tmp / "again.json", {**request, "labels": ["cached"]}, timeout)
            if "cached" in again:
                rec["cached"] = again["cached"]
                rec["cached_process_seconds"] = again["process_seconds"]
        return rec


def _child_run(path: Path, request: dict, timeout: float) -> dict:
    """One child process running ``request``'s fits; its record."""
    path.write_text(json.dumps(request))
    t = time.perf_counter()
    try:
        done = subprocess.run(
            [sys.executable, __file__, str(path)],
            capture_output=True,
            text=True,
            timeout=timeout,
            env=child_env(),
        )
    except subprocess.TimeoutExpired:
        done = None
    path = path.with_suffix(".out.json")
    if done is not None and done.returncode != 0:  # a failed fit is no measurement
        raise child_failed("the fit's child process", done.returncode, done.stderr)
    if not path.exists():
        if done is not None:
            raise ExperimentError("the fit's child process exited without a result")
        return {"error_message": f"timeout: no result within {timeout:g} s"}
    rec = json.loads(path.read_text())
    if done is None:
        rec["warm_timeout"] = timeout
    rec["process_seconds"] = time.perf_counter() - t
    return rec


def _child(request_path: str) -> None:
    t_start = time.perf_counter()
    req = json.loads(Path(request_path).read_text())
    inv = load_helper("_inverse")
    kwargs = dict(req["kwargs"])
    if kwargs.get("geometry"):
        kwargs["geometry"] = parse_geometry(kwargs["geometry"], "geometry")
    images = np.load(req["images"])
    lfj.enable_compilation_cache(req["cache"])
    out = {"imports_seconds": time.perf_counter() - t_start}
    for label in req["labels"]:
        load = os.getloadavg()[0]
        log, t0 = [], time.perf_counter()
        res = lfj.fit_images(
            images,
            lfj.Stripes(),
            progress=lambda m, log=log, t0=t0: log.append(f"{time.perf_counter() - t0:.1f} s {m}"),
            **kwargs,
        )
        out[label] = {
            **inv.result_record(res, req["truth"]),
            "reasons": list(res.reasons),
            "load_avg": load,
            "log": log,
        }
        # After each fit: a warm fit past the time limit leaves the cold one's record.
        Path(request_path).with_suffix(".out.json").write_text(json.dumps(inv.jsonable(out)))


def _marched_how(model: dict) -> str:
    """How a marched model's stripes were rendered: from one period (the stripe cell,
    every bounce on the model's grid), after a coarse tail's K0, or neither."""
    coarse, cell = model.get("coarse_tail"), model.get("stripe_cell")
    if cell:
        return f" (stripe cell, shift_orders {cell['shift_orders']})"
    return f" (coarse after {coarse['after']})" if coarse else ""


def _summary_row(name: str, height: int, rec: dict) -> dict:
    if "error_message" in rec:
        return {"medium": name, "height": height, "error_message": rec["error_message"]}
    cold, warm = rec["cold"], rec.get("warm", {"seconds": {"total": None}})
    model = cold["model"]
    tail = model.get("tail")
    return {
        "medium": name,
        "height": height,
        "cold_seconds": cold["seconds"]["total"],
        "cold_compile": cold["seconds"]["compile"],
        "cold_run": cold["seconds"]["run"],
        "warm_seconds": warm["seconds"]["total"],
        "cached_seconds": rec.get("cached", {"seconds": {"total": None}})["seconds"]["total"],
        "process_seconds": rec["process_seconds"],
        "errors": cold["errors"],
        "iterations": cold["iterations"],
        "model": (
            f"K = {model['bounces']}" + _marched_how(model)
            if tail is None
            else f"K0 = {tail['K0']} + {tail['method']} ({tail.get('steps')} steps)"
        ),
        "n_theta": model["n_theta"],
        "refine": model["refine"],
        "converged": cold["converged"],
        "reasons": cold["reasons"],
        "load_avg": cold["load_avg"],
    }


def _write(ctx, cfg: Config, rows: list, records: dict) -> None:
    """fit_speed.json with the rows so far, each timed also against the first medium's
    (the milk's) fit at the same height, and the chart of warm time against height."""
    inv = load_helper("_inverse")
    first = {r["height"]: r for r in rows if r["medium"] == rows[0]["medium"]}
    for r in rows:
        base = first.get(r["height"], {})
        if "cold_seconds" in r and "cold_seconds" in base:
            r["cold_vs_first"] = r["cold_seconds"] / base["cold_seconds"]
            r["run_vs_first"] = r["cold_run"] / base["cold_run"]
        if r.get("warm_seconds") and base.get("warm_seconds"):
            r["warm_vs_first"] = r["warm_seconds"] / base["warm_seconds"]
    if cfg.height_media:
        _height_figure(ctx, rows)
    data = {
        "width": cfg.width,
        "height": cfg.height,
        "fit": cfg.fit,
        "rows": rows,
        "records": records,
        **provenance(),
    }
    ctx.write_json("fit_speed.json", inv.jsonable(data))


def _height_figure(ctx, rows: list) -> None:
    """Warm and cached fit seconds against the capture's height, one line a medium."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for name in dict.fromkeys(r["medium"] for r in rows):
        mine = sorted((r for r in rows if r["medium"] == name), key=lambda r: r["height"])
        if len(mine) < 2:
            continue
        h = [r["height"] for r in mine]
        line = ax.plot(h, [r.get("warm_seconds") or np.nan for r in mine], "o-", label=name)
        cached = [r.get("cached_seconds") or np.nan for r in mine]
        ax.plot(h, cached, "s--", color=line[0].get_color(), alpha=0.6)
    ax.set_xscale("log", base=2)
    ax.set_xticks(sorted({r["height"] for r in rows}))
    ax.get_xaxis().set_major_formatter(lambda v, _: f"{v:g}")
    ax.set_xlabel("capture height (rows; width fixed)")
    ax.set_ylabel("joint fit (s): warm o-, cached s--")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, ctx.out / "fit_speed_height.png")


def _units(cfg: Config) -> list[tuple[dict, int]]:
    """(medium, capture height) of every fit: each medium at the config's height, the
    ``height_media`` also at each of ``heights``."""
    units = [(m, cfg.height) for m in cfg.media]
    for m in cfg.media:
        if m["name"] in cfg.height_media:
            units += [(m, h) for h in cfg.heights if h != cfg.height]
    return units


def run(config: dict, out: Path, ctx) -> dict:
    cfg = typed_config(Config, config)
    inv = load_helper("_inverse")
    records, rows = {}, []
    for medium, height in _units(cfg):
        name = medium["name"]

        def measure(medium=medium, name=name, height=height):
            ctx.progress(f"{name} ({height} rows): capture")
            images = _capture(cfg, medium, height)
            ctx.progress(f"{name} ({height} rows): fits in a fresh process")
            kwargs = _fit_kwargs(cfg, medium)
            try:
                return _in_fresh_process(images, inv.truth_of(medium), kwargs, cfg.timeout)
            except ExperimentError as e:
                raise ExperimentError(f"fit_speed: media {name}: {e}") from None

        # Each medium's record kept as it is measured: a failed or stopped run resumes.
        key = (
            f"fit_speed|lib{inv.library_fingerprint()}|{cfg.width}x{height}|"
            f"{json.dumps(medium, sort_keys=True)}|{json.dumps(cfg.fit, sort_keys=True)}|"
            f"timeout{cfg.timeout}"
        )
        rec = ctx.cached(key, measure)
        records[f"{name}@{height}"] = {"medium": medium, "height": height, **rec}
        rows.append(_summary_row(name, height, rec))
        ctx.progress(f"{name}: {json.dumps(inv.jsonable(rows[-1]))}")
    _write(ctx, cfg, rows, records)
    return {"rows": inv.jsonable(rows)}


if __name__ == "__main__":
    _child(sys.argv[1])
