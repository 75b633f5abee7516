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

import time
from pathlib import Path

import numpy as np

import lightfield_jax as lfj
from lightfield_jax.app.experiment import check_config, load_helper

inv = load_helper("_inverse")

_KEYS = {
    "experiment",
    "dtype",
    "width",
    "height",
    "thickness",
    "n",
    "sigma_t",
    "media",
    "period",
    "lit",
    "bounces",
    "photons",
    "batches",
    "camera_sampling",
    "seed",
    "n_z",
    "fit",
    "model_error",
}
BOUNDS = {"sigma_t": 0.01, "sigma_s": 0.03, "g": 0.02}  # relative, relative, absolute


def _check(config: dict) -> None:
    check_config("slab_recovery", config, _KEYS)
    for m in config["media"]:
        if set(m) != {"albedo", "g"} or not (0 < m["albedo"] < 1 and -1 < m["g"] < 1):
            raise ValueError(
                f"slab_recovery: media: each must be {{albedo: (0, 1), g: (-1, 1)}}, got {m}"
            )
    if not (isinstance(config["batches"], int) and config["batches"] >= 2):
        raise ValueError(
            f"slab_recovery: batches: must be an integer >= 2, got {config['batches']}"
        )


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
    _check(config)
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
