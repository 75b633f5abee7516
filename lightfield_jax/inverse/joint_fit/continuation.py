"""From a start's cheap answer to its final model: the cheap solve itself
(:func:`cheap_solve`, solved again on a finer cheap slab where it ran away), then the
model the answer needs reached by defect correction or else solved on
(:func:`continuation`, :func:`corrected`), unless it cannot beat an answer already found
(:func:`cannot_win`)."""

from __future__ import annotations

import dataclasses

from lightfield_jax.inverse.basins import Scan
from lightfield_jax.inverse.correction import correct, projected
from lightfield_jax.inverse.joint import pack
from lightfield_jax.inverse.joint_fit.context import FitContext
from lightfield_jax.inverse.joint_fit.refit import refit
from lightfield_jax.inverse.joint_fit.slope import off_course
from lightfield_jax.inverse.joint_fit.stage import (
    Stage,
    joint_parts,
    model_weights,
    render_model,
    rms,
    solve_stage,
    usable_render,
)
from lightfield_jax.inverse.lstsq import scaled_lstsq
from lightfield_jax.inverse.model_size import (
    ModelSpec,
    at_least,
    by_measured_ratio,
    covers,
    finer_cheap,
    orders,
    size_model,
)
from lightfield_jax.inverse.noise import noise_scale
from lightfield_jax.inverse.verdict import at_bound
from lightfield_jax.runtime.timing import stopwatch

# A later start's answer is not taken to its model where both its cheap misfit and the
# misfit predicted for it there exceed the best answer's by this share
# (:func:`cannot_win`).
HOPELESS_MARGIN = 0.25


def cannot_win(ctx: FitContext, first: Stage, target: ModelSpec, best) -> str | None:
    """A reason where ``first`` (a later start's cheap answer) is not worth taking to
    ``target``, else ``None``. ``best`` is the best (cheap stage, final stage) so far.
    In the data's weights: the cheap misfit exceeds the best cheap misfit, and the
    misfit ``target`` reaches from ``first``'s answer by one Gauss–Newton step (one
    primal render there, the cheap Jacobian) exceeds the best final misfit, both by
    :data:`HOPELESS_MARGIN`. Measured on a read-noise capture (milk, 48×36, 0.3 %):
    the second basin's answer at g −0.9 asked for 256 θ bins and a 2× grid, whose
    correction did not converge and whose solve took 124 s to end at 1.79× the first
    basin's misfit, the prediction's own ratio (1.79)."""
    w = first.weights
    best_first, best_last = best
    cheap = float(first.residual @ first.residual)
    if not cheap > (1.0 + HOPELESS_MARGIN) * float(best_first.residual @ best_first.residual):
        return None
    rendered = usable_render(ctx, target, first.values, first.y.dtype)
    if rendered is None:
        return None
    _, r_fine = projected(w, rendered[0], ctx.data.images)
    delta = scaled_lstsq(first.jac, -r_fine)
    moved = r_fine + first.jac @ delta
    predicted = float(moved @ moved)
    _, r_best = projected(w, best_last.unit, ctx.data.images)
    s_best = float(r_best @ r_best)
    if not predicted > (1.0 + HOPELESS_MARGIN) * s_best:
        return None
    return (
        f"worse than an answer found: its misfit on the final model {predicted / s_best:.3g}× "
        "the best answer's (one Gauss-Newton step predicted); not refined"
    )


def continuation(ctx: FitContext, first: Stage, the_scan: Scan, best=None) -> Stage:
    """The joint fit after its first stage ``first`` (the cheap model's solve): the
    model its answer needs (the larger of that and the context's ``floor``) reached by defect
    correction (``correct``: :func:`corrected`), or else solved on (capped by
    ``max_cells``: a solve, then its refit with the model's weights, :func:`~.refit.refit`).
    Returns the last stage (``first`` itself when it ends at a bound of the model or in
    a basin worse than the scan's best; the cheap model's refit with the model's
    weights where that model already covers the need)."""
    options, say = ctx.options, ctx.say
    coarse = first.model
    v = first.values
    albedo = v["sigma_s"] / v["sigma_t"]
    if off_course(ctx, v, the_scan):
        # At a bound or in a worse basin on the cheap model: not trustworthy whatever
        # the model, and not worth the large model it would ask for.
        say("  at a bound or in a worse basin on the cheap model: not refined")
        return first
    ratio = the_scan.ratio_at(v["g"], albedo)

    def needed(max_cells: int) -> ModelSpec:
        model = size_model(
            ctx.images,
            ctx.pattern,
            albedo=min(albedo, 0.98),
            g=v["g"],
            options=dataclasses.replace(
                options, model=dataclasses.replace(options.model, max_cells=max_cells)
            ),
            margin=1.03,
            sigma_t=v["sigma_t"],
            crop=coarse.crop,
        )
        return by_measured_ratio(model, options, ratio)

    # The solve's model is capped by max_cells (the forward-mode Jacobian's memory);
    # the corrected one, reached by primal renders, by max_render_cells.
    need = at_least(needed(options.model.max_cells), ctx.floor)
    if not first.ok and not tail_failed(first) and not need.converges:
        # Measured: the stability map's divergent truth (ω 0.8, g 0.85 under paper, an
        # explicit 12-bounce truncation, 48×36): the cheap solve ran out of steps at
        # ω 0.99, g 0.94, and the solve on the model it asked for (256 θ bins, refine 2,
        # max_bounces) had not returned after 900 s.
        say(
            f"  the cheap solve did not converge, at values whose bounce series diverges "
            f"(rho {need.rho:.3g} >= 1): not refined"
        )
        return first
    correct = options.trust.correct and first.ok
    target = at_least(needed(options.model.max_render_cells), need) if correct else need
    if covers(coarse, target):
        # The cheap model is already as large as the answer needs: refit it with the
        # model's weights, and that is the answer.
        return refit(ctx, first)
    if best is not None:
        reason = cannot_win(ctx, first, target, best)
        if reason is not None:
            say(f"  {reason}")
            return dataclasses.replace(first, unrefined=reason)
    spent, record = {"compile": 0.0, "run": 0.0}, None
    if correct:
        say(
            f"  defect correction to the final model n_theta {target.grid.n_theta}, refine "
            f"{target.grid.refine}, {orders(target, ctx.pattern)}"
        )
        done, record = corrected(ctx, first, target)
        if done is not None:
            return done
        spent = record["seconds"]
        say(f"  the correction stopped ({record['stopped']}): solving on the final model")
    if covers(coarse, need):
        last = refit(ctx, first)
    else:
        series = orders(need, ctx.pattern)
        say(f"  final model n_theta {need.grid.n_theta}, refine {need.grid.refine}, {series}")
        mid = solve_stage(ctx, need, first.weights, first.y)
        last = refit(ctx, mid)
        last.steps += mid.steps
        last.compile += mid.compile
        last.run += mid.run
    last.compile += spent["compile"]
    last.run += spent["run"]
    if record is not None:
        last.correction = {**record, "fallback": "solved on the model instead"}
    return last


