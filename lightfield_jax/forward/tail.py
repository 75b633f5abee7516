"""The tail of the bounce series, Σ_{k>K0}, from one linear solve instead of a march.

After K0 explicit bounces, the light still to come is a Neumann series in the one-bounce
operator B (transport, then scatter: Q_k ↦ Q_{k+1}) and the camera C (transport, then
the camera row of the scatter: Q_k ↦ I_{k+1}). With Q = Q_{K0+1} the first source not
marched,

    y = Σ_{k>K0} Q_k = Σ_{j≥0} B^j Q  solves  (I − B) y = Q,
    Σ_{k>K0} I_k = I_{K0+1} + C y,      Σ_{k>K0} L_k = T y.

Marching the series costs about log(tol)/log(ρ) bounces (ρ the per-bounce ratio: ~900
for ρ = 0.99 at 1e-4); a Krylov solve of (I − B) y = Q with B applied as a matrix-free
operator (one bounce per application) needs far fewer applications as ρ → 1. This is
source iteration against GMRES in transport-code terms.

The solve talks to a renderer through a narrow interface, a *bounce step*: an
``eqx.Module`` ``step`` with

- ``step(q) -> (q_next, image)``: Q_k ↦ (Q_{k+1}, I_{k+1}), linear in ``q``, built once
  per (σt, σs, g) (its arrays are leaves, so gradients reach them);
- ``step.transport(q) -> field``: L_k = T Q_k in the step's own layout (only for the
  tail's light field).

The bounce loop of :class:`~lightfield_jax.forward.base.AbstractRenderer` hands
:func:`solve_tail` its geometry's step (``step.linear``: the plane's step as is, the
slab's without the clipping of FFT round-off that its march applies), its first
unmarched source Q_{K0+1} and image I_{K0+1}: every geometry gets the tail.

Derivatives (``jax.jvp``, ``jax.jacfwd``, ``jax.grad``, and ``vmap`` over them) are
``lineax.linear_solve``'s own, implicit, without storing the iterations: a tangent is
dy = (I − B)⁻¹(dQ + dB·y), one more solve with the same operator; a cotangent is a solve
with its transpose (the bounce's linear transpose). Every solve, primal, tangent or
cotangent, runs on its right-hand side divided by its max (:class:`_ScaleFree`), so its
tolerance is relative whatever the tangent's scale, and a zero right-hand side (e.g. the
tangent along the gain) gives zero (lineax's BiCGStab would divide 0 by 0).

Tolerance: a solve stops when max|r| ≤ ``tol``·max|Q| (r = Q − (I − B)y, the max norm
over every pixel, direction and pattern). Its error is then at most
‖(I − B)⁻¹‖·tol·max|Q|, with ‖(I − B)⁻¹‖ up to 1/(1 − ratio) for the measured per-bounce
ratio of the scene, while the tail itself grows by less on average: measured (see
docs/tail_acceleration.md), GMRES stayed within ``tol`` (it tests only at the end of each
restart cycle), BiCGStab within ``tol`` up to ratio 0.9 and 1.4–26× above it for
ratios 0.96–0.996. The primal solve reports whether it converged
(``TailSolution.converged``); a tangent or cotangent solve that does not converge raises
at run time (lineax throws there: there is no result to carry the flag).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Bool, Float, Int

from lightfield_jax.checks import number_problem

TAIL_METHODS: tuple[str, ...] = ("gmres", "bicgstab")
# Krylov vectors kept by GMRES between restarts (memory: this many copies of Q).
GMRES_RESTART = 10


class TailNotConvergedWarning(RuntimeWarning):
    """The linear solve of the bounce series' tail stopped before its tolerance."""


