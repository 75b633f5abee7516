"""Rendering a scene: per-bounce images I_k and light fields L_k (docs/model.md §4, §7).

:func:`render` is the entry point: it resolves the discretisation a medium needs for
its geometry (the plane or a slab, :mod:`lightfield_jax.scene.geometry`), picks the
bounce count, refuses or reports a divergent series, and runs the geometry's compiled
renderer (:func:`make_renderer`: a :class:`~lightfield_jax.forward.plane.PlaneRenderer`,
public as ``Renderer``, or a :class:`~lightfield_jax.forward.slab.SlabRenderer`, both
:class:`~lightfield_jax.forward.base.AbstractRenderer`).
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

from lightfield_jax.checks import (
    check_flag,
    check_int,
    check_number,
    gain_problem,
    number_problem,
)
from lightfield_jax.forward.base import (
    MAX_BOUNCES,
    AbstractRenderer,
    check_bounces,
    coarse_lightfield_refusal,
    trace_count,
)
from lightfield_jax.forward.plane import BounceStep, PlaneRenderer, Renderer, coarse_plane_grid
from lightfield_jax.forward.slab import SlabRenderer
from lightfield_jax.forward.slab_memory import slab_render_bytes
from lightfield_jax.forward.tail import TailNotConvergedWarning, TailSolution, check_tail
from lightfield_jax.runtime.memory import check_memory, render_bytes
from lightfield_jax.scene.geometry import Plane, Slab, as_geometry, paper_bound
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import Beam, Full, Illumination, Stripes, period_problem
from lightfield_jax.scene.medium import Medium, bounces_for_tolerance
from lightfield_jax.scene.phase import phase_function, phase_integral

# Explicit bounces ``bounces="auto"`` keeps when a tail solve sums the rest.
EXPLICIT_WITH_TAIL = 4


class DivergentSeriesWarning(RuntimeWarning):
    """The bounce series of the ``paper`` phase convention diverges (ρ = ω·A(g) ≥ 1)."""


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
        coarse_after: the K0 after which the bounces were marched on the coarse grid, or
            ``None`` where every bounce is the grid's own (none asked, a grid that is
            not refined, or no more than K0 bounces).
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
    coarse_after: int | None = eqx.field(static=True, default=None)

    @property
    def total(self) -> Array:
        """Σ_k I_k (the image a camera sees): the K explicit bounces plus the tail."""
        total = jnp.sum(self.images, axis=-3)
        return total if self.tail is None else total + self.tail


def check_scene(where: str, grid, illumination) -> None:
    """Refuse a grid that is not a :class:`Grid`, an illumination that is not a
    :class:`Beam`, :class:`Stripes` or :class:`Full`, and stripes the grid cannot hold
    (``ValueError("WHERE: KEY: ...")``), before any table is built."""
    if not isinstance(grid, Grid):
        raise ValueError(f"{where}: grid: must be a Grid, got {type(grid).__name__}")
    if not isinstance(illumination, (Beam, Stripes, Full)):
        raise ValueError(
            f"{where}: illumination: must be a Beam, Stripes or Full, got "
            f"{type(illumination).__name__}"
        )
    if (problem := period_problem(illumination, grid.width, grid.height)) is not None:
        raise ValueError(f"{where}: illumination.period: {problem}")


def geometry_renderer(
    geometry: Plane | Slab,
    grid: Grid,
    illumination: Illumination,
    bounces: int,
    phase: str,
    *,
    tail: str | None = None,
    tail_tol: float = 1e-4,
    tail_max_steps: int = 500,
    coarse_after: int | None = None,
) -> AbstractRenderer:
    """The compiled forward model of a geometry (``grid``, and a slab's ``n_mu`` and
    ``n_z``, resolved): a :class:`PlaneRenderer` for a :class:`~lightfield_jax.Plane`,
    a :class:`~lightfield_jax.SlabRenderer` for a :class:`~lightfield_jax.Slab`. The
    scene's geometry is data; the forward layer builds its renderer."""
    options = dict(
        tail=tail, tail_tol=tail_tol, tail_max_steps=tail_max_steps, coarse_after=coarse_after
    )
    if isinstance(geometry, Slab):
        return SlabRenderer(grid, illumination, bounces, geometry, phase, **options)
    if isinstance(geometry, Plane):
        return PlaneRenderer(grid, illumination, bounces, phase, **options)
    raise ValueError(f"geometry: must be None, a Plane or a Slab to render, got {geometry!r}")


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
    coarse_after: int | None = None,
) -> AbstractRenderer:
    """The compiled forward model of a scene, built by
    :func:`geometry_renderer`: a :class:`Renderer` for the plane (the
    paper's 2-D model, ``geometry`` ``None`` or :class:`~lightfield_jax.Plane`) or a
    :class:`~lightfield_jax.SlabRenderer` for a :class:`~lightfield_jax.Slab`. Both
    have the same call signature and outputs; ``grid`` (and the slab's ``n_mu``,
    ``n_z``) must be resolved. ``tail``: the orders after ``bounces`` from one Krylov
    solve; ``coarse_after``: the bounces after it marched on a coarse grid (the plane's;
    see :class:`~lightfield_jax.forward.base.AbstractRenderer`).

    The arguments are checked before the renderer's tables are built (ValueError: a
    grid or illumination of another type, stripes longer than the grid, or tables
    beyond the memory limit of :mod:`lightfield_jax.runtime.memory`)."""
    check_scene("make_renderer", grid, illumination)
    geometry = as_geometry(geometry)
    counted = isinstance(bounces, (int, np.integer)) and not isinstance(bounces, bool)
    if grid.n_theta is not None and grid.refine is not None and counted and bounces >= 1:
        # Before the tables: Grid(30000, 30000, 8, 1) allocated 429 GiB (a MemoryError).
        nbytes = model_memory(
            illumination.n_patterns, grid, geometry, int(bounces), tail=tail is not None
        )
        check_memory(
            nbytes,
            f"make_renderer: the {grid.width}x{grid.height} grid ({grid.n_theta} directions, "
            f"refine {grid.refine}, {bounces} bounces, {illumination.n_patterns} patterns)",
        )
    return geometry_renderer(
        geometry,
        grid,
        illumination,
        bounces,
        phase,
        tail=tail,
        tail_tol=tail_tol,
        tail_max_steps=tail_max_steps,
        coarse_after=coarse_after,
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
    coarse_after: int | None = None,
) -> AbstractRenderer:
    """A cached renderer (its tables are built once per static configuration; not
    checked as :func:`make_renderer`'s arguments are: the fit sizes its own models)."""
    return geometry_renderer(
        as_geometry(geometry),
        grid,
        illumination,
        bounces,
        phase,
        tail=tail,
        tail_tol=tail_tol,
        tail_max_steps=tail_max_steps,
        coarse_after=coarse_after,
    )


