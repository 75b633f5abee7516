"""Does the joint fit recover a milk-like medium from a capture of the true slab? (issue 18)

Per medium (σt, ω, g) in a refractive tank of depth h: six shifted period-``period``
stripe images rendered by the independent 3-D slab Monte Carlo
(`reference.montecarlo_slab.monte_carlo_slab`: true depth, not the layered model),
lit from the left wall by the same ``Stripes`` the fit assumes, then fitted with
``fit_images(..., FitOptions(geometry=Slab(h, "refractive", n=n, n_z=n_z)))``.

The capture is the mean of ``batches`` independent Monte Carlo runs (seeds ``seed``,
``seed`` + 1, ...); its per-pixel variance is their sample variance over ``batches``
(the oracle's own per-order standard errors leave out the correlation between orders).
The fit gets that noise as its weights through ``exposure`` = I/var (its weights are
1/√(I + floor) × √(T/max T): ∝ 1/σ_pixel where I is above the floor), so its χ²/dof is
against the capture's real noise.

Written per medium: ``capture_<name>.npz`` (images, variance, the scene) and the fit's
errors against the bounds of the issue (σt 1 %, σs 3 %, g 0.02) with its error budget.
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
    Count,
    Dtype,
    Pixels,
    Positive,
    Range,
    Seed,
    typed_config,
)

inv = load_helper("_inverse")

BOUNDS = {"sigma_t": 0.01, "sigma_s": 0.03, "g": 0.02}  # relative, relative, absolute


@dataclasses.dataclass(frozen=True)
class MediumSpec:
    albedo: Annotated[float, Range(0, 1, open_low=True, open_high=True)]
    g: Annotated[float, Range(-0.99, 0.99)]


@dataclasses.dataclass(frozen=True)
class Config:
    """configs/slab_recovery.yaml: the captures (pixels), the tank (depth h in pixels,
    refractive index), σt, the media (albedo, g), the stripes, the Monte Carlo oracle
    (orders, photons in total over ``batches`` runs from ``seed``, camera sampling) and
    the fit (depth layers, null: the fit's choice; its model-error term)."""

    dtype: Dtype
    width: Pixels
    height: Pixels
    thickness: Positive
    n: float
    sigma_t: Positive
    media: tuple[Annotated[dict, MediumSpec], ...]
    period: Annotated[int, Range(2, 1000)]
    lit: Count
    bounces: Annotated[int, Range(1, 10_000)]
    photons: Annotated[int, Range(1, 10**10)]
    batches: Annotated[int, Range(2, 10_000)]
    camera_sampling: Annotated[float, Range(0, 1)]
    seed: Seed
    n_z: int | None
    fit: bool
    model_error: bool

    def __post_init__(self):
        if not self.media:
            raise ValueError("slab_recovery: media: must list at least one medium")
        if not self.lit < self.period:
            raise ValueError(f"slab_recovery: lit: must be < period, got {self.lit}")
        if self.seed + self.batches > 2**32:
            raise ValueError(
                f"slab_recovery: seed: seed + batches must be < 2**32, got {self.seed}"
            )
        if self.photons < self.batches:
            raise ValueError(f"slab_recovery: photons: at least one per batch, got {self.photons}")
        try:  # the tank as the fit builds it: its thickness, n and n_z checked
            lfj.Slab(self.thickness, "refractive", n=self.n, n_z=self.n_z)
        except ValueError as e:
            raise ValueError(f"slab_recovery: {e}") from None


def name(medium: dict) -> str:
    return f"w{medium['albedo']:g}_g{medium['g']:g}"


def pattern(config: dict) -> lfj.Stripes:
    return lfj.Stripes.shifted(config["period"], config["lit"])


def render_capture(config: dict, medium: dict) -> dict:
    """The Monte Carlo capture of one medium: mean images (P, H, W), their variance, the
    largest untraced share of the input power, seconds."""
    from lightfield_jax.reference.montecarlo_slab import monte_carlo_slab

    st = config["sigma_t"]
    runs, untraced = [], 0.0
    t0 = time.perf_counter()
    for b in range(config["batches"]):
        mc = monte_carlo_slab(
            config["width"],
            config["height"],
            config["thickness"],
            st,
            medium["albedo"] * st,
            medium["g"],
            pattern(config),
            config["bounces"],
            boundary="refractive",
            n=config["n"],
            photons=config["photons"] // config["batches"],
            seed=config["seed"] + b,
            camera_sampling=config["camera_sampling"],
        )
        runs.append(mc.images.sum(axis=1))
        untraced = max(untraced, float(np.max(mc.untraced / mc.input_power)))
    runs = np.asarray(runs)
    return {
        "images": runs.mean(axis=0).tolist(),
        "variance": (runs.var(axis=0, ddof=1) / len(runs)).tolist(),
        "untraced": untraced,
        "seconds": time.perf_counter() - t0,
    }


def write_capture(path: Path, config: dict, medium: dict, capture: dict) -> None:
    scene = {k: config[k] for k in ("thickness", "n", "sigma_t", "period", "lit", "photons")}
    np.savez_compressed(
        path,
        images=np.asarray(capture["images"], np.float64),
        variance=np.asarray(capture["variance"], np.float64),
        albedo=medium["albedo"],
        g=medium["g"],
        **scene,
    )


def fit_capture(config: dict, images: np.ndarray, variance: np.ndarray, progress) -> lfj.FitResult:
    """The joint slab fit of a capture, weighted by its Monte Carlo noise."""
    slab = lfj.Slab(config["thickness"], "refractive", n=config["n"], n_z=config["n_z"])
    exposure = images / np.maximum(variance, np.finfo(np.float64).tiny)
    return lfj.fit_images(
        images,
        pattern(config),
        exposure=exposure,
        options=lfj.FitOptions(geometry=slab, model_error=config["model_error"]),
        progress=progress,
    )


def errors(fit, config: dict, medium: dict) -> dict:
    st = config["sigma_t"]
    return {
        "sigma_t": fit.sigma_t / st - 1,
        "sigma_s": fit.sigma_s / (medium["albedo"] * st) - 1,
        "g": fit.g - medium["g"],
    }


def _fit_row(config: dict, medium: dict, images, variance, ctx) -> dict:
    t0 = time.perf_counter()
    fit = fit_capture(config, images, variance, lambda s: ctx.progress(f"  {s}"))
    err = errors(fit, config, medium)
    return {
        "fit_seconds": time.perf_counter() - t0,
        "fit": fit.to_dict(),
        "errors": err,
        "within_bounds": all(abs(err[k]) <= BOUNDS[k] for k in BOUNDS),
    }


def run(config: dict, out: Path, ctx) -> dict:
    typed_config(Config, config)  # every key checked before any work
    rows = []
    with inv.precision(config["dtype"]):
        for medium in config["media"]:
            key = (
                f"capture|{config['width']}x{config['height']}|h{config['thickness']}|"
                f"n{config['n']}|st{config['sigma_t']}|{name(medium)}|P{config['period']}/"
                f"{config['lit']}|K{config['bounces']}|N{config['photons']}|"
                f"B{config['batches']}|eps{config['camera_sampling']}|seed{config['seed']}"
            )
            ctx.progress(f"{name(medium)}: Monte Carlo capture")
            capture = ctx.cached(key, lambda m=medium: render_capture(config, m))
            write_capture(out / f"capture_{name(medium)}.npz", config, medium, capture)
            images = np.asarray(capture["images"])
            variance = np.asarray(capture["variance"])
            bright = images > 0.05 * images.max()
            row = {
                "medium": medium,
                "capture_seconds": capture["seconds"],
                "untraced": capture["untraced"],
                "relative_noise_median": float(
                    np.median(np.sqrt(variance[bright]) / images[bright])
                ),
                "relative_noise_p90": float(
                    np.percentile(np.sqrt(variance[bright]) / images[bright], 90)
                ),
            }
            if config["fit"]:
                ctx.progress(f"{name(medium)}: joint slab fit")
                fit_key = (
                    f"fit|lib{inv.library_fingerprint()}|{config['dtype']}|nz{config['n_z']}|{key}"
                )
                row.update(
                    ctx.cached(
                        fit_key,
                        lambda m=medium, i=images, v=variance: _fit_row(config, m, i, v, ctx),
                    )
                )
            rows.append(row)
    ctx.write_json("slab_recovery.json", {"config": config, "bounds": BOUNDS, "rows": rows})
    return {"bounds": BOUNDS, "rows": rows}
