"""How accurate is the forward model, and what does accuracy cost?

Per-bounce images I_k (k = 1..``bounces``) of :func:`lightfield_jax.render` against the
independent Monte Carlo oracle (:func:`lightfield_jax.reference.montecarlo.monte_carlo_render`),
over the number of direction bins ``n_theta`` and the spatial refinement ``refine``,
for several beam scenes; and the steady-state wall time of the render that produces
them (compile reported apart).

Error metric: 4×4-binned relative L1, Σ_b |R_b − M_b| / Σ_b |M_b| over 4×4 pixel
blocks b (block sums), R the render, M the Monte Carlo.

The Monte Carlo's own noise. The photons run as ``mc_splits`` independent runs (seeds
``seed``, ``seed + 1``, ...); M is their mean and σ_b, the standard error of bin b of M,
comes from their spread. noise = √(2/π) Σ_b σ_b / Σ_b |M_b| is the relative L1 that M's
noise alone adds (in expectation) to the error of a perfect render. Correlations
between pixels (one photon crosses many) are included, which per-pixel standard errors
would miss. Errors within a few times the noise are noise-limited: they bound the
model's error from above, no more. The energy Σ I_k of each bounce is compared too
(signed bias, with the Monte Carlo's standard error), and for k = 2 also against a
noise-free quadrature of Σ I_2 (:func:`_second_bounce_energy`).

Convergence (order p: error ∝ n^−p). (1) Against the Monte Carlo: least-squares
−d log error / d log n_theta (per refine) and −d log error / d log refine (per n_theta);
a flat curve (p ≈ 0) says another error dominates (space, or the Monte Carlo noise).
(2) Self-convergence (no Monte Carlo noise): Cauchy differences
d(n) = ‖R_n − R_2n‖₁/‖R_2n‖₁ (binned) give the order log2(d(n)/d(2n)) in θ at fixed
refine; refinements 1, 2, 4 at the scene's default n_theta give it in space.

Bounce count: the total image Σ_{k≤K} I_k against the Monte Carlo's Σ over
max(bounces, K_auto) bounces, for K = 1, 2, ...; ``auto`` (tail bound ρ^K/(1−ρ) ≤
tolerance) is marked. Under ``phase: paper`` a medium with ρ = ω·A(g) ≥ 1 has no
convergent total: only its first ``bounces`` bounces are compared, as a truncation.

Timing: each (scene, n_theta, refine, K) render is timed through the public
``lightfield_jax.render`` (first call from cold: table setup + compile + run; then the
median of ``repeats`` steady calls). Right after, a jitted complex64 FFT over a light
field's size (64 × H × W) is timed as a yardstick of the machine's speed at that moment
(other jobs on the machine slow both alike), with the load average. Every Monte Carlo
run and every timing is cached (resume).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
import warnings
from pathlib import Path
from typing import Annotated, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import lightfield_jax as lfj
from lightfield_jax.app.experiment_config import Pixels, Range, Seed, typed_config
from lightfield_jax.app.experiment_records import pyplot, save_figure, write_csv
from lightfield_jax.forward.render import renderer_for
from lightfield_jax.reference.montecarlo import monte_carlo_render
from lightfield_jax.runtime.timing import stopwatch

_SCENE_KEYS = {"name", "sigma_t", "sigma_s", "g", "beam", "phase", "label"}
_BEAM_KEYS = {"x", "y", "direction_deg", "width"}
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


@dataclasses.dataclass(frozen=True)
class BeamSpec:
    """A scene's beam (pixels, degrees): entering at (x, y), heading, width."""

    y: float
    x: float = 0.0
    direction_deg: Annotated[float, Range(-89, 89)] = 0.0
    width: float = 1.0


@dataclasses.dataclass(frozen=True)
class SceneSpec:
    """A scene: its name and label, σt, σs (per pixel), g, phase and beam."""

    name: str
    sigma_t: float
    sigma_s: float
    g: float
    beam: Annotated[dict, BeamSpec]
    phase: str = "paper"
    label: str | None = None


