"""Whether a fit's answer can be trusted: the rules shared by the joint fit and the
two-step methods, each giving the reasons not to trust it (empty: none).

- Not trustworthy (``converged: false`` with the reason, never converged): a solution
  at a parameter bound (:func:`at_bound`), a parameter its 1σ does not determine
  (:func:`unidentified`), a gain that is not positive (:func:`negative_gain`), a
  misfit far above the noise and the model's own error (judged on the
  :class:`~lightfield_jax.inverse.budget.Uncertainty` of
  :mod:`lightfield_jax.inverse.budget`; :func:`untrustworthy` gathers these four), or
  one whose model summed its bounce series' tail with a solve that stopped before its
  tolerance (:func:`tail_unconverged`: the model there is not the series).
- A misfit far above the noise that one constant in every image value explains is
  named with that constant (:func:`constant_offset`, :func:`offset_hint`): a camera
  pedestal left in the images, or a dark frame that subtracts too much.

The joint fit's own verdict (a worse basin than the scan's best, a cut series, when to
stop after the scan) is :mod:`lightfield_jax.inverse.joint_fit.verdict`.
"""

from __future__ import annotations

import math

import numpy as np

from lightfield_jax.inverse.budget import PHYSICAL, Uncertainty
from lightfield_jax.inverse.lstsq import column_norms

# A solution this close to a constraint's edge is at a bound: |g| ≥ G_BOUND, albedo
# below ALBEDO_BOUNDS[0] or above [1], the black level within 0.01 of its range.
G_BOUND = 0.95
ALBEDO_BOUNDS = (0.005, 0.9995)


def at_bound(values: dict, black_range: tuple[float, float] | None = None) -> list[str]:
    """The parameters of a solution that sit at a bound of the model (empty: none).
    ``values`` holds sigma_t, sigma_s, g (and black_level when ``black_range`` is given:
    it was fitted)."""
    reasons = []
    g = values["g"]
    albedo = values["sigma_s"] / values["sigma_t"]
    if abs(g) >= G_BOUND - 1e-6:  # float32's 0.95 is 0.94999999 (the grid's end)
        reasons.append(f"g = {g:.3f} is at its bound (|g| >= {G_BOUND})")
    lo, hi = ALBEDO_BOUNDS
    if not lo < albedo < hi:
        reasons.append(f"albedo = {albedo:.4f} is at its bound (outside ({lo}, {hi}))")
    if black_range is not None:
        b = values["black_level"]
        if not black_range[0] + 0.01 < b < black_range[1] - 0.01:
            reasons.append(f"black level = {b:.3f} is at its bound {list(black_range)}")
    return reasons


# The largest statistical 1σ of an identified parameter: relative for σt and σs,
# absolute for g (whose range is 2). Beyond it the linearised error does not describe
# the fit: on a capture of ~10³ photons at its peak (the paper's milk, 64×48), fitted
# with first-stage weights from the data's local mean (an experiment, not kept), the
# answer had σs ± 215 %, g −0.88 ± 0.20 with the truth g 0.4, 6σ away.
IDENTIFIED = 0.5


def unidentified(values: dict, budget: Uncertainty) -> list[str]:
    """The parameters whose 1σ exceeds :data:`IDENTIFIED` (relative for σt and σs,
    absolute for g): the statistical one (the capture's noise alone: the capture does
    not determine them), else the total one (noise ⊕ the model's error: the model does
    not, e.g. the parts of the capture disagree by more than that). Empty: all are
    determined (NaN where not measured)."""
    reasons = []
    for name in PHYSICAL:
        relative = name != "g"
        scale = abs(values[name]) if relative else 1.0
        for part, what in (
            ("statistical", "statistical 1σ (the capture's noise alone)"),
            ("total", "total 1σ (the noise and the model's error)"),
        ):
            sd = getattr(budget, part).get(name, math.nan)
            if math.isfinite(sd) and sd > IDENTIFIED * scale:
                spread = f"{100 * sd / scale:.0f} %" if relative else f"{sd:.2f}"
                reasons.append(
                    f"{name} is not identifiable from this capture: its {what} is ± {spread}"
                )
                break
    return reasons


def negative_gain(values: dict) -> list[str]:
    """The reason a solution is not to be trusted when its gain (the images' scale
    against the model's light) is not positive: the images are darker where the model
    puts light (negated images, or a dark frame brighter than them). Empty: it is
    positive (or not given)."""
    gain = values.get("gain", math.nan)
    if math.isfinite(gain) and gain <= 0:
        return [
            f"the gain is {gain:.4g}, not positive: the images are darker where the model "
            "puts light (negated images, or a dark frame subtracted that is brighter than "
            "them?)"
        ]
    return []


