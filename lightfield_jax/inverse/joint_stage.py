"""One joint solve and the pieces the joint fit's stages share: the least-squares solver
a fit's options ask for and its status message; a model's renderers (the stripes' and,
where the phases do not tile the period, full illumination's); the shot-noise weights;
:class:`_Stage` (one solve's model, answer, Jacobian and residual) and
:func:`_joint_stage` (one compiled solve from a start, :mod:`lightfield_jax.inverse.joint`);
the basin scan on the cheap model (:func:`_run_scan`, :mod:`lightfield_jax.inverse.basins`);
and a model's render at an answer (:func:`_render_model`).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from lightfield_jax.forward.cell import cell_problem, cell_renderer_for
from lightfield_jax.forward.render import renderer_for
from lightfield_jax.inverse.basins import Scan, basins, scan
from lightfield_jax.inverse.correction import (
    STEP_TOLERANCE,
    design,
    gauss_newton_step,
    in_domain,
    parameter_names,
    projected,
)
from lightfield_jax.inverse.data import FitData as _Data
from lightfield_jax.inverse.joint import BLACK_RANGE, JointSettings, model_at, pack, unpack
from lightfield_jax.inverse.joint import solve as solve_joint
from lightfield_jax.inverse.model_size import SCAN_TAIL_BOUNCES, _Model, _phase_integral
from lightfield_jax.inverse.trust import noise_scale, scaled_lstsq
from lightfield_jax.inverse.two_step import full_for as _full_for
from lightfield_jax.runtime.timing import stopwatch
from lightfield_jax.scene.illumination import Stripes

if TYPE_CHECKING:
    from lightfield_jax.inverse.options import FitOptions


def _solver(options: FitOptions, dtype):
    """The optimistix least-squares solver: ``options.solver``, else Levenberg-Marquardt
    with tolerances from ``options`` or the dtype."""
    if options.solver is not None:
        return options.solver
    wide = jnp.finfo(dtype).bits > 32
    rtol = options.rtol if options.rtol is not None else (1e-8 if wide else 1e-4)
    atol = options.atol if options.atol is not None else (1e-10 if wide else 1e-4)
    return optx.LevenbergMarquardt(rtol=rtol, atol=atol)


def _result_message(result) -> tuple[bool, str]:
    """(converged, what the solver said): its message's first sentence, on one line
    (optimistix's run to several lines of advice for its own users)."""
    ok = bool(result == optx.RESULTS.successful)
    if ok:
        return True, "converged"
    if not hasattr(optx.RESULTS, "__getitem__"):
        return False, "failed"
    text = " ".join(str(optx.RESULTS[result]).split())
    return False, text.split(". ")[0].rstrip(".") or "failed"


def _renderer(model: _Model, illumination, phase: str):
    solve = (
        {}
        if model.tail is None
        else {
            "tail": model.tail,
            "tail_tol": model.tail_tol,
            "tail_max_steps": model.tail_max_steps,
        }
    )
    if (
        model.cell is not None
        and model.geometry is None
        and cell_problem(model.grid, illumination) is None
    ):
        return cell_renderer_for(
            model.grid, illumination, model.bounces, phase, shift_orders=model.cell, **solve
        )
    return renderer_for(
        model.grid,
        illumination,
        model.bounces,
        phase,
        model.geometry,
        coarse_after=model.coarse,
        **solve,
    )


def _joint_parts(pattern: Stripes, model: _Model, phase: str):
    """The stripes' renderer and, when the phases do not tile the period, full
    illumination's (else ``None``)."""
    renderer = _renderer(model, pattern, phase)
    tiles = sorted(p % pattern.period for p in pattern.phases) == list(range(pattern.period))
    return renderer, None if tiles else _renderer(model, _full_for(pattern), phase)


def joint_weights(images, mask, exposure=None, floor=None):
    """Noise weights of the raw images, 1/√(I + floor): shot noise (variance ∝ I) and
    read noise (constant, ``floor`` in units of the shot noise's I: the capture's
    :func:`~lightfield_jax.inverse.trust.noise_floor`), the floor at least 1e-3 of the
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
class _Stage:
    """One joint solve: the model, the answer and what the error budget needs."""

    model: _Model
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


def _joint_stage(data: _Data, pattern, model: _Model, options: FitOptions, black, weights, y0):
    """One compiled joint solve (:func:`lightfield_jax.inverse.joint.solve`) from ``y0``."""
    renderer, full = _joint_parts(pattern, model, options.phase)
    fit_black = black is None
    settings = JointSettings(fit_black, pattern.lit, options.max_steps, model.extrapolate)
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
                        _solver(options, dtype),
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
    ok, msg = _result_message(result)
    tail_dict = None
    if model.tail is not None:
        tail_dict = {"steps": int(tail.steps), "converged": bool(tail.converged)}
        if failure is not None:
            tail_dict["converged"] = False
            tail_dict["error"] = failure
            ok, msg = False, f"the tail solve did not converge ({failure})"
    return _Stage(
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
        rms=_rms(residual, data),
        compile=timing.compile,
        run=timing.run,
        tail=tail_dict,
        jac_unit=jac_r,
    )


def _rms(residual: np.ndarray, data: _Data) -> float:
    n = int(np.sum(data.valid))
    return float(np.sqrt(np.sum(residual**2) / max(n, 1)))


def _joint_reweighted(data: _Data, stage: _Stage):
    """Weights from the fitted model (gain × model) instead of the noisy data (weights
    from the data itself bias a weighted fit toward low values)."""
    return joint_weights(
        stage.values["gain"] * stage.unit, data.valid, data.exposure, data.noise_floor
    )


# The linearised refit (:func:`_linear_refit`) is kept where it moves every parameter by
# at most this much (relative on σt and σs, absolute on g and b): the model's second
# order in that shift, which the linearisation leaves out, is then of order its square
# (1e-4 relative), below the float32 solver's own tolerance (rtol 1e-4).
LINEAR_REFIT_LIMIT = 1e-2


def _linear_refit(data: _Data, stage: _Stage, weights, black) -> _Stage | None:
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
    names = parameter_names(black is None)
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
    y = pack((v["sigma_t"], v["sigma_s"], v["g"], v["black_level"]), black is None, stage.y.dtype)
    return dataclasses.replace(
        stage,
        values=v,
        y=y,
        steps=0,
        unit=unit,
        jac=design(weights, unit, gain, jac_unit),
        weights=np.asarray(weights, np.float64),
        residual=residual,
        rms=_rms(residual, data),
        compile=0.0,
        run=0.0,
        refit="linearised",
    )


def _rendered_at(data: _Data, pattern, stage: _Stage, options: FitOptions, black):
    """``stage`` (a linearised refit) with its model rendered at its answer, kept where
    that render confirms it: inside the parameters' domain, and a Gauss–Newton step
    from the rendered residual (the stage's Jacobian) below the correction's tolerance
    (2·10⁻⁴ relative, or a tenth of the statistical 1σ where that is larger:
    :mod:`.correction`); else ``None``. The residual, χ² and error budget are then
    the render's, not the linear model's."""
    v = stage.values
    if not in_domain(v, BLACK_RANGE if black is None else None):
        return None
    rendered = _usable_render(pattern, stage.model, options, v, stage.y.dtype)
    if rendered is None:
        return None
    unit, tail = rendered
    gain, residual = projected(stage.weights, unit, data.images)
    jac = design(stage.weights, unit, gain, stage.jac_unit)
    noise = noise_scale(data.images, stage.weights, pattern, gain * unit)
    _, size = gauss_newton_step(jac, residual, parameter_names(black is None), v, noise)
    if not size < STEP_TOLERANCE:
        return None
    return dataclasses.replace(
        stage,
        values={**v, "gain": gain},
        unit=unit,
        jac=jac,
        residual=residual,
        rms=_rms(residual, data),
        tail=tail,
    )


def _refit(data: _Data, pattern, stage: _Stage, options: FitOptions, black) -> _Stage:
    """``stage`` refitted with the model's weights at its answer
    (:func:`_joint_reweighted`): linearised where that holds and a render there
    confirms it (:func:`_linear_refit`, :func:`_rendered_at`), else solved again from
    its answer."""
    weights = _joint_reweighted(data, stage)
    linear = _linear_refit(data, stage, weights, black)
    checked = None if linear is None else _rendered_at(data, pattern, linear, options, black)
    if checked is not None:
        return checked
    solved = _joint_stage(data, pattern, stage.model, options, black, weights, stage.y)
    solved.refit = "solved"
    return solved


def _rho_of(options: FitOptions):
    """ρ(g, albedos) of the model's phase convention (ω for the slab and ``normalized``)."""

    def rho(g: float, albedos):
        a = float(_phase_integral(g)) if options.phase == "paper" else 1.0
        return np.asarray(albedos) * a

    return rho


def _run_scan(data: _Data, pattern, model: _Model, options, black, weights, sigma_t0) -> Scan:
    extrapolate = model.tail is not None
    if extrapolate:
        model = dataclasses.replace(model, bounces=SCAN_TAIL_BOUNCES, tail=None)
    renderer, full = _joint_parts(pattern, model, options.phase)
    dtype = jnp.result_type(float)
    with stopwatch() as timing:
        cost, black_map, gs, albedos, ratios, refs, offset = scan(
            renderer,
            full,
            jnp.asarray(data.images, dtype),
            jnp.asarray(weights, dtype),
            sigma_t0,
            phase=options.phase,
            lit=pattern.lit,
            black_level=black,
            rho_limit=_rho_of(options),
            extrapolate=extrapolate,
        )
    found = basins(cost, black_map, gs, albedos, options.basin_tolerance, options.max_basins)
    return Scan(
        gs=gs,
        albedos=albedos,
        misfit=cost,
        black=black_map,
        basins=found,
        sigma_t=sigma_t0,
        seconds={"compile": timing.compile, "run": timing.run},
        ratios=ratios if extrapolate else None,
        sigma_s_ref=refs,
        offset=offset,
    )


def _usable_render(pattern, model: _Model, options: FitOptions, v: dict, dtype):
    """:func:`_render_model` of ``model`` at ``v`` (its renderers for ``pattern``), or
    ``None`` where its tail solve did not converge or the render is not finite."""
    renderer, full = _joint_parts(pattern, model, options.phase)
    unit, tail = _render_model(renderer, full, pattern, model, v, dtype)
    if (tail is not None and not tail["converged"]) or not np.all(np.isfinite(unit)):
        return None
    return unit, tail


def _render_model(renderer, full, pattern, model: _Model, v: dict, dtype):
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
