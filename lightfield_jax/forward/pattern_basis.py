"""Stripe shifts as combinations of fewer patterns and full light.

Everything a render does after the unscattered light is linear in that light, and the
unscattered light of a pattern is its lit fraction of a pixel times a factor of depth
alone where every pattern's lit part of a pixel lies at full light's depth (light along
the entry wall's normal). Where the shifts' lit fractions are then combinations of a
few of them and of full light, so is every image of every shift. Six shifts of a
period-6 pattern with 3 rows lit are three of them and full light (a shift and the one
half a period on add up to full light): the stripe cells' every-shift parts (the plane's
walls' term and wall bands, :mod:`lightfield_jax.forward.cell`; the slab's first orders
and deviation, :mod:`lightfield_jax.forward.slab_cell`) render those instead of all six.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from lightfield_jax.forward.tail import mapped_output
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import (
    Full,
    Stripes,
    cell_moments,
    scaled,
    source_moments,
)

# Relative tolerance of the exactness checks (float64 moments: a combination is exact,
# or off by a pixel's lit fraction).
_TOL = 1e-9


@dataclasses.dataclass(frozen=True)
class PatternBasis:
    """Every pattern as a combination of the ``kept`` ones and full light: pattern p =
    Σ_j coef[p, j]·pattern kept[j] + coef[p, −1]·full light."""

    kept: tuple[int, ...]
    # (patterns, len(kept) + 1), as nested tuples: hashable, for a renderer's static field.
    coef: tuple[tuple[float, ...], ...]

    def __post_init__(self):
        object.__setattr__(self, "coef", tuple(tuple(float(v) for v in row) for row in self.coef))

    def kept_shifts(self, stripes: Stripes) -> Stripes:
        """``stripes`` with the kept shifts only."""
        return dataclasses.replace(stripes, phases=tuple(stripes.phases[i] for i in self.kept))

    def combine(self, kept, full):
        """Every pattern's array (patterns, ...) from the kept patterns' (kept, ...) and
        full light's (broadcastable to one kept pattern's): the same combination of any
        linear function of the patterns' light."""
        c = jnp.asarray(np.array(self.coef), kept.dtype)
        full = jnp.broadcast_to(full, kept.shape[1:])
        return jnp.tensordot(c, jnp.concatenate([kept, full[None]], axis=0), axes=1)

    def expand(self, a, axis: int = 0, light: bool = False):
        """An array over the kept patterns then full light (along ``axis``) as one over
        every pattern; ``light``: of light (images, light fields), which is never
        negative: the combination's rounding below 0 is clipped (a shift half a period
        on is full light less a kept shift, and the slab clips its own rounding in the
        march, which is then not exactly linear: −1e-10 of the peak, not 0)."""
        a = jnp.moveaxis(a, axis, 0)
        every = jnp.moveaxis(self.combine(a[:-1], a[-1]), 0, axis)
        return jnp.maximum(every, 0.0) if light else every

    def holds(self, moments, full_moments) -> bool:
        """Whether the combination is exact for these source moments (each (patterns,
        H, W)) and full light's ((1, H, W))."""
        moments, full_moments = tuple(moments), tuple(full_moments)
        if not _same_depth(moments, full_moments):
            return False
        cov = np.asarray(moments[0], np.float64)
        basis = np.concatenate([cov[list(self.kept)], np.asarray(full_moments[0])], axis=0)
        return _exact(np.array(self.coef), basis, cov)


def _same_depth(moments, full_moments) -> bool:
    """Every pattern's lit part of a pixel at full light's depth (mean and variance):
    the unscattered light is then linear in the lit fraction."""
    cov, mean, var = (np.asarray(a, np.float64) for a in moments)
    fcov, fmean, fvar = (np.asarray(a, np.float64) for a in full_moments)
    lit = cov > 0
    if np.any(lit & ~(fcov > 0)):
        return False
    scale = max(1.0, float(np.abs(fmean).max()))
    same_mean = np.abs(np.where(lit, mean - fmean, 0.0)).max() <= _TOL * scale
    same_var = np.abs(np.where(lit, var - fvar, 0.0)).max() <= _TOL * scale * scale
    return bool(same_mean and same_var)


