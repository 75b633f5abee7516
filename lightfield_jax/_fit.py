"""The inverse problem (MODEL.md sections 5-6): recover σt, σs, g (and the gain) from a
stripe capture.

Methods, all on the same forward model (:class:`~lightfield_jax.Renderer`):

- ``grid`` (the paper's baseline): σt from the decay of the separated direct image D;
  per g on a grid, render I_k^{(g)} with σs = 1 under full illumination (``lax.map``
  over g), take the gain from the single scatter (D ≈ a·I_1^{(g)}, a = c·σs), solve the
  σs polynomial of the paper's eq. 10, M ≈ a·Σ_{k≥2} σs^{k−1} I_k^{(g)}, and keep the
  best g. It inherits the separation's bias (MODEL.md §6): that is its honest result.
- ``gradient``: the same residual and model, solved with optimistix Levenberg-Marquardt
  over (σs, g), differentiated through the renderer.
- ``joint`` (default): σt, σs, g, gain (and the projector's black level when the
  capture does not give it) fitted straight to the raw shifted images by rendering each
  stripe pattern, so no separation bias remains. Starts from the ``gradient`` result.

Every result carries 1σ uncertainties from the Jacobian (noise estimated from the
residual), correlations, the solver's convergence status (never swallowed), iterations,
residual, wall time split into compile and run, and the model used.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import time
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._decay import fit_decay
from ._grid import Grid, default_n_theta, default_refine
from ._illumination import _INWARD_DEG, Full, Stripes
from ._medium import bounces_for_tolerance, phase_function, phase_integral
from ._model_choice import choose, misfit, relative_noise
from ._render import make_renderer
from ._separate import separate
from ._slab import (
    AutoGeometry,
    Plane,
    Slab,
    default_slab_n_theta,
    parse_geometry,
    slab_bounce_ratio,
)

METHODS: tuple[str, ...] = ("joint", "gradient", "grid")
# A(g) of a Python float, compiled once (op by op, its dozen operations would each
# compile on first use).
_phase_integral = jax.jit(phase_integral)
_PARAMS = ("sigma_t", "sigma_s", "g", "gain", "black_level")


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """Settings of a fit (all optional).

    Attributes:
        method: ``joint`` (default), ``gradient`` or ``grid``.
        phase: phase convention of the model (``paper`` or ``normalized``).
        bounces: K, or ``"auto"`` from the tail bound at the starting estimate.
        tolerance: relative tail tolerance for ``bounces: auto``.
        max_bounces: cap on ``auto`` (the paper series near ρ = 1 needs many).
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
            model), a :class:`Slab` (the tank's depth, MODEL.md §7; its 3-D phase
            function is normalised on the sphere, so ``phase`` is ``normalized``), or
            :class:`AutoGeometry` (the plane where its misfit is below the capture's
            noise, else the slab: :mod:`lightfield_jax._model_choice`).
        rtol, atol: solver tolerances (relative, absolute on the unconstrained values
            and on the residual's components); ``None`` picks them from the data's
            dtype (float32: 1e-4, 1e-4; float64: 1e-8, 1e-10). float32 cannot resolve
            changes of the residual much below 1e-4 of its scale: with tighter
            tolerances LM converges within a few steps and then spends ten more
            shrinking its step in rounding noise (same answer to 1e-6).
    """

    method: str = "joint"
    phase: str = "paper"
    bounces: int | str = "auto"
    tolerance: float = 1e-4
    max_bounces: int = 80
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

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"method: must be one of {', '.join(METHODS)}, got {self.method!r}")
        if self.g_grid < 3:
            raise ValueError(f"g_grid: must be at least 3, got {self.g_grid!r}")


@dataclasses.dataclass(frozen=True)
class FitResult:
    """What a fit recovered, and how much to trust it.

    Values are per pixel (σ's), the gain in image units per unit source irradiance.
    ``uncertainty`` holds 1σ errors (NaN where not estimated), ``correlation`` the
    correlation coefficients between fitted parameters (e.g. ``"sigma_t,g"``).
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
        """The ``results.json`` form (MODEL.md units: per pixel; also mm⁻¹ if known)."""
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
            "condition_number": _json_float(self.condition_number),
            "converged": self.converged,
            "message": self.message,
            "iterations": self.iterations,
            "residual": _json_float(self.residual),
            "seconds": self.seconds,
            "model": self.model,
        }
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

    def as_dict(self) -> dict:
        tail = self.rho**self.bounces / (1 - self.rho) if self.converges else None
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
            "tail_bound": tail,
        }


def _signal_crop(images: np.ndarray, pattern: Stripes, fraction: float) -> tuple[int, ...]:
    """Crop along the propagation direction to where the signal stands out: Imax,
    averaged across the light, must exceed its noise floor (the median of the farthest
    tenth) by ``fraction`` of the peak and by three times the floor's scatter. The entry
    wall stays; at least 16 pixels are kept."""
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
    keep = min(n, max(last + 2, 16))
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
) -> _Model:
    """The smallest model the capture needs: bounces from the tail bound at the estimate
    (ρ × ``margin``, capped below 1), θ bins and refinement from g, crop from the
    signal. ``series_converges`` is judged at the estimate itself."""
    p, h, w = images.shape
    crop = _signal_crop(images, pattern, options.crop_fraction) if options.crop else (0, 0, w, h)
    gw = min(0.99, abs(g) + 0.1)
    slab = options.geometry if isinstance(options.geometry, Slab) else None
    if slab is not None:  # less sensitive to g than the plane: a smaller margin
        n_theta = options.n_theta or default_slab_n_theta(min(0.99, abs(g) + 0.05))
        refine = options.refine or 1
        slab = slab.resolve(min(0.99, abs(g) + 0.05))
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
        while width * height * 4 * n_theta * slab.n_mu * refine**2 > 4 * options.max_cells:
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
        # Capped at max_bounces (the model's tail bound is reported with the result).
        k = min(
            bounces_for_tolerance(bound, options.tolerance, max_bounces=10**9),
            options.max_bounces,
        )
    else:
        k = options.max_bounces
    return _Model(
        grid=grid, bounces=max(k, 2), crop=crop, converges=converges, rho=rho, geometry=slab
    )


# ---------------------------------------------------------------------- shared pieces


def _masked_dot(a, b, mask):
    return jnp.sum(jnp.where(mask, a * b, 0.0))