class TailSolution(eqx.Module):
    """Σ_{k>K0} of the bounce series, in the renderer's layout.

    Attributes:
        image: Σ_{k>K0} I_k, Float[Array, "patterns H W"].
        lightfield: Σ_{k>K0} L_k (radiance per radian), Float[Array, "patterns H W
            n_theta"], or ``None`` when light fields were not requested.
        steps: iterations the Krylov solver took (BiCGStab: two bounces each; GMRES:
            restart cycles of 10 bounces and one for the residual each).
        converged: whether the solve met its tolerance (``False``: the tail is the last
            iterate, not a solution; callers must report it).
    """

    image: Float[Array, "patterns H W"]
    lightfield: Float[Array, "patterns H W n_theta"] | None
    steps: Int[Array, ""]
    converged: Bool[Array, ""]


def mapped_output(out, image, field, tail_field):
    """A render's ``(images, light fields[, tail])`` with ``image`` applied to its
    images and its tail's image, ``field`` to its light fields and ``tail_field`` to its
    tail's light field (``None`` stays ``None``; the tail's steps and convergence kept)."""

    def maybe(fn, a):
        return None if a is None else fn(a)

    images, fields = image(out[0]), maybe(field, out[1])
    if len(out) == 2:
        return images, fields
    tail = out[2]
    return (
        images,
        fields,
        TailSolution(
            image(tail.image), maybe(tail_field, tail.lightfield), tail.steps, tail.converged
        ),
    )


def joined_tail(image, solves) -> TailSolution:
    """The tail of a render composed from several renderers' tail ``solves`` whose
    images make ``image``: images only, the most Krylov iterations of any and whether
    every one met its tolerance."""
    return TailSolution(
        image=image,
        lightfield=None,
        steps=jnp.max(jnp.stack([t.steps for t in solves])),
        converged=jnp.all(jnp.stack([t.converged for t in solves])),
    )


def check_tail(tail, tol, max_steps) -> None:
    """Validate the tail settings of a renderer (a one-line error naming the value)."""
    if tail is not None and not (isinstance(tail, str) and tail in TAIL_METHODS):
        raise ValueError(f"tail: must be None or one of {', '.join(TAIL_METHODS)}, got {tail!r}")
    if number_problem(tol, low=0.0, high=1.0, low_open=True, high_open=True) is not None:
        raise ValueError(f"tail_tol: must be a number in (0, 1), got {tol!r}")
    if number_problem(max_steps, integer=True, low=1) is not None:
        raise ValueError(f"tail_max_steps: must be an integer >= 1, got {max_steps!r}")


def _solver(method: str, tol: float, max_steps: int):
    # rtol = 0: lineax scales rtol per element (atol + rtol·|b|), which never converges
    # where the source is ~0 far from the light; _ScaleFree normalises the right-hand
    # side to max|b| = 1 instead, and atol = tol is relative to it.
    if method == "gmres":
        return lx.GMRES(rtol=0.0, atol=tol, max_steps=max_steps, restart=GMRES_RESTART)
    return _BiCGStab(tol=tol, max_steps=max_steps)


