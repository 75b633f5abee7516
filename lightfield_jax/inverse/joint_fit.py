"""The joint fit (:func:`_joint_fit`, the ``joint`` method's solve): the basin scan on a
cheap model, one solve of that model from every start the scan keeps (but those on the
slope of an answer already found, :func:`_downhill_from`), and from each
answer the model it needs, reached by defect correction or else solved on
(:func:`_continuation`, :func:`_corrected`); the best final misfit is kept. Then the
error term from a finer model's residual at the answer (:func:`_finer`,
:func:`_model_shift`), the error budget and the verdict
(:mod:`lightfield_jax.inverse.trust`).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import TYPE_CHECKING

import jax.numpy as jnp
import numpy as np

from lightfield_jax.inverse.basins import Scan, basin_of, nearest_point, worse_basin
from lightfield_jax.inverse.correction import correct, projected
from lightfield_jax.inverse.data import FitData as _Data
from lightfield_jax.inverse.joint import BLACK_RANGE, pack
from lightfield_jax.inverse.joint_stage import (
    _joint_parts,
    _joint_reweighted,
    _joint_stage,
    _refit,
    _render_model,
    _rms,
    _run_scan,
    _Stage,
    _usable_render,
    joint_weights,
)
from lightfield_jax.inverse.model_size import (
    RATIO_MARGIN,
    SCAN_TAIL_BOUNCES,
    _at_least,
    _bucket_bounces,
    _by_measured_ratio,
    _covers,
    _extrapolated,
    _finer_cheap,
    _Model,
    _orders,
    _scan_model,
    _slab_over_cap,
    discretisation,
    richardson_factor,
    size_model,
)
from lightfield_jax.inverse.trust import (
    OFFSET_EXPLAINS,
    at_bound,
    constant_offset,
    error_budget,
    noise_floor,
    noise_scale,
    offset_hint,
    scaled_lstsq,
    split_groups,
    tail_unconverged,
    untrustworthy,
)
from lightfield_jax.runtime.timing import stopwatch
from lightfield_jax.scene.grid import REFINE_LIMIT, default_refine
from lightfield_jax.scene.medium import bounces_for_tolerance

if TYPE_CHECKING:
    from lightfield_jax.inverse.options import FitOptions


# An answer whose σt is more than this factor from the scan's (the direct light's decay
# estimate) is checked by a second scan at its σt (:func:`_rescan`). Measured on 32x24
# captures with σs = σt/2, g 0.4 per pixel: at σt 3, 4 and 5 (mean free path 0.33-0.2
# px) the decay estimates are 2.09, 2.55 and 2.88, the scan's only basin there at
# g -0.45, and its answers at g -0.89, -0.90 and -0.64 with σt 3.40, 4.41 and 3.53
# (ratios 1.62, 1.73 and 1.22 to the estimate), each reported converged; the truth's
# basin fits those captures with a 30-60 % smaller residual. Forward media put their
# answer 1.15-1.2 times their estimate (48x36: ω 0.8 g 0.7, ω 0.95 g 0.5): rescanned
# too, which costs one scan where the answer's basin is the rescan's best.
RESCAN_RATIO = 1.1
# Where the decay estimate of σt is at least this (per pixel: a mean free path of two
# pixels or less), the scan is made at these multiples of it too and the scan with the
# lowest misfit kept. The estimate runs low there (48x36 and 32x24 captures, σs = σt/2,
# g 0.4: 0.84 of the truth at σt 1, 0.77 at 2, 0.70 at 3, 0.64 at 4, 0.58 at 5; the
# answer from the estimate's scan alone at σt 5 is g -0.64, σt 3.53, reported converged).
SHORT_DECAY = 0.5
SIGMA_T_FACTORS = (1.3, 1.7, 2.2)


def _home_basin(scan, values: dict):
    """The grid point of ``scan``'s local minimum whose basin holds ``values``."""
    p = nearest_point(scan.gs, scan.albedos, values["g"], values["sigma_s"] / values["sigma_t"])
    return basin_of(scan.misfit, *p) if np.isfinite(scan.misfit[p]) else None


# The cheap models' stripe cell: the walls' term of the shifts' mean alone (2: no order
# of every shift's own), the fastest (docs/periodic_cell.md).
CHEAP_CELL = 2


