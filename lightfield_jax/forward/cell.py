"""Stripes on the plane from one stripe period: the periodic cell (docs/model.md §4.5).

A homogeneous medium lit through a side wall by stripes of period P repeats every P
rows, and every shift is a roll of one solution, except where the tank's top and bottom
walls break the repetition. :class:`CellRenderer` renders a stripe capture as

    I_1, I_2 of every shift:  exact, on the whole tank (walls included): I_1 is local,
        and I_2 is the unscattered fluence convolved with the first-scatter kernel
        summed over directions (:mod:`lightfield_jax.forward.first_scatter`), one 2-D
        convolution per shift;
    I_k, k ≥ 3:  the cell's I_k (one period, periodic in y, one pattern:
        :class:`PeriodicCell`), rolled to each shift's phase and tiled over the rows,
        plus the walls' term: the tank's render less the periodic grid's, both on the
        native grid (:class:`WallsTerm`); every shift's own for the first
        ``shift_orders`` orders, then the shifts' mean a·(F_k − F̃_k) (F the full light
        of the tank with its walls, F̃ the same light on the periodic grid, a =
        lit/period the pattern's mean). On refined models the ``wall_band`` rows next to
        each wall are corrected to the refined grid on a short tank (:class:`WallBands`).

The approximations against the full-domain render: after ``shift_orders`` the walls act
on the shifts' mean alone (by then each shift's own deficit has spread smoothly), and on
refined models the walls' term is the native grid's outside the wall bands (the same
discretisation for the tank and the periodic grid, so their difference keeps little of
either's error). The cost is the cell's march (P rows, one pattern), the native grid's
walls' terms and the short tank's first orders, instead of every shift over every row.
"""

from __future__ import annotations

import abc
import dataclasses
import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from lightfield_jax.checks import check_int
from lightfield_jax.forward.base import (
    AbstractRenderer,
    FirstOrders,
    as_physical,
    block_mean,
    check_bounces,
    count_trace,
    restrict_moments,
)
from lightfield_jax.forward.first_scatter import kernel_nodes
from lightfield_jax.forward.kernels import fft_convolve, padded_spectrum, splat
from lightfield_jax.forward.pattern_basis import PatternBasis, shift_basis
from lightfield_jax.forward.plane import PlaneRenderer, theta_groups
from lightfield_jax.forward.tail import check_tail, joined_tail
from lightfield_jax.forward.transport import transport_tables
from lightfield_jax.forward.wall_bands import WallBands, short_tank_height
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import (
    Full,
    Stripes,
    along_x,
    cell_moments,
    scaled,
    source_moments,
)
from lightfield_jax.scene.medium import Medium


def folded_index(index: np.ndarray, height: int, width: int, rows: int) -> np.ndarray:
    """Flat kernel indices into (J, 2·height, 2·width) (offsets stored modulo the size)
    as indices into (J, rows, 2·width): the y offsets folded modulo ``rows`` (the
    periodic images of a source ``rows`` apart add up)."""
    plane = 4 * height * width
    j, rem = np.divmod(index.astype(np.int64), plane)
    ty, tx = np.divmod(rem, 2 * width)
    dy = np.where(ty < height, ty, ty - 2 * height)
    return ((j * rows + np.mod(dy, rows)) * 2 * width + tx).astype(np.int32)


def shift_rows(illumination: Stripes, height: int) -> np.ndarray:
    """(patterns, H): the cell's row of each shift's row (a shift by phase φ is the
    cell rolled by φ rows)."""
    phases = np.asarray(illumination.phases)[:, None]
    return np.mod(np.arange(height)[None] + phases, illumination.period)