def _covariance(jac: np.ndarray, residual: np.ndarray, names: list[str]):
    """1σ errors and correlations: cov = s²(JᵀJ)⁻¹, s² = ‖r‖²/(n − p).

    The condition number is that of JᵀJ scaled to unit diagonal (free of the
    parameters' units): large means some combination of parameters is barely
    constrained (e.g. the σt-g valley at high albedo and forward scattering)."""
    n, p = jac.shape
    jtj = jac.T @ jac
    try:
        d = np.sqrt(np.clip(np.diag(jtj), 1e-300, None))
        cond = float(np.linalg.cond(jtj / np.outer(d, d)))
        inv = np.linalg.inv(jtj)
    except np.linalg.LinAlgError:
        return {k: math.inf for k in names}, {}, math.inf
    s2 = float(residual @ residual) / max(n - p, 1)
    cov = s2 * inv
    err = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    unc = {k: float(e) for k, e in zip(names, err, strict=True)}
    corr = {}
    for i in range(p):
        for j in range(i + 1, p):
            d = err[i] * err[j]
            corr[f"{names[i]},{names[j]}"] = float(cov[i, j] / d) if d > 0 else math.nan
    return unc, corr, cond


def _with_forward_jacobian(heavy):
    """``heavy(x, *fixed)`` returning ``(value, jacobian)``, whose JVP in ``x`` is
    ``jacobian @ tx``; the Jacobian (``[..., len(x)]``) comes from one forward-mode pass
    (``jax.jvp`` vmapped over the unit vectors: the primal once, all tangents at once).

    optimistix linearises the residual with ``jax.linearize``, which keeps every
    intermediate of the forward pass (every bounce of every pattern): tens of GB for a
    long bounce series. With few parameters, a forward-mode pass is cheaper than that
    and keeps nothing but the Jacobian. Returning the Jacobian as a value lets the
    caller build derivatives in other parameters from it (and report them as ``aux``)
    without another pass. ``fixed`` are held constant (their tangents are ignored:
    pass ``lax.stop_gradient`` values), and the Jacobian's own tangent is zero (no
    second derivatives).
    """

    def value_and_jacobian(x, *fixed):
        def value(x):
            return heavy(x, *fixed)

        basis = jnp.eye(x.shape[0], dtype=x.dtype)
        return jax.vmap(lambda e: jax.jvp(value, (x,), (e,)), out_axes=(None, -1))(basis)

    return _with_jacobian(value_and_jacobian)


def _with_jacobian(value_and_jacobian):
    """``value_and_jacobian(x, *fixed)`` → ``(value, jacobian)`` as a function whose JVP
    in ``x`` is ``jacobian @ tx`` (see :func:`_with_forward_jacobian`)."""

    @jax.custom_jvp
    def wrapped(x, *fixed):
        return value_and_jacobian(x, *fixed)

    @wrapped.defjvp
    def _jvp(primals, tangents):
        x, *fixed = primals
        out, jac = value_and_jacobian(x, *fixed)
        tangent = jax.tree.map(lambda j: j @ tangents[0], jac)
        return (out, jac), (tangent, jax.tree.map(jnp.zeros_like, jac))

    return wrapped


# Compiled fit programs of this process, by what they depend on (see _timed_compile).
# A second fit of a capture of the same shape (another channel of an RGB capture, the
# next capture of a series, a sweep over seeds) then runs without tracing or compiling.
_COMPILED: collections.OrderedDict = collections.OrderedDict()
_COMPILED_MAX = 32


def clear_compiled() -> None:
    """Forget the fit programs compiled in this process (the next fit compiles again,
    or loads from the persistent XLA cache where that is on): for cold timings."""
    _COMPILED.clear()


def _program_key(static, args):
    leaves, treedef = jax.tree.flatten(args)
    avals = tuple(
        (tuple(np.shape(v)), str(jnp.result_type(v)), bool(getattr(v, "weak_type", False)))
        for v in leaves
    )
    return (static, treedef, avals, jax.config.jax_enable_x64, str(jax.devices()[0]))


def _compiler_options() -> dict | None:
    """XLA options of the fit programs: on the CPU, LLVM's optimisation level 1 instead
    of the default 2. A fit program runs for well under a second and compiles for
    several: level 1 compiles it about 15-25 % faster and it runs as fast (measured on
    the demo capture: the same answers to float32 rounding)."""
    if jax.default_backend() != "cpu":
        return None
    return {"xla_backend_optimization_level": 1}


def _timed_compile(fn, *args, static=None):
    """AOT-compile ``fn`` for ``args``: (compiled, seconds).

    With ``static`` (a hashable description of everything ``fn`` depends on besides
    ``args``: it is a fresh closure each call), the program is kept for this process and
    a later call with the same ``static``, argument structure, shapes and dtypes reuses
    it (0 s). The argument structure includes the renderer's static fields (grid,
    illumination, bounces, phase, geometry)."""
    key = None if static is None else _program_key(static, args)
    if key is not None and key in _COMPILED:
        _COMPILED.move_to_end(key)
        return _COMPILED[key], 0.0
    t = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile(compiler_options=_compiler_options())
    seconds = time.perf_counter() - t
    if key is not None:
        _COMPILED[key] = compiled
        while len(_COMPILED) > _COMPILED_MAX:
            _COMPILED.popitem(last=False)
    return compiled, seconds


def _solver(options: FitOptions, dtype) -> optx.LevenbergMarquardt:
    wide = jnp.finfo(dtype).bits > 32
    rtol = options.rtol if options.rtol is not None else (1e-8 if wide else 1e-4)
    atol = options.atol if options.atol is not None else (1e-10 if wide else 1e-4)
    return optx.LevenbergMarquardt(rtol=rtol, atol=atol)


def _solver_key(options: FitOptions):
    return (options.rtol, options.atol)


def _result_message(result) -> tuple[bool, str]:
    ok = bool(result == optx.RESULTS.successful)
    if ok:
        return True, "converged"
    return False, str(optx.RESULTS[result]) if hasattr(optx.RESULTS, "__getitem__") else "failed"


def _logit(x):
    return math.log(x / (1.0 - x))


# ------------------------------------------------------------------- data preparation


@dataclasses.dataclass
class _Data:
    images: np.ndarray  # (P, h, w), cropped, dark-subtracted
    mask: np.ndarray  # (h, w) valid in every shift
    direct: np.ndarray
    multiple: np.ndarray
    sigma_t0: float
    sigma_t0_err: float
    decay_converged: bool
    exposure: np.ndarray | None = None  # (P, h, w) merged brackets' T (s), or None


