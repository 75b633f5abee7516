"""The bounce-by-bounce renderer: per-bounce images I_k and light fields L_k (docs/model.md §4).

Scheme (docs/model.md §4 says why):

- I_1 is exact: σs·p(π/2)·S with S the pixel-averaged unscattered fluence.
- L_1 is semi-analytic: S convolved with a per-direction-bin kernel
  (:mod:`lightfield_jax.forward.first_scatter`), so the thin beam never smears on the grid.
- From the second bounce on, L_k = T[Q_k] on the (x, y, θ) grid
  (:mod:`lightfield_jax.forward.transport`), with Q_k = σs·∫ p(θ − θ') L_{k−1}(θ') dθ' as one
  matmul with the bin-averaged circulant phase matrix; the camera sum
  I_k = σs·p(π/2)·Σ_θ L_{k−1}·Δθ is one more output row of the same matmul.
- Bounces are a ``lax.scan``; light fields are stacked only on request.

Images are in units of the source (unit irradiance) times the gain; light fields are
radiance per radian, averaged over each pixel and each direction bin.
"""

from __future__ import annotations

import functools
import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from lightfield_jax.forward.first_scatter import (
    convolve_first_scatter,
    convolve_kernels,
    first_scatter_kernel,
    kernel_nodes,
)
from lightfield_jax.forward.tail import (
    TailNotConvergedWarning,
    TailSolution,
    check_tail,
    solve_tail,
)
from lightfield_jax.forward.transport import direction_groups, transport, transport_tables
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import Illumination, Stripes, scaled, source_moments
from lightfield_jax.scene.medium import (
    Medium,
    bounces_for_tolerance,
    phase_function,
    phase_integral,
)

# Sub-samples per bin of the triangle-weighted bin average of p (phase matrix).
_PHASE_SUBSAMPLES = 16
# Explicit bounces ``bounces="auto"`` keeps when a tail solve sums the rest.
EXPLICIT_WITH_TAIL = 4


_TRACES = {"renderer": 0}


def _count_trace() -> None:
    """Called once per trace of :meth:`Renderer.__call__` (a Python side effect that
    runs at trace time only): tests use it to prove new values never recompile."""
    _TRACES["renderer"] += 1


def trace_count() -> int:
    """How many times the renderer has been traced (compiled) in this process."""
    return _TRACES["renderer"]


class DivergentSeriesWarning(RuntimeWarning):
    """The bounce series of the ``paper`` phase convention diverges (ρ = ω·A(g) ≥ 1)."""


@functools.lru_cache(maxsize=8)
def _groups(n_theta: int):
    return direction_groups(n_theta)


def _phase_matrix_taps(g, n_theta: int):
    """c_m = bin-pair average of p at bin offset m: (1/Δθ²)∫_{bin j}∫_{bin j'} p(θ − θ') dθ dθ'."""
    n = _PHASE_SUBSAMPLES
    dtheta = 2 * math.pi / n_theta
    dtype = jnp.result_type(g)
    fine = phase_function((jnp.arange(n_theta * n) * (dtheta / n)).astype(dtype), g)
    s = np.arange(-n, n + 1)
    weights = (1.0 - np.abs(s) / n) / n
    taps = (np.arange(n_theta)[:, None] * n + s[None, :]) % (n_theta * n)
    return jnp.sum(fine[taps] * weights.astype(dtype), axis=1)


def as_physical(sigma_t, sigma_s, g, gain):
    """(σt, σs, g, gain) as arrays of one floating dtype. Python scalars would be static
    under ``filter_jit`` (a recompile per value): every physical value becomes an array."""
    values = [jnp.asarray(v) for v in (sigma_t, sigma_s, g, gain)]
    dtype = jnp.result_type(*values[:3])
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    return tuple(v.astype(dtype) for v in values)


