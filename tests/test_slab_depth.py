"""Depth layers of the slab model (issue 18): the layer weights against brute force
and the depth average, the layered model against its exact Monte Carlo target
(``depth_layers=n_z``) and against the true 3-D slab, the bounce step, and n_z's
choice. The contract over the table of scenes is in the slow tests and in
experiments/slab_depth_accuracy.py."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lightfield_jax as lfj
from lightfield_jax.forward.render import trace_count
from lightfield_jax.forward.slab import SlabRenderer
from lightfield_jax.forward.slab_layers import camera_integrals, transport_weights
from lightfield_jax.reference.montecarlo_slab import monte_carlo_slab
from lightfield_jax.scene.geometry import Slab, default_n_z, resolve_slab_grid
from lightfield_jax.scene.geometry_spec import describe_geometry, parse_geometry

FULL = lfj.Full(0.0, "left")


def render(st, ss, g, slab, width, height, bounces, illum=FULL):
    grid, slab = resolve_slab_grid(lfj.Grid(width, height), slab, g)
    return np.asarray(SlabRenderer(grid, illum, bounces, slab)(st, ss, g)[0], np.float64)[0]


def brute_force(u, h, n_z, source, refl, sigma_t, samples=200_000):
    """Rays leaving source layer ``source`` (uniform) with vertical travel u, unfolded
    periodically: per receiving layer Σ R^m (as a fraction of the source), and the
    camera integrals Δ·mean[R^m e^{−σt(h−y)}], Δ·mean[R^m e^{−σt y}]."""
    dz = h / n_z
    z0 = (source + (np.arange(samples) + 0.5) / samples) * dz
    a = z0 + u
    m = np.floor(a / h)
    y = a - m * h
    rm = np.where(m == 0, 1.0, refl ** np.maximum(m, 1))
    layer = np.minimum(np.floor(y / dz), n_z - 1).astype(int)
    w = np.bincount(layer, rm, minlength=n_z) / samples
    up = dz * np.mean(rm * np.exp(-sigma_t * (h - y)))
    down = dz * np.mean(rm * np.exp(-sigma_t * y))
    return w, up, down


@pytest.mark.parametrize("refl", [0.0, 0.3, 1.0])
@pytest.mark.parametrize("n_z", [1, 3])
def test_layer_weights_against_brute_force(refl, n_z):
    h, sigma_t = 6.4, 0.35
    u = np.array([0.0, 0.7, 2.5, 6.4, 9.1, 23.3])
    with jax.enable_x64(True):
        for source in range(n_z):
            expected = [brute_force(x, h, n_z, source, refl, sigma_t) for x in u]
            w = np.array([e[0] for e in expected])  # (u, receiving layer)
            got = np.stack(
                [
                    np.asarray(
                        transport_weights(jnp.asarray(u / (h / n_z)), refl, n_z, lay - source)
                    )
                    for lay in range(n_z)
                ],
                axis=1,
            )
            np.testing.assert_allclose(got, w, atol=2e-5)
            a, b = camera_integrals(jnp.asarray(u), h, n_z, source, refl, jnp.asarray(sigma_t))
            np.testing.assert_allclose(np.asarray(a), [e[1] for e in expected], rtol=1e-6)
            np.testing.assert_allclose(np.asarray(b), [e[2] for e in expected], rtol=1e-6)


def brute_force_moments(u, h, n_z, source, refl, sigma_t, samples=200_000):
    """The linear profile's coefficients by sampling: a source of profile φ_b (φ_0 = 1,
    φ_1 = 2η − 1 on the layer's local height η) in layer ``source``, its rays unfolded
    with vertical travel u; per receiving layer and coefficient a, (2a + 1)·mean[R^m
    φ_a(ξ) φ_b(η)], and the camera integrals of φ_b."""
    dz = h / n_z
    eta = (np.arange(samples) + 0.5) / samples
    a = (source + eta) * dz + u
    m = np.floor(a / h)
    y = a - m * h
    rm = np.where(m == 0, 1.0, refl ** np.maximum(m, 1))
    layer = np.minimum(np.floor(y / dz), n_z - 1).astype(int)
    xi = y / dz - layer
    phi = (np.ones_like(eta), 2 * eta - 1), (np.ones_like(xi), 2 * xi - 1)
    w = {
        (i, j): (2 * i + 1)
        * np.bincount(layer, rm * phi[1][i] * phi[0][j], minlength=n_z)
        / samples
        for i in (0, 1)
        for j in (0, 1)
    }
    up = dz * np.mean(rm * phi[0][1] * np.exp(-sigma_t * (h - y)))
    down = dz * np.mean(rm * phi[0][1] * np.exp(-sigma_t * y))
    return w, up, down


@pytest.mark.parametrize("refl", [0.0, 0.4, 1.0])
@pytest.mark.parametrize("sigma_t", [0.35, 4.0])
def test_linear_profile_weights_against_brute_force(refl, sigma_t):
    """W^{ab}_δ of the linear profile (w^{10} = −3 w^{01}) and the camera integrals of
    the slope, against sampling the unfolded rays; σt 4 makes each layer 8.5 mean free
    paths thick (the camera integrals' closed form, not the Gauss rule)."""
    h, n_z = 6.4, 3
    u = np.array([0.0, 0.7, 2.5, 6.4, 9.1, 23.3])
    factor = {"00": 1.0, "01": 1.0, "10": -3.0, "11": 1.0}
    with jax.enable_x64(True):
        for source in range(n_z):
            expected = [brute_force_moments(x, h, n_z, source, refl, sigma_t) for x in u]
            for (i, j), name in (((0, 0), "00"), ((0, 1), "01"), ((1, 0), "10"), ((1, 1), "11")):
                w = np.array([e[0][i, j] for e in expected])
                got = np.stack(
                    [
                        factor[name]
                        * np.asarray(
                            transport_weights(
                                jnp.asarray(u / (h / n_z)),
                                refl,
                                n_z,
                                lay - source,
                                "01" if name == "10" else name,
                            )
                        )
                        for lay in range(n_z)
                    ],
                    axis=1,
                )
                np.testing.assert_allclose(got, w, atol=1e-4, err_msg=name)
            a, b = camera_integrals(
                jnp.asarray(u), h, n_z, source, refl, jnp.asarray(sigma_t), moment=1
            )
            scale = max(abs(e[1]) for e in expected) + max(abs(e[2]) for e in expected)
            np.testing.assert_allclose(np.asarray(a), [e[1] for e in expected], atol=1e-6 * scale)
            np.testing.assert_allclose(np.asarray(b), [e[2] for e in expected], atol=1e-6 * scale)


@pytest.mark.parametrize("boundary", ["absorbing", "refractive"])
def test_the_linear_profile_converges_faster_than_the_layer_average(boundary):
    """Second order in the layer thickness: on a beam at the entry wall (ω 0.95, g 0.8,
    orders 3–6), 2 linear layers are closer to the converged depth (8 linear layers)
    than 4 constant ones, and 4 linear layers within 0.2 %."""
    st, ss, g = 0.2, 0.19, 0.8
    beam = lfj.Beam(0.0, 6.5, 0.0, 1.0)

    def sums(n_z, profile):
        slab = Slab(6.4, boundary, n_mu=4, n_z=n_z, depth_profile=profile)
        grid = lfj.Grid(16, 12, 8, 1)
        im = np.asarray(SlabRenderer(grid, beam, 6, slab)(st, ss, g)[0], np.float64)[0]
        return im[2:].sum((1, 2))

    with jax.enable_x64(True):
        converged = sums(8, "linear")
        error = {
            key: np.max(np.abs(sums(*key) / converged - 1))
            for key in ((2, "linear"), (4, "linear"), (4, "constant"))
        }
    assert error[(2, "linear")] < error[(4, "constant")], error
    assert error[(4, "linear")] < 2e-3, error


def test_one_layer_is_the_depth_average():
    """n_z = 1 has the survival S(v) = R^⌊v⌋(1 − f(1 − R)) of the depth-averaged model
    (docs/slab_design.md fact 3; the renders of the two agreed to 1e-16 before the
    depth-averaged code was replaced), and the first two orders do not depend on n_z
    (the first source is uniform in depth)."""
    v = np.linspace(0.0, 7.3, 200)
    for refl in (0.0, 0.4, 1.0):
        m0, f = np.floor(v), v - np.floor(v)
        rm = np.where(m0 == 0, 1.0, refl ** np.maximum(m0, 1))
        s = rm * (1.0 - f * (1.0 - refl))
        np.testing.assert_allclose(np.asarray(transport_weights(jnp.asarray(v), refl, 1, 0)), s)
    # Light that never reaches a face (u = 0): layers change nothing for I_1, I_2.
    a = render(0.2, 0.1, 0.4, Slab(6.4, n_mu=4, n_z=1), 24, 16, 2)
    b = render(0.2, 0.1, 0.4, Slab(6.4, n_mu=4, n_z=3), 24, 16, 2)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7 * a.max())


