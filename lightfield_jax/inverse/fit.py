"""The inverse problem (docs/model.md sections 5-6): recover σt, σs, g (and the gain) from a
stripe capture.

This module is the driver: :func:`fit_images` prepares the data
(:mod:`lightfield_jax.inverse.data`), sizes the first model and hands the problem to a
fit method (:mod:`lightfield_jax.inverse.methods`: ``GridSearch``, ``TwoStep``,
``Joint``, each taking any optimistix least-squares solver), then finishes the result;
it also chooses the geometry under ``geometry: auto`` and renders a result's fitted
images (:func:`fitted_images`). The parts live beside it: the settings and the result
(:class:`FitOptions`, :class:`FitResult`) in :mod:`lightfield_jax.inverse.options`
(the settings' groups by concern in :mod:`lightfield_jax.inverse.settings`), the
model-sizing rules in :mod:`lightfield_jax.inverse.model_size`, the joint fit in
:mod:`lightfield_jax.inverse.joint_fit` (a subpackage: its single solves and shared
pieces in :mod:`lightfield_jax.inverse.joint_fit.stage`); the fit of a whole capture, channel by
channel, is :mod:`lightfield_jax.inverse.capture_fit`. The methods, all on the same
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
their total; :mod:`lightfield_jax.inverse.budget`), χ²/dof, correlations, the solver's
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

import numpy as np

from lightfield_jax.capture.keys import check_pixel_size
from lightfield_jax.checks import number_problem, shown, unmask
from lightfield_jax.inverse.budget import Uncertainty
from lightfield_jax.inverse.data import FitProblem, prepare_data, valid_values
from lightfield_jax.inverse.geometry_model import geometry_model
from lightfield_jax.inverse.joint_fit.stage import model_renderer
from lightfield_jax.inverse.model_choice import choose, misfit, relative_noise
from lightfield_jax.inverse.model_size import ModelSpec, over_cap_note, size_model
from lightfield_jax.inverse.options import (
    PARAMS,
    FitOptions,
    FitResult,
    check_options,
    check_progress,
)
from lightfield_jax.inverse.programs import clear_compiled as clear_compiled
from lightfield_jax.inverse.programs import forget_if_crowded, repairing_compilation_cache
from lightfield_jax.inverse.two_step import full_for as _full_for
from lightfield_jax.runtime.memory import check_memory, fit_memory
from lightfield_jax.scene.geometry import AutoGeometry, as_geometry
from lightfield_jax.scene.geometry_spec import parse_fitted_geometry
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import INWARD_DEG, Stripes, unseparated_rows


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
        mask: ``True`` where the data are valid (finite, unsaturated): per pixel,
            ``(height, width)`` (valid in every shift), or per sample, like ``images``
            (a pixel clipped in some shifts keeps its other shifts in the joint fit; the
            separation, the decay and the two-step methods use only pixels valid in
            every shift). A numpy masked array for ``images`` is honoured: its masked
            values are excluded too (combined with ``mask``).
        black_level: the projector's dark-stripe level relative to a lit stripe, or
            ``None`` (unknown: ``joint`` estimates it, the two-step methods assume 0).
        saturation: value at or above which a sample is clipped: masked like ``mask``'s
            per-sample ``False``. Values clamped at a floor (a pile-up at the images'
            lowest value where a noise could have cut there: a 16-bit file, a camera's
            black subtraction) are found and masked alike; near a clip or a floor the
            joint fit also masks the values its answer puts within 3σ of it and solves
            again (``model["censoring"]``; docs/model.md §6).
        pixel_size_mm: to report coefficients in mm⁻¹ as well.
        options: :class:`FitOptions`; keyword ``overrides`` replace its settings (its
            flat keywords, :meth:`FitOptions.replace`).
        progress: called with a short description of each stage.
        split: ``(direct, multiple)`` images to use instead of separating the capture
            (e.g. a perfect split from a renderer: I_1 and Σ_{k≥2} I_k under full
            illumination). Used by the two-step methods and the joint fit's start.
            Numpy masked arrays are honoured: a pixel masked in either is not used.
        exposure: the effective exposure T of merged exposure brackets, like
            ``images`` (:mod:`lightfield_jax.capture.hdr`): the joint fit weights by √T.
            A numpy masked array is honoured: a value whose T is masked is not used.
    """
    check_options(options, "fit_images")
    check_progress(progress, "fit_images")
    options = (options or FitOptions()).replace(**overrides)
    if black_level is not None:
        # Checked here, before the images' checks, under fit_images' own name (the
        # helper would name it "separate.black_level").
        problem = number_problem(black_level, low=0.0, high=1.0, high_open=True)
        if problem is not None:
            raise ValueError(f"fit_images: black_level: {problem}")
    check_pixel_size(pixel_size_mm)
    images, mask = unmask(images, mask)
    return fit_one(
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


@repairing_compilation_cache()
def fit_one(
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
    floor: ModelSpec | None = None,
    clipped=None,
    floored=None,
) -> FitResult:
    """:func:`fit_images` with a ``floor``: the smallest model to use (its crop, θ bins,
    refinement, bounces), so that the channels of a capture share compiled programs;
    ``clipped`` and ``floored``: the values a capture masked as saturated and as clamped
    at a floor (:func:`prepare_data`)."""
    try:
        shape = np.shape(images)
    except ValueError:  # ragged: prepare_data names it
        shape = ()
    if len(shape) == 3:
        # The command line's memory check, for the Python API too: unchecked, fit_images
        # with n_theta 4096 and refine 8 on 128x96 images runs for minutes toward an
        # allocation it cannot make.
        p, h, w = shape
        check_memory(
            fit_memory(p * h * w, p, h, w, options.model), f"the fit of {p} images of {w}x{h}"
        )
    if as_geometry(options.model.geometry).chosen_by_fit:
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
            clipped=clipped,
            floored=floored,
        )
    # The plane is None from here on; the slab's 3-D Henyey–Greenstein is normalised on
    # the sphere (ρ = ω): its phase convention is "normalized".
    geometry = as_geometry(options.model.geometry)
    options = options.replace(
        geometry=geometry.slab_or_none,
        phase=geometry.phase_convention(options.model.phase),
    )
    say = progress or (lambda _msg: None)
    method = options.method
    if method.per_bounce:
        options = options.replace(tail=None)
    forget_if_crowded(say)
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
        clipped=clipped,
        floored=floored,
    )
    check_separable(options, pattern, split)  # after the images' checks, before any solve
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
    if (note := over_cap_note(model, options)) is not None:
        say(f"note: {note}")
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