@dataclasses.dataclass(frozen=True)
class Config:
    """configs/forward_accuracy.yaml: the grid (pixels, multiples of ``bin``: the error
    metric's block size), the Monte Carlo oracle (photons in total, run as ``mc_splits``
    independent runs from ``seed``), the θ bins and refinements compared, the bounces
    with per-bounce errors, the refinements of the space self-convergence, the timing
    repeats, the auto bounces' tail bound and the scenes."""

    width: Pixels
    height: Pixels
    photons: Annotated[int, Range(1, 10**10)]
    mc_splits: Annotated[int, Range(1, 1000)]
    seed: Seed
    n_theta: tuple[int, ...]
    refine: tuple[int, ...]
    bounces: Annotated[int, Range(1, 100)]
    convergence_refine: tuple[int, ...]
    repeats: Annotated[int, Range(1, 1000)]
    tolerance: Annotated[float, Range(0, 0.1, open_low=True)]
    scenes: tuple[Annotated[dict, SceneSpec], ...]
    bin: Annotated[int, Range(1, 64)] = 4

    def __post_init__(self):
        b = self.bin
        if self.width % b or self.height % b:
            raise ValueError(f"forward_accuracy: width and height must be multiples of bin = {b}")
        if not (self.scenes and self.n_theta and self.refine):
            raise ValueError("forward_accuracy: scenes, n_theta, refine: at least one each")
        if self.photons < self.mc_splits or self.seed + self.mc_splits > 2**32:
            raise ValueError(
                "forward_accuracy: photons, seed: at least one photon per split, and seeds "
                f"seed + mc_splits below 2**32, got {self.photons}, {self.seed}"
            )
        try:  # the grids and scenes as run() builds them: their own checks
            for n_theta in self.n_theta:
                for refine in {*self.refine, *self.convergence_refine}:
                    lfj.Grid(self.width, self.height, n_theta, refine)
            for spec in self.scenes:
                _scene(spec)
        except ValueError as e:
            raise ValueError(f"forward_accuracy: {e}") from None


# ----------------------------------------------------------------------------- metrics


