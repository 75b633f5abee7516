"""Is the layered slab model right bounce by bounce? (issue 18)

Per scene (σt·h, g, the faces) the slab model with its resolved depth layers, and the
depth average (n_z = 1) with the same angular discretisation, against the independent
3-D Monte Carlo of the true slab (`reference.montecarlo_slab.monte_carlo_slab`,
no depth layers), full illumination from the left wall:

- per-order errors of the image sums Σ_xy I_k, k = 1..``orders`` (they do not depend on
  the albedo: I_k(σs) = σs^k I_k(1) exactly in both, path for path in the oracle), with
  the oracle's standard error;
- per albedo ω: the error of the sums of the first j orders (j ≤ ``orders``) and of all
  ``bounces`` orders; the oracle runs once at the largest ω, the others are its exact
  σs^k rescaling (both sides);
- the model's render time (warm) and compile time, layered and depth-averaged.

Figures: the largest per-order error up to ``orders`` per scene (layered against the
depth average, with the oracle's 2σ), and the all-orders error per albedo.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Annotated

import numpy as np

import lightfield_jax as lfj
from lightfield_jax.app.experiment import load_helper
from lightfield_jax.app.experiment_config import (
    Dtype,
    Pixels,
    Positive,
    Range,
    Seed,
    check_choices,
    typed_config,
)
from lightfield_jax.app.experiment_records import pyplot, save_figure
from lightfield_jax.forward.slab import SlabRenderer
from lightfield_jax.reference.montecarlo_slab import monte_carlo_slab
from lightfield_jax.scene.geometry import BOUNDARIES, resolve_slab_grid

inv = load_helper("_inverse")


@dataclasses.dataclass(frozen=True)
class Config:
    """configs/slab_depth_accuracy.yaml: the scenes (h in pixels; σt·h, g and the faces
    swept; the albedos rescaled), the orders compared one by one, the bounces summed,
    and the Monte Carlo oracle's photons, camera sampling and seed."""

    dtype: Dtype
    width: Pixels
    height: Pixels
    thickness: Positive
    optical_thickness: tuple[Annotated[float, Range(0, 1000, open_low=True)], ...]
    g: tuple[Annotated[float, Range(-0.99, 0.99)], ...]
    albedo: tuple[float, ...]
    boundary: tuple[str, ...]
    n: float
    orders: int
    bounces: Annotated[int, Range(1, 10_000)]
    photons: Annotated[int, Range(1, 10**10)]
    camera_sampling: Annotated[float, Range(0, 1)]
    seed: Seed

    def __post_init__(self):
        name = "slab_depth_accuracy"
        check_choices(name, "boundary", self.boundary, BOUNDARIES)
        if not all(0 < a < 1 for a in self.albedo):
            raise ValueError(f"{name}: albedo: each must be in (0, 1), got {list(self.albedo)}")
        if not 1 <= self.orders <= self.bounces:
            raise ValueError(
                f"{name}: orders: must be in [1, bounces={self.bounces}], got {self.orders}"
            )
        if not (self.optical_thickness and self.g and self.albedo and self.boundary):
            raise ValueError(f"{name}: optical_thickness, g, albedo, boundary: at least one each")
        try:  # the tank as the scenes build it
            lfj.Slab(self.thickness, "refractive", n=self.n)
        except ValueError as e:
            raise ValueError(f"{name}: {e}") from None


def _timed_render(grid, slab, bounces, values) -> tuple[np.ndarray, float, float]:
    """Image sums per order, compile+first-call seconds and warm seconds."""
    r = SlabRenderer(grid, lfj.Full(0.0, "left"), bounces, slab)
    t0 = time.perf_counter()
    images = r(*values)[0]
    images.block_until_ready()
    cold = time.perf_counter() - t0
    t0 = time.perf_counter()
    r(*values)[0].block_until_ready()
    warm = time.perf_counter() - t0
    return np.asarray(images, np.float64)[0].sum((1, 2)), cold - warm, warm


def _cell(config: Config, tau: float, g: float, boundary: str) -> dict:
    h, k = float(config.thickness), int(config.bounces)
    st = tau / h
    top = max(config.albedo)
    width, height = config.width, config.height
    t0 = time.perf_counter()
    mc = monte_carlo_slab(
        width,
        height,
        h,
        st,
        top * st,
        g,
        lfj.Full(0.0, "left"),
        k,
        boundary=boundary,
        n=config.n,
        photons=config.photons,
        seed=config.seed,
        camera_sampling=config.camera_sampling,
    )
    mc_seconds = time.perf_counter() - t0
    ref = mc.images[0].sum((1, 2))
    grid, slab = resolve_slab_grid(
        lfj.Grid(width, height), lfj.Slab(h, boundary, n=config.n), g, st, top
    )
    values = (st, top * st, g)
    layered, compile_s, warm_s = _timed_render(grid, slab, k, values)
    average, compile1_s, warm1_s = _timed_render(grid, dataclasses.replace(slab, n_z=1), k, values)
    return {
        "tau": tau,
        "g": g,
        "boundary": boundary,
        "sigma_t": st,
        "n_theta": grid.n_theta,
        "n_mu": slab.n_mu,
        "n_z": slab.n_z,
        "depth_profile": slab.profile,
        "mc": {"sums": ref.tolist(), "stderr": mc.total_stderr[0].tolist(), "seconds": mc_seconds},
        "layered": {"sums": layered.tolist(), "compile_s": compile_s, "render_s": warm_s},
        "average": {"sums": average.tolist(), "compile_s": compile1_s, "render_s": warm1_s},
    }


