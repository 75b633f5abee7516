"""Checks every renderer (lightfield_jax.forward.base.AbstractRenderer) must pass, one
test per check, parametrised over small renderer factories: the plane, its Krylov and
coarse tails, the slab and the stripe cell. Each case keeps the grid, the parameter
values and the tolerance of the renderer's own test that it replaces."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lightfield_jax as lfj
from lightfield_jax.forward.base import trace_count
from lightfield_jax.forward.cell import CellRenderer
from lightfield_jax.forward.render import Renderer, renderer_for
from lightfield_jax.forward.slab import SlabRenderer
from lightfield_jax.scene.geometry import Slab, resolve_slab_grid


def slab_renderer(grid, illum, bounces, slab=None, g=0.4):
    """The slab at the default angular discretisation for ``g``, as the depth average."""
    slab = slab or Slab(6.4)
    if slab.n_z is None:
        slab = dataclasses.replace(slab, n_z=1)
    grid, slab = resolve_slab_grid(grid, slab, g)
    return SlabRenderer(grid, illum, bounces, slab)


def _central_differences(loss, x0, h=1e-6):
    out = []
    for i in range(x0.shape[0]):
        e = np.zeros(x0.shape[0])
        e[i] = h
        out.append((float(loss(x0 + e)) - float(loss(x0 - e))) / (2 * h))
    return np.array(out)


def _loss_with_tail(renderer, weights):
    def loss(p):
        images, _, tail = renderer(p[0], p[1], p[2], p[3])
        return 100.0 * jnp.sum(weights * (images.sum(axis=1) + tail.image))

    return loss


# ---------------------------------------------------------------- no recompiles
# Each factory gives (call, first, later): ``call(*first)`` compiles, ``call(*v)`` for
# every v in ``later`` must trace nothing new (new values, including a gain, are data).


def _plane_render_api():
    grid = lfj.Grid(18, 12, 16, refine=1)  # both fixed: model size never follows g
    illum = lfj.Beam(0.0, 6.0)

    def call(st, ss, g, gain=None):
        gain_kw = {} if gain is None else {"gain": gain}
        lfj.render(lfj.Medium(st, ss, g), grid, illum, bounces=3, **gain_kw)

    values = ((0.3, 0.2, 0.5), (0.1, 0.05, -0.4), (0.5, 0.01, 0.9))
    return call, (0.2, 0.1, 0.3), [(st, ss, g, 2.0 * st) for st, ss, g in values]


def _plane_krylov_tail():
    grid = lfj.Grid(18, 12, 16, refine=1)
    illum = lfj.Beam(0.0, 6.0)
    kw = dict(bounces=2, tail="bicgstab", tail_tol=1e-4)

    def call(st, ss, g, gain=None):
        gain_kw = {} if gain is None else {"gain": gain}
        res = lfj.render(lfj.Medium(st, ss, g, "normalized"), grid, illum, **kw, **gain_kw)
        assert res.tail_converged

    values = ((0.3, 0.29, 0.5), (0.1, 0.05, -0.4), (0.5, 0.01, 0.9))
    return call, (0.2, 0.1, 0.3), [(st, ss, g, 2 * st) for st, ss, g in values]


def _plane_coarse_tail():
    # A refined forward medium whose later bounces march on the native grid.
    grid = lfj.Grid(48, 32, 64, refine=2)
    illum = lfj.Stripes(period=6, lit=3, phases=(0, 3))
    renderer = renderer_for(grid, illum, 10, "normalized", None, coarse_after=4)
    return renderer, (0.2, 0.1, 0.7), [(0.3, 0.29, 0.5), (0.1, 0.05, -0.4)]


def _slab():
    r = slab_renderer(lfj.Grid(24, 16, 8), lfj.Beam(0, 8), 3)
    return r, (0.2, 0.1, 0.3), [(v, 0.1, -0.2, 2.0) for v in (0.25, 0.3)]


def _cell():
    cell = CellRenderer(lfj.Grid(24, 18, 8, 1), lfj.Stripes(6, 3, (0, 1, 2)), 4, shift_orders=3)
    return cell, (0.3, 0.1, 0.2), [(0.4, 0.2, -0.3), (0.5, 0.3, 0.1, 2.0)]


@pytest.mark.parametrize(
    "make",
    [_plane_render_api, _plane_krylov_tail, _plane_coarse_tail, _slab, _cell],
    ids=["plane", "plane-krylov-tail", "plane-coarse-tail", "slab", "cell"],
)
def test_new_values_never_recompile(make):
    call, first, later = make()
    call(*first)
    before = trace_count()
    for values in later:
        call(*values)
    assert trace_count() == before


# ------------------------------------------------ derivatives vs central differences
# Each factory gives (loss, x0, rtol, atol): a scalar loss of (sigma_t, sigma_s, g[, gain]).


def _plane_gradient_case():
    renderer = renderer_for(lfj.Grid(20, 14, 16), lfj.Beam(0.0, 7.0, 10.0, 1.0), 4, "paper")
    weights = jnp.asarray(np.random.default_rng(0).random((1, 4, 14, 20)))

    def loss(params):
        images, _ = renderer(params[0], params[1], params[2], params[3])
        return jnp.sum(weights * images) * 100.0

    return loss, jnp.array([0.2, 0.12, 0.5, 1.3]), 1e-6, 1e-12


def _slab_gradient_case(boundary):
    def make():
        r = slab_renderer(lfj.Grid(24, 16, 8), lfj.Beam(0, 8), 4, Slab(5.0, boundary, n_mu=4))
        weights = jnp.linspace(0.5, 1.5, 24)

        def loss(p):
            return jnp.sum(r(p[0], p[1], p[2])[0] ** 2 * weights)

        return loss, jnp.array([0.25, 0.15, 0.3]), 1e-5, 0.0

    return make


def _plane_tail_gradient_case():
    renderer = Renderer(
        lfj.Grid(14, 10, 16),
        lfj.Beam(0.0, 5.0, 10.0, 1.0),
        2,
        "normalized",
        tail="bicgstab",
        tail_tol=1e-11,
    )
    weights = jnp.asarray(np.random.default_rng(0).random((1, 10, 14)))
    # (sigma_t, sigma_s, g, gain): albedo 0.95
    return _loss_with_tail(renderer, weights), jnp.array([0.4, 0.38, 0.5, 1.3]), 1e-6, 0.0


@pytest.mark.parametrize(
    "make",
    [
        _plane_gradient_case,
        _slab_gradient_case("absorbing"),
        _slab_gradient_case("refractive"),
        _plane_tail_gradient_case,
    ],
    ids=["plane", "slab-absorbing", "slab-refractive", "plane-krylov-tail"],
)
def test_gradients_match_central_differences(make):
    loss, x0, rtol, atol = make()
    grad = np.asarray(jax.grad(loss)(x0))
    np.testing.assert_allclose(grad, _central_differences(loss, x0), rtol=rtol, atol=atol)


def _slab_tail_jvp_case():
    slab = lfj.Slab(3.0, "refractive", n_mu=4, n_z=1)
    renderer = lfj.make_renderer(
        lfj.Grid(10, 8, 8, refine=1),
        lfj.Beam(0.0, 4.0, 10.0, 1.0),
        2,
        "normalized",
        slab,
        tail="bicgstab",
        tail_tol=1e-11,
    )
    weights = jnp.asarray(np.random.default_rng(1).random((1, 8, 10)))
    x0 = jnp.array([0.4, 0.36, 0.4, 1.3])  # (sigma_t, sigma_s, g, gain): albedo 0.9
    # One direction that moves every parameter (the four unit tangents cost a second
    # compile of the slab's tail; the plane's case runs those).
    return _loss_with_tail(renderer, weights), x0, jnp.array([[0.7, -0.4, 1.0, 0.5]])


def _plane_tail_jvp_case():
    loss, x0, _, _ = _plane_tail_gradient_case()
    return loss, x0, jnp.eye(4)


@pytest.mark.parametrize(
    "make", [_plane_tail_jvp_case, _slab_tail_jvp_case], ids=["plane-krylov-tail", "slab-tail"]
)
def test_forward_jacobian_through_the_tail_matches_central_differences(make):
    # The joint fit differentiates with jax.jvp vmapped over tangents (the gain's
    # tangent gives the tail's solve a zero right-hand side).
    loss, x0, tangents = make()
    value, jac = jax.vmap(lambda e: jax.jvp(loss, (x0,), (e,)), out_axes=(None, 0))(tangents)
    assert float(value) == pytest.approx(float(loss(x0)), rel=1e-12)
    h = 1e-6
    fd = [(float(loss(x0 + h * e)) - float(loss(x0 - h * e))) / (2 * h) for e in tangents]
    np.testing.assert_allclose(np.asarray(jac), fd, rtol=1e-6)


# ------------------------------------------------------- linearity in sigma_s
# Each factory gives (images, rtol, atol): images(sigma_s) with bounces on axis -3. Bounce
# k carries k factors of sigma_s, so doubling it multiplies I_k by 2^k exactly.


def _plane_images():
    grid = lfj.Grid(32, 20, 16)
    beam = lfj.Beam(0.0, 10.0, 0.0, 2.0)

    def images(ss):
        return np.asarray(lfj.render(lfj.Medium(0.3, ss, 0.5), grid, beam, bounces=4).images)

    return images, 1e-10, 1e-300


def _slab_images():
    r = slab_renderer(lfj.Grid(48, 32), lfj.Beam(0.0, 16.0, 0.0, 1.0), 4)
    return (lambda ss: np.asarray(r(0.3, ss, 0.4)[0])), 1e-9, 0.0


@pytest.mark.parametrize("make", [_plane_images, _slab_images], ids=["plane", "slab"])
def test_sigma_s_scaling_is_exact(make):
    images, rtol, atol = make()
    a, b = images(0.1), images(0.2)
    assert a.shape[-3] == 4
    for k in range(4):
        expected = 2.0 ** (k + 1) * a[..., k, :, :]
        np.testing.assert_allclose(b[..., k, :, :], expected, rtol=rtol, atol=atol)


# --------------------------------------------- stripes over all phases = lit x full
# Each factory gives (stripes, full, rtol, atol): six phases of 3-lit stripes of
# period 6 sum to three times the full side illumination, bounce by bounce.


def _plane_stripes_and_full():
    grid = lfj.Grid(24, 18, 16)
    medium = lfj.Medium(0.2, 0.1, 0.3)
    stripes = lfj.Stripes(period=6, lit=3, phases=tuple(range(6)))
    a = np.asarray(lfj.render(medium, grid, stripes, bounces=3).images)
    b = np.asarray(lfj.render(medium, grid, lfj.Full(), bounces=3).images)
    return a, b, 1e-9, 1e-15


def _slab_stripes_and_full():
    grid = lfj.Grid(48, 32)
    stripes = lfj.Stripes(6, 3, tuple(range(6)))
    a = np.asarray(slab_renderer(grid, stripes, 3)(0.2, 0.1, 0.4)[0])
    b = np.asarray(slab_renderer(grid, lfj.Full(0.0, "left"), 3)(0.2, 0.1, 0.4)[0])[0]
    return a, b, 2e-4, 1e-6 * b.max()


@pytest.mark.parametrize(
    "make", [_plane_stripes_and_full, _slab_stripes_and_full], ids=["plane", "slab"]
)
def test_stripes_over_all_phases_sum_to_lit_times_full(make):
    stripes, full, rtol, atol = make()
    assert stripes.shape[0] == 6
    np.testing.assert_allclose(stripes.sum(axis=0), 3 * full, rtol=rtol, atol=atol)
