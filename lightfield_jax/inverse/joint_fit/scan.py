"""The joint fit's basin scans on the cheap model (:mod:`lightfield_jax.inverse.basins`):
at the direct light's decay estimate of σt and, for a short mean free path, at larger σt
too (:func:`basin_scan`); again at an answer's σt far from the scan's
(:func:`rescan`); and the starts the scans' basins give (:func:`starts_of`)."""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from lightfield_jax.inverse.basins import Scan, basin_of, basins, nearest_point, scan
from lightfield_jax.inverse.joint_fit.context import FitContext, Seconds
from lightfield_jax.inverse.joint_fit.stage import joint_parts
from lightfield_jax.inverse.model_size import SCAN_TAIL_BOUNCES, ModelSpec
from lightfield_jax.runtime.timing import stopwatch
from lightfield_jax.scene.phase import phase_integral_at

# An answer whose σt is more than this factor from the scan's (the direct light's decay
# estimate) is checked by a second scan at its σt (:func:`rescan`). Measured on 32x24
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


def rho_of(phase: str):
    """ρ(g, albedos) of the model's phase convention (ω for the slab and ``normalized``)."""

    def rho(g: float, albedos):
        a = float(phase_integral_at(g)) if phase == "paper" else 1.0
        return np.asarray(albedos) * a

    return rho


def run_scan(ctx: FitContext, model: ModelSpec, sigma_t0: float) -> Scan:
    """The basin scan of ``model`` at σt = ``sigma_t0`` with the data's weights."""
    options = ctx.options
    extrapolate = model.tail is not None
    if extrapolate:
        model = dataclasses.replace(model, bounces=SCAN_TAIL_BOUNCES, tail=None)
    renderer, full = joint_parts(ctx.pattern, model, options.model.phase)
    dtype = jnp.result_type(float)
    with stopwatch() as timing:
        cost, black_map, gs, albedos, ratios, refs, offset = scan(
            renderer,
            full,
            jnp.asarray(ctx.data.images, dtype),
            jnp.asarray(ctx.weights, dtype),
            sigma_t0,
            phase=options.model.phase,
            lit=ctx.pattern.lit,
            black_level=ctx.black,
            rho_limit=rho_of(options.model.phase),
            extrapolate=extrapolate,
        )
    found = basins(
        cost, black_map, gs, albedos, options.trust.basin_tolerance, options.trust.max_basins
    )
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


def basin_scan(
    ctx: FitContext, model: ModelSpec, seconds: Seconds, widen: bool
) -> tuple[Scan, list[float]]:
    """The scan at the data's decay estimate of σt and, where ``widen`` and that
    estimate is at least :data:`SHORT_DECAY`, at :data:`SIGMA_T_FACTORS` times it too:
    the scan of the lowest misfit, and every σt scanned."""
    st0 = ctx.data.sigma_t0
    the_scan = run_scan(ctx, model, st0)
    seconds.add(**the_scan.seconds)
    scanned = [st0]
    if widen and st0 >= SHORT_DECAY:
        # A mean free path of a few pixels or less: the decay estimate runs low (above),
        # so the scan is made at larger σt too and the one with the best misfit kept.
        for factor in SIGMA_T_FACTORS:
            other = run_scan(ctx, model, st0 * factor)
            seconds.add(**other.seconds)
            scanned.append(st0 * factor)
            if other.basins and (
                not the_scan.basins or other.basins[0].misfit < the_scan.basins[0].misfit
            ):
                the_scan = other
        values = ", ".join(f"{v:.3g}" for v in scanned)
        ctx.say(f"  scanned at sigma_t {values}: kept {the_scan.sigma_t:.3g}")
    return the_scan, scanned


def home_basin(scan: Scan, values: dict):
    """The grid point of ``scan``'s local minimum whose basin holds ``values``."""
    p = nearest_point(scan.gs, scan.albedos, values["g"], values["sigma_s"] / values["sigma_t"])
    return basin_of(scan.misfit, *p) if np.isfinite(scan.misfit[p]) else None


def starts_of(label: str, scan: Scan, found, black: float | None) -> list:
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


def rescan(ctx: FitContext, model: ModelSpec, the_scan: Scan, found: dict, n_found: int):
    """The scan held σt at the direct light's decay estimate. An answer far from it (a
    medium whose mean free path is near a pixel: that decay spans few pixels) may lie
    in a basin the scan at the estimate never saw: where the best answer ``found``'s σt
    is more than ``RESCAN_RATIO`` from the scan's, the scan again at that σt, and its
    basins other than the answer's own as further starts (at most ``max_basins`` less
    the ``n_found`` answers, at least one). Returns ``(starts, scan)``, or
    ``([], None)`` where no rescan is needed."""
    if abs(math.log(found["sigma_t"] / the_scan.sigma_t)) <= math.log(RESCAN_RATIO):
        return [], None
    ctx.say(f"basin scan again at the answer's sigma_t {found['sigma_t']:.4g}")
    again = run_scan(ctx, model, found["sigma_t"])
    home = home_basin(again, found)
    others = [(i, b) for i, b in enumerate(again.basins) if b.index != home]
    others = others[: max(ctx.options.trust.max_basins - n_found, 1)]
    return starts_of("rescan basin", again, others, ctx.black), again


__all__ = [
    "RESCAN_RATIO",
    "SHORT_DECAY",
    "SIGMA_T_FACTORS",
    "basin_scan",
    "home_basin",
    "rescan",
    "rho_of",
    "run_scan",
    "starts_of",
]