def _rescan(data, pattern, scan_model, options, black, weights, the_scan, stages, say):
    """The scan held σt at the direct light's decay estimate. An answer far from it (a
    medium whose mean free path is near a pixel: that decay spans few pixels) may lie
    in a basin the scan at the estimate never saw: where the best answer's σt is more
    than ``RESCAN_RATIO`` from the scan's, the scan again at that σt, and its basins
    other than the answer's own as further starts. Returns ``(starts, scan)``, or
    ``([], None)`` where no rescan is needed."""
    found = min(stages, key=lambda pair: pair[1].rms)[1].values
    if abs(math.log(found["sigma_t"] / the_scan.sigma_t)) <= math.log(RESCAN_RATIO):
        return [], None
    say(f"basin scan again at the answer's sigma_t {found['sigma_t']:.4g}")
    rescan = _run_scan(data, pattern, scan_model, options, black, weights, found["sigma_t"])
    home = _home_basin(rescan, found)
    others = [(i, b) for i, b in enumerate(rescan.basins) if b.index != home]
    others = others[: max(options.max_basins - len(stages), 1)]
    return _starts_of("rescan basin", rescan, others, black), rescan


def _starts_of(label: str, scan, found, black) -> list:
    """The joint fit's starts ``(label i, (σt, σs, g, b))`` of ``scan``'s basins
    ``found`` (pairs ``(i, basin)``): at the scan's σt, b the scan's where it is
    fitted."""
    return [
        (
            f"{label} {i}",
            (scan.sigma_t, b.albedo * scan.sigma_t, b.g, b.black_level if black is None else black),
        )
        for i, b in found
    ]


def _same_answer(a: dict, b: dict) -> bool:
    return (
        abs(a["sigma_t"] / b["sigma_t"] - 1) < 1e-3
        and abs(a["sigma_s"] / b["sigma_s"] - 1) < 1e-2
        and abs(a["g"] - b["g"]) < 1e-2
    )


# Points of the line from a solved answer to another basin's start at which the cheap
# model's misfit is evaluated (:func:`_downhill_from`), as fractions of the way.
LINE_POINTS = (0.0, 0.25, 0.5, 0.75, 0.9, 1.0)


def _downhill_from(
    data, pattern, coarse: _Model, options, weights, start, answer: dict, origins=None
):
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
        rendered = _usable_render(pattern, coarse, options, v, dtype)
        if rendered is None:
            return False
        residual = projected(weights, rendered[0], data.images)[1]
        misfits.append(float(residual @ residual))
        if t == 0:
            origins[id(answer)] = misfits[0]
    # Rising, up to float32 rounding of the render (relative 1e-6 of the misfit).
    slack = 1e-6 * misfits[0]
    return all(later >= earlier - slack for earlier, later in itertools.pairwise(misfits))


def _off_course(v: dict, the_scan, options, black) -> bool:
    """Whether answer ``v`` is at a bound of the model or in a basin of the scan worse
    than its best."""
    albedo = v["sigma_s"] / v["sigma_t"]
    return bool(at_bound(v, BLACK_RANGE if black is None else None)) or (
        worse_basin(the_scan, v["g"], albedo, options.basin_tolerance) is not None
    )


def _anchors(stage: _Stage, the_scan, options, black) -> bool:
    """Whether a cheap solve's answer may stand for the basins on its slopes
    (:func:`_downhill_from`): converged and not :func:`_off_course`."""
    return stage.ok and not _off_course(stage.values, the_scan, options, black)


# A later start's answer is not taken to its model where both its cheap misfit and the
# misfit predicted for it there exceed the best answer's by this share
# (:func:`_cannot_win`).
HOPELESS_MARGIN = 0.25


def _cannot_win(data, pattern, first: _Stage, target: _Model, options, best) -> str | None:
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
    rendered = _usable_render(pattern, target, options, first.values, first.y.dtype)
    if rendered is None:
        return None
    _, r_fine = projected(w, rendered[0], data.images)
    delta = scaled_lstsq(first.jac, -r_fine)
    moved = r_fine + first.jac @ delta
    predicted = float(moved @ moved)
    _, r_best = projected(w, best_last.unit, data.images)
    s_best = float(r_best @ r_best)
    if not predicted > (1.0 + HOPELESS_MARGIN) * s_best:
        return None
    return (
        f"worse than an answer found: its misfit on the final model {predicted / s_best:.3g}× "
        "the best answer's (one Gauss-Newton step predicted); not refined"
    )