def test_layers_match_their_exact_monte_carlo_target():
    """n_z = 3 (an odd count: the middle layer is its own mirror image) against the
    oracle that keeps each order's source as 3 layer averages."""
    st, ss, g, h = 0.3, 0.24, -0.3, 6.4
    beam = lfj.Beam(0.0, 16.0, 0.0, 1.0)
    mc = monte_carlo_slab(
        48,
        32,
        h,
        st,
        ss,
        g,
        beam,
        4,
        boundary="refractive",
        photons=1_000_000,
        depth_layers=3,
        seed=5,
    )
    slab = Slab(h, "refractive", n_mu=4, n_z=3, depth_profile="constant")
    im = render(st, ss, g, slab, 48, 32, 4, beam)
    err = im.sum((1, 2)) / mc.images[0].sum((1, 2)) - 1
    noise = mc.total_stderr[0] / mc.images[0].sum((1, 2))
    # The discretisation (4 μ nodes, 8 azimuth bins) measured ≤ 0.7 % here.
    assert np.all(np.abs(err) < 0.01 + 3 * noise), (err, noise)


def test_forward_peaked_refractive_tank_against_the_true_slab():
    """The issue's worst case (ω .95, g .8, refractive) on a small grid: the resolved
    layers bring I_3..I_6 within 2 % of the 3-D Monte Carlo (plus its noise); the depth
    average (n_z = 1) is off by more than 3 % at I_5 or I_6 (the negative control)."""
    st, g, h, k = 0.2, 0.8, 6.4, 6
    ss = 0.95 * st
    mc = monte_carlo_slab(
        32,
        24,
        h,
        st,
        ss,
        g,
        FULL,
        k,
        boundary="refractive",
        photons=400_000,
        seed=9,
        camera_sampling=0.3,
    )
    ref = mc.images[0].sum((1, 2))
    noise = mc.total_stderr[0] / ref
    slab = Slab(h, "refractive").resolve(g, st, ss / st)
    assert slab.n_z > 1
    layered = render(st, ss, g, slab, 32, 24, k).sum((1, 2)) / ref - 1
    average = render(st, ss, g, dataclasses.replace(slab, n_z=1), 32, 24, k).sum((1, 2)) / ref - 1
    assert np.all(np.abs(layered) < 0.02 + 3 * noise), (layered, noise)
    assert np.max(np.abs(average[4:])) > 0.03 + 3 * np.max(noise[4:]), (average, noise)


