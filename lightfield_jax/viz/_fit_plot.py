"""The figure of a fit: decay profiles along the light and the residual map."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from lightfield_jax.checks import check_number, real_array
from lightfield_jax.checks import shown as brief
from lightfield_jax.inverse.decay import entry_coordinates
from lightfield_jax.inverse.fit import fitted_images
from lightfield_jax.inverse.options import FitResult
from lightfield_jax.inverse.separate import separate
from lightfield_jax.scene.geometry_spec import describe_geometry
from lightfield_jax.scene.illumination import Stripes

from ._common import check_common, finish, new_figure

# What the measured points are compared with: the fitted model's stripe images put
# through the capture's own separation.
SEPARATED_ALIKE = "fit, separated like the capture: compare with the dots"


def _profile(image, s, mask, bins):
    """Mean of ``image`` over pixels in each bin of the path length ``s``."""
    idx = np.digitize(s, bins) - 1
    out = np.full(len(bins) - 1, np.nan)
    for i in range(len(bins) - 1):
        sel = (idx == i) & mask
        if sel.any():
            out[i] = image[sel].mean()
    return out


def _data_limits(ax, image, mask):
    """Show the measured range (down to 1e-4 of its peak): below it a model curve only
    shows float round-off."""
    vals = image[mask]
    top = float(np.nanmax(vals)) if vals.size else 1.0
    if top > 0:
        ax.set_ylim(top * 1e-4, top * 2)


def _truth_result(result: FitResult, truth: dict) -> FitResult:
    """The fit's model at the true values (the fitted gain and black level where the
    truth has none: a merged or rescaled capture's units are not the simulation's),
    rendered at these values: without the fit's step to the continuum, which
    fitted_images takes back from a fitted answer."""
    model = {k: v for k, v in result.model.items() if k != "finer_model"}
    return dataclasses.replace(
        result,
        model=model,
        sigma_t=float(truth["sigma_t"]),
        sigma_s=float(truth["sigma_s"]),
        g=float(truth["g"]),
        gain=float(truth.get("gain", result.gain)),
        black_level=truth.get("black_level", result.black_level),
        phase=truth.get("phase", result.phase),
    )


def _per_mm(value: float, result: FitResult) -> str:
    mm = result.pixel_size_mm
    return f" ({value / mm:.4g} mm$^{{-1}}$)" if mm else ""


def plot_fit(
    images,
    pattern: Stripes,
    result: FitResult,
    path=None,
    *,
    title: str | None = None,
    mask=None,
    truth: dict | None = None,
):
    """Measured (separated) direct and multiple profiles against the fitted model's
    single scatter and its bounces k ≥ 2 along the propagation direction, and the
    raw-image residual map of the fit.

    Pixels outside ``mask`` are left out of the profiles and drawn grey (masked) in the
    residual map; the fit's model region (``result.model["crop"]``: the fit crops where
    the light fades) is outlined, and what lies outside it is hatched and named in the
    title. With ``truth`` (a capture's ``truth``: sigma_t, sigma_s, g and optionally
    gain, black_level, phase) the model at the true values is drawn dotted.

    Args:
        images: the fitted channel's shifted images ``(P, H, W)`` (dark subtracted).
        pattern: their stripes.
        result: the fit.
        path: the PNG to write (atomically), or ``None`` to return the figure.
        title: the figure's title (default: the fit's values and model).
        mask: True where a value was used: per pixel, ``(H, W)``, or per value, like
            ``images`` (the capture's ``sample_mask``); the separated profiles use the
            pixels valid in every shift, the residual each pixel's valid shifts.
        truth: the true parameters, to overlay.
    """
    from matplotlib.patches import Rectangle

    fn = "plot_fit"
    check_common(fn, path, title=title)
    if not isinstance(pattern, Stripes):
        raise ValueError(f"{fn}.pattern: must be a Stripes, got {type(pattern).__name__}")
    if not isinstance(result, FitResult):
        raise ValueError(
            f"{fn}.result: must be a FitResult (lightfield_jax.fit_images), got "
            f"{type(result).__name__}"
        )
    for key in ("sigma_t", "sigma_s", "g", "gain"):
        # Refused here: otherwise the NaN model's separation ends in "separate.images: no
        # pixel is finite ... (NaN or Inf everywhere)", of images that are finite.
        value = getattr(result, key)
        if not (isinstance(value, (int, float, np.number)) and math.isfinite(value)):
            raise ValueError(
                f"{fn}.result: {key} is {brief(value)}: a fit without finite values has no "
                "model to draw"
            )
    # Masked values may be NaN (a capture's non-finite pixels).
    images = real_array(images, f"{fn}.images", (3,), "(shifts, height, width)", finite="some")
    p, h, w = images.shape
    if p != pattern.n_patterns:
        raise ValueError(
            f"{fn}.images: {p} shifted images for a pattern of {pattern.n_patterns} phases"
        )
    given = np.ones((h, w), bool) if mask is None else np.asarray(mask)
    if given.dtype != bool or given.shape not in ((h, w), images.shape):
        raise ValueError(
            f"{fn}.mask: must be a boolean array of shape {(h, w)} or {images.shape}, got "
            f"{given.dtype} of shape {given.shape}"
        )
    crop = result.model.get("crop") if isinstance(result.model, dict) else None
    if not (
        isinstance(crop, (list, tuple))
        and len(crop) == 4
        and 0 <= crop[0] < crop[2] <= w
        and 0 <= crop[1] < crop[3] <= h
    ):
        raise ValueError(
            f"{fn}.result: its model crop {brief(crop)} does not fit the {w}x{h} images "
            "(a fit of other images?)"
        )
    if truth is not None:
        if not isinstance(truth, dict):
            raise ValueError(f"{fn}.truth: must be a mapping or None, got {brief(truth)}")
        for key in ("sigma_t", "sigma_s", "g", "gain"):
            if key in truth:
                check_number(truth[key], f"{fn}.truth.{key}")
    values = np.broadcast_to(given, images.shape)  # per value: (H, W) or (P, H, W)
    valid = np.all(values, axis=0)  # the separation's pixels: valid in every shift
    # A fitted black level can come out slightly negative (noise); the separation takes
    # only physical values.
    b = min(max(result.black_level or 0.0, 0.0), 0.99)
    sep = separate(images, lit_fraction=pattern.lit_fraction, black_level=b)
    d, m = np.asarray(sep.direct), np.asarray(sep.multiple)
    model_stripes, model_full = fitted_images(result, pattern, (h, w))
    # The fitted model's stripe images put through the same separation: what the
    # separated D and M should be (the separation is biased on stripes: its M is not
    # Σ_{k≥2} I_k, nor its D I_1).
    sep_model = separate(
        model_stripes.sum(axis=1), lit_fraction=pattern.lit_fraction, black_level=b
    )
    d_model, m_model = np.asarray(sep_model.direct), np.asarray(sep_model.multiple)
    true_full = None
    if truth and all(k in truth for k in ("sigma_t", "sigma_s", "g")):
        true_full = fitted_images(_truth_result(result, truth), pattern, (h, w))[1]
    s, _ = entry_coordinates(h, w, pattern.entry, pattern.direction_deg)
    x0, y0, x1, y1 = result.model["crop"]
    inside = np.zeros((h, w), bool)
    inside[y0:y1, x0:x1] = True
    used = inside & valid
    bins = np.arange(0.0, float(np.max(s[inside])) + 2.0, 2.0)
    centres = 0.5 * (bins[1:] + bins[:-1])
    along = "distance from the entry wall along the light (px)"
    unit = "mean intensity (image units: the capture's values)"

    fig = new_figure(15, 4.9)
    axes = fig.subplots(1, 3)
    ax = axes[0]
    # The dots are compared with the fit separated as they were (solid): at high albedo
    # the separation's D holds much multiple light, and the model's pure I_1 (dashed)
    # lies far below it without being wrong.
    ax.semilogy(centres, _profile(d, s, used, bins), "k.", label="measured D (separated)")
    ax.semilogy(centres, _profile(d_model, s, used, bins), "C3-", label=SEPARATED_ALIKE)
    ax.semilogy(
        centres,
        _profile(model_full[0], s, used, bins),
        "C0--",
        lw=1.0,
        label="fitted $I_1$ alone (not separated)",
    )
    if true_full is not None:
        ax.semilogy(centres, _profile(true_full[0], s, used, bins), "C2:", label="truth $I_1$")
    _data_limits(ax, d, used)
    ax.set_xlabel(along)
    ax.set_ylabel(unit)
    ax.set_title(
        f"direct: $\\sigma_t$ = {result.sigma_t:.4g} px$^{{-1}}${_per_mm(result.sigma_t, result)}"
        + (f"\ntruth {float(truth['sigma_t']):.4g} px$^{{-1}}$" if true_full is not None else ""),
        fontsize=10,
    )
    ax.legend(fontsize=8)

    ax = axes[1]
    ax.semilogy(centres, _profile(m, s, used, bins), "k.", label="measured M (separated)")
    ax.semilogy(centres, _profile(m_model, s, used, bins), "C3-", label=SEPARATED_ALIKE)
    ax.semilogy(
        centres,
        _profile(model_full[1:].sum(0), s, used, bins),
        "C1--",
        lw=1.0,
        label=r"fitted $\sum_{k\geq2} I_k$ alone (not separated)",
    )
    for k in range(1, min(model_full.shape[0], 6)):
        ax.semilogy(
            centres, _profile(model_full[k], s, used, bins), "--", lw=0.8, label=f"$I_{k + 1}$"
        )
    if true_full is not None:
        ax.semilogy(
            centres,
            _profile(true_full[1:].sum(0), s, used, bins),
            "C2:",
            label=r"truth $\sum_{k\geq2} I_k$",
        )
    _data_limits(ax, m, used)
    ax.set_xlabel(along)
    ax.set_ylabel(unit)
    ax.set_title(
        f"multiple: $\\sigma_s$ = {result.sigma_s:.4g} px$^{{-1}}$"
        f"{_per_mm(result.sigma_s, result)}, g = {result.g:.3f}"
        + (
            f"\ntruth {float(truth['sigma_s']):.4g} px$^{{-1}}$, g {float(truth['g']):.3f}"
            if true_full is not None
            else ""
        ),
        fontsize=10,
    )
    ax.legend(fontsize=7)

    ax = axes[2]
    model_total = model_stripes.sum(axis=1)
    scale = np.nanmax(np.abs(np.where(values, images, 0.0))) or 1.0
    # The mean over each pixel's valid shifts (a pixel clipped in some keeps the others).
    kept = values & inside[None]
    count = kept.sum(axis=0)
    total = np.where(kept, model_total - images, 0.0).sum(axis=0)
    resid = np.where(count > 0, total / np.maximum(count, 1) / scale, np.nan)
    lim = np.nanmax(np.abs(resid)) if np.isfinite(resid).any() else 1.0
    from matplotlib import colormaps

    cmap = colormaps["RdBu_r"].with_extremes(bad="0.75")
    im = ax.imshow(
        resid, cmap=cmap, vmin=-lim, vmax=lim, extent=(0, w, h, 0), interpolation="nearest"
    )
    fig.colorbar(im, ax=ax, label="(model − measured) / max, mean over shifts")
    ax.add_patch(
        Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec="k", lw=1.2, label="model region")
    )
    outside = [(0, 0, w, y0), (0, y1, w, h), (0, y0, x0, y1), (x1, y0, w, y1)]
    for ox0, oy0, ox1, oy1 in outside:
        if ox1 > ox0 and oy1 > oy0:
            ax.add_patch(
                Rectangle((ox0, oy0), ox1 - ox0, oy1 - oy0, fill=False, hatch="//", ec="0.4", lw=0)
            )
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    n_masked = int(((count == 0) & inside).sum())
    cropped = (x0, y0, x1, y1) != (0, 0, w, h)
    ax.set_title(
        "residual of the raw images; grey: masked "
        f"({n_masked} px)"
        + (
            f"\nhatched: cropped, model region x {x0}-{x1}, y {y0}-{y1} of {w}x{h}"
            if cropped
            else ""
        ),
        fontsize=9,
    )
    fig.suptitle(
        title
        or (
            f"{result.method} fit: σt {result.sigma_t:.4g}, σs {result.sigma_s:.4g} px⁻¹, "
            f"g {result.g:.3f} ({'converged' if result.converged else 'NOT converged'}; "
            f"model {describe_geometry(result.model)}, {result.model['width']}x"
            f"{result.model['height']}, n_theta {result.model['n_theta']}, "
            f"K {result.model['bounces']})"
        ),
        fontsize=11,
    )
    return finish(fig, path)
