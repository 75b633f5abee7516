"""Stripe shifts as fewer patterns and full light (lightfield_jax.forward.pattern_basis)."""

import numpy as np
import pytest

from lightfield_jax import Full, Grid, Slab, Stripes
from lightfield_jax.forward.cell import CellRenderer
from lightfield_jax.forward.pattern_basis import pattern_basis, shift_basis
from lightfield_jax.forward.plane import PlaneRenderer
from lightfield_jax.forward.slab import SlabRenderer
from lightfield_jax.forward.slab_cell import SlabCellRenderer
from lightfield_jax.scene.illumination import scaled, source_moments


def _basis(stripes, width=40, height=30):
    full = Full(stripes.direction_deg, stripes.entry)
    moments = (source_moments(light, width, height) for light in (stripes, full))
    return pattern_basis(*moments)


def test_six_shifts_of_half_lit_stripes_are_three_of_them_and_full_light():
    basis = _basis(Stripes(6, 3, (0, 1, 2, 3, 4, 5)))
    assert basis.kept == (0, 1, 2)
    # A shift and the one half a period on add up to full light.
    expected = np.zeros((6, 4))
    expected[:3, :3] = np.eye(3)
    expected[3:, :3] = -np.eye(3)
    expected[3:, 3] = 1.0
    np.testing.assert_array_equal(np.array(basis.coef), expected)
    assert hash(basis) == hash(_basis(Stripes(6, 3, (0, 1, 2, 3, 4, 5))))


@pytest.mark.parametrize(
    "stripes",
    [
        Stripes(6, 3, (0, 1, 2, 3, 4, 5), direction_deg=30.0),  # lit parts at their own depth
        Stripes(8, 3, tuple(range(8))),  # every shift independent
        Stripes(6, 2, (0, 2, 4)),  # two of them and full light: no pattern saved
        Stripes(6, 3, (0, 1, 2)),  # independent
    ],
)
def test_no_basis_where_it_is_not_exact_or_saves_no_pattern(stripes):
    assert _basis(stripes) is None


def _renderer_type(geometry):
    """The full renderer of ``geometry`` and its arguments after the bounces."""
    if geometry == "plane":
        return PlaneRenderer, ("normalized",)
    return SlabRenderer, (Slab(4.0, "refractive", n=1.33, n_mu=4, n_z=1),)


def _every_pattern_marched(renderer_type, grid, light, *args, **kw):
    """A renderer that marches every pattern (the source moments given: no basis)."""
    f = grid.refine or 1
    moments = source_moments(scaled(light, f), grid.width * f, grid.height * f)
    return renderer_type(grid, light, *args, moments=moments, **kw)


@pytest.mark.parametrize("geometry", ["plane", "slab"])
def test_every_shifts_render_is_the_kept_shifts_and_full_lights(geometry):
    # Linearity in the unscattered light: the combination of renders is the render of
    # the combination, order by order, to float32 rounding.
    grid = Grid(30, 24, 16, 1)
    stripes = Stripes(6, 3, (0, 1, 2, 3, 4, 5))
    basis = shift_basis(grid, stripes, Full())
    assert basis is not None
    kind, args = _renderer_type(geometry)

    def render(light):
        return np.asarray(_every_pattern_marched(kind, grid, light, 5, *args)(0.3, 0.25, 0.6)[0])

    every = render(stripes)
    kept = render(Stripes(6, 3, tuple(stripes.phases[i] for i in basis.kept)))
    combined = np.asarray(basis.combine(kept, render(Full())[0]))
    np.testing.assert_allclose(combined, every, rtol=0, atol=2e-6 * every.max())


@pytest.mark.parametrize(
    ("geometry", "refine", "options"),
    [
        ("plane", 1, {"tail": "gmres"}),
        ("plane", 2, {}),
        ("plane", 2, {"coarse_after": 3}),
        ("slab", 1, {"tail": "gmres"}),
    ],
)
def test_full_renders_march_the_kept_shifts_and_full_light(geometry, refine, options):
    # The full-domain renderers march three shifts and full light for the six shifts
    # and return every shift's images, light fields, tail and slope along g as a march
    # of all six does.
    grid = Grid(24, 18, 8, refine)
    kind, args = _renderer_type(geometry)
    fewer = kind(grid, Stripes(), 4, *args, **options)
    every = _every_pattern_marched(kind, grid, Stripes(), 4, *args, **options)
    assert fewer.marched_basis.kept == (0, 1, 2) and every.marched_basis is None
    assert fewer.coverage.shape[0] == 4 and fewer.n_patterns == every.n_patterns == 6
    fields = "coarse_after" not in options
    a, b = (r(0.3, 0.25, 0.6, lightfield=fields) for r in (fewer, every))
    pairs = [(a[0], b[0]), (a[1], b[1])]
    if "tail" in options:
        pairs += [(a[2].image, b[2].image), (a[2].lightfield, b[2].lightfield)]
    else:
        slopes = (r.images_and_g_slope(0.3, 0.25, 0.6) for r in (fewer, every))
        pairs += list(zip(*slopes, strict=True))
    for x, y in pairs:
        if y is None:
            assert x is None
            continue
        x, y = np.asarray(x), np.asarray(y)
        assert x.shape == y.shape
        np.testing.assert_allclose(x, y, rtol=0, atol=3e-6 * np.abs(y).max())
    assert not kind(grid, Stripes(direction_deg=20.0), 4, *args).marched_basis


