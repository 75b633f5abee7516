"""The stripe cell (lightfield_jax.forward.cell) against full-domain renders."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lightfield_jax import Grid, Stripes
from lightfield_jax.forward.cell import CellRenderer, PeriodicCell
from lightfield_jax.forward.plane import PlaneRenderer


def _both(grid, stripes, bounces, **kw):
    full = PlaneRenderer(grid, stripes, bounces, "normalized", tail=kw.get("tail"))
    return full, CellRenderer(grid, stripes, bounces, "normalized", **kw)


def _rows_error(a, b):
    """max over shifts and columns of |b − a| per row, over the row's largest value."""
    return np.max(np.abs(b - a), axis=(0, 2)) / np.max(a, axis=(0, 2))


@pytest.mark.parametrize("direction_deg", [0.0, 25.0])
def test_cell_with_every_shifts_walls_term_on_its_own_grid_is_the_full_render(direction_deg):
    # With the walls' term on the cell's own grid (refine 1), the cell's periodic
    # march must cancel exactly against the periodic grid's: what is left is the exact
    # I_1, I_2 and the tank's render of every shift, i.e. the full-domain render (to
    # the y sweep's history, which starts ``periods`` cells upstream of each shift's
    # rows: a few 1e-6 of the peak here).
    grid = Grid(40, 30, 16, 1)
    stripes = Stripes(6, 3, (0, 1, 2, 3, 4, 5), direction_deg=direction_deg)
    full, cell = _both(grid, stripes, 6)
    a = np.asarray(full(0.3, 0.2, 0.5)[0])
    b = np.asarray(cell(0.3, 0.2, 0.5)[0])
    assert b.shape == a.shape
    np.testing.assert_allclose(b, a, rtol=2e-5, atol=1e-5 * a.max())


def test_periodic_cell_is_the_tank_far_from_its_walls():
    # A dense medium forgets the walls within a few rows: the cell, rolled to each
    # shift, is the full-domain render in the middle of a tall tank, order by order.
    grid = Grid(32, 60, 16, 1)
    stripes = Stripes(6, 2, (0, 1, 2, 3, 4, 5))
    full = np.asarray(PlaneRenderer(grid, stripes, 5, "normalized")(0.8, 0.4, 0.3)[0])
    cell = PeriodicCell(Grid(32, 6, 16, 1), Stripes(6, 2, (0,)), 5, "normalized", tank_height=60)
    one = np.asarray(cell(0.8, 0.4, 0.3)[0])[0]  # (K, 6, W)
    for s in range(6):
        rolled = one[:, (np.arange(60) + s) % 6]
        mid = slice(24, 36)
        np.testing.assert_allclose(
            rolled[:, mid], full[s][:, mid], rtol=1e-4, atol=1e-7 * full.max()
        )


def test_first_two_orders_are_exact_at_the_walls():
    grid = Grid(24, 18, 8, 2)
    stripes = Stripes(6, 3, (0, 2, 4), direction_deg=-20.0)
    full, cell = _both(grid, stripes, 4, shift_orders=2)
    a = np.asarray(full(0.2, 0.1, 0.6)[0])
    b = np.asarray(cell(0.2, 0.1, 0.6)[0])
    np.testing.assert_allclose(b[:, :2], a[:, :2], rtol=1e-5, atol=1e-7 * a.max())


@pytest.mark.parametrize(
    ("shift_orders", "refine", "bound"),
    # The rows' worst error of the series' image, here largest in the rows next to the
    # walls (docs/periodic_cell.md has the measured table for other media).
    [(None, 2, 1e-4), (2, 1, 0.002)],
)
def test_walls_terms_keep_the_rows_next_to_the_walls(shift_orders, refine, bound):
    grid = Grid(36, 30, 16, refine)
    stripes = Stripes(6, 3, (0, 1, 2, 3, 4, 5))
    full, cell = _both(grid, stripes, 10, shift_orders=shift_orders)
    assert (cell.wall_bands is not None) == (refine > 1)
    a = np.asarray(full(0.2, 0.05, 0.4)[0]).sum(axis=1)
    b = np.asarray(cell(0.2, 0.05, 0.4)[0]).sum(axis=1)
    rows = _rows_error(a, b)
    assert rows.max() < bound, rows
    # ... and the error is the walls': it falls off away from them.
    assert rows[10:-10].max() < 0.5 * rows.max()


