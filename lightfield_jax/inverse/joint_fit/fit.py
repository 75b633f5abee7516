"""One joint fit with its global start (:func:`fit_once`): the basin scan on a cheap
model, the search over its basins (:mod:`.search`), then the error term from a finer
model's residual at the best answer (:mod:`.finer`), the error budget and the verdict
(:mod:`lightfield_jax.inverse.budget`, :mod:`.verdict`), gathered in :class:`Answer`."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from lightfield_jax.inverse.budget import error_budget, split_groups
from lightfield_jax.inverse.cheap_cell import CHEAP_CELL
from lightfield_jax.inverse.data import FitData, FitProblem
from lightfield_jax.inverse.joint_fit.context import FitContext, Seconds
from lightfield_jax.inverse.joint_fit.finer import model_shift
from lightfield_jax.inverse.joint_fit.scan import basin_scan
from lightfield_jax.inverse.joint_fit.search import Search, search_basins, starts_for
from lightfield_jax.inverse.joint_fit.stage import Stage, joint_weights
from lightfield_jax.inverse.joint_fit.verdict import offset_stop, verdict
from lightfield_jax.inverse.model_size import (
    SCAN_TAIL_BOUNCES,
    ModelSpec,
    by_measured_ratio,
    discretisation,
    extrapolated,
    orders,
    richardson_factor,
    scan_model,
)
from lightfield_jax.inverse.noise import noise_floor, noise_scale

if TYPE_CHECKING:
    from lightfield_jax.inverse.settings import FitSettings


@dataclasses.dataclass(frozen=True)
class Answer:
    """One joint fit's outcome: the model it ended on, the seconds spent, the values the
    result is built from (:class:`~lightfield_jax.inverse.data.FitSolution`'s) and the
    last stage (its render, weights and residual)."""

    model: ModelSpec
    seconds: dict
    values: dict
    last: Stage


def fit_once(
    problem: FitProblem,
    data: FitData,
    options: FitSettings,
    say,
    start=None,
    *,
    solver=None,
    given=None,
) -> Answer:
    """The joint fit of ``data`` (``problem``'s, or a censored copy): scan, solve every
    basin kept (or the given ``start`` = (σt, σs, g, b), else the method's ``given``
    start = (σs, g)), keep the best; then the error budget and the verdict. ``solver``:
    the method's optimistix least-squares solver (``None``: Levenberg-Marquardt)."""
    seconds = Seconds()
    coarse = scan_model(problem.model.crop, options, problem.rho0)
    if data.exposure is None:  # merged brackets: the variance follows T, not I alone
        data = dataclasses.replace(
            data, noise_floor=noise_floor(data.images, data.mask, problem.pattern)
        )
        if data.noise_floor is not None:
            say(f"  read noise seen: weights 1/sqrt(I + {data.noise_floor:.3g})")
    ctx = FitContext(
        data=data,
        pattern=problem.pattern,
        options=options,
        black=problem.black_level,
        weights=joint_weights(data.images, data.valid, data.exposure, data.noise_floor),
        images=problem.images,
        floor=problem.floor,
        say=say,
        solver=solver,
        start=given,
    )
    marched = (
        f"{coarse.bounces} bounces"
        if coarse.tail is None
        else f"{SCAN_TAIL_BOUNCES} bounces and a geometric tail"
    )
    say(
        f"basin scan: g x albedo on a {coarse.grid.width}x{coarse.grid.height} model, "
        f"n_theta {coarse.grid.n_theta}, {marched}"
    )
    # The scan's misfit map needs the light's shape, not the walls' last tenths of a
    # percent: its stripes are rendered from one period, their mean's walls' term alone.
    scan_cheap = dataclasses.replace(coarse, cell=CHEAP_CELL)
    from_scan = start is None and given is None
    the_scan, scanned = basin_scan(ctx, scan_cheap, seconds, widen=from_scan)
    peak = float(np.max(np.where(data.valid, data.images, -np.inf)))
    # Not in the censoring refit from an answer (``start``): joint_fit does not refit
    # a fit that stopped, and one that did not is refined as it was.
    stop = [] if start is not None else offset_stop(the_scan, options, peak, given is not None)
    if stop:
        say(f"  {stop[0]}")
    starts = starts_for(ctx, the_scan, start, stop)
    # One cheap model for every start: marched where the scan's measured ratio at each
    # start allows it (see by_measured_ratio).
    ratio = max(the_scan.ratio_at(s[2], s[1] / s[0]) for _, s in starts)
    coarse = extrapolated(by_measured_ratio(coarse, options, ratio), options)
    if coarse.extrapolate:  # always corrected to the full final model
        coarse = dataclasses.replace(coarse, cell=CHEAP_CELL)
    if the_scan.ratios is not None:
        say(f"  measured per-bounce ratio {ratio:.3f}")
    say(f"  the solve's model: {orders(coarse, ctx.pattern)}")
    rescans = from_scan and options.trust.basin_search and not stop
    search = search_basins(
        ctx,
        Search(scan=the_scan, coarse=coarse, stop=stop),
        starts,
        scan_cheap if rescans else None,
        seconds,
    )
    return _answer(ctx, search, scanned, peak, seconds)


def _answer(ctx: FitContext, search: Search, scanned: list, peak: float, seconds) -> Answer:
    """The best answer of ``search`` with its error budget, verdict and records."""
    data, options, stop = ctx.data, ctx.options, search.stop
    best = min(range(len(search.stages)), key=lambda i: search.stages[i][1].rms)
    last = search.stages[best][1]
    solved = [r for r in search.tried if "final" in r]
    for i, record in enumerate(solved):
        record["chosen"] = i == best
    names = ["sigma_t", "sigma_s", "g", "gain"] + (["black_level"] if ctx.fit_black else [])
    noise = noise_scale(data.images, last.weights, ctx.pattern, last.values["gain"] * last.unit)
    shift, fine, fine_tail = None, None, None
    if options.trust.model_error and not stop:
        shift, fine, fine_tail, t = model_shift(ctx, last)
        seconds.add_from(t)
    groups = split_groups(data.images.shape, ctx.pattern)
    kappa = None if fine is None else richardson_factor(last.model, fine)
    step = kappa if options.trust.extrapolate else None
    if kappa is not None and step is None:
        # Not extrapolated: the model's error is κ × its step to the finer model, and
        # the model term holds all of it.
        shift = kappa * shift
    budget = error_budget(last.jac, last.residual, names, noise, shift, groups, step)
    v = last.values
    # The answer extrapolated to the continuum (error_budget's ``extrapolate``); the
    # verdict and the fitted images stay the model's own answer's.
    answer = {**v, **{k: v[k] + d for k, d in budget.extrapolation.items()}}
    if stop:  # the cheap answer's other reasons would be that constant's, not the medium's
        reasons = list(stop)
    else:
        reasons = verdict(ctx, search.scan, last, budget, fine, fine_tail, peak)
    ok, msg = last.ok, last.message
    if reasons:
        ok, msg = False, "not trustworthy: " + "; ".join(reasons) + f" (solver: {msg})"
    scan_dict = search.scan.as_dict()
    scan_dict["tried"] = search.tried
    if stop:
        scan_dict["stopped"] = "a constant offset explains the scan's misfit (offset_stop)"
    if len(scanned) > 1:
        scan_dict["sigma_t_scanned"] = scanned
    if search.first_scan is not None:  # search.scan is the rescan
        scan_dict["first_scan"] = search.first_scan.as_dict()
    return Answer(
        model=last.model,
        seconds=seconds.as_dict(),
        values=dict(
            method="joint",
            sigma_t=answer["sigma_t"],
            sigma_s=answer["sigma_s"],
            g=answer["g"],
            gain=answer["gain"],
            black_level=answer["black_level"],
            budget=budget,
            converged=ok,
            message=msg,
            iterations=sum(r.get("iterations", 0) for r in search.tried),
            residual=last.rms,
            basins=scan_dict,
            reasons=tuple(reasons),
            model_dict=_model_record(ctx, last, fine, fine_tail, kappa, budget),
        ),
        last=last,
    )


def _model_record(
    ctx: FitContext, last: Stage, fine: ModelSpec | None, fine_tail, kappa, budget
) -> dict:
    """The record of the answer's model: its size, tail, correction and refit, the
    noise floor of its weights and the finer model of its error term (with κ, the
    continuum's distance past it in model-to-finer steps, and the answer's step there
    where it took it)."""
    data = ctx.data
    model_dict = last.model.as_dict(ctx.pattern)
    if last.tail is not None:
        model_dict["tail"].update(last.tail)
    if last.correction is not None:
        model_dict["correction"] = last.correction
    if last.refit is not None:
        model_dict["refit"] = last.refit
    model_dict["noise_floor"] = data.noise_floor
    if fine is not None:
        model_dict["finer_model"] = {
            # The dimensions it refines (none: nothing finer fits the memory cap, and
            # the term counts only the series' truncation).
            "refined": [
                k for k, n in discretisation(fine).items() if n > discretisation(last.model)[k]
            ],
            "n_theta": fine.grid.n_theta,
            "refine": fine.grid.refine,
            "extrapolation": None
            if kappa is None
            else {"factor": kappa, "step": budget.extrapolation or None},
            "bounces": fine.bounces,
            "extrapolated": fine.extrapolate,
            "coarse_after": fine.coarse,
            **fine.geometry.record(),
            **(
                {"tail": {"method": fine.tail, "tol": fine.tail_tol, **fine_tail}}
                if fine_tail is not None
                else {}
            ),
        }
    return model_dict


__all__ = ["Answer", "fit_once"]
