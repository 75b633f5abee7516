"""When does the paper's plane model do for a real tank? (issue 7)

A tank has a depth h; the paper's model keeps all light in one plane. Per scene (σt·h,
the thickness in mean free paths; albedo; g; the faces) this experiment renders a
noiseless 6-phase stripe capture with the slab model (docs/model.md section 7), fits the
plane model to it with the default ``joint`` method, and records

- the plane fit's relative misfit m = ‖fit − capture‖₂ / ‖capture‖₂ over the model's
  region: the plane model is indistinguishable from the slab where m is below the
  capture's relative noise ε (per-pixel noise std / signal), so ``geometry: auto``
  picks the plane there and the slab elsewhere (:func:`lightfield_jax.inverse.model_choice.choose`);
- the plane fit's parameter errors against the slab's true σt, σs, g: what a user
  who fits the plane model to a tank is told.

Figures: the misfit against σt·h per albedo and boundary with the noise levels as
horizontal lines (the crossover), and the parameter errors.
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
    check_choices,
    typed_config,
)
from lightfield_jax.app.experiment_records import pyplot, save_figure
from lightfield_jax.scene.geometry import BOUNDARIES

inv = load_helper("_inverse")


@dataclasses.dataclass(frozen=True)
class Config:
    """configs/plane_vs_slab.yaml: the slab scenes (σt per pixel; σt·h, albedo, g and the
    faces swept), the noise levels drawn, the joint fit's step limit."""

    dtype: Dtype
    width: Pixels
    height: Pixels
    sigma_t: Positive
    optical_thickness: tuple[Annotated[float, Range(0, 1000, open_low=True)], ...]
    albedo: tuple[Annotated[float, Range(0, 1, open_low=True, open_high=True)], ...]
    g: tuple[Annotated[float, Range(-0.99, 0.99)], ...]
    boundary: tuple[str, ...]
    noise_levels: tuple[Positive, ...]
    max_steps: Annotated[int, Range(1, 100_000)]

    def __post_init__(self):
        check_choices("plane_vs_slab", "boundary", self.boundary, BOUNDARIES)
        if not (self.optical_thickness and self.albedo and self.g and self.boundary):
            raise ValueError(
                "plane_vs_slab: optical_thickness, albedo, g, boundary: at least one each"
            )
        try:  # the tanks as the cells build them (depth h = σt·h / σt)
            for tau in self.optical_thickness:
                lfj.Slab(tau / self.sigma_t, "absorbing")
        except ValueError as e:
            raise ValueError(f"plane_vs_slab: {e}") from None


def _cell(config: Config, tau: float, albedo: float, g: float, boundary: str) -> dict:
    st = float(config.sigma_t)
    h = tau / st
    pattern = lfj.Stripes(6, 3, tuple(range(6)))
    medium = lfj.Medium(st, albedo * st, g)
    geometry = lfj.Slab(h, boundary)
    res = lfj.render(medium, lfj.Grid(config.width, config.height), pattern, geometry=geometry)
    captured = np.asarray(res.total, np.float64)
    t0 = time.perf_counter()
    fit = lfj.fit_images(
        captured.astype(np.float32),
        pattern,
        options=lfj.FitOptions(method="joint", max_steps=config.max_steps),
    )
    seconds = time.perf_counter() - t0
    model, _ = lfj.fitted_images(fit, pattern, captured.shape[-2:])
    model = model.sum(axis=1)
    x0, y0, x1, y1 = fit.model["crop"]
    obs = captured[..., y0:y1, x0:x1]
    mis = model[..., y0:y1, x0:x1] - obs
    misfit = float(np.sqrt(np.sum(mis**2) / np.sum(obs**2)))
    single = float(np.asarray(res.images[:, 0]).sum() / captured.sum())
    return {
        "tau": tau,
        "thickness": h,
        "albedo": albedo,
        "g": g,
        "boundary": boundary,
        "bounces": res.bounces,
        "single_fraction": single,
        "plane": {
            "sigma_t": fit.sigma_t,
            "sigma_s": fit.sigma_s,
            "g": fit.g,
            "converged": bool(fit.converged),
            "seconds": seconds,
        },
        "errors": {
            "sigma_t": fit.sigma_t / st - 1,
            "sigma_s": fit.sigma_s / (albedo * st) - 1,
            "g": fit.g - g,
        },
        "misfit": misfit,
    }


def run(raw: dict, out: Path, ctx) -> dict:
    config = typed_config(Config, raw)

    def key(boundary, g, albedo, tau):
        return (
            f"lib{inv.library_fingerprint()}|{config.dtype}|"
            f"{config.width}x{config.height}|st{config.sigma_t}|"
            f"tau{tau}|w{albedo}|g{g}|{boundary}|steps{config.max_steps}"
        )

    with inv.precision(config.dtype):
        rows = ctx.sweep(
            [
                ("boundary", config.boundary),
                ("g", config.g),
                ("albedo", config.albedo),
                ("tau", config.optical_thickness),
            ],
            key,
            lambda boundary, g, albedo, tau: _cell(config, tau, albedo, g, boundary),
        )
    ctx.write_json("plane_vs_slab.json", {"config": raw, "rows": rows})
    figures = [_plot_misfit(config, rows, out), _plot_errors(config, rows, out)]
    crossover = _crossover(config, rows)
    return {
        "rows": len(rows),
        "figures": figures,
        "crossover": crossover,
        "worst_plane_errors": {
            k: max(abs(r["errors"][k]) for r in rows) for k in ("sigma_t", "sigma_s", "g")
        },
    }