def render_refined(model, values, lightfield: bool, image_scale, field_scale):
    """``model._render`` on its refined working grid (σ/f per refined pixel), then f×f
    blocks averaged back, images × ``image_scale``, light fields × ``field_scale``.
    A model with a tail returns ``(images, fields, tail)``, the tail refined alike."""
    sigma_t, sigma_s, g, gain = as_physical(*values)
    f = model.refine
    out = model._render(sigma_t / f, sigma_s / f, g, gain, lightfield)
    if f == 1:
        return out
    images = image_scale * _block_mean(out[0], f, (-2, -1))
    fields = None if out[1] is None else field_scale * _block_mean(out[1], f, (-3, -2))
    if len(out) == 2:
        return images, fields
    tail = out[2]
    return (
        images,
        fields,
        TailSolution(
            image=image_scale * _block_mean(tail.image, f, (-2, -1)),
            lightfield=None
            if tail.lightfield is None
            else field_scale * _block_mean(tail.lightfield, f, (-3, -2)),
            steps=tail.steps,
            converged=tail.converged,
        ),
    )


def _log_sinhc(x):
    """log(sinh(x)/x) for x ≥ 0, stable for small and large x (and its derivative)."""
    small = x < 0.5
    xl = jnp.where(small, 1.0, x)  # no log(0) in the branch not taken
    large = xl + jnp.log1p(-jnp.exp(-2.0 * xl)) - jnp.log(2.0 * xl)
    x2 = x * x
    return jnp.where(small, x2 / 6.0 - x2 * x2 / 180.0 + x2 * x2 * x2 / 2835.0, large)


def unscattered_fluence(model, sigma_t):
    """The pixel-averaged unscattered fluence (patterns, H, W) of a renderer's source
    moments (see :func:`source_moments`): coverage·e^{−σt·mean}·sinh(x)/x with
    x = σt·√(3·var), the exact average of e^{−σt d} over d uniform on an interval of that
    mean and variance (the case of every pixel of an axis-aligned sheet). It agrees with
    the cumulant form exp(−σt·mean + σt²·var/2) to second order and, unlike it, stays
    exact for dense media (σt of several per pixel)."""
    dtype = sigma_t.dtype
    mean = model.mean_depth.astype(dtype)
    var = jnp.maximum(model.var_depth.astype(dtype), 0.0)
    x = sigma_t * jnp.sqrt(3.0 * var)
    return model.coverage.astype(dtype) * jnp.exp(-sigma_t * mean + _log_sinhc(x))


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

    def transport(self, q):
        """L = T[Q] on the grid (:func:`lightfield_jax.forward.transport.transport`)."""
        return transport(q, self.sigma_t, _groups(self.n_theta), self.tables)

    def scatter(self, field):
        """(Q_next, image) of a light field: rows 0..n−1 and row n of the mixing matmul."""
        out = jnp.einsum("ij,pjhw->pihw", self.mixing, field)
        return self.sigma_s * out[:, : self.n_theta], self.sigma_s * out[:, self.n_theta]

    def __call__(self, q):
        return self.scatter(self.transport(q))