def check_separable(options: FitOptions, pattern, split) -> None:
    """Refuse a two-step method (``per_bounce``: it fits the separated direct and multiple
    light) on stripes whose phases leave rows never lit or never dark, where the
    separation has no value to take (unless a ``split`` is given): its fit ran to a
    bound and a flag "not identifiable" that did not name the cause."""
    method = options.method
    if not method.per_bounce or split is not None or not isinstance(pattern, Stripes):
        return
    rows = unseparated_rows(pattern.period, pattern.lit, pattern.phases)
    if rows is not None:
        raise ValueError(
            f"method {method.name}: the stripes' phases {list(pattern.phases)} (period "
            f"{pattern.period}, lit {pattern.lit}) leave {rows}: the two-step methods fit "
            "the separated direct light, which needs each row lit in one shift and dark in "
            "another; use the joint method (it fits the raw images), or take more shifts"
        )


def _finish(options: FitOptions, t_start: float, seconds: dict, model: ModelSpec, **values):
    """The :class:`FitResult`, with total time, the model used and the error budget."""
    seconds = dict(seconds)
    seconds["total"] = time.perf_counter() - t_start
    # Everything that is not XLA compilation (tracing included) counts as run time.
    seconds["run"] = seconds["total"] - seconds["compile"]
    budget: Uncertainty = values.pop("budget")

    def per_param(d):
        return {k: d.get(k, math.nan) for k in PARAMS if k in d or k != "black_level"}

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
        correlation_statistical=budget.correlation_statistical,
        condition_number=budget.condition_number,
        uncertainty_statistical=per_param(budget.statistical),
        uncertainty_model=per_param(budget.model),
        chi2_dof=budget.chi2_dof,
        chi2_model=budget.chi2_model,
        noise=budget.noise,
        model_limited=budget.model_limited,
        consistency=budget.consistency,
        converged=bool(values.pop("converged")),
        iterations=int(values.pop("iterations")),
        seconds=seconds,
        model=model_dict,
        phase=options.model.phase,
        **values,
    )


def _fit_auto_geometry(images, pattern: Stripes, options: FitOptions, progress, **kwargs):
    """``geometry: auto``: the plane model's fit, kept where its misfit is below the
    capture's relative noise; the slab's fit otherwise. The result carries the choice
    and its evidence in ``model["geometry_choice"]``."""
    say = progress or (lambda _msg: None)
    auto: AutoGeometry = options.model.geometry

    def fit_with(geometry) -> FitResult:
        opts = options.replace(geometry=geometry)
        return fit_one(images, pattern, opts, progress, **kwargs)

    def chose(result: FitResult, choice: dict) -> FitResult:
        return dataclasses.replace(result, model={**result.model, "geometry_choice": choice})

    if abs((pattern.direction_deg - INWARD_DEG[pattern.entry] + 180.0) % 360.0 - 180.0) > 1e-6:
        # The model-free noise estimate differences along a pixel axis; oblique stripes
        # put their edges into it. Without a measurable noise, the slab (always valid).
        say("geometry auto: oblique stripes, the noise is not measurable: slab")
        reason = {"chosen": "slab", "reason": "oblique stripes: noise not measurable"}
        return chose(fit_with(auto.slab), reason)
    say("geometry auto: fitting the plane model")
    plane = fit_with(None)
    if plane.basins is not None and "stopped" in plane.basins:
        # A constant offset in the images (offset_stop) that no geometry has: a slab
        # fit would chase it as the plane's would have (or stop the same way).
        say("geometry auto: the plane fit stopped for a constant offset: no slab fit")
        reason = {
            "chosen": None,
            "reason": "none chosen: the plane fit stopped for a constant offset in the images",
        }
        return chose(plane, reason)
    data = np.asarray(images, np.float64)
    # Pixels valid in every shift, as the fit's own data has them.
    valid, _, _ = valid_values(
        data,
        pattern,
        kwargs.get("mask"),
        kwargs.get("saturation"),
        kwargs.get("clipped"),
        kwargs.get("floored"),
    )
    keep = np.all(valid, axis=0)
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


