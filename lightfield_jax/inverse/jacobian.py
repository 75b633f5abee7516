"""Functions that return their own Jacobian, for solvers that linearise them.

optimistix linearises a residual with ``jax.linearize``, which keeps every intermediate
of the forward pass (every bounce of every pattern): tens of GB for a long bounce
series. With few parameters, a forward-mode pass is cheaper than that and keeps nothing
but the Jacobian; wrapping a function as below makes its JVP the matrix product
``jacobian @ tangent`` of that Jacobian.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from lightfield_jax.forward.kernels import matmul


def with_jacobian(value_and_jacobian):
    """``value_and_jacobian(x, *fixed)`` → ``(value, jacobian)`` (a pytree of values and
    one of Jacobians ``[..., len(x)]``) as a function whose JVP in ``x`` is
    ``jacobian @ tx``. ``fixed`` are held constant (their tangents are ignored: pass
    ``lax.stop_gradient`` values), and the Jacobian's own tangent is zero (no second
    derivatives)."""

    @jax.custom_jvp
    def wrapped(x, *fixed):
        return value_and_jacobian(x, *fixed)

    @wrapped.defjvp
    def _jvp(primals, tangents):
        x, *fixed = primals
        out, jac = value_and_jacobian(x, *fixed)
        tangent = jax.tree.map(lambda j: matmul(j, tangents[0]), jac)
        return (out, jac), (tangent, jax.tree.map(jnp.zeros_like, jac))

    return wrapped


def with_forward_jacobian(heavy):
    """``heavy(x, *fixed)`` as a function returning ``(value, jacobian)``, the Jacobian
    (``[..., len(x)]``) from one forward-mode pass (``jax.jvp`` vmapped over the unit
    vectors: the primal once, all tangents at once); see :func:`with_jacobian`."""

    def value_and_jacobian(x, *fixed):
        def value(x):
            return heavy(x, *fixed)

        basis = jnp.eye(x.shape[0], dtype=x.dtype)
        return jax.vmap(lambda e: jax.jvp(value, (x,), (e,)), out_axes=(None, -1))(basis)

    return with_jacobian(value_and_jacobian)


__all__ = ["with_forward_jacobian", "with_jacobian"]