def _exact(coef, basis, cov) -> bool:
    n = len(cov)
    residual = coef @ basis.reshape(len(basis), -1) - cov.reshape(n, -1)
    return float(np.abs(residual).max()) <= _TOL * max(1.0, float(np.abs(cov).max()))


def pattern_basis(moments, full_moments) -> PatternBasis | None:
    """The fewest patterns (earlier ones first) that with full light combine to every
    pattern of ``moments`` (coverage, mean, var, each (patterns, H, W); full light's
    each (1, H, W)), exactly; ``None`` where that saves no pattern or is not exact
    (oblique light, whose lit part of a pixel lies at each pattern's own depth)."""
    moments, full_moments = tuple(moments), tuple(full_moments)
    if not _same_depth(moments, full_moments):
        return None
    cov = np.asarray(moments[0], np.float64)
    n = len(cov)
    rows = cov.reshape(n, -1)
    full = np.asarray(full_moments[0], np.float64).reshape(1, -1)
    tol = _TOL * max(1.0, float(np.abs(rows).max())) * rows.shape[1]
    kept: list[int] = []
    for p in range(n):
        if np.linalg.matrix_rank(np.concatenate([rows[kept + [p]], full]), tol=tol) > len(kept) + 1:
            kept.append(p)
    if len(kept) + 1 >= n:
        return None
    basis = np.concatenate([rows[kept], full])
    coef = np.linalg.lstsq(basis.T, rows.T, rcond=None)[0].T  # (patterns, kept + 1)
    coef = np.where(np.abs(coef) < _TOL, 0.0, np.round(coef, 12))
    return PatternBasis(tuple(kept), coef) if _exact(coef, basis, cov) else None


def marched_patterns(stripes: Stripes, moments, refine: int):
    """``(basis, moments)``: the kept shifts' then full light's source moments where
    every shift of ``stripes`` is their combination on this working grid (``moments``
    the shifts', each (patterns, H, W), on a grid ``refine`` times finer than the
    native one), else ``(None, moments)``. A full render marches those."""
    full = Full(stripes.direction_deg, stripes.entry)
    height, width = np.shape(moments[0])[1:]
    full = tuple(source_moments(scaled(full, refine), width, height))
    basis = pattern_basis(moments, full)
    if basis is None:
        return None, moments
    kept = list(basis.kept)
    return basis, tuple(
        np.concatenate([np.asarray(a)[kept], b], axis=0) for a, b in zip(moments, full, strict=True)
    )


def every_pattern_output(basis: PatternBasis | None, out):
    """A march's ``(images, light fields[, tail])`` over the marched patterns (images
    and the tail's arrays patterns first, light fields patterns second) as over every
    pattern; ``basis`` ``None``: ``out`` as it is."""
    if basis is None:
        return out

    def light(axis):
        return lambda a: basis.expand(a, axis, light=True)

    return mapped_output(out, light(0), light(1), light(0))


def working_moments(light, grid: Grid):
    """``light``'s source moments on ``grid``'s working (refined) grid, as a renderer
    of that grid builds them."""
    f = grid.refine or 1
    return source_moments(scaled(light, f), grid.width * f, grid.height * f)


def shift_basis(grid: Grid, stripes: Stripes, full: Full) -> PatternBasis | None:
    """The shifts of ``stripes`` on ``grid`` as fewer of them and full light, exact on
    the native tank, on its refined working grid and on a grid periodic in y (the
    stripe cells' walls' terms), or ``None``."""
    basis = pattern_basis(
        source_moments(stripes, grid.width, grid.height),
        source_moments(full, grid.width, grid.height),
    )
    if basis is None:
        return None
    rows = 2 * stripes.period
    checks = (
        [cell_moments(light, grid.width, rows) for light in (stripes, full)],
        [working_moments(light, grid) for light in (stripes, full)],
    )
    return basis if all(basis.holds(*pair) for pair in checks) else None


__all__ = [
    "PatternBasis",
    "every_pattern_output",
    "marched_patterns",
    "pattern_basis",
    "shift_basis",
    "working_moments",
]
