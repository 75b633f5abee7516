"""The model-sizing rules of a fit: :class:`ModelSpec` (the grid, bounces, crop, geometry and
tail solve of one forward model; what the plane and the slab do differently is theirs,
:mod:`lightfield_jax.inverse.geometry_model`) and :func:`size_model` (the smallest model a capture
needs at an estimate: bounces from the tail bound, θ bins and refinement from g, the crop
from the signal, all capped by ``max_cells``); the tail rule and the march sized from a
measured per-bounce ratio; the buckets of bounce counts that let nearby needs share
compiled programs; the basin scan's cheap model and the joint solve's extrapolated one;
and whether one model covers another.

``options`` is a fit's :class:`~lightfield_jax.inverse.settings.FitSettings` (a
:class:`~lightfield_jax.FitOptions`), read for its model settings.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from lightfield_jax.forward.plane import coarse_plane_grid
from lightfield_jax.inverse.geometry_model import (
    GeometryModel,
    PlaneModel,
    geometry_model,
)
from lightfield_jax.inverse.settings import FitSettings
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import Stripes
from lightfield_jax.scene.medium import bounces_for_tolerance
from lightfield_jax.scene.phase import phase_integral_at


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """One forward model of a fit: its grid, bounces (and how the series past them is
    summed), crop and geometry (:class:`~lightfield_jax.inverse.geometry_model.GeometryModel`),
    and the estimate it was sized for."""

    grid: Grid
    bounces: int
    crop: tuple[int, int, int, int]  # x0, y0, x1, y1 inside the image
    converges: bool
    rho: float  # ρ at the estimate the model was sized for
    geometry: GeometryModel = PlaneModel()  # a slab's resolved (n_mu, n_z set)
    tail: str | None = None  # the tail solve after ``bounces`` = K0, or None: marched
    tail_tol: float = 1e-4
    tail_max_steps: int = 200
    ratio: float | None = None  # per-bounce ratio measured at the estimate (sized K)
    extrapolate: bool = False  # the orders past ``bounces`` summed geometrically
    coarse_after: int | None = None  # the plane's bounces after it on its coarse grid
    # Stripes rendered from one period (the shift orders of the geometry's cell renderer:
    # its stripe_cell for a sized model, the shifts' mean alone for the scan's and an
    # extrapolated solve's, whose answers are corrected; the geometry decides where it
    # renders them so), or None: the full render.
    cell: int | None = None

    @property
    def coarse(self) -> int | None:
        """K0 of the coarse tail where it applies (the plane, a march of more bounces,
        a grid coarser than the model's), else ``None``."""
        if self.tail is not None:
            return None
        return self.geometry.coarse(self.grid, self.bounces, self.coarse_after)

    @property
    def tail_bound(self) -> float | None:
        """ρ^K/(1 − ρ) of a marched series (the measured ratio where it sized K, else ρ
        at the estimate): the orders left out, relative to I_1; ``None`` with a tail
        solve, an extrapolated tail or a divergent series."""
        if not (self.converges and self.tail is None and not self.extrapolate):
            return None
        r = self.rho if self.ratio is None else self.ratio
        return r**self.bounces / (1 - r)

    def as_dict(self, illumination=None) -> dict:
        """The model's record; for ``illumination`` (the fit's stripes), what its
        renderer does with them: the stripe cell where it renders them (the coarse tail
        then applies to full light alone: ``coarse_tail.stripes`` false), else no cell
        (``None``: both as the model asks)."""
        cell, coarse = self.cell, self.coarse
        stripes = {}
        if illumination is not None:
            if self.geometry.renders_cell(self, illumination):
                stripes = {"stripes": False}  # the cell marches every bounce on the grid
            else:
                cell = None
        return {
            "geometry": self.geometry.scene.as_dict(),
            **self.geometry.sizing(),
            "width": self.grid.width,
            "height": self.grid.height,
            "n_theta": self.grid.n_theta,
            "refine": self.grid.refine,
            "bounces": self.bounces,
            "crop": list(self.crop),
            "series_converges": self.converges,
            "rho_estimate": self.rho,
            "ratio_measured": self.ratio,
            "tail_bound": self.tail_bound,
            "extrapolated": self.extrapolate,
            # Stripes entering a side wall, rendered from one period (the geometry's cell).
            "stripe_cell": None
            if cell is None
            else {"shift_orders": cell, **self.geometry.cell_record(self)},
            "coarse_tail": None
            if coarse is None
            else {
                "after": coarse,
                "n_theta": coarse_plane_grid(self.grid).n_theta,
                "refine": coarse_plane_grid(self.grid).refine,
                **stripes,
            },
            "tail": None
            if self.tail is None
            else {
                "method": self.tail,
                "K0": self.bounces,
                "tol": self.tail_tol,
                "max_steps": self.tail_max_steps,
            },
        }


def signal_crop(images: np.ndarray, pattern: Stripes, fraction: float) -> tuple[int, ...]:
    """Crop along the propagation direction to where the signal stands out: Imax,
    averaged across the light, must exceed its noise floor (the median of the farthest
    tenth) by ``fraction`` of the peak and by three times the floor's scatter. The entry
    wall stays; at least 16 pixels are kept, in multiples of 8."""
    p, h, w = images.shape
    along_x = pattern.along_x
    imax = np.nanmax(images, axis=0)
    prof = np.nanmean(imax, axis=0 if along_x else 1)
    if pattern.entry in ("right", "bottom"):
        prof = prof[::-1]
    n = prof.size
    tenth = max(n // 10, 2)
    tail = prof[-tenth:]
    floor = float(np.median(tail))
    scatter = float(np.median(np.abs(tail - floor))) * 1.4826
    peak = float(np.max(prof))
    before = float(np.median(prof[-2 * tenth : -tenth]))
    if before - floor > 3.0 * scatter + fraction * (peak - floor):
        # Still decaying at the far wall: the farthest tenth is signal, not a floor.
        return (0, 0, w, h)
    above = prof - floor > max(fraction * (peak - floor), 3.0 * scatter)
    last = int(np.flatnonzero(above).max()) + 1 if above.any() else n
    # Rounded up to a multiple of 8 (within the image): captures and channels of nearby
    # extents share one shape, and so their compiled programs.
    keep = min(n, _bucket(max(last + 2, 16), 8))
    if pattern.entry in ("left", "top"):
        lo, hi = 0, keep
    else:
        lo, hi = n - keep, n
    return (lo, 0, hi, h) if along_x else (0, lo, w, hi)


def size_model(
    images: np.ndarray,
    pattern: Stripes,
    albedo: float,
    g: float,
    options: FitSettings,
    margin: float = 1.15,
    sigma_t: float | None = None,
    crop: tuple[int, int, int, int] | None = None,
) -> ModelSpec:
    """The smallest model the capture needs: bounces from the tail bound at the estimate
    (ρ × ``margin``, capped below 1; rounded up to a bucket), θ bins and refinement from
    g, crop from the signal (or ``crop``). ``series_converges`` is judged at the
    estimate itself."""
    p, h, w = images.shape
    if crop is None:
        crop = (
            signal_crop(images, pattern, options.model.crop_fraction)
            if options.model.crop
            else (0, 0, w, h)
        )
    n_theta, refine, geometry = geometry_model(options.model.geometry).sized(
        options, g, albedo, sigma_t
    )
    width, height = crop[2] - crop[0], crop[3] - crop[1]
    while width * height * n_theta * refine**2 > options.model.max_cells:
        if refine > 1 and options.model.refine is None:
            refine -= 1
        elif n_theta > 32 and options.model.n_theta is None:
            n_theta //= 2
        else:
            break
    n_theta, refine, geometry = geometry.capped(width, height, n_theta, refine, options)
    grid = Grid(width, height, n_theta, refine)
    a = float(phase_integral_at(g)) if options.model.phase == "paper" else 1.0
    rho = geometry.bounce_ratio(min(albedo, 1.0) * a, sigma_t, albedo, g, width, height)
    converges = rho < 1.0
    if isinstance(options.model.bounces, int):
        k = options.model.bounces
    elif converges:
        bound = min(max(rho * margin + 0.01, 0.0), 0.995)
        k = bucket_bounces(bounces_for_tolerance(bound, options.model.tolerance, max_bounces=10**9))
    else:
        k = options.model.max_bounces
    model = ModelSpec(
        grid=grid,
        bounces=max(k, 2),
        crop=crop,
        converges=converges,
        rho=rho,
        geometry=geometry,
        coarse_after=geometry.coarse_after(options),
        cell=geometry.stripe_cell(grid, options),
    )
    return _with_tail(model, options)


def _tail_for(options: FitSettings, model: ModelSpec) -> str | None:
    """The tail solve of a model that would march ``model.bounces`` (``None``: it marches
    them): under ``tail: auto`` with ``bounces: auto``, BiCGStab once they exceed
    ``max_bounces`` (measured on the dense forward medium, 128×96, 32 θ bins, six
    patterns: the value and Jacobian of K0 = 8 bounces and the BiCGStab tail cost what
    80 marched bounces do); under a named method always; never for a divergent series."""
    if not model.converges or options.model.tail is None:
        return None
    if options.model.tail == "auto":
        auto = options.model.bounces == "auto" and model.bounces > options.model.max_bounces
        return "bicgstab" if auto else None
    return options.model.tail


# Added to a measured per-bounce ratio before sizing a march from it (the ratio of the
# scan's last bounce, on its cheap model, at the estimate rather than the answer).
RATIO_MARGIN = 0.02


def by_measured_ratio(model: ModelSpec, options: FitSettings, ratio: float) -> ModelSpec:
    """``model`` marching the bounces the measured per-bounce ``ratio`` asks for (tail
    below ``tolerance`` at ratio + :data:`RATIO_MARGIN`) where that is fewer than the
    albedo's bound asked for: instead of its automatic tail where the count is at most
    ``max_bounces``, or instead of a longer march. Walls leak light at every bounce, so
    the measured ratio is well below ρ = ω: 0.71 for the dense forward medium (ω 0.8)
    on 128×96, a 40-bounce march instead of the bound's 64 (its image sum within 3e-6
    of 160 bounces'), whose value and Jacobian cost 0.4× the tail's (measured at 32 θ
    bins); a ratio near 1 still gets the tail. The error term's finer model marches
    bounces plus a geometric sum of the rest, so a count too short shows there."""
    auto = options.model.tail == "auto" and options.model.bounces == "auto"
    if not (auto and model.converges and math.isfinite(ratio)):
        return model
    bound = min(max(ratio + RATIO_MARGIN, 0.0), 0.995)  # a measured ratio, never below 0
    k = max(
        bucket_bounces(bounces_for_tolerance(bound, options.model.tolerance, max_bounces=10**9)), 2
    )
    if model.tail is not None and k <= options.model.max_bounces:
        return dataclasses.replace(model, bounces=k, tail=None, ratio=ratio)
    if model.tail is None and k < model.bounces:
        return dataclasses.replace(model, bounces=k, ratio=ratio)
    return model


def _with_tail(model: ModelSpec, options: FitSettings) -> ModelSpec:
    """``model`` with a tail and K0 explicit bounces where it gets one, else with its
    bounces capped at ``max_bounces`` (``bounces: auto``; the model's tail bound is
    reported with the result)."""
    tail = _tail_for(options, model)
    if tail is None:
        if options.model.bounces == "auto":
            return dataclasses.replace(model, bounces=min(model.bounces, options.model.max_bounces))
        return model
    return dataclasses.replace(
        model,
        bounces=options.model.tail_bounces,
        tail=tail,
        tail_tol=options.model.tolerance,
        tail_max_steps=options.model.tail_max_steps,
    )


def _bucket(n: int, step: int) -> int:
    return -(-n // step) * step


def bucket_bounces(k: int) -> int:
    """Bounce counts above 8 rounded up to a few buckets (every 4 to 32, every 8 beyond),
    so captures and stages of nearby needs share a compiled program (compiling costs
    seconds, a few more bounces a fraction of the run)."""
    return k if k <= 8 else _bucket(k, 4) if k <= 32 else _bucket(k, 8)


def at_least(model: ModelSpec, floor: ModelSpec | None) -> ModelSpec:
    """``model`` grown to ``floor`` (bounces, θ bins, refinement, elevation nodes)."""
    if floor is None:
        return model
    grid = dataclasses.replace(
        model.grid,
        n_theta=max(model.grid.n_theta, floor.grid.n_theta),
        refine=max(model.grid.refine, floor.grid.refine),
    )
    return dataclasses.replace(
        model,
        grid=grid,
        bounces=max(model.bounces, floor.bounces),
        geometry=model.geometry.at_least(floor.geometry),
    )


def scan_model(crop, options: FitSettings, rho0: float) -> ModelSpec:
    """The cheap model of the basin scan (and, through :func:`extrapolated`, of the
    joint fit's first solve): 32 θ bins
    on the native grid (the slab: 8 azimuth bins, 4 elevation nodes, one constant depth
    layer),
    the bounces the capture's brightness ratio calls for (tail below 1e-3 at
    ρ = max(ρ0, 0.3), ρ0 the separation's estimate with its margin)."""
    width, height = crop[2] - crop[0], crop[3] - crop[1]
    n_theta, geometry = geometry_model(options.model.geometry).cheap(options)
    rho = min(max(rho0, 0.3), 0.95)
    k = bucket_bounces(bounces_for_tolerance(rho, 1e-3, max_bounces=10**9))
    if isinstance(options.model.bounces, int):
        k = options.model.bounces
    model = ModelSpec(
        grid=Grid(width, height, n_theta, 1),
        bounces=max(k, 2),
        crop=crop,
        converges=True,
        rho=rho,
        geometry=geometry,
    )
    return _with_tail(model, options)


def over_cap_note(model: ModelSpec, options: FitSettings) -> str | None:
    """A note where :func:`size_model`'s ``model`` is larger than ``max_cells`` allows
    (``None``: it is not): θ bins or a refinement the options fix are never lowered,
    and θ bins not below 32 on the plane (8, with 4 elevation nodes, on the slab).
    A ``max_cells`` below the smallest model, or fixed bins beyond it, are used with
    this note, not silently."""
    g = model.grid
    size = model.geometry.over_cap(g, options.model.max_cells)
    if size is None:
        return None
    fixed = [
        f"{name} {value}"
        for name, value, given in (
            ("n_theta", g.n_theta, options.model.n_theta),
            ("refine", g.refine, options.model.refine),
        )
        if given is not None
    ]
    fixed += model.geometry.fixed_by(options)
    why = []
    if fixed:
        are = "is" if len(fixed) == 1 else "are"
        why.append(f"{' and '.join(fixed)} {are} fixed by the fit options, never lowered")
    if options.model.n_theta is None:
        why.append(f"n_theta is not lowered below {model.geometry.least}")
    return (
        f"max_cells {options.model.max_cells} is below the model's size ({g.width}x{g.height} "
        f"px, n_theta {g.n_theta}, refine {g.refine}, {size}): {'; '.join(why)}; the fit "
        "solves on that model"
    )


def finer_cheap(model: ModelSpec, options: FitSettings) -> ModelSpec | None:
    """The cheap model with more azimuth bins and elevation nodes for a solve that did
    not converge or ran to a bound (the slab's:
    :meth:`~lightfield_jax.inverse.geometry_model.GeometryModel.finer_cheap`), or
    ``None``."""
    finer = model.geometry.finer_cheap(model.grid, options)
    if finer is None:
        return None
    grid, geometry = finer
    return dataclasses.replace(model, grid=grid, geometry=geometry)


def extrapolated(model: ModelSpec, options: FitSettings) -> ModelSpec:
    """The cheap model of the solve: where the fit corrects its answer to the model it
    needs (``correct``) and sizes the series itself, a long series (a tail, or more
    than :data:`SCAN_TAIL_BOUNCES` bounces) becomes that many bounces and a geometric
    tail (:func:`lightfield_jax.inverse.joint.unit_model`); its Jacobian only guides the
    correction, which renders the series in full."""
    auto = options.model.bounces == "auto" and options.model.tail == "auto"
    long = model.tail is not None or model.bounces > SCAN_TAIL_BOUNCES
    if not (options.trust.correct and auto and long and model.converges):
        return model
    return dataclasses.replace(model, bounces=SCAN_TAIL_BOUNCES, tail=None, extrapolate=True)


# Explicit bounces of the scan on a model with a tail: the orders beyond them are
# extrapolated geometrically (:func:`lightfield_jax.inverse.basins.scan`).
SCAN_TAIL_BOUNCES = 24


def orders(model: ModelSpec, illumination) -> str:
    """The model's bounce series in a progress line (stripes from one period, where its
    geometry renders ``illumination`` so, march every order on the model's grid: no
    coarse tail)."""
    if model.geometry.renders_cell(model, illumination):
        coarse = f" (side-wall stripes from one period: shift_orders {model.cell})"
    elif model.coarse is not None:
        coarse = f" (after {model.coarse} on the coarse grid)"
    else:
        coarse = ""
    if model.extrapolate:
        return f"{model.bounces} bounces{coarse} and a geometric tail"
    if model.tail is None:
        return f"{model.bounces} bounces{coarse}"
    return f"K0 = {model.bounces} and a {model.tail} tail"


def covers(have: ModelSpec, need: ModelSpec) -> bool:
    # A tail sums every order past K0: it covers any bounce count, a march only its own;
    # an extrapolated series (the cheap solve's) covers none (it is always corrected).
    if have.extrapolate:
        return False
    if need.tail is not None:
        summed = have.tail == need.tail and have.bounces >= need.bounces
    else:
        summed = have.tail is not None or have.bounces >= need.bounces
    # Every dimension of the discretisation, a slab's depth layers and elevation nodes
    # included: a cheap model of one layer does not cover a need of eight.
    sizes = discretisation(have)
    finer = all(sizes.get(k, 0) >= v for k, v in discretisation(need).items())
    return have.crop == need.crop and summed and finer


def discretisation(model: ModelSpec) -> dict[str, int]:
    """The model's discretisation: θ bins and refinement; a slab's elevation nodes,
    depth layers and the order of its depth profile (0 constant, 1 linear) too."""
    return {
        "n_theta": model.grid.n_theta,
        "refine": model.grid.refine,
        **model.geometry.discretisation(),
    }


def richardson_factor(model: ModelSpec, fine: ModelSpec) -> float | None:
    """How far past ``fine`` (the error term's finer model) the continuum lies, in units
    of the step from ``model`` to it (its geometry's
    :meth:`~lightfield_jax.inverse.geometry_model.GeometryModel.richardson_factor`:
    r_f/(r_f − r) for a plane refined in space from r to r_f), or ``None``."""
    return model.geometry.richardson_factor(model.grid, fine.grid)


__all__ = [
    "RATIO_MARGIN",
    "SCAN_TAIL_BOUNCES",
    "ModelSpec",
    "at_least",
    "bucket_bounces",
    "by_measured_ratio",
    "covers",
    "discretisation",
    "extrapolated",
    "finer_cheap",
    "orders",
    "over_cap_note",
    "richardson_factor",
    "scan_model",
    "signal_crop",
    "size_model",
]
