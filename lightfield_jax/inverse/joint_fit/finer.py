"""The finer model of a fit's error term (:func:`finer`) and the residual's shift on it
at the answer (:func:`model_shift`)."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import jax.numpy as jnp

from lightfield_jax.app.timing import stopwatch
from lightfield_jax.inverse.joint_fit.context import FitContext
from lightfield_jax.inverse.joint_fit.stage import Stage, joint_parts, render_model
from lightfield_jax.inverse.model_size import _Model, _slab_over_cap
from lightfield_jax.scene.grid import REFINE_LIMIT, default_refine

if TYPE_CHECKING:
    from lightfield_jax.inverse.options import FitOptions


def finer(model: _Model, options: FitOptions, g: float) -> _Model:
    """A finer model than ``model`` for its error term, never coarser in any dimension.

    - The plane: twice the θ bins (past 256 only within twice ``max_render_cells``,
      the memory a render may take) and the spatial refinement the size rule asks for
      at the answer's ``g`` where the fit's model stayed below it (the cell cap sized
      it down: a forward medium's model error is then mostly spatial, and a term that
      did not see it would report the fit as noise-limited), within that cap; where
      neither fits (256 θ bins and refine 2 already), one more refinement if it does.
    - The slab: twice its depth layers (at most 16), elevation nodes (64) and azimuth
      bins (128), in that order of priority, each only within four times
      ``max_render_cells`` (the slab's cell count, :func:`_slab_over_cap`).

    Then the same bounces with the rest of the series extrapolated geometrically or,
    with a tail, the same K0 and a tail tolerance ten times as tight; with a coarse
    tail (the plane's ``coarse_after``), twice as many bounces on the refined grid
    before it, so that the term also sees the coarse grid's error where most of the
    coarse bounces' light is."""
    grid = model.grid
    geometry = model.geometry
    if geometry is not None:

        def doubled(n: int, limit: int) -> int:
            return max(n, min(2 * n, limit))  # never below the model's own

        cap = 4 * options.max_render_cells
        for name, limit in (("n_z", 16), ("n_mu", 64), ("n_theta", 128)):
            g2, s2 = grid, geometry
            if name == "n_theta":
                g2 = dataclasses.replace(grid, n_theta=doubled(grid.n_theta, limit))
            else:
                s2 = dataclasses.replace(
                    geometry, **{name: doubled(getattr(geometry, name), limit)}
                )
            if not _slab_over_cap(g2.width, g2.height, g2.n_theta, g2.refine, s2, cap):
                grid, geometry = g2, s2
    else:
        cap = 2 * options.max_render_cells

        def cells(n_theta: int, refine: int) -> int:
            return grid.width * grid.height * n_theta * refine**2

        n_theta = 2 * grid.n_theta
        refine = max(grid.refine, default_refine(g))
        if cells(n_theta, refine) > cap:
            refine = grid.refine  # at most twice the model's cells (memory)
        if n_theta > 256 and cells(n_theta, refine) > cap:
            n_theta = grid.n_theta
        same = (n_theta, refine) == (grid.n_theta, grid.refine)
        if same and refine < REFINE_LIMIT and cells(n_theta, refine + 1) <= cap:
            refine += 1
        grid = dataclasses.replace(grid, n_theta=n_theta, refine=refine)
    if model.tail is not None:  # the same K0, a tail ten times as tight
        return dataclasses.replace(
            model, grid=grid, geometry=geometry, tail_tol=model.tail_tol / 10
        )
    # The same bounces and, where the fit sized them, the orders past them summed
    # geometrically from the last per-bounce ratio: the series' truncation error shows
    # in r_fine − r as it would with 1.5× + 4 bounces marched, at the cost of the
    # bounces already marched (the dense forward medium, 128×96: 32 bounces instead of
    # 52 at 128 θ bins and refine 2).
    return dataclasses.replace(
        model,
        grid=grid,
        geometry=geometry,
        extrapolate=not isinstance(options.bounces, int),
        coarse_after=None if model.coarse is None else 2 * model.coarse,
    )


def model_shift(ctx: FitContext, stage: Stage) -> tuple:
    """r_fine − r at the solution (one render of :func:`finer`'s model), that model, its
    tail solve's steps and convergence (``None`` without a tail) and its seconds."""
    pattern = ctx.pattern
    fine = finer(stage.model, ctx.options, stage.values["g"])
    renderer, full = joint_parts(pattern, fine, ctx.options.phase)
    v = stage.values
    with stopwatch() as timing:
        unit, fine_tail = render_model(renderer, full, pattern, fine, v, jnp.result_type(float))
    shift = (stage.weights * v["gain"] * (unit - stage.unit)).reshape(-1)
    return shift, fine, fine_tail, timing


__all__ = ["finer", "model_shift"]
