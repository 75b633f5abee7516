"""The settings of a fit that are not its method's, one frozen record per concern, each
checked when made: :class:`ModelOptions` (the forward model: phase convention, bounces
and tail, grid, caps, crop, geometry), :class:`TrustOptions` (what the joint fit does to
earn and judge its answer: basins, the model's error, the defect correction, the
verdict's limits) and :class:`SolverOptions` (the optimistix solves' limits), together a
:class:`FitSettings`: what a fit method's ``solve``
(:class:`~lightfield_jax.inverse.method_base.FitMethod`) reads. The method's own settings
(its solver, start, grid size) are the method's (:mod:`lightfield_jax.inverse.methods`);
:class:`~lightfield_jax.FitOptions` (above this module) is a :class:`FitSettings` with its
method.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from lightfield_jax.checks import check_flag, check_int, check_number, number_problem
from lightfield_jax.forward.base import MAX_BOUNCES, too_many_bounces
from lightfield_jax.forward.tail import TAIL_METHODS
from lightfield_jax.inverse.verdict import OFFSET_EXPLAINS
from lightfield_jax.scene.geometry import AutoGeometry, Plane, Slab, as_geometry
from lightfield_jax.scene.grid import check_n_theta, check_refine
from lightfield_jax.scene.medium import PHASE_CONVENTIONS

# The loosest solver tolerance (looser ones stop the solve where it starts). The most
# bounces a fit marches is the renderer's MAX_BOUNCES (each bounce's images are kept).
MAX_TOLERANCE = 0.01
# The most iterations a solve may be given (max_steps, tail_max_steps; past this no
# limit): the solvers count them in int32 (max_steps 10**12 would end in "an overflow
# ... argument path is y", after the loading and compilation, naming no key).
MAX_ITERATIONS = 10**9
# The smallest relative change float64 resolves: the least that rtol or atol can be.
EPS = float(np.finfo(np.float64).eps)


def _is_int(v) -> bool:
    return number_problem(v, integer=True) is None


def _is_number(v) -> bool:
    return number_problem(v, allow_inf=True) is None


def _python_numbers(record) -> None:
    """NumPy numbers (np.int64(20), a 0-d array) in ``record``'s fields stored as
    Python's: optimistix took max_steps=np.int64(20) only after the scan ("`max_steps`
    must be a Python integer", seconds into the fit)."""
    for field in dataclasses.fields(record):
        value = getattr(record, field.name)
        if isinstance(value, np.generic) or (isinstance(value, np.ndarray) and value.ndim == 0):
            object.__setattr__(record, field.name, value.item())