def model_from(d: dict) -> ModelSpec:
    """The :class:`ModelSpec` of a result's ``model`` dict (one written without the series'
    estimate, e.g. by an earlier version, renders alike: what is not given is unknown)."""
    geometry = geometry_model(parse_fitted_geometry(d.get("geometry"), "model.geometry"))
    tail = d.get("tail") or {}
    return ModelSpec(
        grid=Grid(d["width"], d["height"], d["n_theta"], d["refine"]),
        bounces=d["bounces"],
        crop=tuple(d["crop"]),
        converges=d.get("series_converges", True),
        rho=d.get("rho_estimate", math.nan),
        geometry=geometry,
        tail=tail.get("method"),
        tail_tol=tail.get("tol", 1e-4),
        tail_max_steps=tail.get("max_steps", 200),
        ratio=d.get("ratio_measured"),
        extrapolate=bool(d.get("extrapolated", False)),
        coarse_after=(d.get("coarse_tail") or {}).get("after"),
        cell=(d.get("stripe_cell") or {}).get("shift_orders"),
    )


def _own_answer(result: FitResult) -> dict:
    """The model's own answer of ``result``: its values less the step an extrapolated
    answer took to the continuum (``extrapolate``)."""
    extrapolation = (result.model.get("finer_model") or {}).get("extrapolation") or {}
    step = extrapolation.get("step") or {}
    out = {k: getattr(result, k) - step.get(k, 0.0) for k in ("sigma_t", "sigma_s", "g", "gain")}
    black = result.black_level
    out["black_level"] = None if black is None else black - step.get("black_level", 0.0)
    return out


def fitted_images(result: FitResult, pattern: Stripes, shape: tuple[int, int]):
    """The fitted model's per-bounce images of every pattern and under full illumination,
    gain and black level included, over the cropped model region placed in an image of
    ``shape`` (zeros outside): ``(stripes [P, K, H, W], full [K, H, W])``. A model with
    a tail has K = K0 + 1: the last slice holds the tail Σ_{k>K0} I_k. Rendered at the
    model's own answer: where the reported one is extrapolated to the continuum
    (``model["finer_model"]["extrapolation"]["step"]``), less that step, since the
    model's grid fits the capture at its own answer, not at the continuum's."""
    # Checked first: unchecked, another result (a to_dict()) or pattern raises an
    # AttributeError, a shape of strings or negative sizes numpy's errors, one of
    # 10**6 x 10**6 a MemoryError.
    if not isinstance(result, FitResult):
        raise ValueError(f"fitted_images: result: must be a FitResult, got {type(result).__name__}")
    if not isinstance(pattern, Stripes):
        raise ValueError(f"fitted_images: pattern: must be a Stripes, got {type(pattern).__name__}")
    model = model_from(result.model)
    x0, y0, x1, y1 = model.crop
    dims = () if isinstance(shape, (str, bytes)) or not np.iterable(shape) else tuple(shape)
    if not (
        len(dims) == 2
        and all(number_problem(n, integer=True, low=1) is None for n in dims)
        and dims[0] >= y1
        and dims[1] >= x1
    ):
        raise ValueError(
            f"fitted_images: shape: must be the images' (height, width), holding the fit's "
            f"model crop (x0, y0, x1, y1) = {model.crop}, got {shown(shape)}"
        )
    k = model.bounces + (model.tail is not None)
    check_memory(
        8 * (pattern.n_patterns + 1) * k * dims[0] * dims[1],
        f"fitted_images: {pattern.n_patterns + 1} x {k} images of {dims[1]}x{dims[0]}",
    )

    own = _own_answer(result)

    def render(illumination):
        renderer = model_renderer(model, illumination, result.phase)
        out = renderer.unchecked(own["sigma_t"], own["sigma_s"], own["g"])
        if model.tail is None:
            return np.asarray(out[0])
        return np.concatenate([np.asarray(out[0]), np.asarray(out[2].image)[:, None]], axis=1)

    c, b = own["gain"], own["black_level"] or 0.0
    stripes, full = render(pattern), render(_full_for(pattern))[0]
    stripes = c * ((1 - b) * stripes + b * full[None])
    full = c * full
    out_s = np.zeros(stripes.shape[:2] + dims)
    out_f = np.zeros(full.shape[:1] + dims)
    out_s[..., y0:y1, x0:x1] = stripes
    out_f[..., y0:y1, x0:x1] = full
    return out_s, out_f