def _series(rows: list[dict], boundary: str, g: float, albedo: float) -> list[dict]:
    """The rows of one (boundary, g, albedo), by increasing σt·h."""
    sel = [r for r in rows if (r["boundary"], r["g"], r["albedo"]) == (boundary, g, albedo)]
    return sorted(sel, key=lambda r: r["tau"])


def _crossover(config: Config, rows: list[dict]) -> dict:
    """Per boundary, albedo, g and noise level: the largest σt·h at which the plane's
    misfit is still below the noise (None: nowhere on the sweep)."""
    out: dict = {}
    for boundary in config.boundary:
        for g in config.g:
            for albedo in config.albedo:
                sel = _series(rows, boundary, g, albedo)
                for eps in config.noise_levels:
                    ok = [r["tau"] for r in sel if r["misfit"] < eps]
                    out[f"{boundary}|g{g}|albedo{albedo}|noise{eps}"] = {
                        "plane_ok_at_tau": ok,
                    }
    return out


def _plot_misfit(config: Config, rows: list[dict], out: Path) -> str:
    plt = pyplot()
    bounds, gs = config.boundary, config.g
    fig, axes = plt.subplots(
        len(gs), len(bounds), figsize=(5.2 * len(bounds), 3.9 * len(gs)), squeeze=False
    )
    colors = plt.cm.viridis(np.linspace(0.0, 0.85, len(config.albedo)))
    for i, g in enumerate(gs):
        for j, boundary in enumerate(bounds):
            ax = axes[i, j]
            for albedo, color in zip(config.albedo, colors, strict=True):
                sel = _series(rows, boundary, g, albedo)
                ax.plot(
                    [r["tau"] for r in sel],
                    [max(r["misfit"], 1e-6) for r in sel],
                    "o-",
                    color=color,
                    label=f"albedo {albedo:g}",
                )
            inv.log_axes(ax)
            for eps in config.noise_levels:
                ax.axhline(eps, color="0.5", ls=":", lw=1)
                ax.text(
                    0.99,
                    eps,
                    f"noise {eps:g}",
                    transform=ax.get_yaxis_transform(),
                    ha="right",
                    va="bottom",
                    fontsize=7,
                    color="0.35",
                )
            ax.grid(True, which="both", alpha=0.3)
            ax.set_xlabel("slab thickness in mean free paths, σt·h")
            ax.set_ylabel("plane fit's misfit ‖fit − capture‖ / ‖capture‖")
            ax.set_title(f"{boundary} faces, g {g:g}", fontsize=10)
            ax.legend(fontsize=8)
    fig.suptitle(
        f"Plane model fitted (joint) to noiseless slab captures: σt {config.sigma_t} px⁻¹, "
        f"{config.width}×{config.height}, 6-phase stripes (period 6).\n"
        "geometry: auto keeps the plane model only below the capture's noise (dotted)",
        fontsize=10,
    )
    fig.tight_layout()
    path = out / "plane_misfit.png"
    return save_figure(fig, path).name


def _plot_errors(config: Config, rows: list[dict], out: Path) -> str:
    plt = pyplot()
    params = (
        ("sigma_t", "σt error (relative)"),
        ("sigma_s", "σs error (relative)"),
        ("g", "g error (absolute)"),
    )
    fig, axes = plt.subplots(1, 3, figsize=(14, 3.9))
    colors = plt.cm.viridis(np.linspace(0.0, 0.85, len(config.albedo)))
    styles = dict(zip(config.boundary, ("-", "--"), strict=False))
    markers = dict(zip(config.g, ("o", "s", "^", "v"), strict=False))
    for ax, (key, label) in zip(axes, params, strict=True):
        for boundary in config.boundary:
            for g in config.g:
                for albedo, color in zip(config.albedo, colors, strict=True):
                    sel = _series(rows, boundary, g, albedo)
                    ax.plot(
                        [r["tau"] for r in sel],
                        [r["errors"][key] for r in sel],
                        ls=styles[boundary],
                        marker=markers[g],
                        color=color,
                        ms=4,
                        label=f"{boundary[:4]}., g {g:g}, ω {albedo:g}",
                    )
        ax.axhline(0.0, color="k", lw=0.8)
        inv.log_axes(ax, y=False)
        ax.grid(True, which="both", alpha=0.3)
        ax.set_xlabel("σt·h (thickness in mean free paths)")
        ax.set_ylabel(label)
    axes[0].legend(fontsize=6, ncol=2)
    fig.suptitle(
        "What the plane model reports for a tank: its joint fit to noiseless slab captures "
        f"(σt {config.sigma_t} px⁻¹) against the slab's true coefficients",
        fontsize=10,
    )
    fig.tight_layout()
    path = out / "plane_errors.png"
    return save_figure(fig, path).name
