"""The joint fit's compiled program: σt, σs, g (and the projector's black level b)
fitted straight to the raw shifted stripe images, the gain eliminated in closed form.

The model of pattern p at unit gain is (1 − b)·R_p + b·R_full and the residual is
w·(c·model − observed), c the gain's least-squares value at each point and w the
weights (1/√(I + floor): shot noise). R is rendered one of two ways:

- explicit bounces only: R = Σ_k u^k I_k (I_k ∝ σs^k: ``u`` rescales σs from the
  rendered one), one forward-mode pass along σt and g per step, σs in closed form;
- with a tail (a renderer built with ``tail``: K0 explicit bounces and Σ_{k>K0} from a
  Krylov solve, :mod:`lightfield_jax.forward.tail`): R = Σ_{k≤K0} I_k + tail at the
  actual σs (the tail is not a polynomial in σs), one forward-mode pass along σt, σs
  and g (the tail's tangents are implicit solves with the same operator).

b and the gain enter in closed form either way.

The solve is one module-level jitted function (:func:`solve`): the renderer, the
settings (:class:`JointSettings`) and the optimistix solver are its static parts,
so every call with the same static parts and array shapes reuses one program. At the
solution the program returns the model at unit gain and its Jacobian in the physical
parameters, computed explicitly there (not read from the solver's state), so any
optimistix least-squares solver can be passed.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

from lightfield_jax.forward.kernels import einsum, matmul
from lightfield_jax.inverse.jacobian import with_forward_jacobian
from lightfield_jax.inverse.programs import jitted

# The black level's range: b = −0.2 + 1.2·sigmoid(y).
BLACK_RANGE = (-0.2, 1.0)


@dataclasses.dataclass(frozen=True)
class JointSettings:
    """Static settings of the joint program: whether b is fitted, the lit count of the
    stripe period (R_full = Σ_p R_p / lit when the phases tile it) and the step limit."""

    fit_black: bool
    lit: int
    max_steps: int
    extrapolate: bool = False  # orders past the explicit K extrapolated geometrically


def bounces_at(x, sigma_s, renderer, full):
    """Per-bounce images at unit gain at (σt, g) = ``x`` and ``sigma_s``: every
    pattern's ``(P, K, h, w)`` and, when the phases do not tile the period, full
    illumination's ``(K, h, w)`` (else ``None``)."""
    images = renderer(x[0], sigma_s, x[1])[0]
    return images, None if full is None else full(x[0], sigma_s, x[1])[0][0]


def uses_tail(renderer) -> bool:
    """Whether ``renderer`` sums the series' tail with a solve (its call then returns
    ``(images, fields, tail)``)."""
    return getattr(renderer, "tail", None) is not None


def totals_at(x, renderer, full):
    """Σ_k I_k of all orders (K0 explicit + the tail) at unit gain at (σt, σs, g) =
    ``x``, shaped as one order: every pattern's ``(P, 1, h, w)`` and full
    illumination's ``(1, h, w)`` (or ``None``), for :func:`unit_model` with u = 1."""

    def total(render):
        images, _, tail = render(x[0], x[1], x[2])
        return (jnp.sum(images, axis=1) + tail.image)[:, None]

    return total(renderer), None if full is None else total(full)[0]


class TailStatus(eqx.Module):
    """The tail solves of one render at the solution: the most Krylov iterations of any
    of its renderers and whether all of them met their tolerance (explicit bounces only:
    0 and ``True``)."""

    steps: jax.Array
    converged: jax.Array


def tail_status(renderer, full, sigma_t, sigma_s, g) -> TailStatus:
    """:class:`TailStatus` of a render at these values (a primal render: no tangents)."""
    if not uses_tail(renderer):
        return TailStatus(jnp.array(0), jnp.array(True))
    tails = [r(sigma_t, sigma_s, g)[2] for r in (renderer, full) if r is not None]
    return TailStatus(
        steps=jnp.max(jnp.stack([t.steps for t in tails])),
        converged=jnp.all(jnp.stack([t.converged for t in tails])),
    )


# 1 − u·r is kept above this in the geometric extrapolation (u·r ≥ 1: no finite sum).
_MIN_GAP = 1e-3


