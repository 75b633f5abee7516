"""The slab's in-plane grid for a strongly forward lobe (|g| ≥ :data:`NEAR_WALL_G`).

At g 0.9 the slab model spreads the light of a narrow beam sideways too much: against
the 3-D slab Monte Carlo (a 1-px beam at the entry wall, ω 0.99, refractive faces,
σt·h 1.3) the off-beam rows next to the entry wall are +10.8 % off at order 3 with 32
azimuth bins on the native grid, in every column, not only the first (the beam's
lateral spread, not the wall). The error is the in-plane discretisation, space and
azimuth together (docs/slab_depth.md §7): refine 2 leaves +3.9 %, refine 3 +2.5 %, 64
bins at refine 3 +1.0 %, and the beam's own rows there need 48 elevation nodes (−2.9 %
with 24 at k 6, −1.8 % with 48). So where the medium needs it the slab gets a finer
grid, from a ladder of (azimuth bins, elevation nodes, refinement), finest first, each
rung within :data:`SLAB_REFINE_CELLS`; where none fits, the unrefined defaults.

The choice is data-only (numpy-free): :func:`~lightfield_jax.scene.geometry.resolve_slab_grid`
(renders) and the fit's :class:`~lightfield_jax.inverse.geometry_model.SlabModel` ask it.
"""

from __future__ import annotations

from lightfield_jax.runtime.memory import current_limit

# |g| from which the slab's in-plane grid is refined.
NEAR_WALL_G = 0.9
# Taken off the threshold in the test: a medium's g in float32 (JAX's default) is
# rounded, 0.9 to 0.89999998, and is the medium the rule was measured for.
FLOAT32_ROUNDING = 1e-6

# (azimuth bins, elevation nodes, spatial refinement), finest first. Measured at g 0.9,
# ω 0.99 (a 1-px beam at the entry wall, 24×17, orders 2–6, against 4e7 Monte Carlo
# photons; docs/slab_depth.md §7), the largest error in the off-beam / beam rows next to
# the wall: +1.6 / −1.8 % for the first rung, +1.0 / −2.9 % for the second, +2.5 /
# −3.4 % for the third, +3.9 / −3.6 % for the last; 32 × 24 unrefined (the fallback)
# +10.8 / −5.6 %.
NEAR_WALL_GRIDS = ((64, 48, 3), (64, 24, 3), (64, 24, 2), (32, 24, 2))

# The most light-field values (W·H·refine²·n_theta·n_mu·n_z·profile coefficients) a
# render may get from the automatic refinement: the kernels' spectra are about 72 bytes
# per value in float32 with 2 linear layers (18 kernels of 2H × (W + 1) complex per
# 4 values of a pixel and direction), so about 3.2 GiB here (twice in float64), the
# blocked working set (forward.slab_memory, at most 0.75 GiB) on top. The 24×17 beam of
# the measurement at the first rung has 45.1 million; its render is estimated at
# 4.3 GiB (slab_render_bytes, one pattern, float32).
SLAB_REFINE_CELLS = 48_000_000
# A render's bytes per light-field value on those grids, everything counted (float32):
# the 24×17 beam's 45.1 million values at the first rung are estimated at 4.3 GiB.
RENDER_BYTES_PER_VALUE = 104


def render_cap() -> int:
    """The light-field values a render may get from the automatic refinement: within
    :data:`SLAB_REFINE_CELLS` and within the memory a render may take
    (:func:`~lightfield_jax.runtime.memory.current_limit`: ``--max-memory``,
    ``$LIGHTFIELD_JAX_MAX_MEMORY`` or the machine's free memory), so that a lower rung
    is taken where the finest would be refused."""
    limit, _ = current_limit()
    return min(SLAB_REFINE_CELLS, limit // RENDER_BYTES_PER_VALUE)


# Albedo below which the orders the finer grid corrects (k ≥ 3) carry little light
# (as the depth layers' DIM_ALBEDO).
NEAR_WALL_ALBEDO = 0.3


def needs_near_wall_grid(g: float, albedo: float | None = None) -> bool:
    """Whether a medium of asymmetry ``g`` and albedo ``albedo`` (``None``: unknown, the
    worst case) gets the finer in-plane grid: |g| ≥ :data:`NEAR_WALL_G`, unless dim."""
    bright = albedo is None or float(albedo) >= NEAR_WALL_ALBEDO
    return abs(float(g)) >= NEAR_WALL_G - FLOAT32_ROUNDING and bright


def near_wall_grid(
    width: int,
    height: int,
    depth_values: int,
    n_theta: int | None = None,
    n_mu: int | None = None,
    refine: int | None = None,
    cap: int = SLAB_REFINE_CELLS,
) -> tuple[int | None, int | None, int | None]:
    """``(n_theta, n_mu, refine)``: the finest rung of :data:`NEAR_WALL_GRIDS`, with
    what is given kept (``None``: open), whose light field of ``width`` × ``height`` px
    × ``depth_values`` (layers × profile coefficients) per pixel and direction stays
    within ``cap``; where none does, what was given (``None`` left open: the caller's
    unrefined defaults)."""
    given = (n_theta, n_mu, refine)
    if None not in given:
        return given
    for rung in NEAR_WALL_GRIDS:
        bins, nodes, r = (v if g is None else g for v, g in zip(rung, given, strict=True))
        if width * height * r * r * bins * nodes * depth_values <= cap:
            return bins, nodes, r
    return given


__all__ = [
    "NEAR_WALL_G",
    "NEAR_WALL_GRIDS",
    "SLAB_REFINE_CELLS",
    "near_wall_grid",
    "needs_near_wall_grid",
    "render_cap",
]