def untrustworthy(
    values: dict,
    budget: Uncertainty,
    max_chi2: float,
    black_range: tuple[float, float] | None = None,
) -> list[str]:
    """The reasons a solution is not to be trusted (empty: none): :func:`at_bound`, a
    parameter the capture's noise does not determine (:func:`unidentified`), a gain
    that is not positive (:func:`negative_gain`), and a misfit far above ``max_chi2``
    judged by ``budget.chi2_model`` (noise ⊕ the model's own error, or the noise alone
    where that error was not measured: said so)."""
    reasons = at_bound(values, black_range) + unidentified(values, budget)
    reasons += negative_gain(values)
    if math.isfinite(budget.chi2_model) and budget.chi2_model > max_chi2:
        if budget.model_measured:
            reasons.append(
                f"misfit far above the capture's noise and the model's own error: chi2/dof "
                f"= {budget.chi2_model:.3g} > {max_chi2:g} (against the noise alone: "
                f"{budget.chi2_dof:.3g})"
            )
        else:  # no finer model's error measured: judged against the noise alone
            reasons.append(
                f"misfit far above the capture's noise: chi2/dof = {budget.chi2_model:.3g} "
                f"> {max_chi2:g} (the model's own error not measured)"
            )
    return reasons


# A misfit far above the noise that one constant added to every image value would take
# to OFFSET_EXPLAINS of itself or less (linearised at the answer, beside the parameters'
# columns) is reported with that constant: a camera's pedestal (black offset) left in
# the images, or a dark frame that subtracts too much, is light the model does not have.
OFFSET_EXPLAINS = 0.25


def constant_offset(jac: np.ndarray, residual: np.ndarray, weights: np.ndarray):
    """The constant d in every image value (images = model + d) that best explains the
    weighted residual r = w·(model − images) beside the columns of ``jac`` (linearised
    at the answer), and the misfit left with it as a fraction of the misfit without:
    ``(d, fraction)`` (``(nan, 1.0)`` where it cannot be told)."""
    r = np.asarray(residual, np.float64).reshape(-1)
    w = np.asarray(weights, np.float64).reshape(-1)
    j = np.asarray(jac, np.float64)
    total = float(r @ r)
    if not (np.all(np.isfinite(j)) and np.all(np.isfinite(r)) and total > 0):
        return math.nan, 1.0
    q, _ = np.linalg.qr(j / column_norms(j))
    r_left = r - q @ (q.T @ r)
    column = -w - q @ (q.T @ -w)
    norm2 = float(column @ column)
    if not norm2 > 1e-12 * float(w @ w):
        return math.nan, 1.0
    d = float(column @ r_left) / norm2
    left = float(r_left @ r_left)  # what the parameters' columns leave (at an answer: r)
    return d, max(left - d * d * norm2, 0.0) / left if left > 0 else 1.0


def offset_hint(d: float, left: float, where: str, peak: float) -> list[str]:
    """A reason's hint where a constant offset ``d`` leaves at most
    :data:`OFFSET_EXPLAINS` of a misfit (``left``: the fraction it leaves of ``where``'s
    misfit), ``[]`` otherwise; ``peak``: the images' peak value."""
    if not (math.isfinite(d) and left <= OFFSET_EXPLAINS):
        return []
    cause = (
        "a camera pedestal (black offset) left in the images? (a capture file removes it "
        "with a dark_frame or dark_level)"
        if d > 0
        else "a dark frame or dark_level that subtracts too much?"
    )
    share = f" ({d / peak:+.1%} of the peak)" if peak > 0 and math.isfinite(peak) else ""
    return [
        f"a constant {d:+.4g} in every image value{share} would leave {left:.1%} of the "
        f"{where} misfit: {cause}"
    ]


def tail_unconverged(tail: dict | None, max_steps: int, what: str) -> list[str]:
    """The reason a solution is not to be trusted when ``what``'s tail solve (``tail``:
    its ``steps``, ``converged`` and, where a tangent solve raised, ``error``; ``None``
    without a tail) did not converge (empty: it did, or there is none)."""
    if tail is None or tail["converged"]:
        return []
    detail = tail.get("error") or f"{tail['steps']} iterations"
    return [
        f"the tail solve of {what} did not converge within tail_max_steps = {max_steps} ({detail})"
    ]


__all__ = [
    "ALBEDO_BOUNDS",
    "G_BOUND",
    "IDENTIFIED",
    "OFFSET_EXPLAINS",
    "at_bound",
    "constant_offset",
    "negative_gain",
    "offset_hint",
    "tail_unconverged",
    "unidentified",
    "untrustworthy",
]
