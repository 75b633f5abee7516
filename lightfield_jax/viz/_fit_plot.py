"""The figure of a fit: decay profiles along the light and the residual map."""

from __future__ import annotations

import numpy as np

from .._decay import entry_coordinates
from .._fit import FitResult, fitted_images
from .._illumination import Stripes
from .._io import atomic_path
from .._separate import separate
from .._slab import describe_geometry


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


def plot_fit(images, pattern: Stripes, result: FitResult, path, *, title: str | None = None):
    """Write a PNG: measured (separated) direct and multiple profiles against the fitted
    model's single scatter and its bounces k ≥ 2 along the propagation direction, and the
    raw-image residual map of the fit.

    Args:
        images: the fitted channel's shifted images ``(P, H, W)`` (dark subtracted).
        pattern: their stripes.
        result: the fit.
        path: the PNG to write (atomically).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    images = np.asarray(images, dtype=np.float64)
    p, h, w = images.shape
    # A fitted black level can come out slightly negative (noise); the separation takes
    # only physical values.
    b = min(max(result.black_level or 0.0, 0.0), 0.99)
    sep = separate(images, lit_fraction=pattern.lit_fraction, black_level=b)
    d, m = np.asarray(sep.direct), np.asarray(sep.multiple)
    model_stripes, model_full = fitted_images(result, pattern, (h, w))
    s, _ = entry_coordinates(h, w, pattern.entry, pattern.direction_deg)
    x0, y0, x1, y1 = result.model["crop"]
    inside = np.zeros((h, w), bool)
    inside[y0:y1, x0:x1] = True
    bins = np.arange(0.0, float(np.max(s[inside])) + 2.0, 2.0)
    centres = 0.5 * (bins[1:] + bins[:-1])

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    ax = axes[0]
    ax.semilogy(centres, _profile(d, s, inside, bins), "k.", label="measured D (separated)")
    ax.semilogy(centres, _profile(model_full[0], s, inside, bins), "C0-", label="fitted $I_1$")
    _data_limits(ax, d, inside)
    ax.set_xlabel("distance from the entry wall along the light (px)")
    ax.set_ylabel("mean intensity (image units)")
    ax.set_title(f"direct: $\\sigma_t$ = {result.sigma_t:.4g} px$^{{-1}}$")
    ax.legend()

    ax = axes[1]
    ax.semilogy(centres, _profile(m, s, inside, bins), "k.", label="measured M (separated)")
    ax.semilogy(
        centres,
        _profile(model_full[1:].sum(0), s, inside, bins),
        "C1-",
        label=r"fitted $\sum_{k\geq2} I_k$",
    )
    for k in range(1, min(model_full.shape[0], 6)):
        ax.semilogy(
            centres, _profile(model_full[k], s, inside, bins), "--", lw=0.8, label=f"$I_{k + 1}$"
        )
    _data_limits(ax, m, inside)
    ax.set_xlabel("distance from the entry wall along the light (px)")
    ax.set_ylabel("mean intensity (image units)")
    ax.set_title(f"multiple: $\\sigma_s$ = {result.sigma_s:.4g}, g = {result.g:.3f}")
    ax.legend(fontsize=7)

    ax = axes[2]
    model_total = model_stripes.sum(axis=1)
    scale = np.nanmax(np.abs(images)) or 1.0
    resid = np.where(inside, (model_total - images).mean(axis=0) / scale, np.nan)
    lim = np.nanmax(np.abs(resid)) or 1.0
    im = ax.imshow(resid, cmap="RdBu_r", vmin=-lim, vmax=lim)
    fig.colorbar(im, ax=ax, label="(model − measured) / max, mean over shifts")
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    ax.set_title("residual of the raw images")
    fig.suptitle(
        title
        or (
            f"{result.method} fit: σt {result.sigma_t:.4g}, σs {result.sigma_s:.4g}, "
            f"g {result.g:.3f} ({'converged' if result.converged else 'NOT converged'}; "
            f"model {describe_geometry(result.model)}, {result.model['width']}x"
            f"{result.model['height']}, n_theta {result.model['n_theta']}, "
            f"K {result.model['bounces']})"
        )
    )
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
