"""Is the ``auto`` model size a safe default? Accuracy lost against time saved.

The fit sizes its model from the data (FitOptions defaults, ``auto``): bounces from
the tail bound ρ^K/(1 − ρ) ≤ tolerance at the starting estimate, θ bins (and spatial
refinement) from g, and a crop along the light to where the signal stands above the
noise. This experiment fits the same captures with that model and with a ``large``
fixed one (by default 128 θ bins, 40 bounces, no crop), per scene:

- ``gradient_split``: the two-step ``gradient`` method fed the perfect split of a
  noiseless capture: the model's own error, free of separation bias and noise;
- ``joint``: the default method on a noisy capture (photons and read noise relative to
  the brightest pixel), as a user runs it; on a Dask worker stopped after
  ``joint_timeout`` seconds (recorded as a timeout: too slow to be a usable default).

Truths are rendered finer than either model: at least ``truth.n_theta_min`` θ bins,
refinement from g, bounces from the tail bound at ``truth.tolerance``.

Per scene: error of each parameter (σt, σs relative; g absolute) with each model, the
accuracy ``auto`` loses (|error_auto| − |error_large|, positive = worse) and the time it
saves (t_large / t_auto, wall time including compilation). ``auto`` counts as safe for
a scene when it loses no more than ``safe`` per parameter and converges wherever the
large model does.
"""

from __future__ import annotations

import dataclasses
import math
import re
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
    fit_keywords,
    typed_config,
)
from lightfield_jax.app.experiment_records import pyplot, save_figure

inv = load_helper("_inverse")

METHODS = ("gradient_split", "joint")
MODELS = ("auto", "large")


@dataclasses.dataclass(frozen=True)
class TruthSpec:
    """The truth's finer model: its fewest θ bins, tail tolerance and bounce cap."""

    n_theta_min: Annotated[int, Range(8, 1024)]
    tolerance: Annotated[float, Range(0, 0.1, open_low=True)]
    max_bounces: Annotated[int, Range(1, 10_000)]


@dataclasses.dataclass(frozen=True)
class SafeSpec:
    """The largest accuracy ``auto`` may lose: σt, σs relative, g absolute."""

    sigma_t: Positive
    sigma_s: Positive
    g: Positive


@dataclasses.dataclass(frozen=True)
class Config:
    """configs/model_size.yaml: the captures (pixels; the joint fit's ``noise`` =
    (photons at the peak, read noise / peak) and ``seed``), the large model's
    :class:`~lightfield_jax.FitOptions` overrides, the truth's finer model, the
    methods and scenes compared, the accuracy ``auto`` may lose (``safe``) and the
    joint fit's time limit (s)."""

    dtype: Dtype
    width: Pixels
    height: Pixels
    noise: tuple[Annotated[float, Range(0)], ...]
    seed: Seed
    large: dict
    truth: Annotated[dict, TruthSpec]
    methods: tuple[str, ...]
    scenes: tuple[Annotated[dict, inv.NamedMedium], ...]
    safe: Annotated[dict, SafeSpec]
    joint_timeout: Annotated[float, Range(0, 86_400, open_low=True)]

    def __post_init__(self):
        check_choices("model_size", "methods", self.methods, METHODS)
        if len(self.noise) != 2 or not self.noise[0] > 0:
            raise ValueError(f"model_size: noise: [photons > 0, read >= 0], got {list(self.noise)}")
        if not (self.methods and self.scenes):
            raise ValueError("model_size: methods, scenes: at least one each")
        fit_keywords("model_size", "large", self.large)
        for i, scene in enumerate(self.scenes):  # each truth's capture, as simulate checks it
            capture = inv.capture_config(scene, self.width, self.height)
            inv.check_simulation_config(capture, f"model_size: scenes[{i}]")


