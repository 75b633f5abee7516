"""Which starts of the joint fit are not worth a solve: those on the slope of an answer
already found (:func:`downhill_from`), and which answers may stand for such slopes
(:func:`anchors`: converged, not :func:`off_course`)."""

from __future__ import annotations

import itertools

import jax.numpy as jnp
import numpy as np

from lightfield_jax.inverse.basins import Scan, worse_basin
from lightfield_jax.inverse.correction import projected
from lightfield_jax.inverse.joint_fit.context import FitContext
from lightfield_jax.inverse.joint_fit.stage import Stage, usable_render
from lightfield_jax.inverse.model_size import ModelSpec
from lightfield_jax.inverse.verdict import at_bound


def same_answer(a: dict, b: dict) -> bool:
    return (
        abs(a["sigma_t"] / b["sigma_t"] - 1) < 1e-3
        and abs(a["sigma_s"] / b["sigma_s"] - 1) < 1e-2
        and abs(a["g"] - b["g"]) < 1e-2
    )


# Points of the line from a solved answer to another basin's start at which the cheap
# model's misfit is evaluated (:func:`downhill_from`), as fractions of the way.
LINE_POINTS = (0.0, 0.25, 0.5, 0.75, 0.9, 1.0)


def downhill_from(ctx: FitContext, coarse: ModelSpec, start, answer: dict, origins=None) -> bool:
    """Whether the cheap model's misfit (the gain projected out) rises monotonically
    along the straight line in (albedo, g, b) at the answer's σt from a solved
    ``answer`` to ``start`` (one primal render per point of :data:`LINE_POINTS`; the
    start's albedo and g are the scan's, its σt the answer's, so that the decay
    estimate's error does not add a bowl of its own along the line): then ``start`` is
    not a local minimum of the continuous misfit but a point on the slope of the
    answer's own basin, and solving from it would only find the answer again. A rising
    line is necessary, not sufficient, for that: a minimum off the line, within a
    grid cell of the start, would go unseen (as it does by the scan). Shot noise breaks
    the scan's flat σt–g valley into grid points that are each the lowest of their
    neighbours: on the paper's milk with 2·10⁴ photons (128×96) the scan keeps three
    such basins, each of which solves to the same answer (6, 5 and 7 solver steps). A
    line that rises and falls (a barrier, or a curved valley the chord cuts across),
    or a render that fails, says nothing: the start is solved. ``origins`` keeps the
    misfit at the answer itself (t = 0) between calls, keyed by the answer's ``id``
    (the answers stay alive through the fit)."""
    sigma_t = answer["sigma_t"]
    a = np.array([answer["sigma_s"] / sigma_t, answer["g"], answer["black_level"]])
    b = np.array([start[1] / start[0], start[2], start[3]], dtype=float)
    dtype = jnp.result_type(float)
    misfits, origins = [], {} if origins is None else origins
    for t in LINE_POINTS:
        if t == 0 and id(answer) in origins:
            misfits.append(origins[id(answer)])
            continue
        albedo, g, black = a + t * (b - a)
        v = {"sigma_t": sigma_t, "sigma_s": albedo * sigma_t, "g": g, "black_level": black}
        rendered = usable_render(ctx, coarse, v, dtype)
        if rendered is None:
            return False
        residual = projected(ctx.weights, rendered[0], ctx.data.images)[1]
        misfits.append(float(residual @ residual))
        if t == 0:
            origins[id(answer)] = misfits[0]
    # Rising, up to float32 rounding of the render (relative 1e-6 of the misfit).
    slack = 1e-6 * misfits[0]
    return all(later >= earlier - slack for earlier, later in itertools.pairwise(misfits))


def off_course(ctx: FitContext, v: dict, the_scan: Scan) -> bool:
    """Whether answer ``v`` is at a bound of the model or in a basin of the scan worse
    than its best."""
    albedo = v["sigma_s"] / v["sigma_t"]
    return bool(at_bound(v, ctx.black_range)) or (
        worse_basin(the_scan, v["g"], albedo, ctx.options.trust.basin_tolerance) is not None
    )


def anchors(ctx: FitContext, stage: Stage, the_scan: Scan) -> bool:
    """Whether a cheap solve's answer may stand for the basins on its slopes
    (:func:`downhill_from`): converged and not :func:`off_course`."""
    return stage.ok and not off_course(ctx, stage.values, the_scan)


__all__ = ["LINE_POINTS", "anchors", "downhill_from", "off_course", "same_answer"]
