"""The wall bands of the stripe cell (:class:`~lightfield_jax.forward.cell.CellRenderer`):
the refined grid's detail of the walls' term in the rows next to each wall, from a short
tank rendered for every shift."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from lightfield_jax.forward.pattern_basis import PatternBasis, working_moments
from lightfield_jax.forward.plane import PlaneRenderer
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import Full, Stripes


def _joined(kept: Stripes, full: Full, grid: Grid):
    """The source moments of the kept shifts then full light, on ``grid``'s working
    grid."""
    return tuple(
        np.concatenate(pair, axis=0)
        for pair in zip(working_moments(kept, grid), working_moments(full, grid), strict=True)
    )


def short_tank_height(height: int, period: int, band: int) -> int:
    """The short tank's rows: at least ``2·band + period`` (its two walls' bands apart
    by a period) and congruent to the tank's ``height`` modulo the period, so that its
    top wall meets the stripes in the tank's phase."""
    low = 2 * band + period
    return low + (height - low) % period


class WallBands(eqx.Module):
    """The refined grid's correction of the walls' term in the ``band`` rows next to
    each wall, for orders 3 to ``orders``: on a short tank (:func:`short_tank_height`
    rows, every shift), its walls' term on the model's grid less its walls' term on the
    native grid. The walls' term marched on the native grid misses the refined grid's
    detail next to the walls (I_3 2–4 % off there on refined models); that miss is made
    within a few rows of the wall, where the short tank's walls are the tank's."""

    fine: PlaneRenderer
    native: PlaneRenderer
    band: int = eqx.field(static=True)
    rows: int = eqx.field(static=True)
    # Every shift from fewer of them and full light (the renderers' last pattern), or
    # ``None``: every shift rendered.
    basis: PatternBasis | None = eqx.field(static=True)

    def __init__(
        self,
        grid: Grid,
        stripes: Stripes,
        orders: int,
        phase: str,
        band: int,
        basis: PatternBasis | None = None,
    ):
        self.band = band
        self.rows = short_tank_height(grid.height, stripes.period, band)
        short = Grid(grid.width, self.rows, grid.n_theta, grid.refine)
        native = dataclasses.replace(short, refine=1)
        full = Full(stripes.direction_deg, stripes.entry)
        if basis is not None and not all(  # the kept shifts and full light, exact here
            basis.holds(*(working_moments(light, on) for light in (stripes, full)))
            for on in (short, native)
        ):
            basis = None
        self.basis = basis
        fine_moments = native_moments = None  # None: every shift's
        if basis is not None:
            kept = basis.kept_shifts(stripes)
            fine_moments, native_moments = (_joined(kept, full, on) for on in (short, native))
        self.fine = PlaneRenderer(short, stripes, orders, phase, moments=fine_moments)
        self.native = PlaneRenderer(native, stripes, orders, phase, moments=native_moments)

    def __call__(self, sigma_t, sigma_s, g, cell, free, rows):
        """(patterns, orders − 2, 2·band, W): the correction of orders 3.. in the bottom
        ``band`` rows then the top ``band`` rows; ``cell`` the refined cell's images
        (native grid, (K, period, W)), ``rows`` each shift's cell row of the short tank's
        rows, ``free`` every shift's periodic grid on the native grid (the shifts' walls'
        term's, (patterns, K, period, W))."""
        k, b, n = self.fine.bounces, self.band, self.rows
        detail = self.fine.unchecked(sigma_t, sigma_s, g)[0]
        detail = detail - self.native.unchecked(sigma_t, sigma_s, g)[0]
        if self.basis is not None:  # (kept shifts, full light) → every shift
            detail = self.basis.combine(detail[:-1], detail[-1])
        refined = jnp.moveaxis(cell[:k][:, rows], 0, 1)
        unrefined = free[:, :k][:, :, np.arange(n) % free.shape[2]]
        e = detail - (refined - unrefined)
        return jnp.concatenate([e[:, 2:, :b], e[:, 2:, n - b :]], axis=2)


__all__ = ["WallBands", "short_tank_height"]
