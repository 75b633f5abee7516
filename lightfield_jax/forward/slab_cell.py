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
walls need the walls' term.

:class:`SlabCellRenderer` renders a slab's stripe capture so:

    I_1 … I_S of every shift:  exact, the full render of the first S = ``shift_orders``
        orders on the whole tank (the walls' deficit of the low orders depends on the
        stripes' phase);
    I_k, k > S:  the cell's I_k rolled to each shift's phase and tiled over the rows,
        plus the walls' term of the mean over the period's phases, a·(F_k − F̃_k): F
        the full light of the tank with its walls, F̃ the same light on the periodic
        grid, a = lit/period; plus, with ``deviation``, each shift's own walls' term
        less that mean on a coarse discretisation (which also carries shifts that do
        not tile the period).

The approximation against the full render: after S orders each shift's walls' term is
the mean's and its deviation from it on the coarse discretisation.
The cost is S orders of the full render, full light's march on the tank, the cell's
(P rows, one pattern) and the deviation's (every shift, one layer, fewer nodes), instead
of every shift's march over every row in every layer: about 3× less
(docs/slab_memory.md).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Int

from lightfield_jax.checks import check_int
from lightfield_jax.forward.cell import (
    ComposedRenderer,
    cell_problem,
    folded_index,
    shift_rows,
)
from lightfield_jax.forward.pattern_basis import PatternBasis, shift_basis
from lightfield_jax.forward.slab import SlabRenderer, slab_nodes
from lightfield_jax.forward.tail import joined_tail
from lightfield_jax.scene.geometry import Slab
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import Full, Stripes, along_x, cell_moments, scaled


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


# The orders whose images are every shift's own (the full render's): past them the
# walls act on the shifts' mean and each shift's coarse deviation from it (measured
# against the full render: :func:`deviation_grid`).
SLAB_SHIFT_ORDERS = 3


def deviation_grid(n_theta: int, n_mu: int) -> tuple[int, int]:
    """The coarse discretisation of each shift's deviation from the shifts' mean walls'
    term past the first orders, for a model of ``n_theta`` azimuth bins and ``n_mu``
    elevation nodes: its bins and half its nodes (at least 4), in one depth layer. The
    azimuth bins matter most: against the full render (48×36, ω .99, g .85, 32 bins ×
    16 nodes × 2 layers, 24 orders, three orders exact) the worst row is 0.15 % with
    32 × 8, 0.72 % with 16 × 16 or 16 × 8, 2.0 % with 8 × 4 and 5.4 % with none
    (docs/slab_memory.md)."""
    return n_theta, max(4, n_mu // 2)


def check_deviation(deviation, n_theta: int, slab: Slab) -> tuple[int, int]:
    """``deviation`` as (azimuth bins, elevation nodes), never finer than the model's
    own (``n_theta``, ``slab.n_mu``); a one-line ValueError naming it otherwise."""
    ok = isinstance(deviation, (tuple, list)) and len(deviation) == 2
    ok = ok and all(isinstance(v, int) and not isinstance(v, bool) for v in deviation)
    least_mu = 4 if slab.boundary == "refractive" else 1
    if not ok or deviation[0] < 8 or deviation[0] % 8 or deviation[1] < least_mu:
        raise ValueError(
            f"deviation: must be (azimuth bins, a multiple of 8; elevation nodes, at least "
            f"{least_mu}), got {deviation!r}"
        )
    return min(deviation[0], n_theta), min(deviation[1], slab.n_mu)


class SlabWalls(eqx.Module):
    """A light's walls' term on the slab: its render on the tank less its render on the
    periodic grid (``rows`` rows, periodic in y; its rows repeat down the tank), per
    pattern and order (native grid, unit gain)."""

    tank: SlabRenderer
    free: SlabPeriodicCell

    def __init__(self, grid: Grid, light, rows: int, bounces: int, slab: Slab, phase, solve):
        self.tank = SlabRenderer(grid, light, bounces, slab, phase, **solve)
        free_grid = dataclasses.replace(grid, height=rows)
        self.free = SlabPeriodicCell(
            free_grid, light, bounces, slab, phase, tank_height=grid.height, **solve
        )

    def __call__(self, sigma_t, sigma_s, g):
        """(the term (patterns, K, H, W), the tail's term (patterns, H, W) or ``None``,
        the two tail solutions or ``None``, the tank's own images (patterns, K, H, W))."""
        tank = self.tank.unchecked(sigma_t, sigma_s, g)
        free = self.free.unchecked(sigma_t, sigma_s, g)
        rows = np.arange(self.tank.height // self.tank.refine) % free[0].shape[-2]
        term = tank[0] - free[0][..., rows, :]
        if len(tank) == 2:
            return term, None, None, tank[0]
        tail = tank[2].image - free[2].image[..., rows, :]
        return term, tail, (tank[2], free[2]), tank[0]


class SlabCellRenderer(ComposedRenderer):
    """A slab's stripes rendered from one period (the module's scheme): the call
    signature and outputs of :class:`~lightfield_jax.forward.base.AbstractRenderer`,
    images only (light fields: the full render). ``shift_orders`` S ≥ 2: the orders
    rendered exactly for every shift; ``bounces`` must exceed it (a tail's orders are
    the cell's). ``deviation`` (azimuth bins, elevation nodes), or ``None``: each shift's
    walls' term less the shifts' mean, for the orders past S, rendered on that coarser
    discretisation in one depth layer and added to the mean's; near albedo 1 the walls'
    deficit keeps the stripes' phase for many orders."""

    first: SlabRenderer
    cell: SlabPeriodicCell
    mean_walls: SlabWalls
    # Each shift's walls' term and the mean's on the coarse discretisation, or None.
    deviation: tuple[SlabWalls, SlabWalls] | None
    rows: Int[Array, "patterns H"]
    shift_orders: int = eqx.field(static=True)
    weight: float = eqx.field(static=True)
    # Every shift from fewer of them and full light, where that is exact
    # (:mod:`lightfield_jax.forward.pattern_basis`): the first orders and the deviation
    # render those; ``None``: every shift.
    basis: PatternBasis | None = eqx.field(static=True)

    def __init__(
        self,
        grid: Grid,
        illumination: Stripes,
        bounces: int,
        slab: Slab,
        phase: str = "normalized",
        *,
        tail: str | None = None,
        tail_tol: float = 1e-4,
        tail_max_steps: int = 500,
        shift_orders: int = SLAB_SHIFT_ORDERS,
        deviation: tuple[int, int] | None = None,
    ):
        problem = cell_problem(grid, illumination)
        if problem is not None:
            raise ValueError(f"SlabCellRenderer: {problem}")
        if deviation is not None:
            n_theta, n_mu = check_deviation(deviation, grid.n_theta, slab)
        self._setup(grid, illumination, bounces, phase, tail, tail_tol, tail_max_steps)
        s = self.shift_orders = check_int(shift_orders, "shift_orders", low=2)
        # I_1..I_S are every shift's own, every later order (a tail's too) the cell's.
        if s >= self.bounces:
            raise ValueError(
                f"SlabCellRenderer: shift_orders {s} leaves no order to the cell "
                f"({self.bounces} bounces): render the whole tank"
            )
        solve = {"tail": tail, "tail_tol": tail_tol, "tail_max_steps": tail_max_steps}
        period, k = illumination.period, self.bounces
        full = Full(illumination.direction_deg, illumination.entry)
        self.basis = shift_basis(grid, illumination, full)
        # Every shift, or the kept ones.
        shifts = illumination if self.basis is None else self.basis.kept_shifts(illumination)
        self.first = SlabRenderer(grid, shifts, s, slab, phase)
        one = dataclasses.replace(illumination, phases=(0,))
        self.cell = SlabPeriodicCell(
            dataclasses.replace(grid, height=period),
            one,
            k,
            slab,
            phase,
            tank_height=grid.height,
            **solve,
        )
        # Full light is uniform in y: two rows of the periodic grid hold it.
        self.mean_walls = SlabWalls(grid, full, 2, k, slab, phase, solve)
        self.weight = illumination.lit / period
        self.deviation = None
        if deviation is not None:
            coarse = dataclasses.replace(slab, n_mu=n_mu, n_z=1, depth_profile=None)
            cg = dataclasses.replace(grid, n_theta=n_theta)
            self.deviation = (
                SlabWalls(cg, shifts, period, k, coarse, phase, solve),
                SlabWalls(cg, full, 2, k, coarse, phase, solve),
            )
        self.rows = jnp.asarray(shift_rows(illumination, grid.height), jnp.int32)

    @property
    def image_scale(self) -> float:
        return 1.0

    def compose(self, sigma_t, sigma_s, g, gain):
        s, a = self.shift_orders, self.weight
        first = self.first.unchecked(sigma_t, sigma_s, g)[0]  # (patterns, S, H, W)
        cell = self.cell.unchecked(sigma_t, sigma_s, g)
        walls, walls_tail, walls_solves, full = self.mean_walls(sigma_t, sigma_s, g)
        if self.basis is not None:  # the kept shifts and full light → every shift
            first = self.basis.combine(first, full[0, :s])
        later = jnp.moveaxis(cell[0][0][:, self.rows], 0, 1)  # (patterns, K, H, W)
        later = later[:, s:] + a * walls[:, s:]
        tail_image = None if self.tail is None else cell[2].image[0][self.rows] + a * walls_tail
        solves = [] if self.tail is None else [cell[2], *walls_solves]
        if self.deviation is not None:
            (own, own_tail, own_solves, _), (mean, mean_tail, mean_solves, _) = (
                part(sigma_t, sigma_s, g) for part in self.deviation
            )
            if self.basis is not None:
                own = self.basis.combine(own, mean[0])
                own_tail = None if own_tail is None else self.basis.combine(own_tail, mean_tail[0])
            later = later + (own - a * mean)[:, s:]
            if self.tail is not None:
                tail_image = tail_image + own_tail - a * mean_tail
                solves += [*own_solves, *mean_solves]
        images = gain * jnp.concatenate([first, later], axis=1)[:, : self.bounces]
        if self.tail is None:
            return images, None
        return images, joined_tail(gain * tail_image, solves)


# A cached SlabCellRenderer (its tables built once per static configuration), as
# renderer_for is for the full render.
slab_cell_renderer_for = functools.lru_cache(maxsize=16)(SlabCellRenderer)


__all__ = [
    "SLAB_SHIFT_ORDERS",
    "SlabCellRenderer",
    "SlabPeriodicCell",
    "SlabWalls",
    "check_deviation",
    "deviation_grid",
    "shift_rows",
    "slab_cell_renderer_for",
]