def _binned(images: np.ndarray, b: int) -> np.ndarray:
    """Block sums over b×b pixels of (..., H, W)."""
    *lead, h, w = images.shape
    return images.reshape(*lead, h // b, b, w // b, b).sum(axis=(-3, -1))


def _rel_l1(a: np.ndarray, ref: np.ndarray) -> float:
    return float(np.abs(a - ref).sum() / np.abs(ref).sum())


# ------------------------------------------------------------------------- measurements


def _monte_carlo(ctx, scene: Scene, cfg: Config, k_mc: int) -> dict:
    """``mc_splits`` independent runs (seeds seed, seed+1, ...), each cached; binned.

    Returns the mean M, the standard error of each bin of M (from the spread of the
    splits), and the splits' energies per bounce.
    """
    splits = cfg.mc_splits
    n = cfg.photons // splits
    runs = []
    for i in range(splits):
        seed = cfg.seed + i
        key = (
            f"mc|{json.dumps(scene.params, sort_keys=True)}|{cfg.width}x{cfg.height}"
            f"|K{k_mc}|N{n}|seed{seed}|bin{cfg.bin}"
        )

        def compute(seed=seed, i=i):
            ctx.progress(f"Monte Carlo {scene.name} {i + 1}/{splits}")
            t0 = time.perf_counter()
            res = monte_carlo_render(
                cfg.width,
                cfg.height,
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
                "binned": _binned(res.images[0], cfg.bin).tolist(),
                "seconds": time.perf_counter() - t0,
                "photons": n,
            }

        runs.append(ctx.cached(key, compute))
    a = np.stack([np.asarray(r["binned"]) for r in runs])  # (splits, K, h, w)
    return {
        "mean": a.mean(axis=0),
        "splits": a,
        "seconds": sum(r["seconds"] for r in runs),
        "photons": n * splits,
    }


def _l1_noise(splits: np.ndarray) -> float:
    """Expected relative L1 of the mean's noise: √(2/π)·Σ_b σ_b / Σ_b |M_b|, σ_b the
    standard error of bin b from the spread of the splits."""
    mean = splits.mean(axis=0)
    se = splits.std(axis=0, ddof=1) / math.sqrt(splits.shape[0])
    return float(math.sqrt(2 / math.pi) * se.sum() / np.abs(mean).sum())


def _energy_noise(splits: np.ndarray) -> float:
    """Relative standard error of the mean's total (energy)."""
    e = splits.reshape(splits.shape[0], -1).sum(axis=1)
    return float(e.std(ddof=1) / math.sqrt(len(e)) / e.mean())


def _second_bounce_energy(scene: Scene, width: int, height: int) -> float:
    """Σ_pixels I_2 by quadrature, with no grid and no Monte Carlo noise (docs/model.md §4).

    Light scattered once at x' heading θ travels until it collides or leaves, so the
    area integral of its fluence is Q_1(x', θ)(1 − e^{−σt d(x', θ)})/σt, d the distance
    to the wall. Hence ΣI_2 = σs p(π/2) ∫∫ S(x') ∫ σs p(θ − θ0)(1 − e^{−σt d})/σt dθ dx'
    over the beam (S = e^{−σt t} at distance t along it, unit transverse irradiance).
    Gauss–Legendre in t (per unit length) and across the beam, midpoints in θ.
    """
    st, ss, g = (float(v) for v in (scene.medium.sigma_t, scene.medium.sigma_s, scene.medium.g))
    if scene.medium.phase != "paper":
        raise ValueError("the quadrature reference is written for phase: paper")
    beam = scene.beam
    t0 = math.radians(beam.direction_deg)
    w0 = np.array([math.cos(t0), math.sin(t0)])
    normal = np.array([-w0[1], w0[0]])
    n_theta = 4096
    theta = (np.arange(n_theta) + 0.5) * (2 * math.pi / n_theta)
    c, s = np.cos(theta), np.sin(theta)
    redistribution = ss * _hg(theta - t0, g) * (2 * math.pi / n_theta) / st

    def to_wall(px, py, cx, sx):
        with np.errstate(divide="ignore", invalid="ignore"):
            dx = np.where(cx > 0, (width - px) / cx, np.where(cx < 0, -px / cx, np.inf))
            dy = np.where(sx > 0, (height - py) / sx, np.where(sx < 0, -py / sx, np.inf))
        return np.maximum(np.minimum(dx, dy), 0.0)

    ug, uw = np.polynomial.legendre.leggauss(8)
    tg, tw = np.polynomial.legendre.leggauss(8)
    total = 0.0
    for u, wu in zip(0.5 * beam.width * ug, 0.5 * beam.width * uw, strict=True):
        start = np.array([beam.x, beam.y]) + u * normal
        length = float(to_wall(start[0], start[1], w0[0], w0[1]))
        panels = max(1, math.ceil(length))
        edges = np.linspace(0.0, length, panels + 1)
        h = np.diff(edges)
        t = (edges[:-1, None] + 0.5 * h[:, None] * (1 + tg[None, :])).ravel()
        wt = (0.5 * h[:, None] * tw[None, :]).ravel()
        px, py = start[0] + t * w0[0], start[1] + t * w0[1]
        d = to_wall(px[:, None], py[:, None], c[None, :], s[None, :])
        inner = (redistribution * -np.expm1(-st * d)).sum(axis=1)
        total += wu * float((wt * np.exp(-st * t) * inner).sum())
    return ss * float(_hg(math.pi / 2, g)) * total


def _hg(theta, g: float):
    """The paper's phase function (3-D HG at the in-plane angle), written out here so
    the reference shares no code with the renderer."""
    return (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * np.cos(theta)) ** 1.5)


def _render_images(
    ctx, scene: Scene, cfg: Config, n_theta: int, refine: int, k: int, compiled: set
) -> np.ndarray:
    """Binned I_1..I_k of one render (cached)."""
    key = (
        f"images|{json.dumps(scene.params, sort_keys=True)}|{cfg.width}x{cfg.height}"
        f"|nt{n_theta}|r{refine}|K{k}|bin{cfg.bin}|{jnp.result_type(float)}"
    )

    def compute():
        ctx.progress(f"render {scene.name} n_theta {n_theta} refine {refine}")
        grid = lfj.Grid(cfg.width, cfg.height, n_theta, refine)
        compiled.add((grid, scene.beam, k, scene.medium.phase))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", lfj.DivergentSeriesWarning)
            images = np.asarray(lfj.render(scene.medium, grid, scene.beam, k).images, np.float64)
        return _binned(images, cfg.bin).tolist()

    return np.asarray(ctx.cached(key, compute))