def _continuation(
    data, pattern, first: _Stage, options, black, images, floor, the_scan, say, best=None
):
    """The joint fit after its first stage ``first`` (the cheap model's solve): the
    model its answer needs (the larger of that and ``floor``) reached by defect
    correction (``correct``: :func:`_corrected`), or else solved on (capped by
    ``max_cells``: a solve, then its refit with the model's weights, :func:`_refit`).
    Returns the last stage (``first`` itself when it ends at a bound of the model or in
    a basin worse than the scan's best; the cheap model's refit with the model's
    weights where that model already covers the need)."""
    coarse = first.model
    v = first.values
    albedo = v["sigma_s"] / v["sigma_t"]
    if _off_course(v, the_scan, options, black):
        # At a bound or in a worse basin on the cheap model: not trustworthy whatever
        # the model, and not worth the large model it would ask for.
        say("  at a bound or in a worse basin on the cheap model: not refined")
        return first
    ratio = the_scan.ratio_at(v["g"], albedo)

    def needed(max_cells: int) -> _Model:
        model = size_model(
            images,
            pattern,
            albedo=min(albedo, 0.98),
            g=v["g"],
            options=dataclasses.replace(options, max_cells=max_cells),
            margin=1.03,
            sigma_t=v["sigma_t"],
            crop=coarse.crop,
        )
        return _by_measured_ratio(model, options, ratio)

    # The solve's model is capped by max_cells (the forward-mode Jacobian's memory);
    # the corrected one, reached by primal renders, by max_render_cells.
    need = _at_least(needed(options.max_cells), floor)
    if not first.ok and not _tail_failed(first) and not need.converges:
        # Measured: the stability map's divergent truth (ω 0.8, g 0.85 under paper, an
        # explicit 12-bounce truncation, 48×36): the cheap solve ran out of steps at
        # ω 0.99, g 0.94, and the solve on the model it asked for (256 θ bins, refine 2,
        # max_bounces) had not returned after 900 s.
        say(
            f"  the cheap solve did not converge, at values whose bounce series diverges "
            f"(rho {need.rho:.3g} >= 1): not refined"
        )
        return first
    correct = options.correct and first.ok
    target = _at_least(needed(options.max_render_cells), need) if correct else need
    if _covers(coarse, target):
        # The cheap model is already as large as the answer needs: refit it with the
        # model's weights, and that is the answer.
        return _refit(data, pattern, first, options, black)
    if best is not None:
        reason = _cannot_win(data, pattern, first, target, options, best)
        if reason is not None:
            say(f"  {reason}")
            return dataclasses.replace(first, unrefined=reason)
    spent, record = {"compile": 0.0, "run": 0.0}, None
    if correct:
        say(
            f"  defect correction to the final model n_theta {target.grid.n_theta}, refine "
            f"{target.grid.refine}, {_orders(target)}"
        )
        done, record = _corrected(data, pattern, first, target, options, black, say)
        if done is not None:
            return done
        spent = record["seconds"]
        say(f"  the correction stopped ({record['stopped']}): solving on the final model")
    if _covers(coarse, need):
        last = _refit(data, pattern, first, options, black)
    else:
        say(
            f"  final model n_theta {need.grid.n_theta}, refine {need.grid.refine}, {_orders(need)}"
        )
        mid = _joint_stage(data, pattern, need, options, black, first.weights, first.y)
        last = _refit(data, pattern, mid, options, black)
        last.steps += mid.steps
        last.compile += mid.compile
        last.run += mid.run
    last.compile += spent["compile"]
    last.run += spent["run"]
    if record is not None:
        last.correction = {**record, "fallback": "solved on the model instead"}
    return last


def _tail_failed(stage: _Stage) -> bool:
    """Whether the stage's tail solve failed (it then did not run its solver)."""
    return stage.tail is not None and "error" in stage.tail


def _runaway(stage: _Stage) -> bool:
    """A cheap solve that did not converge (a tail that failed aside) or ended with g or
    the albedo at a bound."""
    return (not stage.ok and not _tail_failed(stage)) or bool(at_bound(stage.values))


