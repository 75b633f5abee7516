"""What a fit's model does per geometry (:class:`GeometryModel`): the plane
(:class:`PlaneModel`) and the slab (:class:`SlabModel`) as peers, each owning its
sizing from an estimate and under the cell cap, its cheap model, its finer models, its
discretisation and its renderer (the plane's stripes from one period, the periodic
cell, where the model allows it). :func:`geometry_model` is the one place a scene
geometry picks its strategy.

``options`` is a fit's :class:`~lightfield_jax.inverse.settings.FitSettings` (a
:class:`~lightfield_jax.FitOptions`), read for its model settings.
"""

from __future__ import annotations

import abc
import dataclasses

from lightfield_jax.forward.cell import SHIFT_ORDERS, cell_problem, cell_renderer_for
from lightfield_jax.forward.plane import coarse_plane_grid
from lightfield_jax.forward.render import renderer_for
from lightfield_jax.forward.slab import slab_bounce_ratio
from lightfield_jax.forward.slab_cell import (
    SLAB_SHIFT_ORDERS,
    deviation_grid,
    slab_cell_renderer_for,
)
from lightfield_jax.inverse.cheap_cell import walls_coarsen
from lightfield_jax.inverse.settings import FitSettings
from lightfield_jax.inverse.slab_caps import (
    MIN_CAPPED_MU,
    capped_sizes,
    finer_order,
    fixed_n_mu,
    slab_cells,
    slab_rule_inputs,
)
from lightfield_jax.scene.geometry import Plane, Slab, as_geometry, default_slab_n_theta
from lightfield_jax.scene.grid import REFINE_LIMIT, Grid, default_n_theta, default_refine
from lightfield_jax.scene.slab_grid import NEAR_WALL_G, near_wall_grid, needs_near_wall_grid

# The slab's cheap model for a second try (:meth:`GeometryModel.finer_cheap`): azimuth
# bins and elevation nodes.
RETRY_SLAB = (16, 8)
# No cap on the near-wall grid when a fit sizes its model: the cell cap comes after
# (:meth:`SlabModel.capped` lowers the refinement first).
NEAR_WALL_UNCAPPED = 1 << 62
# The fewest bounces a slab model renders with its stripe cell (4 × its shift orders).
SLAB_CELL_BOUNCES = 4 * SLAB_SHIFT_ORDERS


def plane_cells(grid: Grid) -> int:
    """The plane's light-field cells: pixels × θ bins × refine²."""
    return grid.width * grid.height * grid.n_theta * grid.refine**2