class Renderer(eqx.Module):
    """A compiled forward model for one grid, illumination and bounce count.

    Construction precomputes every static table (source moments, kernel quadrature,
    sweep stencils); calling it with (σt, σs, g, gain) runs one jit-compiled function
    in which those values are traced, so new values never recompile.

    Call signature: ``renderer(sigma_t, sigma_s, g, gain=1.0, lightfield=False)``
    returns ``(images, lightfields)``: images Float[Array, "patterns bounces H W"]
    (index k−1 holds I_k) and, when requested, lightfields
    Float[Array, "bounces+1 patterns H W n_theta"] (L_0..L_K), else ``None``.

    With ``tail`` (``"gmres"`` or ``"bicgstab"``) the first ``bounces`` = K0 orders stay
    explicit and exact as above, and the rest of the series Σ_{k>K0} comes from one
    Krylov solve (:mod:`lightfield_jax.forward.tail`, relative tolerance ``tail_tol``, at most
    ``tail_max_steps`` iterations): the call returns ``(images, lightfields, tail)``
    with ``tail`` a :class:`~lightfield_jax.forward.tail.TailSolution` (tail image
    "patterns H W", its light field "patterns H W n_theta" or ``None``, the solver's
    steps and whether it converged). The image of all orders is
    ``images.sum(axis=1) + tail.image``.
    """

    height: int = eqx.field(static=True)  # of the (refined) working grid
    width: int = eqx.field(static=True)
    n_theta: int = eqx.field(static=True)
    refine: int = eqx.field(static=True)
    bounces: int = eqx.field(static=True)
    phase: str = eqx.field(static=True)
    theta0_bin: int = eqx.field(static=True)
    tail: str | None = eqx.field(static=True)
    tail_tol: float = eqx.field(static=True)
    tail_max_steps: int = eqx.field(static=True)
    coverage: Float[Array, "patterns H W"]
    mean_depth: Float[Array, "patterns H W"]
    var_depth: Float[Array, "patterns H W"]
    nodes: dict
    node_angle: Float[Array, " nodes"]
    tables: dict
    circulant: Array

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
    ):
        if grid.n_theta is None:
            raise ValueError("Renderer needs grid.n_theta: call Grid.resolve(g) first")
        if not isinstance(bounces, (int, np.integer)) or isinstance(bounces, bool) or bounces < 1:
            raise ValueError(f"bounces: must be an integer >= 1, got {bounces!r}")
        Medium(1.0, 0.5, 0.0, phase)  # validates the phase name
        check_tail(tail, tail_tol, tail_max_steps)
        self.tail, self.tail_tol, self.tail_max_steps = tail, float(tail_tol), int(tail_max_steps)
        f = self.refine = 1 if grid.refine is None else grid.refine
        self.height, self.width, self.n_theta = grid.height * f, grid.width * f, grid.n_theta
        self.bounces = int(bounces)
        self.phase = phase
        illumination.entry_wall(grid.width, grid.height)  # validates the entry point
        cov, mean, var = source_moments(scaled(illumination, f), self.width, self.height)
        self.coverage = jnp.asarray(cov)
        self.mean_depth = jnp.asarray(mean)
        self.var_depth = jnp.asarray(var)
        theta0 = math.radians(illumination.direction_deg)
        self.theta0_bin = int(round(theta0 / grid.dtheta)) % grid.n_theta
        nodes = kernel_nodes(self.width, self.height, grid.n_theta)
        self.nodes = {k: jnp.asarray(v) for k, v in nodes.items() if k not in ("phi", "dr")}
        self.node_angle = jnp.asarray(nodes["phi"] - theta0)
        self.tables = transport_tables(_groups(grid.n_theta))
        j = np.arange(grid.n_theta)
        self.circulant = jnp.asarray((j[:, None] - j[None, :]) % grid.n_theta, dtype=jnp.int32)

    @property
    def n_patterns(self) -> int:
        return self.coverage.shape[0]

    def __call__(self, sigma_t, sigma_s, g, gain=1.0, lightfield: bool = False):
        # Per-pixel coefficients on the refined grid are σ/f and its unit irradiance is
        # f times ours: images scale by f, light fields by 1.
        return render_refined(self, (sigma_t, sigma_s, g, gain), lightfield, self.refine, 1)

    def bounce_step(self, sigma_t, sigma_s, g) -> BounceStep:
        """The one-bounce operator Q_k ↦ (Q_{k+1}, I_{k+1}) at these values, on the
        working grid (σ per working pixel: divide by ``refine`` first)."""
        return self._step(sigma_t, sigma_s, self._phase_parts(g)[2])

    def _step(self, sigma_t, sigma_s, mixing) -> BounceStep:
        return BounceStep(sigma_t, sigma_s, mixing, self.tables, self.n_theta)

    @eqx.filter_jit
    def _render(self, sigma_t, sigma_s, g, gain, lightfield: bool):
        dtype = sigma_t.dtype
        n = self.n_theta
        dtheta = 2 * math.pi / n

        _count_trace()
        source = unscattered_fluence(self, sigma_t)
        p_camera, node_p, mixing = self._phase_parts(g)
        step = self._step(sigma_t, sigma_s, mixing)
        # With a tail one more bounce is marched: its source Q_{K0+1} and image I_{K0+1}
        # seed the tail's solve.
        march = self.bounces + (self.tail is not None)

        images = [sigma_s * p_camera * source]
        fields = []
        if lightfield:
            l0 = jnp.zeros((source.shape[0], n) + source.shape[1:], dtype)
            fields.append(l0.at[:, self.theta0_bin].set(source / dtheta))
        if march > 1 or lightfield:
            kernel = first_scatter_kernel(self.nodes, node_p, sigma_t, n, self.height, self.width)
            l1 = sigma_s * convolve_first_scatter(source, kernel)
            if lightfield:
                fields.append(l1)
        images = [jnp.stack(images)]
        fields = [jnp.stack(fields)] if lightfield else []
        if march > 1:
            q, image = step.scatter(l1)
            images.append(image[None])

            def bounce(q, _):
                field = step.transport(q)
                q_next, image = step.scatter(field)
                return q_next, (image, field if lightfield else None)

            if march > 2:
                q, (more, more_fields) = jax.lax.scan(bounce, q, None, length=march - 2)
                images.append(more)
                if lightfield:
                    fields.append(more_fields)
            if lightfield and self.tail is None:
                fields.append(step.transport(q)[None])  # L_K0
        images = jnp.concatenate(images, axis=0)
        stacked = gain * jnp.moveaxis(images[: self.bounces], 0, 1)
        lf = gain * jnp.moveaxis(jnp.concatenate(fields, axis=0), 2, -1) if lightfield else None
        if self.tail is None:
            return stacked, lf
        tail = solve_tail(
            step, q, images[-1], self.tail, self.tail_tol, self.tail_max_steps, lightfield
        )
        return (
            stacked,
            lf,
            TailSolution(
                image=gain * tail.image,
                lightfield=None
                if tail.lightfield is None
                else gain * jnp.moveaxis(tail.lightfield, 1, -1),
                steps=tail.steps,
                converged=tail.converged,
            ),
        )

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

    def images_and_g_slope(self, sigma_t, sigma_s, g, gain=1.0):
        """Per-bounce images and their derivative in g, ``(images, d images/dg)``, each
        Float[Array, "patterns bounces H W"]: the forward-mode derivative along g in
        about the cost of one render of twice the patterns, and, unlike ``jax.jvp``,
        in one copy of the render's code (half the XLA compile of a JVP).

        g enters a render only through the phase function (the camera's p(π/2), the
        first-scatter kernel's node values and the mixing matrix); the unscattered
        light, the FFT convolution and the transport are linear in what g changes and
        do not depend on it. So the tangent travels beside the primal as extra
        patterns through the same convolution and transport, and only the small
        phase-function pieces are differentiated (by ``jax.jvp``)."""
        if self.tail is not None:
            raise ValueError(
                f"images_and_g_slope: per-bounce images only; this renderer has tail "
                f"{self.tail!r} (use jax.jvp through the call)"
            )
        sigma_t, sigma_s, g, gain = as_physical(sigma_t, sigma_s, g, gain)
        f = self.refine
        images, slopes = self._render_g_slope(sigma_t / f, sigma_s / f, g, gain)
        if f == 1:
            return images, slopes
        return f * _block_mean(images, f, (-2, -1)), f * _block_mean(slopes, f, (-2, -1))

    @eqx.filter_jit
    def _render_g_slope(self, sigma_t, sigma_s, g, gain):
        n = self.n_theta
        groups = _groups(n)
        _count_trace()
        source = unscattered_fluence(self, sigma_t)
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
            both = sigma_s * convolve_kernels(source, kernels.reshape((-1,) + kernels.shape[2:]))
            # (2·patterns, n, H, W): the primal's patterns, then the tangent's (the
            # primal clipped at 0 as in a render, the tangent as jax.jvp gives it).
            l1 = both[:, :n]
            field = jnp.concatenate([jnp.maximum(l1, 0.0), jnp.where(l1 > 0, both[:, n:], 0.0)])
            # d(M·L) = dM·L + M·dL: one matmul for the primal, one for the tangent.
            tangent_mixing = jnp.concatenate([dmixing, mixing], axis=1)

            def scatter(field):
                fl, dfl = field[:n_pat], field[n_pat:]
                out = jnp.einsum("ij,pjhw->pihw", mixing, fl)
                dout = jnp.einsum(
                    "ij,pjhw->pihw", tangent_mixing, jnp.concatenate([fl, dfl], axis=1)
                )
                both = sigma_s * jnp.concatenate([out, dout], axis=0)
                return both[:, :n], both[:, n]

            q, image = scatter(field)
            bounces.append(image[None])

            def bounce(q, _):
                q_next, image = scatter(transport(q, sigma_t, groups, self.tables))
                return q_next, image

            if self.bounces > 2:
                bounces.append(jax.lax.scan(bounce, q, None, length=self.bounces - 2)[1])
        # (K, 2·patterns, H, W) → (patterns, K, H, W) each
        both = gain * jnp.moveaxis(jnp.concatenate(bounces, axis=0), 0, 1)
        return both[:n_pat], both[n_pat:]


