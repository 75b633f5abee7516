"""Figures of a real capture: what the pipeline sees before a fit (:func:`plot_inspect`)
and the fitted coefficients of each colour channel (:func:`plot_channels`).

Both write a PNG atomically and return its path (or, without ``path``, return the
matplotlib ``Figure``, built without pyplot).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from lightfield_jax.capture.inspect import SNR_USABLE, Inspection
from lightfield_jax.capture.keys import check_pixel_size
from lightfield_jax.checks import check_number
from lightfield_jax.checks import shown as brief
from lightfield_jax.inverse.capture_fit import CaptureFit

from ._common import check_common
from ._common import finish as _finish
from ._common import new_figure as _figure

_CHANNEL_COLOURS = {"R": "tab:red", "G": "tab:green", "B": "tab:blue", "Y": "0.2"}


def _kind(value, kind: type, key: str, made_by: str) -> None:
    """A result of another kind (a FitResult for a CaptureFit, a path for an
    Inspection) is named, not an AttributeError deep in the figure."""
    if not isinstance(value, kind):
        raise ValueError(
            f"{key}: must be {'an' if kind.__name__[0] in 'AEIOU' else 'a'} {kind.__name__} "
            f"({made_by}), got {type(value).__name__}"
        )


def _colour(name: str, i: int) -> str:
    return _CHANNEL_COLOURS.get(name, f"C{i}")


def _log_image(ax, image: np.ndarray, title: str, fig):
    from matplotlib.colors import LogNorm

    positive = image[image > 0]
    top = float(positive.max()) if positive.size else 1.0
    shown = np.clip(np.where(np.isfinite(image), image, 0.0), top * 1e-4, None)
    im = ax.imshow(shown, norm=LogNorm(vmin=top * 1e-4, vmax=top), cmap="magma")
    ax.set_title(title)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    fig.colorbar(im, ax=ax, shrink=0.8)


def _wall_segment(entry: str, roi):
    x0, y0, x1, y1 = roi
    return {
        "left": ([x0, x0], [y0, y1]),
        "right": ([x1, x1], [y0, y1]),
        "top": ([x0, x1], [y0, y0]),
        "bottom": ([x0, x1], [y1, y1]),
    }[entry]


def plot_inspect(inspection: Inspection, path=None):
    """What the pipeline sees: the frame with the medium's ROI, entry wall and the
    light's direction; the separated direct and multiple images; the masked pixels;
    and the SNR and mean of D and M along the light, per channel. For exposure
    brackets, a third row: a merged image, the camera's response curve and how many
    exposures clipped at each pixel (:func:`_plot_brackets`)."""
    from matplotlib.patches import Rectangle

    _kind(inspection, Inspection, "plot_inspect.inspection", "lightfield_jax.inspect_capture")
    check_common("plot_inspect", path)
    c = inspection.capture
    p, h, w, n = c.images.shape
    rows = 2 if c.brackets is None else 3
    fig = _figure(16, 4.5 * rows)
    axes = fig.subplots(rows, 3)

    ax = axes[0, 0]
    overview = c.overview.sum(axis=-1) if c.overview is not None else c.images.mean(0).sum(-1)
    full_h, full_w = overview.shape
    roi = c.roi or (0, 0, full_w, full_h)
    _log_image(ax, overview, "camera frame (mean of the shifts)", fig)
    x0, y0, x1, y1 = roi
    ax.add_patch(Rectangle((x0 - 0.5, y0 - 0.5), x1 - x0, y1 - y0, fill=False, ec="lime", lw=1.5))
    xs, ys = _wall_segment(c.pattern.entry, roi)
    ax.plot(np.array(xs) - 0.5, np.array(ys) - 0.5, color="cyan", lw=3, label="entry wall")
    t = math.radians(c.pattern.direction_deg)
    length = 0.35 * min(x1 - x0, y1 - y0) + 0.15 * max(x1 - x0, y1 - y0)
    start = (float(np.mean(xs)) - 0.5, float(np.mean(ys)) - 0.5)
    ax.annotate(
        "",
        xy=(start[0] + length * math.cos(t), start[1] + length * math.sin(t)),
        xytext=start,
        arrowprops={"arrowstyle": "->", "color": "cyan", "lw": 2},
    )
    det = c.detected
    conf = f", confidence {det.confidence:.2f}" if det is not None else ""
    ax.set_title(
        f"ROI {list(roi)}, entry {c.pattern.entry}, θ0 {c.pattern.direction_deg:.2f}°{conf}",
        fontsize=9,
    )
    ax.legend(loc="lower right", fontsize=7)

    _log_image(axes[0, 1], inspection.direct.sum(axis=-1), "direct D (single scatter)", fig)
    _log_image(axes[0, 2], inspection.multiple.sum(axis=-1), "multiple M (global)", fig)

    ax = axes[1, 0]
    masked = ~c.mask.all(axis=-1)
    shown = np.where(masked, 1.0, 0.0)
    ax.imshow(shown, cmap="Reds", vmin=0, vmax=1.2)
    ax.set_title(
        f"pixels masked in some image: {int(masked.sum())} (saturated "
        f"{c.n_masked['saturated']}, non-finite {c.n_masked['nonfinite']}; "
        f"{c.n_masked.get('values', 0)} values)",
        fontsize=9,
    )
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")

    ax = axes[1, 1]
    for i, name in enumerate(c.channel_names):
        colour = _colour(name, i)
        ax.semilogy(inspection.bins, inspection.snr_direct[i], "-", color=colour, label=f"D {name}")
        ax.semilogy(
            inspection.bins, inspection.snr_multiple[i], "--", color=colour, label=f"M {name}"
        )
    ax.axhline(SNR_USABLE, color="0.5", lw=0.8, ls=":")
    ax.set_xlabel("distance from the entry wall along the light (px)")
    ax.set_ylabel("SNR (mean / robust pixel noise)")
    ax.set_title("signal-to-noise along the beam")
    ax.legend(fontsize=7, ncol=2)

    ax = axes[1, 2]
    index = np.floor(inspection.distance / (inspection.bins[1] - inspection.bins[0])).astype(int)
    for i, name in enumerate(c.channel_names):
        colour = _colour(name, i)
        for image, style, label in (
            (inspection.direct[..., i], "-", "D"),
            (inspection.multiple[..., i], "--", "M"),
        ):
            prof = np.full(inspection.bins.size, np.nan)
            for k in range(prof.size):
                sel = c.mask[..., i] & (index == k)
                if sel.any():
                    prof[k] = float(np.mean(image[sel]))
            prof = np.where(prof > 0, prof, np.nan)
            ax.semilogy(inspection.bins, prof, style, color=colour, label=f"{label} {name}")
    ax.set_xlabel("distance from the entry wall along the light (px)")
    ax.set_ylabel("mean intensity (image units)")
    ax.set_title("direct and multiple light along the beam")
    ax.legend(fontsize=7, ncol=2)
    if c.brackets is not None:
        _plot_brackets(fig, axes[2], c)
    fig.suptitle(f"lightfield-jax inspect: {c.source.name}")
    return _finish(fig, path)


def _plot_brackets(fig, axes, c) -> None:
    """The merge of exposure brackets: the first shift's merged image, the inverse
    response x = f⁻¹(z) with the clip and near-black limits, and per pixel the number
    of exposures whose samples were clipped (mean over shifts and channels)."""
    b = c.brackets
    _log_image(axes[0], c.images[0].sum(axis=-1), "merged radiance, shift 0 (ROI)", fig)

    ax = axes[1]
    z = np.linspace(0.0, 1.0, 513)
    n = b.response.curve.shape[1]
    x = b.response.linearize(np.repeat(z[:, None], n, axis=1))
    for i in range(n):
        name = c.channel_names[i] if n == len(c.channel_names) else "all"
        ax.plot(z, x[:, i], color=_colour(name, i), label=f"{b.response.kind} response {name}")
    ax.axvline(b.clip, color="0.3", ls="--", lw=0.8, label=f"clipped above {b.clip:g}")
    # With a dark frame near black is judged against each sample's predicted signal,
    # not at a fixed code: no line to draw.
    for i, v in enumerate(() if getattr(b, "dark_frame", False) else b.near_black):
        ax.axvline(
            v,
            color="0.6",
            ls=":",
            lw=0.8,
            label="near black below (no dark frame)" if i == 0 else None,
        )
    ax.set_xlabel("sample value z (integer codes / their maximum)")
    ax.set_ylabel("linear exposure x = f⁻¹(z) (relative)")
    ax.set_title("camera response used by the merge", fontsize=9)
    ax.legend(fontsize=7)

    ax = axes[2]
    clipped = b.clipped_fraction.sum(axis=0)
    j = len(b.times)
    im = ax.imshow(clipped, cmap="viridis", vmin=0, vmax=j, interpolation="nearest")
    fig.colorbar(im, ax=ax, shrink=0.8, label="exposures clipped (mean over shifts)")
    per = ", ".join(
        f"{t * 1e3:g} ms {100 * float(f.mean()):.0f}%"
        for t, f in zip(b.times, b.clipped_fraction, strict=True)
    )
    ax.set_title(f"clipped samples (whole frame): {per}", fontsize=9)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")


def plot_channels(
    fit: CaptureFit,
    path=None,
    *,
    truth: Sequence[Mapping[str, float]] | None = None,
    pixel_size_mm: float | None = None,
):
    """σt, σs and g of every fitted channel with their 1σ error bars (per pixel, or per
    mm with ``pixel_size_mm``); ``truth`` adds one mapping of true values per channel."""
    fn = "plot_channels"
    _kind(fit, CaptureFit, f"{fn}.fit", "lightfield_jax.fit_capture")
    check_common(fn, path)
    # None: per pixel; 0 is refused (not taken as None), a negative pitch too (it would
    # draw negative coefficients).
    check_pixel_size(pixel_size_mm, f"{fn}.pixel_size_mm")
    names = list(fit.channels)
    if truth is not None:
        if (
            isinstance(truth, Mapping)
            or not isinstance(truth, Sequence)
            or len(truth) != len(names)
        ):
            raise ValueError(
                f"{fn}.truth: must be a list of {len(names)} mappings (one per channel "
                f"{', '.join(names)}), got {brief(truth)}"
            )
        for i, values in enumerate(truth):
            if not isinstance(values, Mapping):
                raise ValueError(f"{fn}.truth[{i}]: must be a mapping, got {brief(values)}")
            for key in ("sigma_t", "sigma_s", "g"):
                if key in values:
                    check_number(values[key], f"{fn}.truth[{i}].{key}")
    scale = 1.0 / pixel_size_mm if pixel_size_mm else 1.0
    unit = "mm$^{-1}$" if pixel_size_mm else "px$^{-1}$"
    fig = _figure(12, 3.8)
    axes = fig.subplots(1, 3)
    x = np.arange(len(names))
    for ax, key, label in zip(
        axes,
        ("sigma_t", "sigma_s", "g"),
        (f"$\\sigma_t$ ({unit})", f"$\\sigma_s$ ({unit})", "g"),
        strict=True,
    ):
        k = 1.0 if key == "g" else scale
        for i, (name, r) in enumerate(zip(names, fit.results, strict=True)):
            err = r.uncertainty.get(key, math.nan)
            ax.errorbar(
                x[i],
                getattr(r, key) * k,
                yerr=None if not math.isfinite(err) else err * k,
                fmt="o",
                color=_colour(name, i),
                capsize=4,
                mfc="white" if not r.converged else _colour(name, i),
            )
            if truth is not None and key in truth[i]:
                ax.plot(x[i] + 0.15, truth[i][key] * k, "kx", label="truth" if i == 0 else None)
        ax.set_xticks(x, names)
        ax.set_xlim(-0.6, len(names) - 0.4)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if truth is not None:
            ax.legend(fontsize=7)
    method = fit.results[0].method
    state = "all converged" if fit.converged else "NOT all converged (open markers)"
    fig.suptitle(f"{method} fit per channel, 1σ error bars ({state})")
    return _finish(fig, path)
