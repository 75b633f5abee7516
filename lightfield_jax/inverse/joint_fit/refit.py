"""A stage refitted with its model's weights (:func:`refit`): linearised at its answer
where that holds and a render there confirms it, else solved again."""

from __future__ import annotations

import dataclasses

import numpy as np

from lightfield_jax.inverse.correction import (
    STEP_TOLERANCE,
    design,
    gauss_newton_step,
    in_domain,
    parameter_names,
    projected,
)
from lightfield_jax.inverse.joint import pack
from lightfield_jax.inverse.joint_fit.context import FitContext
from lightfield_jax.inverse.joint_fit.stage import (
    Stage,
    model_weights,
    rms,
    solve_stage,
    usable_render,
)
from lightfield_jax.inverse.lstsq import scaled_lstsq
from lightfield_jax.inverse.noise import noise_scale

# The linearised refit (:func:`linear_refit`) is kept where it moves every parameter by
# at most this much (relative on σt and σs, absolute on g and b): the model's second
# order in that shift, which the linearisation leaves out, is then of order its square
# (1e-4 relative), below the float32 solver's own tolerance (rtol 1e-4).
LINEAR_REFIT_LIMIT = 1e-2


def linear_refit(ctx: FitContext, stage: Stage, weights) -> Stage | None:
    """``stage``'s answer refitted with new ``weights`` on the model linearised at it
    (R ≈ R₀ + ∂R·Δθ: its render and Jacobian, no render; the gain projected out as in
    the solve; Gauss–Newton to the linear problem's minimum). ``None`` where the stage
    has no Jacobian or the shift is past :data:`LINEAR_REFIT_LIMIT`: the caller then
    solves with the new weights. The model's weights differ from the data's by the
    noise, so the refit moves the answer by about its 1σ (1.7σ in σt on the paper's
    milk, 48×32, 2·10⁴ photons), which is 10⁻⁴ of σt: far inside the linear range.
    There the linearised answer is the solved one's to 0.01σ, and the solve of 1
    (noiseless) to 7 (shot noise) solver steps it replaces took 0.6–2.2 s warm on the
    128×96 milk (docs/fit_speed.md)."""
    if not stage.ok or stage.jac_unit is None or not np.all(np.isfinite(stage.jac_unit)):
        return None
    data = ctx.data
    names = parameter_names(ctx.fit_black)
    jac_unit = stage.jac_unit
    p0 = np.array([stage.values[k] for k in names])
    scale = np.array([p0[0], p0[1]] + [1.0] * (len(names) - 2))
    shift = np.zeros_like(p0)
    for _ in range(20):
        unit = stage.unit + jac_unit @ shift
        gain, residual = projected(weights, unit, data.images)
        jac = design(weights, unit, gain, jac_unit)
        delta = scaled_lstsq(jac, -residual)
        delta = np.delete(delta, 3)  # the gain's column: projected
        shift += delta
        if np.max(np.abs(delta) / scale) < 1e-9:
            break
    else:
        return None
    if np.max(np.abs(shift) / scale) > LINEAR_REFIT_LIMIT:
        return None
    unit = stage.unit + jac_unit @ shift
    gain, residual = projected(weights, unit, data.images)
    v = {**stage.values, **dict(zip(names, (p0 + shift).tolist(), strict=True)), "gain": gain}
    y = pack((v["sigma_t"], v["sigma_s"], v["g"], v["black_level"]), ctx.fit_black, stage.y.dtype)
    return dataclasses.replace(
        stage,
        values=v,
        y=y,
        steps=0,
        unit=unit,
        jac=design(weights, unit, gain, jac_unit),
        weights=np.asarray(weights, np.float64),
        residual=residual,
        rms=rms(residual, data),
        compile=0.0,
        run=0.0,
        refit="linearised",
    )


def rendered_at(ctx: FitContext, stage: Stage) -> Stage | None:
    """``stage`` (a linearised refit) with its model rendered at its answer, kept where
    that render confirms it: inside the parameters' domain, and a Gauss–Newton step
    from the rendered residual (the stage's Jacobian) below the correction's tolerance
    (2·10⁻⁴ relative, or a tenth of the statistical 1σ where that is larger:
    :mod:`.correction`); else ``None``. The residual, χ² and error budget are then
    the render's, not the linear model's."""
    data, v = ctx.data, stage.values
    if not in_domain(v, ctx.black_range):
        return None
    rendered = usable_render(ctx, stage.model, v, stage.y.dtype)
    if rendered is None:
        return None
    unit, tail = rendered
    gain, residual = projected(stage.weights, unit, data.images)
    jac = design(stage.weights, unit, gain, stage.jac_unit)
    noise = noise_scale(data.images, stage.weights, ctx.pattern, gain * unit)
    _, size = gauss_newton_step(jac, residual, parameter_names(ctx.fit_black), v, noise)
    if not size < STEP_TOLERANCE:
        return None
    return dataclasses.replace(
        stage,
        values={**v, "gain": gain},
        unit=unit,
        jac=jac,
        residual=residual,
        rms=rms(residual, data),
        tail=tail,
    )


def refit(ctx: FitContext, stage: Stage) -> Stage:
    """``stage`` refitted with the model's weights at its answer
    (:func:`~.stage.model_weights`): linearised where that holds and a render there
    confirms it (:func:`linear_refit`, :func:`rendered_at`), else solved again from
    its answer."""
    weights = model_weights(ctx.data, stage)
    linear = linear_refit(ctx, stage, weights)
    checked = None if linear is None else rendered_at(ctx, linear)
    if checked is not None:
        return checked
    solved = solve_stage(ctx, stage.model, weights, stage.y)
    solved.refit = "solved"
    return solved


__all__ = ["LINEAR_REFIT_LIMIT", "linear_refit", "refit", "rendered_at"]
