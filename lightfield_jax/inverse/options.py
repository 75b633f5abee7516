"""The settings and the result of a fit: :class:`FitOptions` (every setting of
:func:`~lightfield_jax.fit_images`, checked when made: the fit method with its own
settings, and the others by concern, :mod:`lightfield_jax.inverse.settings`, made from
flat keywords) and :class:`FitResult` (the fitted values, their 1σ uncertainties and
correlations, the verdict, the timings and the model used), with the helpers of its
``results.json`` form (:meth:`FitResult.to_dict`: strict JSON, σa's and the albedo's
errors from the correlations).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from lightfield_jax.checks import shown
from lightfield_jax.inverse.method_base import METHOD_KEYS, FitMethod, check_method_setting
from lightfield_jax.inverse.methods import METHODS, method_for
from lightfield_jax.inverse.settings import (
    GROUP_OF,
    GROUPS,
    FitSettings,
    ModelOptions,
    SolverOptions,
    TrustOptions,
    grouped,
)
from lightfield_jax.scene.phase import phase_integral_at

PARAMS = ("sigma_t", "sigma_s", "g", "gain", "black_level")

# Every flat setting, in the order documented.
FLAT_KEYS = ("method", *GROUP_OF, *METHOD_KEYS)


def _is_kept(kept) -> bool:
    """Whether ``kept`` is what :class:`FitOptions` keeps: (key, value) pairs of the
    method settings a later method takes."""
    return isinstance(kept, (tuple, list)) and all(
        isinstance(p, (tuple, list)) and len(p) == 2 and p[0] in ("g_grid", "start_grid")
        for p in kept
    )


@dataclasses.dataclass(frozen=True, init=False)
class FitOptions(FitSettings):
    """Settings of a fit (all optional): the fit ``method`` with its own settings, and
    the settings of every method by concern (:mod:`lightfield_jax.inverse.settings`):
    ``model`` (:class:`~lightfield_jax.inverse.settings.ModelOptions`), ``trust``
    (:class:`~lightfield_jax.inverse.settings.TrustOptions`) and ``solve``
    (:class:`~lightfield_jax.inverse.settings.SolverOptions`).

    Made from flat keywords, as a capture file's ``fit:`` section and
    :func:`~lightfield_jax.fit_images` give them: ``FitOptions(method="grid", n_theta=32,
    g_grid=21)``; each goes to its group, or to the method. :meth:`replace` changes flat
    settings the same way.

    Attributes:
        method: the fit method (:mod:`lightfield_jax.inverse.methods`), given as
            ``joint`` (default), ``gradient`` or ``grid`` or as a method
            (:class:`~lightfield_jax.Joint`, :class:`~lightfield_jax.TwoStep`,
            :class:`~lightfield_jax.GridSearch`).
        model, trust, solve: the groups of settings (each field also a flat keyword and
            a read-only attribute: ``options.n_theta`` is ``options.model.n_theta``;
            a method's own setting reads from the method that takes it:
            ``options.start`` is ``options.method.start``).

    The flat keywords of the methods' own settings: ``g_grid`` (the grid's
    ``GridSearch.g_values``: g values searched on (−0.95, 0.95)), ``start_grid``
    (``TwoStep.start_grid``: g values of the coarse search that starts ``gradient``;
    0, the default, none: its solve starts at g = 0),
    ``start`` (``Joint.start``: (σs, g) to start the joint fit from instead of the
    scan's basins, σt from the decay fit; the scan still runs, to report a worse basin)
    and ``solver`` (``Joint.solver``, ``TwoStep.solver``: any optimistix least-squares
    solver; default Levenberg-Marquardt with the ``solve`` tolerances). A method given
    as a value keeps its own where it sets one. ``start`` or ``solver`` for a method that
    does not use them is refused; ``g_grid`` and ``start_grid`` are checked, apply to
    the method that takes them and, given with one that does not, are kept for a method
    chosen later (``FitOptions(g_grid=21).replace(method="grid")`` searches 21 values).
    """

    method: FitMethod = METHODS["joint"]
    # ``g_grid`` / ``start_grid`` given with a method that does not take them, as
    # (key, value) pairs, for a method chosen later (:meth:`replace`, ``fit_images``'s
    # ``method``).
    kept: tuple[tuple[str, int], ...] = ()

    def __init__(
        self,
        method: str | FitMethod = "joint",
        *,
        model: ModelOptions | None = None,
        trust: TrustOptions | None = None,
        solve: SolverOptions | None = None,
        kept: tuple[tuple[str, int], ...] = (),
        **settings,
    ):
        if not _is_kept(kept):  # else dict() raises Python's own, naming nothing
            raise TypeError(
                f"FitOptions: kept: must be (key, value) pairs of g_grid or start_grid, got "
                f"{kept!r:.80}"
            )
        settings = {**dict(kept), **settings}  # dataclasses.replace passes ``kept`` on
        unknown = [k for k in settings if k not in GROUP_OF and k not in METHOD_KEYS]
        if unknown:
            raise TypeError(
                f"FitOptions: unknown setting {unknown[0]!r} (the settings: {', '.join(FLAT_KEYS)})"
            )
        method = method_for(method)  # a known name or a FitMethod
        groups = grouped(
            {k: v for k, v in settings.items() if k in GROUP_OF},
            model=model,
            trust=trust,
            solve=solve,
        )
        for group, record in groups.items():
            object.__setattr__(self, group, record)
        kept = []
        for key in METHOD_KEYS:
            if key in settings:
                value = check_method_setting(key, settings[key])
                method = _routed(method, key, value)
                if key not in method.option_names and key in ("g_grid", "start_grid"):
                    kept.append((key, value))
        object.__setattr__(self, "method", method)
        object.__setattr__(self, "kept", tuple(kept))

    def __getattr__(self, name: str):
        # A flat setting reads from its group (``options.n_theta`` is
        # ``options.model.n_theta``), or from the method that takes it
        # (``options.start`` is ``options.method.start``), as it is given.
        group = GROUP_OF.get(name)
        if group is not None:
            return getattr(getattr(self, group), name)
        if name in METHOD_KEYS:
            method = self.__dict__.get("method")
            field = None if method is None else method.option_names.get(name)
            if field is not None:
                return getattr(method, field)
            taken = "" if method is None else f" (the {method.name} method does not take it)"
            raise AttributeError(f"FitOptions has no setting {name!r}{taken}")
        raise AttributeError(f"FitOptions has no setting {name!r}")

    def flat(self) -> dict:
        """Every setting as a flat keyword (the method as itself, its own settings as
        their flat keywords where it sets them): ``FitOptions(**options.flat())``
        equals ``options``."""
        out = {"method": self.method}
        for group in GROUPS:
            record = getattr(self, group)  # shallow: a Slab stays a Slab
            out.update({f.name: getattr(record, f.name) for f in dataclasses.fields(record)})
        out.update(self.method.own_options())
        out.update(self.kept)
        return out

    def replace(self, **settings) -> FitOptions:
        """These options with flat ``settings`` changed (the keywords of
        :class:`FitOptions`). A method's own setting given here replaces the method's
        (``replace(g_grid=21)`` of a grid search on 30 values searches 21). A method
        given by name takes the settings of the method it replaces that it uses
        (``start`` for a method that does not use it is refused, as when given)."""
        flat = self.flat()
        if "method" not in settings:
            # The method's own settings travel in ``flat`` as keywords: on its defaults,
            # the method lets one given here win (a method keeps its own over a keyword).
            flat["method"] = _without_own(self.method)
        return FitOptions(**{**flat, **settings})


def _without_own(method: FitMethod) -> FitMethod:
    """``method`` with its own flat settings (:meth:`FitMethod.own_options`) back at its
    defaults."""
    defaults = {f.name: f.default for f in dataclasses.fields(method)}
    fields = [method.option_names[key] for key in method.own_options()]
    return dataclasses.replace(method, **{f: defaults[f] for f in fields}) if fields else method


def _routed(method: FitMethod, key: str, value) -> FitMethod:
    """``method`` with the flat setting ``key`` where it takes it and does not set its
    own; a ``start`` or ``solver`` it does not use refused, a ``g_grid`` or
    ``start_grid`` it does not take (another method's, checked) not kept."""
    field = method.option_names.get(key)
    if field is None:
        if key in ("start", "solver") and value is not None:
            # Refused, not ignored silently: a start with the grid search, which
            # searches g; a solver with it, which solves nothing.
            raise ValueError(
                f"{key}: the {method.name} method does not use it (start: the joint "
                "fit's; solver: the joint and gradient fits'): drop it, or choose a "
                "method that does"
            )
        return method
    if key in method.own_options():
        return method  # the method's own setting
    return dataclasses.replace(method, **{field: value})


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
            f"(its settings can also be given as keywords: {where}(..., max_steps=20))"
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