def _truth(scene: dict, config: Config) -> lfj.SimulatedCapture:
    medium = lfj.Medium(scene["sigma_t"], scene["sigma_s"], scene["g"], scene.get("phase", "paper"))
    spec = config.truth
    k = lfj.bounces_for_tolerance(float(medium.rho), spec["tolerance"], max_bounces=100_000)
    cfg = inv.capture_config(
        scene,
        config.width,
        config.height,
        bounces=min(k, spec["max_bounces"]),
        n_theta=max(spec["n_theta_min"], lfj.default_n_theta(scene["g"])),
    )
    return inv.simulate(cfg)


def _fit(scene: dict, method: str, model: str, sim, config: Config) -> dict:
    truth = inv.truth_of(scene)
    peak = float(np.max(sim.images))
    options = dict(config.large) if model == "large" else {}
    options["phase"] = scene.get("phase", "paper")
    pattern = sim.config.illumination
    if method == "gradient_split":
        split = tuple(a / peak for a in inv.perfect_split(sim))
        images = inv.camera(sim.images, None, 0)
        rec = inv.fit_record(
            images, pattern, truth, method="gradient", black_level=0.0, split=split, **options
        )
    else:
        images = inv.camera(sim.images, tuple(config.noise), config.seed)
        rec = inv.fit_record_limited(
            images,
            pattern,
            truth,
            timeout=config.joint_timeout,
            dtype=config.dtype,
            xla_cache_dir=None,
            method="joint",
            black_level=0.0,
            **options,
        )
    rec["truth_model"] = {"bounces": sim.n_bounces, "n_theta": sim.n_theta, "refine": sim.refine}
    return inv.jsonable(rec)


def _compare(recs: dict, safe: dict) -> dict:
    """What ``auto`` loses against ``large`` and the time it saves. Without a large
    result (timeout, exception) auto is judged against the truth instead: it must
    converge with errors within ``safe``; the speed-up is then a lower bound."""
    auto, large = recs["auto"], recs["large"]
    lost = {}
    for k in inv.PARAMS:
        a, b = auto["errors"][k], large["errors"][k]
        lost[k] = None if a is None or b is None else abs(a) - abs(b)
    t_a, t_l = auto["seconds"]["total"], large["seconds"]["total"]
    if auto["errors"]["error"] is None:
        safe_here, basis = False, "auto gave no result"
    elif large["errors"]["error"] is None:
        within = all(abs(auto["errors"][k]) <= safe[k] for k in inv.PARAMS)
        safe_here, basis = within and auto["converged"], "against the truth (large: no result)"
    else:
        within = all(v <= safe[k] for k, v in lost.items())
        safe_here = within and (auto["converged"] or not large["converged"])
        basis = "against the large model"
    return {
        "accuracy_lost": lost,
        "speedup": t_l / t_a if t_a else math.nan,
        "speedup_is_bound": large["errors"]["error"] is None,
        "seconds_saved": t_l - t_a,
        "safe": bool(safe_here),
        "judged": basis,
        "auto_model": auto.get("model"),
        "large_model": large.get("model"),
    }


