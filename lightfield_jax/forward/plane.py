"""The plane: the paper's 2-D model, bounce by bounce (docs/model.md §4).

Scheme (docs/model.md §4 says why):

- I_1 is exact: σs·p(π/2)·S with S the pixel-averaged unscattered fluence.
- L_1 is semi-analytic: S convolved with a per-direction-bin kernel
  (:mod:`lightfield_jax.forward.first_scatter`), so the thin beam never smears on the grid.
- From the second bounce on, L_k = T[Q_k] on the (x, y, θ) grid
  (:mod:`lightfield_jax.forward.transport`), with Q_k = σs·∫ p(θ − θ') L_{k−1}(θ') dθ' as one
  matmul with the bin-averaged circulant phase matrix; the camera sum
  I_k = σs·p(π/2)·Σ_θ L_{k−1}·Δθ is one more output row of the same matmul.

The bounce loop, refinement, stacking and the tail are the base class's
(:class:`~lightfield_jax.forward.base.AbstractRenderer`). Images are in units of the
source (unit irradiance) times the gain; light fields are radiance per radian, averaged
over each pixel and each direction bin.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from lightfield_jax.forward.base import AbstractRenderer, FirstOrders, block_mean, count_trace
from lightfield_jax.forward.first_scatter import (
    convolve_kernels,
    convolve_separable,
    first_scatter_kernel,
    kernel_nodes,
    separable_source,
)
from lightfield_jax.forward.kernels import bin_pair_offsets, einsum
from lightfield_jax.forward.transport import direction_groups, transport, transport_tables
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import Illumination
from lightfield_jax.scene.medium import Medium
from lightfield_jax.scene.phase import phase_function

# Sub-samples per bin of the triangle-weighted bin average of p (phase matrix).
_PHASE_SUBSAMPLES = 16


@functools.lru_cache(maxsize=8)
def theta_groups(n_theta: int):
    return direction_groups(n_theta)


def _phase_matrix_taps(g, n_theta: int):
    """c_m = bin-pair average of p at bin offset m: (1/Δθ²)∫_{bin j}∫_{bin j'} p(θ − θ') dθ dθ'."""
    dtype = jnp.result_type(g)
    delta, weights = bin_pair_offsets(n_theta, _PHASE_SUBSAMPLES)
    return jnp.sum(phase_function(jnp.asarray(delta, dtype), g) * weights.astype(dtype), axis=1)


def coarse_plane_grid(grid: Grid) -> Grid | None:
    """The plane's coarse grid for the bounces after ``coarse_after``: the native grid
    (refine 1), the same θ bins; ``None`` where ``grid`` is not refined. Measured on the
    dense forward medium (ω 0.8, g 0.7, 128×96, 64 θ bins, refine 2, 32 bounces, the
    coarse grid after 8): per-bounce image sums within 0.04 % of the full march's, the
    series' image within 5e-5 of its peak; half the θ bins as well drifted by 2 % per
    bounce sum by the 32nd bounce."""
    if (grid.refine or 1) == 1:
        return None
    return Grid(grid.width, grid.height, grid.n_theta, 1)


class BounceStep(eqx.Module):
    """One bounce on the plane's grid, Q_k ↦ (Q_{k+1}, I_{k+1}), built once per (σt, σs, g).

    ``step(q)`` is ``scatter(transport(q))``: L_k = T[Q_k] (black walls), then
    Q_{k+1} = σs·∫ p(θ − θ') L_k dθ' and I_{k+1} = σs·p(π/2)·Σ_θ L_k·Δθ from one matmul
    with the mixing matrix. Linear in q; σt, σs and the mixing matrix are leaves (a
    linear solve over the step differentiates through them). Sources and fields are
    direction-major, Float[Array, "patterns n_theta H W"]; images "patterns H W".
    """

    sigma_t: Float[Array, ""]
    sigma_s: Float[Array, ""]
    mixing: Float[Array, "n_theta+1 n_theta"]
    tables: dict
    n_theta: int = eqx.field(static=True)
    periods: int = eqx.field(static=True, default=0)  # > 0: periodic in y (the cell)

    @property
    def linear(self) -> BounceStep:
        """The step itself: it is exactly linear (no clipping)."""
        return self

    def transport(self, q):
        """L = T[Q] on the grid (:func:`lightfield_jax.forward.transport.transport`)."""
        return transport(q, self.sigma_t, theta_groups(self.n_theta), self.tables, self.periods)

    def scatter(self, field):
        """(Q_next, image) of a light field: rows 0..n−1 and row n of the mixing matmul."""
        out = einsum("ij,pjhw->pihw", self.mixing, field)
        return self.sigma_s * out[:, : self.n_theta], self.sigma_s * out[:, self.n_theta]

    def step(self, q):
        """(Q_{k+1}, I_{k+1}, L_k) from Q_k."""
        field = self.transport(q)
        q_next, image = self.scatter(field)
        return q_next, image, field

    def __call__(self, q):
        return self.scatter(self.transport(q))


