"""The slab on one stripe period (lightfield_jax.forward.slab_cell) against the full
slab render, in the rows the tank's walls do not reach."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lightfield_jax.forward.slab import SlabRenderer
from lightfield_jax.forward.slab_cell import SlabPeriodicCell, shift_rows
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