def _time_render(
    ctx, scene: Scene, cfg: Config, n_theta: int, refine: int, k: int, compiled: set
) -> dict:
    """First call (setup + compile + run) and steady-state median of one render (cached)."""
    key = (
        f"time|{json.dumps(scene.params, sort_keys=True)}|{cfg.width}x{cfg.height}"
        f"|nt{n_theta}|r{refine}|K{k}|rep{cfg.repeats}|{jnp.result_type(float)}|cold|yard"
    )

    def compute():
        ctx.progress(f"time {scene.name} n_theta {n_theta} refine {refine} K {k}")
        grid = lfj.Grid(cfg.width, cfg.height, n_theta, refine)

        def call():
            return lfj.render(scene.medium, grid, scene.beam, k).images.block_until_ready()

        # A cold start: a renderer compiled earlier in this run (same grid, beam and K
        # for another medium: new values never recompile) would report no compile time.
        static = (grid, scene.beam, k, scene.medium.phase)
        if static in compiled:
            jax.clear_caches()
            renderer_for.cache_clear()
        compiled.add(static)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", lfj.DivergentSeriesWarning)
            with stopwatch() as first:
                call()
            times = []
            for _ in range(cfg.repeats):
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
            "yardstick_fft_s": _yardstick(64, cfg.height, cfg.width, repeats=7),
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
    for k in range(1, cfg.bounces + 1):
        for refine in cfg.refine:
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
        [(a, _rel_l1(images[a][k], images[b][k])) for a, b in zip(keys, keys[1:], strict=False)]
        for k in range(k_max)
    ]


# ------------------------------------------------------------------------------ run