def _errors(row: dict, model: str, albedo: float, top: float, orders: int) -> dict:
    """Relative errors against the oracle at albedo ω (σs^k rescaling of both)."""
    ref = np.asarray(row["mc"]["sums"])
    se = np.asarray(row["mc"]["stderr"])
    got = np.asarray(row[model]["sums"])
    scale = (albedo / top) ** np.arange(1, ref.size + 1)
    ref, se, got = ref * scale, se * scale, got * scale
    cum_ref, cum_got = np.cumsum(ref), np.cumsum(got)
    return {
        "per_order": (got[:orders] / ref[:orders] - 1).tolist(),
        "per_order_noise": (se[:orders] / ref[:orders]).tolist(),
        "cumulative": (cum_got[:orders] / cum_ref[:orders] - 1).tolist(),
        "all_orders": float(cum_got[-1] / cum_ref[-1] - 1),
        "all_orders_noise": float(np.sum(se) / cum_ref[-1]),  # orders correlate: a bound
        "tail_fraction": float(ref[-1] / cum_ref[-1]),
    }


def run(raw: dict, out: Path, ctx) -> dict:
    config = typed_config(Config, raw)

    def key(boundary, tau, g):
        return (
            f"lib{inv.library_fingerprint()}|{config.dtype}|"
            f"{config.width}x{config.height}|h{config.thickness}|"
            f"n{config.n}|tau{tau}|g{g}|{boundary}|w{max(config.albedo)}|"
            f"K{config.bounces}|N{config.photons}|"
            f"eps{config.camera_sampling}|seed{config.seed}"
        )

    with inv.precision(config.dtype):
        rows = ctx.sweep(
            [("boundary", config.boundary), ("tau", config.optical_thickness), ("g", config.g)],
            key,
            lambda boundary, tau, g: _cell(config, tau, g, boundary),
        )
    top, orders = max(config.albedo), config.orders
    table = []
    for row in rows:
        for albedo in config.albedo:
            keys = ("tau", "g", "boundary", "n_theta", "n_mu", "n_z", "depth_profile")
            entry = {k: row.get(k) for k in keys}
            entry["albedo"] = albedo
            for model in ("layered", "average"):
                entry[model] = _errors(row, model, albedo, top, orders)
            table.append(entry)
    ctx.write_json("slab_depth_accuracy.json", {"config": raw, "rows": rows, "table": table})
    figure = _plot(config, table, out)

    def worst(model, part):
        return max(max(abs(e) for e in np.atleast_1d(t[model][part])) for t in table)

    return {
        "scenes": len(rows),
        "figure": figure,
        "worst_per_order": {m: worst(m, "per_order") for m in ("layered", "average")},
        "worst_cumulative": {m: worst(m, "cumulative") for m in ("layered", "average")},
        "worst_all_orders": {m: worst(m, "all_orders") for m in ("layered", "average")},
        "worst_oracle_noise_per_order": worst("layered", "per_order_noise"),
        "largest_tail_fraction": max(t["layered"]["tail_fraction"] for t in table),
        "render_s": {m: sum(r[m]["render_s"] for r in rows) for m in ("layered", "average")},
        "compile_s": {m: sum(r[m]["compile_s"] for r in rows) for m in ("layered", "average")},
    }


def _plot(config: Config, table: list[dict], out: Path) -> str:
    plt = pyplot()
    top = max(config.albedo)
    scenes = [t for t in table if t["albedo"] == top]
    labels = [f"{t['boundary'][:4]}. τ{t['tau']:g} g{t['g']:g} (n_z {t['n_z']})" for t in scenes]
    x = np.arange(len(scenes))
    fig, axes = plt.subplots(1, 2, figsize=(max(9.0, 0.45 * len(scenes) + 6), 4.6))
    ax = axes[0]
    for model, color, dx in (("average", "tab:red", -0.15), ("layered", "tab:blue", 0.15)):
        worst = [max(abs(e) for e in t[model]["per_order"]) * 100 for t in scenes]
        ax.plot(x + dx, worst, "o", color=color, label=f"{model} (max over k ≤ {config.orders})")
    noise = [2 * max(t["layered"]["per_order_noise"]) * 100 for t in scenes]
    ax.bar(x, noise, width=0.6, color="0.85", label="oracle's 2σ (largest k)")
    ax.axhline(2.0, color="k", ls=":", lw=1)
    ax.set_ylabel("|error| of Σ I_k against the 3-D Monte Carlo (%)")
    ax.set_xticks(x, labels, rotation=75, fontsize=7)
    ax.legend(fontsize=7)
    ax.set_title("per bounce", fontsize=10)
    ax = axes[1]
    for i, albedo in enumerate(config.albedo):
        rows = [t for t in table if t["albedo"] == albedo]
        ax.plot(
            x + 0.1 * (i - 1),
            [abs(t["layered"]["all_orders"]) * 100 for t in rows],
            "s",
            label=f"layered, ω {albedo:g}",
        )
        ax.plot(
            x + 0.1 * (i - 1),
            [abs(t["average"]["all_orders"]) * 100 for t in rows],
            "x",
            color="0.4",
            label="average" if i == 0 else None,
        )
    ax.axhline(1.0, color="k", ls=":", lw=1)
    ax.set_ylabel(f"|error| of Σ_k≤{config.bounces} I_k (%)")
    ax.set_xticks(x, labels, rotation=75, fontsize=7)
    ax.legend(fontsize=7)
    ax.set_title("all orders", fontsize=10)
    fig.suptitle(
        f"Slab model (resolved depth layers) vs the 3-D slab Monte Carlo: h "
        f"{config.thickness} px, {config.width}×{config.height}, full illumination, "
        f"{config.photons:.0e} photons",
        fontsize=10,
    )
    fig.tight_layout()
    path = out / "slab_depth_accuracy.png"
    return save_figure(fig, path).name