def _separate_and_decay(images, mask, pattern: Stripes, black_level, saturation, split=None):
    if split is None:
        sep = separate(
            jnp.asarray(images),
            lit_fraction=pattern.lit_fraction,
            black_level=0.0 if black_level is None else float(black_level),
        )
        direct, multiple = np.asarray(sep.direct), np.asarray(sep.multiple)
    else:
        direct, multiple = (np.asarray(a, dtype=images.dtype) for a in split)
        if direct.shape != images.shape[1:] or multiple.shape != images.shape[1:]:
            raise ValueError(
                f"split: direct and multiple must have the images' shape {images.shape[1:]}, "
                f"got {direct.shape} and {multiple.shape}"
            )
    decay = fit_decay(
        direct,
        direction_deg=pattern.direction_deg,
        entry=pattern.entry,
        mask=jnp.asarray(mask),
        saturation=saturation,
    )
    return direct, multiple, decay


# ------------------------------------------------------------------ grid and gradient


def _full_for(pattern: Stripes) -> Full:
    return Full(direction_deg=pattern.direction_deg, entry=pattern.entry)


def _poly_fit_sigma_s(d, m, i1, ik, mask, u_max, n_grid: int = 2001):
    """The paper's eq. 10 for one g, on images rendered at a reference σs_ref:
    I_k(σs) = u^k I_k(σs_ref), u = σs/σs_ref. The gain from the single scatter,
    a = ⟨D, I_1⟩/⟨I_1, I_1⟩, then u* = argmin_{0≤u≤u_max} ‖M − a Σ_{k≥2} u^{k−1} I_k‖²
    (exact polynomial minimisation: dense evaluation, then Newton on the derivative).
    Returns (u*, a, residual²), the residual² summed from the residual itself: the
    expanded polynomial is a difference of large terms, which in float32 cannot tell
    apart values of g near the minimum (it left the grid's g error at ~1e-3 however
    dense the grid)."""
    a = _masked_dot(d, i1, mask) / _masked_dot(i1, i1, mask)
    kk = ik.shape[0]
    gram = jnp.einsum("khw,lhw->kl", jnp.where(mask, ik, 0.0), ik)
    mk = jnp.einsum("khw,hw->k", jnp.where(mask, ik, 0.0), m)
    mm = _masked_dot(m, m, mask)
    # cost(u) = mm − 2a·Σ_k u^k mk_k + a²·Σ_kl u^k u^l G_kl = Σ_n c_n u^n, n = 0..2K: its
    # coefficients once, then values and derivatives of a polynomial (no autodiff of
    # a Newton loop, which would be most of the compiled program).
    n = 2 * kk + 1
    degree = jnp.arange(1, kk + 1)
    pairs = degree[:, None] + degree[None, :]
    coef = jnp.zeros(n, gram.dtype).at[0].set(mm).at[degree].add(-2 * a * mk)
    coef = coef.at[pairs.reshape(-1)].add((a**2 * gram).reshape(-1))
    orders = jnp.arange(n, dtype=gram.dtype)

    def powers(u, shift):  # u^(n − shift), 0 where n < shift
        e = orders - shift
        return jnp.where(e >= 0, u ** jnp.maximum(e, 0.0), 0.0)

    def cost(u):
        return powers(u, 0) @ coef

    d1_coef = coef * orders
    d2_coef = coef * orders * (orders - 1)
    grid = jnp.linspace(0.0, 1.0, n_grid) * u_max
    costs = jax.vmap(cost)(grid)
    u = grid[jnp.argmin(costs)]
    for _ in range(6):
        d1, d2 = powers(u, 1) @ d1_coef, powers(u, 2) @ d2_coef
        u = jnp.clip(u - d1 / jnp.where(d2 > 0, d2, jnp.inf), 0.0, u_max)
    r = m - a * jnp.einsum("k,khw->hw", u ** degree.astype(ik.dtype), ik)
    return u, a, _masked_dot(r, r, mask)


# ρ of the reference render of the two-step methods: I_k grows like ρ^k, so rendering
# at σs = 1 (the paper's choice) overflows float32 within a few dozen bounces at high
# albedo; at ρ_ref ≤ 0.9 every I_k stays below I_1.
_RHO_REF = 0.9


def _reference_sigma_s(sigma_t, g, phase: str):
    """σs_ref for the two-step renders at g, and u_max = σs_max/σs_ref: the largest σs
    that is both ≤ σt and inside the convergent region ρ ≤ 1."""
    in_plane = phase_integral(g) if phase == "paper" else 1.0
    ref = sigma_t * jnp.minimum(1.0, _RHO_REF / in_plane)
    rho_ref = ref / sigma_t * in_plane
    return ref, jnp.minimum(sigma_t / ref, 1.0 / rho_ref)


def _parabolic_minimum(xs, costs, best):
    """The vertex of the parabola through the grid's best point and its two
    neighbours (uniform spacing), kept within one spacing of the best point: (x, t)
    with t the offset in spacings. At an end of the grid, the best point itself."""
    n = xs.shape[0]
    i = jnp.clip(best, 1, n - 2)
    lo, mid, hi = costs[i - 1], costs[i], costs[i + 1]
    curvature = lo - 2 * mid + hi
    t = jnp.where(curvature > 0, 0.5 * (lo - hi) / jnp.where(curvature > 0, curvature, 1.0), 0.0)
    t = jnp.where((best > 0) & (best < n - 1), jnp.clip(t, -1.0, 1.0), 0.0)
    return xs[best] + t * (xs[1] - xs[0]), t


def _rendered_and_g_slope(renderer, sigma_t, phase: str):
    """``x = [g]`` → (I_k at (σt, σs_ref(g), g) under full illumination, (K, h, w), and
    dI_k/dg, (K, h, w, 1)), differentiable in ``x`` through that slope. The plane's
    renderer gives the slope in one pass of its own code
    (:meth:`~lightfield_jax.Renderer.images_and_g_slope`); I_k ∝ σs^k carries the
    change of σs_ref with g. Other renderers go through ``jax.jvp``."""

    def reference(g):
        return _reference_sigma_s(sigma_t, g, phase)[0]

    if not hasattr(renderer, "images_and_g_slope"):
        return _with_forward_jacobian(lambda x: renderer(sigma_t, reference(x[0]), x[0])[0][0])

    def value_and_jacobian(x):
        g = x[0]
        ref, dref = jax.jvp(reference, (g,), (jnp.ones_like(g),))
        images, slope = renderer.images_and_g_slope(sigma_t, ref, g)
        images, slope = images[0], slope[0]
        k = jnp.arange(1, images.shape[0] + 1, dtype=images.dtype)[:, None, None]
        return images, (slope + images * k * (dref / ref))[..., None]

    return _with_jacobian(value_and_jacobian)


