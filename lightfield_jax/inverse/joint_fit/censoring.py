"""The joint fit of a capture (:func:`joint_fit`, the ``joint`` method's solve): one fit
(:func:`~.fit.fit_once`) and, where values were clipped, the values its answer puts
within the noise of the clip masked and the fit solved once more from its answer
(:func:`near_the_clip`)."""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

import numpy as np

from lightfield_jax.inverse.data import FitData
from lightfield_jax.inverse.joint_fit.fit import fit_once
from lightfield_jax.inverse.joint_fit.stage import Stage

if TYPE_CHECKING:
    from lightfield_jax.inverse.settings import FitSettings


# Values whose fitted light lies within this many noise σ below the clip are masked too:
# the clip dropped the upward fluctuations of those values and kept the downward ones
# (censoring), which biases the fit low there (σt −0.64 %, −3.2σ, at a 5 % clip).
CLIP_SIGMAS = 3.0
# The censoring refit is not made where it would mask more than this share of the
# values left (the clip's level cannot be where most of the capture's light is).
CENSOR_MOST = 0.25


def near_the_clip(
    data: FitData, fitted: np.ndarray, sigma: np.ndarray, floor: bool | None = None
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


def stage_sigma(stage: Stage, noise: float) -> np.ndarray:
    """The 1σ of each value's noise at ``stage`` (α/w², the weights' variance model),
    NaN where it is masked or the noise is unknown."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sqrt(noise) / np.where(stage.weights > 0, stage.weights, np.nan)


def joint_fit(problem, options: FitSettings, say, solver=None, start=None):
    """The joint fit of a :class:`~lightfield_jax.inverse.data.FitProblem`: the model,
    the seconds and the values of its :class:`~lightfield_jax.inverse.data.FitSolution`.
    Where values were clipped, the values the answer puts within ``CLIP_SIGMAS`` of the
    clip are masked and the fit solved once more from its answer; the first answer is
    kept where that one fails or is not trusted (``model.censoring`` in the result says
    what was done). ``solver`` and ``start``: the joint method's (``None``:
    Levenberg-Marquardt, the basin scan's starts)."""

    chosen = {"solver": solver, "given": start}
    answer = fit_once(problem, problem.data, options, say, **chosen)
    model, seconds, values, last = answer.model, answer.seconds, answer.values, answer.last
    noise = values["budget"].noise
    if not math.isfinite(noise) or "stopped" in values["basins"]:
        # (stopped: a constant offset explains the misfit; values near a clip are not
        # what keeps such a fit from being trusted)
        return model, seconds, values
    data = problem.data
    fitted, sigma = last.values["gain"] * last.unit, stage_sigma(last, noise)
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
        again = fit_once(
            problem,
            censored,
            options,
            say,
            (v["sigma_t"], v["sigma_s"], v["g"], v["black_level"]),
            **chosen,
        )
    except ValueError as e:
        failed = f"failed ({e})"
    else:
        model2, values2 = again.model, again.values
        seconds = {k: seconds[k] + again.seconds[k] for k in seconds}
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


__all__ = ["CENSOR_MOST", "CLIP_SIGMAS", "joint_fit", "near_the_clip", "stage_sigma"]