def _mirrored(q, n_z: int):
    """The layer mirror z → h − z of a layered source: layers reversed within each
    profile coefficient, the slopes' sign flipped."""
    q = np.asarray(q)
    blocks = [
        q[:, a * n_z : (a + 1) * n_z][:, ::-1] * (-1.0) ** a for a in range(q.shape[1] // n_z)
    ]
    return np.concatenate(blocks, axis=1)


@pytest.mark.parametrize("profile", ["constant", "linear"])
def test_bounce_is_a_pure_linear_step_that_reproduces_the_render(profile):
    with jax.enable_x64(True):
        slab = Slab(5.0, "refractive", n_mu=4, n_z=3, depth_profile=profile)
        grid, slab = resolve_slab_grid(lfj.Grid(16, 12, 8), slab, 0.6)
        r = SlabRenderer(grid, lfj.Beam(0, 6), 4, slab)
        st, ss, g = jnp.asarray(0.25), jnp.asarray(0.2), jnp.asarray(0.6)
        images = np.asarray(r(st, ss, g)[0])[0]
        orders = eqx.filter_jit(lambda m, *v: m.scattered_orders(*v))(r, st, ss, g)
        bounce, i2, q = orders.step, orders.second_image, orders.source
        np.testing.assert_allclose(np.asarray(i2)[0], images[1], rtol=1e-10)
        step = eqx.filter_jit(lambda b, q: b(q))
        q3, i3 = step(bounce, q)
        _, i4 = step(bounce, q3)
        np.testing.assert_allclose(np.asarray(i3)[0], images[2], rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(np.asarray(i4)[0], images[3], rtol=1e-10, atol=1e-14)
        q6, _ = step(bounce, 2.0 * q)
        np.testing.assert_allclose(np.asarray(q6), 2.0 * np.asarray(q3), rtol=1e-10, atol=1e-14)
        # The mirror symmetry L(z, −μ) = L(h − z, μ) is built in: the scattered source of a
        # layer-mirrored field is the layer-mirrored source.
        scatter = eqx.filter_jit(lambda b, q: b.scatter(q))
        assert q.shape[1] == 3 * slab.depth_coefficients
        flipped = scatter(bounce, jnp.asarray(_mirrored(q, 3)))
        np.testing.assert_allclose(
            np.asarray(flipped), _mirrored(scatter(bounce, q), 3), rtol=1e-10, atol=1e-14
        )


def test_layered_gradients_and_no_recompile():
    with jax.enable_x64(True):
        slab = Slab(5.0, "refractive", n_mu=4, n_z=2)
        grid, slab = resolve_slab_grid(lfj.Grid(16, 12, 8), slab, 0.3)
        r = SlabRenderer(grid, lfj.Beam(0, 6), 3, slab)
        weights = jnp.linspace(0.5, 1.5, 16)

        def loss(p):
            return jnp.sum(r(p[0], p[1], p[2])[0] ** 2 * weights)

        p = jnp.array([0.3, 0.2, 0.3])
        grad = np.asarray(jax.grad(loss)(p))
        fd = np.array([(loss(p + e * 1e-6) - loss(p - e * 1e-6)) / 2e-6 for e in jnp.eye(3)])
        np.testing.assert_allclose(grad, fd, rtol=1e-5)
    r(0.2, 0.1, 0.3)
    before = trace_count()
    for v in (0.25, 0.3):
        r(v, 0.15, -0.2, 2.0)
    assert trace_count() == before


def test_lightfields_integrate_the_layers():
    """The depth-integrated light field does not depend on how the depth is cut for
    L_0, L_1 (the first source is uniform in depth), and has the model's shape."""
    grid, slab = resolve_slab_grid(lfj.Grid(16, 12, 8), Slab(5.0, n_mu=4, n_z=1), 0.4)
    a = SlabRenderer(grid, lfj.Beam(0, 6), 3, slab)(0.2, 0.15, 0.4, lightfield=True)[1]
    b = SlabRenderer(grid, lfj.Beam(0, 6), 3, dataclasses.replace(slab, n_z=4))(
        0.2, 0.15, 0.4, lightfield=True
    )[1]
    assert a.shape == b.shape == (4, 1, 12, 16, 8)
    a, b = np.asarray(a), np.asarray(b)
    np.testing.assert_allclose(b[:2], a[:2], rtol=1e-4, atol=1e-6 * a[1].max())


def test_layer_count_follows_the_scene_and_is_reported():
    # Dim scenes keep the depth average; bright, thick or forward-peaked ones get layers.
    assert Slab(6.4).resolve(0.4, 0.2051, 0.0366 / 0.2051).n_z == 1
    assert Slab(6.4, "refractive").resolve(0.8, 0.2, 0.95).n_z > 1
    assert Slab(6.4, n_z=3).resolve(0.8, 0.2, 0.95).n_z == 3
    for boundary in ("absorbing", "refractive"):
        assert default_n_z(None, None, boundary) >= default_n_z(1.3, 0.95, boundary) > 1
    slab = Slab(6.4, "refractive").resolve(0.8, 0.2, 0.95)
    assert slab.as_dict()["n_z"] == slab.n_z
    # The profile in effect is reported, and a description parses back to the same model.
    assert slab.as_dict()["depth_profile"] == slab.profile == "linear"
    assert parse_geometry(slab.as_dict()).as_dict() == slab.as_dict()
    assert dataclasses.replace(slab, n_z=1).profile == "constant"
    assert Slab(6.4, n_z=1, depth_profile="linear").depth_coefficients == 2
    text = describe_geometry({"geometry": slab.as_dict()})
    assert f"n_z {slab.n_z} (linear in depth)" in text
    # A fit result written before the profile existed kept layer averages: read so.
    from lightfield_jax.scene.geometry_spec import parse_fitted_geometry

    old = {"kind": "slab", "thickness": 6.4, "boundary": "absorbing", "n_mu": 4, "n_z": 8}
    assert parse_fitted_geometry(old).profile == "constant"
    assert parse_fitted_geometry(slab.as_dict()).profile == "linear"
    with pytest.raises(ValueError, match=r"geometry\.depth_profile: must be one of constant"):
        parse_geometry({"kind": "slab", "thickness": 5, "depth_profile": "cubic"})
    for bad in (0, 17, 2.5, True):
        with pytest.raises(ValueError, match=r"geometry\.n_z: must be an integer in \[1, 16\]"):
            parse_geometry({"kind": "slab", "thickness": 5, "n_z": bad})


def mc_sums(st, ss, g, h, boundary, bounces, photons, seed, width=48, height=32):
    mc = monte_carlo_slab(
        width,
        height,
        h,
        st,
        ss,
        g,
        FULL,
        bounces,
        boundary=boundary,
        photons=photons,
        seed=seed,
        camera_sampling=0.3,
    )
    return mc.images[0].sum((1, 2)), mc.total_stderr[0]


@pytest.mark.slow
@pytest.mark.parametrize(
    "tau,g,albedo,boundary",
    [
        (1.28, 0.8, 0.95, "refractive"),  # the worst case (σt .2, h 6.4)
        (0.3, 0.9, 0.99, "refractive"),
        (3.0, -0.3, 0.5, "absorbing"),
        (1.3, 0.4, 0.95, "absorbing"),
    ],
)
def test_contract_against_the_true_slab(tau, g, albedo, boundary):
    """Per-order image sums and their running sums within 2 % up to k = 6, and the sum
    of all orders within 1 %, against the 3-D slab Monte Carlo (plus twice its
    standard error), full illumination on 48×32, h 6.4 px, resolved n_z."""
    h, k = 6.4, 40
    st = tau / h
    ref, se = mc_sums(st, albedo * st, g, h, boundary, k, 2_000_000, 13)
    slab = Slab(h, boundary).resolve(g, st, albedo)
    got = render(st, albedo * st, g, slab, 48, 32, k).sum((1, 2))
    err, noise = got[:6] / ref[:6] - 1, se[:6] / ref[:6]
    assert np.all(np.abs(err) < 0.02 + 2 * noise), (err, noise)
    cum = np.cumsum(got[:6]) / np.cumsum(ref[:6]) - 1
    assert np.all(np.abs(cum) < 0.02 + 2 * noise), (cum, noise)
    assert ref[-1] < 1e-3 * ref.sum()  # the 40 orders are all that matter
    assert abs(got.sum() / ref.sum() - 1) < 0.01 + 2 * se.sum() / ref.sum()