class GeometryModel(abc.ABC):
    """A fit model's geometry: the plane or the slab, and what the fit does with it."""

    @property
    @abc.abstractmethod
    def scene(self) -> Plane | Slab:
        """The geometry the renderers take (a slab resolved: ``n_mu``, ``n_z`` set)."""

    @abc.abstractmethod
    def sized(
        self, options: FitSettings, g: float, albedo: float, sigma_t: float | None
    ) -> tuple[int, int, GeometryModel]:
        """θ bins, refinement and this geometry resolved for an estimate (g, albedo,
        σt), before the cell cap."""

    def capped(self, width: int, height: int, n_theta: int, refine: int, options: FitSettings):
        """``(n_theta, refine, geometry)`` within ``max_cells`` where the plane's cap
        (θ bins and refinement) left it above (the slab's fields are larger)."""
        return n_theta, refine, self

    def bounce_ratio(self, rho: float, sigma_t, albedo: float, g: float, w: int, h: int):
        """The per-bounce ratio of the series at the estimate (``rho``: ω·A(g))."""
        return rho

    def coarse_after(self, options: FitSettings) -> int | None:
        """The bounces after which the series continues on a coarser grid, or ``None``."""
        return None

    def coarse(self, grid: Grid, bounces: int, after: int | None) -> int | None:
        """K0 of the coarse tail where it applies, else ``None``."""
        return None

    @abc.abstractmethod
    def cheap(self, options: FitSettings) -> tuple[int, GeometryModel]:
        """θ bins and the geometry of the basin scan's cheap model."""

    def smallest(self) -> GeometryModel:
        """This geometry at its cheapest discretisation where the user left it open
        (a capture's floor, grown to each channel's model)."""
        return self

    def at_least(self, floor: GeometryModel) -> GeometryModel:
        """This geometry grown to ``floor``'s discretisation."""
        return self

    def grown(self, slab: Slab) -> Slab:
        """``slab`` grown to this geometry's discretisation (a floor's)."""
        return slab

    @abc.abstractmethod
    def over_cap(self, grid: Grid, max_cells: int) -> str | None:
        """The model's size where it passes ``max_cells``, else ``None``."""

    def fixed_by(self, options: FitSettings) -> list[str]:
        """What the user fixed beyond θ bins and refinement (never lowered by the cap)."""
        return []

    least = "32"  # the fewest θ bins the cap leaves, in words

    def finer_cheap(self, grid: Grid, options: FitSettings) -> tuple[Grid, GeometryModel] | None:
        """A finer cheap model for a solve that ran away, or ``None``."""
        return None

    def discretisation(self) -> dict[str, int]:
        """The sizes of this geometry's own dimensions (beyond θ bins and refinement)."""
        return {}

    @abc.abstractmethod
    def finer(
        self, grid: Grid, options: FitSettings, g: float, albedo: float | None = None
    ) -> tuple[Grid, GeometryModel]:
        """The grid and geometry of the error term's finer model at the answer's ``g``
        and ``albedo`` (``None``: unknown), never coarser."""

    def richardson_factor(self, grid: Grid, fine_grid: Grid) -> float | None:
        """How far past the finer model (``fine_grid``) the continuum lies, in units of
        the step from the model (``grid``) to it, where that is known (``None``: not
        known; the error term then holds the step alone)."""
        return None

    def record(self) -> dict:
        """This geometry's discretisation in a result's record."""
        return {}

    def sizing(self) -> dict:
        """What a sizing rule of this geometry asked for beyond its defaults, for the
        model's record (``{}``: nothing)."""
        return {}

    def deeper(self, than: GeometryModel) -> bool:
        """Whether this geometry needs much more than ``than``'s (a refit's worth)."""
        return False

    def words(self) -> str:
        """This geometry's discretisation in a progress line (``""``: none)."""
        return ""

    def stripe_cell(self, grid: Grid, options: FitSettings) -> int | None:
        """The stripe cell's ``shift_orders`` a model on ``grid`` renders stripes with
        (:class:`~lightfield_jax.forward.cell.CellRenderer`), or ``None``: the full
        render."""
        return None

    def renders_cell(self, model, illumination) -> bool:
        """Whether :meth:`renderer` renders ``illumination`` from one stripe period
        (then ``model``'s coarse tail does not apply: the cell marches every bounce on
        the model's grid)."""
        return False

    def cell_record(self, model) -> dict:
        """What the record of a model that renders the cell adds to its shift orders."""
        return {}

    def renderer(self, model, illumination, phase: str, **solve):
        """``model``'s renderer for ``illumination`` (its cell where ``model.cell``)."""
        return renderer_for(
            model.grid,
            illumination,
            model.bounces,
            phase,
            self.scene,
            coarse_after=model.coarse,
            **solve,
        )


