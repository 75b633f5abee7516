"""The settings and the result of a fit: :class:`FitOptions` (every setting of
:func:`~lightfield_jax.fit_images`, checked when made) and :class:`FitResult` (the fitted
values, their 1σ uncertainties and correlations, the verdict, the timings and the model
used), with the helpers of its ``results.json`` form (:meth:`FitResult.to_dict`: strict
JSON, σa's and the albedo's errors from the correlations).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import optimistix as optx

from lightfield_jax.checks import check_flag, check_int, check_number, number_problem, shown
from lightfield_jax.forward.base import MAX_BOUNCES, too_many_bounces
from lightfield_jax.forward.tail import TAIL_METHODS
from lightfield_jax.inverse.method_base import (
    MAX_G_VALUES,
    FitMethod,
    check_method,
    check_solver,
    check_start,
)
from lightfield_jax.inverse.verdict import OFFSET_EXPLAINS
from lightfield_jax.scene.geometry import AutoGeometry, Plane, Slab, as_geometry
from lightfield_jax.scene.grid import check_n_theta, check_refine
from lightfield_jax.scene.medium import PHASE_CONVENTIONS
from lightfield_jax.scene.phase import phase_integral_at

PARAMS = ("sigma_t", "sigma_s", "g", "gain", "black_level")

# The loosest solver tolerance (looser ones stop the solve where it starts). The most
# bounces a fit marches is the renderer's MAX_BOUNCES (each bounce's images are kept).
MAX_TOLERANCE = 0.01
# The most iterations a solve may be given (max_steps, tail_max_steps; past this no
# limit): the solvers count them in int32 (max_steps 10**12 would end in "an overflow
# ... argument path is y", after the loading and compilation, naming no key).
MAX_ITERATIONS = 10**9


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """Settings of a fit (all optional).

    Attributes:
        method: ``joint`` (default), ``gradient`` or ``grid``, or a fit method
            (:class:`~lightfield_jax.Joint`, :class:`~lightfield_jax.TwoStep`,
            :class:`~lightfield_jax.GridSearch`: :mod:`lightfield_jax.inverse.methods`)
            whose own settings (its solver, start, grid size) replace these.
        phase: phase convention of the model (``paper`` or ``normalized``).
        bounces: K, or ``"auto"`` from the tail bound at the starting estimate. K is
            marched as given, so it cannot go with a named ``tail`` (whose explicit
            bounces are ``tail_bounces``).
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
        coarse_after: (``joint``, plane) the bounces after this many are marched on the
            native grid where the model the answer needs is refined (|g| > 0.65) and
            marches more: later bounces are smooth in space, and this changes the image
            of the series by 5e-5 (g 0.7) to 6e-4 (g 0.8) of its peak at 0.4–0.5× the
            render's cost (docs/tail_acceleration.md); ``None``: every bounce on the
            model's grid. The error term's finer model marches twice as many bounces
            refined before its coarse tail, so its term sees the coarse grid's error
            where most of the coarse bounces' light is.
        tail_max_steps: iteration limit of a tail solve; one that stops there makes
            the result not trustworthy.
        n_theta: direction bins, or ``None`` to choose them from the starting g.
        refine: spatial refinement, or ``None`` to choose it from the starting g.
        g_grid: number of g values of the ``grid`` method's search on (−0.95, 0.95).
        start_grid: number of g values of the coarse search that starts ``gradient``.
        max_cells: cap on the model's working size (W·H·n_theta·refine²): the
            refinement, then n_theta, are lowered to fit it; never values the options
            fix, nor n_theta below 32 (8 on the slab): a model left larger is said in
            a note (the progress callback's ``note: ...``).
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
            and on the residual's components; the joint fit's residual is solved
            normalised, Σ(w·I)² = 1e3: :data:`~lightfield_jax.inverse.joint.RESIDUAL_GAIN`);
            ``None`` picks them from the data's
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
        stripe_cell: (``joint``, plane) render stripes entering a side wall from one
            stripe period (:class:`~lightfield_jax.forward.cell.CellRenderer`, within
            0.2 % of the full render) in the final model and the error term where they
            are refined (refine ≥ 2): a warm fit of a dense forward capture about 3×
            faster; the first fit of a process compiles more (docs/periodic_cell.md).
            ``False``: those models render the whole tank.
        extrapolate: (``joint``, plane) where the error term's finer model is finer in
            space, report the answer extrapolated to the continuum: the model's
            discretisation error is first order in the cell size, so the answer steps
            r_f/(r_f − r) times the finer model's shift (Richardson) and the model term
            is that shift; ``False``: the model's own answer, with that whole step as
            its model term.
        max_render_cells: cap on the corrected model's working size (as ``max_cells``,
            for primal renders, which need no tangents).
        correction_renders: at most this many renders at iterates in the correction
            (besides one per parameter for the Jacobian); it stops sooner where its
            steps, shrinking at their last rate, would not converge within them.
        max_chi2: χ²/dof against the capture's noise above which a joint fit is not
            trustworthy (its misfit is far above the noise).
        offset_stop: (``joint``) where one constant added to every image value would
            leave less than this share of the basin scan's best misfit (a camera
            pedestal or a dark level that subtracts too much: light the model does not
            have), the fit stops after the scan and one solve on the cheap model, not
            trusted, and names the constant; ``0`` never stops there (the constant is
            then named after the full fit). At most 0.25.
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
    coarse_after: int | None = 8
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
    extrapolate: bool = False
    stripe_cell: bool = True
    max_render_cells: int = 8_000_000
    correction_renders: int = 16
    max_chi2: float = 100.0
    offset_stop: float = 0.05
    solver: optx.AbstractLeastSquaresSolver | None = None

    def __post_init__(self):
        method = check_method(self.method)  # a known name or a FitMethod's
        if self.tail is not None and not (
            isinstance(self.tail, str) and (self.tail == "auto" or self.tail in TAIL_METHODS)
        ):
            raise ValueError(
                f"tail: must be auto, None or one of {', '.join(TAIL_METHODS)}, got {self.tail!r}"
            )
        if number_problem(self.bounces, integer=True) is None and self.tail in TAIL_METHODS:
            # A named tail keeps tail_bounces explicit bounces: a count given as
            # ``bounces`` as well would be silently replaced.
            raise ValueError(
                f"bounces: {self.bounces} marches exactly that many bounces, but tail: "
                f"{self.tail} keeps tail_bounces ({self.tail_bounces}) explicit bounces "
                "before its solve: give tail_bounces instead (or tail: null to march)"
            )
        # Every number is one (True, "8", 8.5 or None refused: lightfield_jax.checks);
        # every switch a bool ("no" is true).
        for name, least in (
            ("tail_bounces", 2),
            ("tail_max_steps", 1),
            ("max_basins", 1),
            ("correction_renders", 1),
            ("max_cells", 1),
            ("max_render_cells", 1),
        ):
            check_int(getattr(self, name), name, low=least)
        check_int(self.tail_max_steps, "tail_max_steps", high=MAX_ITERATIONS)
        if self.coarse_after is not None:
            check_int(self.coarse_after, "coarse_after", low=2, high=MAX_BOUNCES)
        check_int(self.g_grid, "g_grid", low=3, high=MAX_G_VALUES)
        check_number(self.basin_tolerance, "basin_tolerance", low=0.0, allow_inf=True)
        check_number(self.offset_stop, "offset_stop", low=0.0, high=OFFSET_EXPLAINS)
        flags = ("crop", "basin_search", "model_error", "correct", "extrapolate", "stripe_cell")
        for name in flags:
            check_flag(getattr(self, name), name)
        if self.geometry is not None:
            as_geometry(self.geometry)
        if not self.max_render_cells >= self.max_cells:
            raise ValueError(
                f"max_render_cells: must be at least max_cells ({self.max_cells}), got "
                f"{self.max_render_cells!r}"
            )
        self._check_ranges()
        object.__setattr__(self, "start", check_start(self.start))  # a tuple of floats
        check_solver(self.solver)
        # A setting the chosen method does not use is refused, not ignored silently (a
        # start with the grid search, which searches g; a solver with it, which solves
        # nothing).
        unused = {"start": self.start is not None and method != "joint"}
        unused["solver"] = self.solver is not None and method == "grid"
        for name, is_unused in unused.items():
            if is_unused:
                raise ValueError(
                    f"{name}: the {method} method does not use it (start: the joint "
                    "fit's; solver: the joint and gradient fits'): drop it, or choose a "
                    "method that does"
                )
        # NumPy numbers (np.int64(20), a 0-d array) are numbers here, stored as Python's:
        # optimistix took max_steps=np.int64(20) only after the scan ("`max_steps` must
        # be a Python integer", seconds into the fit).
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, np.generic) or (isinstance(value, np.ndarray) and value.ndim == 0):
                object.__setattr__(self, field.name, value.item())

    def _check_ranges(self) -> None:
        """Refuse settings the fit would otherwise ignore or quietly replace (a bounce
        count below 1 taken as 2, ``max_cells: 0`` or ``crop_fraction: 5`` ignored, a
        negative tolerance)."""

        def is_int(v) -> bool:
            return number_problem(v, integer=True) is None

        def is_number(v) -> bool:
            return number_problem(v, allow_inf=True) is None

        if not isinstance(self.phase, str) or self.phase not in PHASE_CONVENTIONS:
            raise ValueError(
                f"phase: must be one of {', '.join(PHASE_CONVENTIONS)}, got {self.phase!r}"
            )
        if (
            self.bounces != "auto"
            if isinstance(self.bounces, str)
            else not (is_int(self.bounces) and self.bounces >= 1)
        ):
            raise ValueError(f"bounces: must be an integer >= 1 or 'auto', got {self.bounces!r}")
        for name in ("bounces", "tail_bounces", "max_bounces"):
            value = getattr(self, name)
            if is_int(value) and value > MAX_BOUNCES:
                raise ValueError(too_many_bounces(name, value))

        if not (is_number(self.tolerance) and 0.0 < self.tolerance < 1.0):
            raise ValueError(f"tolerance: must lie in (0, 1), got {self.tolerance!r}")
        check_n_theta(self.n_theta, "n_theta")
        check_refine(self.refine, "refine")
        if not (is_int(self.start_grid) and self.start_grid >= 3):
            raise ValueError(f"start_grid: must be at least 3, got {self.start_grid!r}")
        for name in ("max_bounces", "max_cells", "max_steps"):
            value = getattr(self, name)
            if not (is_int(value) and value >= 1):
                raise ValueError(f"{name}: must be an integer >= 1, got {value!r}")
        check_int(self.start_grid, "start_grid", high=MAX_G_VALUES)
        check_int(self.max_steps, "max_steps", high=MAX_ITERATIONS)
        if not (is_number(self.crop_fraction) and 0.0 <= self.crop_fraction < 1.0):
            raise ValueError(
                f"crop_fraction: must lie in [0, 1) (a fraction of the peak), "
                f"got {self.crop_fraction!r}"
            )
        for name in ("rtol", "atol"):
            value = getattr(self, name)
            if value is not None and not (is_number(value) and 0.0 <= value <= MAX_TOLERANCE):
                # Looser, Levenberg-Marquardt stops at its start (measured: rtol = atol =
                # 0.1 returned the scan's start point, sigma_t 38 sigma off, "converged").
                raise ValueError(
                    f"{name}: must lie in [0, {MAX_TOLERANCE:g}] or be None, got {value!r}"
                )
        if not (is_number(self.max_chi2) and self.max_chi2 > 0):
            raise ValueError(f"max_chi2: must be > 0, got {self.max_chi2!r}")