def unit_model(bounces, lit: int, u, black, extrapolate: bool = False):
    """Σ_k u^k I_k of every pattern at unit gain, with the projector's black level b:
    (1 − b)·R_p + b·R_full (R_full = Σ_p R_p / lit when the phases tile the period).

    ``extrapolate``: the orders past the last one, K, are summed geometrically,
    Σ_{k≥K} u^k I_k ≈ u^K I_K/(1 − u r) with r = ΣI_K/ΣI_{K−1} the images' last
    per-bounce ratio (as the basin scan does): a cheap model of a long series, which
    the fit corrects to the marched one (:mod:`lightfield_jax.inverse.correction`)."""
    images, full_images = bounces
    k = images.shape[1]
    powers = u ** jnp.arange(1, k + 1, dtype=images.dtype)
    if extrapolate and k >= 2:
        r = jnp.sum(images[:, -1]) / jnp.sum(images[:, -2])
        gap = jnp.maximum(1.0 - u * r, _MIN_GAP)
        powers = powers.at[-1].divide(gap)
    r = einsum("k,pkhw->phw", powers, images)
    r_full = (
        jnp.sum(r, axis=0) / lit
        if full_images is None
        else einsum("k,khw->hw", powers, full_images)
    )
    return (1.0 - black) * r + black * r_full[None]


def unpack(y, fit_black: bool, black_fixed):
    """Unconstrained y → (σt, σs, g, b): σt > 0, 0 < σs < σt, |g| < 1, b in range."""
    sigma_t = jnp.exp(y[0])
    sigma_s = sigma_t * jax.nn.sigmoid(y[1])
    g = jnp.tanh(y[2])
    lo, hi = BLACK_RANGE
    black = lo + (hi - lo) * jax.nn.sigmoid(y[3]) if fit_black else black_fixed
    return sigma_t, sigma_s, g, black


def pack(start, fit_black: bool, dtype):
    """(σt, σs, g, b) → the unconstrained start y (kept off the constraints' edges)."""
    st0, ss0, g0, b0 = start
    frac = min(max(ss0 / st0, 1e-3), 1 - 1e-3)
    y0 = [math.log(st0), _logit(frac), math.atanh(max(min(g0, 0.95), -0.95))]
    if fit_black:
        lo, hi = BLACK_RANGE
        b = min(max(b0, lo + 0.05), hi - 0.05)
        y0.append(_logit((b - lo) / (hi - lo)))
    return jnp.asarray(y0, dtype)


def _logit(x):
    return math.log(x / (1.0 - x))


_bounces_and_slopes = with_forward_jacobian(bounces_at)
_totals_and_slopes = with_forward_jacobian(totals_at)


def _forward_variables(renderer, sigma_t, sigma_s, g):
    """The forward-mode variables x of a render at these values and θ = (σt, σs, g, …)
    ↦ (Δx, u): their step and the σs factor. Explicit: x = (σt, g), the orders I_k
    rendered at σs held fixed (u = σs'/σs, closed form). With a tail: x = (σt, σs, g),
    one order (the sum of all), u = 1."""
    if uses_tail(renderer):
        x = jnp.stack([sigma_t, sigma_s, g])
        return x, lambda theta: (theta[:3] - x, 1.0)
    ref = jax.lax.stop_gradient(sigma_s)
    x = jnp.stack([sigma_t, g])
    return x, lambda theta: (jnp.stack([theta[0], theta[2]]) - x, theta[1] / ref)


def _orders_and_slopes(renderer, full, sigma_t, sigma_s, g):
    """The orders of the model at these values and their slopes along
    :func:`_forward_variables`' x (one forward-mode pass)."""
    x, _ = _forward_variables(renderer, sigma_t, sigma_s, g)
    if uses_tail(renderer):
        return _totals_and_slopes(x, renderer, full)
    return _bounces_and_slopes(x, jax.lax.stop_gradient(sigma_s), renderer, full)


def model_and_jacobian(settings: JointSettings, renderer, full, black_fixed, y, rendered=None):
    """At y: the model at unit gain R (P, h, w) and ∂R/∂θ (P, h, w, n) in the physical
    parameters θ = (σt, σs, g[, b]), from one forward-mode pass (along σt and g, or σt,
    σs and g with a tail; b in closed form), or from ``rendered``: that pass's
    ``(orders, slopes)`` at y, already done."""
    st, ss, g, b = unpack(y, settings.fit_black, black_fixed)
    _, step = _forward_variables(renderer, st, ss, g)
    if rendered is None:
        rendered = _orders_and_slopes(renderer, full, st, ss, g)
    orders, slopes = rendered

    def model(theta):
        dx, u = step(theta)
        lin = jax.tree.map(lambda v, j: v + matmul(j, dx), orders, slopes)
        black = theta[3] if settings.fit_black else b
        return unit_model(lin, settings.lit, u, black, settings.extrapolate)

    theta = jnp.stack([st, ss, g] + ([b] if settings.fit_black else []))
    value = unit_model(orders, settings.lit, 1.0, b, settings.extrapolate)
    return value, jax.jacfwd(model)(theta)


