"""The finer model of a fit's error term (:func:`finer`) and the residual's shift on it
at the answer (:func:`model_shift`)."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import jax.numpy as jnp

from lightfield_jax.inverse.joint_fit.context import FitContext
from lightfield_jax.inverse.joint_fit.stage import Stage, joint_parts, render_model
from lightfield_jax.inverse.model_size import ModelSpec
from lightfield_jax.runtime.timing import stopwatch

if TYPE_CHECKING:
    from lightfield_jax.inverse.settings import FitSettings


def finer(
    model: ModelSpec, options: FitSettings, g: float, albedo: float | None = None
) -> ModelSpec:
    """A finer model than ``model`` for its error term at the answer's ``g`` and
    ``albedo`` (``None``: unknown), never coarser in any dimension:
    its geometry's finer discretisation
    (:meth:`~lightfield_jax.inverse.geometry_model.GeometryModel.finer`: the plane's
    θ bins and refinement, the slab's depth layers, elevation nodes and azimuth bins,
    each within a multiple of ``max_render_cells``).

    Then the same bounces with the rest of the series extrapolated geometrically or,
    with a tail, the same K0 and a tail tolerance ten times as tight; with a coarse
    tail (the plane's ``coarse_after``), twice as many bounces on the refined grid
    before it, so that the term also sees the coarse grid's error where most of the
    coarse bounces' light is."""
    grid, geometry = model.geometry.finer(model.grid, options, g, albedo)
    # Rendered as its geometry renders a sized model on that grid (the stripe cell on a
    # refined plane): the cell's own error, 0.2 % at most, is a tenth of the term's.
    cell = geometry.stripe_cell(grid, options)
    if model.tail is not None:  # the same K0, a tail ten times as tight
        return dataclasses.replace(
            model, grid=grid, geometry=geometry, tail_tol=model.tail_tol / 10, cell=cell
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
        extrapolate=not isinstance(options.model.bounces, int),
        coarse_after=None if model.coarse is None else 2 * model.coarse,
        cell=cell,
    )


def model_shift(ctx: FitContext, stage: Stage) -> tuple:
    """r_fine − r at the solution (one render of :func:`finer`'s model), that model, its
    tail solve's steps and convergence (``None`` without a tail) and its seconds."""
    pattern = ctx.pattern
    v = stage.values
    fine = finer(stage.model, ctx.options, v["g"], v["sigma_s"] / v["sigma_t"])
    renderer, full = joint_parts(pattern, fine, ctx.options.model.phase)
    with stopwatch() as timing:
        unit, fine_tail = render_model(renderer, full, pattern, fine, v, jnp.result_type(float))
    shift = (stage.weights * v["gain"] * (unit - stage.unit)).reshape(-1)
    return shift, fine, fine_tail, timing


__all__ = ["finer", "model_shift"]