def resolve_model(medium: Medium, grid: Grid, geometry=None):
    """``(grid, geometry, rho)`` with the discretisation filled in from g by the
    geometry (:meth:`~lightfield_jax.Plane.resolve_model`: the plane's
    :meth:`Grid.resolve`, or the slab's
    :func:`~lightfield_jax.scene.geometry.resolve_slab_grid`), the geometry as an
    object (``None`` becomes :class:`~lightfield_jax.Plane`) and ρ the per-bounce
    energy ratio bound (the slab's 3-D phase function is normalised on the sphere:
    ρ = ω)."""
    return as_geometry(geometry).resolve_model(medium, grid)


def model_memory(
    n_patterns: int,
    grid: Grid,
    geometry,
    bounces: int,
    lightfield: bool = False,
    tail: bool = False,
) -> int:
    """Bytes a render of ``n_patterns`` illuminations on a resolved ``grid`` needs (an
    upper bound from the sizes alone): a resolved slab's
    :func:`~lightfield_jax.forward.slab_memory.slab_render_bytes` (its kernels, its
    blocks' fields and spectra, the images), else the plane's
    :func:`~lightfield_jax.runtime.memory.render_bytes`."""
    slab = as_geometry(geometry).slab_or_none
    if slab is None or slab.n_mu is None or slab.n_z is None:
        return render_bytes(
            n_patterns,
            grid.height,
            grid.width,
            grid.n_theta,
            refine=grid.refine,
            bounces=bounces,
            lightfield=lightfield,
        )
    return slab_render_bytes(
        n_patterns,
        grid.height,
        grid.width,
        grid.n_theta,
        slab.n_mu,
        slab.n_z,
        slab.depth_coefficients,
        refine=grid.refine,
        bounces=bounces,
        lightfield=lightfield,
        tail=tail,
    )