class PeriodicCell(PlaneRenderer):
    """The plane on a grid periodic in y, for one period of stripes or full light
    (:class:`~lightfield_jax.forward.plane.PlaneRenderer`'s loop and bounce step; its
    transport periodic in y, its first-scatter kernel folded modulo the cell).

    ``grid`` is the cell (its height the period, in native rows), ``illumination`` one
    phase of stripes (phase 0) or :class:`~lightfield_jax.scene.illumination.Full`
    entering the left or right wall; ``tank_height`` (native rows) bounds how far a ray
    travels in y, as in the tank: the kernel's offsets and the y sweep's history.
    """

    def __init__(
        self,
        grid: Grid,
        illumination: Stripes | Full,
        bounces: int,
        phase: str,
        *,
        tank_height: int,
        tail: str | None = None,
        tail_tol: float = 1e-4,
        tail_max_steps: int = 500,
        moments=None,
    ):
        if not along_x(illumination.entry):
            raise ValueError("PeriodicCell: the cell is periodic in y: light enters a side wall")
        Medium(1.0, 0.5, 0.0, phase)  # validates the phase name
        self.bounces = check_bounces(bounces)
        check_tail(tail, tail_tol, tail_max_steps)
        self.tail, self.tail_tol, self.tail_max_steps = tail, float(tail_tol), int(tail_max_steps)
        f = self.refine = 1 if grid.refine is None else grid.refine
        self.height, self.width, self.n_theta = grid.height * f, grid.width * f, grid.n_theta
        self.phase = phase
        self.coarse_after = None
        self.marched_basis = None
        if moments is None:
            moments = cell_moments(scaled(illumination, f), self.width, self.height)
        cov, mean, var = moments
        self.coverage, self.mean_depth, self.var_depth = (jnp.asarray(a) for a in (cov, mean, var))
        theta0 = math.radians(illumination.direction_deg)
        self.theta0_bin = int(round(theta0 / grid.dtheta)) % grid.n_theta
        tank = max(tank_height, grid.height) * f
        nodes = kernel_nodes(self.width, tank, grid.n_theta)
        self.nodes = {
            "r": jnp.asarray(nodes["r"]),
            "weight": jnp.asarray(nodes["weight"]),
            "splat": jnp.asarray(nodes["splat"]),
            "index": jnp.asarray(folded_index(nodes["index"], tank, self.width, self.height)),
        }
        self.node_angle = jnp.asarray(nodes["phi"] - theta0)
        self.tables = transport_tables(theta_groups(grid.n_theta))
        j = np.arange(grid.n_theta)
        self.circulant = jnp.asarray((j[:, None] - j[None, :]) % grid.n_theta, dtype=jnp.int32)
        self.separable, self.across, self.along_at = None, None, None
        self.periods = max(1, math.ceil(tank / self.height))

    def coarse_grid(self, grid: Grid) -> Grid | None:
        return None

    def kernel(self, node_values) -> Float[Array, "n_theta rows 2W"]:
        """The first-scatter kernel (without σs) of node values p(φ − θ0)·e^{−σt r}·w,
        folded modulo the cell's rows."""
        size = self.n_theta * self.height * 2 * self.width
        k = splat(self.nodes["index"], self.nodes["splat"], node_values[None], size)
        return k.reshape(self.n_theta, self.height, 2 * self.width)

    def node_values(self, node_p, sigma_t):
        dtype = node_p.dtype
        r = self.nodes["r"].astype(dtype)
        return node_p * jnp.exp(-sigma_t * r) * self.nodes["weight"].astype(dtype)

    def first_orders(self, sigma_t, sigma_s, g, source, scattered: bool) -> FirstOrders:
        p_camera, node_p, mixing = self._phase_parts(g)
        image = sigma_s * p_camera * source
        if not scattered:
            return FirstOrders(image)
        kernel = self.kernel(self.node_values(node_p, sigma_t))
        rows, width = self.height, self.width
        # Periodic in y (no padding), zero-padded in x.
        spectrum = jnp.fft.rfft2(source, s=(rows, 2 * width))[:, None]
        l1 = jnp.fft.irfft2(spectrum * jnp.fft.rfft2(kernel)[None], s=(rows, 2 * width))
        l1 = sigma_s * jnp.maximum(l1[..., :width], 0.0)
        step = self._step(sigma_t, sigma_s, mixing)
        q2, i2 = step.scatter(l1)
        return FirstOrders(image, step, i2, l1, q2)


