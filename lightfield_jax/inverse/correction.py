"""Defect correction: the answer of a large model from primal renders alone.

The joint fit solves on a cheap model (few θ bins, the native grid) because every
solver step needs a forward-mode Jacobian: three tangents through every bounce. The
model the answer needs (more θ bins, a refined grid for forward scattering, more
bounces) is then reached by the classical defect-correction iteration

    p ← p − J_c⁺ · r(p),

r the weighted residual of the large model (one primal render per iteration, the gain
in closed form as in the solve) and J_c the cheap model's Jacobian at its answer,
re-weighted and re-scaled to the current gain. It converges linearly, at the rate
‖I − J_c⁺ J‖: the models differ by a few percent, so a few renders do what a full
solve on the large model did (measured: docs/fit_speed.md). Its fixed point solves
J_cᵀ r = 0 instead of Jᵀ r = 0: at a residual of pure noise the difference is a
fraction of the statistical 1σ of the size of J − J_c.

An iteration that stops shrinking, leaves the parameters' domain or meets a tail
solve that did not converge ends without an answer; the caller then solves on the
large model itself.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

# A step below this (relative on σt and σs, absolute on g and b), or below
# NOISE_FRACTION of the parameter's statistical 1σ, ends the iteration.
STEP_TOLERANCE = 2e-4
NOISE_FRACTION = 0.1
# Steps must shrink at least this fast after the second iteration.
MAX_RATE = 0.7


def design(weights, unit, gain: float, jac_unit) -> np.ndarray:
    """The weighted Jacobian ∂r/∂(σt, σs, g, gain[, b]) (N × p) of r = w·(gain·R − I)
    from R (P, h, w) and ∂R/∂(σt, σs, g[, b]) (P, h, w, n) at unit gain."""
    w = np.asarray(weights, np.float64)
    cols = (w[..., None] * gain * np.asarray(jac_unit, np.float64)).reshape(-1, jac_unit.shape[-1])
    wr = (w * np.asarray(unit, np.float64)).reshape(-1, 1)
    return np.concatenate([cols[:, :3], wr, cols[:, 3:]], axis=1)


def projected(weights, unit, obs) -> tuple[float, np.ndarray]:
    """The gain's least-squares value for model ``unit`` and the weighted residual."""
    w = np.asarray(weights, np.float64)
    wr = w * np.asarray(unit, np.float64)
    obs = np.asarray(obs, np.float64)
    gain = float(np.sum(wr * w * obs) / np.sum(wr * wr))
    return gain, (w * (gain * np.asarray(unit, np.float64) - obs)).reshape(-1)


@dataclasses.dataclass
class Correction:
    """The iteration's end: ``values`` (σt, σs, g, black level, gain) at its last render,
    the model there at unit gain, the weighted Jacobian and residual, one record per
    step, and why it stopped (``converged``: the last step was below tolerance)."""

    values: dict
    unit: np.ndarray | None
    jac: np.ndarray | None
    residual: np.ndarray | None
    steps: list
    converged: bool
    reason: str
    tail: dict | None = None


def in_domain(v: dict, black_range) -> bool:
    """Whether σt > 0, 0 < σs < σt, |g| < 0.99 (and b inside ``black_range``)."""
    ok = v["sigma_t"] > 0 and 0 < v["sigma_s"] < v["sigma_t"] and abs(v["g"]) < 0.99
    if black_range is not None:
        ok = ok and black_range[0] < v["black_level"] < black_range[1]
    return bool(ok)


def correct(
    render: Callable[[dict], tuple[np.ndarray, dict | None]],
    obs,
    weights,
    values: dict,
    jac_unit,
    black_range: tuple[float, float] | None,
    max_iterations: int = 8,
    noise: float = float("nan"),
) -> Correction:
    """Defect-correct ``values`` (σt, σs, g, black_level) to the model ``render`` draws.

    ``render(values)`` returns the large model at unit gain (P, h, w) and its tail
    solve's ``{"steps", "converged"}`` (``None`` without a tail); ``jac_unit`` is the
    cheap model's ∂R/∂(σt, σs, g[, b]) at unit gain; ``black_range`` is the black
    level's range when it is fitted (``None``: given); ``noise`` is the variance of
    one weighted residual that the capture's noise gives (NaN: unknown), which sets
    how small a step must be to end the iteration."""
    names = ["sigma_t", "sigma_s", "g"] + (["black_level"] if black_range is not None else [])
    v = {k: float(values[k]) for k in ("sigma_t", "sigma_s", "g", "black_level")}
    steps, last_size = [], None
    unit = jac = residual = tail = None
    for it in range(max_iterations):
        rendered = v
        unit, tail = render(v)
        unit = np.asarray(unit, np.float64)
        if tail is not None and not tail["converged"]:
            reason = "its tail solve did not converge"
            return Correction(v, None, None, None, steps, False, reason, tail)
        if not np.all(np.isfinite(unit)):
            return Correction(v, None, None, None, steps, False, "a non-finite render", tail)
        gain, residual = projected(weights, unit, obs)
        jac = design(weights, unit, gain, jac_unit)
        delta, *_ = np.linalg.lstsq(jac, -residual, rcond=None)
        step = {k: float(d) for k, d in zip(names, np.delete(delta, 3), strict=True)}
        scale = {"sigma_t": v["sigma_t"], "sigma_s": v["sigma_s"], "g": 1.0, "black_level": 1.0}
        scale = {k: scale[k] * STEP_TOLERANCE for k in names}
        if noise > 0:  # a tenth of the statistical 1σ, where larger
            sigma = np.sqrt(noise * np.clip(np.diag(np.linalg.pinv(jac.T @ jac)), 0, None))
            sigma = np.delete(sigma, 3)
            scale = {
                k: max(scale[k], NOISE_FRACTION * s) for k, s in zip(names, sigma, strict=True)
            }
        size = max(abs(step[k]) / scale[k] for k in names) * STEP_TOLERANCE
        steps.append({"size": size, **step})
        v["gain"] = gain
        if size < STEP_TOLERANCE:
            return Correction(v, unit, jac, residual, steps, True, "converged", tail)
        if last_size is not None and it >= 2 and size > MAX_RATE * last_size:
            return Correction(v, unit, jac, residual, steps, False, "its steps stopped shrinking")
        last_size = size
        for _ in range(6):  # halved until inside the domain
            new = {**v, **{k: v[k] + step[k] for k in names}}
            if in_domain(new, black_range):
                break
            step = {k: s / 2 for k, s in step.items()}
        else:
            return Correction(v, unit, jac, residual, steps, False, "its step left the domain")
        v = new
    reason = f"no convergence in {max_iterations} renders"
    return Correction(rendered, unit, jac, residual, steps, False, reason, tail)


__all__ = ["Correction", "correct", "design", "in_domain", "projected"]