def _two_step_residual(rendered_and_slope, sigma_t, d, m, mask, scale, phase: str, p):
    """The residual of eq. 10 at p = (σs, g) and its Jacobian written out: ``(r,
    ∂r/∂(σs, g) (N, 2), a = c·σs)``, r = mask·(M − a_ref Σ_{k≥2} u^{k−1} I_k)/scale with
    the images rendered at σs_ref(g), u = σs/σs_ref and a_ref = ⟨D, I_1⟩/⟨I_1, I_1⟩.
    The images' slope along g comes from ``rendered_and_slope``
    (:func:`_rendered_and_g_slope`); σs and the gain enter in closed form, so the
    Jacobian costs no autodiff of this code (a small program)."""
    sigma_s, g = p[0], p[1]
    ref, dref = jax.jvp(lambda g: _reference_sigma_s(sigma_t, g, phase)[0], (g,), (1.0 + 0 * g,))
    images, slope = rendered_and_slope(p[1:])
    slope = slope[..., 0]
    i1, s1 = images[0], slope[0]
    n1, n2 = _masked_dot(d, i1, mask), _masked_dot(i1, i1, mask)
    a_ref = n1 / n2  # the gain from the single scatter, and its slope along g
    da_ref = (_masked_dot(d, s1, mask) * n2 - 2 * n1 * _masked_dot(i1, s1, mask)) / n2**2
    k = jnp.arange(1, images.shape[0], dtype=images.dtype)
    u = sigma_s / ref  # I_k(σs) = u^k I_k(σs_ref)
    series = jnp.einsum("k,khw->hw", u**k, images[1:])
    d_series_du = jnp.einsum("k,khw->hw", k * u ** (k - 1), images[1:])
    # along g at fixed σs: the images change, and u with σs_ref
    d_series_dg = jnp.einsum("k,khw->hw", u**k, slope[1:]) - d_series_du * u * dref / ref
    jac = jnp.stack([a_ref * d_series_du / ref, da_ref * series + a_ref * d_series_dg], axis=-1)
    r = jnp.where(mask, (m - a_ref * series) / scale, 0.0).reshape(-1)
    jac = -jnp.where(mask[..., None], jac / scale, 0.0).reshape(-1, 2)
    return r, jac, a_ref * ref


def _two_step(data: _Data, pattern, model: _Model, options: FitOptions, sigma_t, method: str):
    """The paper's two-step problem after σt: ``grid`` searches g on a grid; ``gradient``
    searches a coarse grid, then solves (σs, g) with Levenberg-Marquardt; ``start``
    searches the coarse grid and refines its best g by a parabola (the joint fit's
    start). One compiled function (search, solve and the Jacobian for the
    uncertainties).

    σs enters the model only through the polynomial (I_k ∝ σs^k), so the residual's
    derivative in σs is exact without the renderer, and one forward-mode pass through
    the renderer along g gives the Jacobian of each step."""
    renderer = make_renderer(
        model.grid, _full_for(pattern), model.bounces, options.phase, model.geometry
    )
    dtype = jnp.result_type(float)
    d = jnp.asarray(data.direct, dtype)
    m = jnp.asarray(data.multiple, dtype)
    mask = jnp.asarray(data.mask)
    # Residuals in units of the data's RMS, so solver tolerances mean the same for any
    # exposure.
    scale = float(np.sqrt(np.mean(np.square(data.multiple[data.mask])))) or 1.0
    n_g = options.g_grid if method == "grid" else options.start_grid
    gs = jnp.linspace(-0.95, 0.95, n_g, dtype=dtype)

    def run(renderer, sigma_t, d, m, mask, gs, scale):
        def rendered(g):  # I_k at (σt, σs_ref(g), g): (K, h, w)
            ref, _ = _reference_sigma_s(sigma_t, g, options.phase)
            return renderer(sigma_t, ref, g)[0][0]

        def per_g(g):
            ref, u_max = _reference_sigma_s(sigma_t, g, options.phase)
            images = rendered(g)
            u, a_ref, cost = _poly_fit_sigma_s(d, m, images[0], images[1:], mask, u_max)
            return u * ref, a_ref * ref, cost  # σs, a = c·σs, residual²

        rendered_and_slope = _rendered_and_g_slope(renderer, sigma_t, options.phase)

        def residual(p):
            return _two_step_residual(
                rendered_and_slope, sigma_t, d, m, mask, scale, options.phase, p
            )

        s_all, a_all, cost = jax.lax.map(per_g, gs)
        best = jnp.argmin(cost)
        s, g = s_all[best], gs[best]
        # The vertex of the parabola through the best g and its neighbours: the joint
        # fit's start, and where Levenberg-Marquardt starts.
        g_vertex, t = _parabolic_minimum(gs, cost, best)
        near = jnp.clip(best + jnp.sign(t).astype(best.dtype), 0, n_g - 1)
        s_vertex = s + jnp.abs(t) * (s_all[near] - s)
        if method == "start":
            nan = jnp.full((1,), jnp.nan, dtype)
            return s_vertex, g_vertex, a_all[best], nan, nan, optx.RESULTS.successful, 0
        if method == "grid":
            r, jac, a = residual(jnp.stack([s, g]))
            return s, g, a, r, jac, optx.RESULTS.successful, jnp.asarray(n_g)

        def s_max(g):
            ref, u_max = _reference_sigma_s(sigma_t, g, options.phase)
            return ref * u_max

        frac = jnp.clip(s_vertex / s_max(g_vertex), 1e-3, 1 - 1e-3)
        y0 = jnp.stack([jnp.log(frac / (1 - frac)), jnp.arctanh(jnp.clip(g_vertex, -0.95, 0.95))])

        def unpack(y):  # 0 < σs < min(σt, the σs where ρ = 1), |g| < 1
            g = jnp.tanh(y[1])
            return jnp.stack([s_max(g) * jax.nn.sigmoid(y[0]), g])

        def residual_y(y):  # the residual and its Jacobian in y, as (r, J)
            r, jac, _a = residual(unpack(y))
            return r, jac @ jax.jacfwd(unpack)(y)

        # Levenberg-Marquardt linearises a matrix product J·δy (the custom JVP), not
        # the residual's code: one copy of the renderer in the loop, a small program.
        residual_y = _with_jacobian(residual_y)
        solver = _solver(options, y0.dtype)
        sol = optx.least_squares(
            lambda y, _: residual_y(y)[0],
            solver,
            y0,
            max_steps=options.max_steps,
            throw=False,
        )
        s, g = unpack(sol.value)
        # The Jacobian at the accepted point, from the solver's state (no second copy
        # of the renderer), with ∂(σs, g)/∂y to map it to (σs, g) outside.
        info = sol.state.f_info
        jac = (info.jac.as_matrix(), jax.jacfwd(unpack)(sol.value))
        # a = ⟨D, I_1⟩/⟨I_1, I_1⟩ and I_1 ∝ p_g(π/2): rescale from the grid's best g.
        a = a_all[best] * phase_function(jnp.pi / 2, gs[best]) / phase_function(jnp.pi / 2, g)
        return s, g, a, info.residual, jac, sol.result, sol.stats["num_steps"]

    # Every value that depends on the data is an argument, not a constant of the
    # program: a persistent compilation cache then serves any capture of this shape.
    args = (renderer, jnp.asarray(sigma_t, dtype), d, m, mask, gs, jnp.asarray(scale, dtype))
    static = ("two_step", method, options.phase, _solver_key(options), options.max_steps)
    compiled, t_compile = _timed_compile(run, *args, static=static)
    s, g, a, r, jac, result, steps = compiled(*args)
    s, g = float(s), float(g)
    if method == "start":
        return s, g, t_compile
    r = np.asarray(r)
    if isinstance(jac, tuple):  # ∂r/∂y and ∂(σs, g)/∂y: ∂r/∂(σs, g) = J_y (∂p/∂y)⁻¹
        jac_y, dp_dy = (np.asarray(a, np.float64) for a in jac)
        jac = jac_y @ np.linalg.inv(dp_dy)
    unc, corr, cond = _covariance(np.asarray(jac), r, ["sigma_s", "g"])
    rms = scale * float(np.sqrt(np.sum(r**2) / max(int(np.sum(data.mask)), 1)))
    gain = float(a) / s if s > 0 else math.inf
    ok, msg = _result_message(result)
    if method == "grid":
        msg = f"grid search over {n_g} values of g"
    return s, g, gain, rms, unc, corr, cond, ok, msg, int(steps), t_compile