def render_memory(
    n_patterns: int,
    grid: Grid,
    geometry,
    medium: Medium,
    bounces: int,
    lightfield: bool = False,
    tail: bool = False,
) -> int:
    """:func:`model_memory` of the discretisation the geometry resolves for ``medium``
    (:func:`resolve_model`)."""
    grid, geometry, _ = resolve_model(medium, grid, geometry)
    return model_memory(n_patterns, grid, geometry, bounces, lightfield, tail)


def resolve_bounces(
    rho: float, bounces: int | str, tolerance: float = 1e-4, tail: str | None = None, *, paper=True
) -> int:
    """An explicit bounce count, or ``"auto"``: the tail bound ρ^K/(1 − ρ) ≤ tolerance,
    with ρ the model's per-bounce energy ratio bound (see :func:`resolve_model`; ``paper``:
    it is ω·A(g), :func:`~lightfield_jax.scene.geometry.paper_bound`); with a ``tail``
    solve, at most :data:`EXPLICIT_WITH_TAIL` of them (the solve does the rest)."""
    if isinstance(bounces, str):
        if bounces != "auto":
            raise ValueError(f"bounces: must be a positive integer or 'auto', got {bounces!r}")
        if tail is not None:
            if rho >= 1.0:
                return EXPLICIT_WITH_TAIL  # refused by the caller with the reason
            return min(bounces_for_tolerance(float(rho), tolerance, math.inf), EXPLICIT_WITH_TAIL)
        return bounces_for_tolerance(float(rho), tolerance, paper=paper)
    if number_problem(bounces, integer=True, low=1) is not None:
        raise ValueError(f"bounces: must be a positive integer or 'auto', got {bounces!r}")
    return check_bounces(bounces)


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
    coarse_after: int | None = None,
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
            Σ_{k>K}, comes from one Krylov solve (plane and slab; ``bounces="auto"`` then
            keeps at most :data:`EXPLICIT_WITH_TAIL` explicit bounces). The result's
            ``tail`` holds its image and ``total`` includes it.
        tail_tol: the tail solve's relative residual tolerance (GMRES: the tail's error
            stayed below it in the measurements; BiCGStab's ran up to 26× above it when
            the scene's per-bounce ratio approaches 1: see docs/tail_acceleration.md).
        tail_max_steps: the most iterations the tail solve may take.
        coarse_after: ``None``, or K0: the plane's bounces after K0 are marched on its
            coarse grid (the native grid where ``grid.refine`` > 1: 5e-5 to 6e-4 of the
            peak from the full march, docs/tail_acceleration.md); not with ``tail`` or
            ``lightfield``.

    Under ``phase="paper"`` with ρ ≥ 1 an explicit K still renders, the result has
    ``converges=False`` and a :class:`DivergentSeriesWarning` is issued; a tail is
    refused there (``ValueError``: the series it would sum diverges). A tail solve that
    stops before its tolerance gives ``tail_converged=False`` and a
    :class:`~lightfield_jax.forward.tail.TailNotConvergedWarning`.
    """
    if not isinstance(medium, Medium):
        raise ValueError(f"render: medium: must be a Medium, got {type(medium).__name__}")
    check_scene("render", grid, illumination)
    check_flag(lightfield, "render: lightfield")
    check_number(tolerance, "render: tolerance", low=0.0, high=1.0, low_open=True, high_open=True)
    check_tail(tail, tail_tol, tail_max_steps)
    if isinstance(gain, jax.core.Tracer):  # under jit or grad: its shape only
        if np.ndim(gain) != 0:
            raise ValueError(f"render: gain: must be a single number, got shape {gain.shape}")
    elif (problem := gain_problem(gain)) is not None:
        raise ValueError(f"render: gain: {problem}")
    for name in ("sigma_t", "sigma_s", "g"):
        if isinstance(getattr(medium, name), jax.core.Tracer):
            raise ValueError(
                f"render: medium.{name}: got a traced value (under jax.jit, grad or vmap): "
                "render picks the model's size from concrete values; to transform, use "
                "lfj.make_renderer(grid, illumination, bounces, phase, geometry) and call it "
                "with (sigma_t, sigma_s, g, gain)"
            )
    grid, geometry, rho = resolve_model(medium, grid, geometry)
    paper = paper_bound(medium, geometry)
    k = resolve_bounces(float(rho), bounces, tolerance, tail, paper=paper)
    if coarse_after is not None:  # before the renderer's tables
        check_int(coarse_after, "coarse_after", low=2, high=MAX_BOUNCES)
        coarse = geometry.slab_or_none is None and coarse_plane_grid(grid) is not None
        if lightfield and coarse and k > coarse_after:
            raise ValueError(coarse_lightfield_refusal(coarse_after))
    converges = bool(rho < 1.0)
    bound = f"albedo*A(g) = {float(rho):.4f}" if paper else f"albedo = {float(rho):.4f}"
    if tail is not None and not converges:
        raise ValueError(
            f"tail: rho = {bound} >= 1: the bounce series diverges and has no tail to sum; "
            f"use {'phase: normalized' if paper else 'sigma_s < sigma_t'} or tail: None"
        )
    if not converges:
        warnings.warn(
            f"rho = {bound} >= 1: the bounce series "
            f"{'of the paper phase convention ' if paper else ''}does not converge; the "
            f"{k} rendered bounces are a truncation of a divergent series",
            DivergentSeriesWarning,
            stacklevel=2,
        )
    # Before the renderer's tables: a typo in the grid (Grid(32000, 24000)) or the
    # bounces asked for terabytes, found by a MemoryError or the OOM killer minutes later.
    check_memory(
        render_memory(
            illumination.n_patterns, grid, geometry, medium, k, lightfield, tail is not None
        ),
        f"render: the {grid.width}x{grid.height} grid ({grid.n_theta} directions, refine "
        f"{grid.refine}, {k} bounces, {illumination.n_patterns} patterns"
        f"{', light fields' if lightfield else ''})",
    )
    renderer = renderer_for(
        grid,
        illumination,
        k,
        medium.phase,
        geometry,
        tail,
        tail_tol,
        tail_max_steps,
        coarse_after=coarse_after,
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
        coarse_after=renderer.coarse_after,
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
    check_number(sigma_t, "sigma_t", low=0.0, low_open=True)
    check_number(sigma_s, "sigma_s", low=0.0, high=float(sigma_t))
    check_number(g, "g", low=-1.0, high=1.0, low_open=True, high_open=True)
    c = np.arange(check_int(width, "width", low=1))
    p90 = float(phase_function(math.pi / 2, g))
    return sigma_s * p90 * np.exp(-sigma_t * c) * (-np.expm1(-sigma_t)) / sigma_t


__all__ = [
    "AbstractRenderer",
    "BounceStep",
    "DivergentSeriesWarning",
    "EXPLICIT_WITH_TAIL",
    "PlaneRenderer",
    "TailNotConvergedWarning",
    "Renderer",
    "RenderResult",
    "geometry_renderer",
    "make_renderer",
    "render",
    "model_memory",
    "render_memory",
    "renderer_for",
    "resolve_model",
    "resolve_bounces",
    "single_scatter_closed_form",
    "phase_integral",
    "trace_count",
]