def test_shifts_mean_walls_term_keeps_the_cells_histories_in_a_thin_medium():
    # Full light's periodic grid is a period of the stripes, as the cell's: its march
    # keeps the rows the cell keeps. On two rows it kept longer histories, which a thin
    # medium in a short tank remembers (measured: 0.22 % off the full render in the
    # worst row, 0.10 % now; the shifts' own terms for 5 orders, the mean's after).
    grid = Grid(64, 48, 16, 2)
    full, cell = _both(grid, Stripes(), 20, shift_orders=5)
    a = np.asarray(full(0.05, 0.045, 0.5)[0]).sum(axis=1)
    rows = _rows_error(a, np.asarray(cell(0.05, 0.045, 0.5)[0]).sum(axis=1))
    assert rows.max() < 0.0013, rows


@pytest.mark.slow
def test_wall_bands_take_the_refined_grids_detail_next_to_the_walls():
    # On a refined grid the native grid's walls' term misses the detail of the first
    # orders next to the walls; the short tank's correction brings those rows to the
    # middle rows' error (measured: 1.2e-4 without, 2.6e-5 with, 9.6e-6 in the middle).
    grid = Grid(36, 30, 16, 2)
    stripes = Stripes(6, 3, (0, 1, 2, 3, 4, 5))
    full = PlaneRenderer(grid, stripes, 10, "normalized")
    a = np.asarray(full(0.2, 0.05, 0.4)[0]).sum(axis=1)
    errors = []
    for band in (0, 2):
        cell = CellRenderer(grid, stripes, 10, "normalized", shift_orders=6, wall_band=band)
        errors.append(_rows_error(a, np.asarray(cell(0.2, 0.05, 0.4)[0]).sum(axis=1)))
    without, with_band = errors
    walls = [0, 1, -2, -1]
    assert with_band[walls].max() < 0.25 * without[walls].max(), (without, with_band)
    assert with_band.max() < 5e-5, with_band


def test_tail_solve_on_the_cell_sums_the_same_series():
    grid = Grid(24, 18, 8, 1)
    stripes = Stripes(6, 3, (0, 1, 2, 3, 4, 5))
    full, cell = _both(grid, stripes, 3, tail="gmres", tail_tol=1e-6)
    _, _, ta = full(0.3, 0.27, 0.5)
    images, fields, tb = cell(0.3, 0.27, 0.5)
    assert fields is None
    assert bool(tb.converged)
    # To the y sweep's history (the cell's rows see the tank's height upstream, each
    # shift's own rows a little more or less) and the three solves' tolerances.
    np.testing.assert_allclose(tb.image, ta.image, rtol=1e-4, atol=5e-4 * float(ta.image.max()))


def test_cell_derivatives_are_the_full_renders():
    # A tank tall enough that the y sweep's history (its height) is many free paths.
    grid = Grid(20, 36, 8, 1)
    stripes = Stripes(6, 3, (0, 1, 2, 3, 4, 5))
    full, cell = _both(grid, stripes, 4)

    def total(r):
        return lambda x: jnp.sum(r(x[0], x[1], x[2])[0], axis=1)

    x = jnp.array([0.25, 0.15, 0.5])
    for v in (jnp.array([1.0, 0, 0]), jnp.array([0, 1.0, 0]), jnp.array([0, 0, 1.0])):
        da = jax.jvp(total(full), (x,), (v,))[1]
        db = jax.jvp(total(cell), (x,), (v,))[1]
        np.testing.assert_allclose(db, da, rtol=1e-4, atol=5e-4 * float(jnp.abs(da).max()))
    slope = cell.images_and_g_slope(0.25, 0.15, 0.5)[1]
    expected = full.images_and_g_slope(0.25, 0.15, 0.5)[1]
    np.testing.assert_allclose(slope, expected, atol=5e-4 * float(jnp.abs(expected).max()))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"illumination": Stripes(6, 3, (0, 1), entry="top")}, "top or bottom wall"),
        ({"shift_orders": 1}, "shift_orders: must be an integer >= 2"),
        ({"walls_coarsen": 5}, "walls_coarsen 5 must divide the grid"),
        ({"illumination": Stripes(24, 3, (0, 1))}, "period is not shorter than the tank"),
    ],
)
def test_cell_refusals(kwargs, message):
    args = {"illumination": Stripes(6, 3, (0, 1))} | kwargs
    with pytest.raises(ValueError, match=message):
        CellRenderer(Grid(24, 18, 8, 1), bounces=3, **args)


