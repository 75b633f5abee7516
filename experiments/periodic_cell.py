"""What does rendering stripes from one period cost and change, against every shift?

For each medium of ``media`` (its θ bins and refinement from g, :meth:`Grid.resolve`),
on six-shift stripes entering the left wall, it renders the full-domain render of every
shift (:class:`lightfield_jax.forward.plane.PlaneRenderer`, the reference) and the
stripe cell (:class:`lightfield_jax.CellRenderer`) with each ``shift_orders`` (the orders
whose walls' term is every shift's own; ``all``: every order's),
and measures, on the image of all orders Σ_k I_k:

- ``row_error``: per row, max over shifts and columns of |Δ| over the row's largest
  value; ``row_error_max`` its worst row, ``row_error_walls`` the worst of the two rows
  next to the walls, ``row_error_middle`` the worst of the middle half;
- ``order_error``: per order k, max |ΔI_k| / max I_k (I_1 and I_2 are exact);
- time of one render (first call, then the median and the least of ``repeats`` steady
  calls) and ``speedup`` = full seconds / cell seconds of the medians,
  ``speedup_fastest`` of the least (on a shared machine, the calls least slowed);
  ``speedup_every_fastest`` the same against the full render marching every shift (the
  full render marches fewer shifts and full light where that is exact,
  :mod:`lightfield_jax.forward.pattern_basis`; this was the full render before that).

Everything in float32 (the package's default).
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
from lightfield_jax.forward.pattern_basis import working_moments
from lightfield_jax.forward.plane import PlaneRenderer
from lightfield_jax.runtime.timing import repeated_calls


@dataclasses.dataclass(frozen=True)
class MediumSpec:
    """One medium: its name, σt, σs (per pixel), g, the bounces K and the stripes'
    heading."""

    name: str
    sigma_t: Positive
    sigma_s: Annotated[float, Range(0)]
    g: Annotated[float, Range(-0.99, 0.99)]
    bounces: Annotated[int, Range(3, 1000)]
    direction_deg: Annotated[float, Range(-60, 60)] = 0.0


@dataclasses.dataclass(frozen=True)
class CellSpec:
    """One stripe cell: the orders whose walls' term is every shift's own (``all``: every
    order's) and the rows next to each wall corrected to the refined grid."""

    shift_orders: Annotated[int, Range(2, 1000)] | Literal["all"]
    wall_band: Annotated[int, Range(0, 1000)] = 0
    band_orders: Annotated[int, Range(3, 1000)] | None = None


def _label(cell: dict) -> str:
    label = f"shift_orders {cell['shift_orders']}, wall_band {cell.get('wall_band', 0)}"
    orders = cell.get("band_orders")
    return label if orders is None else f"{label}, band_orders {orders}"


@dataclasses.dataclass(frozen=True)
class Config:
    """configs/periodic_cell.yaml: the grid (pixels), the stripes (period, lit rows), the
    phase convention, the walls' terms, the media and the timing repeats."""

    width: Pixels
    height: Pixels
    period: Annotated[int, Range(2, 64)]
    lit: Annotated[int, Range(1, 63)]
    phase: Literal["normalized", "paper"]
    cells: tuple[Annotated[dict, CellSpec], ...]
    media: tuple[Annotated[dict, MediumSpec], ...]
    repeats: Annotated[int, Range(1, 1000)]

    def __post_init__(self):
        if not (self.media and self.cells):
            raise ValueError("periodic_cell: media, cells: at least one each")
        for i, m in enumerate(self.media):
            try:  # the medium and the stripes as run() builds them
                lfj.Medium(m["sigma_t"], m["sigma_s"], m["g"], self.phase)
                lfj.Stripes.shifted(self.period, self.lit, direction_deg=m.get("direction_deg"))
            except ValueError as e:
                raise ValueError(f"periodic_cell: media[{i}]: {e}") from None
        if self.period >= self.height:
            raise ValueError(
                f"periodic_cell: period: must be shorter than height {self.height}, got "
                f"{self.period}"
            )


def _timed(renderer, medium: lfj.Medium, repeats: int) -> dict:
    def call():
        images = renderer(medium.sigma_t, medium.sigma_s, medium.g)[0]
        return np.asarray(jax.block_until_ready(images), np.float64)

    return repeated_calls(call, repeats)


def _case(ctx, cfg: dict, spec: dict) -> list[dict]:
    """The rows of one medium: the full render, then the cell with each walls' term."""
    medium = lfj.Medium(spec["sigma_t"], spec["sigma_s"], spec["g"], cfg["phase"])
    grid = lfj.Grid(cfg["width"], cfg["height"]).resolve(spec["g"])
    stripes = lfj.Stripes.shifted(
        cfg["period"], cfg["lit"], direction_deg=spec.get("direction_deg")
    )
    k = spec["bounces"]
    base = {
        "medium": spec["name"],
        **{key: spec.get(key, 0.0) for key in ("sigma_t", "sigma_s", "g", "direction_deg")},
        "albedo": float(medium.albedo),
        "bounces": k,
        "n_theta": grid.n_theta,
        "refine": grid.refine,
    }
    ctx.progress(f"{spec['name']}: full-domain render, {k} bounces")
    full = _timed(PlaneRenderer(grid, stripes, k, medium.phase), medium, cfg["repeats"])
    ref = full.pop("out")
    ctx.progress(f"{spec['name']}: full-domain render of every shift")
    every = PlaneRenderer(grid, stripes, k, medium.phase, moments=working_moments(stripes, grid))
    every = _timed(every, medium, cfg["repeats"])
    every_error = float(np.max(np.abs(every.pop("out") - ref)) / np.max(np.abs(ref)))
    total = ref.sum(axis=1)
    rows = [
        dict(base, shift_orders=None, **full),
        dict(base, shift_orders=None, every_pattern=True, max_error=every_error, **every),
    ]
    middle = slice(cfg["height"] // 4, cfg["height"] - cfg["height"] // 4)
    for scheme in cfg["cells"]:
        ctx.progress(f"{spec['name']}: cell, {_label(scheme)}")
        walls, band = scheme["shift_orders"], scheme.get("wall_band", 0)
        orders = None if walls == "all" else walls
        band_orders = scheme.get("band_orders")
        cell = lfj.CellRenderer(
            grid,
            stripes,
            k,
            medium.phase,
            shift_orders=orders,
            wall_band=band,
            band_orders=band_orders,
        )
        timed = _timed(cell, medium, cfg["repeats"])
        images = timed.pop("out")
        row_error = np.max(np.abs(images.sum(axis=1) - total), axis=(0, 2)) / np.max(
            total, axis=(0, 2)
        )
        order_error = np.max(np.abs(images - ref), axis=(0, 2, 3)) / np.max(
            np.abs(ref), axis=(0, 2, 3)
        )
        rows.append(
            dict(
                base,
                shift_orders=walls,
                wall_band=band,
                band_orders=band_orders,
                row_error=row_error.tolist(),
                row_error_max=float(row_error.max()),
                row_error_walls=float(max(row_error[0], row_error[-1])),
                row_error_middle=float(row_error[middle].max()),
                order_error=order_error.tolist(),
                speedup=full["seconds"] / timed["seconds"],
                speedup_fastest=full["fastest_s"] / timed["fastest_s"],
                speedup_every_fastest=every["fastest_s"] / timed["fastest_s"],
                **timed,
            )
        )
    return rows


def run(config: dict, out: Path, ctx) -> dict:
    typed_config(Config, config)  # every key checked before any work
    cfg = dict(config)
    rows = ctx.rows_per_medium(cfg, lambda spec: _case(ctx, cfg, spec))
    data = {
        "grid": {"width": cfg["width"], "height": cfg["height"]},
        "illumination": {"stripes": "left wall", "period": cfg["period"], "lit": cfg["lit"]},
        "phase": cfg["phase"],
        "media": cfg["media"],
        "cells": cfg["cells"],
        "repeats": cfg["repeats"],
        "dtype": "float32",
        "load_average_1min": os.getloadavg()[0],
        **provenance(),
        "rows": rows,
    }
    ctx.write_json("periodic_cell.json", data)
    figure = _plot(data, ctx.figure_path("periodic_cell.png"))
    keys = (
        "medium",
        "refine",
        "shift_orders",
        "wall_band",
        "band_orders",
        "row_error_walls",
        "row_error_max",
        "row_error_middle",
        "seconds",
        "fastest_s",
        "every_pattern",
    )
    return {
        "figure": str(figure),
        "table": [
            {k: r.get(k) for k in keys + ("speedup", "speedup_fastest", "speedup_every_fastest")}
            for r in rows
        ],
    }


def _plot(data: dict, path: Path) -> Path:
    # One panel per walls' term: the rows' error profile of each medium (log scale),
    # with the speedup in its label.
    cells = data["cells"]
    fig = pyplot().figure(figsize=(5.5 * len(cells), 4.2), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(cells)))
    for ax, cell in zip(axes, cells, strict=True):
        for i, spec in enumerate(data["media"]):
            row = next(
                r
                for r in data["rows"]
                if r["medium"] == spec["name"]
                and r["shift_orders"] == cell["shift_orders"]
                and r.get("wall_band") == cell.get("wall_band", 0)
                and r.get("band_orders") == cell.get("band_orders")
            )
            ax.plot(
                np.maximum(row["row_error"], 1e-7),
                color=f"C{i}",
                label=(
                    f"{spec['name']} (refine {row['refine']}): {row['speedup_fastest']:.1f}x faster"
                ),
            )
        ax.axhline(3e-3, color="0.5", ls=":", lw=1)
        ax.set_yscale("log")
        ax.set_xlabel("row (walls at both ends)")
        ax.set_ylabel("max |Δ Σ_k I_k| / row's max, over shifts")
        ax.set_title(_label(cell), fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    grid, ill = data["grid"], data["illumination"]
    fig.suptitle(
        f"Stripe cell vs full-domain render: {grid['width']}×{grid['height']} px, "
        f"period-{ill['period']} stripes (lit {ill['lit']}), 6 shifts, {data['phase']} phase, "
        f"float32",
        fontsize=9,
    )
    return save_figure(fig, path)
