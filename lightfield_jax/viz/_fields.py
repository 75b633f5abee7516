"""The paper's image figures (Mukaigawa, Raskar & Yagi 2010, Figs. 13-14) for any result.

The conventions of :mod:`lightfield_jax.viz._paper` (image frame, source units, ``path``
or a returned ``Figure``).

- :func:`plot_lightfield` (Fig. 13): a light field L(x, y, θ) as a pseudo-colour
  fluence image with polar glyphs of the direction distribution at sample points.
- :func:`plot_bounce_images` (Fig. 14): the per-bounce images side by side (e.g. of an
  oblique beam).

Both also take a :class:`~lightfield_jax.RenderResult` itself (its ``images``, or its
``lightfields`` L_0..L_K); of a stripe render, the sum over the shifted patterns (each
row lit ``lit`` times: ``lit`` × full illumination).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from lightfield_jax.checks import check_flag, check_int, check_number
from lightfield_jax.checks import shown as brief
from lightfield_jax.forward.render import RenderResult
from lightfield_jax.scene.illumination import (
    Beam,
    Illumination,
)

from ._common import (
    MAX_GLYPHS,
    MAX_PANELS,
    UNITS,
    bounce_images,
    check_common,
    check_illumination,
    check_panels,
    checked_array,
    render_fields,
)
from ._common import finish as _finish
from ._common import new_figure as _figure

# ------------------------------------------------------------ Fig. 13: light field


def plot_lightfield(
    lightfield,
    path=None,
    *,
    labels: Sequence[str] | None = None,
    points: Sequence[tuple[float, float]] | None = None,
    spacing: float | None = None,
    glyph_radius: float | None = None,
    glyph_scale: str = "local",
    log: bool = True,
    dynamic_range: float = 1e4,
    columns: int = 3,
    title: str | None = None,
    show: int = 4,
):
    """Fig. 13: light field(s) as fluence images with polar glyphs of L(θ).

    The colour is the fluence Σ_θ L(θ)·Δθ of each pixel. At each sample point a glyph
    is the closed curve (x, y) + R·r(θ)·(cos θ, sin θ) over the bin centres θ_j, with
    r = L(θ)/max: how much light travels in each direction there (θ from +x toward +y,
    i.e. drawn in the image frame; a beam heading +x has its lobe pointing right).

    Args:
        lightfield: one light field (height, width, n_theta), e.g.
            ``render(..., lightfield=True).lightfields[k]`` for L_k (radiance per
            radian), or several stacked (panels, height, width, n_theta), or a
            :class:`~lightfield_jax.RenderResult` rendered with ``lightfield=True``
            (panels L_0..L_``show`` and Σ_k L_k).
        path: PNG to write, or ``None`` to return the figure.
        labels: one panel title per light field (default ``L_1``, ``L_2``, ... for a
            stack, ``L`` for one).
        points: glyph centres (x, y) in pixels; default a regular grid every
            ``spacing`` pixels (default: an eighth of the larger side).
        glyph_radius: glyph size in pixels (default 0.45 × spacing).
        glyph_scale: ``"local"`` (each glyph scaled to its own maximum: the shape of
            the direction distribution) or ``"global"`` (to the largest L(θ) at any
            sample point of the panel: the shape and how much light there is).
        log: colour on a log scale over ``dynamic_range`` below the panel's maximum.
        dynamic_range: the colour range; no glyph is drawn where the fluence is below
            the panel's maximum / dynamic_range.
        columns: panels per row.
        title: figure title.
        show: of a RenderResult, the last bounce drawn on its own.
    """
    from matplotlib.colors import LogNorm, Normalize

    fn = "plot_lightfield"
    check_common(fn, path, dynamic_range=dynamic_range, title=title)
    check_flag(log, f"{fn}.log")
    if not isinstance(glyph_scale, str) or glyph_scale not in ("local", "global"):
        raise ValueError(f"{fn}.glyph_scale: must be 'local' or 'global', got {brief(glyph_scale)}")
    check_int(columns, f"{fn}.columns", low=1, high=MAX_PANELS)
    if isinstance(lightfield, RenderResult):
        lightfield, rendered = render_fields(lightfield, show)
        labels = rendered if labels is None else labels
    what = "(height, width, n_theta) or (panels, height, width, n_theta), or a RenderResult"
    fields = checked_array(lightfield, (3, 4), f"{fn}.lightfield", what)
    single = fields.ndim == 3
    if single:
        fields = fields[None]
    n_panels, height, width, n_theta = fields.shape
    check_panels(n_panels, fn, "light fields")
    if labels is None:
        labels = ["L"] if single else [f"$L_{{{i + 1}}}$" for i in range(n_panels)]
    if isinstance(labels, (str, bytes)) or not isinstance(labels, Sequence):
        raise ValueError(f"{fn}.labels: must be a list of {n_panels} titles, got {brief(labels)}")
    if len(labels) != n_panels:
        raise ValueError(f"{fn}.labels: need {n_panels} labels, got {len(labels)}")
    dtheta = 2 * math.pi / n_theta
    theta = np.arange(n_theta + 1) * dtheta  # closed curve
    side = max(height, width)
    if spacing is None:
        spacing = side / 8
    else:
        # At least 1 px and at most MAX_GLYPHS glyphs over the panel (1e-3 px asked for
        # 7.7e8 glyphs: minutes, then memory).
        least = max(1.0, math.sqrt(height * width / MAX_GLYPHS))
        unit = f" px (at most about {MAX_GLYPHS} glyphs on the {width}x{height} panel)"
        spacing = check_number(spacing, f"{fn}.spacing", low=least, high=side, unit=unit)
    if glyph_radius is None:
        radius = 0.45 * spacing
    else:
        radius = check_number(
            glyph_radius, f"{fn}.glyph_radius", low=0.0, low_open=True, high=side, unit=" px"
        )
    if points is None:
        xs = np.arange(spacing / 2, width, spacing)
        ys = np.arange(spacing / 2, height, spacing)
        points = [(x, y) for y in ys for x in xs]
    else:
        points = _points(points, fn, height, width)
    ncols = min(columns, n_panels)
    nrows = math.ceil(n_panels / ncols)
    fig = _figure(5.2 * ncols, 0.5 + 4.6 * nrows * height / width * 1.15)
    axes = np.atleast_1d(fig.subplots(nrows, ncols, squeeze=False)).ravel()
    for ax, field, label in zip(axes, fields, labels, strict=False):
        fluence = field.sum(axis=-1) * dtheta
        top = float(np.max(fluence)) if np.max(fluence) > 0 else 1.0
        floor = top / dynamic_range
        norm = LogNorm(floor, top) if log else Normalize(0.0, top)
        shown = np.maximum(fluence, floor) if log else fluence
        im = ax.imshow(
            shown, cmap="magma", norm=norm, extent=(0, width, height, 0), interpolation="nearest"
        )
        fig.colorbar(im, ax=ax, shrink=0.85, label=f"fluence Σθ L Δθ ({UNITS})")
        # No glyph where the fluence is below the colour range: there a float32 render
        # holds round-off of either sign, not a direction distribution.
        samples = []
        for x, y in points:
            r, c = min(int(y), height - 1), min(int(x), width - 1)
            if fluence[r, c] >= floor:
                samples.append((x, y, np.maximum(field[r, c], 0.0)))
        global_max = max((float(v.max()) for _, _, v in samples), default=0.0)
        for x, y, dist in samples:
            scale = float(dist.max()) if glyph_scale == "local" else global_max
            if scale <= 0:
                continue
            r = np.append(dist, dist[0]) / scale
            ax.plot(
                x + radius * r * np.cos(theta),
                y + radius * r * np.sin(theta),
                "-",
                color="cyan",
                lw=0.9,
            )
            ax.plot(x, y, ".", color="white", ms=2)
        ax.set_xlim(0, width)
        ax.set_ylim(height, 0)
        ax.set_xlabel("x (px)")
        ax.set_ylabel("y (px)")
        ax.set_title(f"{label} ({n_theta} direction bins)", fontsize=10)
    for ax in axes[n_panels:]:
        ax.set_visible(False)
    fig.suptitle(
        title
        or "Light field: fluence (colour) and direction distribution L(θ) (cyan glyphs, "
        f"{glyph_scale} scale; θ from +x toward +y)",
        fontsize=10,
    )
    return _finish(fig, path)


def _points(points, fn: str, height: int, width: int) -> list[tuple[float, float]]:
    """Glyph centres (x, y): at most MAX_GLYPHS, each on the panel."""
    a = checked_array(points, (2,), f"{fn}.points", "of (x, y) pairs, shape (n, 2)")
    if a.shape[1] != 2 or len(a) > MAX_GLYPHS:
        raise ValueError(
            f"{fn}.points: must be at most {MAX_GLYPHS} (x, y) pairs, shape (n, 2), got "
            f"shape {a.shape}"
        )
    off = (a[:, 0] < 0) | (a[:, 0] > width) | (a[:, 1] < 0) | (a[:, 1] > height)
    if off.any():
        raise ValueError(
            f"{fn}.points: must lie on the {width}x{height} panel (0 <= x <= {width}, "
            f"0 <= y <= {height}), got {tuple(a[off][0])}"
        )
    return [(float(x), float(y)) for x, y in a]


# -------------------------------------------------------- Fig. 14: per-bounce images


def plot_bounce_images(
    images,
    path=None,
    *,
    total: bool = True,
    show: int | None = None,
    illumination: Illumination | None = None,
    log: bool = True,
    dynamic_range: float = 1e4,
    columns: int = 3,
    title: str | None = None,
):
    """Fig. 14: the per-bounce images I_1..I_K (and their sum) side by side.

    Each panel has its own colour scale (bounces differ by orders of magnitude), log
    over ``dynamic_range`` below its maximum by default.

    Args:
        images: (K, height, width), index k−1 holding I_k, or a
            :class:`~lightfield_jax.RenderResult`.
        path: PNG to write, or ``None`` to return the figure.
        total: add a panel with Σ_k I_k (over all K bounces given).
        show: show the panels of I_1..I_show only (default: all K).
        illumination: optionally the light, drawn as an arrow at its entry (a Beam).
        log: log colour scales over ``dynamic_range`` below each panel's maximum
            (values below, including float32 round-off of either sign, show as the
            lowest colour).
        columns: panels per row.
        title: figure title.
    """
    from matplotlib.colors import LogNorm, Normalize

    fn = "plot_bounce_images"
    check_common(fn, path, dynamic_range=dynamic_range, title=title)
    check_illumination(illumination, fn)
    check_flag(total, f"{fn}.total")
    check_flag(log, f"{fn}.log")
    check_int(columns, f"{fn}.columns", low=1, high=MAX_PANELS)
    if show is not None:
        check_int(show, f"{fn}.show", low=1)
    images = bounce_images(images, f"{fn}.images")
    shown = images if show is None else images[:show]
    check_panels(len(shown) + bool(total), fn, "bounce images")
    panels = [(f"$I_{{{k}}}$", im) for k, im in enumerate(shown, start=1)]
    if total:
        panels.append((rf"$\Sigma_{{k=1}}^{{{len(images)}}} I_k$", images.sum(axis=0)))
    _, height, width = images.shape
    ncols = min(columns, len(panels))
    nrows = math.ceil(len(panels) / ncols)
    fig = _figure(5.0 * ncols, 0.6 + 4.3 * nrows * height / width * 1.15)
    axes = np.atleast_1d(fig.subplots(nrows, ncols, squeeze=False)).ravel()
    for ax, (label, image) in zip(axes, panels, strict=False):
        top = float(np.max(image)) if np.max(image) > 0 else 1.0
        norm = LogNorm(top / dynamic_range, top) if log else Normalize(0.0, top)
        shown = np.maximum(image, top / dynamic_range) if log else image
        im = ax.imshow(
            shown, cmap="inferno", norm=norm, extent=(0, width, height, 0), interpolation="nearest"
        )
        fig.colorbar(im, ax=ax, shrink=0.85, label=f"intensity ({UNITS})")
        if isinstance(illumination, Beam):
            t0 = math.radians(illumination.direction_deg)
            length = 0.12 * max(width, height)
            ax.annotate(
                "",
                xy=(illumination.x + length * math.cos(t0), illumination.y + length * math.sin(t0)),
                xytext=(illumination.x, illumination.y),
                arrowprops={"arrowstyle": "->", "color": "cyan", "lw": 1.5},
            )
        ax.set_xlim(0, width)
        ax.set_ylim(height, 0)
        ax.set_xlabel("x (px)")
        ax.set_ylabel("y (px)")
        ax.set_title(f"{label} (max {top:.3g})", fontsize=10)
    for ax in axes[len(panels) :]:
        ax.set_visible(False)
    fig.suptitle(title or "Images of light that scattered k times", fontsize=11)
    return _finish(fig, path)
