"""The inverse problem (docs/model.md sections 5-6): recover σt, σs, g (and the gain) from a
stripe capture.

This module is the driver: :func:`fit_images` prepares the data
(:mod:`lightfield_jax.inverse.data`), sizes the first model and hands the problem to a
fit method (:mod:`lightfield_jax.inverse.methods`: ``GridSearch``, ``TwoStep``,
``Joint``, each taking any optimistix least-squares solver); it holds the joint fit's
stages, the model sizing and the result (the fit of a whole capture, channel by
channel, is :mod:`lightfield_jax.inverse.capture_fit`). The methods, all on the same
forward model (:class:`~lightfield_jax.Renderer`):

- ``grid`` (the paper's baseline): σt from the decay of the separated direct image D;
  per g on a grid, render I_k^{(g)} with σs = 1 under full illumination (``lax.map``
  over g), take the gain from the single scatter (D ≈ a·I_1^{(g)}, a = c·σs), solve the
  σs polynomial of the paper's eq. 10, M ≈ a·Σ_{k≥2} σs^{k−1} I_k^{(g)}, and keep the
  best g. It inherits the separation's bias (docs/model.md §6): that is its honest result.
- ``gradient``: the same residual and model (:mod:`lightfield_jax.inverse.two_step`),
  solved over (σs, g) by an optimistix least-squares solver (Levenberg-Marquardt by
  default), differentiated through the renderer.
- ``joint`` (default): σt, σs, g, gain (and the projector's black level when the
  capture does not give it) fitted straight to the raw shifted images by rendering each
  stripe pattern, so no separation bias remains. It starts from a global scan of the
  misfit over (g, albedo) on a cheap model (:mod:`lightfield_jax.inverse.basins`), solves
  every basin near the best (cheap model, then the model its answer needs) and keeps
  the best.

Every result carries 1σ uncertainties from the Jacobian (the joint fit: statistical
from the capture's measured noise, a model term from a finer model's residual, and
their total; :mod:`lightfield_jax.inverse.trust`), χ²/dof, correlations, the solver's
convergence status (never swallowed; false with the reasons for a solution that is not
trustworthy), iterations, residual, wall time split into compile and run, and the model
used. Programs are compiled once per static settings and shape bucket
(:mod:`lightfield_jax.inverse.programs`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from lightfield_jax.app.timing import stopwatch
from lightfield_jax.forward.render import renderer_for
from lightfield_jax.forward.slab import slab_bounce_ratio
from lightfield_jax.forward.tail import TAIL_METHODS
from lightfield_jax.inverse.basins import Scan, basins, scan, worse_basin
from lightfield_jax.inverse.correction import correct, design, projected
from lightfield_jax.inverse.data import FitData as _Data
from lightfield_jax.inverse.data import FitProblem, prepare_data
from lightfield_jax.inverse.joint import BLACK_RANGE, JointSettings, model_at, pack, unpack
from lightfield_jax.inverse.joint import solve as solve_joint
from lightfield_jax.inverse.methods import FitMethod, check_solver, check_start, method_for
from lightfield_jax.inverse.model_choice import choose, misfit, relative_noise
from lightfield_jax.inverse.programs import clear_compiled as clear_compiled
from lightfield_jax.inverse.trust import (
    Uncertainty,
    at_bound,
    error_budget,
    noise_scale,
    tail_unconverged,
    untrustworthy,
)
from lightfield_jax.inverse.two_step import full_for as _full_for
from lightfield_jax.scene.geometry import (
    AutoGeometry,
    Plane,
    Slab,
    as_geometry,
    default_slab_n_theta,
    parse_geometry,
)
from lightfield_jax.scene.grid import Grid, default_n_theta, default_refine
from lightfield_jax.scene.illumination import _INWARD_DEG, Stripes
from lightfield_jax.scene.medium import bounces_for_tolerance, phase_integral

# A(g) of a Python float, compiled once (op by op, its dozen operations would each
# compile on first use).
_phase_integral = jax.jit(phase_integral)
_PARAMS = ("sigma_t", "sigma_s", "g", "gain", "black_level")


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """Settings of a fit (all optional).

    Attributes:
        method: ``joint`` (default), ``gradient`` or ``grid``, or a fit method
            (:class:`~lightfield_jax.Joint`, :class:`~lightfield_jax.TwoStep`,
            :class:`~lightfield_jax.GridSearch`: :mod:`lightfield_jax.inverse.methods`)
            whose own settings (its solver, start, grid size) replace these.
        phase: phase convention of the model (``paper`` or ``normalized``).
        bounces: K, or ``"auto"`` from the tail bound at the starting estimate.
        tolerance: relative tail tolerance for ``bounces: auto``.
        max_bounces: cap on ``auto`` without a tail (the paper series near ρ = 1 needs
            many).
        tail: (``joint``) how the bounce series is summed past its explicit bounces:
            ``"auto"`` (default: the plane's series is marched while ``bounces: auto``
            asks for at most ``max_bounces`` bounces, else ``tail_bounces`` explicit
            bounces and a BiCGStab solve of the rest), ``None`` (always marched, capped
            at ``max_bounces``), or ``"gmres"`` / ``"bicgstab"`` (always that solve
            after ``tail_bounces``; :mod:`lightfield_jax.forward.tail`). The tail's
            relative tolerance is ``tolerance``. Plane and slab alike.
        tail_bounces: K0, the explicit bounces kept before a tail solve.
        tail_max_steps: iteration limit of a tail solve; one that stops there makes
            the result not trustworthy.
        n_theta: direction bins, or ``None`` to choose them from the starting g.
        refine: spatial refinement, or ``None`` to choose it from the starting g.
        g_grid: number of g values of the ``grid`` method's search on (−0.95, 0.95).
        start_grid: number of g values of the coarse search that starts ``gradient``.
        max_cells: cap on the model's working size (W·H·n_theta·refine²): the
            refinement, then n_theta, are lowered to fit it.
        crop: crop the model along the propagation direction to where the signal is
            above ``crop_fraction`` of its peak.
        crop_fraction: see ``crop``.
        max_steps: iteration limit of the optimistix solves.
        geometry: the model's geometry: ``None`` or :class:`Plane` (the paper's 2-D
            model), a :class:`Slab` (the tank's depth, docs/model.md §7; its 3-D phase
            function is normalised on the sphere, so ``phase`` is ``normalized``), or
            :class:`AutoGeometry` (the plane where its misfit is below the capture's
            noise, else the slab: :mod:`lightfield_jax.inverse.model_choice`).
        rtol, atol: solver tolerances (relative, absolute on the unconstrained values
            and on the residual's components); ``None`` picks them from the data's
            dtype (float32: 1e-4, 1e-4; float64: 1e-8, 1e-10). float32 cannot resolve
            changes of the residual much below 1e-4 of its scale: with tighter
            tolerances LM converges within a few steps and then spends ten more
            shrinking its step in rounding noise (same answer to 1e-6).
        basin_search: (``joint``) solve every basin the global scan keeps, not only
            its best (:mod:`lightfield_jax.inverse.basins`).
        max_basins: at most this many basins are solved.
        basin_tolerance: a local minimum of the scan is kept when its misfit is at most
            (1 + tolerance) × the best.
        start: (σs, g) to start the joint fit from instead of the scan's basins (σt
            from the decay fit); the scan still runs, to report a worse basin.
        model_error: (``joint``) estimate the model's error at the solution from one
            render with a finer model (in ``uncertainty_model``).
        correct: (``joint``) reach the model the answer needs by defect correction
            (:mod:`lightfield_jax.inverse.correction`: primal renders of that model
            with the cheap model's Jacobian, its own by forward differences where
            those steps stop shrinking) instead of solving on it; where the iteration does not
            converge the fit solves on that model as capped by ``max_cells``.
        max_render_cells: cap on the corrected model's working size (as ``max_cells``,
            for primal renders, which need no tangents).
        correction_renders: at most this many renders at iterates in the correction
            (besides one per parameter for the Jacobian).
        max_chi2: χ²/dof against the capture's noise above which a joint fit is not
            trustworthy (its misfit is far above the noise).
        solver: any optimistix least-squares solver (default: Levenberg-Marquardt with
            ``rtol``, ``atol``).
    """

    method: str | FitMethod = "joint"
    phase: str = "paper"
    bounces: int | str = "auto"
    tolerance: float = 1e-4
    max_bounces: int = 80
    tail: str | None = "auto"
    tail_bounces: int = 8
    tail_max_steps: int = 200
    n_theta: int | None = None
    refine: int | None = None
    g_grid: int = 39
    start_grid: int = 9
    max_cells: int = 2_000_000
    crop: bool = True
    crop_fraction: float = 1e-4
    max_steps: int = 100
    rtol: float | None = None
    atol: float | None = None
    geometry: Plane | Slab | AutoGeometry | None = None
    basin_search: bool = True
    max_basins: int = 3
    basin_tolerance: float = 1.0
    start: tuple[float, float] | None = None
    model_error: bool = True
    correct: bool = True
    max_render_cells: int = 8_000_000
    correction_renders: int = 8
    max_chi2: float = 100.0
    solver: optx.AbstractLeastSquaresSolver | None = None

    def __post_init__(self):
        method_for(self.method)  # a known name or a FitMethod
        if self.tail is not None and self.tail != "auto" and self.tail not in TAIL_METHODS:
            raise ValueError(
                f"tail: must be auto, None or one of {', '.join(TAIL_METHODS)}, got {self.tail!r}"
            )
        if not isinstance(self.tail_bounces, int) or self.tail_bounces < 2:
            raise ValueError(f"tail_bounces: must be an integer >= 2, got {self.tail_bounces!r}")
        if not isinstance(self.tail_max_steps, int) or self.tail_max_steps < 1:
            raise ValueError(
                f"tail_max_steps: must be an integer >= 1, got {self.tail_max_steps!r}"
            )
        if self.g_grid < 3:
            raise ValueError(f"g_grid: must be at least 3, got {self.g_grid!r}")
        if self.max_basins < 1:
            raise ValueError(f"max_basins: must be at least 1, got {self.max_basins!r}")
        if not self.basin_tolerance >= 0:
            raise ValueError(f"basin_tolerance: must be >= 0, got {self.basin_tolerance!r}")
        if not isinstance(self.correction_renders, int) or self.correction_renders < 1:
            raise ValueError(
                f"correction_renders: must be an integer >= 1, got {self.correction_renders!r}"
            )
        if not self.max_render_cells >= self.max_cells:
            raise ValueError(
                f"max_render_cells: must be at least max_cells ({self.max_cells}), got "
                f"{self.max_render_cells!r}"
            )
        check_start(self.start)
        check_solver(self.solver)


@dataclasses.dataclass(frozen=True)
class FitResult:
    """What a fit recovered, and how much to trust it.

    Values are per pixel (σ's), the gain in image units per unit source irradiance.
    ``uncertainty`` holds the total 1σ errors (NaN where not estimated): the statistical
    part (``uncertainty_statistical``: the capture's noise, scaled up by √(χ²/dof)
    where that exceeds 1) ⊕ the model part (``uncertainty_model``: the shift a finer
    model's residual implies at the solution; the joint fit only). ``correlation`` holds
    the correlation coefficients between fitted parameters (e.g. ``"sigma_t,g"``).
    ``chi2_dof`` is the misfit against the capture's noise (``noise``: the variance of
    one weighted residual that noise alone gives), ``chi2_model`` against the noise ⊕
    the model's own error (what the verdict uses); ``model_limited`` is true where the
    model term is the larger for σt, σs or g. ``converged`` is false, with
    ``reasons``, for a solution that is not trustworthy: at a parameter bound, with a
    misfit far above the noise, or in a basin worse than another the scan found.
    ``basins`` (joint) holds the scan and every start tried, with its answer.
    """

    method: str
    sigma_t: float
    sigma_s: float
    g: float
    gain: float
    black_level: float | None
    uncertainty: dict
    correlation: dict
    converged: bool
    message: str
    iterations: int
    residual: float
    seconds: dict
    model: dict
    phase: str = "paper"
    pixel_size_mm: float | None = None
    condition_number: float = math.nan
    uncertainty_statistical: dict = dataclasses.field(default_factory=dict)
    uncertainty_model: dict = dataclasses.field(default_factory=dict)
    chi2_dof: float = math.nan
    chi2_model: float = math.nan
    noise: float = math.nan
    model_limited: bool = False
    reasons: tuple[str, ...] = ()
    basins: dict | None = None

    @property
    def sigma_a(self) -> float:
        return self.sigma_t - self.sigma_s

    @property
    def albedo(self) -> float:
        return self.sigma_s / self.sigma_t

    @property
    def rho(self) -> float:
        if not math.isfinite(self.g):
            return math.nan
        a = float(_phase_integral(self.g)) if self.phase == "paper" else 1.0
        return self.albedo * a

    def to_dict(self) -> dict:
        """The ``results.json`` form (docs/model.md units: per pixel; also mm⁻¹ if known)."""
        unc = dict(self.uncertainty)
        if "sigma_a" not in unc:
            unc["sigma_a"] = _combine(unc, self.correlation, "sigma_t", "sigma_s", -1.0)
        if "albedo" not in unc:
            unc["albedo"] = _albedo_error(self, unc)
        out = {
            "method": self.method,
            "sigma_t": _json_float(self.sigma_t),
            "sigma_s": _json_float(self.sigma_s),
            "sigma_a": _json_float(self.sigma_a),
            "g": _json_float(self.g),
            "albedo": _json_float(self.albedo),
            "gain": _json_float(self.gain),
            "black_level": None if self.black_level is None else _json_float(self.black_level),
            "rho": _json_float(self.rho),
            "phase": self.phase,
            "uncertainty": {k: _json_float(v) for k, v in unc.items()},
            "correlation": {k: _json_float(v) for k, v in self.correlation.items()},
            "uncertainty_statistical": {
                k: _json_float(v) for k, v in self.uncertainty_statistical.items()
            },
            "uncertainty_model": {k: _json_float(v) for k, v in self.uncertainty_model.items()},
            "chi2_dof": _json_float(self.chi2_dof),
            "chi2_model": _json_float(self.chi2_model),
            "noise": _json_float(self.noise),
            "model_limited": self.model_limited,
            "condition_number": _json_float(self.condition_number),
            "converged": self.converged,
            "reasons": list(self.reasons),
            "message": self.message,
            "iterations": self.iterations,
            "residual": _json_float(self.residual),
            "seconds": self.seconds,
            "model": self.model,
        }
        if self.basins is not None:
            out["basins"] = _json_clean(self.basins)
        if self.pixel_size_mm:
            mm = self.pixel_size_mm
            out["per_mm"] = {
                "pixel_size_mm": mm,
                "sigma_t": _json_float(self.sigma_t / mm),
                "sigma_s": _json_float(self.sigma_s / mm),
                "sigma_a": _json_float(self.sigma_a / mm),
                "uncertainty": {
                    k: _json_float(unc[k] / mm) for k in ("sigma_t", "sigma_s", "sigma_a")
                },
            }
        return out


def _json_float(v):
    v = float(v)
    return v if math.isfinite(v) else None


def _json_clean(obj):
    """Nested dicts/lists with non-finite floats as ``None`` (strict JSON)."""
    if isinstance(obj, dict):
        return {k: _json_clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_clean(v) for v in obj]
    if isinstance(obj, float):
        return _json_float(obj)
    return obj


def _combine(unc, corr, a, b, sign):
    ua, ub = unc.get(a, math.nan), unc.get(b, math.nan)
    r = corr.get(f"{a},{b}", corr.get(f"{b},{a}", 0.0))
    return math.sqrt(max(ua**2 + ub**2 + 2 * sign * r * ua * ub, 0.0))


def _albedo_error(res: FitResult, unc) -> float:
    ut, us = unc.get("sigma_t", math.nan), unc.get("sigma_s", math.nan)
    if math.isnan(ut):
        ut = 0.0
    r = res.correlation.get("sigma_t,sigma_s", 0.0)
    w = res.albedo
    rel2 = (us / res.sigma_s) ** 2 + (ut / res.sigma_t) ** 2
    rel2 -= 2 * r * (us / res.sigma_s) * (ut / res.sigma_t)
    return w * math.sqrt(max(rel2, 0.0))


# ---------------------------------------------------------------------------- model size


@dataclasses.dataclass(frozen=True)
class _Model:
    grid: Grid
    bounces: int
    crop: tuple[int, int, int, int]  # x0, y0, x1, y1 inside the image
    converges: bool
    rho: float  # ρ at the estimate the model was sized for
    geometry: Slab | None = None  # resolved (n_mu set); None: the plane
    tail: str | None = None  # the tail solve after ``bounces`` = K0, or None: marched
    tail_tol: float = 1e-4
    tail_max_steps: int = 200
    ratio: float | None = None  # per-bounce ratio measured at the estimate (sized K)
    extrapolate: bool = False  # the orders past ``bounces`` summed geometrically

    def as_dict(self) -> dict:
        marched = self.converges and self.tail is None and not self.extrapolate
        r = self.rho if self.ratio is None else self.ratio
        tail = r**self.bounces / (1 - r) if marched else None
        return {
            "geometry": (self.geometry or Plane()).as_dict(),
            "width": self.grid.width,
            "height": self.grid.height,
            "n_theta": self.grid.n_theta,
            "refine": self.grid.refine,
            "bounces": self.bounces,
            "crop": list(self.crop),
            "series_converges": self.converges,
            "rho_estimate": self.rho,
            "ratio_measured": self.ratio,
            "tail_bound": tail,
            "extrapolated": self.extrapolate,
            "tail": None
            if self.tail is None
            else {
                "method": self.tail,
                "K0": self.bounces,
                "tol": self.tail_tol,
                "max_steps": self.tail_max_steps,
            },
        }


def _signal_crop(images: np.ndarray, pattern: Stripes, fraction: float) -> tuple[int, ...]:
    """Crop along the propagation direction to where the signal stands out: Imax,
    averaged across the light, must exceed its noise floor (the median of the farthest
    tenth) by ``fraction`` of the peak and by three times the floor's scatter. The entry
    wall stays; at least 16 pixels are kept, in multiples of 8."""
    p, h, w = images.shape
    along_x = pattern.entry in ("left", "right")
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
    options: FitOptions,
    margin: float = 1.15,
    sigma_t: float | None = None,
    crop: tuple[int, int, int, int] | None = None,
) -> _Model:
    """The smallest model the capture needs: bounces from the tail bound at the estimate
    (ρ × ``margin``, capped below 1; rounded up to a bucket), θ bins and refinement from
    g, crop from the signal (or ``crop``). ``series_converges`` is judged at the
    estimate itself."""
    p, h, w = images.shape
    if crop is None:
        crop = (
            _signal_crop(images, pattern, options.crop_fraction) if options.crop else (0, 0, w, h)
        )
    gw = min(0.99, abs(g) + 0.1)
    slab = as_geometry(options.geometry).slab_or_none
    if slab is not None:  # less sensitive to g than the plane: a smaller margin
        # Depth layers, elevation nodes and azimuth bins from the estimate (the albedo
        # and σt·h decide how much the depth must be resolved).
        g_slab, albedo_slab = min(0.99, abs(g) + 0.05), min(max(albedo, 0.0), 1.0)
        n_theta = options.n_theta or default_slab_n_theta(g_slab, slab.boundary, albedo_slab)
        refine = options.refine or 1
        slab = slab.resolve(g_slab, sigma_t=sigma_t, albedo=albedo_slab)
    else:
        n_theta = options.n_theta or default_n_theta(gw)
        refine = options.refine or default_refine(abs(g))
    width, height = crop[2] - crop[0], crop[3] - crop[1]
    while width * height * n_theta * refine**2 > options.max_cells:
        if refine > 1 and options.refine is None:
            refine -= 1
        elif n_theta > 32 and options.n_theta is None:
            n_theta //= 2
        else:
            break
    if slab is not None:
        # A slab works on azimuth × elevation fields over the 2H × 2W FFT domain.
        user_mu = options.geometry.n_mu is not None
        while (
            width * height * 4 * n_theta * slab.n_mu * slab.n_z * refine**2 > 4 * options.max_cells
        ):
            if n_theta > 8 and options.n_theta is None:
                n_theta //= 2
            elif slab.n_mu > 4 and not user_mu:
                slab = dataclasses.replace(slab, n_mu=slab.n_mu // 2)
            else:
                break
    grid = Grid(width, height, n_theta, refine)
    a = float(_phase_integral(g)) if options.phase == "paper" else 1.0
    rho = min(albedo, 1.0) * a
    if slab is not None and sigma_t is not None:
        # Light leaves through the faces: the slab's measured per-bounce ratio, not ω.
        rho = min(rho, slab_bounce_ratio(slab, sigma_t, min(albedo, 1.0), g, width, height))
    converges = rho < 1.0
    if isinstance(options.bounces, int):
        k = options.bounces
    elif converges:
        bound = min(rho * margin + 0.01, 0.995)
        k = _bucket_bounces(bounces_for_tolerance(bound, options.tolerance, max_bounces=10**9))
    else:
        k = options.max_bounces
    model = _Model(
        grid=grid, bounces=max(k, 2), crop=crop, converges=converges, rho=rho, geometry=slab
    )
    return _with_tail(model, options)


def _tail_for(options: FitOptions, model: _Model) -> str | None:
    """The tail solve of a model that would march ``model.bounces`` (``None``: it marches
    them): under ``tail: auto`` with ``bounces: auto``, BiCGStab once they exceed
    ``max_bounces`` (measured on the dense forward medium, 128×96, 32 θ bins, six
    patterns: the value and Jacobian of K0 = 8 bounces and the BiCGStab tail cost what
    80 marched bounces do); under a named method always; never for a divergent series."""
    if not model.converges or options.tail is None:
        return None
    if options.tail == "auto":
        auto = options.bounces == "auto" and model.bounces > options.max_bounces
        return "bicgstab" if auto else None
    return options.tail


# Added to a measured per-bounce ratio before sizing a march from it (the ratio of the
# scan's last bounce, on its cheap model, at the estimate rather than the answer).
RATIO_MARGIN = 0.02


def _by_measured_ratio(model: _Model, options: FitOptions, ratio: float) -> _Model:
    """``model`` marching the bounces the measured per-bounce ``ratio`` asks for (tail
    below ``tolerance`` at ratio + :data:`RATIO_MARGIN`) where that is fewer than the
    albedo's bound asked for: instead of its automatic tail where the count is at most
    ``max_bounces``, or instead of a longer march. Walls leak light at every bounce, so
    the measured ratio is well below ρ = ω: 0.71 for the dense forward medium (ω 0.8)
    on 128×96, a 40-bounce march instead of the bound's 64 (its image sum within 3e-6
    of 160 bounces'), whose value and Jacobian cost 0.4× the tail's (measured at 32 θ
    bins); a ratio near 1 still gets the tail. The error term's finer model marches
    bounces plus a geometric sum of the rest, so a count too short shows there."""
    auto = options.tail == "auto" and options.bounces == "auto"
    if not (auto and model.converges and math.isfinite(ratio)):
        return model
    bound = min(ratio + RATIO_MARGIN, 0.995)
    k = max(_bucket_bounces(bounces_for_tolerance(bound, options.tolerance, max_bounces=10**9)), 2)
    if model.tail is not None and k <= options.max_bounces:
        return dataclasses.replace(model, bounces=k, tail=None, ratio=ratio)
    if model.tail is None and k < model.bounces:
        return dataclasses.replace(model, bounces=k, ratio=ratio)
    return model


def _with_tail(model: _Model, options: FitOptions) -> _Model:
    """``model`` with a tail and K0 explicit bounces where it gets one, else with its
    bounces capped at ``max_bounces`` (``bounces: auto``; the model's tail bound is
    reported with the result)."""
    tail = _tail_for(options, model)
    if tail is None:
        if options.bounces == "auto":
            return dataclasses.replace(model, bounces=min(model.bounces, options.max_bounces))
        return model
    return dataclasses.replace(
        model,
        bounces=options.tail_bounces,
        tail=tail,
        tail_tol=options.tolerance,
        tail_max_steps=options.tail_max_steps,
    )


# ---------------------------------------------------------------------- shared pieces


def _solver(options: FitOptions, dtype):
    """The optimistix least-squares solver: ``options.solver``, else Levenberg-Marquardt
    with tolerances from ``options`` or the dtype."""
    if options.solver is not None:
        return options.solver
    wide = jnp.finfo(dtype).bits > 32
    rtol = options.rtol if options.rtol is not None else (1e-8 if wide else 1e-4)
    atol = options.atol if options.atol is not None else (1e-10 if wide else 1e-4)
    return optx.LevenbergMarquardt(rtol=rtol, atol=atol)


def _result_message(result) -> tuple[bool, str]:
    ok = bool(result == optx.RESULTS.successful)
    if ok:
        return True, "converged"
    return False, str(optx.RESULTS[result]) if hasattr(optx.RESULTS, "__getitem__") else "failed"


# ---------------------------------------------------------------------------- joint


def _renderer(model: _Model, illumination, phase: str):
    if model.tail is None:
        return renderer_for(model.grid, illumination, model.bounces, phase, model.geometry)
    return renderer_for(
        model.grid,
        illumination,
        model.bounces,
        phase,
        model.geometry,
        model.tail,
        model.tail_tol,
        model.tail_max_steps,
    )


def _joint_parts(pattern: Stripes, model: _Model, phase: str):
    """The stripes' renderer and, when the phases do not tile the period, full
    illumination's (else ``None``)."""
    renderer = _renderer(model, pattern, phase)
    tiles = sorted(p % pattern.period for p in pattern.phases) == list(range(pattern.period))
    return renderer, None if tiles else _renderer(model, _full_for(pattern), phase)


def joint_weights(images, mask, exposure=None):
    """Shot-noise weights of the raw images, 1/√(I + floor) (floor 1e-3 of the peak), 0
    outside ``mask``; times √(T/max T) for merged exposure brackets of effective exposure
    T (their variance is ∝ I/T, :mod:`lightfield_jax.capture.hdr`)."""
    floor = 1e-3 * np.nanmax(np.where(mask[None], images, 0.0))
    w = 1.0 / np.sqrt(np.clip(images, 0.0, None) + floor)
    if exposure is not None:
        w = w * np.sqrt(exposure / np.max(exposure))
    return np.where(mask[None], w, 0.0)


@dataclasses.dataclass
class _Stage:
    """One joint solve: the model, the answer and what the error budget needs."""

    model: _Model
    values: dict  # sigma_t, sigma_s, g, black_level, gain
    y: jax.Array
    ok: bool
    message: str
    steps: int
    unit: np.ndarray  # the model at unit gain, (P, h, w)
    jac: np.ndarray  # ∂r/∂(σt, σs, g, gain[, b]), (N, p)
    weights: np.ndarray
    residual: np.ndarray
    rms: float
    compile: float
    run: float
    tail: dict | None = None  # the tail solve at the answer: steps, converged (or error)
    jac_unit: np.ndarray | None = None  # ∂R/∂(σt, σs, g[, b]) at unit gain, (P, h, w, n)
    correction: dict | None = None  # the defect correction that produced it, if any


def _joint_stage(data: _Data, pattern, model: _Model, options: FitOptions, black, weights, y0):
    """One compiled joint solve (:func:`lightfield_jax.inverse.joint.solve`) from ``y0``."""
    renderer, full = _joint_parts(pattern, model, options.phase)
    fit_black = black is None
    settings = JointSettings(fit_black, pattern.lit, options.max_steps, model.extrapolate)
    dtype = y0.dtype
    obs = jnp.asarray(data.images, dtype)
    black_fixed = jnp.asarray(0.0 if fit_black else black, dtype)
    with stopwatch() as timing:
        failure = None
        if model.tail is not None:
            # The tail's tangent solves (the Jacobian) raise where they do not converge
            # (lineax): a tail that does not converge at the start is reported from a
            # primal render, without running the solver.
            unit, tail = model_at(
                renderer, full, pattern.lit, *unpack(y0, fit_black, black_fixed), dtype
            )
            if not bool(tail.converged):
                failure = f"at the start, {int(tail.steps)} iterations"
        if failure is None:
            try:
                y, result, steps, unit, jac_r, tail = jax.block_until_ready(
                    solve_joint(
                        settings,
                        _solver(options, dtype),
                        renderer,
                        full,
                        obs,
                        black_fixed,
                        jnp.asarray(weights, dtype),
                        y0,
                    )
                )
            except RuntimeError:
                if model.tail is None:
                    raise
                failure = "a tangent solve of the Jacobian during the solve"
                unit, tail = model_at(
                    renderer, full, pattern.lit, *unpack(y0, fit_black, black_fixed), dtype
                )
        if failure is not None:  # the answer is the start, not trustworthy
            y, steps, result = y0, 0, optx.RESULTS.nonlinear_divergence
            jac_r = jnp.full(unit.shape + (3 + fit_black,), jnp.nan, dtype)
    st, ss, g, b = (float(v) for v in unpack(y, fit_black, black_fixed))
    w = np.asarray(weights, np.float64)
    unit = np.asarray(unit, np.float64)
    jac_r = np.asarray(jac_r, np.float64)
    gain, residual = projected(w, unit, data.images)
    jac = design(w, unit, gain, jac_r)
    ok, msg = _result_message(result)
    tail_dict = None
    if model.tail is not None:
        tail_dict = {"steps": int(tail.steps), "converged": bool(tail.converged)}
        if failure is not None:
            tail_dict["converged"] = False
            tail_dict["error"] = failure
            ok, msg = False, f"the tail solve did not converge ({failure})"
    return _Stage(
        model=model,
        values={"sigma_t": st, "sigma_s": ss, "g": g, "black_level": b, "gain": gain},
        y=y,
        ok=ok,
        message=msg,
        steps=int(steps),
        unit=unit,
        jac=jac,
        weights=w,
        residual=residual,
        rms=_rms(residual, data),
        compile=timing.compile,
        run=timing.run,
        tail=tail_dict,
        jac_unit=jac_r,
    )


def _rms(residual: np.ndarray, data: _Data) -> float:
    n = int(np.sum(data.mask)) * data.images.shape[0]
    return float(np.sqrt(np.sum(residual**2) / max(n, 1)))


def _joint_reweighted(data: _Data, stage: _Stage):
    """Weights from the fitted model (gain × model) instead of the noisy data (weights
    from the data itself bias a weighted fit toward low values)."""
    return joint_weights(stage.values["gain"] * stage.unit, data.mask, data.exposure)


def _bucket(n: int, step: int) -> int:
    return -(-n // step) * step


def _bucket_bounces(k: int) -> int:
    """Bounce counts above 8 rounded up to a few buckets (every 4 to 32, every 8 beyond),
    so captures and stages of nearby needs share a compiled program (compiling costs
    seconds, a few more bounces a fraction of the run)."""
    return k if k <= 8 else _bucket(k, 4) if k <= 32 else _bucket(k, 8)


def _at_least(model: _Model, floor: _Model | None) -> _Model:
    """``model`` grown to ``floor`` (bounces, θ bins, refinement, elevation nodes)."""
    if floor is None:
        return model
    grid = dataclasses.replace(
        model.grid,
        n_theta=max(model.grid.n_theta, floor.grid.n_theta),
        refine=max(model.grid.refine, floor.grid.refine),
    )
    geometry = model.geometry
    if geometry is not None and floor.geometry is not None:
        geometry = dataclasses.replace(
            geometry,
            n_mu=max(geometry.n_mu, floor.geometry.n_mu),
            n_z=max(geometry.n_z, floor.geometry.n_z),
        )
    return dataclasses.replace(
        model, grid=grid, bounces=max(model.bounces, floor.bounces), geometry=geometry
    )


def _scan_model(crop, options: FitOptions, rho0: float) -> _Model:
    """The cheap model of the basin scan (and, through :func:`_extrapolated`, of the
    joint fit's first solve): 32 θ bins
    on the native grid (the slab: 8 azimuth bins, 4 elevation nodes, one depth layer),
    the bounces the capture's brightness ratio calls for (tail below 1e-3 at
    ρ = max(ρ0, 0.3), ρ0 the separation's estimate with its margin)."""
    width, height = crop[2] - crop[0], crop[3] - crop[1]
    n_theta, geometry = min(options.n_theta or 32, 32), None
    slab = as_geometry(options.geometry).slab_or_none
    if slab is not None:
        n_theta = min(options.n_theta or 8, 8)
        geometry = dataclasses.replace(slab, n_mu=min(slab.n_mu or 4, 4), n_z=1)
    rho = min(max(rho0, 0.3), 0.95)
    k = _bucket_bounces(bounces_for_tolerance(rho, 1e-3, max_bounces=10**9))
    if isinstance(options.bounces, int):
        k = options.bounces
    model = _Model(
        grid=Grid(width, height, n_theta, 1),
        bounces=max(k, 2),
        crop=crop,
        converges=True,
        rho=rho,
        geometry=geometry,
    )
    return _with_tail(model, options)


def _extrapolated(model: _Model, options: FitOptions) -> _Model:
    """The cheap model of the solve: where the fit corrects its answer to the model it
    needs (``correct``) and sizes the series itself, a long series (a tail, or more
    than :data:`SCAN_TAIL_BOUNCES` bounces) becomes that many bounces and a geometric
    tail (:func:`lightfield_jax.inverse.joint.unit_model`); its Jacobian only guides the
    correction, which renders the series in full."""
    auto = options.bounces == "auto" and options.tail == "auto"
    long = model.tail is not None or model.bounces > SCAN_TAIL_BOUNCES
    if not (options.correct and auto and long and model.converges):
        return model
    return dataclasses.replace(model, bounces=SCAN_TAIL_BOUNCES, tail=None, extrapolate=True)


def _rho_of(options: FitOptions):
    """ρ(g, albedos) of the model's phase convention (ω for the slab and ``normalized``)."""

    def rho(g: float, albedos):
        a = float(_phase_integral(g)) if options.phase == "paper" else 1.0
        return np.asarray(albedos) * a

    return rho


# Explicit bounces of the scan on a model with a tail: the orders beyond them are
# extrapolated geometrically (:func:`lightfield_jax.inverse.basins.scan`).
SCAN_TAIL_BOUNCES = 24


def _run_scan(data: _Data, pattern, model: _Model, options, black, weights, sigma_t0) -> Scan:
    extrapolate = model.tail is not None
    if extrapolate:
        model = dataclasses.replace(model, bounces=SCAN_TAIL_BOUNCES, tail=None)
    renderer, full = _joint_parts(pattern, model, options.phase)
    dtype = jnp.result_type(float)
    with stopwatch() as timing:
        cost, black_map, gs, albedos, ratios, refs = scan(
            renderer,
            full,
            jnp.asarray(data.images, dtype),
            jnp.asarray(weights, dtype),
            sigma_t0,
            phase=options.phase,
            lit=pattern.lit,
            black_level=black,
            rho_limit=_rho_of(options),
            extrapolate=extrapolate,
        )
    found = basins(cost, black_map, gs, albedos, options.basin_tolerance, options.max_basins)
    return Scan(
        gs=gs,
        albedos=albedos,
        misfit=cost,
        black=black_map,
        basins=found,
        sigma_t=sigma_t0,
        seconds={"compile": timing.compile, "run": timing.run},
        ratios=ratios if extrapolate else None,
        sigma_s_ref=refs,
    )


def _same_answer(a: dict, b: dict) -> bool:
    return (
        abs(a["sigma_t"] / b["sigma_t"] - 1) < 1e-3
        and abs(a["sigma_s"] / b["sigma_s"] - 1) < 1e-2
        and abs(a["g"] - b["g"]) < 1e-2
    )


def _continuation(data, pattern, first: _Stage, options, black, images, floor, the_scan, say):
    """The joint fit after its first stage ``first`` (the cheap model's solve): the
    model its answer needs (the larger of that and ``floor``) reached by defect
    correction (``correct``: :func:`_corrected`), or else solved on (capped by
    ``max_cells``: two solves, the second with the model's weights). Returns the last
    stage (``first`` itself when it ends at a bound of the model or in a basin worse
    than the scan's best; a refit of the cheap model with the model's weights where
    that model already covers the need)."""
    coarse = first.model
    v = first.values
    albedo = v["sigma_s"] / v["sigma_t"]
    if at_bound(v, BLACK_RANGE if black is None else None) or worse_basin(
        the_scan, v["g"], albedo, options.basin_tolerance
    ):
        # At a bound or in a worse basin on the cheap model: not trustworthy whatever
        # the model, and not worth the large model it would ask for.
        say("  at a bound or in a worse basin on the cheap model: not refined")
        return first
    ratio = the_scan.ratio_at(v["g"], albedo)

    def needed(max_cells: int) -> _Model:
        model = size_model(
            images,
            pattern,
            albedo=min(albedo, 0.98),
            g=v["g"],
            options=dataclasses.replace(options, max_cells=max_cells),
            margin=1.03,
            sigma_t=v["sigma_t"],
            crop=coarse.crop,
        )
        return _by_measured_ratio(model, options, ratio)

    # The solve's model is capped by max_cells (the forward-mode Jacobian's memory);
    # the corrected one, reached by primal renders, by max_render_cells.
    need = needed(options.max_cells)
    correct = options.correct and first.ok
    if correct:
        target = _at_least(_at_least(needed(options.max_render_cells), need), floor)
    else:
        need = target = _at_least(need, floor)
    if _covers(coarse, target):
        # The cheap model is already as large as the answer needs: refit it with the
        # model's weights, and that is the answer.
        return _joint_stage(
            data, pattern, coarse, options, black, _joint_reweighted(data, first), first.y
        )
    spent, record = {"compile": 0.0, "run": 0.0}, None
    if correct:
        say(
            f"  defect correction to the final model n_theta {target.grid.n_theta}, refine "
            f"{target.grid.refine}, {_orders(target)}"
        )
        done, record = _corrected(data, pattern, first, target, options, black, say)
        if done is not None:
            return done
        spent = record["seconds"]
        say(f"  the correction stopped ({record['stopped']}): solving on the final model")
    if _covers(coarse, need):
        last = _joint_stage(
            data, pattern, coarse, options, black, _joint_reweighted(data, first), first.y
        )
    else:
        say(
            f"  final model n_theta {need.grid.n_theta}, refine {need.grid.refine}, {_orders(need)}"
        )
        mid = _joint_stage(data, pattern, need, options, black, first.weights, first.y)
        last = _joint_stage(
            data, pattern, need, options, black, _joint_reweighted(data, mid), mid.y
        )
        last.steps += mid.steps
        last.compile += mid.compile
        last.run += mid.run
    last.compile += spent["compile"]
    last.run += spent["run"]
    if record is not None:
        last.correction = {**record, "fallback": "solved on the model instead"}
    return last


def _orders(model: _Model) -> str:
    if model.extrapolate:
        return f"{model.bounces} bounces and a geometric tail"
    if model.tail is None:
        return f"{model.bounces} bounces"
    return f"K0 = {model.bounces} and a {model.tail} tail"


def _corrected(data: _Data, pattern, first: _Stage, target: _Model, options, black, say):
    """``target``'s answer by defect correction from ``first`` (the cheap model's solve:
    its answer and Jacobian, model weights from its answer; :mod:`.correction`): the
    stage (``None`` where the iteration did not converge) and its record."""
    renderer, full = _joint_parts(pattern, target, options.phase)
    dtype = first.y.dtype
    weights = _joint_reweighted(data, first)

    def render(v):
        return _render_model(renderer, full, pattern, target, v, dtype)

    with stopwatch() as timing:
        c = correct(
            render,
            data.images,
            weights,
            first.values,
            first.jac_unit,
            BLACK_RANGE if black is None else None,
            options.correction_renders,
            noise_scale(data.images, weights, pattern),
        )
    for step in c.steps:
        say(f"    step {step['size']:.2e} ({step['jacobian']} Jacobian)")
    record = {
        "renders": c.renders,
        "converged": c.converged,
        "stopped": c.reason,
        "steps": c.steps,
        "seconds": {"compile": timing.compile, "run": timing.run},
    }
    if not (c.converged and first.ok):
        return None, record
    v = c.values
    stage = _Stage(
        model=target,
        values={k: v[k] for k in ("sigma_t", "sigma_s", "g", "black_level", "gain")},
        y=pack((v["sigma_t"], v["sigma_s"], v["g"], v["black_level"]), black is None, dtype),
        ok=True,
        message=first.message,
        steps=0,
        unit=c.unit,
        jac=c.jac,
        weights=weights,
        residual=c.residual,
        rms=_rms(c.residual, data),
        compile=timing.compile,
        run=timing.run,
        tail=c.tail,
        jac_unit=None,
        correction=record,
    )
    return stage, record


def _render_model(renderer, full, pattern, model: _Model, v: dict, dtype):
    """``model``'s render at unit gain at ``v`` (σt, σs, g, black level), as float64
    numpy, and its tail solve's ``{"steps", "converged"}`` (``None`` without a tail)."""
    unit, tail = model_at(
        renderer,
        full,
        pattern.lit,
        v["sigma_t"],
        v["sigma_s"],
        v["g"],
        v["black_level"],
        dtype,
        model.extrapolate,
    )
    unit = np.asarray(jax.block_until_ready(unit), np.float64)
    status = None
    if model.tail is not None:
        status = {"steps": int(tail.steps), "converged": bool(tail.converged)}
    return unit, status


def _finer(model: _Model, options: FitOptions, g: float) -> _Model:
    """A finer model than ``model`` for its error term: twice the θ bins (and the slab's
    elevation nodes and depth layers); on the plane also the spatial refinement the size
    rule asks for at the answer's ``g`` where the fit's model stayed below it (the cell
    cap sized it down: a forward medium's model error is then mostly spatial, and a
    term that did not see it would report the fit as noise-limited); the same bounces
    with the rest of the series extrapolated geometrically or, with a tail, the same K0
    and a tail tolerance ten times as tight."""
    grid = model.grid
    geometry = model.geometry
    if geometry is not None:
        geometry = dataclasses.replace(
            geometry, n_mu=min(2 * geometry.n_mu, 32), n_z=min(2 * geometry.n_z, 8)
        )
        grid = dataclasses.replace(grid, n_theta=min(2 * grid.n_theta, 64))
    else:
        grid = dataclasses.replace(
            grid,
            n_theta=min(2 * grid.n_theta, 256),
            refine=max(grid.refine, default_refine(g)),
        )
    if model.tail is not None:  # the same K0, a tail ten times as tight
        return dataclasses.replace(
            model, grid=grid, geometry=geometry, tail_tol=model.tail_tol / 10
        )
    # The same bounces and, where the fit sized them, the orders past them summed
    # geometrically from the last per-bounce ratio: the series' truncation error shows
    # in r_fine − r as it did when 1.5× + 4 bounces were marched, at the cost of the
    # bounces already marched (the dense forward medium, 128×96: 32 bounces instead of
    # 52 at 128 θ bins and refine 2).
    return dataclasses.replace(
        model, grid=grid, geometry=geometry, extrapolate=not isinstance(options.bounces, int)
    )


def _model_shift(data: _Data, pattern, stage: _Stage, options: FitOptions) -> tuple:
    """r_fine − r at the solution (one render of :func:`_finer`'s model), that model, its
    tail solve's steps and convergence (``None`` without a tail) and its seconds."""
    fine = _finer(stage.model, options, stage.values["g"])
    renderer, full = _joint_parts(pattern, fine, options.phase)
    v = stage.values
    with stopwatch() as timing:
        unit, fine_tail = _render_model(renderer, full, pattern, fine, v, jnp.result_type(float))
    shift = (stage.weights * v["gain"] * (unit - stage.unit)).reshape(-1)
    return shift, fine, fine_tail, timing


def _joint_fit(data: _Data, pattern, options: FitOptions, black, images, crop, rho0, floor, say):
    """The joint fit with its global start (:mod:`lightfield_jax.inverse.basins`): scan, solve
    every basin kept (or the given start), keep the best; then the error budget and the
    verdict. Returns the :func:`_finish` keywords and the seconds."""
    seconds = {"compile": 0.0, "run": 0.0}

    def count(t):
        seconds["compile"] += t["compile"] if isinstance(t, dict) else t.compile
        seconds["run"] += t["run"] if isinstance(t, dict) else t.run

    coarse = _scan_model(crop, options, rho0)
    weights = joint_weights(data.images, data.mask, data.exposure)
    marched = (
        f"{coarse.bounces} bounces"
        if coarse.tail is None
        else f"{SCAN_TAIL_BOUNCES} bounces and a geometric tail"
    )
    say(
        f"basin scan: g x albedo on a {coarse.grid.width}x{coarse.grid.height} model, "
        f"n_theta {coarse.grid.n_theta}, {marched}"
    )
    the_scan = _run_scan(data, pattern, coarse, options, black, weights, data.sigma_t0)
    count(the_scan.seconds)
    st0 = data.sigma_t0
    if options.start is not None:
        ss, g = options.start
        starts = [("given", (st0, ss, g, 0.0 if black is None else black))]
    else:
        found = the_scan.basins if options.basin_search else the_scan.basins[:1]
        if not found:
            raise ValueError(
                "the basin scan found no valid model for this capture (every albedo's "
                "bounce series diverges or is truncated): give bounces or a start"
            )
        starts = [
            (f"basin {i}", (st0, b.albedo * st0, b.g, b.black_level if black is None else black))
            for i, b in enumerate(found)
        ]
    # One cheap model for every start: marched where the scan's measured ratio at each
    # start allows it (see _by_measured_ratio).
    ratio = max(the_scan.ratio_at(s[2], s[1] / s[0]) for _, s in starts)
    coarse = _extrapolated(_by_measured_ratio(coarse, options, ratio), options)
    if the_scan.ratios is not None:
        say(f"  measured per-bounce ratio {ratio:.3f}")
    say(f"  the solve's model: {_orders(coarse)}")
    tried, stages, labels = [], [], []
    dtype = jnp.result_type(float)
    for label, start in starts:
        say(f"joint fit from {label}: sigma_s {start[1]:.4g}, g {start[2]:.3f}")
        y0 = pack(start, black is None, dtype)
        first = _joint_stage(data, pattern, coarse, options, black, weights, y0)
        count(first)
        record = {
            "label": label,
            "start": {"sigma_t": start[0], "sigma_s": start[1], "g": start[2]},
        }
        same = next(
            (i for i, (f, _) in enumerate(stages) if _same_answer(f.values, first.values)), None
        )
        if same is not None:  # the cheap model's answer of an earlier start: not again
            tried.append({**record, "same_as": labels[same]})
            say(f"  {label}: the same answer as {labels[same]}")
            continue
        last = _continuation(data, pattern, first, options, black, images, floor, the_scan, say)
        count(last)
        tried.append(
            {
                **record,
                "final": {k: last.values[k] for k in ("sigma_t", "sigma_s", "g")},
                "residual": last.rms,
                "converged": last.ok,
                "iterations": first.steps + last.steps,
            }
        )
        say(
            f"  {label}: sigma_t {last.values['sigma_t']:.5g}, sigma_s "
            f"{last.values['sigma_s']:.5g}, g {last.values['g']:.4f}, residual {last.rms:.4g} "
            f"after {first.steps + last.steps} solver iterations"
        )
        stages.append((first, last))
        labels.append(label)
    # The best final misfit (models may differ between starts: the weighted RMS is
    # comparable across them).
    best = min(range(len(stages)), key=lambda i: stages[i][1].rms)
    last = stages[best][1]
    solved = [r for r in tried if "final" in r]
    for i, record in enumerate(solved):
        record["chosen"] = i == best

    names = ["sigma_t", "sigma_s", "g", "gain"] + (["black_level"] if black is None else [])
    fit_black = black is None
    noise = noise_scale(data.images, last.weights, pattern)
    shift, fine, fine_tail = None, None, None
    if options.model_error:
        shift, fine, fine_tail, t = _model_shift(data, pattern, last, options)
        count(t)
    budget = error_budget(last.jac, last.residual, names, noise, shift)
    v = last.values
    reasons = untrustworthy(v, budget, options.max_chi2, BLACK_RANGE if fit_black else None)
    reasons += tail_unconverged(last.tail, last.model.tail_max_steps, "the model")
    reasons += tail_unconverged(fine_tail, fine.tail_max_steps if fine else 0, "the finer model")
    other = worse_basin(the_scan, v["g"], v["sigma_s"] / v["sigma_t"], options.basin_tolerance)
    if other is not None:
        reasons.append(
            f"in a worse basin than the scan's best (g {other.g:.2f}, albedo "
            f"{other.albedo:.2f}, scan misfit {other.misfit:.3g})"
        )
    ok, msg = last.ok, last.message
    if reasons:
        ok, msg = False, "not trustworthy: " + "; ".join(reasons) + f" (solver: {msg})"
    model_dict = last.model.as_dict()
    if last.tail is not None:
        model_dict["tail"].update(last.tail)
    if last.correction is not None:
        model_dict["correction"] = last.correction
    if fine is not None:
        model_dict["finer_model"] = {
            "n_theta": fine.grid.n_theta,
            "refine": fine.grid.refine,
            "bounces": fine.bounces,
            "extrapolated": fine.extrapolate,
            **(
                {"n_mu": fine.geometry.n_mu, "n_z": fine.geometry.n_z}
                if fine.geometry is not None
                else {}
            ),
            **(
                {"tail": {"method": fine.tail, "tol": fine.tail_tol, **fine_tail}}
                if fine_tail is not None
                else {}
            ),
        }
    scan_dict = the_scan.as_dict()
    scan_dict["tried"] = tried
    return (
        last.model,
        seconds,
        dict(
            method="joint",
            sigma_t=v["sigma_t"],
            sigma_s=v["sigma_s"],
            g=v["g"],
            gain=v["gain"],
            black_level=v["black_level"],
            budget=budget,
            converged=ok,
            message=msg,
            iterations=sum(r["iterations"] for r in solved),
            residual=last.rms,
            basins=scan_dict,
            reasons=tuple(reasons),
            model_dict=model_dict,
        ),
    )


# ------------------------------------------------------------------------- driver


def fit_images(
    images,
    pattern: Stripes,
    *,
    mask=None,
    black_level: float | None = None,
    saturation: float | None = None,
    pixel_size_mm: float | None = None,
    options: FitOptions | None = None,
    progress: Callable[[str], None] | None = None,
    split=None,
    exposure=None,
    **overrides,
) -> FitResult:
    """Fit one channel of a stripe capture.

    Args:
        images: the shifted images, ``(shifts, height, width)``, dark frame already
            subtracted, cropped to the medium (its edges are the walls).
        pattern: the stripes that lit them (one phase per image).
        mask: ``True`` where a pixel is valid (finite, unsaturated) in every shift.
        black_level: the projector's dark-stripe level relative to a lit stripe, or
            ``None`` (unknown: ``joint`` estimates it, the two-step methods assume 0).
        saturation: value at or above which pixels are clipped (excluded).
        pixel_size_mm: to report coefficients in mm⁻¹ as well.
        options: :class:`FitOptions`; keyword ``overrides`` replace its fields.
        progress: called with a short description of each stage.
        split: ``(direct, multiple)`` images to use instead of separating the capture
            (e.g. a perfect split from a renderer: I_1 and Σ_{k≥2} I_k under full
            illumination). Used by the two-step methods and the joint fit's start.
        exposure: the effective exposure T of merged exposure brackets, like
            ``images`` (:mod:`lightfield_jax.capture.hdr`): the joint fit weights by √T.
    """
    options = dataclasses.replace(options or FitOptions(), **overrides)
    return _fit_one(
        images,
        pattern,
        options,
        progress,
        mask=mask,
        black_level=black_level,
        saturation=saturation,
        pixel_size_mm=pixel_size_mm,
        split=split,
        exposure=exposure,
    )


def _fit_one(
    images,
    pattern: Stripes,
    options: FitOptions,
    progress,
    *,
    mask=None,
    black_level=None,
    saturation=None,
    pixel_size_mm=None,
    split=None,
    exposure=None,
    floor: _Model | None = None,
) -> FitResult:
    """:func:`fit_images` with a ``floor``: the smallest model to use (its crop, θ bins,
    refinement, bounces), so that the channels of a capture share compiled programs."""
    if as_geometry(options.geometry).chosen_by_fit:
        return _fit_auto_geometry(
            images,
            pattern,
            options,
            progress,
            mask=mask,
            black_level=black_level,
            saturation=saturation,
            pixel_size_mm=pixel_size_mm,
            split=split,
            exposure=exposure,
        )
    # The plane is None from here on; the slab's 3-D Henyey–Greenstein is normalised on
    # the sphere (ρ = ω): its phase convention is "normalized".
    geometry = as_geometry(options.geometry)
    options = dataclasses.replace(
        options,
        geometry=geometry.slab_or_none,
        phase=geometry.phase_convention(options.phase),
    )
    say = progress or (lambda _msg: None)
    method = method_for(options.method)
    t_start = time.perf_counter()
    say("separating direct and multiple scattering")
    whole = prepare_data(
        images,
        pattern,
        mask=mask,
        black_level=black_level,
        saturation=saturation,
        split=split,
        exposure=exposure,
    )
    # A first model. Σ M / Σ D ≈ Σ_{k≥2} I_k / I_1 ≈ ρ/(1 − ρ) sizes the bounces (with
    # margin: the separation biases M low).
    ratio = max(whole.multiple_ratio, 0.0)
    rho0 = min(ratio / (1.0 + ratio) * 1.5 + 0.05, 0.95)
    crop = floor.crop if floor is not None else None
    model = size_model(
        whole.images,
        pattern,
        albedo=rho0,
        g=0.0,
        options=options,
        sigma_t=whole.sigma_t0,
        crop=crop,
    )
    problem = FitProblem(
        data=whole.cropped(model.crop),
        images=whole.images,
        pattern=pattern,
        black_level=black_level,
        model=model,
        rho0=rho0,
        floor=floor,
    )
    solution = method.solve(problem, options, say)
    return _finish(
        options,
        t_start,
        solution.seconds,
        solution.model,
        pixel_size_mm=pixel_size_mm,
        **solution.values,
    )


def _covers(have: _Model, need: _Model) -> bool:
    # A tail sums every order past K0: it covers any bounce count, a march only its own;
    # an extrapolated series (the cheap solve's) covers none (it is always corrected).
    if have.extrapolate:
        return False
    if need.tail is not None:
        orders = have.tail == need.tail and have.bounces >= need.bounces
    else:
        orders = have.tail is not None or have.bounces >= need.bounces
    return (
        have.crop == need.crop
        and orders
        and have.grid.n_theta >= need.grid.n_theta
        and have.grid.refine >= need.grid.refine
    )


def _finish(options: FitOptions, t_start: float, seconds: dict, model: _Model, **values):
    """The :class:`FitResult`, with total time, the model used and the error budget."""
    seconds = dict(seconds)
    seconds["total"] = time.perf_counter() - t_start
    # Everything that is not XLA compilation (tracing included) counts as run time.
    seconds["run"] = seconds["total"] - seconds["compile"]
    budget: Uncertainty = values.pop("budget")

    def per_param(d):
        return {k: d.get(k, math.nan) for k in _PARAMS if k in d or k != "black_level"}

    black = values.pop("black_level")
    numbers = ("sigma_t", "sigma_s", "g", "gain", "residual")
    bad = [k for k in numbers[:4] if not math.isfinite(float(values[k]))]
    if bad:  # never a silent NaN: the fit failed
        values["converged"] = False
        values["message"] = f"non-finite result ({', '.join(bad)}); {values['message']}"
    model_dict = values.pop("model_dict", None) or model.as_dict()
    return FitResult(
        **{k: float(values.pop(k)) for k in numbers},
        black_level=None if black is None else float(black),
        uncertainty=per_param(budget.total),
        correlation=budget.correlation,
        condition_number=budget.condition_number,
        uncertainty_statistical=per_param(budget.statistical),
        uncertainty_model=per_param(budget.model),
        chi2_dof=budget.chi2_dof,
        chi2_model=budget.chi2_model,
        noise=budget.noise,
        model_limited=budget.model_limited,
        converged=bool(values.pop("converged")),
        iterations=int(values.pop("iterations")),
        seconds=seconds,
        model=model_dict,
        phase=options.phase,
        **values,
    )


def _fit_auto_geometry(images, pattern: Stripes, options: FitOptions, progress, **kwargs):
    """``geometry: auto``: the plane model's fit, kept where its misfit is below the
    capture's relative noise; the slab's fit otherwise. The result carries the choice
    and its evidence in ``model["geometry_choice"]``."""
    say = progress or (lambda _msg: None)
    auto: AutoGeometry = options.geometry

    def fit_with(geometry) -> FitResult:
        opts = dataclasses.replace(options, geometry=geometry)
        return fit_images(images, pattern, options=opts, progress=progress, **kwargs)

    def chose(result: FitResult, choice: dict) -> FitResult:
        return dataclasses.replace(result, model={**result.model, "geometry_choice": choice})

    if abs((pattern.direction_deg - _INWARD_DEG[pattern.entry] + 180.0) % 360.0 - 180.0) > 1e-6:
        # The model-free noise estimate differences along a pixel axis; oblique stripes
        # put their edges into it. Without a measurable noise, the slab (always valid).
        say("geometry auto: oblique stripes, the noise is not measurable: slab")
        reason = {"chosen": "slab", "reason": "oblique stripes: noise not measurable"}
        return chose(fit_with(auto.slab), reason)
    say("geometry auto: fitting the plane model")
    plane = fit_with(None)
    data = np.asarray(images, np.float64)
    mask = kwargs.get("mask")
    keep = np.all(np.isfinite(data), axis=0)
    if mask is not None:
        keep &= np.asarray(mask, bool)
    model, _ = fitted_images(plane, pattern, data.shape[-2:])
    x0, y0, x1, y1 = plane.model["crop"]
    region = np.zeros_like(keep)
    region[y0:y1, x0:x1] = True
    noise = relative_noise(data, pattern, keep & region)
    decision = choose(misfit(model.sum(axis=1), data, keep & region), noise, auto.threshold)
    say(
        f"geometry auto: plane misfit {decision.plane_misfit:.2e}, noise "
        f"{decision.noise:.2e}, plane error {decision.plane_error:.2e}: {decision.chosen}"
    )
    if decision.chosen == "plane":
        return chose(plane, decision.as_dict())
    result = fit_with(auto.slab)
    seconds = dict(result.seconds)
    seconds["plane_fit"] = plane.seconds.get("total", math.nan)
    seconds["total"] = seconds.get("total", 0.0) + seconds["plane_fit"]
    return chose(dataclasses.replace(result, seconds=seconds), decision.as_dict())


def _model_from(d: dict) -> _Model:
    """The :class:`_Model` of a result's ``model`` dict (one written without the series'
    estimate, e.g. by an earlier version, renders alike: what is not given is unknown)."""
    geometry = parse_geometry(d.get("geometry"), "model.geometry")
    tail = d.get("tail") or {}
    return _Model(
        grid=Grid(d["width"], d["height"], d["n_theta"], d["refine"]),
        bounces=d["bounces"],
        crop=tuple(d["crop"]),
        converges=d.get("series_converges", True),
        rho=d.get("rho_estimate", math.nan),
        geometry=geometry.slab_or_none,
        tail=tail.get("method"),
        tail_tol=tail.get("tol", 1e-4),
        tail_max_steps=tail.get("max_steps", 200),
        ratio=d.get("ratio_measured"),
        extrapolate=bool(d.get("extrapolated", False)),
    )


def fitted_images(result: FitResult, pattern: Stripes, shape: tuple[int, int]):
    """The fitted model's per-bounce images of every pattern and under full illumination,
    gain and black level included, over the cropped model region placed in an image of
    ``shape`` (zeros outside): ``(stripes [P, K, H, W], full [K, H, W])``. A model with
    a tail has K = K0 + 1: the last slice holds the tail Σ_{k>K0} I_k."""
    model = _model_from(result.model)

    def render(illumination):
        out = _renderer(model, illumination, result.phase)(result.sigma_t, result.sigma_s, result.g)
        if model.tail is None:
            return np.asarray(out[0])
        return np.concatenate([np.asarray(out[0]), np.asarray(out[2].image)[:, None]], axis=1)

    c, b = result.gain, result.black_level or 0.0
    stripes, full = render(pattern), render(_full_for(pattern))[0]
    stripes = c * ((1 - b) * stripes + b * full[None])
    full = c * full
    x0, y0, x1, y1 = model.crop
    out_s = np.zeros(stripes.shape[:2] + tuple(shape))
    out_f = np.zeros(full.shape[:1] + tuple(shape))
    out_s[..., y0:y1, x0:x1] = stripes
    out_f[..., y0:y1, x0:x1] = full
    return out_s, out_f