def test_cell_renders_no_light_fields():
    cell = CellRenderer(Grid(24, 18, 8, 1), Stripes(6, 3, (0, 1)), 3)
    with pytest.raises(ValueError, match="renders images only"):
        cell(0.3, 0.1, 0.2, lightfield=True)


def test_the_fits_cheap_models_render_stripes_from_one_period():
    # The scan's and the extrapolated solve's models (cell set) take the cell; every
    # other model, full light and the slab take the full render.
    import dataclasses

    from lightfield_jax import Slab
    from lightfield_jax.inverse.geometry_model import SlabModel
    from lightfield_jax.inverse.joint_fit.stage import model_renderer
    from lightfield_jax.inverse.model_size import ModelSpec
    from lightfield_jax.scene.illumination import Full

    stripes = Stripes(6, 3, (0, 1, 2, 3, 4, 5))
    model = ModelSpec(Grid(24, 18, 8, 1), 4, (0, 0, 24, 18), converges=True, rho=0.5)
    assert type(model_renderer(model, stripes, "paper")) is PlaneRenderer
    cheap = dataclasses.replace(model, cell=2)
    cell = model_renderer(cheap, stripes, "paper")
    assert isinstance(cell, CellRenderer) and cell.shift_orders == 2
    assert type(model_renderer(cheap, Full(), "paper")) is PlaneRenderer
    slab = Slab(3.0, "absorbing", n_mu=4, n_z=1)
    on_slab = model_renderer(dataclasses.replace(cheap, geometry=SlabModel(slab)), stripes, "paper")
    assert not isinstance(on_slab, CellRenderer)
    # A sized slab model (the slab's shift orders, a long series, a deviation grid
    # coarser than its own) renders its cell; the cheap one (the shifts' mean alone), a
    # short series or a model as coarse as the deviation grid, the whole tank.
    from lightfield_jax.forward.slab import SlabRenderer
    from lightfield_jax.forward.slab_cell import SLAB_SHIFT_ORDERS, SlabCellRenderer
    from lightfield_jax.inverse.geometry_model import SLAB_CELL_BOUNCES

    assert isinstance(on_slab, SlabRenderer)
    layered = SlabModel(Slab(3.0, "absorbing", n_mu=8, n_z=2))
    sized = dataclasses.replace(
        cheap, geometry=layered, cell=SLAB_SHIFT_ORDERS, bounces=SLAB_CELL_BOUNCES
    )
    assert isinstance(model_renderer(sized, stripes, "paper"), SlabCellRenderer)
    for other in (
        dataclasses.replace(sized, bounces=SLAB_CELL_BOUNCES - 1),
        dataclasses.replace(sized, geometry=SlabModel(slab)),  # 4 nodes, 1 layer
    ):
        assert type(model_renderer(other, stripes, "paper")) is SlabRenderer


