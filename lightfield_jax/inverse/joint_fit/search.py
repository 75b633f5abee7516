"""The joint fit's search over starts: one cheap solve from every start the basin scan
keeps (:func:`starts_for`), but those on the slope of an answer already found, and each
new answer taken to the model it needs (:func:`try_start`); then, where the best answer's
σt is far from the scan's, the basins of a scan at that σt the same way
(:func:`search_basins`)."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from lightfield_jax.inverse.basins import Scan
from lightfield_jax.inverse.joint import pack
from lightfield_jax.inverse.joint_fit.context import FitContext, Seconds
from lightfield_jax.inverse.joint_fit.continuation import cheap_solve, continuation
from lightfield_jax.inverse.joint_fit.scan import rescan, starts_of
from lightfield_jax.inverse.joint_fit.slope import anchors, downhill_from, same_answer
from lightfield_jax.inverse.joint_fit.stage import Stage
from lightfield_jax.inverse.model_size import ModelSpec
from lightfield_jax.runtime.timing import stopwatch

PARAMS = ("sigma_t", "sigma_s", "g")


@dataclasses.dataclass
class Search:
    """The state of the search over starts.

    Attributes:
        scan: the basin scan the answers are judged against (the rescan, once made).
        coarse: the cheap model every start is solved on first.
        stop: the reason the fit stops after the cheap solve (a constant offset
            explains the scan's misfit), or ``[]``.
        tried: one record per start (solved, on a slope, the same answer, not refined).
        stages: per answer kept, its (cheap stage, final stage).
        labels: per answer kept, its start's label.
        origins: per anchoring answer, its misfit on the cheap model (:func:`downhill_from`).
        first_scan: the scan before the rescan replaced it, or ``None``.
    """

    scan: Scan
    coarse: ModelSpec
    stop: list[str]
    tried: list[dict] = dataclasses.field(default_factory=list)
    stages: list[tuple[Stage, Stage]] = dataclasses.field(default_factory=list)
    labels: list[str] = dataclasses.field(default_factory=list)
    origins: dict = dataclasses.field(default_factory=dict)
    first_scan: Scan | None = None

    def best(self) -> tuple[Stage, Stage] | None:
        """The (cheap, final) stages of the lowest final misfit so far (models may
        differ between starts: the weighted RMS is comparable across them)."""
        return min(self.stages, key=lambda pair: pair[1].rms, default=None)


def starts_for(ctx: FitContext, the_scan: Scan, start, stop: list[str]) -> list:
    """The starts ``(label, (σt, σs, g, b))``: the given ``start`` (σt, σs, g, b), else
    the method's ``start`` (σs, g) at the scan's σt, else every basin the scan kept (its
    best alone without ``basin_search`` or where the fit ``stop``s after it)."""
    black = ctx.black
    if start is not None:
        return [("given", tuple(start) if black is None else (*start[:3], black))]
    if ctx.start is not None:
        ss, g = ctx.start
        return [("given", (ctx.data.sigma_t0, ss, g, 0.0 if black is None else black))]
    found = the_scan.basins if ctx.options.trust.basin_search else the_scan.basins[:1]
    if not found:
        raise ValueError(
            "the basin scan found no valid model for this capture (every albedo's "
            "bounce series diverges or is truncated): give bounces or a start"
        )
    return starts_of("basin", the_scan, enumerate(found[: 1 if stop else None]), black)


def try_start(ctx: FitContext, search: Search, label: str, start, seconds: Seconds) -> None:
    """One start of the search: skipped where it lies on the slope of an answer found,
    else solved on the cheap model; a new answer is taken to its model
    (:func:`continuation`) unless it cannot win, and kept in ``search``."""
    say = ctx.say
    say(f"joint fit from {label}: sigma_s {start[1]:.4g}, g {start[2]:.3f}")
    record = {"label": label, "start": dict(zip(PARAMS, start[:3], strict=True))}
    with stopwatch() as timing:
        slope = next(
            (
                i
                for i, (f, _) in enumerate(search.stages)
                if anchors(ctx, f, search.scan)
                and downhill_from(ctx, search.coarse, start, f.values, search.origins)
            ),
            None,
        )
    seconds.add_from(timing)
    if slope is not None:  # on the slope of an answer already found: not solved
        same_as = search.labels[slope]
        search.tried.append({**record, "same_as": same_as, "by": "a line downhill to it"})
        say(f"  {label}: on a slope down to {same_as}'s answer")
        return
    y0 = pack(start, ctx.fit_black, jnp.result_type(float))
    first, ran, retried = cheap_solve(ctx, search.coarse, y0)
    for stage in ran:
        seconds.add_from(stage)
    if retried is not None:
        record["retried"] = retried
    same = next(
        (i for i, (f, _) in enumerate(search.stages) if same_answer(f.values, first.values)),
        None,
    )
    if same is not None:  # the cheap model's answer of an earlier start: not again
        search.tried.append({**record, "same_as": search.labels[same], "iterations": first.steps})
        say(f"  {label}: the same answer as {search.labels[same]}")
        return
    last = (
        first  # a pedestal's misfit: the final model's solves would chase it
        if search.stop
        else continuation(ctx, first, search.scan, search.best())
    )
    if last.unrefined is not None:  # worse than an answer found: not a candidate
        search.tried.append(
            {
                **record,
                "cheap": {k: first.values[k] for k in PARAMS},
                "not_refined": last.unrefined,
                "iterations": first.steps,
            }
        )
        return
    steps = first.steps
    if last is not first:  # else its seconds and steps are counted already
        seconds.add_from(last)
        steps += last.steps
    search.tried.append(
        {
            **record,
            "final": {k: last.values[k] for k in PARAMS},
            "residual": last.rms,
            "converged": last.ok,
            "iterations": steps,
        }
    )
    say(
        f"  {label}: sigma_t {last.values['sigma_t']:.5g}, sigma_s "
        f"{last.values['sigma_s']:.5g}, g {last.values['g']:.4f}, residual {last.rms:.4g} "
        f"after {steps} solver iterations"
    )
    search.stages.append((first, last))
    search.labels.append(label)


def search_basins(
    ctx: FitContext,
    search: Search,
    starts: list,
    scan_cheap: ModelSpec | None,
    seconds: Seconds,
) -> Search:
    """Every start of ``starts`` tried (:func:`try_start`); then, with a ``scan_cheap``
    (the starts came from the scan, ``basin_search`` is on and the fit goes on past the
    cheap solve) and an answer found, the rescan's starts where its σt asks for one
    (:func:`~.scan.rescan`)."""
    for label, start in starts:
        try_start(ctx, search, label, start, seconds)
    if scan_cheap is None or not search.stages:
        return search
    more, again = rescan(ctx, scan_cheap, search.scan, search.best()[1].values, len(search.stages))
    if again is None:
        return search
    seconds.add(**again.seconds)
    search.first_scan, search.scan = search.scan, again
    for label, start in more:
        try_start(ctx, search, label, start, seconds)
    return search


__all__ = ["Search", "search_basins", "starts_for", "try_start"]