class PlaneRenderer(AbstractRenderer):
    """The paper's 2-D model (:class:`~lightfield_jax.forward.base.AbstractRenderer`,
    whose call signature and outputs it has): ``Renderer(grid, illumination, bounces,
    phase="paper", *, tail=None, tail_tol=1e-4, tail_max_steps=500,
    coarse_after=None)``; ``grid.n_theta`` must be set (:meth:`~lightfield_jax.Grid.resolve`).
    Its coarse grid (``coarse_after``) is :func:`coarse_plane_grid`'s. Public as
    ``Renderer``."""

    nodes: dict
    node_angle: Float[Array, " nodes"]
    tables: dict
    circulant: Array
    # Where the unscattered fluence factors as u_p(across)·f(along) (see
    # :func:`~lightfield_jax.forward.first_scatter.separable_source`): the axis f varies
    # along ("x" or "y", else None), u, and the pattern and row (column) where f is read
    # off the fluence (the largest u).
    separable: str | None = eqx.field(static=True)
    across: Array | None
    along_at: tuple[int, int] | None = eqx.field(static=True)
    # > 0: the grid is periodic in y (the stripe cell, :mod:`lightfield_jax.forward.cell`)
    periods: int = eqx.field(static=True, default=0)

    def __init__(
        self,
        grid: Grid,
        illumination: Illumination,
        bounces: int,
        phase: str = "paper",
        *,
        tail: str | None = None,
        tail_tol: float = 1e-4,
        tail_max_steps: int = 500,
        coarse_after: int | None = None,
        moments=None,
    ):
        self._setup(
            grid,
            illumination,
            bounces,
            phase,
            tail,
            tail_tol,
            tail_max_steps,
            coarse_after,
            moments,
            basis=True,
        )
        Medium(1.0, 0.5, 0.0, phase)  # validates the phase name
        theta0 = math.radians(illumination.direction_deg)
        nodes = kernel_nodes(self.width, self.height, grid.n_theta)
        self.nodes = {k: jnp.asarray(v) for k, v in nodes.items() if k not in ("phi", "dr")}
        self.node_angle = jnp.asarray(nodes["phi"] - theta0)
        self.tables = transport_tables(theta_groups(grid.n_theta))
        j = np.arange(grid.n_theta)
        self.circulant = jnp.asarray((j[:, None] - j[None, :]) % grid.n_theta, dtype=jnp.int32)
        split = separable_source(self.coverage, self.mean_depth, self.var_depth)
        self.separable = None if split is None else split[0]
        self.across = None if split is None else jnp.asarray(split[1])
        self.along_at = (
            None
            if split is None
            else tuple(int(i) for i in np.unravel_index(np.argmax(split[1]), split[1].shape))
        )

    @property
    def direct_depth(self) -> float:
        return 1.0

    @property
    def image_scale(self) -> float:
        # Per-pixel coefficients on the refined grid are σ/f and its unit irradiance is
        # f times ours: images scale by f, light fields by 1.
        return self.refine

    @property
    def field_scale(self) -> float:
        return 1.0

    def integrate(self, field):
        return field

    def _convolve(self, source, kernels):
        """source (P, H, W) ⊛ kernels (J, 2H, 2W) → (P, J, H, W): by two matrix products
        where the source is separable (:func:`convolve_separable`; f read off the
        source where u is largest), else by FFTs."""
        if self.separable is None:
            return convolve_kernels(source, kernels)
        p, a = self.along_at
        across = self.across.astype(source.dtype)
        if self.separable == "x":
            return convolve_separable(across, source[p, a, :] / across[p, a], kernels)
        along = source[p, :, a] / across[p, a]
        out = convolve_separable(across, along, jnp.swapaxes(kernels, -1, -2))
        return jnp.swapaxes(out, -1, -2)

    def coarse_grid(self, grid: Grid) -> Grid | None:
        return coarse_plane_grid(grid)

    def restrict(self, q):
        """Q of the working grid (P, n, fH, fW) on the native grid: summed over each
        pixel's f×f cells (σ per working cell is σ/f, so Q per pixel is f times their
        mean)."""
        f = self.refine
        return f * block_mean(q, f, (-2, -1))

    def bounce_step(self, sigma_t, sigma_s, g) -> BounceStep:
        return self._step(sigma_t, sigma_s, self._phase_parts(g)[2])

    def coarse_step(self, sigma_t, sigma_s, g) -> BounceStep:
        """This renderer's own step at σ per native pixel: the coarse grid has the same
        θ bins, so the same transport tables and mixing matrix, and the step takes the
        grid from its source's shape."""
        f = self.refine
        return self.bounce_step(sigma_t * f, sigma_s * f, g)

    def _step(self, sigma_t, sigma_s, mixing) -> BounceStep:
        return BounceStep(sigma_t, sigma_s, mixing, self.tables, self.n_theta, self.periods)

    def first_orders(self, sigma_t, sigma_s, g, source, scattered: bool) -> FirstOrders:
        p_camera, node_p, mixing = self._phase_parts(g)
        image = sigma_s * p_camera * source
        if not scattered:
            return FirstOrders(image)
        kernel = first_scatter_kernel(
            self.nodes, node_p, sigma_t, self.n_theta, self.height, self.width
        )
        # Clipped at 0: FFT round-off leaves values about 1e-7 of the maximum below it,
        # which would break logarithms and 1/model weights downstream.
        l1 = sigma_s * jnp.maximum(self._convolve(source, kernel), 0.0)
        step = self._step(sigma_t, sigma_s, mixing)
        q2, i2 = step.scatter(l1)
        return FirstOrders(image, step, i2, l1, q2)

    def _phase_parts(self, g):
        """What g changes in a render: p(π/2) (the camera), p at the first-scatter
        kernel's nodes, and the mixing matrix (rows 0..n−1: the in-plane redistribution
        Q/σs, row n: the camera I/σs)."""
        dtype = g.dtype
        n = self.n_theta
        dtheta = 2 * math.pi / n
        p_camera = phase_function(jnp.asarray(math.pi / 2, dtype), g)
        taps = _phase_matrix_taps(g, n)
        node_p = phase_function(self.node_angle.astype(dtype), g)
        if self.phase == "normalized":
            in_plane = jnp.sum(taps) * dtheta
            taps = taps / in_plane
            node_p = node_p / in_plane  # the camera keeps p(π/2) (docs/model.md §2)
        mixing = jnp.concatenate(
            [taps[self.circulant] * dtheta, jnp.full((1, n), p_camera * dtheta, dtype)], axis=0
        )
        return p_camera, node_p, mixing

    def _march_g_slope(self, sigma_t, sigma_s, g, gain):
        """The slope along g in about the cost of one render of twice the patterns,
        and, unlike ``jax.jvp``, in one copy of the render's code (half the XLA compile
        of a JVP).

        g enters a render only through the phase function (the camera's p(π/2), the
        first-scatter kernel's node values and the mixing matrix); the unscattered
        light, the FFT convolution and the transport are linear in what g changes and
        do not depend on it. So the tangent travels beside the primal as extra
        patterns through the same convolution and transport, and only the small
        phase-function pieces are differentiated (by ``jax.jvp``)."""
        if self.coarse_after is not None:  # the march's later bounces are the coarse grid's
            return self._march_g_jvp(sigma_t, sigma_s, g, gain)
        n = self.n_theta
        groups = theta_groups(n)
        count_trace()
        source = self.unscattered(sigma_t)
        (p_camera, node_p, mixing), (dp_camera, dnode_p, dmixing) = jax.jvp(
            self._phase_parts, (g,), (jnp.ones_like(g),)
        )
        n_pat = source.shape[0]
        # I_1 of the primal's patterns, then of the tangent's: (1, 2·patterns, H, W).
        bounces = [sigma_s * jnp.concatenate([p_camera * source, dp_camera * source])[None]]
        if self.bounces > 1:
            # The kernel is linear in the node values: K and dK/dg in one scatter, and
            # L_1, dL_1/dg in one convolution (2n kernels of one source).
            kernels = jax.vmap(
                lambda p: first_scatter_kernel(self.nodes, p, sigma_t, n, self.height, self.width)
            )(jnp.stack([node_p, dnode_p]))
            both = sigma_s * self._convolve(source, kernels.reshape((-1,) + kernels.shape[2:]))
            # (2·patterns, n, H, W): the primal's patterns, then the tangent's (the
            # primal clipped at 0 as in a render, the tangent as jax.jvp gives it).
            l1 = both[:, :n]
            field = jnp.concatenate([jnp.maximum(l1, 0.0), jnp.where(l1 > 0, both[:, n:], 0.0)])
            # d(M·L) = dM·L + M·dL: one matmul for the primal, one for the tangent.
            tangent_mixing = jnp.concatenate([dmixing, mixing], axis=1)

            def scatter(field):
                fl, dfl = field[:n_pat], field[n_pat:]
                out = einsum("ij,pjhw->pihw", mixing, fl)
                dout = einsum("ij,pjhw->pihw", tangent_mixing, jnp.concatenate([fl, dfl], axis=1))
                both = sigma_s * jnp.concatenate([out, dout], axis=0)
                return both[:, :n], both[:, n]

            q, image = scatter(field)
            bounces.append(image[None])

            def bounce(q, _):
                q_next, image = scatter(transport(q, sigma_t, groups, self.tables, self.periods))
                return q_next, image

            if self.bounces > 2:
                bounces.append(jax.lax.scan(bounce, q, None, length=self.bounces - 2)[1])
        # (K, 2·patterns, H, W) → (patterns, K, H, W) each
        both = gain * jnp.moveaxis(jnp.concatenate(bounces, axis=0), 0, 1)
        return both[:n_pat], both[n_pat:]


# The plane's renderer under its public name.
Renderer = PlaneRenderer
