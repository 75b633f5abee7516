"""What do the coarse tail's later bounces cost and change, against the full march?

A plane renderer on a refined working grid (``refine`` 2) marches every bounce there;
with ``coarse_after`` = K0 (:func:`lightfield_jax.render`, ``renderer_for``) it marches
the first K0 bounces there and the later ones on the native grid (refine 1, the same θ
bins), whose images are repeated over each pixel's working cells. For each medium of
``media`` (its own bounce count K and θ bins from g, :meth:`Grid.resolve`), on one scene
(six-shift stripes from the left wall), it renders the full march (the reference: the
same grid and K, ``coarse_after`` None) and the coarse tail for each K0 of
``coarse_after``, and measures:

- error of the image of all orders Σ_k I_k against the full march's: max |Δ| / peak
  (``error_max``) and relative L1 (``error_l1``), over every pattern;
- ``bounce_deviation``: the largest relative deviation of the per-bounce image sums
  s_k (over patterns and pixels) from the full march's, over the bounces k > K0 (the
  first K0 are the renderer's own: ``explicit_deviation``, 0 up to rounding);
- time of one render: the first call (compile apart) and the median of ``repeats``
  steady calls (a first call running longer than 10 s is not repeated: its run time
  counts); speedup = full seconds / coarse seconds.

Everything in float32 (the package's default). The figure shows the error and the
speedup against K0 per medium; the JSON holds every number and call.
"""

from __future__ import annotations

import dataclasses
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


@dataclasses.dataclass(frozen=True)
class MediumSpec:
    """One medium: its name, σt, σs (per pixel), g and the bounces K of its march."""

    name: str
    sigma_t: Positive
    sigma_s: Annotated[float, Range(0)]
    g: Annotated[float, Range(-0.99, 0.99)]
    bounces: Annotated[int, Range(3, 1000)]


@dataclasses.dataclass(frozen=True)
class Config:
    """configs/coarse_tail.yaml: the grid (pixels, refinement), the stripes (period,
    lit rows), the phase convention, the media, the K0 values and the timing repeats
    (see the module's doc)."""

    width: Pixels
    height: Pixels
    refine: Annotated[int, Range(2, 4)]
    period: Annotated[int, Range(2, 64)]
    lit: Annotated[int, Range(1, 63)]
    phase: Literal["normalized", "paper"]
    media: tuple[Annotated[dict, MediumSpec], ...]
    coarse_after: tuple[Annotated[int, Range(2, 1000)], ...]
    repeats: Annotated[int, Range(1, 1000)]

    def __post_init__(self):
        if not (self.media and self.coarse_after):
            raise ValueError("coarse_tail: media, coarse_after: at least one each")
        names = [m["name"] for m in self.media]
        if len(set(names)) != len(names):
            raise ValueError(f"coarse_tail: media: names must differ, got {names}")
        for i, m in enumerate(self.media):
            try:  # the medium as run() builds it: its own checks
                lfj.Medium(m["sigma_t"], m["sigma_s"], m["g"], self.phase)
            except ValueError as e:
                raise ValueError(f"coarse_tail: media[{i}]: {e}") from None
            if max(self.coarse_after) >= m["bounces"]:
                raise ValueError(
                    f"coarse_tail: media[{i}].bounces: must exceed every coarse_after "
                    f"(max {max(self.coarse_after)}), got {m['bounces']}"
                )
        try:  # the grid and stripes as run() builds them: their own checks
            lfj.Grid(self.width, self.height, None, self.refine)
            lfj.Stripes.shifted(self.period, self.lit)
        except ValueError as e:
            raise ValueError(f"coarse_tail: {e}") from None


def _render(medium: lfj.Medium, grid, illumination, k: int, k0: int | None):
    """Per-bounce images (patterns, K, H, W) of the march, float64 on the host."""
    renderer = renderer_for(grid, illumination, k, medium.phase, None, coarse_after=k0)

    def call():
        images = renderer(medium.sigma_t, medium.sigma_s, medium.g)[0]
        return np.asarray(jax.block_until_ready(images), np.float64)

    return call


def _case(ctx, cfg: dict, spec: dict) -> list[dict]:
    """The rows of one medium: the full march, then the coarse tail for each K0."""
    medium = lfj.Medium(spec["sigma_t"], spec["sigma_s"], spec["g"], cfg["phase"])
    grid = lfj.Grid(cfg["width"], cfg["height"], None, cfg["refine"]).resolve(spec["g"])
    illumination = lfj.Stripes.shifted(cfg["period"], cfg["lit"])
    k = spec["bounces"]
    base = {
        "medium": spec["name"],
        "sigma_t": spec["sigma_t"],
        "sigma_s": spec["sigma_s"],
        "g": spec["g"],
        "albedo": float(medium.albedo),
        "bounces": k,
        "n_theta": grid.n_theta,
        "refine": grid.refine,
    }
    ctx.progress(f"{spec['name']}: full march, {k} bounces")
    timed = repeated_calls(_render(medium, grid, illumination, k, None), cfg["repeats"])
    images_ref = timed.pop("out")
    total_ref = images_ref.sum(axis=1)
    sums_ref = images_ref.sum(axis=(0, 2, 3))
    peak = float(total_ref.max())
    full = dict(base, coarse_after=None, peak=peak, **timed)
    full["share_per_bounce"] = (sums_ref / sums_ref.sum()).tolist()
    rows = [full]
    for k0 in cfg["coarse_after"]:
        ctx.progress(f"{spec['name']}: coarse_after {k0}")
        timed = repeated_calls(_render(medium, grid, illumination, k, k0), cfg["repeats"])
        images = timed.pop("out")
        delta = images.sum(axis=1) - total_ref
        sums = images.sum(axis=(0, 2, 3))
        deviation = np.abs(sums - sums_ref) / np.abs(sums_ref)
        rows.append(
            dict(
                base,
                coarse_after=k0,
                error_max=float(np.abs(delta).max() / peak),
                error_l1=float(np.abs(delta).sum() / np.abs(total_ref).sum()),
                bounce_deviation=float(deviation[k0:].max()),
                worst_bounce=int(np.argmax(deviation[k0:])) + k0 + 1,
                explicit_deviation=float(deviation[:k0].max()),
                share_after=float(sums_ref[k0:].sum() / sums_ref.sum()),
                speedup=full["seconds"] / timed["seconds"],
                **timed,
            )
        )
    return rows


