"""The Henyey–Greenstein phase function of both geometries, and its in-plane integral
A(g) (docs/model.md sections 2 and 7).

The plane (the paper's model) evaluates the 3-D function at the in-plane angle θ
between incoming and outgoing direction, where it is not normalised
(:func:`phase_function`, :func:`phase_integral`); the slab evaluates it at the cosine
of the 3-D scattering angle, where it is normalised on the sphere (:func:`hg`). Both
go through one expression, written so that float32 (JAX's default) holds up to
|g| → 1.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from lightfield_jax.checks import shown

# Nodes of the periodic trapezoid rule for A(g). The rule converges like
# exp(-N (1 - |g|)), so 4096 nodes are exact to float64 for |g| <= 0.99.
_A_NODES = 4096


def _henyey_greenstein(one_minus_cos, one_plus_cos, g):
    """(1/4π) (1 − g²) / (1 + g² − 2 g cos θ)^{3/2}, given 1 − cos θ and 1 + cos θ.

    1 + g² − 2g·cos θ is evaluated as (1 − g)² + 2g·(1 − cos θ) (g ≥ 0) or
    (1 + g)² − 2g·(1 + cos θ) (g < 0), and 1 − g² as (1 − g)(1 + g): equal in exact
    arithmetic, but the direct form cancels at the forward (backward) peak, to 0 in
    float32 for |g| ≳ 0.9997 (an infinite p, A(g) and ρ) and 10 % low at |g| = 0.999.
    """
    base = jnp.where(
        g >= 0,
        (1.0 - g) ** 2 + 2.0 * g * one_minus_cos,
        (1.0 + g) ** 2 - 2.0 * g * one_plus_cos,
    )
    return (1.0 - g) * (1.0 + g) / (4.0 * jnp.pi * base**1.5)


def hg(cos_angle, g):
    """The 3-D Henyey–Greenstein phase function at the cosine of the scattering angle,
    normalised on the sphere (the slab's phase function).

    Traced or concrete ``g`` alike, unchecked: the renderers have validated it.
    """
    cos_angle = jnp.asarray(cos_angle)
    g = jnp.asarray(g)
    # 1 − c and 1 + c are exact where they matter (c near ±1, at the peaks).
    return _henyey_greenstein(1.0 - cos_angle, 1.0 + cos_angle, g)


def phase_function(theta: ArrayLike, g: ArrayLike) -> Float[Array, "..."]:
    """The paper's phase function, eq. (2): the 3-D Henyey-Greenstein function
    evaluated at the in-plane angle ``theta`` between incoming and outgoing direction,

    p(θ) = (1/4π) (1 − g²) / (1 + g² − 2 g cos θ)^{3/2}.

    It is *not* normalised in the plane: see :func:`phase_integral`.

    Raises:
        ValueError: a concrete ``g`` (not a JAX tracer: under ``jit`` or ``grad`` it is
            not checked) with a value outside (−1, 1) or NaN (|g| ≥ 1 gives finite
            nonsense: p(θ) ≤ 0 everywhere, or 0/0).
    """
    _check_asymmetry(g, "phase_function")
    theta = jnp.asarray(theta)
    g = jnp.asarray(g)
    # 1 − cos θ = 2 sin²(θ/2) and 1 + cos θ = 2 cos²(θ/2): accurate for small θ (and
    # near π), where cos θ rounds to ±1.
    return _henyey_greenstein(2.0 * jnp.sin(0.5 * theta) ** 2, 2.0 * jnp.cos(0.5 * theta) ** 2, g)


def phase_integral(g: ArrayLike) -> Float[Array, ""]:
    """A(g) = ∫_{−π}^{π} p(θ) dθ, the in-plane integral of the paper's phase function.

    A(0) = 0.5, A(0.4) ≈ 0.619, A(0.8) ≈ 1.622; A(−g) = A(g). Computed with the
    periodic trapezoid rule (spectrally accurate, differentiable in g).
    """
    _check_asymmetry(g, "phase_integral")
    theta = jnp.arange(_A_NODES) * (2.0 * jnp.pi / _A_NODES)
    g = jnp.asarray(g)
    return jnp.sum(phase_function(theta, g[..., None]), axis=-1) * (2.0 * jnp.pi / _A_NODES)


def _check_asymmetry(g, where: str) -> None:
    """Refuse a concrete ``g`` (a number or an array of them) with a value outside
    (−1, 1) or NaN, as ``ValueError("WHERE: g: ...")``; a tracer passes unchecked."""
    if isinstance(g, jax.core.Tracer):
        return
    try:
        a = np.asarray(g)
    except (TypeError, ValueError):
        return  # not numbers: jnp.asarray names it
    if a.dtype.kind not in "iuf" or a.size == 0:
        if a.dtype.kind in "bOUS" or a.dtype.kind == "c":
            raise ValueError(f"{where}: g: must be a real number, got {shown(g)}")
        return
    bad = ~(np.abs(a) < 1.0)
    if not bad.any():
        return
    first = float(a[bad].flat[0])
    got = (
        f"{first!r}"
        if a.ndim == 0
        else f"{int(bad.sum())} of {a.size} values outside, e.g. {first!r}"
    )
    raise ValueError(f"{where}: g: must satisfy -1 < g < 1, got {got}")


# A(g) of a Python float, compiled once (op by op, its dozen operations would each
# compile on first use).
phase_integral_at = jax.jit(phase_integral)


__all__ = ["hg", "phase_function", "phase_integral", "phase_integral_at"]
