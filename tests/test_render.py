"""Forward model: closed forms, symmetries, energy balance (gradients, no recompiles,
sigma_s scaling and stripe sums: with the other renderers' in test_renderers.py)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lightfield_jax as lfj
from lightfield_jax.forward.render import renderer_for

MILK = dict(sigma_t=0.2051, sigma_s=0.0366, g=0.4)


def _images(medium, grid, illum, k, **kw):
    return np.asarray(lfj.render(medium, grid, illum, bounces=k, **kw).images)


def test_phase_integral_reference_values():
    # docs/model.md section 2.
    for g, a in ((0.0, 0.5), (0.4, 0.619), (0.7, 1.105), (0.8, 1.622), (0.9, 3.20)):
        assert float(lfj.phase_integral(g)) == pytest.approx(a, abs=1.5e-3)
        assert float(lfj.phase_integral(-g)) == pytest.approx(float(lfj.phase_integral(g)))


def test_single_scatter_of_a_beam_matches_closed_form():
    grid = lfj.Grid(64, 24, 32)
    images = _images(lfj.Medium(**MILK), grid, lfj.Beam(0.0, 12.5), 1)
    expected = lfj.single_scatter_closed_form(MILK["sigma_t"], MILK["sigma_s"], MILK["g"], 64)
    np.testing.assert_allclose(images[0, 12], expected, rtol=1e-3)
    assert np.all(images[0, :12] == 0) and np.all(images[0, 13:] == 0)


@pytest.mark.parametrize("sigma_t", [0.05, 0.5, 2.0])
def test_single_scatter_closed_form_over_sigma_t(sigma_t):
    grid = lfj.Grid(40, 8, 16)
    images = _images(lfj.Medium(sigma_t, 0.5 * sigma_t, 0.2), grid, lfj.Beam(0.0, 4.5), 1)
    expected = lfj.single_scatter_closed_form(sigma_t, 0.5 * sigma_t, 0.2, 40)
    np.testing.assert_allclose(images[0, 4], expected, rtol=1e-2)


def test_oblique_beam_stays_a_beam():
    w, h, theta0 = 64, 48, 30.0
    grid = lfj.Grid(w, h, 32)
    medium = lfj.Medium(0.1, 0.04, 0.8)
    i1 = _images(medium, grid, lfj.Beam(0.0, 5.0, theta0, 1.0), 1)[0]
    t = math.radians(theta0)
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    distance_to_axis = np.abs(-(xx - 0.0) * math.sin(t) + (yy - 5.0) * math.cos(t))
    # Nothing farther than half the width plus a pixel's half-diagonal from the axis.
    assert np.all(i1[distance_to_axis > 0.5 + math.sqrt(0.5)] == 0)
    # Per column, the lit part integrates the attenuated sheet: (w/cos)·e^{−σt x/cos}.
    p90 = float(lfj.phase_function(math.pi / 2, 0.8))
    cols = np.arange(40)  # before the beam reaches the bottom wall
    s0, s1 = cols / math.cos(t), (cols + 1) / math.cos(t)
    expected = 0.04 * p90 * (np.exp(-0.1 * s0) - np.exp(-0.1 * s1)) / 0.1
    np.testing.assert_allclose(i1.sum(axis=0)[cols], expected, rtol=1e-2)


def test_mirror_symmetry_in_y_and_x():
    grid = lfj.Grid(36, 28, 32)
    medium = lfj.Medium(0.25, 0.2, 0.6)
    a = _images(medium, grid, lfj.Beam(0.0, 9.0, 20.0, 1.5), 4)
    b = _images(medium, grid, lfj.Beam(0.0, 28 - 9.0, -20.0, 1.5), 4)
    np.testing.assert_allclose(b, a[:, ::-1, :], rtol=1e-9, atol=1e-14)
    c = _images(medium, grid, lfj.Beam(36.0, 9.0, 160.0, 1.5), 4)
    np.testing.assert_allclose(c, a[:, :, ::-1], rtol=1e-9, atol=1e-14)


@pytest.mark.parametrize("g", [0.0, 0.6])
def test_transposed_scene_gives_transposed_images(g):
    # A beam from the top heading down on the transposed grid is the same scene
    # rotated; with g = 0 the scattering is isotropic in the plane as well.
    medium = lfj.Medium(0.2, 0.15, g)
    a = _images(medium, lfj.Grid(32, 32, 32), lfj.Beam(0.0, 12.5), 3)
    b = _images(medium, lfj.Grid(32, 32, 32), lfj.Beam(12.5, 0.0, 90.0), 3)
    for k in range(3):
        err = np.abs(b[k].T - a[k]).sum() / a[k].sum()
        # The diagonal bins belong to the x sweep in both scenes, which breaks the
        # transposition symmetry at the per-mille level.
        assert err < 1e-2, (k, err)


@pytest.mark.parametrize("g", [0.0, 0.7, -0.5])
def test_second_bounce_matches_direct_quadrature(g):
    # I_2(x) = σs² p(π/2) ∫ dl e^{−σt l} p(angle(x − b(l))) e^{−σt r}/r for a unit beam
    # b(l) = (l, y_b + u) along +x, integrated over the beam's length and width u and
    # averaged over the target pixel by sub-sampling.
    sigma_t, sigma_s, w, h, yb = 0.15, 0.1, 40, 30, 10.5
    images = _images(lfj.Medium(sigma_t, sigma_s, g), lfj.Grid(w, h, 64), lfj.Beam(0.0, yb), 2)
    p90 = float(lfj.phase_function(np.pi / 2, g))
    l = (np.arange(8000) + 0.5) * (w / 8000)
    sub = (np.arange(6) + 0.5) / 6
    across = (np.arange(8) + 0.5) / 8 - 0.5
    for r, c in ((16, 5), (22, 20), (3, 30), (28, 38), (15, 12), (13, 5)):
        vals = []
        for sy in sub:
            for sx in sub:
                dx = c + sx - l
                for u in across:
                    dy = r + sy - (yb + u)
                    dist = np.hypot(dx, dy)
                    p = np.asarray(lfj.phase_function(np.arctan2(dy, dx), g))
                    vals.append(np.sum(np.exp(-sigma_t * (l + dist)) * p / dist) * (w / 8000))
        expected = sigma_s**2 * p90 * np.mean(vals)
        assert images[1, r, c] == pytest.approx(expected, rel=5e-3), (r, c)


def _outflux(lf_k, sigma_t, dtheta):
    """Power of L_k leaving through the four walls (radiance at the edge pixel centres,
    attenuated over the remaining half pixel)."""
    n = lf_k.shape[-1]
    theta = np.arange(n) * dtheta
    c, s = np.cos(theta), np.sin(theta)
    total = 0.0
    for edge, cos_n in (
        (lf_k[:, -1, :], c),  # right wall, outward normal +x
        (lf_k[:, 0, :], -c),  # left
        (lf_k[-1, :, :], s),  # bottom
        (lf_k[0, :, :], -s),  # top
    ):
        out = cos_n > 1e-12
        att = np.exp(-sigma_t * 0.5 / np.where(out, cos_n, 1.0))
        total += np.sum(edge[:, out] * cos_n[out] * att[out]) * dtheta
    return total


@pytest.mark.parametrize("phase", ["paper", "normalized"])
def test_energy_balance_per_bounce(phase):
    # What a generation emits = what it loses to collisions + what leaves the walls.
    sigma_t, sigma_s, g = 0.12, 0.1, 0.5
    grid = lfj.Grid(48, 40, 32)
    medium = lfj.Medium(sigma_t, sigma_s, g, phase)
    res = lfj.render(medium, grid, lfj.Beam(0.0, 20.0, 0.0, 2.0), 4, lightfield=True)
    lf = np.asarray(res.lightfields)
    dtheta = 2 * np.pi / 32
    a = float(lfj.phase_integral(g)) if phase == "paper" else 1.0
    fluence = lf.sum(axis=-1) * dtheta  # (K+1, H, W)
    # Generation 0: the beam (power 2) is collided or leaves the far wall.
    entered = 2.0
    escaped0 = 2.0 * math.exp(-sigma_t * 48)
    assert sigma_t * fluence[0].sum() + escaped0 == pytest.approx(entered, rel=1e-3)
    for k in (1, 2, 3):
        emitted = sigma_s * a * fluence[k - 1].sum()
        lost = sigma_t * fluence[k].sum() + _outflux(lf[k], sigma_t, dtheta)
        assert lost == pytest.approx(emitted, rel=0.02), (k, lost / emitted)


def test_float32_and_float64_both_run():
    grid = lfj.Grid(20, 12, 16)
    renderer = renderer_for(grid, lfj.Beam(0.0, 6.0), 3, "paper")
    f32, _ = renderer(jnp.float32(0.2), jnp.float32(0.1), jnp.float32(0.4))
    f64, _ = renderer(jnp.float64(0.2), jnp.float64(0.1), jnp.float64(0.4))
    assert f32.dtype == jnp.float32 and f64.dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(f32), np.asarray(f64), rtol=2e-4, atol=1e-9)


def test_auto_bounces_from_tail_bound():
    medium = lfj.Medium(**MILK)
    res = lfj.render(medium, lfj.Grid(32, 16, 16), lfj.Beam(0.0, 8.0), "auto", tolerance=1e-4)
    rho = float(medium.rho)
    k = res.bounces
    assert rho**k / (1 - rho) <= 1e-4 < rho ** (k - 1) / (1 - rho)
    assert res.converges


def test_auto_refuses_divergent_series_and_explicit_k_says_so():
    medium = lfj.Medium(0.2, 0.15, 0.9)  # rho = 0.75 * 3.2 = 2.4
    assert float(medium.rho) > 1
    with pytest.raises(ValueError, match="diverges"):
        lfj.render(medium, lfj.Grid(16, 12, 16), lfj.Beam(0.0, 6.0), "auto")
    with pytest.warns(lfj.DivergentSeriesWarning):
        res = lfj.render(medium, lfj.Grid(16, 12, 16), lfj.Beam(0.0, 6.0), 3)
    assert not res.converges
    assert res.images.shape == (3, 12, 16)
    normalized = lfj.Medium(0.2, 0.15, 0.9, "normalized")
    assert lfj.render(normalized, lfj.Grid(16, 12, 16), lfj.Beam(0.0, 6.0), "auto").converges


def test_lightfield_shapes_and_camera_consistency():
    medium = lfj.Medium(0.2, 0.1, 0.4)
    res = lfj.render(medium, lfj.Grid(20, 12, 16), lfj.Beam(0.0, 6.0), 3, lightfield=True)
    assert res.lightfields.shape == (4, 12, 20, 16)
    dtheta = 2 * np.pi / 16
    p90 = float(lfj.phase_function(np.pi / 2, 0.4))
    lf = np.asarray(res.lightfields)
    for k in range(1, 4):
        expected = 0.1 * p90 * lf[k - 1].sum(axis=-1) * dtheta
        np.testing.assert_allclose(np.asarray(res.images[k - 1]), expected, rtol=1e-9)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: lfj.Medium(-0.1, 0.0, 0.0), "sigma_t"),
        (lambda: lfj.Medium(0.1, 0.2, 0.0), "sigma_s"),
        (lambda: lfj.Medium(0.1, 0.05, 1.0), "g"),
        (lambda: lfj.Medium(0.1, 0.05, 0.0, "flat"), "phase"),
        (lambda: lfj.Grid(16, 12, 12), "n_theta"),
        (lambda: lfj.Grid(1, 12, 16), "width"),
        (lambda: lfj.Beam(0.0, 6.0, 180.0).entry_wall(16, 12), "point into"),
        (lambda: lfj.Beam(3.0, 6.0).entry_wall(16, 12), "wall"),
        (lambda: lfj.Stripes(period=6, lit=6), "lit"),
        (lambda: lfj.Full(entry="front"), "entry"),
    ],
)
def test_bad_scene_values_raise_clear_errors(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_refined_grid_keeps_closed_forms_and_agrees_with_native():
    medium = lfj.Medium(0.2, 0.1, 0.5)
    beam = lfj.Beam(0.0, 8.5)
    fine = _images(medium, lfj.Grid(32, 16, 16, refine=2), beam, 3)
    native = _images(medium, lfj.Grid(32, 16, 16, refine=1), beam, 3)
    expected = lfj.single_scatter_closed_form(0.2, 0.1, 0.5, 32)
    np.testing.assert_allclose(fine[0, 8], expected, rtol=1e-3)
    doubled = _images(lfj.Medium(0.2, 0.2, 0.5), lfj.Grid(32, 16, 16, refine=2), beam, 3)
    for k in range(3):
        np.testing.assert_allclose(doubled[k], 2.0 ** (k + 1) * fine[k], rtol=1e-9, atol=1e-300)
        assert np.abs(fine[k] - native[k]).sum() / native[k].sum() < 0.05


def test_default_resolution_follows_g():
    assert lfj.Grid(8, 8).resolve(0.4) == lfj.Grid(8, 8, 32, 1)
    assert lfj.Grid(8, 8).resolve(-0.8) == lfj.Grid(8, 8, 64, 2)
    assert lfj.Grid(8, 8, 128).resolve(0.95).n_theta == 128


@pytest.mark.parametrize(
    "illum, bounces, refine, phase",
    [
        (lfj.Full(), 1, 1, "paper"),
        (lfj.Full(), 2, 1, "paper"),
        (lfj.Full(), 5, 1, "paper"),
        (lfj.Stripes(period=6, lit=3, phases=(0, 2, 4)), 4, 2, "normalized"),
        (lfj.Beam(0.0, 4.0, 20.0, 1.0), 3, 1, "paper"),  # an oblique beam
    ],
)
def test_images_and_g_slope_match_the_render_and_its_jvp(illum, bounces, refine, phase):
    grid = lfj.Grid(20, 14, 16, refine=refine)
    renderer = renderer_for(grid, illum, bounces, phase)
    st, ss, g = 0.2, 0.12, 0.45
    images, slope = renderer.images_and_g_slope(st, ss, g, 1.7)
    want, want_slope = jax.jvp(lambda x: renderer(st, ss, x, 1.7)[0], (g,), (1.0,))
    assert images.shape == slope.shape == want.shape
    np.testing.assert_allclose(images, want, rtol=1e-12, atol=1e-15)
    scale = float(jnp.max(jnp.abs(want_slope)))
    assert scale > 0
    np.testing.assert_allclose(slope, want_slope, rtol=0, atol=1e-12 * scale)
    # and it is the derivative: central differences along g
    h = 1e-6
    fd = (renderer(st, ss, g + h, 1.7)[0] - renderer(st, ss, g - h, 1.7)[0]) / (2 * h)
    np.testing.assert_allclose(slope, fd, rtol=0, atol=1e-6 * scale)


@pytest.mark.parametrize(
    ("illumination", "axis"),
    [
        (lfj.Stripes(), "x"),
        (lfj.Stripes(entry="top"), "y"),
        (lfj.Stripes(direction_deg=20.0), None),
    ],
)
def test_separable_first_scatter_equals_the_fft(monkeypatch, illumination, axis):
    """Light entering a wall along its normal: L_1's convolution as two matrix products
    gives the FFT's images and slopes (to float32 rounding); oblique light keeps the
    FFT."""
    import lightfield_jax.forward.plane as plane

    grid = lfj.Grid(24, 18, 16, 1)
    fast = plane.PlaneRenderer(grid, illumination, 4)
    monkeypatch.setattr(plane, "separable_source", lambda *a: None)
    slow = plane.PlaneRenderer(grid, illumination, 4)
    assert fast.separable == axis and slow.separable is None
    values = (jnp.float32(0.2), jnp.float32(0.1), jnp.float32(0.6))

    def images(renderer):
        def f(st, g):
            return renderer(st, values[1], g)[0]

        return jax.jvp(f, (values[0], values[2]), (jnp.float32(1.0), jnp.float32(0.5)))

    (a, da), (b, db) = images(fast), images(slow)
    assert float(jnp.max(jnp.abs(a - b))) < 1e-6 * float(jnp.max(b))
    assert float(jnp.max(jnp.abs(da - db))) < 1e-6 * float(jnp.max(jnp.abs(db)))


@pytest.mark.parametrize("shape", [(5, 37), (37, 5), (9, 9)])
@pytest.mark.parametrize("periods", [0, 2])
def test_sweep_of_a_short_wide_grid_is_the_step_by_step_sweep(monkeypatch, shape, periods):
    """Where one direction group marches many more steps than the other, a scan step
    advances it several steps: the same light as one step each, walls and wrap alike."""
    from lightfield_jax.forward import transport as tr

    groups = tr.direction_groups(16)
    tables = tr.transport_tables(groups)
    q = jax.random.uniform(jax.random.PRNGKey(3), (2, 16) + shape)

    def light():
        return np.asarray(tr.transport(q, jnp.float32(0.3), groups, tables, periods=periods))

    several = light()
    monkeypatch.setattr(tr, "_MAX_STEPS_PER_STEP", 1)
    one = light()
    assert np.max(np.abs(several - one)) <= 1e-6 * np.max(np.abs(one))
    assert np.max(np.abs(one)) > 0