def run(config: dict, out: Path, ctx) -> dict:
    typed_config(Config, config)  # every key checked before any work
    cfg = dict(config)
    rows = ctx.rows_per_medium(cfg, lambda spec: _case(ctx, cfg, spec))
    data = {
        "grid": {"width": cfg["width"], "height": cfg["height"], "refine": cfg["refine"]},
        "illumination": {
            "stripes": "left wall",
            "period": cfg["period"],
            "lit": cfg["lit"],
            "shifts": cfg["period"],
        },
        "phase": cfg["phase"],
        "media": cfg["media"],
        "coarse_after": cfg["coarse_after"],
        "repeats": cfg["repeats"],
        "dtype": "float32",
        "load_average_1min": os.getloadavg()[0],
        **provenance(),
        "rows": rows,
    }
    ctx.write_json("coarse_tail.json", data)
    figure = _plot(data, ctx.figure_path("coarse_tail.png"))
    return {
        "figure": str(figure),
        "table": [
            {
                k: r.get(k)
                for k in (
                    "medium",
                    "bounces",
                    "coarse_after",
                    "error_max",
                    "error_l1",
                    "bounce_deviation",
                    "seconds",
                    "speedup",
                )
            }
            for r in rows
        ],
    }


def _plot(data: dict, path: Path) -> Path:
    # Two panels: error of the image of all orders against K0, speedup against K0;
    # one colour per medium.
    fig = pyplot().figure(figsize=(11, 4.2), layout="constrained")
    ax_e, ax_s = fig.subplots(1, 2)
    for i, spec in enumerate(data["media"]):
        rows = [r for r in data["rows"] if r["medium"] == spec["name"]]
        coarse = [r for r in rows if r["coarse_after"] is not None]
        if not coarse:
            continue
        full = next(r for r in rows if r["coarse_after"] is None)
        x = [r["coarse_after"] for r in coarse]
        label = (
            f"{spec['name']} (σt {spec['sigma_t']}, σs {spec['sigma_s']}, g {spec['g']}; "
            f"K {spec['bounces']}, n_theta {full['n_theta']})"
        )
        ax_e.plot(x, [max(r["error_max"], 1e-9) for r in coarse], "o-", color=f"C{i}", label=label)
        ax_e.plot(x, [max(r["error_l1"], 1e-9) for r in coarse], "s--", color=f"C{i}")
        # speedup of the fastest steady calls (the least disturbed by other jobs)
        ax_s.plot(
            x,
            [min(full["times_s"]) / min(r["times_s"]) for r in coarse],
            "o-",
            color=f"C{i}",
            label=f"{spec['name']}: full {min(full['times_s']):.2f} s",
        )
    for ax in (ax_e, ax_s):
        ax.set_xscale("log", base=2)
        ax.set_xticks(data["coarse_after"], [str(k) for k in data["coarse_after"]])
        ax.minorticks_off()
        ax.set_xlabel("K0 = coarse_after (bounces on the refined grid)")
        ax.grid(True, which="both", alpha=0.3)
    ax_e.set_yscale("log")
    ax_e.set_ylabel("error of Σ_k I_k vs the full march")
    ax_e.set_title("error: max |Δ| / peak (solid), relative L1 (dashed)", fontsize=9)
    ax_s.set_ylabel("speedup: full / coarse seconds (fastest steady call)")
    ax_s.axhline(1.0, color="0.5", ls=":", lw=1)
    ax_s.set_title("speedup of one render", fontsize=9)
    ax_e.legend(fontsize=7)
    ax_s.legend(fontsize=7)
    grid, ill = data["grid"], data["illumination"]
    fig.suptitle(
        f"Coarse tail: bounces after K0 on the native grid vs all on the refined grid.\n"
        f"{grid['width']}×{grid['height']} px, refine {grid['refine']}, {ill['shifts']}-shift "
        f"period-{ill['period']} stripes from the left wall, {data['phase']} phase, float32; "
        f"{os.cpu_count()} cores, load {data['load_average_1min']:.1f}",
        fontsize=9,
    )
    return save_figure(fig, path)