def cell_problem(grid: Grid, illumination) -> str | None:
    """Why stripes on this grid are not rendered from one period (``None``: they can
    be): the cell is for stripes entering a side wall (periodic in y), shorter than
    the tank."""
    if not isinstance(illumination, Stripes):
        return "only stripes repeat"
    if not along_x(illumination.entry):
        return "the cell is periodic in y: stripes entering the top or bottom wall"
    if illumination.period >= grid.height:
        return "the period is not shorter than the tank"
    return None


# The orders whose walls' term is every shift's own (the later ones take the shifts'
# mean), and the native rows next to each wall whose walls' term is corrected to the
# refined grid (WallBands; 0: none). Measured against the full render (128×96, six
# shifts, docs/periodic_cell.md): on a milk-like medium (σt .2, σs .19, g .8, refine 2)
# the rows' worst error of the series' image is 0.86 % with 6 orders and no band, 0.79 %
# with 10 and no band (the native grid's walls' term next to the walls), 0.18 % with 10
# and a band of 2 rows; 0.3 % with 8 and a band. Each shift's walls' term keeps the
# shift-dependent deficit the walls make in the low orders, which spreads smoothly to
# the high orders over the whole tank: the shifts' mean alone (2) is 2–6 % off.
SHIFT_ORDERS = 10
WALL_BAND = 2
# The orders the wall bands correct (the refined grid's detail next to the walls is made
# in the first ones). Against the full render (128×96, six shifts, min of 3 calls): 3–5
# leaves a worst row of 0.068 % (dense forward, σt .2, σs .16, g .7) and 0.23 % (milk-
# like), 3–10 0.061 % and 0.18 %, for 1.3× and 1.2× slower renders.
BAND_ORDERS = 5


