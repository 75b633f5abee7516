"""One joint solve and the pieces the joint fit's steps share: the least-squares solver
a fit's options ask for and its status message; a model's renderers (the stripes' and,
where the phases do not tile the period, full illumination's); the shot-noise weights;
:class:`Stage` (one solve's model, answer, Jacobian and residual) and
:func:`solve_stage` (one compiled solve from a start, :mod:`lightfield_jax.inverse.joint`);
and a model's render at an answer (:func:`render_model`, :func:`usable_render`).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from lightfield_jax.inverse.correction import design, projected
from lightfield_jax.inverse.data import FitData
from lightfield_jax.inverse.joint import JointSettings, model_at, unpack
from lightfield_jax.inverse.joint import solve as solve_joint
from lightfield_jax.inverse.joint_fit.context import FitContext
from lightfield_jax.inverse.model_size import ModelSpec
from lightfield_jax.inverse.two_step import full_for
from lightfield_jax.runtime.timing import stopwatch
from lightfield_jax.scene.illumination import Stripes

if TYPE_CHECKING:
    from lightfield_jax.inverse.settings import SolverOptions


def least_squares_solver(solver, limits: SolverOptions, dtype):
    """The optimistix least-squares solver: ``solver`` (a fit method's), else
    Levenberg-Marquardt with the tolerances of ``limits`` or the dtype."""
    if solver is not None:
        return solver
    wide = jnp.finfo(dtype).bits > 32
    rtol = limits.rtol if limits.rtol is not None else (1e-8 if wide else 1e-4)
    atol = limits.atol if limits.atol is not None else (1e-10 if wide else 1e-4)
    return optx.LevenbergMarquardt(rtol=rtol, atol=atol)


def result_message(result) -> tuple[bool, str]:
    """(converged, what the solver said): its message's first sentence, on one line
    (optimistix's run to several lines of advice for its own users)."""
    ok = bool(result == optx.RESULTS.successful)
    if ok:
        return True, "converged"
    if not hasattr(optx.RESULTS, "__getitem__"):
        return False, "failed"
    text = " ".join(str(optx.RESULTS[result]).split())
    return False, text.split(". ")[0].rstrip(".") or "failed"


def model_renderer(model: ModelSpec, illumination, phase: str):
    """``model``'s renderer for ``illumination``, with its tail solve: its geometry's
    choice (the plane's stripes from one period where ``model.cell`` is set)."""
    solve = (
        {}
        if model.tail is None
        else {
            "tail": model.tail,
            "tail_tol": model.tail_tol,
            "tail_max_steps": model.tail_max_steps,
        }
    )
    return model.geometry.renderer(model, illumination, phase, **solve)


def joint_parts(pattern: Stripes, model: ModelSpec, phase: str):
    """The stripes' renderer and, when the phases do not tile the period, full
    illumination's (else ``None``)."""
    renderer = model_renderer(model, pattern, phase)
    tiles = sorted(p % pattern.period for p in pattern.phases) == list(range(pattern.period))
    return renderer, None if tiles else model_renderer(model, full_for(pattern), phase)


def joint_weights(images, mask, exposure=None, floor=None):
    """Noise weights of the raw images, 1/√(I + floor): shot noise (variance ∝ I) and
    read noise (constant, ``floor`` in units of the shot noise's I: the capture's
    :func:`~lightfield_jax.inverse.noise.noise_floor`), the floor at least 1e-3 of the
    peak; 0 outside ``mask`` (per pixel, ``(h, w)``, or per sample, like ``images``);
    times √(T/max T) for merged exposure brackets of effective exposure T (their
    variance is ∝ I/T, :mod:`lightfield_jax.capture.hdr`)."""
    mask = np.broadcast_to(np.asarray(mask, bool), np.shape(images))
    least = 1e-3 * np.nanmax(np.where(mask, images, 0.0))
    floor = least if floor is None else max(floor, least)
    w = 1.0 / np.sqrt(np.clip(images, 0.0, None) + floor)
    if exposure is not None:
        w = w * np.sqrt(exposure / np.max(exposure))
    return np.where(mask, w, 0.0)


@dataclasses.dataclass
class Stage:
    """One joint solve: the model, the answer and what the error budget needs."""

    model: ModelSpec
    values: dict  # sigma_t, sigma_s, g, black_level, gain
    y: jax.Array
    ok: bool
    message: str
    steps: int
    unit: np.ndarray  # the model at unit gain, (P, h, w)
    jac: np.ndarray  # ∂r/∂(σt, σs, g, gain[, b]), (N, p)
    weights: np.ndarray
    residual: np.ndarray
    rms: float
    compile: float
    run: float
    tail: dict | None = None  # the tail solve at the answer: steps, converged (or error)
    jac_unit: np.ndarray | None = None  # ∂R/∂(σt, σs, g[, b]) at unit gain, (P, h, w, n)
    correction: dict | None = None  # the defect correction that produced it, if any
    refit: str | None = None  # how its weights' refit was done ("linearised", "solved")
    unrefined: str | None = None  # why a cheap solve was not taken to its model


def solve_stage(ctx: FitContext, model: ModelSpec, weights, y0) -> Stage:
    """One compiled joint solve (:func:`lightfield_jax.inverse.joint.solve`) of ``model``
    from ``y0`` with ``weights``."""
    data, pattern, options, black = ctx.data, ctx.pattern, ctx.options, ctx.black
    renderer, full = joint_parts(pattern, model, options.model.phase)
    fit_black = black is None
    settings = JointSettings(fit_black, pattern.lit, options.solve.max_steps, model.extrapolate)
    dtype = y0.dtype
    obs = jnp.asarray(data.images, dtype)
    black_fixed = jnp.asarray(0.0 if fit_black else black, dtype)
    with stopwatch() as timing:
        failure = None
        if model.tail is not None:
            # The tail's tangent solves (the Jacobian) raise where they do not converge
            # (lineax): a tail that does not converge at the start is reported from a
            # primal render, without running the solver.
            unit, tail = model_at(
                renderer, full, pattern.lit, *unpack(y0, fit_black, black_fixed), dtype
            )
            if not bool(tail.converged):
                failure = f"at the start, {int(tail.steps)} iterations"
        if failure is None:
            try:
                y, result, steps, unit, jac_r, tail = jax.block_until_ready(
                    solve_joint(
                        settings,
                        least_squares_solver(ctx.solver, options.solve, dtype),
                        renderer,
                        full,
                        obs,
                        black_fixed,
                        jnp.asarray(weights, dtype),
                        y0,
                    )
                )
            except RuntimeError:
                if model.tail is None:
                    raise
                failure = "a tangent solve of the Jacobian during the solve"
                unit, tail = model_at(
                    renderer, full, pattern.lit, *unpack(y0, fit_black, black_fixed), dtype
                )
        if failure is not None:  # the answer is the start, not trustworthy
            y, steps, result = y0, 0, optx.RESULTS.nonlinear_divergence
            jac_r = jnp.full(unit.shape + (3 + fit_black,), jnp.nan, dtype)
    st, ss, g, b = (float(v) for v in unpack(y, fit_black, black_fixed))
    w = np.asarray(weights, np.float64)
    unit = np.asarray(unit, np.float64)
    jac_r = np.asarray(jac_r, np.float64)
    gain, residual = projected(w, unit, data.images)
    jac = design(w, unit, gain, jac_r)
    ok, msg = result_message(result)
    tail_dict = None
    if model.tail is not None:
        tail_dict = {"steps": int(tail.steps), "converged": bool(tail.converged)}
        if failure is not None:
            tail_dict["converged"] = False
            tail_dict["error"] = failure
            ok, msg = False, f"the tail solve did not converge ({failure})"
    return Stage(
        model=model,
        values={"sigma_t": st, "sigma_s": ss, "g": g, "black_level": b, "gain": gain},
        y=y,
        ok=ok,
        message=msg,
        steps=int(steps),
        unit=unit,
        jac=jac,
        weights=w,
        residual=residual,
        rms=rms(residual, data),
        compile=timing.compile,
        run=timing.run,
        tail=tail_dict,
        jac_unit=jac_r,
    )


def rms(residual: np.ndarray, data: FitData) -> float:
    n = int(np.sum(data.valid))
    return float(np.sqrt(np.sum(residual**2) / max(n, 1)))


def model_weights(data: FitData, stage: Stage):
    """Weights from the fitted model (gain × model) instead of the noisy data (weights
    from the data itself bias a weighted fit toward low values)."""
    return joint_weights(
        stage.values["gain"] * stage.unit, data.valid, data.exposure, data.noise_floor
    )


def usable_render(ctx: FitContext, model: ModelSpec, v: dict, dtype):
    """:func:`render_model` of ``model`` at ``v`` (its renderers for the fit's pattern),
    or ``None`` where its tail solve did not converge or the render is not finite."""
    renderer, full = joint_parts(ctx.pattern, model, ctx.options.model.phase)
    unit, tail = render_model(renderer, full, ctx.pattern, model, v, dtype)
    if (tail is not None and not tail["converged"]) or not np.all(np.isfinite(unit)):
        return None
    return unit, tail


def render_model(renderer, full, pattern, model: ModelSpec, v: dict, dtype):
    """``model``'s render at unit gain at ``v`` (σt, σs, g, black level), as float64
    numpy, and its tail solve's ``{"steps", "converged"}`` (``None`` without a tail)."""
    unit, tail = model_at(
        renderer,
        full,
        pattern.lit,
        v["sigma_t"],
        v["sigma_s"],
        v["g"],
        v["black_level"],
        dtype,
        model.extrapolate,
    )
    unit = np.asarray(jax.block_until_ready(unit), np.float64)
    status = None
    if model.tail is not None:
        status = {"steps": int(tail.steps), "converged": bool(tail.converged)}
    return unit, status


__all__ = [
    "Stage",
    "joint_parts",
    "joint_weights",
    "least_squares_solver",
    "model_renderer",
    "model_weights",
    "render_model",
    "result_message",
    "rms",
    "solve_stage",
    "usable_render",
]
