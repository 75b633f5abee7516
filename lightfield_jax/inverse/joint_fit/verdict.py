"""Why a joint fit's answer is not trustworthy (:func:`verdict`): the error budget's
reasons, a constant offset that explains the misfit (:func:`offset_reason`; one large
enough stops the fit after the scan, :func:`offset_stop`), a tail solve or a march that
did not converge (:func:`cut_series`), a worse basin than the scan's best."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from lightfield_jax.inverse.basins import Scan, worse_basin
from lightfield_jax.inverse.joint_fit.context import FitContext
from lightfield_jax.inverse.joint_fit.stage import Stage
from lightfield_jax.inverse.model_size import RATIO_MARGIN, ModelSpec, bucket_bounces
from lightfield_jax.inverse.verdict import (
    OFFSET_EXPLAINS,
    constant_offset,
    offset_hint,
    tail_unconverged,
    untrustworthy,
)
from lightfield_jax.scene.medium import bounces_for_tolerance

if TYPE_CHECKING:
    from lightfield_jax.inverse.settings import FitSettings


# A marched series whose left-out orders exceed this share of I_1 is not a model of the
# capture (the limit the two-step methods apply to a convergent series' march,
# methods.TRUNCATION_LIMIT).
CUT_LIMIT = 0.01


def offset_stop(
    the_scan: Scan, options: FitSettings, peak: float, from_start: bool = False
) -> list[str]:
    """The reason to stop after the basin scan (``[]``: go on): a constant offset in
    every image value leaves less than ``options.trust.offset_stop`` of the scan's best
    misfit. The scan's misfit then is mostly that constant, many times the noise and the
    cheap model's own error, and the full model's solves would chase it (g toward its
    bound, the model growing with it) for minutes to end not trusted. ``from_start``:
    the fit solves a start it was given, not the scan's basins."""
    found = the_scan.offset
    if found is None or not found.fraction < options.trust.offset_stop:
        return []
    hint = offset_hint(found.value, found.fraction, "basin scan's", peak)
    if not hint:
        return []
    solved = "the given start's" if from_start else "its best basin's"
    return [
        f"{hint[0]}; the fit stopped after the scan and {solved} cheap solve "
        f"(offset_stop: {options.trust.offset_stop:g})"
    ]


def offset_reason(the_scan: Scan, last: Stage, peak: float) -> list[str]:
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


def offset_hint_below_far(far: bool, reasons: list[str], chi2_dof: float) -> bool:
    """Whether a fit whose misfit is not far above the noise (``far``: the offset was
    already looked for) still looks for a constant offset: it is not trusted for other
    ``reasons`` and its χ²/dof is at least :data:`OFFSET_HINT_CHI2`."""
    return (not far) and bool(reasons) and math.isfinite(chi2_dof) and chi2_dof >= OFFSET_HINT_CHI2


def cut_series(model: ModelSpec, the_scan, v: dict, options: FitSettings) -> list[str]:
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
        if options.model.phase == "paper":
            return [
                cut + "under phase: paper this medium gains light at every bounce and no "
                "count of bounces sums it: fit with fit: {phase: normalized} (--phase "
                "normalized), or the tank's depth (geometry: slab)"
            ]
        return [cut + f"fit: {{bounces: {max(2 * model.bounces, 8)}}} marches more of them"]
    need = bucket_bounces(
        bounces_for_tolerance(min(r + RATIO_MARGIN, 0.995), options.model.tolerance, 10**9)
    )
    if options.model.tail is None:  # the march is capped at max_bounces
        return [cut + f"fit: {{max_bounces: {need}}} marches the bounces this ratio needs"]
    solve = (
        "" if isinstance(options.model.bounces, int) else " or fit: {tail: bicgstab} (a tail solve)"
    )
    return [cut + f"fit: {{bounces: {need}}} marches the bounces this ratio needs{solve}"]


def verdict(
    ctx: FitContext, the_scan: Scan, last: Stage, budget, fine, fine_tail, peak
) -> list[str]:
    """Why the answer ``last`` is not trustworthy (``[]``: it is): the budget's
    (:func:`untrustworthy`), a constant offset that explains its misfit, a tail solve or
    a march that did not converge, a worse basin than the scan's best."""
    options, v = ctx.options, last.values
    reasons = untrustworthy(v, budget, options.trust.max_chi2, ctx.black_range)
    far = math.isfinite(budget.chi2_model) and budget.chi2_model > options.trust.max_chi2
    if far:
        reasons += offset_reason(the_scan, last, peak)
    reasons += tail_unconverged(last.tail, last.model.tail_max_steps, "the model")
    reasons += tail_unconverged(fine_tail, fine.tail_max_steps if fine else 0, "the finer model")
    reasons += cut_series(last.model, the_scan, v, options)
    other = worse_basin(
        the_scan, v["g"], v["sigma_s"] / v["sigma_t"], options.trust.basin_tolerance
    )
    if other is not None:
        reasons.append(
            f"in a worse basin than the scan's best (g {other.g:.2f}, albedo "
            f"{other.albedo:.2f}, scan misfit {other.misfit:.3g})"
        )
    if offset_hint_below_far(far, reasons, budget.chi2_dof):
        reasons += offset_reason(the_scan, last, peak)
    return reasons


__all__ = [
    "CUT_LIMIT",
    "OFFSET_HINT_CHI2",
    "cut_series",
    "offset_hint_below_far",
    "offset_reason",
    "offset_stop",
    "verdict",
]
