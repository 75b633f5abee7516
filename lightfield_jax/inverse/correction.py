"""Defect correction: the answer of a large model from primal renders alone.

The joint fit solves on a cheap model (32 θ bins, the native grid, a long series cut
short and extrapolated) because every solver step needs a forward-mode Jacobian: three
tangents through every bounce. The model the answer needs (more θ bins, a refined grid
for forward scattering, the whole series) is then reached in two phases:

1. the defect-correction iteration p ← p − J_c⁺ · r(p): r the large model's weighted
   residual (one primal render per iteration, the gain in closed form as in the
   solve), J_c the cheap model's Jacobian at its answer (at the cheap model's gain:
   gain·∂R is what both models approximate). It converges linearly, at the rate
   ‖I − J_c⁺ J‖, to where J_cᵀ r = 0;
2. only where those steps stop shrinking (the cheap Jacobian too far from the large
   model's): the large model's own Jacobian J by forward differences at the best
   point so far (one primal render per parameter) and Gauss–Newton steps with it.
   Not every correction finishes this way, as that measures worse: on a forward medium
   at ω 0.99 (128×96, float32) the difference Jacobian moves σt from +0.6 % to +3.2 %
   off the truth along the flat σt–g valley.

An iteration that stops shrinking, leaves the parameters' domain, meets a non-finite
render or a tail solve that did not converge ends without an answer; the caller then
solves on a model of its own.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from lightfield_jax.inverse.lstsq import gram_inverse, scaled_lstsq

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
    renders: int = 0


def in_domain(v: dict, black_range) -> bool:
    """Whether σt > 0, 0 < σs < σt, |g| < 0.99 (and b inside ``black_range``)."""
    ok = v["sigma_t"] > 0 and 0 < v["sigma_s"] < v["sigma_t"] and abs(v["g"]) < 0.99
    if black_range is not None:
        ok = ok and black_range[0] < v["black_level"] < black_range[1]
    return bool(ok)


# Forward-difference steps of the large model's Jacobian: relative on σt and σs,
# absolute on g and b. The Jacobian is taken again at the answer when that lies more
# than REFRESH tolerances from where it was taken.
DIFFERENCE_STEP = 1e-3
REFRESH = 10.0


def _step_size(step: dict, v: dict, jac, names, noise: float) -> float:
    """max_k |step_k| / tolerance_k × STEP_TOLERANCE (below STEP_TOLERANCE: done), the
    tolerance STEP_TOLERANCE relative on σt, σs (absolute on g, b) or NOISE_FRACTION of
    the statistical 1σ where that is larger."""
    tol = {"sigma_t": v["sigma_t"], "sigma_s": v["sigma_s"], "g": 1.0, "black_level": 1.0}
    tol = {k: tol[k] * STEP_TOLERANCE for k in names}
    if noise > 0:
        sigma = np.sqrt(noise * np.clip(np.diag(gram_inverse(jac, pseudo=True)), 0, None))
        for k, s in zip(names, np.delete(sigma, 3), strict=True):
            tol[k] = max(tol[k], NOISE_FRACTION * s)
    return max(abs(step[k]) / tol[k] for k in names) * STEP_TOLERANCE


def parameter_names(fit_black: bool) -> list[str]:
    """The fitted parameters besides the gain: σt, σs, g (and b where it is fitted)."""
    return ["sigma_t", "sigma_s", "g"] + (["black_level"] if fit_black else [])


def gauss_newton_step(jac, residual, names, v: dict, noise: float) -> tuple[dict, float]:
    """The Gauss–Newton step of the weighted residual with ``jac`` (columns σt, σs, g,
    gain[, b]: :func:`design`) as ``{name: step}`` (the gain's dropped: projected) and
    its size against the tolerance (:func:`_step_size`)."""
    delta = scaled_lstsq(jac, -residual)
    step = {k: float(d) for k, d in zip(names, np.delete(delta, 3), strict=True)}
    return step, _step_size(step, v, jac, names, noise)


def correct(
    render: Callable[[dict], tuple[np.ndarray, dict | None]],
    obs,
    weights,
    values: dict,
    jac_unit,
    black_range: tuple[float, float] | None,
    max_iterations: int = 16,
    noise: float = float("nan"),
) -> Correction:
    """Correct ``values`` (σt, σs, g, black_level, gain: the cheap model's answer) to
    the model ``render`` draws (see the module).

    ``render(values)`` returns the large model at unit gain (P, h, w) and its tail
    solve's ``{"steps", "converged"}`` (``None`` without a tail); ``jac_unit`` is the
    cheap model's ∂R/∂(σt, σs, g[, b]) at unit gain; ``black_range`` is the black
    level's range when it is fitted (``None``: given); ``noise`` is the variance of
    one weighted residual that the capture's noise gives (NaN: unknown), which sets
    how small a step must be to end the iteration. At most ``max_iterations`` renders
    at iterates, plus one per parameter for the large model's Jacobian; the iteration
    ends early where its steps, shrinking at their last rate, would not reach the
    tolerance within them."""
    names = parameter_names(black_range is not None)
    v = {k: float(values[k]) for k in ("sigma_t", "sigma_s", "g", "black_level")}
    gain_cheap = float(values["gain"])
    steps, last_size, exact = [], None, None
    rendered, unit, jac, residual, tail = v, None, None, None, None
    count = [0]

    def drawn(at):
        count[0] += 1
        unit, tail = render(at)
        unit = np.asarray(unit, np.float64)
        if tail is not None and not tail["converged"]:
            return None, tail, "its tail solve did not converge"
        if not np.all(np.isfinite(unit)):
            return None, tail, "a non-finite render"
        return unit, tail, None

    def stop(reason, ok=False):
        return Correction(rendered, unit, jac, residual, steps, ok, reason, tail, count[0])

    def gauss_newton(jac_now):
        return gauss_newton_step(jac_now, residual, names, v, noise)

    def refresh():
        """The large model's Jacobian at ``v`` by forward differences (``exact``)."""
        nonlocal exact, jac_at, tail
        columns = []
        for k in names:
            h = DIFFERENCE_STEP * (v[k] if k in ("sigma_t", "sigma_s") else 1.0)
            moved, tail_k, failure = drawn({**v, k: v[k] + h})
            if failure:
                tail = tail_k
                return failure
            columns.append((moved - unit) / h)
        exact, jac_at = np.stack(columns, axis=-1), v
        return None

    def exact_step():
        """The large model's Jacobian at ``v`` and its Gauss–Newton step (recorded):
        ``(jac, step, size, failure)``."""
        failure = refresh()
        if failure:
            return None, None, None, failure
        jac = design(weights, unit, gain, exact)
        step, size = gauss_newton(jac)
        steps.append({"size": size, "jacobian": "exact", **step})
        return jac, step, size, None

    jac_at = None
    best = None  # the lowest misfit rendered: (‖r‖², values, model, tail, residual)
    for iteration in range(1, max_iterations + 1):
        rendered = v
        unit, tail, failure = drawn(v)
        if failure:
            return stop(failure)
        gain, residual = projected(weights, unit, obs)
        v["gain"] = gain
        if best is None or residual @ residual < best[0]:
            best = (residual @ residual, v, unit, tail, residual)
        jac = design(weights, unit, *((gain_cheap, jac_unit) if exact is None else (gain, exact)))
        step, size = gauss_newton(jac)
        steps.append({"size": size, "jacobian": "cheap" if exact is None else "exact", **step})
        slow = last_size is not None and size > MAX_RATE * last_size
        if exact is None and slow:
            # Phase 2 (the cheap Jacobian is too far from the large model's): the large
            # model's own Jacobian at the best point so far, and its step.
            _, v, unit, tail, residual = best
            rendered, gain = v, v["gain"]
            jac, step, size, failure = exact_step()
            if failure:
                return stop(failure)
            last_size, slow = None, False
        if size < STEP_TOLERANCE and exact is not None and jac_at is not v:
            # Converged with a Jacobian from elsewhere: its own here, and one more look
            # (the answer is where the large model's Jacobian at it is orthogonal to
            # the residual, which a misfit makes depend on where J was taken).
            far = {k: v[k] - jac_at[k] for k in names}
            if _step_size(far, v, jac, names, noise) > REFRESH * STEP_TOLERANCE:
                jac, step, size, failure = exact_step()
                if failure:
                    return stop(failure)
        if size < STEP_TOLERANCE:
            return stop("converged", ok=True)
        if slow:
            return stop("its steps stopped shrinking")
        if last_size is not None and len(steps) >= 3:
            rate = size / last_size
            need = math.log(STEP_TOLERANCE / size) / math.log(rate) if rate > 0 else 0.0
            if iteration + need > max_iterations:
                return stop(
                    f"its steps shrink by {rate:.2f} per render: no convergence within "
                    f"{max_iterations} renders at iterates"
                )
        last_size = size
        for _ in range(6):  # halved until inside the domain
            new = {**v, **{k: v[k] + step[k] for k in names}}
            if in_domain(new, black_range):
                break
            step = {k: s / 2 for k, s in step.items()}
        else:
            return stop("its step left the domain")
        v = new
    return stop(f"no convergence in {max_iterations} renders at iterates")


__all__ = [
    "Correction",
    "correct",
    "design",
    "gauss_newton_step",
    "in_domain",
    "parameter_names",
    "projected",
]
