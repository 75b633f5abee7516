"""The slab on one stripe period: a grid periodic in y (docs/slab_memory.md).

A homogeneous slab lit through a side wall by stripes of period P repeats every P rows
away from the tank's top and bottom walls, as the plane does
(:mod:`lightfield_jax.forward.cell`). :class:`SlabPeriodicCell` is the slab model
(:class:`~lightfield_jax.forward.slab.SlabRenderer`: its layers, faces, kernels and
bounce step) on one period, periodic in y: the kernels' y offsets folded modulo the
cell (the periodic images of a source P rows apart add up) and the FFT domain
(P, 2W), zero-padded in x only. Its images of one phase, rolled to each shift's phase
and tiled over the rows, are the full tank's in the rows the walls do not reach
(tested against the full render: ``tests/test_slab_cell.py``); the rows next to the
walls need the walls' term, which this module does not give.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from lightfield_jax.forward.cell import cell_moments, folded_index
from lightfield_jax.forward.slab import SlabRenderer, slab_nodes
from lightfield_jax.scene.geometry import Slab
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import Full, Stripes, along_x, scaled


class SlabPeriodicCell(SlabRenderer):
    """The slab on a grid periodic in y, for one period of stripes or full light.

    ``grid`` is the cell (its height the period, in native rows), ``illumination`` one
    phase of stripes or :class:`~lightfield_jax.scene.illumination.Full` entering the
    left or right wall; ``tank_height`` (native rows) bounds how far a ray travels in y,
    as in the tank (the kernels' offsets). Called as
    :class:`~lightfield_jax.forward.slab.SlabRenderer` is; its images are the cell's
    rows.
    """

    def __init__(
        self,
        grid: Grid,
        illumination: Stripes | Full,
        bounces: int,
        slab: Slab,
        phase: str = "normalized",
        *,
        tank_height: int,
        tail: str | None = None,
        tail_tol: float = 1e-4,
        tail_max_steps: int = 500,
    ):
        if not along_x(illumination.entry):
            raise ValueError(
                "SlabPeriodicCell: the cell is periodic in y: light enters a side wall"
            )
        f = 1 if grid.refine is None else grid.refine
        rows, width = grid.height * f, grid.width * f
        super().__init__(
            grid,
            illumination,
            bounces,
            slab,
            phase,
            tail=tail,
            tail_tol=tail_tol,
            tail_max_steps=tail_max_steps,
            moments=cell_moments(scaled(illumination, f), width, rows),
        )
        tank = max(int(tank_height), grid.height) * f
        nodes = slab_nodes(width, tank, grid.n_theta)
        self.r_sub = jnp.asarray(nodes["r_sub"])
        self.w_sub = jnp.asarray(nodes["w_sub"])
        theta0 = math.radians(illumination.direction_deg)
        self.cos_phi = jnp.asarray(np.cos(nodes["phi"] - theta0))
        self.index = jnp.asarray(folded_index(nodes["index"], tank, width, rows))
        self.splat = jnp.asarray(nodes["splat"])
        self.fft_rows = rows  # periodic in y: no padding


def shift_rows(illumination: Stripes, height: int) -> np.ndarray:
    """(patterns, H): the cell's row of each shift's row (a shift by phase φ is the
    cell rolled by φ rows)."""
    phases = np.asarray(illumination.phases)[:, None]
    return np.mod(np.arange(height)[None] + phases, illumination.period)


__all__ = ["SlabPeriodicCell", "shift_rows"]