# The weighted residual is solved divided by the weighted data's norm and times
# √RESIDUAL_GAIN (the answer does not change): JᵀJ is then of order RESIDUAL_GAIN per
# unit of y, above the Levenberg-Marquardt damping λ = 1/step size (1 at the start)
# whatever the capture's units, so the first steps are nearly Gauss-Newton's instead
# of short gradient steps. Measured (noiseless, 128×96, same run): the paper's milk 8
# solver steps → 3 and warm 4.8 s → 3.2 s; the dense forward medium 58.8 s → 48.6 s.
# 1e4 reached float32's floor in 2 steps and then spent 6 rejected ones there.
RESIDUAL_GAIN = 1e3


def _residual_scale(weights, obs):
    norm2 = jnp.sum((weights * obs) ** 2)
    return jnp.sqrt(RESIDUAL_GAIN / jnp.where(norm2 > 0, norm2, 1.0))


def _solve(
    settings: JointSettings,
    solver_static,
    solver_arrays,
    renderer,
    full,
    obs,
    black_fixed,
    weights,
    y0,
):
    solver = eqx.combine(solver_arrays, solver_static)
    scale = _residual_scale(weights, obs)

    def residual(y, _args):
        st, ss, g, b = unpack(y, settings.fit_black, black_fixed)
        rendered = _orders_and_slopes(renderer, full, st, ss, g)
        orders = rendered[0]
        if uses_tail(renderer):
            r = unit_model(orders, settings.lit, 1.0, b)
        else:
            u = ss / jax.lax.stop_gradient(ss)
            r = unit_model(orders, settings.lit, u, b, settings.extrapolate)
        wr = weights * r
        gain = jnp.sum(wr * weights * obs) / jnp.sum(wr * wr)
        # The render and its slopes are the solve's auxiliary output: the model and its
        # Jacobian at the answer come from them, not from a second forward-mode pass.
        return (scale * weights * (gain * r - obs)).reshape(-1), jax.lax.stop_gradient(rendered)

    sol = optx.least_squares(
        residual, solver, y0, has_aux=True, max_steps=settings.max_steps, throw=False
    )
    # Gauss-Newton solvers (Levenberg-Marquardt among them) keep the auxiliary output at
    # their last accepted point, which is the answer (``sol.aux`` is the one before it);
    # any other solver's answer gets its own forward-mode pass (a second copy of the
    # render in the compiled program: about 1.5 s more to compile).
    at_answer = sol.state.aux if isinstance(solver, optx.AbstractGaussNewton) else None
    model, jac = model_and_jacobian(settings, renderer, full, black_fixed, sol.value, at_answer)
    st, ss, g, _ = unpack(sol.value, settings.fit_black, black_fixed)
    tail = tail_status(renderer, full, st, ss, g)
    return sol.value, sol.result, sol.stats["num_steps"], model, jac, tail


def solve(settings: JointSettings, solver, renderer, full, obs, black_fixed, weights, y0):
    """Run ``solver`` on the weighted joint residual from ``y0``: ``(y, result, steps,
    R, ∂R/∂θ, tail)`` with R the model at unit gain at the solution (see the module) and
    ``tail`` the :class:`TailStatus` of a render there.

    With a tail, a tangent solve that does not converge stops the program with an
    error (lineax raises there); the caller reports it (see ``fit``)."""
    # The solver's arrays (e.g. a learning rate) are traced, the rest is static.
    arrays, static = eqx.partition(solver, eqx.is_array)
    run = jitted(_solve, ("settings", "solver_static"))
    return run(settings, static, arrays, renderer, full, obs, black_fixed, weights, y0)


def _model_only(lit: int, extrapolate: bool, renderer, full, sigma_t, sigma_s, g, black):
    if uses_tail(renderer):
        orders = totals_at(jnp.stack([sigma_t, sigma_s, g]), renderer, full)
    else:
        orders = bounces_at(jnp.stack([sigma_t, g]), sigma_s, renderer, full)
    status = tail_status(renderer, full, sigma_t, sigma_s, g)
    return unit_model(orders, lit, 1.0, black, extrapolate), status


def model_at(renderer, full, lit: int, sigma_t, sigma_s, g, black, dtype, extrapolate=False):
    """The model at unit gain R (P, h, w) of ``renderer`` at given values and the
    :class:`TailStatus` of its render (one forward render; used for a finer model's
    residual at a solution, the defect correction, and a start's check)."""
    vals = (jnp.asarray(v, dtype) for v in (sigma_t, sigma_s, g, black))
    return jitted(_model_only, ("lit", "extrapolate"))(lit, extrapolate, renderer, full, *vals)


__all__ = [
    "JointSettings",
    "TailStatus",
    "bounces_at",
    "model_and_jacobian",
    "model_at",
    "pack",
    "solve",
    "tail_status",
    "totals_at",
    "unit_model",
    "unpack",
    "uses_tail",
]