# ---------------------------------------------------------------------------- joint


def _joint_parts(pattern: Stripes, model: _Model, options: FitOptions):
    renderer = make_renderer(model.grid, pattern, model.bounces, options.phase, model.geometry)
    all_phases = sorted(p % pattern.period for p in pattern.phases) == list(range(pattern.period))
    full = (
        None
        if all_phases
        else make_renderer(
            model.grid, _full_for(pattern), model.bounces, options.phase, model.geometry
        )
    )
    return renderer, full


def _joint_bounces(x, sigma_s, renderer, full):
    """Per-bounce images at unit gain at (σt, g) = ``x`` and ``sigma_s``: every
    pattern's ``(P, K, h, w)`` and, when the phases do not tile the period, full
    illumination's ``(K, h, w)`` (else ``None``)."""
    images = renderer(x[0], sigma_s, x[1])[0]
    return images, None if full is None else full(x[0], sigma_s, x[1])[0][0]


def _joint_model(bounces, lit: int, u, black):
    """Σ_k u^k I_k of every pattern at unit gain (I_k ∝ σs^k: ``u`` rescales σs from the
    rendered one), with the projector's black level b: (1 − b)·R_p + b·R_full
    (R_full = Σ_p R_p / lit when the phases tile the period)."""
    images, full_images = bounces
    powers = u ** jnp.arange(1, images.shape[1] + 1, dtype=images.dtype)
    r = jnp.einsum("k,pkhw->phw", powers, images)
    r_full = (
        jnp.sum(r, axis=0) / lit
        if full_images is None
        else jnp.einsum("k,khw->hw", powers, full_images)
    )
    return (1.0 - black) * r + black * r_full[None]


def _unpack(y, fit_black: bool, black_fixed):
    sigma_t = jnp.exp(y[0])
    sigma_s = sigma_t * jax.nn.sigmoid(y[1])
    g = jnp.tanh(y[2])
    black = -0.2 + 1.2 * jax.nn.sigmoid(y[3]) if fit_black else black_fixed
    return sigma_t, sigma_s, g, black


def _joint_weights(images, mask, exposure=None):
    """Shot noise: 1/√(I + floor), times √T for merged brackets (Var I ∝ I/T)."""
    floor = 1e-3 * np.nanmax(np.where(mask[None], images, 0.0))
    w = 1.0 / np.sqrt(np.clip(images, 0.0, None) + floor)
    if exposure is not None:
        w = w * np.sqrt(exposure / np.max(exposure))
    return np.where(mask[None], w, 0.0)


def _joint_program(data: _Data, pattern: Stripes, model: _Model, options: FitOptions, black):
    """The compiled joint solve: ``solve(weights, y0)`` runs Levenberg-Marquardt on the
    raw images, weighted (1/√(I + floor): shot noise), with the gain eliminated (its
    least-squares value at each point), and returns ``(y, result, steps, residual,
    (R, J))``: R the model at unit gain and J its Jacobian in the physical parameters
    (σt, σs, g and b if fitted) at the accepted point. One forward-mode pass along σt
    and g per step; σs (I_k ∝ σs^k), b and the gain enter in closed form."""
    renderer, full = _joint_parts(pattern, model, options)
    obs = jnp.asarray(data.images)
    fit_black = black is None
    black_fixed = jnp.asarray(0.0 if black is None else float(black), obs.dtype)
    lit = pattern.lit
    bounces_and_slopes = _with_forward_jacobian(_joint_bounces)

    def solve(renderer, full, obs, black_fixed, weights, y0):
        def residual(y, _args):
            st, ss, g, b = _unpack(y, fit_black, black_fixed)
            x = jnp.stack([st, g])
            ref = jax.lax.stop_gradient(ss)
            bounces, slopes = bounces_and_slopes(x, ref, renderer, full)
            r = _joint_model(bounces, lit, ss / ref, b)
            wr = weights * r
            gain = jnp.sum(wr * weights * obs) / jnp.sum(wr * wr)

            # R and its Jacobian in the physical parameters, for the uncertainties: the
            # rendered images extended linearly along the forward-mode slopes (exact
            # first derivatives; no further pass through the renderer).
            fixed = jax.lax.stop_gradient((x, bounces, slopes))

            def unit_model(theta):
                dx = jnp.stack([theta[0], theta[2]]) - fixed[0]
                lin = jax.tree.map(lambda v, j: v + j @ dx, fixed[1], fixed[2])
                return _joint_model(lin, lit, theta[1] / ref, theta[3] if fit_black else b)

            theta = jax.lax.stop_gradient(jnp.stack([st, ss, g] + ([b] if fit_black else [])))
            aux = (jax.lax.stop_gradient(r), jax.jacfwd(unit_model)(theta))
            return (weights * (gain * r - obs)).reshape(-1), aux

        solver = _solver(options, y0.dtype)
        sol = optx.least_squares(
            residual, solver, y0, max_steps=options.max_steps, has_aux=True, throw=False
        )
        return sol.value, sol.result, sol.stats["num_steps"], sol.state.f_info.residual, sol.aux

    weights0 = jnp.asarray(_joint_weights(data.images, data.mask, data.exposure), obs.dtype)
    y_shape = jnp.zeros(4 if fit_black else 3, obs.dtype)
    args = (renderer, full, obs, black_fixed)
    static = ("joint", fit_black, lit, _solver_key(options), options.max_steps)
    compiled, t_compile = _timed_compile(solve, *args, weights0, y_shape, static=static)

    def run(weights, y0):
        return jax.block_until_ready(compiled(*args, weights, y0))

    return run, weights0, t_compile