def _block_mean(a, f: int, axes: tuple[int, int]):
    """Average f×f blocks over two adjacent axes."""
    ay, ax = (ax_ % a.ndim for ax_ in axes)
    shape = a.shape[:ay] + (a.shape[ay] // f, f, a.shape[ax] // f, f) + a.shape[ax + 1 :]
    return a.reshape(shape).mean(axis=(ay + 1, ay + 3))


class RenderResult(eqx.Module):
    """What :func:`render` returns.

    Attributes:
        images: per-bounce images, index k−1 holds I_k: Float[Array, "K H W"] for a
            beam or full illumination, Float[Array, "patterns K H W"] for stripes.
        lightfields: L_0..L_K (radiance per radian), Float[Array, "K+1 H W n_theta"]
            (``"patterns K+1 H W n_theta"`` for stripes), or ``None``.
        bounces: K.
        n_theta: number of direction bins used.
        refine: spatial refinement of the working grid used.
        rho: ω·A(g) (paper) or ω (normalized), the per-bounce energy ratio bound.
        converges: whether the bounce series converges (ρ < 1).
        tail: with a tail solve, Σ_{k>K} I_k in the layout of one image ("H W" or
            "patterns H W"), else ``None``.
        tail_lightfield: Σ_{k>K} L_k ("H W n_theta" or "patterns H W n_theta") when a
            tail and light fields were requested, else ``None``.
        tail_method: the tail's solver (``"gmres"``, ``"bicgstab"``) or ``None``.
        tail_steps: the tail solver's iterations, or ``None``.
        tail_converged: whether the tail solve met its tolerance (``None``: no tail).
    """

    images: Array
    lightfields: Array | None
    bounces: int = eqx.field(static=True)
    n_theta: int = eqx.field(static=True)
    refine: int = eqx.field(static=True)
    rho: Float[Array, ""]
    converges: bool = eqx.field(static=True)
    tail: Array | None = None
    tail_lightfield: Array | None = None
    tail_method: str | None = eqx.field(static=True, default=None)
    tail_steps: int | None = eqx.field(static=True, default=None)
    tail_converged: bool | None = eqx.field(static=True, default=None)

    @property
    def total(self) -> Array:
        """Σ_k I_k (the image a camera sees): the K explicit bounces plus the tail."""
        total = jnp.sum(self.images, axis=-3)
        return total if self.tail is None else total + self.tail


def make_renderer(
    grid: Grid,
    illumination: Illumination,
    bounces: int,
    phase: str,
    geometry=None,
    *,
    tail: str | None = None,
    tail_tol: float = 1e-4,
    tail_max_steps: int = 500,
):
    """The compiled forward model of a scene: a :class:`Renderer` for the plane (the
    paper's 2-D model, ``geometry`` ``None`` or :class:`~lightfield_jax.Plane`) or a
    :class:`~lightfield_jax.SlabRenderer` for a :class:`~lightfield_jax.Slab`. Both
    have the same call signature and outputs; ``grid`` (and the slab's ``n_mu``) must
    be resolved. ``tail`` (plane only): the orders after ``bounces`` from one Krylov
    solve (see :class:`Renderer`)."""
    from lightfield_jax.forward.slab import Plane, Slab, SlabRenderer

    if isinstance(geometry, Slab):
        if tail is not None:
            raise ValueError(f"tail: {tail!r} is not available for the slab geometry yet")
        return SlabRenderer(grid, illumination, bounces, geometry, phase)
    if geometry is not None and not isinstance(geometry, Plane):
        raise ValueError(f"geometry: must be None, a Plane or a Slab, got {geometry!r}")
    return Renderer(
        grid,
        illumination,
        bounces,
        phase,
        tail=tail,
        tail_tol=tail_tol,
        tail_max_steps=tail_max_steps,
    )


@functools.lru_cache(maxsize=16)
def renderer_for(
    grid: Grid,
    illumination: Illumination,
    bounces: int,
    phase: str,
    geometry=None,
    tail: str | None = None,
    tail_tol: float = 1e-4,
    tail_max_steps: int = 500,
) -> Renderer:
    """A cached renderer (its tables are built once per static configuration)."""
    return make_renderer(
        grid,
        illumination,
        bounces,
        phase,
        geometry,
        tail=tail,
        tail_tol=tail_tol,
        tail_max_steps=tail_max_steps,
    )


def resolve_model(medium: Medium, grid: Grid, geometry=None):
    """``(grid, geometry, rho)`` with the discretisation filled in from g: the plane's
    defaults (:meth:`Grid.resolve`) or the slab's (:func:`resolve_slab_grid`), and ρ
    the per-bounce energy ratio bound (the slab's 3-D phase function is normalised on
    the sphere: ρ = ω)."""
    from lightfield_jax.forward.slab import Plane, Slab, resolve_slab_grid, rho_bound

    g = float(medium.g)
    if isinstance(geometry, Slab):
        grid, geometry = resolve_slab_grid(
            grid, geometry, g, float(medium.sigma_t), float(medium.albedo)
        )
        return grid, geometry, rho_bound(medium, geometry)
    if geometry is not None and not isinstance(geometry, Plane):
        raise ValueError(f"geometry: must be a Plane or a Slab, got {geometry!r}")
    return grid.resolve(g), None, rho_bound(medium)


def resolve_bounces(
    rho: float, bounces: int | str, tolerance: float = 1e-4, tail: str | None = None
) -> int:
    """An explicit bounce count, or ``"auto"``: the tail bound ρ^K/(1 − ρ) ≤ tolerance,
    with ρ the model's per-bounce energy ratio bound (see :func:`resolve_model`); with a
    ``tail`` solve, at most :data:`EXPLICIT_WITH_TAIL` of them (the solve does the rest)."""
    if isinstance(bounces, str):
        if bounces != "auto":
            raise ValueError(f"bounces: must be a positive integer or 'auto', got {bounces!r}")
        if tail is not None:
            if rho >= 1.0:
                return EXPLICIT_WITH_TAIL  # refused by the caller with the reason
            return min(bounces_for_tolerance(float(rho), tolerance, math.inf), EXPLICIT_WITH_TAIL)
        return bounces_for_tolerance(float(rho), tolerance)
    if not isinstance(bounces, (int, np.integer)) or isinstance(bounces, bool) or bounces < 1:
        raise ValueError(f"bounces: must be a positive integer or 'auto', got {bounces!r}")
    return int(bounces)


def render(
    medium: Medium,
    grid: Grid,
    illumination: Illumination,
    bounces: int | str = "auto",
    *,
    tolerance: float = 1e-4,
    gain=1.0,
    lightfield: bool = False,
    geometry=None,
    tail: str | None = None,
    tail_tol: float = 1e-4,
    tail_max_steps: int = 500,
) -> RenderResult:
    """Render per-bounce images (and optionally light fields) of a scene.

    Args:
        medium: the medium (σt, σs, g per pixel; phase convention).
        grid: the grid; ``n_theta=None`` picks it from g.
        illumination: :class:`Beam`, :class:`Stripes` or :class:`Full`.
        bounces: K, or ``"auto"`` for the smallest K whose tail bound is below
            ``tolerance`` (refused with ``ValueError`` when ρ ≥ 1).
        gain: source gain c multiplying every image.
        lightfield: also return L_0..L_K.
        geometry: ``None`` or :class:`~lightfield_jax.Plane` (the paper's 2-D model) or
            a :class:`~lightfield_jax.Slab` (the tank's depth in 3-D, docs/model.md §7: the
            3-D Henyey–Greenstein phase function whatever ``medium.phase`` says; light
            fields are integrated over depth and elevation).
        tail: ``None`` (the series stops after K bounces), or ``"gmres"`` /
            ``"bicgstab"``: the K bounces stay explicit and the rest of the series,
            Σ_{k>K}, comes from one Krylov solve (plane only; ``bounces="auto"`` then
            keeps at most :data:`EXPLICIT_WITH_TAIL` explicit bounces). The result's
            ``tail`` holds its image and ``total`` includes it.
        tail_tol: the tail solve's relative residual tolerance (GMRES: the tail's error
            stayed below it in the measurements; BiCGStab's ran up to 26× above it when
            the scene's per-bounce ratio approaches 1: see docs/tail_acceleration.md).
        tail_max_steps: the most iterations the tail solve may take.

    Under ``phase="paper"`` with ρ ≥ 1 an explicit K still renders, the result has
    ``converges=False`` and a :class:`DivergentSeriesWarning` is issued; a tail is
    refused there (``ValueError``: the series it would sum diverges). A tail solve that
    stops before its tolerance gives ``tail_converged=False`` and a
    :class:`~lightfield_jax.forward.tail.TailNotConvergedWarning`.
    """
    grid, geometry, rho = resolve_model(medium, grid, geometry)
    k = resolve_bounces(float(rho), bounces, tolerance, tail)
    converges = bool(rho < 1.0)
    if tail is not None and not converges:
        raise ValueError(
            f"tail: rho = albedo*A(g) = {float(rho):.4f} >= 1: the bounce series diverges "
            "and has no tail to sum; use phase: normalized or tail: None"
        )
    if not converges:
        warnings.warn(
            f"rho = albedo*A(g) = {float(rho):.4f} >= 1: the bounce series of the 'paper' "
            f"phase convention does not converge; the {k} rendered bounces are a truncation "
            "of a divergent series",
            DivergentSeriesWarning,
            stacklevel=2,
        )
    renderer = renderer_for(
        grid, illumination, k, medium.phase, geometry, tail, tail_tol, tail_max_steps
    )
    images, fields, *solved = renderer(medium.sigma_t, medium.sigma_s, medium.g, gain, lightfield)
    extra = {}
    if solved:
        extra = _tail_entries(solved[0], tail, tail_tol, not isinstance(illumination, Stripes))
    if not isinstance(illumination, Stripes):
        images = images[0]
        fields = fields[:, 0] if fields is not None else None
    elif fields is not None:
        fields = jnp.moveaxis(fields, 1, 0)  # pattern-major, like the images
    return RenderResult(
        images=images,
        lightfields=fields,
        bounces=k,
        n_theta=grid.n_theta,
        refine=grid.refine,
        rho=rho,
        converges=converges,
        **extra,
    )


def _tail_entries(solved: TailSolution, method: str, tol: float, single: bool) -> dict:
    """A tail solution's :class:`RenderResult` fields; warns when it did not converge."""
    converged = bool(solved.converged)
    steps = int(solved.steps)
    if not converged:
        warnings.warn(
            f"tail: the {method} solve stopped after {steps} iterations before its "
            f"tolerance {tol:g}: the tail image is its last iterate, not a solution",
            TailNotConvergedWarning,
            stacklevel=3,
        )
    image, field = solved.image, solved.lightfield
    if single:
        image = image[0]
        field = None if field is None else field[0]
    return dict(
        tail=image,
        tail_lightfield=field,
        tail_method=method,
        tail_steps=steps,
        tail_converged=converged,
    )


def single_scatter_closed_form(
    sigma_t: float, sigma_s: float, g: float, width: int
) -> Float[np.ndarray, " W"]:
    """I_1 along a unit beam heading +x from the left wall, pixel-averaged per column
    (docs/model.md §4): σs p(π/2) e^{−σt c} (1 − e^{−σt})/σt."""
    c = np.arange(width)
    p90 = float(phase_function(math.pi / 2, g))
    return sigma_s * p90 * np.exp(-sigma_t * c) * (-np.expm1(-sigma_t)) / sigma_t


__all__ = [
    "BounceStep",
    "DivergentSeriesWarning",
    "EXPLICIT_WITH_TAIL",
    "TailNotConvergedWarning",
    "Renderer",
    "RenderResult",
    "make_renderer",
    "render",
    "renderer_for",
    "resolve_model",
    "resolve_bounces",
    "single_scatter_closed_form",
    "phase_integral",
]
