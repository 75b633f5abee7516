"""The slab model under the cell cap: which of its angles and its refinement the cap
lowers first (:meth:`~lightfield_jax.inverse.geometry_model.SlabModel.capped`)."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

from lightfield_jax.scene.geometry import Slab, as_geometry, default_n_mu, default_slab_n_theta

if TYPE_CHECKING:
    from lightfield_jax.inverse.settings import FitSettings

# The fewest elevation nodes the cell cap leaves a slab (the cheap model's count; a
# refractive face needs 2 on each side of the critical angle).
MIN_CAPPED_MU = 4
# The elevation nodes the cap lowers a near-wall model's to first: the default's at
# g ≥ 0.85 (scene.geometry.default_n_mu).
NEAR_WALL_MU_FLOOR = 24
# The elevation nodes the error term's finer model doubles first where a model has fewer
# (and the rule asks for more): 16 nodes are within 0.1 % of 24 far from the entry wall
# at g 0.8, 8 nodes 2.9 % short (docs/slab_depth.md section 8).
ACCURATE_MU = 16


def slab_cells(width: int, height: int, n_theta: int, refine: int, slab: Slab) -> int:
    """The slab's light-field values over the 2H × 2W FFT domain: azimuth × elevation ×
    depth (layers × profile coefficients) × refined pixels."""
    cells = width * height * 4 * n_theta * slab.n_mu * slab.n_z * refine**2
    return cells * slab.depth_coefficients


def fixed_n_mu(options: FitSettings) -> int | None:
    """The elevation nodes the fit's own slab geometry fixes, or ``None``."""
    user = as_geometry(options.model.geometry).slab_or_none
    return None if user is None else user.n_mu


def capped_sizes(
    width: int,
    height: int,
    n_theta: int,
    refine: int,
    slab: Slab,
    near_wall: bool,
    options: FitSettings,
) -> tuple[int, int, int]:
    """``(n_theta, refine, n_mu)`` lowered until the slab is within four times
    ``max_cells`` (a plane's cell count), or as far as the floors go. What each step
    costs in accuracy decides the order (docs/slab_depth.md section 8: full light on a
    48×36 refractive slab at g 0.8, the far half's light against 64 azimuth bins × 16
    nodes: 32 × 24 −0.7 %, 32 × 16 −0.8 %, 16 × 16 −3.4 %, 32 × 8 −2.9 %, 16 × 8 −5.4 %,
    32 × 4 −9.9 %): the near-wall grid's refinement (refine² of every field) and its
    nodes (``near_wall``) first, then bins down to 16, nodes down to 8, bins to 8 and
    nodes to 4. The nodes the rule asked for (16 to |g| 0.85, 24 beyond:
    :func:`~lightfield_jax.scene.geometry.default_n_mu`) stay until the bins are down
    to 16: the table is of g 0.8, and does not say that fewer than 24 suffice beyond.
    A count the options fix is never lowered."""
    model = options.model
    fixed = {"refine": model.refine, "n_theta": model.n_theta, "n_mu": fixed_n_mu(options)}
    sizes = {"refine": refine, "n_theta": n_theta, "n_mu": slab.n_mu}
    floors = [("refine", 1)] + ([("n_mu", NEAR_WALL_MU_FLOOR)] if near_wall else [])
    floors += [("n_theta", 16), ("n_mu", 8), ("n_theta", 8), ("n_mu", MIN_CAPPED_MU)]

    def over() -> bool:
        at = dataclasses.replace(slab, n_mu=sizes["n_mu"])
        cells = slab_cells(width, height, sizes["n_theta"], sizes["refine"], at)
        return cells > 4 * model.max_cells

    while over():
        step = next(((k, f) for k, f in floors if fixed[k] is None and sizes[k] > f), None)
        if step is None:
            break
        name, floor = step
        sizes[name] = sizes[name] - 1 if name == "refine" else max(floor, sizes[name] // 2)
    return sizes["n_theta"], sizes["refine"], sizes["n_mu"]


# The sizing rules' margin on |g| for a slab (less sensitive to g than the plane).
SLAB_G_MARGIN = 0.05


def slab_rule_inputs(g: float, albedo: float | None) -> tuple[float, float | None]:
    """The (g, albedo) a slab's sizing rules read for an estimate's: |g| with
    :data:`SLAB_G_MARGIN` (at most 0.99) and the albedo within [0, 1] (``None`` kept:
    unknown)."""
    a = None if albedo is None else min(max(float(albedo), 0.0), 1.0)
    return min(0.99, abs(float(g)) + SLAB_G_MARGIN), a


def finer_order(n_theta: int, slab: Slab, g: float, albedo: float | None = None) -> list[str]:
    """The order in which the error term's finer model doubles a slab model's sizes
    (:meth:`~lightfield_jax.inverse.geometry_model.SlabModel.finer`): depth layers,
    elevation nodes, azimuth bins; but first the azimuth bins where they are fewer than
    :func:`~lightfield_jax.scene.geometry.default_slab_n_theta` asks for at ``g``, and
    the elevation nodes where they are fewer than 16 and than
    :func:`~lightfield_jax.scene.geometry.default_n_mu` asks for: what the cap lowered,
    then the model's largest errors (docs/slab_depth.md section 8). The rule's own 4
    nodes at |g| ≤ 0.5 (measured enough there, docs/slab_design.md section 6) leave
    the layers first. The rules read ``g`` and ``albedo`` as the sizing does
    (:func:`slab_rule_inputs`)."""
    g, albedo = slab_rule_inputs(g, albedo)
    rule_mu = min(ACCURATE_MU, default_n_mu(g, slab.thickness, slab.boundary, albedo))
    below = {
        "n_theta": n_theta < default_slab_n_theta(g, slab.boundary, albedo),
        "n_mu": slab.n_mu < rule_mu,
    }
    first = [name for name, low in below.items() if low]
    return first + [name for name in ("n_z", "n_mu", "n_theta") if name not in first]


__all__ = [
    "ACCURATE_MU",
    "MIN_CAPPED_MU",
    "NEAR_WALL_MU_FLOOR",
    "capped_sizes",
    "fixed_n_mu",
    "SLAB_G_MARGIN",
    "finer_order",
    "slab_rule_inputs",
    "slab_cells",
]
