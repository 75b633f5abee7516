"""What does the rest of the bounce series cost, marched or solved?

A render keeps ``explicit_bounces`` = K0 bounces explicit; the rest of the series,
Σ_{k>K0} I_k, is either marched bounce by bounce (the plain series) or solved for in one
Krylov solve over the one-bounce operator (``tail: gmres`` / ``tail: bicgstab`` of
:func:`lightfield_jax.render`). For each per-bounce ratio bound ρ (``rho``) and phase
convention (``normalized``: σs = ρ·σt; ``paper``: σs = ρ·σt/A(g), so ω·A(g) = ρ < 1),
on one scene (full illumination from the left wall), it measures per method:

- ``series_auto``: the plain series with the bounce count ``bounces: auto`` gives,
  K = ⌈log(target·(1 − ρ))/log ρ⌉ (the tail bound; ``bounces_for_tolerance``, uncapped;
  not run above ``max_auto_bounces``);
- ``series_needed``: the plain series with the fewest bounces whose error is at most
  ``target`` (known only from the reference: an oracle count, the best a march can do);
- ``gmres``, ``bicgstab``: K0 explicit bounces and the tail solve at ``tail_tol``.

Error: relative L1 of the image of all orders against the reference, the plain series
marched until its last bounce's share, extrapolated geometrically, is below
``reference_tol`` (the bounce count doubles until it is). Time: the median of
``repeats`` steady calls (the first call, with its compile, reported apart); a first
call running longer than 10 s is not repeated (its run time counts, compile apart). The
figure shows the fastest steady call (the least disturbed by other jobs on a shared
machine), the JSON every call. Everything runs in float32 (the package's default), the
reference too. Each ``sigma_t`` (per pixel) is one scene: walls leak less light per
bounce from an optically larger scene, so its measured per-bounce ratio comes closer
to ρ.

Slab rows (``slab:``, docs/model.md §7): the same methods on a tank of depth
``thickness`` with absorbing and refractive faces (``boundaries``), ρ = ω (the slab's
3-D phase function is normalised on the sphere), on their own smaller grid: the tail
solve iterates the slab's bounce step through the same base-class loop as the plane.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import Annotated, Literal

import jax
import numpy as np

import lightfield_jax as lfj
from lightfield_jax.app.experiment_config import Pixels, Positive, Range, typed_config
from lightfield_jax.app.experiment_records import provenance, pyplot, save_figure
from lightfield_jax.forward.render import renderer_for
from lightfield_jax.runtime.timing import repeated_calls
from lightfield_jax.scene.medium import bounces_for_tolerance

_METHODS = ("series_auto", "series_needed", "gmres", "bicgstab")
Rho = Annotated[float, Range(0, 1, open_low=True, open_high=True)]
Boundary = Literal["absorbing", "refractive"]


@dataclasses.dataclass(frozen=True)
class SlabRows:
    """The slab rows: their grid, tank (depth in pixels, elevations, layers), σt per
    pixel, g, faces and ρ = albedo."""

    width: Pixels
    height: Pixels
    n_theta: int
    thickness: Positive
    n_mu: int
    n_z: int
    sigma_t: tuple[Positive, ...]
    g: Annotated[float, Range(-0.99, 0.99)]
    boundaries: tuple[Boundary, ...]
    rho: tuple[Rho, ...]

    def __post_init__(self):
        if not (self.sigma_t and self.boundaries and self.rho):
            raise ValueError("tail_acceleration: slab: sigma_t, boundaries, rho: at least one each")
        try:  # the grid and tanks as run() builds them: their own checks
            lfj.Grid(self.width, self.height, self.n_theta, 1)
            lfj.Slab(self.thickness, "absorbing", n_mu=self.n_mu, n_z=self.n_z)
        except ValueError as e:
            raise ValueError(f"tail_acceleration: slab: {e}") from None


@dataclasses.dataclass(frozen=True)
class Config:
    """configs/tail_acceleration.yaml: the grid, σt (per pixel), g, ρ, phases and
    methods, K0, the tolerances, the auto bounce count's limit, the timing repeats and
    the slab rows (see the module's doc)."""

    width: Pixels
    height: Pixels
    n_theta: int
    refine: int
    sigma_t: tuple[Positive, ...]
    g: Annotated[float, Range(-0.99, 0.99)]
    rho: tuple[Rho, ...]
    phases: tuple[Literal["normalized", "paper"], ...]
    methods: tuple[Literal[_METHODS], ...]
    explicit_bounces: Annotated[int, Range(1, 1000)]
    tail_tol: Annotated[float, Range(0, 0.1, open_low=True)]
    target: Annotated[float, Range(0, 0.1, open_low=True)]
    reference_tol: Annotated[float, Range(0, 0.1, open_low=True)]
    max_auto_bounces: Annotated[int, Range(1, 100_000)]
    repeats: Annotated[int, Range(1, 1000)]
    slab: Annotated[dict, SlabRows]

    def __post_init__(self):
        lists = ("sigma_t", "rho", "phases", "methods")
        if not all(getattr(self, k) for k in lists):
            raise ValueError(f"tail_acceleration: {', '.join(lists)}: at least one each")
        try:
            lfj.Grid(self.width, self.height, self.n_theta, self.refine)
        except ValueError as e:
            raise ValueError(f"tail_acceleration: {e}") from None


def _medium(cfg: dict, sigma_t: float, rho: float, phase: str) -> lfj.Medium:
    st, g = float(sigma_t), float(cfg["g"])
    a = 1.0 if phase == "normalized" else float(lfj.phase_integral(g))
    if rho / a >= 1.0:
        raise ValueError(f"tail_acceleration: rho {rho} needs albedo {rho / a:.3f} >= 1 ({phase})")
    return lfj.Medium(st, rho / a * st, g, phase)


def _plain(medium, grid, k: int, geometry):
    """Per-bounce images (K, H, W) of the plain series, float64 on the host."""
    renderer = renderer_for(grid, lfj.Full(), k, medium.phase, geometry)

    def call():
        images = renderer(medium.sigma_t, medium.sigma_s, medium.g)[0]
        return np.asarray(jax.block_until_ready(images)[0], np.float64)

    return call


def _reference(ctx, medium, grid, cfg: dict, geometry) -> tuple[np.ndarray, int]:
    """Per-bounce image sums s_k of a series marched until its geometric tail estimate
    s_K·r/(1 − r)/Σs (r = s_K/s_{K−1}) is below ``reference_tol``; returns the total image
    and the bounce sums."""
    k = 256
    while True:
        ctx.progress(f"reference: {k} bounces")
        images = _plain(medium, grid, k, geometry)()
        sums = images.sum(axis=(1, 2))
        r = sums[-1] / sums[-2] if sums[-2] > 0 else 0.0  # float32 underflows to 0
        if r < 1 and sums[-1] * r / (1 - r) <= cfg["reference_tol"] * sums.sum():
            return images, sums
        if k >= 65536:
            raise RuntimeError(f"tail_acceleration: reference not converged at {k} bounces")
        k *= 2


def _rel_l1(a, b) -> float:
    return float(np.abs(np.asarray(a, np.float64) - b).sum() / np.abs(b).sum())


def _case(
    ctx, cfg: dict, grid: lfj.Grid, sigma_t: float, rho: float, phase: str, slab=None
) -> list[dict]:
    """The rows of one scene and ρ: the plane (``slab`` None) under ``phase``, or the
    slab (ρ = ω, its own normalised 3-D phase function)."""
    if slab is None:
        medium, geometry, label = _medium(cfg, sigma_t, rho, phase), lfj.Plane(), "plane"
    else:
        medium = lfj.Medium(sigma_t, rho * sigma_t, cfg["slab"]["g"], "normalized")
        geometry, label = slab, f"slab {slab.boundary}"
    images_ref, sums = _reference(ctx, medium, grid, cfg, geometry)
    total_ref = images_ref.sum(axis=0)
    k0 = cfg["explicit_bounces"]
    tail_ref = images_ref[k0:].sum(axis=0)
    # Error of the first K bounces alone (images are non-negative: the L1 of a partial
    # sum's error is the sum of the rest).
    partial_error = 1.0 - np.cumsum(sums) / sums.sum()
    k_needed = int(np.argmax(partial_error <= cfg["target"])) + 1
    base = {
        "geometry": label,
        "sigma_t": sigma_t,
        "phase": phase,
        "rho": rho,
        "albedo": float(medium.albedo),
        "sigma_s": float(medium.sigma_s),
        "reference_bounces": int(len(sums)),
        "measured_ratio": float(sums[-1] / sums[-2]) if sums[-2] > 0 else 0.0,
    }
    rows = []
    for method in cfg["methods"]:
        ctx.progress(f"{label} {phase} rho {rho}: {method}")
        row = dict(base, method=method)
        if method.startswith("series"):
            if method == "series_auto":
                k = bounces_for_tolerance(rho, cfg["target"], math.inf)
            else:
                k = k_needed
            row.update(bounces=k, explicit_bounces=k)
            if k > cfg["max_auto_bounces"]:
                row.update(skipped=f"{k} bounces > max_auto_bounces {cfg['max_auto_bounces']}")
                rows.append(row)
                continue
            timed = repeated_calls(_plain(medium, grid, k, geometry), cfg["repeats"])
            total = timed.pop("out").sum(axis=0)
            row.update(error_total=_rel_l1(total, total_ref))
        else:
            renderer = renderer_for(
                grid, lfj.Full(), k0, medium.phase, geometry, method, cfg["tail_tol"]
            )

            def call(renderer=renderer):
                images, _, tail = renderer(medium.sigma_t, medium.sigma_s, medium.g)
                return jax.block_until_ready((images, tail))

            timed = repeated_calls(call, cfg["repeats"])
            images, tail = timed.pop("out")
            images = np.asarray(images[0], np.float64)
            tail_image = np.asarray(tail.image[0], np.float64)
            row.update(
                bounces=None,
                explicit_bounces=k0,
                steps=int(tail.steps),
                converged=bool(tail.converged),
                error_total=_rel_l1(images.sum(axis=0) + tail_image, total_ref),
                error_tail=_rel_l1(tail_image, tail_ref),
                error_explicit=_rel_l1(images, images_ref[:k0]),
            )
        row.update(timed)
        rows.append(row)
    return rows


def run(config: dict, out: Path, ctx) -> dict:
    typed_config(Config, config)  # every key checked before any work
    cfg = dict(config)
    grid = lfj.Grid(cfg["width"], cfg["height"], cfg["n_theta"], cfg["refine"])
    rows = []
    shared = {k: v for k, v in cfg.items() if k not in ("sigma_t", "rho", "phases", "slab")}
    for sigma_t in cfg["sigma_t"]:
        for phase in cfg["phases"]:
            for rho in cfg["rho"]:
                key = f"{sigma_t}|{phase}|{rho}|{sorted(shared.items())}"
                rows += ctx.cached(
                    key,
                    lambda s=sigma_t, p=phase, r=rho: _case(ctx, cfg, grid, s, r, p),
                )
    sc = cfg["slab"]
    slab_grid = lfj.Grid(sc["width"], sc["height"], sc["n_theta"], 1)
    slab_shared = {k: v for k, v in sc.items() if k not in ("sigma_t", "boundaries", "rho")}
    for sigma_t in sc["sigma_t"]:
        for boundary in sc["boundaries"]:
            slab = lfj.Slab(sc["thickness"], boundary, n_mu=sc["n_mu"], n_z=sc["n_z"])
            for rho in sc["rho"]:
                key = (
                    f"slab|{slab}|{sigma_t}|{rho}|{sorted(slab_shared.items())}|"
                    f"{sorted(shared.items())}"
                )
                rows += ctx.cached(
                    key,
                    lambda s=sigma_t, b=slab, r=rho: _case(
                        ctx, cfg, slab_grid, s, r, "normalized", b
                    ),
                )
    data = {
        "grid": {
            "width": grid.width,
            "height": grid.height,
            "n_theta": grid.n_theta,
            "refine": grid.refine,
        },
        "sigma_t": cfg["sigma_t"],
        "g": cfg["g"],
        "slab": cfg["slab"],
        "explicit_bounces": cfg["explicit_bounces"],
        "tail_tol": cfg["tail_tol"],
        "target": cfg["target"],
        "dtype": "float32",
        "load_average_1min": os.getloadavg()[0],
        **provenance(),
        "rows": rows,
    }
    ctx.write_json("tail_acceleration.json", data)
    figure = _plot(data, ctx.figure_path("tail_acceleration.png"))
    return {
        "figure": str(figure),
        "table": [
            {
                k: r.get(k)
                for k in (
                    "geometry",
                    "sigma_t",
                    "phase",
                    "rho",
                    "method",
                    "bounces",
                    "steps",
                    "seconds",
                    "error_total",
                    "skipped",
                )
            }
            for r in rows
        ],
    }


def _plot(data: dict, path: Path) -> Path:
    # One panel row per plane scene (σt; line style: phase convention), one for the
    # slab rows (line style: the faces).
    panels = [
        (
            f"plane σt {st}",
            lambda r, st=st: r.get("geometry", "plane") == "plane" and r["sigma_t"] == st,
            "phase",
            {"normalized": "-", "paper": "--"},
        )
        for st in data["sigma_t"]
    ]
    panels += [
        (
            f"slab σt {st}",
            lambda r, st=st: r.get("geometry", "plane") != "plane" and r["sigma_t"] == st,
            "geometry",
            {"slab absorbing": "-", "slab refractive": "--"},
        )
        for st in data["slab"]["sigma_t"]
    ]
    fig = pyplot().figure(figsize=(11, 4.2 * len(panels)), layout="constrained")
    axes = fig.subplots(len(panels), 2, squeeze=False)
    x_all = [1.0 - r["rho"] for r in data["rows"]]
    grid, slab = data["grid"], data["slab"]
    for (ax_t, ax_e), (name, keep, style_key, styles) in zip(axes, panels, strict=True):
        for ax in (ax_t, ax_e):
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlim(2.0 * max(x_all), 0.5 * min(x_all))  # ρ grows to the right
            ax.autoscale(enable=False, axis="x")
            ax.set_xlabel("1 − ρ  (ρ: per-bounce ratio bound ω·A(g) or ω)")
            ax.grid(True, which="both", alpha=0.3)
        for i, method in enumerate(_METHODS):
            for style, ls in styles.items():
                rows = [
                    r
                    for r in data["rows"]
                    if r["method"] == method
                    and keep(r)
                    and r.get(style_key, "plane") == style
                    and "seconds" in r
                ]
                if not rows:
                    continue
                x = [1.0 - r["rho"] for r in rows]
                kw = dict(color=f"C{i}", ls=ls, marker="o", label=f"{method} ({style})")
                ax_t.plot(x, [min(r["times_s"]) for r in rows], **kw)
                ax_e.plot(x, [max(r["error_total"], 1e-9) for r in rows], **kw)
        st = float(name.split()[-1])
        if name.startswith("slab"):
            size = (
                f"{slab['width']}×{slab['height']} px, h {slab['thickness']:g} px, "
                f"g {slab['g']}, n_theta {slab['n_theta']}, n_mu {slab['n_mu']}, "
                f"n_z {slab['n_z']}"
            )
        else:
            size = f"{grid['width'] * st:g} × {grid['height'] * st:g} mean free paths"
        ax_t.set_title(f"{name} ({size}): time", fontsize=9)
        ax_e.set_title(f"{name}: error (floored at 1e-9)", fontsize=9)
        ax_t.set_ylabel("seconds per render, fastest steady call")
        ax_e.set_ylabel("relative L1 error of Σ_k I_k vs reference")
        ax_e.axhline(data["target"], color="0.5", ls=":", lw=1, label="target = tail_tol")
        ax_e.legend(fontsize=7)
    plane = (
        f"Plane {grid['width']}×{grid['height']} px, n_theta {grid['n_theta']}, g {data['g']}; "
        if data["sigma_t"]
        else ""
    )
    fig.suptitle(
        f"Bounce series after K0 = {data['explicit_bounces']} explicit bounces: marched vs "
        f"solved. {plane}full illumination, float32; {os.cpu_count()} cores, load "
        f"{data['load_average_1min']:.1f}",
        fontsize=9,
    )
    return save_figure(fig, path)