def run(raw: dict, out: Path, ctx) -> dict:
    config = typed_config(Config, raw)
    records: dict = {}
    with inv.precision(config.dtype):
        for scene in config.scenes:
            sims: dict = {}

            def sim(scene=scene, sims=sims):
                if "sim" not in sims:
                    sims["sim"] = _truth(scene, config)
                return sims["sim"]

            for method in config.methods:
                for model in MODELS:
                    ctx.progress(f"{scene['name']}: {method}, {model} model")
                    key = (
                        f"lib{inv.library_fingerprint()}|{config.dtype}|"
                        f"{config.width}x{config.height}|{scene}|"
                        f"{method}|{model}|{config.large if model == 'large' else ''}|"
                        f"{config.truth}|{list(config.noise)}|{config.seed}"
                    )
                    records[(scene["name"], method, model)] = ctx.cached(
                        key,
                        lambda s=scene, m=method, mo=model: _fit(s, m, mo, sim(s), config),
                    )
    comparison = {
        method: {
            s["name"]: _compare(
                {mo: records[(s["name"], method, mo)] for mo in MODELS}, config.safe
            )
            for s in config.scenes
        }
        for method in config.methods
    }
    ctx.write_json(
        "model_size.json",
        inv.jsonable(
            {
                "comparison": comparison,
                "records": [  # size: auto or large; model: the model the fit used
                    {"scene": s, "method": m, "size": mo, **r} for (s, m, mo), r in records.items()
                ],
            }
        ),
    )
    figure = _plot(config, records, comparison, out)
    speedups = [c["speedup"] for per in comparison.values() for c in per.values()]
    return inv.jsonable(
        {
            "figures": [figure],
            "data": ["model_size.json"],
            "auto_safe": all(c["safe"] for per in comparison.values() for c in per.values()),
            "unsafe": [
                f"{m}/{s}" for m, per in comparison.items() for s, c in per.items() if not c["safe"]
            ],
            "median_speedup": inv.median(speedups),
            "per_scene": {
                m: {
                    s: {
                        "accuracy_lost": c["accuracy_lost"],
                        "speedup": c["speedup"],
                        "speedup_is_bound": c["speedup_is_bound"],
                        "safe": c["safe"],
                        "judged": c["judged"],
                        "auto_model": _short(c["auto_model"]),
                        "errors": {mo: records[(s, m, mo)]["errors"] for mo in MODELS},
                        "seconds": {mo: records[(s, m, mo)]["seconds"]["total"] for mo in MODELS},
                        "converged": {mo: records[(s, m, mo)]["converged"] for mo in MODELS},
                    }
                    for s, c in per.items()
                }
                for m, per in comparison.items()
            },
            "timing_note": "one fit each; the machine may have been shared (load_avg per record)",
            "library_fingerprint": inv.library_fingerprint(),
        }
    )


def _short(model: dict | None) -> str | None:
    if not model:
        return None
    crop = model["crop"]
    return (
        f"{model['bounces']} bounces, {model['n_theta']} θ, refine {model['refine']}, "
        f"{crop[2] - crop[0]}×{crop[3] - crop[1]} px"
    )


_METHOD_TEXT = {
    "gradient_split": "gradient fed the perfect split, noiseless (the model's own error)",
    "joint": "joint on a noisy capture (as a user runs it)",
}


def _no_result(rec: dict) -> str:
    """Why a fit gave no values, shortly (timeout, auto's refusal, an exception)."""
    msg = str(rec.get("error_message") or "no result")
    if rec.get("timeout"):
        return "timeout"
    found = re.search(r"auto needs (\d+) bounces for rho = ([0-9.]+)", msg)
    if found:
        return f"auto refused: needs\n{found[1]} bounces (ρ {float(found[2]):.3g})"
    return msg.split(":")[0][:20]