@pytest.mark.parametrize(
    ("stripe_cell", "refine", "expected"), [(True, 2, 10), (False, 2, None), (True, 1, None)]
)
def test_sized_refined_plane_models_render_side_wall_stripes_from_one_period(
    stripe_cell, refine, expected
):
    # The final model and the error term's finer model: the cell with its defaults on a
    # refined grid unless the fit option turns it off; the native grid renders the tank.
    import lightfield_jax as lfj
    from lightfield_jax.inverse.joint_fit.finer import finer
    from lightfield_jax.inverse.model_size import size_model

    options = lfj.FitOptions(phase="normalized", refine=refine, stripe_cell=stripe_cell)
    model = size_model(np.zeros((6, 18, 24)), Stripes(), 0.8, 0.7, options, 1.03, 0.2)
    assert model.cell == expected
    assert model.as_dict()["stripe_cell"] == (
        None if expected is None else {"shift_orders": 10, "walls_coarsen": 1}
    )
    assert finer(model, options, 0.7).cell == (10 if stripe_cell else None)


def test_a_models_record_says_what_its_renderer_does_with_the_fits_stripes():
    # The cell marches every bounce on the model's grid: where it renders the fit's
    # stripes, the record's coarse tail is full light's alone; where it does not
    # (stripes entering the top wall, full light), no cell. Without the stripes, both
    # as the model asks; a result's model read back renders as the fit did.
    from lightfield_jax.inverse.fit import model_from
    from lightfield_jax.inverse.model_size import ModelSpec
    from lightfield_jax.scene.illumination import Full

    grid = Grid(24, 18, 8, 2)
    model = ModelSpec(grid, 12, (0, 0, 24, 18), converges=True, rho=0.5, cell=10, coarse_after=4)
    asked = model.as_dict()
    assert (
        asked["stripe_cell"] == {"shift_orders": 10, "walls_coarsen": 1}
        and asked["coarse_tail"]["after"] == 4
    )
    assert "stripes" not in asked["coarse_tail"]
    side = model.as_dict(Stripes())
    assert side["stripe_cell"] == {"shift_orders": 10, "walls_coarsen": 1}
    assert side["coarse_tail"]["after"] == 4 and side["coarse_tail"]["stripes"] is False
    for light in (Stripes(entry="top"), Full()):
        record = model.as_dict(light)
        assert record["stripe_cell"] is None and record["coarse_tail"] == asked["coarse_tail"]
    back = model_from(side)
    assert (back.cell, back.coarse_after) == (10, 4)


@pytest.mark.parametrize("stripe_cell", [True, False])
def test_sized_slab_models_render_side_wall_stripes_from_one_period(stripe_cell):
    import lightfield_jax as lfj
    from lightfield_jax.forward.slab_cell import SLAB_SHIFT_ORDERS
    from lightfield_jax.inverse.joint_fit.finer import finer
    from lightfield_jax.inverse.model_size import size_model

    slab = lfj.Slab(6.4, "refractive", n=1.33)
    options = lfj.FitOptions(phase="normalized", geometry=slab, stripe_cell=stripe_cell)
    model = size_model(np.zeros((6, 18, 24)), Stripes(), 0.95, 0.8, options, 1.03, 0.2)
    expected = SLAB_SHIFT_ORDERS if stripe_cell else None
    assert model.cell == expected and finer(model, options, 0.8).cell == expected


def test_the_cheap_models_cell_marches_its_walls_term_twice_as_coarse():
    """The basin scan's and the cheap solve's cell (the shifts' mean alone: their answers
    are corrected to the final model) marches the walls' term on a grid twice as coarse
    where 2 divides the model; the final models' cells on their own grid."""
    from lightfield_jax.inverse.cheap_cell import CHEAP_CELL
    from lightfield_jax.inverse.model_size import ModelSpec

    for (width, height), cell, coarsen in [
        ((24, 18), CHEAP_CELL, 2),
        ((25, 18), CHEAP_CELL, 1),  # 2 does not divide the width
        ((24, 18), 10, 1),
    ]:
        model = ModelSpec(
            Grid(width, height, 8, 1), 12, (0, 0, width, height), converges=True, rho=0.5,
            cell=cell,
        )  # fmt: skip
        assert model.as_dict()["stripe_cell"] == {"shift_orders": cell, "walls_coarsen": coarsen}
        renderer = model.geometry.renderer(model, Stripes(), "paper")
        assert renderer.mean_walls.coarsen == coarsen