def _joint_start(start, fit_black: bool, dtype):
    st0, ss0, g0, b0 = start
    frac = min(max(ss0 / st0, 1e-3), 1 - 1e-3)
    y0 = [math.log(st0), _logit(frac), math.atanh(max(min(g0, 0.95), -0.95))]
    if fit_black:
        y0.append(_logit((min(max(b0, -0.15), 0.95) + 0.2) / 1.2))
    return jnp.asarray(y0, dtype)


def _joint_reweighted(data: _Data, weights, res):
    """Weights from the fitted model (data + residual/weight) instead of the noisy data
    (weights from the data itself bias a weighted fit toward low values)."""
    w = np.asarray(weights)
    fitted = data.images + np.where(
        w > 0, np.asarray(res).reshape(w.shape) / np.where(w > 0, w, 1), 0
    )
    return jnp.asarray(_joint_weights(fitted, data.mask, data.exposure), weights.dtype)


def _joint_result(data: _Data, black, weights, solved, steps, t_compile, t_run) -> dict:
    """The values, uncertainties (full Jacobian in σt, σs, g, gain (, b)) and stats."""
    y, result, _steps, res, (r_unit, jac_r) = solved
    fit_black = black is None
    black_fixed = 0.0 if black is None else float(black)
    st, ss, g, b = (float(v) for v in _unpack(y, fit_black, black_fixed))
    obs = np.asarray(data.images, np.float64)
    w = np.asarray(weights, np.float64)
    wr = w * np.asarray(r_unit, np.float64)
    gain = float(np.sum(wr * w * obs) / np.sum(wr * wr))
    cols = (w[..., None] * gain * np.asarray(jac_r, np.float64)).reshape(-1, jac_r.shape[-1])
    jac = np.concatenate([cols[:, :3], wr.reshape(-1, 1), cols[:, 3:]], axis=1)
    names = ["sigma_t", "sigma_s", "g", "gain"] + (["black_level"] if fit_black else [])
    res = np.asarray(res, np.float64)
    unc, corr, cond = _covariance(jac, res, names)
    n = int(np.sum(data.mask)) * obs.shape[0]
    rms = float(np.sqrt(np.sum(res**2) / max(n, 1)))
    return {
        "sigma_t": st,
        "sigma_s": ss,
        "g": g,
        "gain": gain,
        "black_level": b if fit_black else black_fixed,
        "result": result,
        "steps": int(steps),
        "compile": t_compile,
        "run": t_run,
        "unc": unc,
        "corr": corr,
        "cond": cond,
        "rms": rms,
    }