def run(config: dict, out: Path, ctx) -> dict:
    cfg = typed_config(Config, config)
    scenes = [_scene(s) for s in cfg.scenes]
    w, h, kb = cfg.width, cfg.height, cfg.bounces
    error_rows, time_rows, total_rows, convergence, scene_info = [], [], [], {}, {}
    compiled: set = set()  # static renderer configurations compiled in this process

    for scene in scenes:
        default = lfj.Grid(w, h).resolve(float(scene.medium.g))
        k_auto = lfj.bounces_for_tolerance(scene.rho, cfg.tolerance) if scene.converges else None
        k_mc = max(kb, k_auto or 0)
        n_thetas = sorted(set(cfg.n_theta) | {default.n_theta})
        refines = sorted(set(cfg.refine) | {default.refine})
        mc = _monte_carlo(ctx, scene, cfg, k_mc)
        m, splits = mc["mean"], mc["splits"]
        noise = [_l1_noise(splits[:, k]) for k in range(k_mc)]
        energy_noise = [_energy_noise(splits[:, k]) for k in range(k_mc)]
        mc_total = m.sum(axis=0)
        total_noise = _l1_noise(splits.sum(axis=1))
        e2 = ctx.cached(
            f"I2-energy|{json.dumps(scene.params, sort_keys=True)}|{w}x{h}",
            lambda scene=scene: _second_bounce_energy(scene, w, h),
        )
        scene_info[scene.name] = {
            "label": scene.label,
            "params": scene.params,
            "rho": scene.rho,
            "converges": scene.converges,
            "auto_bounces": k_auto,
            "default_n_theta": default.n_theta,
            "default_refine": default.refine,
            "mc_bounces": k_mc,
            "mc_photons": mc["photons"],
            "mc_splits": cfg.mc_splits,
            "mc_energy_noise": energy_noise[:kb],
            "i2_energy_quadrature": e2,
            "i2_energy_mc_bias": float(m[1].sum() / e2 - 1.0),
            "mc_seconds": mc["seconds"],
            "mc_noise": noise[:kb],
            "mc_noise_total": total_noise,
        }
        images = {}
        timed_k = sorted({*range(1, kb + 1)} | ({k_auto} if k_auto else set()))
        for refine in refines:
            for n_theta in n_thetas:
                timings = {
                    k: _time_render(ctx, scene, cfg, n_theta, refine, k, compiled) for k in timed_k
                }
                r = _render_images(ctx, scene, cfg, n_theta, refine, k_mc, compiled)
                images[(n_theta, refine)] = r
                is_default = (n_theta, refine) == (default.n_theta, default.refine)
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
                            "yardstick_fft_s": t["yardstick_fft_s"],
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
                            "energy_bias": float(r[k - 1].sum() / m[k - 1].sum() - 1.0),
                            "energy_noise": energy_noise[k - 1],
                            "energy_bias_exact": float(r[1].sum() / e2 - 1.0) if k == 2 else None,
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
                                "mc_noise_total": total_noise,
                                "render_median_s": timings[k]["median_s"] if k in timings else None,
                            }
                        )
        # Self-convergence in θ (every refine) and in space (default n_theta).
        self_theta = {
            refine: _cauchy(images, [(n, refine) for n in n_thetas], kb) for refine in refines
        }
        space_keys = []
        for refine in sorted(set(cfg.convergence_refine) | {default.refine}):
            key = (default.n_theta, refine)
            if key not in images:
                images[key] = _render_images(
                    ctx, scene, cfg, default.n_theta, refine, k_mc, compiled
                )
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

    _write_csv(out / "errors.csv", error_rows)
    _write_csv(out / "timings.csv", time_rows)
    _write_csv(out / "total_vs_bounces.csv", total_rows)
    data = {
        "grid": {"width": w, "height": h, "bin": cfg.bin},
        "scenes": scene_info,
        "errors": error_rows,
        "timings": time_rows,
        "total_vs_bounces": total_rows,
        "convergence": convergence,
        "yardstick_shape": [64, h, w],
        "dtype": str(jnp.result_type(float)),
        "repeats": cfg.repeats,
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
    header = list(rows[0])
    write_csv(path, header, ([row[k] for k in header] for row in rows))


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
            "default_energy_bias_per_k": {r["k"]: r["energy_bias"] for r in default_rows},
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
    loads = [r["load_average_1min"] for r in data["timings"]]
    yard = [r["yardstick_fft_s"] for r in data["timings"]]
    return {
        "scenes": scenes,
        "yardstick_fft_s": [min(yard), float(np.median(yard)), max(yard)],
        "load_average_1min": [min(loads), max(loads)],
        "figures": [str(p.name) for p in figures],
        "data": ["forward_accuracy.json", "errors.csv", "timings.csv", "total_vs_bounces.csv"],
    }


# ---------------------------------------------------------------------------- figures


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


def _error_time_panel(ax, rows: list[dict], key: str) -> None:
    """Error ``key`` (%) against render time (ms), one line per refinement labelled with
    its θ bins, the default grid starred."""
    styles = {1: ("o", "-"), 2: ("s", "--"), 3: ("^", ":"), 4: ("D", "-.")}
    for i, refine in enumerate(sorted({r["refine"] for r in rows})):
        pts = sorted((r for r in rows if r["refine"] == refine), key=lambda r: r["n_theta"])
        marker, line = styles.get(refine, ("x", "-"))
        x = [1e3 * r["render_median_s"] for r in pts]
        y = [100 * r[key] for r in pts]
        ax.loglog(x, y, marker=marker, ls=line, color=f"C{i}", label=f"refine {refine}")
        for r, xi, yi in zip(pts, x, y, strict=False):
            ax.annotate(
                f"{r['n_theta']}",
                (xi, yi),
                textcoords="offset points",
                xytext=(4, 4),
                fontsize=7,
                color=f"C{i}",
            )
    for r in rows:
        if r["is_default"]:
            ax.loglog(
                1e3 * r["render_median_s"],
                100 * r[key],
                "*",
                ms=16,
                mfc="none",
                mec="k",
                mew=1.5,
                label="default grid",
            )


def _plot_error_vs_time(out: Path, scene: Scene, data: dict) -> Path:
    plt = pyplot()
    info = data["scenes"][scene.name]
    rows = [r for r in data["errors"] if r["scene"] == scene.name]
    ks = sorted({r["k"] for r in rows})
    totals = [r for r in data["total_vs_bounces"] if r["scene"] == scene.name and r["is_auto"]]
    ncols = len(ks) + (1 if totals else 0)
    fig, axes = plt.subplots(1, ncols, figsize=(4.3 * ncols, 4.4), squeeze=False)
    for ax, k in zip(axes[0], ks, strict=False):
        _error_time_panel(ax, [r for r in rows if r["k"] == k], "error")
        ax.axhline(100 * info["mc_noise"][k - 1], color="0.5", ls=":", label="MC noise level")
        _log_ticks(ax)
        ax.set_title(f"$I_{k}$ (render of K = {k} bounces)")
        ax.set_xlabel("render wall time, steady state (ms)")
        ax.set_ylabel("4×4-binned relative L1 error vs MC (%)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    if totals:
        ax = axes[0][-1]
        _error_time_panel(ax, totals, "error_total")
        ax.axhline(100 * info["mc_noise_total"], color="0.5", ls=":", label="MC noise level")
        _log_ticks(ax)
        ax.set_title(f"total image, K = auto = {info['auto_bounces']} bounces")
        ax.set_xlabel("render wall time, steady state (ms)")
        ax.set_ylabel("4×4-binned relative L1 error vs MC (%)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    timed = [r for r in data["timings"] if r["scene"] == scene.name]
    loads = [r["load_average_1min"] for r in timed]
    yard = [1e3 * r["yardstick_fft_s"] for r in timed]
    fig.suptitle(
        _scene_title(data, scene.name)
        + f"\ntimes: median of {data['repeats']} calls; machine load (1-min average) "
        f"{min(loads):.1f}–{max(loads):.1f} on {os.cpu_count()} cores; yardstick (complex64 "
        f"FFT of {'×'.join(map(str, data['yardstick_shape']))}, timed with each render) "
        f"{min(yard):.1f}–{max(yard):.1f} ms" + "\nlabels: n_theta; ★ default grid "
        f"(n_theta {info['default_n_theta']}, refine {info['default_refine']})"
        + (
            ""
            if info["converges"]
            else f"; ρ ≥ 1: the series diverges, its first {len(ks)} bounces (each finite) compared"
        ),
        fontsize=9,
    )
    fig.tight_layout()
    return save_figure(fig, out / f"error_vs_time_{scene.name}.png")


def _plot_convergence(out: Path, scenes: list[Scene], data: dict) -> Path:
    plt = pyplot()
    ncols = len(scenes)
    fig, axes = plt.subplots(3, ncols, figsize=(max(4.6 * ncols, 7), 12), squeeze=False)
    for j, scene in enumerate(scenes):
        info = data["scenes"][scene.name]
        conv = data["convergence"][scene.name]
        ax = axes[0][j]
        for c in conv["theta_vs_mc"]:
            k, refine = c["k"], c["refine"]
            order = c["order_all"]
            ax.loglog(
                c["n_theta"],
                [100 * e for e in c["error"]],
                marker="o",
                ls="-" if refine == 1 else "--",
                color=f"C{k - 1}",
                label=f"k={k}, refine {refine} (order {_fmt(order)})",
            )
        for k, n in enumerate(info["mc_noise"], start=1):
            ax.axhline(100 * n, color=f"C{k - 1}", ls=":", lw=0.8)
        _n_axis(ax, conv["theta_vs_mc"][0]["n_theta"], "direction bins n_theta")
        ax.set_ylabel("binned relative L1 error vs MC (%)")
        ax.set_title(f"{info['label']}: error vs Monte Carlo\n(dotted: MC noise level)", fontsize=9)
        ax.legend(fontsize=6)
        ax = axes[1][j]
        for c in conv["theta_self"]:
            k, refine = c["k"], c["refine"]
            if k == 1 or not c["n_theta"]:
                continue
            orders = ", ".join(_fmt(o) for o in c["orders"]) or "–"
            ax.loglog(
                c["n_theta"],
                [100 * d for d in c["difference_to_2n"]],
                marker="o",
                ls="-" if refine == 1 else "--",
                color=f"C{k - 1}",
                label=f"k={k}, refine {refine} (orders {orders})",
            )
        _n_axis(ax, conv["theta_self"][0]["n_theta"], "n_theta (difference to 2·n_theta)")
        ax.set_ylabel("‖R_n − R_2n‖₁ / ‖R_2n‖₁, binned (%)")
        ax.set_title(f"{info['label']}: self-convergence in θ (no MC noise)", fontsize=9)
        ax.legend(fontsize=6)
        ax = axes[2][j]
        for c in conv["space_self"]:
            k = c["k"]
            if k == 1 or not c["refine"]:
                continue
            orders = ", ".join(_fmt(o) for o in c["orders"]) or "–"
            ax.loglog(
                c["refine"],
                [100 * d for d in c["difference_to_next"]],
                marker="s",
                color=f"C{k - 1}",
                label=f"k={k} (orders {orders})",
            )
        _n_axis(ax, conv["space_self"][0]["refine"], "refine (difference to the next refine)")
        ax.set_ylabel("‖R_r − R_next‖₁ / ‖R_next‖₁, binned (%)")
        ax.set_title(
            f"{info['label']}: self-convergence in space\n(n_theta {info['default_n_theta']})",
            fontsize=9,
        )
        ax.legend(fontsize=6)
    fig.suptitle(
        f"Convergence of the per-bounce images I_k, {data['grid']['width']}×"
        f"{data['grid']['height']} px, 4×4-binned relative L1\norder p: error ∝ n^−p",
        fontsize=10,
    )
    fig.tight_layout()
    return save_figure(fig, out / "convergence.png")


def _fmt(order: float | None) -> str:
    return "–" if order is None else f"{round(order, 2) + 0.0:.2f}"


def _n_axis(ax, values, label: str) -> None:
    """A log2 axis ticked at the sampled values, plain numbers, and readable log y ticks."""
    from matplotlib.ticker import NullFormatter

    ax.set_xscale("log", base=2)
    if values:
        ax.set_xticks(values)
        ax.set_xticklabels([f"{v:g}" for v in values])
    ax.xaxis.set_minor_formatter(NullFormatter())
    _log_ticks(ax, x=False)
    ax.set_xlabel(label)
    ax.grid(True, which="both", alpha=0.3)


def _log_ticks(ax, x: bool = True, y: bool = True) -> None:
    """Ticks at 1, 2, 5 × 10^n labelled as plain numbers (no overlapping minor labels)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    for on, axis in ((x, ax.xaxis), (y, ax.yaxis)):
        if on:
            axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 3.0, 5.0)))
            axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            axis.set_minor_formatter(NullFormatter())


def _plot_total_vs_bounces(out: Path, scenes: list[Scene], data: dict) -> Path:
    plt = pyplot()
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
                [r["bounces"] for r in pts],
                [100 * r["error_total"] for r in pts],
                marker="o" if default else ".",
                lw=2.2 if default else 0.8,
                color=f"C{i % 10}",
                ls="-" if refine == 1 else "--",
                label=f"n_theta {n_theta}, refine {refine}" + (" (default)" if default else ""),
            )
        auto = info["auto_bounces"]
        ax.axvline(auto, color="k", ls=":", label=f"auto K = {auto}")
        ax.axhline(100 * info["mc_noise_total"], color="0.5", ls=":", label="MC noise level")
        _log_ticks(ax, x=False)
        ax.set_xlabel("bounces K rendered")
        ax.set_ylabel(r"error of $\Sigma_{k\leq K} I_k$ vs MC total (%)")
        ax.set_title(
            f"{info['label']} (ρ = {info['rho']:.3f}; MC {info['mc_bounces']} bounces)", fontsize=9
        )
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6)
    fig.suptitle("Total image against the bounce count (4×4-binned relative L1)", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, out / "error_vs_bounces.png")