class WallsTerm(eqx.Module):
    """The walls' term of some orders: the tank's render on a coarse grid less the
    periodic grid's, times ``weight`` (native grid, unit gain). For ``light`` the
    stripes, every shift's own; for full light, the shifts' mean (``weight`` the lit
    fraction)."""

    tank: PlaneRenderer
    unwalled: PeriodicCell
    weight: float = eqx.field(static=True)
    coarsen: int = eqx.field(static=True)

    def __init__(
        self, grid: Grid, light, bounces: int, phase: str, weight, coarsen, solve, period=None
    ):
        c = self.coarsen = coarsen
        self.weight = float(weight)
        tank = restrict_moments(*source_moments(light, grid.width, grid.height), c)
        coarse = Grid(grid.width // c, grid.height // c, grid.n_theta, 1)
        self.tank = PlaneRenderer(coarse, light, bounces, phase, moments=tank, **solve)
        # The periodic grid: a period of ``light`` (of ``period`` rows, given), at least
        # two coarse rows. Its march keeps the last of ``tank_height`` rows: a grid of
        # other rows keeps other histories, which differ where the tank is a few mean
        # free paths tall.
        rows = math.lcm(period or getattr(light, "period", 1), c)
        rows *= 2 if rows == c else 1
        free = restrict_moments(*cell_moments(light, grid.width, rows), c)
        self.unwalled = PeriodicCell(
            Grid(grid.width // c, rows // c, grid.n_theta, 1),
            light,
            bounces,
            phase,
            tank_height=grid.height // c,
            moments=free,
            **solve,
        )

    def __call__(self, sigma_t, sigma_s, g):
        """(per-order term (patterns or 1, K, H, W); with a tail solve, (its tail's term,
        the two tail solutions), else ``None``; the periodic grid's own images (patterns
        or 1, K, its rows, W; on the coarse grid, unit weight))."""
        c = self.coarsen
        tank = self.tank.unchecked(sigma_t * c, sigma_s * c, g)
        free = self.unwalled.unchecked(sigma_t * c, sigma_s * c, g)
        rows = np.arange(self.tank.height) % self.unwalled.height

        def up(x):
            x = self.weight * x
            return jnp.repeat(jnp.repeat(x, c, axis=-2), c, axis=-1) / c if c > 1 else x

        orders = up(tank[0] - free[0][..., rows, :])
        if len(tank) == 2:
            return orders, None, free[0]
        tail = (up(tank[2].image - free[2].image[..., rows, :]), tank[2], free[2])
        return orders, tail, free[0]


class ComposedRenderer(AbstractRenderer):
    """A renderer of stripes composed from other renderers (the stripe cell's parts):
    the call signature and outputs of
    :class:`~lightfield_jax.forward.base.AbstractRenderer`, per-bounce images of every
    shift on the native grid, no light fields and no coarse tail. Subclasses give
    :meth:`compose`: ``(images (patterns, K, H, W) at ``gain``, the tail's
    :class:`~lightfield_jax.forward.tail.TailSolution` or ``None``)``."""

    # What AbstractRenderer asks of a geometry: the parts render.
    def first_orders(self, sigma_t, sigma_s, g, source, scattered: bool) -> FirstOrders:
        raise NotImplementedError(f"{type(self).__name__} renders through its parts")

    def integrate(self, field):
        return field

    @property
    def direct_depth(self) -> float:
        return 1.0

    @property
    def field_scale(self) -> float:
        return 1.0

    @abc.abstractmethod
    def compose(self, sigma_t, sigma_s, g, gain):
        """(images, tail or ``None``) at these physical values."""

    def unchecked(self, sigma_t, sigma_s, g, gain=1.0, lightfield: bool = False):
        if lightfield:
            raise ValueError(
                "lightfield: a stripe cell renders images only; render light fields on the "
                "whole grid (stripe_cell: false)"
            )
        sigma_t, sigma_s, g, gain = as_physical(sigma_t, sigma_s, g, gain)
        images, tail = self._images(sigma_t, sigma_s, g, gain)
        return (images, None) if tail is None else (images, None, tail)

    def images_and_g_slope(self, sigma_t, sigma_s, g, gain=1.0):
        if self.tail is not None:
            raise ValueError(
                f"images_and_g_slope: per-bounce images only; this renderer has tail "
                f"{self.tail!r} (use jax.jvp through the call)"
            )
        sigma_t, sigma_s, g, gain = as_physical(sigma_t, sigma_s, g, gain)
        return self._g_slope(sigma_t, sigma_s, g, gain)

    @eqx.filter_jit
    def _g_slope(self, sigma_t, sigma_s, g, gain):
        return jax.jvp(
            lambda g: self.compose(sigma_t, sigma_s, g, gain)[0], (g,), (jnp.ones_like(g),)
        )

    @eqx.filter_jit
    def _images(self, sigma_t, sigma_s, g, gain):
        return self.compose(sigma_t, sigma_s, g, gain)


class CellRenderer(ComposedRenderer):
    """Stripes on the plane rendered from one period (the module's scheme): the call
    signature and outputs of :class:`~lightfield_jax.forward.base.AbstractRenderer`,
    per-bounce images of every shift on the whole grid; no light fields (those of a
    full-domain render: :class:`~lightfield_jax.forward.plane.PlaneRenderer`) and no
    coarse tail (the cell is marched on its refined grid throughout).

    ``shift_orders``: the orders whose walls' term is every shift's own (``None``:
    every order's); ``walls_coarsen``: the walls' term is marched on a grid this many
    times coarser than the native one (it must divide the grid's width and height);
    ``wall_band``: the native rows next to each wall whose walls' term is corrected to
    the refined grid (refined grids, ``walls_coarsen`` 1, a tank at least twice the
    short tank's height; 0: none) in orders 3 to ``band_orders`` (``None``: to
    ``shift_orders``).
    """

    cell: PeriodicCell
    shift_walls: WallsTerm | None
    mean_walls: WallsTerm | None
    wall_bands: WallBands | None
    sum_index: Int[Array, "nodes 4"]
    rows: Int[Array, "patterns H"]
    shift_orders: int = eqx.field(static=True)
    basis: PatternBasis | None = eqx.field(static=True)

    def __init__(
        self,
        grid: Grid,
        illumination: Stripes,
        bounces: int,
        phase: str = "paper",
        *,
        tail: str | None = None,
        tail_tol: float = 1e-4,
        tail_max_steps: int = 500,
        shift_orders: int | None = SHIFT_ORDERS,
        walls_coarsen: int = 1,
        wall_band: int = WALL_BAND,
        band_orders: int | None = BAND_ORDERS,
    ):
        problem = cell_problem(grid, illumination)
        if problem is not None:
            raise ValueError(f"CellRenderer: {problem}")
        c = check_int(walls_coarsen, "walls_coarsen", low=1)
        if grid.width % c or grid.height % c:
            raise ValueError(
                f"CellRenderer: walls_coarsen {c} must divide the grid ({grid.width}x{grid.height})"
            )
        self._setup(grid, illumination, bounces, phase, tail, tail_tol, tail_max_steps)
        solve = {"tail": tail, "tail_tol": tail_tol, "tail_max_steps": tail_max_steps}
        period = illumination.period
        one = dataclasses.replace(illumination, phases=(0,))
        cell_grid = Grid(grid.width, period, grid.n_theta, self.refine)
        self.cell = PeriodicCell(
            cell_grid, one, self.bounces, phase, tank_height=grid.height, **solve
        )
        k = self.bounces
        if shift_orders is None:
            shift_orders = k + 1  # the tail's too
        self.shift_orders = check_int(shift_orders, "shift_orders", low=2)
        marched = k >= 3 or tail is not None
        self.shift_walls, self.mean_walls = None, None
        full = Full(illumination.direction_deg, illumination.entry)
        # Past K, only with a tail: its term is every shift's own too.
        every = self.shift_orders > k
        own_terms = marched and self.shift_orders >= 3
        # Fewer shifts and full light (the mean's) where those give every shift's.
        usable = own_terms and not every and c == 1
        self.basis = shift_basis(grid, illumination, full) if usable else None
        if own_terms:
            # Every shift, or fewer of them whose walls' terms and full light's give
            # every shift's.
            shifts = illumination if self.basis is None else self.basis.kept_shifts(illumination)
            self.shift_walls = WallsTerm(
                grid,
                shifts,
                k if every else self.shift_orders,
                phase,
                1.0,
                c,
                solve if every else {},
            )
        if marched and not every:
            # Full light's periodic grid is a period of the stripes, as the cell's and
            # the shifts' are (their marches keep the same histories; the basis needs
            # it). With two rows it kept longer ones: 0.2 % off the full render in the
            # middle rows of a 64×48 tank at σt 0.05, against 0.1 % (refine 2, 20 orders).
            self.mean_walls = WallsTerm(
                grid, full, k, phase, illumination.lit / period, c, solve, period
            )
        band = check_int(wall_band, "wall_band", low=0)
        self.wall_bands = None
        orders = min(self.shift_orders, k)
        if band_orders is not None:
            orders = min(check_int(band_orders, "band_orders", low=3), orders)
        if self.shift_walls is not None and self.refine > 1 and band > 0 and c == 1:
            if 2 * short_tank_height(grid.height, period, band) <= grid.height:
                self.wall_bands = WallBands(grid, illumination, orders, phase, band, self.basis)
        # The θ-summed kernel on the whole (refined) tank: the same nodes as the cell's.
        nodes = kernel_nodes(self.width, self.height, grid.n_theta)
        self.sum_index = jnp.asarray(np.mod(nodes["index"], 4 * self.height * self.width))
        self.rows = jnp.asarray(shift_rows(illumination, grid.height), jnp.int32)

    @property
    def image_scale(self) -> float:
        return self.refine

    def _first_two(self, sigma_t, sigma_s, g):
        """I_1 and I_2 of every shift on the whole tank (native grid, unit gain)."""
        f = self.refine
        st, ss = sigma_t / f, sigma_s / f
        source = self.unscattered(st)
        p_camera, node_p, _ = self.cell._phase_parts(g)
        out = [ss * p_camera * source]
        if self.bounces >= 2:
            values = self.cell.node_values(node_p, st)
            size = 4 * self.height * self.width
            kernel = splat(self.sum_index, self.cell.nodes["splat"], values[None], size)
            kernel = kernel.reshape(2 * self.height, 2 * self.width)
            summed = fft_convolve(
                padded_spectrum(source), jnp.fft.rfft2(kernel), self.height, self.width
            )
            dtheta = 2 * math.pi / self.n_theta
            out.append(ss * ss * p_camera * dtheta * jnp.maximum(summed, 0.0))
        images = jnp.stack(out, axis=1)  # (patterns, 1 or 2, fH, fW)
        return f * block_mean(images, f, (-2, -1)) if f > 1 else images

    def _walls_term(self, sigma_t, sigma_s, g):
        """The walls' term per shift and order ≥ 3 (native grid, unit gain): every
        shift's own up to ``shift_orders``, the shifts' mean after; the tail's; and every
        shift's periodic grid on the native grid (``None`` without the shifts' own)."""
        terms, tail, free, mean = [], None, None, None
        if self.shift_walls is not None:
            own, tail, free = self.shift_walls(sigma_t, sigma_s, g)
            terms.append(own[:, 2 : self.shift_orders])
        if self.mean_walls is not None:
            mean, tail, free_full = self.mean_walls(sigma_t, sigma_s, g)
            if self.basis is not None:
                # Every shift from the kept ones' and full light's (the mean over the lit
                # fraction), their periodic grids (the same rows) likewise.
                full = mean[0, 2 : self.shift_orders] / self.mean_walls.weight
                terms[0] = self.basis.combine(terms[0], full)
                free = self.basis.combine(free, free_full[0, : free.shape[1]])
            n = self.n_patterns
            terms.append(jnp.broadcast_to(mean, (n,) + mean.shape[1:])[:, self.shift_orders :])
        return jnp.concatenate(terms, axis=1), tail, free

    def compose(self, sigma_t, sigma_s, g, gain):
        count_trace()
        first = self._first_two(sigma_t, sigma_s, g)
        if self.bounces <= 2 and self.tail is None:
            return gain * first[:, : self.bounces], None
        cell = self.cell.unchecked(sigma_t, sigma_s, g)
        walls, walls_tail, free = self._walls_term(sigma_t, sigma_s, g)
        later = jnp.moveaxis(cell[0][0][:, self.rows], 0, 1)  # (patterns, K, H, W)
        later = later[:, 2:] + walls
        if self.wall_bands is not None:
            bands = self.wall_bands
            n, b = bands.rows, bands.band
            fix = bands(sigma_t, sigma_s, g, cell[0][0], free, self.rows[:, :n])
            m = fix.shape[1]
            later = later.at[:, :m, :b].add(fix[:, :, :b])
            top = self.height // self.refine - b
            later = later.at[:, :m, top:].add(fix[:, :, b:])
        images = jnp.concatenate([first, later], axis=1)
        images = gain * images[:, : self.bounces]
        if self.tail is None:
            return images, None
        tail_image, tank_tail, free_tail = walls_tail
        cell_tail = cell[2]
        image = gain * (cell_tail.image[0][self.rows] + tail_image)
        return images, joined_tail(image, (cell_tail, tank_tail, free_tail))


# A cached CellRenderer (its tables built once per static configuration), as
# renderer_for is for the full render.
cell_renderer_for = functools.lru_cache(maxsize=16)(CellRenderer)