def test_cell_renderers_use_the_basis_only_where_it_holds():
    grid = Grid(48, 36, 16, 2)
    straight, oblique = Stripes(), Stripes(direction_deg=20.0)
    # Full light comes from the shifts' mean walls' term, marched past shift_orders.
    cell = CellRenderer(grid, straight, 12, "normalized", shift_orders=5)
    assert cell.basis.kept == (0, 1, 2) and cell.wall_bands.basis is not None
    assert CellRenderer(grid, oblique, 12, "normalized", shift_orders=5).basis is None
    assert CellRenderer(grid, straight, 6, "normalized", shift_orders=None).basis is None
    slab = Slab(4.0, "refractive", n=1.33, n_mu=4, n_z=1)
    assert SlabCellRenderer(Grid(48, 36, 8, 1), straight, 6, slab).basis.kept == (0, 1, 2)
    assert SlabCellRenderer(Grid(48, 36, 8, 1), oblique, 6, slab).basis is None


def test_two_renderers_of_one_configuration_share_their_compiled_program():
    # The basis is a static field: two equal renderers compare equal (a jit cache hit),
    # not an error comparing arrays.
    grid = Grid(24, 18, 8, 2)
    a, b = (CellRenderer(grid, Stripes(), 8, "normalized", shift_orders=5) for _ in range(2))
    assert a.basis == b.basis
    np.testing.assert_array_equal(np.asarray(a(0.3, 0.2, 0.5)[0]), np.asarray(b(0.3, 0.2, 0.5)[0]))


@pytest.mark.parametrize("geometry", ["plane", "slab"])
def test_stripe_cells_render_the_same_with_and_without_the_basis(geometry, monkeypatch):
    # The basis changes what is rendered, not the images: every shift's walls' terms,
    # wall bands and (slab) first orders and deviation as without it.
    stripes = Stripes()

    def cell():
        if geometry == "plane":
            r = CellRenderer(Grid(36, 24, 16, 2), stripes, 10, "normalized", shift_orders=5)
        else:
            slab = Slab(4.0, "refractive", n=1.33, n_mu=4, n_z=1)
            r = SlabCellRenderer(Grid(36, 24, 8, 1), stripes, 8, slab, deviation=(8, 4))
        return r, np.asarray(r(0.25, 0.22, 0.7)[0])

    with_basis, a = cell()
    assert with_basis.basis is not None
    module = "cell" if geometry == "plane" else "slab_cell"
    monkeypatch.setattr(f"lightfield_jax.forward.{module}.shift_basis", lambda *_: None)
    without, b = cell()
    assert without.basis is None
    np.testing.assert_allclose(a, b, rtol=0, atol=3e-6 * b.max())


def test_combined_shifts_are_light_and_never_negative():
    # The slab clips its march's rounding at 0, so its march is not exactly linear: a
    # shift combined as full light less a kept shift came out about -1e-10 of the peak
    # in 269 pixels of this render before the combination was clipped.
    slab = Slab(4.0, "refractive", n=1.33, n_mu=4, n_z=1)
    renderer = SlabRenderer(Grid(24, 18, 8, 1), Stripes(), 4, slab)
    assert renderer.marched_basis is not None
    images, fields = renderer(2.0, 1.0, 0.9, lightfield=True)
    assert float(np.min(images)) >= 0.0 and float(np.min(fields)) >= 0.0


def test_the_slab_estimate_covers_the_blocks_of_the_marched_patterns():
    # Four marched patterns take other blocks than six: here one block of 4 patterns,
    # whose Krylov vectors the estimate must hold (it held a 1-pattern block's).
    from lightfield_jax.forward.slab_memory import (
        KERNEL_COPIES,
        field_bytes,
        kernel_count,
        slab_blocks,
        slab_render_bytes,
        spectrum_bytes,
        working_bytes,
    )
    from lightfield_jax.forward.tail import GMRES_RESTART

    h, w, n_theta, n_mu = 96, 256, 16, 16  # 128×48 at refine 2
    patterns, mu = slab_blocks(4, h, w, n_theta, n_mu, 1, 1)
    need = working_bytes(patterns, mu, h, w, n_theta, n_mu, 1, 1)
    need += (GMRES_RESTART + 3) * patterns * field_bytes(h, w, n_theta, n_mu, 1)
    need += KERNEL_COPIES * kernel_count(1, 1) * spectrum_bytes(h, w, n_theta, n_mu, 1)
    assert patterns == 4
    assert slab_render_bytes(6, 48, 128, n_theta, n_mu, 1, 1, refine=2, tail=True) >= need