@dataclasses.dataclass(frozen=True)
class ModelOptions:
    """The forward model a fit renders (all optional).

    Attributes:
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
        tail_max_steps: iteration limit of a tail solve; one that stops there makes
            the result not trustworthy.
        coarse_after: (``joint``, plane) the bounces after this many are marched on the
            native grid where the model the answer needs is refined (|g| > 0.65) and
            marches more: later bounces are smooth in space, and this changes the image
            of the series by 5e-5 (g 0.7) to 6e-4 (g 0.8) of its peak at 0.4–0.5× the
            render's cost (docs/tail_acceleration.md); ``None``: every bounce on the
            model's grid. The error term's finer model marches twice as many bounces
            refined before its coarse tail, so its term sees the coarse grid's error
            where most of the coarse bounces' light is.
        n_theta: direction bins, or ``None`` to choose them from the starting g.
        refine: spatial refinement, or ``None`` to choose it from the starting g.
        max_cells: cap on the model's working size (W·H·n_theta·refine²): the
            refinement, then n_theta, are lowered to fit it (on the slab, whose fields
            are allowed 4 × this, n_theta to 16 before the elevation nodes, then both
            in turn: :mod:`~lightfield_jax.inverse.slab_caps`); never values the options
            fix, nor n_theta below 32 (8 on the slab, with 4 elevation nodes): a model
            left larger is said in a note (the progress callback's ``note: ...``).
        crop: crop the model along the propagation direction to where the signal is
            above ``crop_fraction`` of its peak.
        crop_fraction: see ``crop``.
        geometry: the model's geometry: ``None`` or :class:`Plane` (the paper's 2-D
            model), a :class:`Slab` (the tank's depth, docs/model.md §7; its 3-D phase
            function is normalised on the sphere, so ``phase`` is ``normalized``), or
            :class:`AutoGeometry` (the plane where its misfit is below the capture's
            noise, else the slab: :mod:`lightfield_jax.inverse.model_choice`).
        stripe_cell: (``joint``) render stripes entering a side wall from one stripe
            period in the final model and the error term: on the plane where they are
            refined (refine ≥ 2; :class:`~lightfield_jax.forward.cell.CellRenderer`,
            within 0.25 % of the full render, a warm fit of a dense forward capture
            about 3× faster, docs/periodic_cell.md), on the slab where the series is
            long (:class:`~lightfield_jax.forward.slab_cell.SlabCellRenderer`, about 3×
            faster renders, within 0.2 % of the full render in every row,
            docs/slab_memory.md); the first fit of a process compiles more. ``False``:
            those models render the whole tank.
        max_render_cells: cap on the corrected model's working size (as ``max_cells``,
            for primal renders, which need no tangents).
    """

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
    max_cells: int = 2_000_000
    crop: bool = True
    crop_fraction: float = 1e-4
    geometry: Plane | Slab | AutoGeometry | None = None
    stripe_cell: bool = True
    max_render_cells: int = 8_000_000

    def __post_init__(self):
        if self.tail is not None and not (
            isinstance(self.tail, str) and (self.tail == "auto" or self.tail in TAIL_METHODS)
        ):
            raise ValueError(
                f"tail: must be auto, None or one of {', '.join(TAIL_METHODS)}, got {self.tail!r}"
            )
        if _is_int(self.bounces) and self.tail in TAIL_METHODS:
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
            ("max_cells", 1),
            ("max_render_cells", 1),
        ):
            check_int(getattr(self, name), name, low=least)
        check_int(self.tail_max_steps, "tail_max_steps", high=MAX_ITERATIONS)
        if self.coarse_after is not None:
            check_int(self.coarse_after, "coarse_after", low=2, high=MAX_BOUNCES)
        for name in ("crop", "stripe_cell"):
            check_flag(getattr(self, name), name)
        if self.geometry is not None:
            as_geometry(self.geometry)
        if not self.max_render_cells >= self.max_cells:
            raise ValueError(
                f"max_render_cells: must be at least max_cells ({self.max_cells}), got "
                f"{self.max_render_cells!r}"
            )
        self._check_ranges()
        _python_numbers(self)

    def _check_ranges(self) -> None:
        """Refuse settings the fit would otherwise ignore or quietly replace (a bounce
        count below 1 taken as 2, ``max_cells: 0`` or ``crop_fraction: 5`` ignored, a
        negative tolerance)."""
        if not isinstance(self.phase, str) or self.phase not in PHASE_CONVENTIONS:
            raise ValueError(
                f"phase: must be one of {', '.join(PHASE_CONVENTIONS)}, got {self.phase!r}"
            )
        if (
            self.bounces != "auto"
            if isinstance(self.bounces, str)
            else not (_is_int(self.bounces) and self.bounces >= 1)
        ):
            raise ValueError(f"bounces: must be an integer >= 1 or 'auto', got {self.bounces!r}")
        for name in ("bounces", "tail_bounces", "max_bounces"):
            value = getattr(self, name)
            if _is_int(value) and value > MAX_BOUNCES:
                raise ValueError(too_many_bounces(name, value))
        if not (_is_number(self.tolerance) and 0.0 < self.tolerance < 1.0):
            raise ValueError(f"tolerance: must lie in (0, 1), got {self.tolerance!r}")
        check_n_theta(self.n_theta, "n_theta")
        check_refine(self.refine, "refine")
        for name in ("max_bounces", "max_cells"):
            value = getattr(self, name)
            if not (_is_int(value) and value >= 1):
                raise ValueError(f"{name}: must be an integer >= 1, got {value!r}")
        if not (_is_number(self.crop_fraction) and 0.0 <= self.crop_fraction < 1.0):
            raise ValueError(
                f"crop_fraction: must lie in [0, 1) (a fraction of the peak), "
                f"got {self.crop_fraction!r}"
            )


@dataclasses.dataclass(frozen=True)
class TrustOptions:
    """How the joint fit earns its answer and judges it (all optional).

    Attributes:
        basin_search: (``joint``) solve every basin the global scan keeps, not only
            its best (:mod:`lightfield_jax.inverse.basins`).
        max_basins: at most this many basins are solved.
        basin_tolerance: a local minimum of the scan is kept when its misfit is at most
            (1 + tolerance) × the best.
        model_error: (``joint``) estimate the model's error at the solution from one
            render with a finer model (in ``uncertainty_model``).
        correct: (``joint``) reach the model the answer needs by defect correction
            (:mod:`lightfield_jax.inverse.correction`: primal renders of that model
            with the cheap model's Jacobian, its own by forward differences where
            those steps stop shrinking) instead of solving on it; where the iteration
            does not converge the fit solves on that model as capped by ``max_cells``.
        extrapolate: (``joint``, plane) where the error term's finer model is finer in
            space (forward media: a refined model, or one kept coarser by ``refine``
            or the cap), report the answer extrapolated to
            the continuum: the model's discretisation error is first order in the cell
            size, so the answer steps r_f/(r_f − r) times the finer model's shift
            (Richardson) and the model term is that shift (dense forward Monte Carlo
            captures: σt within 1 %, where the model's own answer is 2.5–3 % high).
            ``False``: the model's own answer, with that whole step as its model term
            (a capture rendered on the model's own grid is fitted exactly this way).
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
    """

    basin_search: bool = True
    max_basins: int = 3
    basin_tolerance: float = 1.0
    model_error: bool = True
    correct: bool = True
    extrapolate: bool = True
    correction_renders: int = 16
    max_chi2: float = 100.0
    offset_stop: float = 0.05

    def __post_init__(self):
        check_int(self.max_basins, "max_basins", low=1)
        check_int(self.correction_renders, "correction_renders", low=1)
        check_number(self.basin_tolerance, "basin_tolerance", low=0.0, allow_inf=True)
        check_number(self.offset_stop, "offset_stop", low=0.0, high=OFFSET_EXPLAINS)
        for name in ("basin_search", "model_error", "correct", "extrapolate"):
            check_flag(getattr(self, name), name)
        if not (_is_number(self.max_chi2) and self.max_chi2 > 0):
            raise ValueError(f"max_chi2: must be > 0, got {self.max_chi2!r}")
        _python_numbers(self)


