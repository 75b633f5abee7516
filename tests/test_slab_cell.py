"""The slab on one stripe period (lightfield_jax.forward.slab_cell) against the full
slab render, in the rows the tank's walls do not reach."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lightfield_jax.forward.slab import SlabRenderer
from lightfield_jax.forward.slab_cell import SlabCellRenderer, SlabPeriodicCell, shift_rows
from lightfield_jax.scene.geometry import Slab
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import Full, Stripes


@pytest.mark.parametrize("direction", [0.0, pytest.param(20.0, marks=pytest.mark.slow)])
def test_the_cell_rolled_to_each_shift_is_the_full_render_away_from_the_walls(direction):
    height, width, k = 36, 16, 4
    slab = Slab(3.0, "refractive", n_mu=4, n_z=2)
    stripes = Stripes(6, 3, direction_deg=direction)
    full = np.asarray(SlabRenderer(Grid(width, height, 8, 1), stripes, k, slab)(0.6, 0.55, 0.6)[0])
    one = dataclasses.replace(stripes, phases=(0,))
    cell = SlabPeriodicCell(Grid(width, 6, 8, 1), one, k, slab, tank_height=height)
    images = np.asarray(cell(0.6, 0.55, 0.6)[0])[0]  # (K, period, W)
    assert images.shape == (k, 6, width)
    tiled = np.moveaxis(images[:, shift_rows(stripes, height)], 0, 1)  # (patterns, K, H, W)
    # 15 rows (9 mean free paths) from either wall; every order and shift.
    middle = slice(15, 21)
    error = np.abs(tiled[..., middle, :] - full[..., middle, :])
    peak = full.max(axis=(0, 2, 3))[None, :, None, None]
    assert float(np.max(error / peak)) < 1e-4
    # The rows next to the walls are not the cell's: the walls' term is missing there.
    assert float(np.max(np.abs(tiled[..., 0, :] - full[..., 0, :]) / peak[..., 0])) > 1e-2


def test_the_cell_refuses_light_through_the_top_wall():
    with pytest.raises(ValueError, match="periodic in y"):
        SlabPeriodicCell(
            Grid(12, 6, 8, 1), Full(270.0, "bottom"), 3, Slab(2.0, n_mu=4, n_z=1), tank_height=24
        )


def _slab_case(**kw):
    height, width, k = 24, 16, 6
    slab = Slab(3.0, "refractive", n=1.33, n_mu=4, n_z=2)
    stripes = Stripes(6, 3, (0, 1, 2, 3, 4, 5))
    grid = Grid(width, height, 8, 1)
    full = SlabRenderer(grid, stripes, k, slab, **kw)
    return grid, stripes, k, slab, full


def _row_error(images, reference):
    """Per row, the worst |Δ| over shifts and columns over the row's largest value."""
    return np.max(np.abs(images - reference), axis=(0, 2)) / np.max(reference, axis=(0, 2))


# ω .95, g .8: the walls' deficit keeps the stripes' phase for many orders.
DEEP = (0.4, 0.38, 0.8)


def test_the_slab_stripe_cell_is_the_full_render_with_walls():
    grid, stripes, k, slab, full = _slab_case()
    reference = np.asarray(full(*DEEP)[0])
    cell = SlabCellRenderer(grid, stripes, k, slab, shift_orders=3, deviation=(8, 4))
    images = np.asarray(cell(*DEEP)[0])
    assert images.shape == reference.shape
    # The first orders are every shift's own: the full render's.
    np.testing.assert_allclose(images[:, :3], reference[:, :3], rtol=1e-5, atol=1e-9)
    # Measured 0.31 % next to the walls (the shifts' mean alone: 4.5 %).
    assert float(_row_error(images.sum(1), reference.sum(1)).max()) < 5e-3


@pytest.mark.slow
def test_the_coarse_deviation_takes_most_of_what_the_mean_leaves_next_to_the_walls():
    grid, stripes, k, slab, full = _slab_case()
    reference = np.asarray(full(*DEEP)[0]).sum(1)
    errors = {}
    for deviation in (None, (8, 4)):
        cell = SlabCellRenderer(grid, stripes, k, slab, shift_orders=3, deviation=deviation)
        errors[deviation] = _row_error(np.asarray(cell(*DEEP)[0]).sum(1), reference).max()
    assert errors[None] > 2e-2 and errors[(8, 4)] < 0.2 * errors[None]


@pytest.mark.slow
@pytest.mark.parametrize("values", [(0.4, 0.3, 0.5), DEEP])
def test_the_slab_stripe_cells_tail_and_g_slope_are_the_full_renders(values):
    grid, stripes, k, slab, full = _slab_case(tail="gmres", tail_tol=1e-6)
    reference = full(*values)
    cell = SlabCellRenderer(
        grid, stripes, k, slab, shift_orders=3, deviation=(8, 4), tail="gmres", tail_tol=1e-6
    )
    images, fields, tail = cell(*values)
    assert fields is None and bool(tail.converged)
    series = np.asarray(images.sum(1) + tail.image)
    exact = np.asarray(reference[0].sum(1) + reference[2].image)
    # The tail carries each shift's deviation too (without it, 0.7 % at ω .95, g .8).
    assert float(_row_error(series, exact).max()) < 5e-3
    # The slope along g is the derivative of the same images.
    marched = SlabCellRenderer(grid, stripes, k, slab, shift_orders=3, deviation=(8, 4))
    _, slope = marched.images_and_g_slope(*values)
    h = 1e-2
    st, ss, g = values
    up, down = (np.asarray(marched(st, ss, g + d)[0]) for d in (h, -h))
    slope = np.asarray(slope)
    scale = np.max(np.abs(slope), axis=(0, 2, 3), keepdims=True)
    np.testing.assert_allclose(slope / scale, (up - down) / (2 * h) / scale, atol=2e-3)


def test_the_slab_stripe_cell_refuses_what_it_cannot_render():
    grid, stripes, _, slab, _ = _slab_case()
    for kw in ({}, {"tail": "gmres"}):  # a tail's orders too would be the cell's
        with pytest.raises(ValueError, match="no order to the cell"):
            SlabCellRenderer(grid, stripes, 3, slab, shift_orders=3, **kw)
    with pytest.raises(ValueError, match="period is not shorter"):
        SlabCellRenderer(Grid(16, 6, 8, 1), stripes, 5, slab)
    for bad in ((8, 2), (0, 4), 8, (8.0, 4), [12, 4]):
        with pytest.raises(ValueError, match="deviation: must be"):
            SlabCellRenderer(grid, stripes, 5, slab, deviation=bad)
    with pytest.raises(ValueError, match="lightfield"):
        SlabCellRenderer(grid, stripes, 5, slab)(0.4, 0.3, 0.5, lightfield=True)