def _joint_solve(
    data: _Data, pattern: Stripes, model: _Model, options: FitOptions, start, black, reweight
):
    """Levenberg-Marquardt on the raw images (:func:`_joint_program`) from ``start``
    = (σt, σs, g, b). With ``reweight``, a second solve from the first one's answer
    uses weights from the fitted model (:func:`_joint_reweighted`)."""
    run, weights, t_compile = _joint_program(data, pattern, model, options, black)
    t = time.perf_counter()
    solved = run(weights, _joint_start(start, black is None, weights.dtype))
    steps = int(solved[2])
    if reweight:
        weights = _joint_reweighted(data, weights, solved[3])
        solved = run(weights, solved[0])
        steps += int(solved[2])
    return _joint_result(data, black, weights, solved, steps, t_compile, time.perf_counter() - t)


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
            ``images`` (:mod:`lightfield_jax._hdr`): the joint fit weights by √T.
    """
    options = dataclasses.replace(options or FitOptions(), **overrides)
    if isinstance(options.geometry, AutoGeometry):
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
    if isinstance(options.geometry, Plane):
        options = dataclasses.replace(options, geometry=None)
    elif isinstance(options.geometry, Slab):
        # The slab's 3-D Henyey–Greenstein is normalised on the sphere: ρ = ω.
        options = dataclasses.replace(options, phase="normalized")
    elif options.geometry is not None:
        raise ValueError(
            f"geometry: must be a Plane, Slab or AutoGeometry, got {options.geometry!r}"
        )
    say = progress or (lambda _msg: None)
    t_start = time.perf_counter()
    images = np.asarray(images, dtype=jnp.result_type(float))
    if images.ndim != 3 or images.shape[0] != pattern.n_patterns:
        raise ValueError(
            f"images: expected ({pattern.n_patterns}, height, width) for {pattern.n_patterns} "
            f"phases, got shape {images.shape}"
        )
    finite = np.all(np.isfinite(images), axis=0)
    mask = finite if mask is None else (np.asarray(mask, bool) & finite)
    images = np.where(mask[None], images, 0.0)

    say("separating direct and multiple scattering")
    direct, multiple, decay = _separate_and_decay(
        images, mask, pattern, black_level, saturation, split
    )
    sigma_t0 = float(decay.sigma_t)
    if not math.isfinite(sigma_t0) or sigma_t0 <= 0:
        raise ValueError(f"the direct image's decay gives no usable sigma_t ({sigma_t0!r})")

    # A first model for the two-step estimate. Σ M / Σ D ≈ Σ_{k≥2} I_k / I_1 ≈ ρ/(1 − ρ)
    # sizes the bounces (with margin: the separation biases M low).
    ratio = float(
        np.sum(np.where(mask, multiple, 0.0)) / max(np.sum(np.where(mask, direct, 0.0)), 1e-30)
    )
    rho0 = min(max(ratio, 0.0) / (1.0 + max(ratio, 0.0)) * 1.5 + 0.05, 0.95)
    model = size_model(images, pattern, albedo=rho0, g=0.0, options=options, sigma_t=sigma_t0)
    x0, y0, x1, y1 = model.crop
    data = _Data(
        images=images[:, y0:y1, x0:x1],
        mask=mask[y0:y1, x0:x1],
        direct=direct[y0:y1, x0:x1],
        multiple=multiple[y0:y1, x0:x1],
        sigma_t0=sigma_t0,
        sigma_t0_err=float(decay.sigma_t_stderr),
        decay_converged=bool(decay.converged),
        exposure=None if exposure is None else np.asarray(exposure)[:, y0:y1, x0:x1],
    )
    seconds = {"compile": 0.0, "run": 0.0}
    two_step_unc = {"sigma_t": data.sigma_t0_err}

    if options.method in ("grid", "gradient"):
        name = options.method
        say(
            f"{name}: search over g"
            + (" and Levenberg-Marquardt over (sigma_s, g)" if name == "gradient" else "")
        )
        s, g, gain, rms, unc, corr, cond, ok, msg, steps, tc = _two_step(
            data, pattern, model, options, sigma_t0, name
        )
        seconds["compile"] += tc
        # The first model was sized before g was known (g = 0). Where the estimate needs
        # a much larger one (4× the θ bins, a finer grid, more bounces: a forward-peaked
        # medium), solve once more with it; a 2× θ difference costs less than a refit.
        if math.isfinite(s) and math.isfinite(g) and s > 0:
            need = size_model(
                images,
                pattern,
                albedo=min(s / sigma_t0, 0.98),
                g=g,
                options=options,
                sigma_t=sigma_t0,
            )
            if need.crop == model.crop and (
                need.grid.n_theta >= 4 * model.grid.n_theta
                or need.grid.refine > model.grid.refine
                or need.bounces > model.bounces
            ):
                say(
                    f"{name}: again with the model the estimate needs (n_theta "
                    f"{need.grid.n_theta}, refine {need.grid.refine}, {need.bounces} bounces)"
                )
                model = _Model(
                    grid=Grid(
                        need.grid.width,
                        need.grid.height,
                        max(need.grid.n_theta, model.grid.n_theta),
                        max(need.grid.refine, model.grid.refine),
                    ),
                    bounces=max(need.bounces, model.bounces),
                    crop=model.crop,
                    converges=need.converges,
                    rho=need.rho,
                    geometry=need.geometry,
                )
                s, g, gain, rms, unc, corr, cond, ok, msg, steps, tc = _two_step(
                    data, pattern, model, options, sigma_t0, name
                )
                seconds["compile"] += tc
        if not data.decay_converged:
            ok, msg = False, "the decay fit of sigma_t did not converge"
        iterations = options.g_grid if name == "grid" else steps
        return _finish(
            options,
            t_start,
            seconds,
            model,
            method=name,
            sigma_t=sigma_t0,
            sigma_s=s,
            g=g,
            gain=gain,
            black_level=black_level,
            uncertainty={**two_step_unc, **unc},
            correlation=corr,
            converged=ok,
            message=msg,
            iterations=iterations,
            residual=rms,
            pixel_size_mm=pixel_size_mm,
            condition_number=cond,
        )

    say(f"joint start: search over {options.start_grid} values of g (two-step residual)")
    s, g, tc = _two_step(data, pattern, model, options, sigma_t0, "start")
    seconds["compile"] += tc

    # Joint, in two stages: a coarse model (32 θ bins, native grid) from the two-step
    # estimate, then the model the coarse estimate needs, polished from there. The
    # model-weighted refit runs once, on the last stage.
    fit_black = black_level is None
    start = (sigma_t0, s, g, 0.0 if fit_black else black_level)
    coarse = dataclasses.replace(options, n_theta=options.n_theta or 32, refine=options.refine or 1)
    if isinstance(options.geometry, Slab):  # 8 azimuth bins, 4 elevation nodes
        slab = options.geometry
        coarse = dataclasses.replace(
            coarse,
            n_theta=options.n_theta or 8,
            geometry=dataclasses.replace(slab, n_mu=slab.n_mu or 4),
        )
    total_steps = 0
    prev_model = run = weights = solved = None
    for name, opts in (("coarse", coarse), ("final", options)):
        # The coarse stage starts from the separation's estimate (σs biased low, MODEL.md
        # §6): double it; the final stage starts from the coarse fit (small margin).
        coarse_stage = name == "coarse"
        model = size_model(
            images,
            pattern,
            albedo=min(start[1] / start[0] * (2.0 if coarse_stage else 1.0), 0.98),
            g=start[2],
            options=opts,
            margin=1.15 if coarse_stage else 1.03,
            sigma_t=start[0],
        )
        t = time.perf_counter()
        if prev_model is not None and _covers(prev_model, model):
            # The coarse model is already as large as the estimate needs: refit it with
            # the model's weights, and that is the answer.
            weights = _joint_reweighted(data, weights, solved[3])
            solved = run(weights, solved[0])
            out = _joint_result(
                data, black_level, weights, solved, int(solved[2]), 0.0, time.perf_counter() - t
            )
            seconds["run"] += out["run"]
            total_steps += out["steps"]
            break
        x0, y0, x1, y1 = model.crop
        data.images = images[:, y0:y1, x0:x1]
        data.mask = mask[y0:y1, x0:x1]
        if exposure is not None:
            data.exposure = np.asarray(exposure)[:, y0:y1, x0:x1]
        say(
            f"joint fit ({name} model {model.grid.width}x{model.grid.height}, "
            f"n_theta {model.grid.n_theta}, refine {model.grid.refine}, {model.bounces} bounces)"
        )
        run, weights, t_compile = _joint_program(data, pattern, model, opts, black_level)
        t = time.perf_counter()
        solved = run(weights, _joint_start(start, fit_black, weights.dtype))
        steps = int(solved[2])
        if not coarse_stage:
            weights = _joint_reweighted(data, weights, solved[3])
            solved = run(weights, solved[0])
            steps += int(solved[2])
        out = _joint_result(
            data, black_level, weights, solved, steps, t_compile, time.perf_counter() - t
        )
        seconds["compile"] += out["compile"]
        seconds["run"] += out["run"]
        total_steps += out["steps"]
        say(
            f"  {name}: {out['steps']} steps, "
            f"{out['compile']:.1f} s compile, {out['run']:.1f} s run"
        )
        start = (out["sigma_t"], out["sigma_s"], out["g"], out["black_level"])
        prev_model = model
    ok, msg = _result_message(out["result"])
    return _finish(
        options,
        t_start,
        seconds,
        prev_model,
        method="joint",
        sigma_t=out["sigma_t"],
        sigma_s=out["sigma_s"],
        g=out["g"],
        gain=out["gain"],
        black_level=out["black_level"],
        uncertainty=out["unc"],
        correlation=out["corr"],
        converged=ok,
        message=msg,
        iterations=total_steps,
        residual=out["rms"],
        pixel_size_mm=pixel_size_mm,
        condition_number=out["cond"],
    )


def _covers(have: _Model, need: _Model) -> bool:
    return (
        have.crop == need.crop
        and have.bounces >= need.bounces
        and have.grid.n_theta >= need.grid.n_theta
        and have.grid.refine >= need.grid.refine
    )


def _finish(options: FitOptions, t_start: float, seconds: dict, model: _Model, **values):
    """The :class:`FitResult`, with total time and the model used."""
    seconds = dict(seconds)
    seconds["total"] = time.perf_counter() - t_start
    # Everything that is not XLA compilation counts as run time.
    seconds["run"] = seconds["total"] - seconds["compile"]
    unc = values.pop("uncertainty")
    unc = {k: unc.get(k, math.nan) for k in _PARAMS if k in unc or k != "black_level"}
    black = values.pop("black_level")
    numbers = ("sigma_t", "sigma_s", "g", "gain", "residual", "condition_number")
    bad = [k for k in numbers[:4] if not math.isfinite(float(values[k]))]
    if bad:  # never a silent NaN: the fit failed
        values["converged"] = False
        values["message"] = f"non-finite result ({', '.join(bad)}); {values['message']}"
    return FitResult(
        **{k: float(values.pop(k)) for k in numbers},
        black_level=None if black is None else float(black),
        uncertainty=unc,
        converged=bool(values.pop("converged")),
        iterations=int(values.pop("iterations")),
        seconds=seconds,
        model=model.as_dict(),
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


# --------------------------------------------------------------------------- captures


@dataclasses.dataclass(frozen=True)
class CaptureFit:
    """The fit of every channel of a capture (one :class:`FitResult` each)."""

    channels: tuple[str, ...]
    results: tuple[FitResult, ...]

    @property
    def converged(self) -> bool:
        return all(r.converged for r in self.results)

    def __getitem__(self, channel: str) -> FitResult:
        return self.results[self.channels.index(channel)]

    def to_dict(self) -> dict:
        """``results.json``: the result's keys for one channel; for several, each key
        holds a list in channel order and ``per_channel`` the full results."""
        if len(self.results) == 1:
            return {**self.results[0].to_dict(), "channel": self.channels[0]}
        dicts = [r.to_dict() for r in self.results]
        keys = (
            "sigma_t",
            "sigma_s",
            "sigma_a",
            "g",
            "albedo",
            "gain",
            "black_level",
            "rho",
            "iterations",
            "residual",
        )
        out = {k: [d[k] for d in dicts] for k in keys}
        out["uncertainty"] = {
            k: [d["uncertainty"].get(k) for d in dicts] for k in dicts[0]["uncertainty"]
        }
        out.update(
            method=dicts[0]["method"],
            converged=self.converged,
            seconds={"total": sum(d["seconds"]["total"] for d in dicts)},
            model=[d["model"] for d in dicts],
            channels=list(self.channels),
            per_channel=dict(zip(self.channels, dicts, strict=True)),
        )
        return out


def fit_capture(
    capture,
    method: str = "joint",
    *,
    channels: Sequence[str] | None = None,
    options: FitOptions | None = None,
    progress: Callable[[str], None] | None = None,
    **overrides,
) -> CaptureFit:
    """Fit a loaded capture (:func:`~lightfield_jax.load_capture`), channel by channel.

    Args:
        capture: the capture (images dark-subtracted and cropped to the medium).
        method: ``joint`` (default), ``gradient`` or ``grid``.
        channels: channel names to fit (default: every channel the capture holds).
        options, overrides: see :func:`fit_images`.
        progress: called with a description of each stage.
    """
    names = tuple(capture.channel_names)
    chosen = names if channels is None else tuple(channels)
    for c in chosen:
        if c not in names:
            raise ValueError(f"channel: {c!r} is not in the capture (it has {', '.join(names)})")
    results = []
    say = progress or (lambda _m: None)
    opts = options or FitOptions()
    if opts.geometry is None and "geometry" not in overrides:
        geometry = parse_geometry(getattr(capture, "geometry", None), "geometry", allow_auto=True)
        options = dataclasses.replace(opts, geometry=geometry)
    for c in chosen:
        i = names.index(c)
        results.append(
            fit_images(
                capture.images[..., i],
                capture.pattern,
                mask=np.all(capture.mask[..., i : i + 1], axis=-1),
                black_level=capture.black_level,
                saturation=capture.saturation,
                pixel_size_mm=capture.pixel_size_mm,
                exposure=_channel_exposure(capture, i),
                options=options,
                progress=(lambda m, c=c: say(f"[{c}] {m}")) if len(chosen) > 1 else say,
                method=method,
                **overrides,
            )
        )
    return CaptureFit(channels=chosen, results=tuple(results))


def _channel_exposure(capture, i: int):
    """Channel i of a capture's merged-bracket exposure T, or ``None``."""
    exposure = getattr(capture, "exposure", None)
    return None if exposure is None else exposure[..., i]


