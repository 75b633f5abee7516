"""How accurate is the forward model, and what does accuracy cost?

Per-bounce images I_k (k = 1..``bounces``) of :func:`lightfield_jax.render` against the
independent Monte Carlo oracle (:func:`lightfield_jax._montecarlo.monte_carlo_render`),
over the number of direction bins ``n_theta`` and the spatial refinement ``refine``,
for several beam scenes; and the steady-state wall time of the render that produces
them (compile reported apart).

Error metric: 4×4-binned relative L1, Σ_b |R_b − M_b| / Σ_b |M_b| over 4×4 pixel
blocks b (block sums), R the render, M the Monte Carlo.

The Monte Carlo's own noise. The photons run as two independent halves A and B (seeds
``seed`` and ``seed + 1``); M = (A + B)/2. Per bin, (A − B)/2 has the variance of M's
noise, so noise = ½ Σ_b |A_b − B_b| / Σ_b |M_b| is the relative L1 that M's noise alone
adds (in expectation) to the error of a perfect render. Correlations between pixels
(one photon crosses many) are included, which per-pixel standard errors would miss.
Errors within a few times the noise are noise-limited: they bound the model's error
from above, no more.

Convergence (order p: error ∝ n^−p). (1) Against the Monte Carlo: least-squares
−d log error / d log n_theta (per refine) and −d log error / d log refine (per n_theta);
a flat curve (p ≈ 0) says another error dominates (space, or the Monte Carlo noise). (2) Self-convergence (no
Monte Carlo noise): Cauchy differences d(n) = ‖R_n − R_2n‖₁/‖R_2n‖₁ (binned) give the
order log2(d(n)/d(2n)) in θ at fixed refine; refinements 1, 2, 4 at the scene's default
n_theta give it in space.

Bounce count: the total image Σ_{k≤K} I_k against the Monte Carlo's Σ over
max(bounces, K_auto) bounces, for K = 1, 2, ...; ``auto`` (tail bound ρ^K/(1−ρ) ≤
tolerance) is marked. Under ``phase: paper`` a medium with ρ = ω·A(g) ≥ 1 has no
convergent total: only its first ``bounces`` bounces are compared, as a truncation.

Timing: each (scene, n_theta, refine, K) render is timed through the public
``lightfield_jax.render`` (first call: table setup + compile + run; then the median of
``repeats`` steady calls). A jitted complex FFT of a light field's size is timed at the
start and the end as a yardstick of the machine's speed at the time (other jobs on the
machine slow both alike). Every Monte Carlo run and every timing is cached (resume).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import time
import warnings
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import lightfield_jax as lfj
from lightfield_jax._io import atomic_path
from lightfield_jax._montecarlo import monte_carlo_render
from lightfield_jax._timing import stopwatch

_SCENE_KEYS = {"name", "sigma_t", "sigma_s", "g", "beam", "phase", "label"}
_BEAM_KEYS = {"x", "y", "direction_deg", "width"}
_KEYS = {
    "experiment",
    "width",
    "height",
    "photons",
    "seed",
    "n_theta",
    "refine",
    "bounces",
    "convergence_refine",
    "repeats",
    "tolerance",
    "bin",
    "scenes",
}
# An error below this multiple of the Monte Carlo noise is reported as noise-limited.
_NOISE_LIMITED = 3.0


class Scene(NamedTuple):
    # (A NamedTuple, not a dataclass: the experiment runner loads this script without
    # registering it in sys.modules, which dataclasses with string annotations need.)
    name: str
    label: str
    medium: lfj.Medium
    beam: lfj.Beam
    params: dict

    @property
    def rho(self) -> float:
        return float(self.medium.rho)

    @property
    def converges(self) -> bool:
        return self.rho < 1.0


def _scene(spec: dict) -> Scene:
    unknown = sorted(set(spec) - _SCENE_KEYS)
    if unknown:
        raise ValueError(f"forward_accuracy: scenes: unknown keys {unknown}")
    beam_spec = dict(spec.get("beam") or {})
    bad = sorted(set(beam_spec) - _BEAM_KEYS)
    if bad:
        raise ValueError(f"forward_accuracy: scenes[{spec.get('name')}].beam: unknown keys {bad}")
    beam_spec.setdefault("x", 0.0)
    medium = lfj.Medium(spec["sigma_t"], spec["sigma_s"], spec["g"], spec.get("phase", "paper"))
    beam = lfj.Beam(**beam_spec)
    params = {k: spec[k] for k in ("sigma_t", "sigma_s", "g")}
    params.update(phase=medium.phase, beam=dataclasses.asdict(beam))
    return Scene(spec["name"], spec.get("label", spec["name"]), medium, beam, params)


def _check_config(config: dict) -> dict:
    unknown = sorted(set(config) - _KEYS)
    if unknown:
        raise ValueError(f"forward_accuracy: unknown config keys {unknown}")
    missing = sorted(_KEYS - {"bin"} - set(config))
    if missing:
        raise ValueError(f"forward_accuracy: missing config keys {missing}")
    cfg = dict(config)
    cfg.setdefault("bin", 4)
    b = cfg["bin"]
    if cfg["width"] % b or cfg["height"] % b:
        raise ValueError(f"forward_accuracy: width and height must be multiples of bin = {b}")
    return cfg


# ----------------------------------------------------------------------------- metrics


def _binned(images: np.ndarray, b: int) -> np.ndarray:
    """Block sums over b×b pixels of (..., H, W)."""
    *lead, h, w = images.shape
    return images.reshape(*lead, h // b, b, w // b, b).sum(axis=(-3, -1))


def _rel_l1(a: np.ndarray, ref: np.ndarray) -> float:
    return float(np.abs(a - ref).sum() / np.abs(ref).sum())


# ------------------------------------------------------------------------- measurements


def _monte_carlo(ctx, scene: Scene, cfg: dict, k_mc: int) -> dict:
    """Two independent halves, each cached; binned images (float64 lists)."""
    halves = []
    n = cfg["photons"] // 2
    for i in range(2):
        seed = cfg["seed"] + i
        key = (
            f"mc|{json.dumps(scene.params, sort_keys=True)}|{cfg['width']}x{cfg['height']}"
            f"|K{k_mc}|N{n}|seed{seed}|bin{cfg['bin']}"
        )

        def compute(seed=seed):
            ctx.progress(f"Monte Carlo {scene.name} half {seed - cfg['seed'] + 1}/2")
            t0 = time.perf_counter()
            res = monte_carlo_render(
                cfg["width"],
                cfg["height"],
                float(scene.medium.sigma_t),
                float(scene.medium.sigma_s),
                float(scene.medium.g),
                scene.beam,
                k_mc,
                phase=scene.medium.phase,
                photons=n,
                seed=seed,
            )
            return {
                "binned": _binned(res.images[0], cfg["bin"]).tolist(),
                "seconds": time.perf_counter() - t0,
                "photons": n,
            }

        halves.append(ctx.cached(key, compute))
    a, b = (np.asarray(h["binned"]) for h in halves)
    return {
        "mean": 0.5 * (a + b),
        "half_difference": 0.5 * (a - b),
        "seconds": sum(h["seconds"] for h in halves),
    }


def _render_images(ctx, scene: Scene, cfg: dict, n_theta: int, refine: int, k: int) -> np.ndarray:
    """Binned I_1..I_k of one render (cached)."""
    key = (
        f"images|{json.dumps(scene.params, sort_keys=True)}|{cfg['width']}x{cfg['height']}"
        f"|nt{n_theta}|r{refine}|K{k}|bin{cfg['bin']}|{jnp.result_type(float)}"
    )

    def compute():
        ctx.progress(f"render {scene.name} n_theta {n_theta} refine {refine}")
        grid = lfj.Grid(cfg["width"], cfg["height"], n_theta, refine)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", lfj.DivergentSeriesWarning)
            images = np.asarray(lfj.render(scene.medium, grid, scene.beam, k).images, np.float64)
        return _binned(images, cfg["bin"]).tolist()

    return np.asarray(ctx.cached(key, compute))


def _time_render(ctx, scene: Scene, cfg: dict, n_theta: int, refine: int, k: int) -> dict:
    """First call (setup + compile + run) and steady-state median of one render (cached)."""
    key = (
        f"time|{json.dumps(scene.params, sort_keys=True)}|{cfg['width']}x{cfg['height']}"
        f"|nt{n_theta}|r{refine}|K{k}|rep{cfg['repeats']}|{jnp.result_type(float)}"
    )

    def compute():
        ctx.progress(f"time {scene.name} n_theta {n_theta} refine {refine} K {k}")
        grid = lfj.Grid(cfg["width"], cfg["height"], n_theta, refine)

        def call():
            return lfj.render(scene.medium, grid, scene.beam, k).images.block_until_ready()

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", lfj.DivergentSeriesWarning)
            with stopwatch() as first:
                call()
            times = []
            for _ in range(cfg["repeats"]):
                t0 = time.perf_counter()
                call()
                times.append(time.perf_counter() - t0)
        return {
            "first_call_s": first.total,
            "compile_s": first.compile,
            "median_s": float(np.median(times)),
            "min_s": float(np.min(times)),
            "times_s": times,
            "load_average_1min": os.getloadavg()[0],
        }

    return ctx.cached(key, compute)


def _yardstick(n_theta: int, height: int, width: int, repeats: int = 20) -> float:
    """Median seconds of one jitted complex64 fft2 over (n_theta, height, width)."""
    fft = jax.jit(jnp.fft.fft2)
    field = jnp.ones((n_theta, height, width), jnp.complex64)
    fft(field).block_until_ready()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fft(field).block_until_ready()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


# --------------------------------------------------------------------------- analysis


def _order(x, y) -> float | None:
    """−d log y / d log x, least squares over the points (None for fewer than 2)."""
    x, y = np.log(np.asarray(x, float)), np.log(np.asarray(y, float))
    if len(x) < 2:
        return None
    return -float(np.polyfit(x, y, 1)[0])


def _convergence(scene: Scene, rows: list[dict], self_theta: dict, self_space: dict, cfg):
    """Orders in θ and in space, against the Monte Carlo and self-convergence."""
    out = {"theta_vs_mc": [], "space_vs_mc": [], "theta_self": [], "space_self": []}
    for k in range(1, cfg["bounces"] + 1):
        for refine in cfg["refine"]:
            sel = sorted(
                (r for r in rows if r["k"] == k and r["refine"] == refine),
                key=lambda r: r["n_theta"],
            )
            above = [r for r in sel if r["error"] > _NOISE_LIMITED * r["mc_noise"]]
            out["theta_vs_mc"].append(
                {
                    "k": k,
                    "refine": refine,
                    "n_theta": [r["n_theta"] for r in sel],
                    "error": [r["error"] for r in sel],
                    "order_all": _order([r["n_theta"] for r in sel], [r["error"] for r in sel]),
                    "order_above_noise": _order(
                        [r["n_theta"] for r in above], [r["error"] for r in above]
                    ),
                    "points_above_noise": len(above),
                }
            )
        for n_theta in sorted({r["n_theta"] for r in rows}):
            sel = sorted(
                (r for r in rows if r["k"] == k and r["n_theta"] == n_theta),
                key=lambda r: r["refine"],
            )
            if len(sel) >= 2:
                out["space_vs_mc"].append(
                    {
                        "k": k,
                        "n_theta": n_theta,
                        "refine": [r["refine"] for r in sel],
                        "error": [r["error"] for r in sel],
                        "order": _order([r["refine"] for r in sel], [r["error"] for r in sel]),
                        "noise_limited": [r["noise_limited"] for r in sel],
                    }
                )
        for refine, diffs in self_theta.items():
            d = diffs[k - 1]
            out["theta_self"].append(
                {
                    "k": k,
                    "refine": refine,
                    "n_theta": [p[0] for p in d],
                    "difference_to_2n": [p[1] for p in d],
                    "orders": [
                        math.log2(a[1] / b[1]) if a[1] > 0 and b[1] > 0 else None
                        for a, b in zip(d, d[1:], strict=False)
                    ],
                }
            )
        d = self_space["differences"][k - 1]
        out["space_self"].append(
            {
                "k": k,
                "n_theta": self_space["n_theta"],
                "refine": [p[0] for p in d],
                "difference_to_next": [p[1] for p in d],
                "orders": [
                    math.log(a[1] / b[1]) / math.log(b[0] / a[0]) if a[1] > 0 and b[1] > 0 else None
                    for a, b in zip(d, d[1:], strict=False)
                ],
            }
        )
    return out


def _cauchy(images: dict, keys: list, k_max: int) -> list[list[tuple]]:
    """Per bounce: (key_i, ‖R_i − R_{i+1}‖₁/‖R_{i+1}‖₁) over successive keys."""
    return [
        [
            (a, _rel_l1(images[a][k], images[b][k]))
            for a, b in zip(keys, keys[1:], strict=False)
        ]
        for k in range(k_max)
    ]


# ------------------------------------------------------------------------------ run


def run(config: dict, out: Path, ctx) -> dict:
    cfg = _check_config(config)
    scenes = [_scene(s) for s in cfg["scenes"]]
    w, h, kb = cfg["width"], cfg["height"], cfg["bounces"]
    yard_start = _yardstick(64, h, w)
    error_rows, time_rows, total_rows, convergence, scene_info = [], [], [], {}, {}

    for scene in scenes:
        default = lfj.Grid(w, h).resolve(float(scene.medium.g))
        k_auto = (
            lfj.bounces_for_tolerance(scene.rho, cfg["tolerance"]) if scene.converges else None
        )
        k_mc = max(kb, k_auto or 0)
        n_thetas = sorted(set(cfg["n_theta"]) | {default.n_theta})
        refines = sorted(set(cfg["refine"]) | {default.refine})
        mc = _monte_carlo(ctx, scene, cfg, k_mc)
        m, half = mc["mean"], mc["half_difference"]
        noise = [float(np.abs(half[k]).sum() / np.abs(m[k]).sum()) for k in range(k_mc)]
        mc_total = m.sum(axis=0)
        scene_info[scene.name] = {
            "label": scene.label,
            "params": scene.params,
            "rho": scene.rho,
            "converges": scene.converges,
            "auto_bounces": k_auto,
            "default_n_theta": default.n_theta,
            "default_refine": default.refine,
            "mc_bounces": k_mc,
            "mc_photons": 2 * (cfg["photons"] // 2),
            "mc_seconds": mc["seconds"],
            "mc_noise": noise[:kb],
        }
        images = {}
        timed_k = sorted({*range(1, kb + 1)} | ({k_auto} if k_auto else set()))
        for refine in refines:
            for n_theta in n_thetas:
                r = _render_images(ctx, scene, cfg, n_theta, refine, k_mc)
                images[(n_theta, refine)] = r
                is_default = (n_theta, refine) == (default.n_theta, default.refine)
                timings = {k: _time_render(ctx, scene, cfg, n_theta, refine, k) for k in timed_k}
                for k in timed_k:
                    t = timings[k]
                    time_rows.append(
                        {
                            "scene": scene.name,
                            "n_theta": n_theta,
                            "refine": refine,
                            "bounces": k,
                            "is_auto": k == k_auto,
                            "is_default": is_default,
                            **{x: t[x] for x in ("median_s", "min_s", "compile_s")},
                            "first_call_s": t["first_call_s"],
                            "load_average_1min": t["load_average_1min"],
                        }
                    )
                for k in range(1, kb + 1):
                    err = _rel_l1(r[k - 1], m[k - 1])
                    error_rows.append(
                        {
                            "scene": scene.name,
                            "k": k,
                            "n_theta": n_theta,
                            "refine": refine,
                            "is_default": is_default,
                            "error": err,
                            "mc_noise": noise[k - 1],
                            "noise_limited": err <= _NOISE_LIMITED * noise[k - 1],
                            "render_median_s": timings[k]["median_s"],
                            "render_compile_s": timings[k]["compile_s"],
                        }
                    )
                if scene.converges:
                    for k in range(1, k_mc + 1):
                        total_rows.append(
                            {
                                "scene": scene.name,
                                "n_theta": n_theta,
                                "refine": refine,
                                "is_default": is_default,
                                "bounces": k,
                                "is_auto": k == k_auto,
                                "error_total": _rel_l1(r[:k].sum(axis=0), mc_total),
                                "render_median_s": timings[k]["median_s"] if k in timings else None,
                            }
                        )
        # Self-convergence in θ (every refine) and in space (default n_theta).
        self_theta = {
            refine: _cauchy(images, [(n, refine) for n in n_thetas], kb) for refine in refines
        }
        space_keys = []
        for refine in sorted(set(cfg["convergence_refine"]) | {default.refine}):
            key = (default.n_theta, refine)
            if key not in images:
                images[key] = _render_images(ctx, scene, cfg, default.n_theta, refine, k_mc)
            space_keys.append(key)
        space = _cauchy(images, space_keys, kb)
        self_theta = {
            refine: [[(key[0], d) for key, d in per_k] for per_k in diffs]
            for refine, diffs in self_theta.items()
        }
        self_space = {
            "n_theta": default.n_theta,
            "differences": [[(key[1], d) for key, d in per_k] for per_k in space],
        }
        rows = [r for r in error_rows if r["scene"] == scene.name]
        convergence[scene.name] = _convergence(scene, rows, self_theta, self_space, cfg)

    yard_end = _yardstick(64, h, w)
    _write_csv(out / "errors.csv", error_rows)
    _write_csv(out / "timings.csv", time_rows)
    _write_csv(out / "total_vs_bounces.csv", total_rows)
    data = {
        "grid": {"width": w, "height": h, "bin": cfg["bin"]},
        "scenes": scene_info,
        "errors": error_rows,
        "timings": time_rows,
        "total_vs_bounces": total_rows,
        "convergence": convergence,
        "yardstick_fft_s": {"start": yard_start, "end": yard_end, "shape": [64, h, w]},
        "dtype": str(jnp.result_type(float)),
    }
    ctx.write_json("forward_accuracy.json", data)

    figures = []
    for scene in scenes:
        figures.append(_plot_error_vs_time(out, scene, data))
    figures.append(_plot_convergence(out, scenes, data))
    if total_rows:
        figures.append(_plot_total_vs_bounces(out, scenes, data))
    return _summary(data, figures)


def _write_csv(path: Path, rows: list[dict]) -> None:
    if not rows:
        return
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def _summary(data: dict, figures: list[Path]) -> dict:
    """The numbers a reader wants first: per scene, k and grid, error and time."""
    scenes = {}
    for name, info in data["scenes"].items():
        default_rows = [r for r in data["errors"] if r["scene"] == name and r["is_default"]]
        best = {}
        for r in data["errors"]:
            if r["scene"] == name and (r["k"] not in best or r["error"] < best[r["k"]]["error"]):
                best[r["k"]] = r
        conv = data["convergence"][name]
        scenes[name] = {
            "rho": info["rho"],
            "converges": info["converges"],
            "auto_bounces": info["auto_bounces"],
            "default_grid": {"n_theta": info["default_n_theta"], "refine": info["default_refine"]},
            "mc_noise_per_k": info["mc_noise"],
            "default_error_per_k": {r["k"]: r["error"] for r in default_rows},
            "default_time_per_k_s": {r["k"]: r["render_median_s"] for r in default_rows},
            "best_error_per_k": {
                k: {x: r[x] for x in ("error", "n_theta", "refine", "render_median_s")}
                for k, r in sorted(best.items())
            },
            "theta_order_self": {
                f"k{c['k']}_refine{c['refine']}": c["orders"] for c in conv["theta_self"]
            },
            "space_order_self": {f"k{c['k']}": c["orders"] for c in conv["space_self"]},
            "theta_order_vs_mc": {
                f"k{c['k']}_refine{c['refine']}": c["order_all"] for c in conv["theta_vs_mc"]
            },
            "space_order_vs_mc": {
                f"k{c['k']}_n_theta{c['n_theta']}": c["order"] for c in conv["space_vs_mc"]
            },
        }
        totals = [
            r
            for r in data["total_vs_bounces"]
            if r["scene"] == name and r["is_default"] and r["is_auto"]
        ]
        if totals:
            scenes[name]["default_auto_total_error"] = totals[0]["error_total"]
    return {
        "scenes": scenes,
        "yardstick_fft_s": data["yardstick_fft_s"],
        "figures": [str(p.name) for p in figures],
        "data": ["forward_accuracy.json", "errors.csv", "timings.csv", "total_vs_bounces.csv"],
    }


# ---------------------------------------------------------------------------- figures


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    _plt().close(fig)
    return path


def _scene_title(data: dict, name: str) -> str:
    info = data["scenes"][name]
    p = info["params"]
    beam = p["beam"]
    g = data["grid"]
    return (
        f"{info['label']}: σt {p['sigma_t']:g}, σs {p['sigma_s']:g} px⁻¹, g {p['g']:g}, "
        f"ρ = ω·A(g) = {info['rho']:.3f} ({p['phase']}); beam from ({beam['x']:g}, "
        f"{beam['y']:g}) at {beam['direction_deg']:g}°, {g['width']}×{g['height']} px; "
        f"MC {info['mc_photons']:.1e} photons"
    )


def _plot_error_vs_time(out: Path, scene: Scene, data: dict) -> Path:
    plt = _plt()
    info = data["scenes"][scene.name]
    rows = [r for r in data["errors"] if r["scene"] == scene.name]
    ks = sorted({r["k"] for r in rows})
    totals = [
        r for r in data["total_vs_bounces"] if r["scene"] == scene.name and r["is_auto"]
    ]
    ncols = len(ks) + (1 if totals else 0)
    fig, axes = plt.subplots(1, ncols, figsize=(4.3 * ncols, 4.4), squeeze=False)
    styles = {1: ("o", "-"), 2: ("s", "--"), 3: ("^", ":"), 4: ("D", "-.")}
    for ax, k in zip(axes[0], ks, strict=False):
        sel = [r for r in rows if r["k"] == k]
        for i, refine in enumerate(sorted({r["refine"] for r in sel})):
            pts = sorted((r for r in sel if r["refine"] == refine), key=lambda r: r["n_theta"])
            marker, line = styles.get(refine, ("x", "-"))
            x = [1e3 * r["render_median_s"] for r in pts]
            y = [100 * r["error"] for r in pts]
            ax.loglog(x, y, marker=marker, ls=line, color=f"C{i}", label=f"refine {refine}")
            for r, xi, yi in zip(pts, x, y, strict=False):
                ax.annotate(
                    f"{r['n_theta']}", (xi, yi), textcoords="offset points", xytext=(4, 4),
                    fontsize=7, color=f"C{i}",
                )
        for r in sel:
            if r["is_default"]:
                ax.loglog(
                    1e3 * r["render_median_s"], 100 * r["error"], "*", ms=16, mfc="none",
                    mec="k", mew=1.5, label="default grid",
                )
        ax.axhline(100 * info["mc_noise"][k - 1], color="0.5", ls=":", label="MC noise level")
        ax.set_title(f"$I_{k}$ (render of K = {k} bounces)")
        ax.set_xlabel("render wall time, steady state (ms)")
        ax.set_ylabel("4×4-binned relative L1 error vs MC (%)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    if totals:
        ax = axes[0][-1]
        for i, refine in enumerate(sorted({r["refine"] for r in totals})):
            pts = sorted((r for r in totals if r["refine"] == refine), key=lambda r: r["n_theta"])
            marker, line = styles.get(refine, ("x", "-"))
            x = [1e3 * r["render_median_s"] for r in pts]
            y = [100 * r["error_total"] for r in pts]
            ax.loglog(x, y, marker=marker, ls=line, color=f"C{i}", label=f"refine {refine}")
            for r, xi, yi in zip(pts, x, y, strict=False):
                ax.annotate(
                    f"{r['n_theta']}", (xi, yi), textcoords="offset points", xytext=(4, 4),
                    fontsize=7, color=f"C{i}",
                )
            for r in pts:
                if r["is_default"]:
                    ax.loglog(
                        1e3 * r["render_median_s"], 100 * r["error_total"], "*", ms=16,
                        mfc="none", mec="k", mew=1.5, label="default grid",
                    )
        ax.set_title(f"total image, K = auto = {info['auto_bounces']} bounces")
        ax.set_xlabel("render wall time, steady state (ms)")
        ax.set_ylabel("4×4-binned relative L1 error vs MC (%)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(
        _scene_title(data, scene.name) + "\nlabels: n_theta; ★ default grid "
        f"(n_theta {info['default_n_theta']}, refine {info['default_refine']})"
        + ("" if info["converges"] else "; ρ ≥ 1: series diverges, bounces compared as is"),
        fontsize=9,
    )
    fig.tight_layout()
    return _save(fig, out / f"error_vs_time_{scene.name}.png")


def _plot_convergence(out: Path, scenes: list[Scene], data: dict) -> Path:
    plt = _plt()
    fig, axes = plt.subplots(2, len(scenes), figsize=(4.3 * len(scenes), 8), squeeze=False)
    for j, scene in enumerate(scenes):
        info = data["scenes"][scene.name]
        conv = data["convergence"][scene.name]
        ax = axes[0][j]
        for c in conv["theta_vs_mc"]:
            k, refine = c["k"], c["refine"]
            ls = "-" if refine == 1 else "--"
            order = c["order_all"]
            ax.loglog(
                c["n_theta"], [100 * e for e in c["error"]], marker="o", ls=ls, color=f"C{k - 1}",
                label=f"k={k}, refine {refine} (order {order:.2f})" if order is not None else None,
            )
        for k, n in enumerate(info["mc_noise"], start=1):
            ax.axhline(100 * n, color=f"C{k - 1}", ls=":", lw=0.8)
        ax.set_xscale("log", base=2)
        ax.set_xlabel("direction bins n_theta")
        ax.set_ylabel("binned relative L1 error vs MC (%)")
        ax.set_title(f"{info['label']}: vs Monte Carlo (dotted: MC noise)", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6)
        ax = axes[1][j]
        for c in conv["theta_self"]:
            k, refine = c["k"], c["refine"]
            if k == 1:
                continue
            ls = "-" if refine == 1 else "--"
            orders = ", ".join("–" if o is None else f"{o:.2f}" for o in c["orders"])
            ax.loglog(
                c["n_theta"], [100 * d for d in c["difference_to_2n"]], marker="o", ls=ls,
                color=f"C{k - 1}", label=f"θ: k={k}, refine {refine} (orders {orders})",
            )
        for c in conv["space_self"]:
            k = c["k"]
            if k == 1:
                continue
            orders = ", ".join("–" if o is None else f"{o:.2f}" for o in c["orders"])
            ax.loglog(
                [c["n_theta"] * r for r in c["refine"]],
                [100 * d for d in c["difference_to_next"]], marker="x", ls="-.", color=f"C{k + 2}",
                label=f"space: k={k}, refine {c['refine']} at n_theta {c['n_theta']} "
                f"(x = n_theta·refine; orders {orders})",
            )
        ax.set_xscale("log", base=2)
        ax.set_xlabel("n_theta (θ study) or n_theta × refine (space study)")
        ax.set_ylabel("‖R − R_next‖₁/‖R_next‖₁, binned (%)")
        ax.set_title(f"{info['label']}: self-convergence (no MC noise)", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6)
    fig.suptitle(
        f"Convergence of the per-bounce images, {data['grid']['width']}×"
        f"{data['grid']['height']} px, 4×4-binned relative L1",
        fontsize=10,
    )
    fig.tight_layout()
    return _save(fig, out / "convergence.png")


def _plot_total_vs_bounces(out: Path, scenes: list[Scene], data: dict) -> Path:
    plt = _plt()
    shown = [s for s in scenes if data["scenes"][s.name]["converges"]]
    fig, axes = plt.subplots(1, len(shown), figsize=(4.5 * len(shown), 4.2), squeeze=False)
    for ax, scene in zip(axes[0], shown, strict=False):
        info = data["scenes"][scene.name]
        rows = [r for r in data["total_vs_bounces"] if r["scene"] == scene.name]
        for i, (n_theta, refine) in enumerate(sorted({(r["n_theta"], r["refine"]) for r in rows})):
            pts = sorted(
                (r for r in rows if (r["n_theta"], r["refine"]) == (n_theta, refine)),
                key=lambda r: r["bounces"],
            )
            default = pts[0]["is_default"]
            ax.semilogy(
                [r["bounces"] for r in pts], [100 * r["error_total"] for r in pts],
                marker="o" if default else ".", lw=2.2 if default else 0.8, color=f"C{i % 10}",
                ls="-" if refine == 1 else "--",
                label=f"n_theta {n_theta}, refine {refine}" + (" (default)" if default else ""),
            )
        ax.axvline(info["auto_bounces"], color="k", ls=":", label=f"auto K = {info['auto_bounces']}")
        ax.set_xlabel("bounces K rendered")
        ax.set_ylabel("error of Σ_{k≤K} I_k vs MC total (%)")
        ax.set_title(f"{info['label']} (ρ = {info['rho']:.3f}; MC {info['mc_bounces']} bounces)",
                     fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6)
    fig.suptitle("Total image against the bounce count (4×4-binned relative L1)", fontsize=10)
    fig.tight_layout()
    return _save(fig, out / "error_vs_bounces.png")