@dataclasses.dataclass(frozen=True)
class PlaneModel(GeometryModel):
    """The plane: θ bins and refinement from g, a coarse tail, the periodic cell."""

    @property
    def scene(self) -> Plane:
        return Plane()

    def sized(self, options, g, albedo, sigma_t):
        gw = min(0.99, abs(g) + 0.1)
        return (
            options.model.n_theta or default_n_theta(gw),
            options.model.refine or default_refine(abs(g)),
            self,
        )

    def coarse_after(self, options):
        return options.model.coarse_after

    def coarse(self, grid, bounces, after):
        if after is None or bounces <= after or coarse_plane_grid(grid) is None:
            return None
        return after

    def cheap(self, options):
        return min(options.model.n_theta or 32, 32), self

    def over_cap(self, grid, max_cells):
        cells = plane_cells(grid)
        return None if cells <= max_cells else f"{cells} cells"

    def finer(self, grid, options, g, albedo=None):
        """One spatial refinement more than a refined model's (the size rule's at the
        answer's ``g`` where larger, as for an unrefined one), within twice
        ``max_render_cells`` (the memory a render may take), and twice the θ bins (past
        256 only within that cap; dropped first where both do not fit); where neither
        changes, one more refinement if it fits. The plane's error is first order in the
        cell size (:meth:`richardson_factor`): a term that kept the model's refinement
        did not see the dense forward medium's (64 θ bins, refine 2, Monte Carlo
        capture: σt +2.5 % reported as ± 0.2 %)."""
        cap = 2 * options.model.max_render_cells

        def cells(n_theta: int, refine: int) -> int:
            return grid.width * grid.height * n_theta * refine**2

        n_theta = 2 * grid.n_theta
        # A refined model (a forward medium's) one refinement more, an unrefined one the
        # size rule's at g; space first where both do not fit with the θ bins doubled.
        refine = max(grid.refine + 1 if grid.refine > 1 else 1, default_refine(g))
        refine = min(refine, REFINE_LIMIT)
        if refine > grid.refine and cells(n_theta, refine) > cap >= cells(grid.n_theta, refine):
            n_theta = grid.n_theta
        if cells(n_theta, refine) > cap:
            refine = grid.refine  # at most twice the model's cells (memory)
        if n_theta > 256 and cells(n_theta, refine) > cap:
            n_theta = grid.n_theta
        same = (n_theta, refine) == (grid.n_theta, grid.refine)
        if same and refine < REFINE_LIMIT and cells(n_theta, refine + 1) <= cap:
            refine += 1
        return dataclasses.replace(grid, n_theta=n_theta, refine=refine), self

    def richardson_factor(self, grid, fine_grid):
        """r_f/(r_f − r) where ``fine_grid`` is refined in space from r to r_f: images of
        the dense forward medium (σt .2, σs .16, g .7, 128×96, 64 θ bins, 60 bounces) at
        refine 1, 2 and 3 differ as I_1 − I_2 = 3.2 (I_2 − I_3) (weighted, correlation
        0.99; first order gives 3), so the model at refine 2 is three times its step to
        refine 3 from the continuum (the Monte Carlo's), not one."""
        r, r_f = grid.refine, fine_grid.refine
        return None if r_f <= r else r_f / (r_f - r)

    def stripe_cell(self, grid, options):
        """On a refined grid, the cell with its defaults: within 0.25 % of the full
        render in every row and several times faster (docs/periodic_cell.md), where the
        model's own discretisation error is percents (the error term's refine + 1). On
        the native grid it is no faster than the full render."""
        return SHIFT_ORDERS if options.model.stripe_cell and grid.refine > 1 else None

    def renders_cell(self, model, illumination) -> bool:
        return model.cell is not None and cell_problem(model.grid, illumination) is None

    def cell_record(self, model):
        return {"walls_coarsen": walls_coarsen(model)}

    def renderer(self, model, illumination, phase, **solve):
        if self.renders_cell(model, illumination):
            return cell_renderer_for(
                model.grid,
                illumination,
                model.bounces,
                phase,
                shift_orders=model.cell,
                walls_coarsen=walls_coarsen(model),
                **solve,
            )
        return super().renderer(model, illumination, phase, **solve)