def fitted_images(result: FitResult, pattern: Stripes, shape: tuple[int, int]):
    """The fitted model's per-bounce images of every pattern and under full illumination,
    gain and black level included, over the cropped model region placed in an image of
    ``shape`` (zeros outside): ``(stripes [P, K, H, W], full [K, H, W])``."""
    m = result.model
    grid = Grid(m["width"], m["height"], m["n_theta"], m["refine"])
    geometry = parse_geometry(m.get("geometry"), "model.geometry")
    geometry = geometry if isinstance(geometry, Slab) else None
    st, ss, g, c = result.sigma_t, result.sigma_s, result.g, result.gain
    b = result.black_level or 0.0
    k = m["bounces"]
    stripes = np.asarray(make_renderer(grid, pattern, k, result.phase, geometry)(st, ss, g)[0])
    full = np.asarray(
        make_renderer(grid, _full_for(pattern), k, result.phase, geometry)(st, ss, g)[0][0]
    )
    stripes = c * ((1 - b) * stripes + b * full[None])
    full = c * full
    x0, y0, x1, y1 = m["crop"]
    out_s = np.zeros(stripes.shape[:2] + tuple(shape))
    out_f = np.zeros(full.shape[:1] + tuple(shape))
    out_s[..., y0:y1, x0:x1] = stripes
    out_f[..., y0:y1, x0:x1] = full
    return out_s, out_f
