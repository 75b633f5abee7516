"""The cheap models' stripe cell: how the basin scan and the extrapolated cheap solve,
whose answers the defect correction takes to the final model, render plane stripes from
one period (:class:`~lightfield_jax.forward.cell.CellRenderer`)."""

from __future__ import annotations

# The cheap models' stripe cell: the walls' term of the shifts' mean alone (2: no order
# of every shift's own), the fastest (docs/periodic_cell.md).
CHEAP_CELL = 2
# That cell marches its walls' term on a grid this many times coarser than the native
# one where it divides the tank. Measured on the dense forward medium (docs/fit_speed.md,
# "The cheap models' walls' term on a coarser grid"): the scan and cheap solve 2-2.5×
# faster, the warm fit 1.2-1.7× at 48-192 rows, the answers within 1.5e-4.
CHEAP_WALLS_COARSEN = 2


def walls_coarsen(model) -> int:
    """The walls' term's coarsening of ``model``'s stripe cell (:data:`CHEAP_WALLS_COARSEN`
    for the cheap models' cell, else 1)."""
    c = CHEAP_WALLS_COARSEN
    cheap = model.cell == CHEAP_CELL and model.grid.width % c == 0 and model.grid.height % c == 0
    return c if cheap else 1


__all__ = ["CHEAP_CELL", "CHEAP_WALLS_COARSEN", "walls_coarsen"]