@dataclasses.dataclass(frozen=True)
class SlabModel(GeometryModel):
    """The slab: azimuth bins, elevation nodes and depth layers from the estimate,
    within four times the plane's cell cap (its fields span the 2H × 2W FFT domain)."""

    slab: Slab
    # The (azimuth bins, elevation nodes, refinement) the near-wall rule asked for
    # (|g| ≥ 0.9), before the cap; ``None`` where it did not apply. Recorded with the
    # model.
    near_wall: tuple[int, int, int] | None = None

    @property
    def scene(self) -> Slab:
        return self.slab

    def sized(self, options, g, albedo, sigma_t):
        # Less sensitive to g than the plane: a smaller margin. Depth layers, elevation
        # nodes and azimuth bins from the estimate (the albedo and σt·h decide how much
        # the depth must be resolved).
        # A forward lobe (|g| ≥ 0.9 with the margin) asks for the finer in-plane grid
        # (scene.slab_grid: 64 bins, 48 μ nodes, refine 3); the cap (:meth:`capped`)
        # lowers what it added first.
        g_slab, albedo_slab = slab_rule_inputs(g, albedo)
        slab, n_theta, refine = self.slab, options.model.n_theta, options.model.refine
        asked = None
        if needs_near_wall_grid(g_slab, albedo_slab):
            asked = near_wall_grid(1, 1, 1, n_theta, slab.n_mu, refine, cap=NEAR_WALL_UNCAPPED)
            n_theta, n_mu, refine = asked
            slab = dataclasses.replace(slab, n_mu=n_mu)
        slab = slab.resolve(g_slab, sigma_t=sigma_t, albedo=albedo_slab)
        n_theta = n_theta or default_slab_n_theta(g_slab, self.slab.boundary, albedo_slab)
        return n_theta, refine or 1, SlabModel(slab, near_wall=asked)

    def over(self, width, height, n_theta, refine, max_cells: int) -> bool:
        """Whether the slab passes a cap of ``max_cells`` (a plane's cell count): it
        works on azimuth × elevation × depth fields over the 2H × 2W FFT domain,
        allowed 4 × ``max_cells``."""
        return slab_cells(width, height, n_theta, refine, self.slab) > 4 * max_cells

    def capped(self, width, height, n_theta, refine, options):
        n_theta, refine, n_mu = capped_sizes(
            width, height, n_theta, refine, self.slab, self.near_wall is not None, options
        )
        return (
            n_theta,
            refine,
            dataclasses.replace(self, slab=dataclasses.replace(self.slab, n_mu=n_mu)),
        )

    def bounce_ratio(self, rho, sigma_t, albedo, g, w, h):
        if sigma_t is None:
            return rho
        # Light leaves through the faces: the slab's measured per-bounce ratio, not ω.
        return min(rho, slab_bounce_ratio(self.slab, sigma_t, min(albedo, 1.0), g, w, h))

    def cheap(self, options):
        slab = dataclasses.replace(
            self.slab,
            n_mu=min(self.slab.n_mu or MIN_CAPPED_MU, MIN_CAPPED_MU),
            n_z=1,
            depth_profile=None,  # one layer, its average: the user's profile is the need's
        )
        return min(options.model.n_theta or 8, 8), SlabModel(slab)

    def smallest(self):
        slab = self.slab
        return SlabModel(
            dataclasses.replace(slab, n_mu=slab.n_mu or MIN_CAPPED_MU, n_z=slab.n_z or 1)
        )

    def at_least(self, floor):
        return dataclasses.replace(self, slab=floor.grown(self.slab))

    def grown(self, slab):
        floor = self.slab
        slab = dataclasses.replace(
            slab, n_mu=max(slab.n_mu, floor.n_mu), n_z=max(slab.n_z, floor.n_z)
        )
        if floor.profile == "linear" and slab.profile != "linear":
            slab = dataclasses.replace(slab, depth_profile="linear")
        return slab

    def over_cap(self, grid, max_cells):
        if not self.over(grid.width, grid.height, grid.n_theta, grid.refine, max_cells):
            return None
        slab = self.slab
        slab_cells = plane_cells(grid) * 4 * slab.n_mu * slab.n_z * slab.depth_coefficients
        return f"{slab.n_mu} elevation nodes: {slab_cells} slab cells, 4 x max_cells allowed"

    def fixed_by(self, options):
        return [] if fixed_n_mu(options) is None else [f"{self.slab.n_mu} elevation nodes"]

    least = f"8 (nor elevation nodes below {MIN_CAPPED_MU})"

    def finer_cheap(self, grid, options):
        """16 azimuth bins and 8 elevation nodes, for a solve that did not converge or
        ran to a bound on the 8 × 4 one: a forward medium's lobe is not resolved there.
        Measured on the 3-D Monte Carlo's capture of ω 0.99, g 0.9 behind refractive
        faces (32×24): on 8 × 4 the solve ran its 100 steps to albedo 1.0000 (σt −15 %);
        on 16 × 8 it converged and the correction reached σt +1.8 %, σs +1.7 %, g
        +0.011. ``None`` where the user fixed the bins or nodes, where the model has them
        already, or where it would pass ``max_cells``."""
        n_theta, n_mu = RETRY_SLAB
        if (
            options.model.n_theta is not None
            or fixed_n_mu(options) is not None
            or (grid.n_theta >= n_theta and self.slab.n_mu >= n_mu)
        ):
            return None
        grid = dataclasses.replace(grid, n_theta=max(grid.n_theta, n_theta))
        retry = SlabModel(dataclasses.replace(self.slab, n_mu=max(self.slab.n_mu, n_mu)))
        if retry.over(grid.width, grid.height, grid.n_theta, grid.refine, options.model.max_cells):
            return None
        return grid, retry

    def discretisation(self):
        slab = self.slab
        return {"n_mu": slab.n_mu, "n_z": slab.n_z, "depth_order": slab.depth_coefficients - 1}

    def finer(self, grid, options, g, albedo=None):
        """Twice its depth layers (at most 16), elevation nodes (64) and azimuth bins
        (128), in that order of priority, each only within four times
        ``max_render_cells``; first what the cap left below the rule at ``g``
        (:func:`~lightfield_jax.inverse.slab_caps.finer_order`)."""

        def doubled(n: int, limit: int) -> int:
            return max(n, min(2 * n, limit))  # never below the model's own

        cap = 4 * options.model.max_render_cells
        model = self
        limits = {"n_z": 16, "n_mu": 64, "n_theta": 128}
        for name in finer_order(grid.n_theta, self.slab, g, albedo):
            g2, m2 = grid, model
            if name == "n_theta":
                g2 = dataclasses.replace(grid, n_theta=doubled(grid.n_theta, limits[name]))
            else:
                n = doubled(getattr(model.slab, name), limits[name])
                m2 = SlabModel(dataclasses.replace(model.slab, **{name: n}))
            # (a cap of four times the render's cells, as the slab's own cap is of the
            # plane's: sixteen times max_render_cells in all)
            if not m2.over(g2.width, g2.height, g2.n_theta, g2.refine, cap):
                grid, model = g2, m2
        return grid, model

    def record(self):
        slab = self.slab
        return {"n_mu": slab.n_mu, "n_z": slab.n_z, "depth_profile": slab.profile}

    def sizing(self):
        if self.near_wall is None:
            return {}
        n_theta, n_mu, refine = self.near_wall
        asked = {"n_theta": n_theta, "n_mu": n_mu, "refine": refine}
        return {"near_wall_grid": {"g_from": NEAR_WALL_G, "asked": asked}}

    def stripe_cell(self, grid, options):
        """The slab's stripe cell (:class:`~lightfield_jax.forward.slab_cell.SlabCellRenderer`:
        the first orders of every shift exact, the later ones from one period with the
        walls' term of the shifts' mean and each shift's deviation from it on a coarse
        discretisation) for a sized model, where ``stripe_cell`` allows it."""
        return SLAB_SHIFT_ORDERS if options.model.stripe_cell else None

    def renders_cell(self, model, illumination) -> bool:
        # The whole tank for the cheap models (the shifts' mean alone is 7 % off next
        # to the walls at ω .95, g .8; their Jacobian guides the correction), short
        # series and models no finer than the deviation grid (the cell's parts then
        # cost more than the full render: K 4 and 6 at 48×36 1.6–2.2× slower).
        if model.cell is None or model.cell < SLAB_SHIFT_ORDERS:
            return False
        slab = self.slab
        _, n_mu = deviation_grid(model.grid.n_theta, slab.n_mu)
        coarser = n_mu < slab.n_mu * slab.n_z * slab.depth_coefficients
        return (
            coarser
            and model.bounces >= SLAB_CELL_BOUNCES
            and cell_problem(model.grid, illumination) is None
        )

    def cell_record(self, model):
        return {"deviation": list(deviation_grid(model.grid.n_theta, self.slab.n_mu))}

    def renderer(self, model, illumination, phase, **solve):
        if self.renders_cell(model, illumination):
            return slab_cell_renderer_for(
                model.grid,
                illumination,
                model.bounces,
                self.slab,
                phase,
                shift_orders=model.cell,
                deviation=deviation_grid(model.grid.n_theta, self.slab.n_mu),
                **solve,
            )
        return super().renderer(model, illumination, phase, **solve)

    def deeper(self, than):
        # A slab's depth layers and elevation nodes too (g decides the nodes, the
        # albedo the layers).
        have = than.discretisation()
        return self.slab.n_z > have.get("n_z", 0) or self.slab.n_mu >= 2 * have.get("n_mu", 0)

    def words(self):
        return f", n_mu {self.slab.n_mu}, n_z {self.slab.n_z}"


def geometry_model(geometry) -> GeometryModel:
    """The strategy of a fit's ``geometry`` option (``None``: the plane; an auto
    geometry's slab, its candidate)."""
    slab = as_geometry(geometry).slab_or_none
    return PlaneModel() if slab is None else SlabModel(slab)


__all__ = [
    "MIN_CAPPED_MU",
    "RETRY_SLAB",
    "GeometryModel",
    "PlaneModel",
    "SlabModel",
    "geometry_model",
    "plane_cells",
]