def _plot(config, records, comparison, out: Path) -> str:
    from matplotlib.patches import Patch

    plt = pyplot()

    methods = config.methods
    scenes = [s["name"] for s in config.scenes]
    fig, axes = plt.subplots(len(methods), 2, figsize=(13, 1.4 + 4.4 * len(methods)), squeeze=False)
    x = np.arange(len(scenes))
    colors = {"auto": "tab:blue", "large": "tab:gray"}
    hatches = {"sigma_t": "", "sigma_s": "//", "g": ".."}
    floor = 1e-7
    for i, method in enumerate(methods):
        ax = axes[i, 0]
        for j, k in enumerate(hatches):
            for mo, dx in (("auto", -0.2), ("large", 0.2)):
                vals = [records[(s, method, mo)]["errors"][k] for s in scenes]
                ys = [max(abs(v), floor) if v is not None else 0.0 for v in vals]
                ax.bar(
                    x + dx + (j - 1) * 0.12,
                    ys,
                    0.12,
                    color=colors[mo],
                    hatch=hatches[k],
                    edgecolor="k",
                    lw=0.3,
                )
        for xi, s in zip(x, scenes, strict=True):
            for mo, dx in (("auto", -0.2), ("large", 0.2)):
                rec = records[(s, method, mo)]
                if rec["errors"]["error"] is None:
                    ax.text(
                        xi + dx,
                        3 * floor,
                        _no_result(rec),
                        rotation=90,
                        ha="center",
                        va="bottom",
                        fontsize=7,
                        color="tab:red",
                    )
        ax.set_yscale("log")
        ax.set_ylim(floor, 3.0)
        ax.set_xticks(x, scenes, rotation=15, fontsize=8)
        ax.set_ylabel(f"|error|: σt, σs relative, g absolute (floor {floor:g})", fontsize=8)
        ax.set_title(f"{method}: accuracy — {_METHOD_TEXT.get(method, method)}", fontsize=9)
        ax.grid(True, axis="y", which="major", alpha=0.3)
        handles = [Patch(color=c, label=f"{mo} model") for mo, c in colors.items()]
        handles += [
            Patch(facecolor="w", edgecolor="k", hatch=h, label=k.replace("sigma_", "σ"))
            for k, h in hatches.items()
        ]
        ax.legend(handles=handles, fontsize=7, ncol=5, loc="upper left")
        ax = axes[i, 1]
        for mo, dx in (("auto", -0.2), ("large", 0.2)):
            t = [records[(s, method, mo)]["seconds"]["total"] for s in scenes]
            ax.bar(x + dx, t, 0.4, color=colors[mo], label=f"{mo} model")
        for xi, s in zip(x, scenes, strict=True):
            c = comparison[method][s]
            top = max(records[(s, method, mo)]["seconds"]["total"] for mo in ("auto", "large"))
            if records[(s, method, "auto")]["errors"]["error"] is None:
                text = "auto:\nno result"
            else:
                text = ("≥" if c["speedup_is_bound"] else "") + f"×{c['speedup']:.1f}"
                text += "" if c["safe"] else "\nunsafe"
            ax.annotate(
                text,
                (xi, top),
                xytext=(0, 2),
                textcoords="offset points",
                ha="center",
                va="bottom",
                fontsize=8,
                color="k" if c["safe"] else "tab:red",
            )
        inv.log_axes(ax, x=False)
        lo, hi = ax.get_ylim()
        ax.set_ylim(lo, hi * 6)
        ax.set_xticks(x, scenes, rotation=15, fontsize=8)
        ax.set_ylabel(
            "wall time per fit [s] (compilation included; a timeout: the limit)", fontsize=8
        )
        ax.set_title(
            f"{method}: time (×: large time / auto time; unsafe: auto lost more than allowed)",
            fontsize=9,
        )
        ax.legend(fontsize=7, loc="upper left")
        ax.grid(True, axis="y", which="major", alpha=0.3)
    lg, tr, sf = config.large, config.truth, config.safe
    parts = [
        f"{s['name']} σt {s['sigma_t']:g}, σs {s['sigma_s']:g}, g {s['g']:g}"
        + (f" ({s['phase']} phase)" if s.get("phase") else "")
        for s in config.scenes
    ]
    scene_text = ";\n".join("; ".join(parts[i : i + 3]) for i in range(0, len(parts), 3))
    photons, read = config.noise
    loads = [r.get("load_avg") for r in records.values() if r.get("load_avg") is not None]
    load_text = f"; load average {min(loads):.0f}–{max(loads):.0f} on this machine" if loads else ""
    fig.suptitle(
        f"The auto model (FitOptions defaults) against a large fixed one ({lg.get('n_theta')} θ "
        f"bins, {lg.get('bounces')} bounces, crop {lg.get('crop')}), "
        f"{config.width}×{config.height} px six-shift captures (period 6), "
        f"{config.dtype}\n"
        f"truth rendered with ≥ {tr['n_theta_min']} θ bins, bounces to tail {tr['tolerance']:g}; "
        f"joint's noise: {photons:g} photons at the peak, read {read:g} of the peak; "
        f"joint stopped after {config.joint_timeout:g} s{load_text}\n"
        f"safe: auto loses at most σt {sf['sigma_t']:g}, σs {sf['sigma_s']:g} (relative), "
        f"g {sf['g']:g} (absolute) against large\nscenes (σ in px⁻¹): " + scene_text,
        fontsize=9,
    )
    fig.tight_layout()
    name = "model_size.png"
    save_figure(fig, out / name, dpi=100)
    return name