class _BiCGStab(lx.AbstractLinearSolver):
    """Unpreconditioned BiCGStab (van der Vorst 1992) from y = 0, stopping at
    max|r| ≤ ``tol`` (on a right-hand side of max 1, see :class:`_ScaleFree`).

    Written here rather than taken from lineax: lineax 0.1.1's BiCGStab tests breakdown
    in float32 as ``alpha < 1e-16`` (signed), so a negative ⟨r̂, v⟩ of a nonsymmetric
    operator, legitimate, stops it after a step or two (measured on this operator: 2
    steps, the tail 50 % off, reported as not converged). Breakdown here is an exact zero
    of ⟨r̂, r⟩ or ⟨r̂, v⟩ (reported unless the residual is already below ``tol``)."""

    tol: float
    max_steps: int

    def init(self, operator, options):
        return operator

    def compute(self, state, vector, options):
        operator = state
        dot = jnp.vdot
        r_hat = vector

        def residual_max(r):
            return jnp.max(jnp.abs(r))

        def cond(carry):
            _, r, _, _, _, _, _, step, broke = carry
            return (residual_max(r) > self.tol) & (step < self.max_steps) & ~broke

        def body(carry):
            y, r, p, v, rho, alpha, omega, step, _ = carry
            rho_new = dot(r_hat, r)
            beta = (rho_new / rho) * (alpha / omega)
            p = r + beta * (p - omega * v)
            v = operator.mv(p)
            denominator = dot(r_hat, v)
            broke = (rho_new == 0) | (denominator == 0)
            alpha = rho_new / jnp.where(denominator == 0, 1.0, denominator)
            s = r - alpha * v
            t = operator.mv(s)
            tt = dot(t, t)
            omega = jnp.where(tt > 0, dot(t, s) / jnp.where(tt > 0, tt, 1.0), 0.0)
            broke = broke | (omega == 0)
            y = y + alpha * p + omega * s
            r = s - omega * t
            return y, r, p, v, rho_new, alpha, omega, step + 1, broke

        one = jnp.ones((), vector.dtype)
        zero = jnp.zeros_like(vector)
        init = (zero, vector, zero, zero, one, one, one, jnp.array(0), jnp.array(False))
        y, r, *_, steps, broke = jax.lax.while_loop(cond, body, init)
        converged = residual_max(r) <= self.tol
        result = lx.RESULTS.where(
            converged,
            lx.RESULTS.successful,
            lx.RESULTS.where(broke, lx.RESULTS.breakdown, lx.RESULTS.max_steps_reached),
        )
        return y, result, {"num_steps": steps}

    def transpose(self, state, options):
        return state.transpose(), options

    def conj(self, state, options):
        return state, options

    def assume_full_rank(self):
        return True


class _OneMinusBounce(eqx.Module):
    """y ↦ (I − B) y, with B the next-source part of a bounce step."""

    step: eqx.Module

    def __call__(self, y):
        return y - self.step(y)[0]


class _ScaleFree(lx.AbstractLinearSolver):
    """``inner`` on b/max|b| (solution times max|b|): the tolerance is relative to each
    right-hand side, and b = 0 gives 0 without running ``inner``'s iteration on it."""

    inner: lx.AbstractLinearSolver

    def init(self, operator, options):
        return self.inner.init(operator, options)

    def compute(self, state, vector, options):
        scale = jnp.max(jnp.abs(vector))
        nonzero = scale > 0
        b = jnp.where(nonzero, vector / jnp.where(nonzero, scale, 1.0), jnp.ones_like(vector))
        y, result, stats = self.inner.compute(state, b, options)
        y = jnp.where(nonzero, scale * y, jnp.zeros_like(y))
        return y, lx.RESULTS.where(nonzero, result, lx.RESULTS.successful), stats

    def transpose(self, state, options):
        return self.inner.transpose(state, options)

    def conj(self, state, options):
        return self.inner.conj(state, options)

    def assume_full_rank(self):
        return True


def solve_tail(
    step,
    source: Float[Array, "patterns n_theta H W"],
    first_image: Float[Array, "patterns H W"],
    method: str,
    tol: float,
    max_steps: int,
    lightfield: bool,
) -> TailSolution:
    """Solve (I − B) y = Q for ``source`` Q = Q_{K0+1}: the tail's image Σ_{k>K0} I_k =
    ``first_image`` + C y and, when ``lightfield``, its field Σ_{k>K0} L_k = T y in the
    step's own layout (the renderer puts it in its output layout)."""
    operator = lx.FunctionLinearOperator(
        _OneMinusBounce(step), jax.eval_shape(lambda: source), closure_convert=False
    )
    solver = _ScaleFree(_solver(method, tol, max_steps))
    sol = lx.linear_solve(operator, source, solver, throw=False)
    y = sol.value
    return TailSolution(
        image=first_image + step(y)[1],
        lightfield=step.transport(y) if lightfield else None,
        steps=sol.stats["num_steps"],
        converged=sol.result == lx.RESULTS.successful,
    )