@dataclasses.dataclass(frozen=True)
class FitResult:
    """What a fit recovered, and how much to trust it.

    Values are per pixel (σ's), the gain in image units per unit source irradiance.
    ``uncertainty`` holds the total 1σ errors (NaN where not estimated): the statistical
    part (``uncertainty_statistical``: the capture's noise, scaled up by √(χ²/dof)
    where that exceeds 1) ⊕ the model part (``uncertainty_model``: the shift a finer
    model's residual implies at the solution; the joint fit only). ``correlation`` holds
    the correlation coefficients between fitted parameters (e.g. ``"sigma_t,g"``) of the
    total's covariance (the noise's, plus the finer model's signed shift as a rank-one
    term), which goes with ``uncertainty``; ``correlation_statistical`` the noise's.
    ``chi2_dof`` is the misfit against the capture's noise (``noise``: the variance of
    one weighted residual that noise alone gives), ``chi2_model`` against the noise ⊕
    the model's own error (what the verdict uses). ``consistency`` (joint) holds, per
    split of the capture in two (``near/far`` from the entry wall, ``lit/dark`` by the
    stripes), the χ²₃ of the two parts' disagreement, its chance ``p`` and each part's
    larger shift from the answer: a split with ``p`` below 1e-3 shows a model error the
    finer model cannot, and its shift enters the model part. ``model_limited`` is true
    where the model part is the larger for σt, σs or g. ``converged`` is false, with
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
    correlation_statistical: dict = dataclasses.field(default_factory=dict)
    chi2_dof: float = math.nan
    chi2_model: float = math.nan
    noise: float = math.nan
    model_limited: bool = False
    consistency: dict = dataclasses.field(default_factory=dict)
    reasons: tuple[str, ...] = ()
    basins: dict | None = None

    @property
    def sigma_a(self) -> float:
        return self.sigma_t - self.sigma_s

    @property
    def albedo(self) -> float:
        if not self.sigma_t:
            return math.nan
        return self.sigma_s / self.sigma_t

    @property
    def rho(self) -> float:
        if not math.isfinite(self.g):
            return math.nan
        a = float(phase_integral_at(self.g)) if self.phase == "paper" else 1.0
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
            "correlation_statistical": {
                k: _json_float(v) for k, v in self.correlation_statistical.items()
            },
            "uncertainty_statistical": {
                k: _json_float(v) for k, v in self.uncertainty_statistical.items()
            },
            "uncertainty_model": {k: _json_float(v) for k, v in self.uncertainty_model.items()},
            "chi2_dof": _json_float(self.chi2_dof),
            "chi2_model": _json_float(self.chi2_model),
            "noise": _json_float(self.noise),
            "model_limited": self.model_limited,
            "consistency": {
                split: {
                    "chi2": _json_float(v["chi2"]),
                    "p": _json_float(v["p"]),
                    "shift": {k: _json_float(x) for k, x in v["shift"].items()},
                }
                for split, v in self.consistency.items()
            },
            "condition_number": _json_float(self.condition_number),
            "converged": self.converged,
            "reasons": list(self.reasons),
            "message": self.message,
            "iterations": self.iterations,
            "residual": _json_float(self.residual),
            # NaN or inf in the model's records (a tail solve's residual, a correction
            # step's misfit) made the strict JSON write fail after the fit.
            "seconds": _json_clean(self.seconds),
            "model": _json_clean(self.model),
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


def check_options(options, where: str) -> None:
    """Refuse ``options`` that are neither a :class:`FitOptions` nor ``None``
    (``ValueError("WHERE: options: ...")``), so that a dict does not end in dataclasses'
    bare "replace() should be called on dataclass instances", nor a falsy value ({}, 0)
    stand for the defaults."""
    if options is not None and not isinstance(options, FitOptions):
        raise ValueError(
            f"{where}: options: must be a FitOptions or None, got {type(options).__name__} "
            f"(its fields can also be given as keywords: {where}(..., max_steps=20))"
        )


def check_progress(progress, where: str, name: str = "progress") -> None:
    """Refuse a ``progress`` (or another callback, ``name``) that is neither callable
    nor ``None`` (``ValueError("WHERE: NAME: ...")``) at once: otherwise
    ``progress=True`` runs until the first stage, then fails with "TypeError: 'bool'
    object is not callable"."""
    if progress is not None and not callable(progress):
        takes = (
            "one argument (each stage's description)"
            if name == "progress"
            else "a channel's name and its result"
        )
        raise ValueError(
            f"{where}: {name}: must be a function of {takes} or None, got {shown(progress)}"
        )


def _json_float(v):
    v = float(v)
    return v if math.isfinite(v) else None


def _json_clean(obj):
    """Nested dicts/lists with non-finite floats as ``None`` (strict JSON)."""
    if isinstance(obj, dict):
        return {k: _json_clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_clean(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
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
    if not res.sigma_t or not math.isfinite(res.sigma_t):
        return math.nan
    # w = σs/σt: dw = dσs/σt - w dσt/σt, finite at σs = 0 (w = 0).
    w = res.sigma_s / res.sigma_t
    a, b = us / res.sigma_t, w * ut / res.sigma_t
    return math.sqrt(max(a**2 + b**2 - 2 * r * a * b, 0.0))
