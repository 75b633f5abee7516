"""Do gradient solves beat the paper's grid search at equal accuracy, and by how much?

Recovery error of σt, σs, g against wall time (compile and run apart) of each inverse
method on the paper's milk (σt 0.2051, σs 0.0366, g 0.4 per pixel), a period-6 stripe
capture with 6 shifts:

- ``grid-N``: the paper's method, g searched on N values (``g_grids``; on the perfect
  split also ``dense_g_grids``: there the grid's error falls with N, while on the stripe
  captures it sits on the separation's bias at every N);
- ``gradient``: the same residual solved with optimistix Levenberg-Marquardt;
- ``joint``: the raw shifted images, no separation (skipped on the perfect split,
  which it does not use);
- ``jaxopt-lm``, ``jaxopt-gn``: an outside comparison, jaxopt's Levenberg-Marquardt and
  Gauss-Newton on the same two-step residual over (σs, g), built from the package's
  :class:`~lightfield_jax.Renderer` as ``gradient`` builds it (same σt from the decay
  of D, same model size, same reparametrisation and same coarse start over
  ``start_grid`` values of g).

Captures: ``noiseless``; ``noisy`` (Poisson photons + Gaussian read noise, a new seed
per repeat); ``perfect_split``: the noiseless capture with the true split (I_1 and
Σ_{k≥2} I_k under full illumination) given to the two-step methods, so that the chart
shows the solvers' difference apart from the separation's bias.

Error (one number per fit): max(|Δσt|/σt, |Δσs|/σs, |Δg|). Coverage: how often the
reported 1σ uncertainties hold the truth (z = error/σ over repeats and parameters);
meaningful on the noisy capture, where the repeats draw new noise. Every fit runs ``repeats``
times; medians are reported (the machine may be shared: each record keeps the 1-minute
load average at its start). One untimed fit runs first, so that what all fits of a
capture this size share (the separation and the decay fit of σt, compiled on first use)
is warm for every timed one. Each fit is timed twice: ``total`` (split into ``compile``
and ``run``) is a cold fit, its compiled programs forgotten first
(:func:`lightfield_jax.clear_compiled`; no persistent XLA cache): the fit's own
programs compile (a fit in a new process pays the shared pieces too, about 2-3 s more
on this CPU: ``lightfield-jax bench --fits`` times that); ``warm`` is the same fit once more in
the same process, which reuses the compiled programs (what a second channel, the next
capture of a series or a sweep over seeds costs).

Speed-up at matched accuracy, two ways. (1) At the method's own accuracy: for a
method with error e and time t, the grid search's time to reach e is interpolated
log-log along its N-curve (the first density whose error is at most e, times
(1 + ``match_slack``)); if no density reaches e the ratio at the densest grid is a
lower bound (``>``), and an extrapolation (grid error ∝ 1/N through the densest grid,
grid time linear in N through the two densest) is given as an estimate. (2) At fixed
target errors (``match_errors``), for each method that reaches the target: the grid's
time to reach it (interpolated, else extrapolated) over the method's time. Speed-ups
are given for the cold wall time (compile included), its run time (compile excluded)
and the warm wall time. A grid
that holds the true g by chance (g = 0.4 is the 28th of 39 values) is exact there and
nowhere else: it is drawn apart and left out of the comparison.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
import warnings
from pathlib import Path
from typing import Annotated

import jax
import numpy as np

import lightfield_jax as lfj
from lightfield_jax.app.experiment import load_helper
from lightfield_jax.app.experiment_config import (
    Count,
    Dtype,
    Pixels,
    Positive,
    Range,
    check_choices,
    typed_config,
)
from lightfield_jax.app.experiment_records import pyplot, save_figure, write_csv
from lightfield_jax.inverse import two_step
from lightfield_jax.inverse.data import prepare_data
from lightfield_jax.runtime.timing import stopwatch

inv = load_helper("_inverse")

CAPTURES = ("noiseless", "noisy", "perfect_split")
# Times compared: a cold fit's wall time and its run time (compile excluded), and the
# wall time of the same fit again in the same process (compiled programs reused).
_PARTS = ("total", "run", "warm")
METHODS = ("grid", "gradient", "joint", "jaxopt_lm", "jaxopt_gn")
GridSize = Annotated[int, Range(2, 100_000)]  # g values of a grid search


@dataclasses.dataclass(frozen=True)
class Config:
    """configs/inverse_speed_accuracy.yaml: the capture (pixels, the medium, stripe
    period and lit width, gain, the noisy capture's noise), the captures and methods
    compared, the grid densities (``dense_g_grids``: perfect split only, run
    ``dense_repeats`` times, default ``repeats``), the solvers' coarse start and step
    limit, and the matched-accuracy slack and target errors."""

    dtype: Dtype
    width: Pixels
    height: Pixels
    medium: Annotated[dict, inv.MediumSpec]
    period: Annotated[int, Range(2, 1000)]
    lit: Count
    gain: Positive
    noise: dict
    captures: tuple[str, ...]
    g_grids: tuple[GridSize, ...]
    methods: tuple[str, ...]
    repeats: Annotated[int, Range(1, 1000)]
    start_grid: GridSize
    max_steps: Annotated[int, Range(1, 100_000)]
    match_slack: Annotated[float, Range(0)]
    match_errors: tuple[Annotated[float, Range(0, 1, open_low=True)], ...]
    dense_g_grids: tuple[GridSize, ...] = ()
    dense_repeats: Annotated[int, Range(1, 1000)] | None = None

    def __post_init__(self):
        name = "inverse_speed_accuracy"
        check_choices(name, "captures", self.captures, CAPTURES)
        check_choices(name, "methods", self.methods, METHODS)
        if not (self.captures and self.methods and self.g_grids):
            raise ValueError(f"{name}: captures, methods, g_grids: at least one each")
        # The captures as simulate checks them (the medium, stripes, gain, the noise).
        capture = inv.capture_config(
            self.medium,
            self.width,
            self.height,
            period=self.period,
            lit=self.lit,
            noise=self.noise,
            gain=self.gain,
        )
        inv.check_simulation_config(capture, name)


def _repeats(config: Config, capture: str, label: str) -> int:
    """How often a fit runs: ``repeats``, or ``dense_repeats`` (default: the same) for
    the dense grids of the perfect split (minutes per fit; their time is run time,
    which varies little)."""
    dense = label.startswith("grid-") and int(label.split("-")[1]) in set(
        config.dense_g_grids
    ) - set(config.g_grids)
    if dense and capture == "perfect_split":
        dense_repeats = config.repeats if config.dense_repeats is None else config.dense_repeats
        return min(dense_repeats, config.repeats)
    return config.repeats


def _labels(config: Config, capture: str) -> list[str]:
    out = []
    for m in config.methods:
        if m == "grid":
            dense = config.dense_g_grids if capture == "perfect_split" else ()
            out += [f"grid-{n}" for n in sorted(set(config.g_grids) | set(dense))]
        elif not (m == "joint" and capture == "perfect_split"):
            out.append(m.replace("_", "-"))
    return out


# ------------------------------------------------------------------------ jaxopt


def _import_jaxopt():
    """jaxopt, imported here only: it is unmaintained and warns on import."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="JAXopt is no longer maintained")
        try:
            import jaxopt
        except ImportError:
            raise ImportError(
                "methods: jaxopt_lm / jaxopt_gn need jaxopt: pip install -e '.[experiments]'"
            ) from None
    return jaxopt


def _jaxopt_run(solver: str, max_steps: int, renderer, sigma_t, d, m, mask, gs, scale):
    """The two-step problem in jaxopt: the package's search over ``gs`` and its start,
    then jaxopt's solver on the package's two-step residual in the package's
    parametrisation (:mod:`lightfield_jax.inverse.two_step`)."""
    jaxopt = _import_jaxopt()
    s_all, cost = two_step.search_g(renderer, sigma_t, d, m, mask, gs, "paper")
    start = two_step.search_start(gs, s_all, cost, sigma_t, "paper")
    slope = two_step.rendered_and_g_slope(renderer, sigma_t, "paper")

    def residual(y):
        p = two_step.to_params(y, sigma_t, "paper")
        return two_step.two_step_residual(slope, sigma_t, d, m, mask, scale, "paper", p)[0]

    if solver == "lm":
        opt = jaxopt.LevenbergMarquardt(
            residual_fun=residual,
            maxiter=max_steps,
            stop_criterion="madsen-nielsen",
            xtol=1e-5,
            gtol=1e-12,
            solver="cholesky",
            materialize_jac=True,
        )
    else:
        opt = jaxopt.GaussNewton(residual_fun=residual, maxiter=max_steps, tol=1e-4)
    sol = opt.run(start)
    s, g = two_step.to_params(sol.params, sigma_t, "paper")
    return s, g, sol.state.iter_num, sol.state.error


# Compiled once per (solver, step limit) and shapes: jit's own cache, no hand-made one.
_jaxopt_jitted = jax.jit(_jaxopt_run, static_argnames=("solver", "max_steps"))


def jaxopt_two_step(images, pattern, model: dict, solver: str, split, config: Config) -> dict:
    """The ``gradient`` method's two-step problem solved by jaxopt (``lm`` or ``gn``).

    Same pieces as the package's two-step solve (:mod:`lightfield_jax.inverse.two_step`): σt
    from the decay of D, the model size the package chose (``model``: crop, θ bins,
    refinement, bounces), the residual (M − a Σ_{k≥2} σs^{k−1} I_k)/rms(M) with the gain
    from the single scatter, the parametrisation (σs = σs_max(g)·sigmoid(y₀),
    g = tanh(y₁)) and the start (the vertex through the best of ``start_grid`` values of
    g). Tolerances: LM stops on a relative step below 1e-5 (optimistix's rtol for
    float32), Gauss-Newton on a gradient norm below 1e-4; both at ``max_steps``.
    """
    load = os.getloadavg()[0]
    t_start = time.perf_counter()
    data = prepare_data(images, pattern, black_level=0.0, split=split)
    data = data.cropped(tuple(model["crop"]))
    grid = lfj.Grid(*data.mask.shape[::-1], model["n_theta"], model["refine"])
    renderer = lfj.Renderer(grid, two_step.full_for(pattern), model["bounces"], "paper")
    args = two_step.problem_arrays(data, renderer, config.start_grid)
    with warnings.catch_warnings(), stopwatch() as timing:
        warnings.filterwarnings("ignore", category=DeprecationWarning, module="jaxopt")
        out = _jaxopt_jitted(solver, config.max_steps, *args)
        s, g, iters, err = jax.block_until_ready(out)
    total = time.perf_counter() - t_start
    iters = int(iters)
    values = {"sigma_t": data.sigma_t0, "sigma_s": float(s), "g": float(g)}
    finite = all(math.isfinite(v) for v in values.values())
    return {
        **values,
        "finite": finite,
        "converged": finite and iters < config.max_steps,
        "message": f"jaxopt {solver}: {iters} iterations, stop error {float(err):.3g}",
        "iterations": iters,
        "seconds": {"compile": timing.compile, "run": total - timing.compile, "total": total},
        "model": model,
        "load_avg": load,
    }


# ------------------------------------------------------------------------ the runs


class _Captures:
    """The captures, rendered on first use only (a resumed run may need none)."""

    def __init__(self, config: Config):
        self.config = config
        self._sims: dict = {}

    def get(self, name: str, repeat: int):
        key = (name, repeat if name == "noisy" else 0)
        if key not in self._sims:
            c = self.config
            noise = None
            if name == "noisy":
                noise = {**c.noise, "seed": int(c.noise.get("seed", 0)) + repeat}
            cfg = inv.capture_config(
                c.medium,
                c.width,
                c.height,
                period=c.period,
                lit=c.lit,
                noise=noise,
                gain=c.gain,
            )
            self._sims[key] = inv.simulate(cfg)
        sim = self._sims[key]
        split = inv.perfect_split(sim) if name == "perfect_split" else None
        return sim, split


def _one(config, captures, capture, label, repeat, records) -> dict:
    """One fit, cold (compiled programs forgotten first), then warm (the same fit again
    in this process): the cold record with ``seconds["warm"]``, the warm fit's wall
    time, and ``warm_same``, whether it gave the same values."""
    lfj.clear_compiled()
    cold = _fit_once(config, captures, capture, label, repeat, records)
    warm = _fit_once(config, captures, capture, label, repeat, records)
    cold["seconds"]["warm"] = warm["seconds"]["total"]
    cold["warm_same"] = all(cold.get(k) == warm.get(k) for k in inv.PARAMS)
    return cold


def _fit_once(config, captures, capture, label, repeat, records) -> dict:
    truth = inv.truth_of(config.medium)
    sim, split = captures.get(capture, repeat)
    pattern = sim.config.illumination
    if label.startswith("jaxopt"):
        model = records[(capture, "gradient", repeat)]["model"]
        rec = jaxopt_two_step(sim.images, pattern, model, label[-2:], split, config)
        rec["errors"] = inv.errors(rec, truth)
        return rec
    method, _, n = label.partition("-")
    extra = {"g_grid": int(n)} if n else {}
    return inv.fit_record(
        sim.images,
        pattern,
        truth,
        black_level=0.0,
        method=method,
        split=split,
        start_grid=config.start_grid,
        max_steps=config.max_steps,
        **extra,
    )


def _matched(grid_pts, err, slack) -> dict:
    """The grid search's time to reach error ``err``: interpolated log-log along its
    N-curve (``reached``), else a lower bound (its densest grid) and an extrapolation
    (error ∝ 1/N and time linear in N through the two densest grids)."""
    pts = sorted(grid_pts)  # by N
    target = err * (1 + slack)
    for i, (_n, e, t) in enumerate(pts):
        if e <= target:
            if i == 0 or pts[i - 1][1] <= e or e <= 0:
                return {"grid_seconds": t, "how": "reached"}
            _n0, e0, t0 = pts[i - 1]
            f = (math.log(e0) - math.log(target)) / (math.log(e0) - math.log(e))
            t_grid = math.exp(math.log(t0) + f * (math.log(t) - math.log(t0)))
            return {"grid_seconds": t_grid, "how": "reached"}
    out = {"grid_seconds": pts[-1][2], "how": "bound"}
    # Extrapolate only a falling curve: a flat one sits on a floor (the separation's
    # bias) that no density gets below.
    if len(pts) >= 2 and err > 0 and pts[-1][1] < 0.8 * pts[-2][1]:
        (n1, _e1, t1), (n2, e2, t2) = pts[-2], pts[-1]
        n_star = e2 * n2 / target
        out["extrapolated_seconds"] = t2 + (t2 - t1) / (n2 - n1) * max(n_star - n2, 0.0)
        out["extrapolated_n"] = n_star
    return out


def _coverage(recs, truth) -> dict | None:
    """How well the reported 1σ uncertainties describe the errors: z = error / σ over
    repeats and parameters; fractions within 1σ and 2σ (0.68 and 0.95 if honest)."""
    z = [
        (x[k] - truth[k]) / x["uncertainty"][k]
        for x in recs
        for k in inv.PARAMS
        if x.get("uncertainty") and x["uncertainty"].get(k) and x.get(k) is not None
    ]
    if not z:
        return None
    a = np.abs(z)
    return {
        "n": len(z),
        "within_1_sigma": float(np.mean(a <= 1)),
        "within_2_sigma": float(np.mean(a <= 2)),
        "median_abs_z": float(np.median(a)),
    }


def _at_targets(rows, grid_pts, targets) -> dict:
    """Speed-up over the grid search at fixed accuracies: for each target error that a
    method reaches, the grid's time to reach it (interpolated, else extrapolated) over
    the method's time."""
    out = {}
    for lb, v in rows.items():
        if lb.startswith("grid-") or not grid_pts["total"]:
            continue
        per = {}
        for target in targets:
            if v["errors"]["error"] > target:
                per[str(target)] = None  # the method itself does not reach it
                continue
            entry = {}
            for part in _PARTS:
                m = _matched(grid_pts[part], target, 0.0)
                if m["how"] == "bound" and "extrapolated_seconds" not in m:
                    entry = {"grid": "never: its error does not fall with N (a floor)"}
                    break
                t_grid = m.get("extrapolated_seconds", m["grid_seconds"])
                how = m["how"] if m["how"] == "reached" else "extrapolated"
                entry[part] = t_grid / v["seconds"][part]
                entry[f"grid_{part}_seconds"] = t_grid
                entry["grid"] = how + (
                    f" (N~{m['extrapolated_n']:.0f})" if "extrapolated_n" in m else ""
                )
            per[str(target)] = entry
        out[lb] = per
    return out


def _on_grid(g: float, n: int) -> bool:
    """Whether the grid method's N values of g (linspace(−0.95, 0.95, N)) include g."""
    return bool(np.min(np.abs(np.linspace(-0.95, 0.95, n) - g)) < 1e-6)


def _aggregate(config, records, labels_by_capture):
    agg = {}
    for capture, labels in labels_by_capture.items():
        rows = {}
        for label in labels:
            recs = [records[(capture, label, r)] for r in range(_repeats(config, capture, label))]
            rows[label] = {
                "errors": {
                    k: inv.median(x["errors"][k] for x in recs)
                    for k in ("sigma_t", "sigma_s", "g", "error")
                },
                "abs_errors": {
                    k: inv.median(abs(x["errors"][k]) for x in recs if x["errors"][k] is not None)
                    for k in ("sigma_t", "sigma_s", "g")
                },
                "seconds": {
                    k: inv.median(x["seconds"][k] for x in recs)
                    for k in ("compile", "run", "total", "warm")
                },
                "converged": sum(bool(x["converged"]) for x in recs),
                "repeats": len(recs),
                "iterations": inv.median(x.get("iterations", math.nan) for x in recs),
                "load_avg": inv.median(x.get("load_avg", math.nan) for x in recs),
                "coverage": _coverage(recs, inv.truth_of(config.medium)),
            }
        truth_g = float(config.medium["g"])
        for lb, v in rows.items():
            if lb.startswith("grid-"):
                v["truth_on_grid"] = _on_grid(truth_g, int(lb.split("-")[1]))
        # A grid that holds the true g by chance is exact there and nowhere else: it is
        # left out of the matched-accuracy comparison.
        grid_pts = {
            part: [
                (int(lb.split("-")[1]), v["errors"]["error"], v["seconds"][part])
                for lb, v in rows.items()
                if lb.startswith("grid-") and not v["truth_on_grid"]
            ]
            for part in _PARTS
        }
        speedups = {}
        for lb, v in rows.items():
            if lb.startswith("grid-") or not grid_pts["total"]:
                continue
            sp = {}
            for part in _PARTS:
                m = _matched(grid_pts[part], v["errors"]["error"], config.match_slack)
                t = v["seconds"][part]
                m["method_seconds"] = t
                m["speedup"] = m["grid_seconds"] / t
                if "extrapolated_seconds" in m:
                    m["extrapolated_speedup"] = m["extrapolated_seconds"] / t
                sp[part] = m
            speedups[lb] = sp
        agg[capture] = {
            "methods": rows,
            "speedup_vs_grid": speedups,
            "speedup_at_targets": _at_targets(rows, grid_pts, config.match_errors),
        }
    return agg


def run(raw: dict, out: Path, ctx) -> dict:
    config = typed_config(Config, raw)
    captures = _Captures(config)
    labels_by_capture = {c: _labels(config, c) for c in config.captures}
    records: dict = {}
    tag = (
        f"lib{inv.library_fingerprint()}|{config.dtype}|"
        f"{config.width}x{config.height}|{config.medium}|"
        f"p{config.period}/{config.lit}|gain{config.gain}|noise{config.noise}|"
        f"start{config.start_grid}|steps{config.max_steps}"
    )
    with inv.precision(config.dtype):
        # One untimed fit first: what every fit of a capture this size shares (the
        # separation and the decay fit of σt, compiled on first use) is then warm for
        # all, and the first timed fit does not pay for it alone.
        first = config.captures[0]
        _fit_once(config, captures, first, f"grid-{min(config.g_grids)}", 0, records)
        for repeat in range(config.repeats):
            for capture, labels in labels_by_capture.items():
                todo = list(labels)
                if any(lb.startswith("jaxopt") for lb in todo) and "gradient" not in todo:
                    todo.insert(0, "gradient")  # the model size jaxopt reuses
                for label in todo:
                    if repeat >= _repeats(config, capture, label):
                        continue
                    ctx.progress(f"repeat {repeat + 1}/{config.repeats}: {capture}, {label}")
                    key = f"{tag}|{capture}|{label}|{repeat}"
                    records[(capture, label, repeat)] = ctx.cached(
                        key,
                        lambda c=capture, lb=label, r=repeat: inv.jsonable(
                            _one(config, captures, c, lb, r, records)
                        ),
                    )
    agg = _aggregate(config, records, labels_by_capture)
    _write_csv(out / "speed_accuracy.csv", records, labels_by_capture, config)
    ctx.write_json(
        "speed_accuracy.json",
        inv.jsonable(
            {
                "truth": inv.truth_of(config.medium),
                "aggregate": agg,
                "records": [
                    {"capture": c, "method": lb, "repeat": r, **rec}
                    for (c, lb, r), rec in records.items()
                ],
            }
        ),
    )
    figures = _plot(config, agg, records, labels_by_capture, out)
    return inv.jsonable(
        {
            "figures": figures,
            "data": ["speed_accuracy.json", "speed_accuracy.csv"],
            "timing_note": (
                "medians over repeats; the machine may have been shared (load_avg per record)"
            ),
            "library_fingerprint": inv.library_fingerprint(),
            "captures": {
                c: {
                    "methods": {
                        lb: {
                            "error": v["errors"]["error"],
                            "sigma_t": v["errors"]["sigma_t"],
                            "sigma_s": v["errors"]["sigma_s"],
                            "g": v["errors"]["g"],
                            "compile_s": v["seconds"]["compile"],
                            "run_s": v["seconds"]["run"],
                            "total_s": v["seconds"]["total"],
                            "warm_s": v["seconds"]["warm"],
                            "converged": f"{v['converged']}/{v['repeats']}",
                            "coverage": v["coverage"],
                        }
                        for lb, v in a["methods"].items()
                    },
                    "speedup_vs_grid": {
                        lb: {part: _speedup_text(s) for part, s in sp.items()}
                        for lb, sp in a["speedup_vs_grid"].items()
                    },
                    "speedup_at_target_error": {
                        lb: {
                            t: None
                            if e is None
                            else e["grid"]
                            if "total" not in e
                            else (
                                f"{e['total']:.2f}x cold wall, {e['run']:.2f}x cold run, "
                                f"{e['warm']:.2f}x warm wall; grid {e['grid']}"
                            )
                            for t, e in per.items()
                        }
                        for lb, per in a["speedup_at_targets"].items()
                    },
                }
                for c, a in agg.items()
            },
        }
    )


def _speedup_text(s: dict) -> str:
    if s["how"] == "reached":
        return f"{s['speedup']:.2f}x"
    text = f">{s['speedup']:.2f}x (no grid reached it)"
    if "extrapolated_speedup" in s:
        text += f", ~{s['extrapolated_speedup']:.1f}x extrapolated (N~{s['extrapolated_n']:.0f})"
    return text


def _write_csv(path: Path, records, labels_by_capture, config) -> None:
    cols = [
        "capture",
        "method",
        "repeat",
        "sigma_t",
        "sigma_s",
        "g",
        "err_sigma_t",
        "err_sigma_s",
        "err_g",
        "error",
        "compile_s",
        "run_s",
        "total_s",
        "warm_s",
        "converged",
        "iterations",
        "load_avg",
    ]

    def rows():
        for capture, labels in labels_by_capture.items():
            for label in labels:
                for r in range(_repeats(config, capture, label)):
                    x = records[(capture, label, r)]
                    e = x["errors"]
                    yield (
                        [
                            capture,
                            label,
                            r,
                            x.get("sigma_t"),
                            x.get("sigma_s"),
                            x.get("g"),
                            e["sigma_t"],
                            e["sigma_s"],
                            e["g"],
                            e["error"],
                            x["seconds"]["compile"],
                            x["seconds"]["run"],
                            x["seconds"]["total"],
                            x["seconds"]["warm"],
                            x["converged"],
                            x.get("iterations"),
                            x.get("load_avg"),
                        ]
                    )

    write_csv(path, cols, rows())


# ------------------------------------------------------------------------ figures

_STYLE = {
    "gradient": ("tab:blue", "o"),
    "joint": ("tab:green", "s"),
    "jaxopt-lm": ("tab:purple", "^"),
    "jaxopt-gn": ("tab:brown", "v"),
}
_PART_LABELS = {
    "total": "cold wall time",
    "run": "cold run time (no compile)",
    "warm": "warm wall time (compiled)",
}
_TITLES = {
    "noiseless": "noiseless capture",
    "noisy": "noisy capture (photons + read)",
    "perfect_split": "perfect split (solver only)",
}


def _plot(config, agg, records, labels_by_capture, out: Path) -> list[str]:

    plt = pyplot()

    floor = 1e-7  # errors below this are drawn at it (log axes)
    caps = list(agg)
    names = []

    fig, axes = plt.subplots(3, len(caps), figsize=(4.6 * len(caps), 11.0), squeeze=False)
    for j, c in enumerate(caps):
        rows = agg[c]["methods"]
        for i, part in enumerate(_PARTS):
            ax = axes[i, j]
            grid = sorted(
                ((int(lb.split("-")[1]), v) for lb, v in rows.items() if lb.startswith("grid-")),
                key=lambda t: t[0],
            )
            if grid:
                curve = [(n, v) for n, v in grid if not v["truth_on_grid"]]
                ts = [v["seconds"][part] for _, v in curve]
                es = [max(v["errors"]["error"], floor) for _, v in curve]
                ax.plot(ts, es, "-", color="tab:red", marker="D", label="grid (N values of g)")
                for n, v in grid:
                    t, e = v["seconds"][part], max(v["errors"]["error"], floor)
                    if v["truth_on_grid"]:
                        ax.plot(t, e, "D", mfc="none", color="tab:red", label="grid holding true g")
                    ax.annotate(
                        str(n),
                        (t, e),
                        textcoords="offset points",
                        xytext=(4, 4),
                        fontsize=7,
                        color="tab:red",
                    )
            for lb, v in rows.items():
                if lb.startswith("grid-"):
                    continue
                color, marker = _STYLE.get(lb, ("k", "x"))
                ax.plot(
                    v["seconds"][part],
                    max(v["errors"]["error"], floor),
                    marker,
                    color=color,
                    ms=8,
                    ls="none",
                    label=lb,
                )
            inv.log_axes(ax)
            ax.grid(True, which="both", alpha=0.3)
            ax.set_xlabel(f"{_PART_LABELS[part]} per fit [s]")
            ax.set_ylabel("error: max(|Δσt|/σt, |Δσs|/σs, |Δg|)")
            ax.set_title(f"{_TITLES[c]}: {_PART_LABELS[part]}", fontsize=9)
            if i == 0 and j == 0:
                ax.legend(fontsize=7)
    fig.suptitle(
        f"Paper's milk {config.width}×{config.height}, {config.period}-px stripes: "
        f"error vs time (median of {config.repeats})",
        fontsize=10,
    )
    fig.tight_layout()
    name = "speed_accuracy.png"
    save_figure(fig, out / name, dpi=120)
    names.append(name)

    fig, axes = plt.subplots(3, len(caps), figsize=(4.6 * len(caps), 9.5), squeeze=False)
    for j, c in enumerate(caps):
        rows = agg[c]["methods"]
        for i, (k, what) in enumerate(
            (("sigma_t", "|Δσt|/σt"), ("sigma_s", "|Δσs|/σs"), ("g", "|Δg|"))
        ):
            ax = axes[i, j]
            for lb, v in rows.items():
                color, marker = (
                    ("tab:red", "D") if lb.startswith("grid-") else _STYLE.get(lb, ("k", "x"))
                )
                ax.plot(
                    v["seconds"]["total"],
                    max(v["abs_errors"][k], floor),
                    marker,
                    color=color,
                    ls="none",
                    label=None if lb.startswith("grid-") else lb,
                )
                if lb.startswith("grid-"):
                    ax.annotate(
                        lb[5:],
                        (v["seconds"]["total"], max(v["abs_errors"][k], floor)),
                        textcoords="offset points",
                        xytext=(3, 3),
                        fontsize=6,
                    )
            inv.log_axes(ax)
            ax.grid(True, which="both", alpha=0.3)
            ax.set_ylabel(what)
            if i == 0:
                ax.set_title(_TITLES[c], fontsize=9)
            if i == 2:
                ax.set_xlabel("wall time per fit [s]")
            if i == 0 and j == 0:
                ax.legend(fontsize=7)
    fig.tight_layout()
    name = "errors_by_parameter.png"
    save_figure(fig, out / name, dpi=110)
    names.append(name)

    fig, axes = plt.subplots(1, len(caps), figsize=(4.6 * len(caps), 3.8), squeeze=False)
    for j, c in enumerate(caps):
        rows = agg[c]["methods"]
        ax = axes[0, j]
        labels = list(rows)
        comp = [rows[lb]["seconds"]["compile"] for lb in labels]
        runs = [rows[lb]["seconds"]["run"] for lb in labels]
        x = np.arange(len(labels))
        ax.bar(x, comp, color="tab:gray", label="compile")
        ax.bar(x, runs, bottom=comp, color="tab:orange", label="run")
        ax.set_xticks(x, labels, rotation=60, fontsize=7)
        ax.set_ylabel("seconds (median)")
        ax.set_title(_TITLES[c], fontsize=9)
        if j == 0:
            ax.legend(fontsize=7)
    fig.tight_layout()
    name = "time_split.png"
    save_figure(fig, out / name, dpi=110)
    names.append(name)
    return names