def _cheap_solve(data, pattern, coarse: _Model, options, black, weights, y0, say):
    """The cheap model's solve from ``y0``; a slab's that ran away (:func:`_runaway`) is
    solved again on :func:`_finer_cheap`'s model, kept where it converged off the
    bounds or fits better. Returns the stage kept, every stage run (for their seconds)
    and the retry's record (``None`` without one)."""
    first = _joint_stage(data, pattern, coarse, options, black, weights, y0)
    retry = _finer_cheap(coarse, options)
    if retry is None or not _runaway(first):
        return first, [first], None
    say(
        "  the cheap model's solve did not converge or ended at a bound: again on "
        f"n_theta {retry.grid.n_theta}, n_mu {retry.geometry.n_mu}"
    )
    again = _joint_stage(data, pattern, retry, options, black, weights, y0)
    kept = not _runaway(again) or again.rms < first.rms
    record = {
        "n_theta": retry.grid.n_theta,
        "n_mu": retry.geometry.n_mu,
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


def _corrected(data: _Data, pattern, first: _Stage, target: _Model, options, black, say):
    """``target``'s answer by defect correction from ``first`` (the cheap model's solve:
    its answer and Jacobian, model weights from its answer; :mod:`.correction`): the
    stage (``None`` where the iteration did not converge) and its record."""
    renderer, full = _joint_parts(pattern, target, options.phase)
    dtype = first.y.dtype
    weights = _joint_reweighted(data, first)

    def render(v):
        return _render_model(renderer, full, pattern, target, v, dtype)

    with stopwatch() as timing:
        c = correct(
            render,
            data.images,
            weights,
            first.values,
            first.jac_unit,
            BLACK_RANGE if black is None else None,
            options.correction_renders,
            noise_scale(data.images, weights, pattern, first.values["gain"] * first.unit),
        )
    for step in c.steps:
        say(f"    step {step['size']:.2e} ({step['jacobian']} Jacobian)")
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
    stage = _Stage(
        model=target,
        values={k: v[k] for k in ("sigma_t", "sigma_s", "g", "black_level", "gain")},
        y=pack((v["sigma_t"], v["sigma_s"], v["g"], v["black_level"]), black is None, dtype),
        ok=True,
        message=first.message,
        steps=0,
        unit=c.unit,
        jac=c.jac,
        weights=weights,
        residual=c.residual,
        rms=_rms(c.residual, data),
        compile=timing.compile,
        run=timing.run,
        tail=c.tail,
        jac_unit=None,
        correction=record,
    )
    return stage, record


def _finer(model: _Model, options: FitOptions, g: float) -> _Model:
    """A finer model than ``model`` for its error term, never coarser in any dimension.

    - The plane: one spatial refinement more than a refined model's (the size rule's
      at the answer's ``g`` where larger, as for an unrefined one), within twice
      ``max_render_cells`` (the memory a render may take), and twice the θ bins (past
      256 only within that cap; dropped first where both do not fit); where neither
      changes, one more refinement if it fits. Its error is first order in the cell size
      (:func:`~lightfield_jax.inverse.model_size.richardson_factor`): a term that kept
      the model's refinement did not see the dense forward medium's (64 θ bins, refine
      2, Monte Carlo capture: σt +2.5 % reported as ± 0.2 %).
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
        # A refined model (a forward medium's) one refinement more, an unrefined one the
        # size rule's at g; space first where both do not fit with the θ bins doubled.
        refine = max(grid.refine + 1 if grid.refine > 1 else 1, default_refine(g))
        refine = min(refine, REFINE_LIMIT)
        if refine > grid.refine and cells(n_theta, refine) > cap >= cells(grid.n_theta, refine):
            n_theta = grid.n_theta
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


# A marched series whose left-out orders exceed this share of I_1 is not a model of the
# capture (the limit the two-step methods apply to a convergent series' march,
# methods.TRUNCATION_LIMIT).
CUT_LIMIT = 0.01


def _offset_stop(the_scan: Scan, options: FitOptions, peak: float) -> list[str]:
    """The reason to stop after the basin scan (``[]``: go on): a constant offset in
    every image value leaves less than ``options.offset_stop`` of the scan's best
    misfit. The scan's misfit then is mostly that constant, many times the noise and the
    cheap model's own error, and the full model's solves would chase it (g toward its
    bound, the model growing with it) for minutes to end not trusted."""
    found = the_scan.offset
    if found is None or not found.fraction < options.offset_stop:
        return []
    hint = offset_hint(found.value, found.fraction, "basin scan's", peak)
    if not hint:
        return []
    solved = "the given start's" if options.start is not None else "its best basin's"
    return [
        f"{hint[0]}; the fit stopped after the scan and {solved} cheap solve "
        f"(offset_stop: {options.offset_stop:g})"
    ]


def _offset_reason(the_scan: Scan, last: _Stage, peak: float) -> list[str]:
    """Where the misfit is far above the noise: the constant offset in every image value
    that explains most of it (a camera pedestal left in the images), from the basin
    scan, else linearised at the answer (:func:`offset_hint`)."""
    found = the_scan.offset
    if found is not None and found.fraction <= OFFSET_EXPLAINS:
        return offset_hint(found.value, found.fraction, "basin scan's", peak)
    d, left = constant_offset(last.jac, last.residual, last.weights)
    return offset_hint(d, left, "answer's", peak)


# A fit not trusted for other reasons (a bound, an undetermined parameter) whose misfit
# is this many times the noise or more, though not far above it, also names a constant
# offset that explains it: a small pedestal, or a dark level 0.4 % of the peak too high,
# ends such a fit at chi2 14 with sigma_s 27 % off, which before said nothing of it.
OFFSET_HINT_CHI2 = 4.0


def _offset_hint_below_far(far: bool, reasons: list[str], chi2_dof: float) -> bool:
    """Whether a fit whose misfit is not far above the noise (``far``: the offset was
    already looked for) still looks for a constant offset: it is not trusted for other
    ``reasons`` and its χ²/dof is at least :data:`OFFSET_HINT_CHI2`."""
    return (not far) and bool(reasons) and math.isfinite(chi2_dof) and chi2_dof >= OFFSET_HINT_CHI2


def _cut_series(model: _Model, the_scan, v: dict, options: FitOptions) -> list[str]:
    """A reason where the model marched a series (no tail solve, no extrapolation) whose
    per-bounce ratio measured by the scan, at the answer, says the orders past its
    ``bounces`` are not negligible: r^K/(1 − r) of I_1 above :data:`CUT_LIMIT`, or r ≥ 1.
    That happens where the bound called the series divergent (ρ ≥ 1 at the estimate:
    the paper's phase gains energy per bounce for g ≳ 0.7, ρ = ω·A(g)), where the count
    was sized from the ratio at the estimate and the answer's is higher, and where a
    count was given (``bounces: K``, or ``tail: null`` capping the march at
    ``max_bounces``). The reason names the setting that sums the orders left out:
    ``max_bounces`` changes nothing where the count was sized or given."""
    if model.tail is not None or model.extrapolate:
        return []
    r = the_scan.ratio_at(v["g"], v["sigma_s"] / v["sigma_t"])
    if not math.isfinite(r):
        r = model.rho
    left = math.inf if r >= 1 else r**model.bounces / (1 - r)
    if left <= CUT_LIMIT:
        return []
    cut = (
        f"the bounce series is cut at {model.bounces} bounces where it has not converged "
        f"(per-bounce ratio {r:.3f} at the answer, ρ {model.rho:.3f} at the estimate): "
        "the orders left out are not negligible; "
    )
    if r >= 1 or not model.converges:
        if options.phase == "paper":
            return [
                cut + "under phase: paper this medium gains light at every bounce and no "
                "count of bounces sums it: fit with fit: {phase: normalized} (--phase "
                "normalized), or the tank's depth (geometry: slab)"
            ]
        return [cut + f"fit: {{bounces: {max(2 * model.bounces, 8)}}} marches more of them"]
    need = _bucket_bounces(
        bounces_for_tolerance(min(r + RATIO_MARGIN, 0.995), options.tolerance, 10**9)
    )
    if options.tail is None:  # the march is capped at max_bounces
        return [cut + f"fit: {{max_bounces: {need}}} marches the bounces this ratio needs"]
    solve = "" if isinstance(options.bounces, int) else " or fit: {tail: bicgstab} (a tail solve)"
    return [cut + f"fit: {{bounces: {need}}} marches the bounces this ratio needs{solve}"]


def _model_shift(data: _Data, pattern, stage: _Stage, options: FitOptions) -> tuple:
    """r_fine − r at the solution (one render of :func:`_finer`'s model), that model, its
    tail solve's steps and convergence (``None`` without a tail) and its seconds."""
    fine = _finer(stage.model, options, stage.values["g"])
    renderer, full = _joint_parts(pattern, fine, options.phase)
    v = stage.values
    with stopwatch() as timing:
        unit, fine_tail = _render_model(renderer, full, pattern, fine, v, jnp.result_type(float))
    shift = (stage.weights * v["gain"] * (unit - stage.unit)).reshape(-1)
    return shift, fine, fine_tail, timing


def _verdict(
    the_scan: Scan, last: _Stage, budget, fine, fine_tail, options: FitOptions, peak, fit_black
) -> list[str]:
    """Why the answer ``last`` is not trustworthy (``[]``: it is): the budget's
    (:func:`untrustworthy`), a constant offset that explains its misfit, a tail solve or
    a march that did not converge, a worse basin than the scan's best."""
    v = last.values
    reasons = untrustworthy(v, budget, options.max_chi2, BLACK_RANGE if fit_black else None)
    far = math.isfinite(budget.chi2_model) and budget.chi2_model > options.max_chi2
    if far:
        reasons += _offset_reason(the_scan, last, peak)
    reasons += tail_unconverged(last.tail, last.model.tail_max_steps, "the model")
    reasons += tail_unconverged(fine_tail, fine.tail_max_steps if fine else 0, "the finer model")
    reasons += _cut_series(last.model, the_scan, v, options)
    other = worse_basin(the_scan, v["g"], v["sigma_s"] / v["sigma_t"], options.basin_tolerance)
    if other is not None:
        reasons.append(
            f"in a worse basin than the scan's best (g {other.g:.2f}, albedo "
            f"{other.albedo:.2f}, scan misfit {other.misfit:.3g})"
        )
    if _offset_hint_below_far(far, reasons, budget.chi2_dof):
        reasons += _offset_reason(the_scan, last, peak)
    return reasons


def _joint_fit(
    data: _Data, pattern, options: FitOptions, black, images, crop, rho0, floor, say, start=None
):
    """The joint fit with its global start (:mod:`lightfield_jax.inverse.basins`): scan, solve
    every basin kept (or the given start: ``start`` = (σt, σs, g, b), else
    ``options.start`` = (σs, g)), keep the best; then the error budget and the verdict.
    Returns the model, the seconds, the :func:`_finish` keywords and the last stage."""
    seconds = {"compile": 0.0, "run": 0.0}

    def count(t):
        seconds["compile"] += t["compile"] if isinstance(t, dict) else t.compile
        seconds["run"] += t["run"] if isinstance(t, dict) else t.run

    coarse = _scan_model(crop, options, rho0)
    if data.exposure is None:  # merged brackets: the variance follows T, not I alone
        data = dataclasses.replace(data, noise_floor=noise_floor(data.images, data.mask, pattern))
        if data.noise_floor is not None:
            say(f"  read noise seen: weights 1/sqrt(I + {data.noise_floor:.3g})")
    weights = joint_weights(data.images, data.valid, data.exposure, data.noise_floor)
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
    scan_model = dataclasses.replace(coarse, cell=CHEAP_CELL)
    the_scan = _run_scan(data, pattern, scan_model, options, black, weights, data.sigma_t0)
    count(the_scan.seconds)
    st0 = data.sigma_t0
    from_scan = start is None and options.start is None
    scanned = [st0]
    if from_scan and st0 >= SHORT_DECAY:
        # A mean free path of a few pixels or less: the decay estimate runs low (below),
        # so the scan is made at larger σt too and the one with the best misfit kept.
        for factor in SIGMA_T_FACTORS:
            other = _run_scan(data, pattern, scan_model, options, black, weights, st0 * factor)
            count(other.seconds)
            scanned.append(st0 * factor)
            if other.basins and (
                not the_scan.basins or other.basins[0].misfit < the_scan.basins[0].misfit
            ):
                the_scan = other
        values = ", ".join(f"{v:.3g}" for v in scanned)
        say(f"  scanned at sigma_t {values}: kept {the_scan.sigma_t:.3g}")
    peak = float(np.max(np.where(data.valid, data.images, -np.inf)))
    # Not in the censoring refit from an answer (``start``): joint_fit does not refit
    # a fit that stopped, and one that did not is refined as it was.
    stop = [] if start is not None else _offset_stop(the_scan, options, peak)
    if stop:
        say(f"  {stop[0]}")
    if start is not None:
        starts = [("given", tuple(start) if black is None else (*start[:3], black))]
    elif options.start is not None:
        ss, g = options.start
        starts = [("given", (st0, ss, g, 0.0 if black is None else black))]
    else:
        found = the_scan.basins if options.basin_search else the_scan.basins[:1]
        if not found:
            raise ValueError(
                "the basin scan found no valid model for this capture (every albedo's "
                "bounce series diverges or is truncated): give bounces or a start"
            )
        starts = _starts_of("basin", the_scan, enumerate(found[: 1 if stop else None]), black)
    # One cheap model for every start: marched where the scan's measured ratio at each
    # start allows it (see _by_measured_ratio).
    ratio = max(the_scan.ratio_at(s[2], s[1] / s[0]) for _, s in starts)
    coarse = _extrapolated(_by_measured_ratio(coarse, options, ratio), options)
    if coarse.extrapolate:  # always corrected to the full final model
        coarse = dataclasses.replace(coarse, cell=CHEAP_CELL)
    if the_scan.ratios is not None:
        say(f"  measured per-bounce ratio {ratio:.3f}")
    say(f"  the solve's model: {_orders(coarse)}")
    tried, stages, labels = [], [], []
    origins = {}  # per anchoring answer, its misfit on the cheap model (_downhill_from)
    dtype = jnp.result_type(float)
    rescan = None
    pending = list(starts)
    while True:
        if (
            not pending
            and rescan is None
            and from_scan
            and options.basin_search
            and stages
            and not stop
        ):
            pending, rescan = _rescan(
                data, pattern, scan_model, options, black, weights, the_scan, stages, say
            )
            if rescan is not None:
                count(rescan.seconds)
                first_scan, the_scan = the_scan, rescan
        if not pending:
            break
        label, start = pending.pop(0)
        say(f"joint fit from {label}: sigma_s {start[1]:.4g}, g {start[2]:.3f}")
        record = {
            "label": label,
            "start": {"sigma_t": start[0], "sigma_s": start[1], "g": start[2]},
        }
        with stopwatch() as timing:
            slope = next(
                (
                    i
                    for i, (f, _) in enumerate(stages)
                    if _anchors(f, the_scan, options, black)
                    and _downhill_from(
                        data, pattern, coarse, options, weights, start, f.values, origins
                    )
                ),
                None,
            )
        count(timing)
        if slope is not None:  # on the slope of an answer already found: not solved
            tried.append({**record, "same_as": labels[slope], "by": "a line downhill to it"})
            say(f"  {label}: on a slope down to {labels[slope]}'s answer")
            continue
        y0 = pack(start, black is None, dtype)
        first, ran, retried = _cheap_solve(data, pattern, coarse, options, black, weights, y0, say)
        for stage in ran:
            count(stage)
        if retried is not None:
            record["retried"] = retried
        same = next(
            (i for i, (f, _) in enumerate(stages) if _same_answer(f.values, first.values)), None
        )
        if same is not None:  # the cheap model's answer of an earlier start: not again
            tried.append({**record, "same_as": labels[same], "iterations": first.steps})
            say(f"  {label}: the same answer as {labels[same]}")
            continue
        best = min(stages, key=lambda pair: pair[1].rms, default=None)
        last = (
            first  # a pedestal's misfit: the final model's solves would chase it
            if stop
            else _continuation(
                data, pattern, first, options, black, images, floor, the_scan, say, best
            )
        )
        if last.unrefined is not None:  # worse than an answer found: not a candidate
            tried.append(
                {
                    **record,
                    "cheap": {k: first.values[k] for k in ("sigma_t", "sigma_s", "g")},
                    "not_refined": last.unrefined,
                    "iterations": first.steps,
                }
            )
            continue
        steps = first.steps
        if last is not first:  # else its seconds and steps are counted already
            count(last)
            steps += last.steps
        tried.append(
            {
                **record,
                "final": {k: last.values[k] for k in ("sigma_t", "sigma_s", "g")},
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
        stages.append((first, last))
        labels.append(label)
    # The best final misfit (models may differ between starts: the weighted RMS is
    # comparable across them).
    best = min(range(len(stages)), key=lambda i: stages[i][1].rms)
    last = stages[best][1]
    solved = [r for r in tried if "final" in r]
    for i, record in enumerate(solved):
        record["chosen"] = i == best

    names = ["sigma_t", "sigma_s", "g", "gain"] + (["black_level"] if black is None else [])
    fit_black = black is None
    noise = noise_scale(data.images, last.weights, pattern, last.values["gain"] * last.unit)
    shift, fine, fine_tail = None, None, None
    if options.model_error and not stop:
        shift, fine, fine_tail, t = _model_shift(data, pattern, last, options)
        count(t)
    groups = split_groups(data.images.shape, pattern)
    kappa = None if fine is None else richardson_factor(last.model, fine)
    step = kappa if options.extrapolate else None
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
        reasons = _verdict(the_scan, last, budget, fine, fine_tail, options, peak, fit_black)
    ok, msg = last.ok, last.message
    if reasons:
        ok, msg = False, "not trustworthy: " + "; ".join(reasons) + f" (solver: {msg})"
    model_dict = last.model.as_dict()
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
            # κ: the model is κ × its step to the finer model from the continuum (None:
            # not refined in space); the answer's step there where it took it
            # (``extrapolate``), else the model term held κ × the step.
            "extrapolation": None
            if kappa is None
            else {"factor": kappa, "step": budget.extrapolation or None},
            "bounces": fine.bounces,
            "extrapolated": fine.extrapolate,
            "coarse_after": fine.coarse,
            **(
                {
                    "n_mu": fine.geometry.n_mu,
                    "n_z": fine.geometry.n_z,
                    "depth_profile": fine.geometry.profile,
                }
                if fine.geometry is not None
                else {}
            ),
            **(
                {"tail": {"method": fine.tail, "tol": fine.tail_tol, **fine_tail}}
                if fine_tail is not None
                else {}
            ),
        }
    scan_dict = the_scan.as_dict()
    scan_dict["tried"] = tried
    if stop:
        scan_dict["stopped"] = "a constant offset explains the scan's misfit (offset_stop)"
    if len(scanned) > 1:
        scan_dict["sigma_t_scanned"] = scanned
    if rescan is not None:  # the_scan is the rescan; the first one is the scan kept before
        scan_dict["first_scan"] = first_scan.as_dict()
    return (
        last.model,
        seconds,
        dict(
            method="joint",
            sigma_t=answer["sigma_t"],
            sigma_s=answer["sigma_s"],
            g=answer["g"],
            gain=answer["gain"],
            black_level=answer["black_level"],
            budget=budget,
            converged=ok,
            message=msg,
            iterations=sum(r.get("iterations", 0) for r in tried),
            residual=last.rms,
            basins=scan_dict,
            reasons=tuple(reasons),
            model_dict=model_dict,
        ),
        last,
    )


# Values whose fitted light lies within this many noise σ below the clip are masked too:
# the clip dropped the upward fluctuations of those values and kept the downward ones
# (censoring), which biases the fit low there (σt −0.64 %, −3.2σ, at a 5 % clip).
CLIP_SIGMAS = 3.0
# The censoring refit is not made where it would mask more than this share of the
# values left (the clip's level cannot be where most of the capture's light is).
CENSOR_MOST = 0.25


def near_the_clip(
    data: _Data, fitted: np.ndarray, sigma: np.ndarray, floor: bool | None = None
) -> np.ndarray | None:
    """The valid values of ``data`` whose ``fitted`` light plus ``CLIP_SIGMAS`` times
    their noise ``sigma`` reaches the clip's level there (``data.clip_level``, per
    value), or minus that reaches the floor's (``data.floor_level``: values clamped
    from below), or ``None`` where none does, nothing was clipped or the noise is
    unknown. ``floor``: only the floor's (``True``) or only the clip's (``False``)."""
    risk = np.zeros(data.valid.shape, bool)
    for level, low in ((data.clip_level, False), (data.floor_level, True)):
        if level is None or floor is (not low):  # nothing was clipped there, or not asked
            continue
        if np.shape(fitted) != level.shape:
            raise ValueError(f"near_the_clip: fitted {np.shape(fitted)} against {level.shape}")
        with np.errstate(invalid="ignore"):
            if low:
                risk |= data.valid & (fitted - CLIP_SIGMAS * sigma <= level)
            else:
                risk |= data.valid & (fitted + CLIP_SIGMAS * sigma >= level)
    return risk if risk.any() else None


def _stage_sigma(stage, noise: float) -> np.ndarray:
    """The 1σ of each value's noise at ``stage`` (α/w², the weights' variance model),
    NaN where it is masked or the noise is unknown."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sqrt(noise) / np.where(stage.weights > 0, stage.weights, np.nan)


def joint_fit(problem, options: FitOptions, say):
    """The joint fit of a :class:`~lightfield_jax.inverse.data.FitProblem` (the model,
    seconds and :func:`_finish` keywords). Where values were clipped, the values the
    answer puts within ``CLIP_SIGMAS`` of the clip are masked and the fit solved once
    more from its answer; the first answer is kept where that one fails or is not
    trusted (``model.censoring`` in the result says what was done)."""

    def run(data, start=None):
        return _joint_fit(
            data,
            problem.pattern,
            options,
            problem.black_level,
            problem.images,
            problem.model.crop,
            problem.rho0,
            problem.floor,
            say,
            start,
        )

    model, seconds, values, last = run(problem.data)
    noise = values["budget"].noise
    if not math.isfinite(noise) or "stopped" in values["basins"]:
        # (stopped: a constant offset explains the misfit; values near a clip are not
        # what keeps such a fit from being trusted)
        return model, seconds, values
    data = problem.data
    fitted, sigma = last.values["gain"] * last.unit, _stage_sigma(last, noise)
    top = near_the_clip(data, fitted, sigma, floor=False)
    low = near_the_clip(data, fitted, sigma, floor=True)
    if top is None and low is None:
        return model, seconds, values
    left = int(data.valid.sum())
    n_top = 0 if top is None else int(top.sum())
    n_low = 0 if low is None else int(low.sum())
    record = {"values_near_clip": n_top, "values_near_floor": n_low, "sigmas": CLIP_SIGMAS}
    if n_top > CENSOR_MOST * left:
        say(f"  {n_top} of {left} values near the clip: not masked (more than {CENSOR_MOST:.0%})")
        values["model_dict"]["censoring"] = {**record, "refit": "skipped: too many"}
        return model, seconds, values
    risk = near_the_clip(data, fitted, sigma)  # both: the clip's and the floor's
    n = int(risk.sum())
    say(
        f"  {n} value(s) within {CLIP_SIGMAS:g} sigma of the clip or the floor (censored): "
        "masked, solved again"
    )
    valid = data.valid & ~risk
    censored = dataclasses.replace(
        data, images=np.where(valid, data.images, 0.0), mask=np.all(valid, axis=0), samples=valid
    )
    v = last.values
    first = {k: float(v[k]) for k in ("sigma_t", "sigma_s", "g")}
    try:
        model2, more, values2, _ = run(
            censored, (v["sigma_t"], v["sigma_s"], v["g"], v["black_level"])
        )
    except ValueError as e:
        failed = f"failed ({e})"
    else:
        seconds = {k: seconds[k] + more[k] for k in seconds}
        numbers = [values2[k] for k in ("sigma_t", "sigma_s", "g", "gain")]
        if values2["converged"] or not values["converged"]:
            if all(math.isfinite(float(x)) for x in numbers):
                values2["iterations"] += values["iterations"]
                values2["model_dict"]["censoring"] = {**record, "refit": "kept", "first": first}
                return model2, seconds, values2
        failed = f"not kept ({values2['message']})"
    say(f"  the refit without the values near the clip {failed}: the first answer kept")
    values["model_dict"]["censoring"] = {**record, "refit": failed, "first": first}
    return model, seconds, values