@dataclasses.dataclass(frozen=True)
class SolverOptions:
    """The limits of the optimistix solves (all optional).

    Attributes:
        max_steps: iteration limit of the optimistix solves.
        rtol, atol: tolerances of the default solver, Levenberg-Marquardt (relative,
            absolute on the unconstrained values and on the residual's components; the
            joint fit's residual is solved normalised, Σ(w·I)² = 1e3:
            :data:`~lightfield_jax.inverse.joint.RESIDUAL_GAIN`); ``None`` picks them
            from the data's dtype (float32: 1e-4, 1e-4; float64: 1e-8, 1e-10). float32
            cannot resolve changes of the residual much below 1e-4 of its scale: with
            tighter tolerances LM converges within a few steps and then spends ten more
            shrinking its step in rounding noise (same answer to 1e-6).
    """

    max_steps: int = 100
    rtol: float | None = None
    atol: float | None = None

    def __post_init__(self):
        if not (_is_int(self.max_steps) and self.max_steps >= 1):
            raise ValueError(f"max_steps: must be an integer >= 1, got {self.max_steps!r}")
        check_int(self.max_steps, "max_steps", high=MAX_ITERATIONS)
        for name in ("rtol", "atol"):
            value = getattr(self, name)
            if value is not None and not (_is_number(value) and 0.0 <= value <= MAX_TOLERANCE):
                # Looser, Levenberg-Marquardt stops at its start (measured: rtol = atol =
                # 0.1 returned the scan's start point, sigma_t 38 sigma off, "converged").
                raise ValueError(
                    f"{name}: must lie in [0, {MAX_TOLERANCE:g}] or be None, got {value!r}"
                )
        if self.rtol is not None and self.atol is not None and max(self.rtol, self.atol) < EPS:
            # A change below float64's resolution is no change: the solve ran to
            # max_steps and ended "not converged" (measured: 14 s on a 32x24 capture).
            raise ValueError(
                f"rtol, atol: {self.rtol!r} and {self.atol!r} can never be met (below "
                f"float64's resolution, {EPS:.2g}); give one of them >= {EPS:.2g}, or None "
                "for the defaults"
            )
        _python_numbers(self)


@dataclasses.dataclass(frozen=True)
class FitSettings:
    """What a fit method reads besides its own settings: the ``model`` it renders, how
    it earns and judges its answer (``trust``) and the limits of its solves (``solve``)."""

    model: ModelOptions = dataclasses.field(default_factory=ModelOptions)
    trust: TrustOptions = dataclasses.field(default_factory=TrustOptions)
    solve: SolverOptions = dataclasses.field(default_factory=SolverOptions)


# Each flat setting (a capture file's ``fit:`` key, a fit_images keyword) and its group.
GROUPS: dict[str, type] = {"model": ModelOptions, "trust": TrustOptions, "solve": SolverOptions}
GROUP_OF: dict[str, str] = {
    f.name: group for group, record in GROUPS.items() for f in dataclasses.fields(record)
}


def grouped(settings: dict, **given) -> dict:
    """The groups (``model``, ``trust``, ``solve``: each a record, ``given`` or the
    defaults) with the flat ``settings`` of each (keys of :data:`GROUP_OF`) set: each
    group checked as it is made."""
    out = {}
    for group, record in GROUPS.items():
        value = given.get(group)
        if value is not None and not isinstance(value, record):
            raise ValueError(
                f"{group}: must be a {record.__name__} or None, got {type(value).__name__}"
            )
        own = {k: v for k, v in settings.items() if GROUP_OF[k] == group}
        value = value or record()
        out[group] = dataclasses.replace(value, **own) if own else value
    return out


__all__ = [
    "GROUPS",
    "GROUP_OF",
    "MAX_ITERATIONS",
    "MAX_TOLERANCE",
    "FitSettings",
    "ModelOptions",
    "SolverOptions",
    "TrustOptions",
    "grouped",
]