def tail_failed(stage: Stage) -> bool:
    """Whether the stage's tail solve failed (it then did not run its solver)."""
    return stage.tail is not None and "error" in stage.tail


def runaway(stage: Stage) -> bool:
    """A cheap solve that did not converge (a tail that failed aside) or ended with g or
    the albedo at a bound."""
    return (not stage.ok and not tail_failed(stage)) or bool(at_bound(stage.values))


def cheap_solve(ctx: FitContext, coarse: ModelSpec, y0) -> tuple[Stage, list[Stage], dict | None]:
    """The cheap model's solve from ``y0``; a slab's that ran away (:func:`runaway`) is
    solved again on :func:`finer_cheap`'s model, kept where it converged off the
    bounds or fits better. Returns the stage kept, every stage run (for their seconds)
    and the retry's record (``None`` without one)."""
    first = solve_stage(ctx, coarse, ctx.weights, y0)
    retry = finer_cheap(coarse, ctx.options)
    if retry is None or not runaway(first):
        return first, [first], None
    ctx.say(
        "  the cheap model's solve did not converge or ended at a bound: again on "
        f"n_theta {retry.grid.n_theta}, n_mu {retry.geometry.discretisation()['n_mu']}"
    )
    again = solve_stage(ctx, retry, ctx.weights, y0)
    kept = not runaway(again) or again.rms < first.rms
    record = {
        "n_theta": retry.grid.n_theta,
        "n_mu": retry.geometry.discretisation()["n_mu"],
        "first": {k: first.values[k] for k in ("sigma_t", "sigma_s", "g")},
        "first_converged": first.ok,
        "converged": again.ok,
        "kept": kept,
    }
    ran = [first, again]
    first, other = (again, first) if kept else (first, again)
    # The steps of both solves (their seconds come from ``ran``), on a copy: ``ran``
    # keeps each stage's own.
    first = dataclasses.replace(first, steps=first.steps + other.steps)
    return first, ran, record


def corrected(ctx: FitContext, first: Stage, target: ModelSpec) -> tuple[Stage | None, dict]:
    """``target``'s answer by defect correction from ``first`` (the cheap model's solve:
    its answer and Jacobian, model weights from its answer; :mod:`.correction`): the
    stage (``None`` where the iteration did not converge) and its record."""
    data, pattern, options = ctx.data, ctx.pattern, ctx.options
    renderer, full = joint_parts(pattern, target, options.model.phase)
    dtype = first.y.dtype
    weights = model_weights(data, first)

    def render(v):
        return render_model(renderer, full, pattern, target, v, dtype)

    with stopwatch() as timing:
        c = correct(
            render,
            data.images,
            weights,
            first.values,
            first.jac_unit,
            ctx.black_range,
            options.trust.correction_renders,
            noise_scale(data.images, weights, pattern, first.values["gain"] * first.unit),
        )
    for step in c.steps:
        ctx.say(f"    step {step['size']:.2e} ({step['jacobian']} Jacobian)")
    record = {
        "renders": c.renders,
        "converged": c.converged,
        "stopped": c.reason,
        "steps": c.steps,
        "seconds": {"compile": timing.compile, "run": timing.run},
    }
    if not (c.converged and first.ok):
        return None, record
    v = c.values
    stage = Stage(
        model=target,
        values={k: v[k] for k in ("sigma_t", "sigma_s", "g", "black_level", "gain")},
        y=pack((v["sigma_t"], v["sigma_s"], v["g"], v["black_level"]), ctx.fit_black, dtype),
        ok=True,
        message=first.message,
        steps=0,
        unit=c.unit,
        jac=c.jac,
        weights=weights,
        residual=c.residual,
        rms=rms(c.residual, data),
        compile=timing.compile,
        run=timing.run,
        tail=c.tail,
        jac_unit=None,
        correction=record,
    )
    return stage, record


__all__ = [
    "HOPELESS_MARGIN",
    "cannot_win",
    "cheap_solve",
    "continuation",
    "corrected",
    "runaway",
    "tail_failed",
]
