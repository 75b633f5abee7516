"""The paper's figures (Mukaigawa, Raskar & Yagi 2010, Figs. 11-14) for any result.

Every function takes arrays (numpy or JAX) in the image frame of docs/model.md section 1
(x = column to the right, y = row downward, θ from +x toward +y, lengths in pixels,
images in source units: unit irradiance times the gain). With ``path`` it writes a PNG
atomically and returns the path; without, it returns the matplotlib ``Figure`` (built
without pyplot, so it changes no backend and needs no closing).

- :func:`plot_direct_decay` (Fig. 11): the direct component's decay along the light,
  log intensity against distance, with and without separation, and the σt fit.
- :func:`plot_bounce_profiles` (Fig. 12): the profile of each bounce image I_k along
  the light; single scatter decays from the wall, higher bounces peak inside.
- :func:`plot_lightfield` (Fig. 13): a light field L(x, y, θ) as a pseudo-colour
  fluence image with polar glyphs of the direction distribution at sample points.
- :func:`plot_bounce_images` (Fig. 14): the per-bounce images side by side (e.g. of an
  oblique beam).

:func:`plot_bounce_profiles`, :func:`plot_lightfield` and :func:`plot_bounce_images`
also take a :class:`~lightfield_jax.RenderResult` itself (its ``images``, or its
``lightfields`` L_0..L_K); of a stripe render, the sum over the shifted patterns (each
row lit ``lit`` times: ``lit`` × full illumination).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import numpy as np

from lightfield_jax.checks import check_flag, check_int, check_number, real_array
from lightfield_jax.checks import shown as brief
from lightfield_jax.forward.render import RenderResult
from lightfield_jax.inverse.decay import DecayFit, entry_coordinates
from lightfield_jax.scene.illumination import (
    _INWARD_DEG,
    Beam,
    Full,
    Illumination,
    Stripes,
    _check_direction,
    _direction,
    along_x,
)

from ._common import finish as _finish
from ._common import new_figure as _figure

_UNITS = "source units"


# ---------------------------------------------------------------------------- helpers


# The most panels a figure draws and glyphs a light-field panel draws: beyond them a
# figure takes minutes (plot_lightfield(spacing=1e-3) asked for 7.7e8 glyphs).
MAX_PANELS = 48
MAX_GLYPHS = 1024
# The finest profile bin along the light (pixels).
MIN_BIN_WIDTH = 0.01


def _array(a, ndim: tuple[int, ...], name: str, what: str, finite: str = "all") -> np.ndarray:
    return real_array(a, name, ndim, what, finite=finite)


def _check_common(fn: str, path, *, bin_width=None, dynamic_range=None, title=None) -> None:
    """The arguments most figures share, checked before any work."""
    if path is not None and not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"{fn}.path: must be a file path or None, got {brief(path)}")
    if bin_width is not None:
        check_number(bin_width, f"{fn}.bin_width", low=MIN_BIN_WIDTH, unit=" px")
    if dynamic_range is not None:
        check_number(dynamic_range, f"{fn}.dynamic_range", low=1.0, low_open=True)
    if title is not None and not isinstance(title, str):
        raise ValueError(f"{fn}.title: must be a string or None, got {brief(title)}")


def _illumination(illumination, fn: str) -> None:
    if illumination is not None and not isinstance(illumination, (Beam, Stripes, Full)):
        raise ValueError(
            f"{fn}.illumination: must be a Beam, Stripes, Full or None, got "
            f"{type(illumination).__name__}"
        )


def _panels(n: int, fn: str, what: str) -> None:
    if n > MAX_PANELS:
        raise ValueError(
            f"{fn}: {n} panels ({what}) are more than the {MAX_PANELS} a figure draws; "
            "select some (e.g. show=6, or a slice of the array)"
        )


def _bounce_images(images, name: str) -> np.ndarray:
    """(K, H, W) per-bounce images from an array or a RenderResult (stripes summed)."""
    if not isinstance(images, RenderResult):
        return _array(images, (3,), name, "(K, height, width) or a RenderResult")
    a = _array(images.images, (3, 4), f"{name}.images", "of a RenderResult")
    return a.sum(axis=0) if a.ndim == 4 else a


def _render_fields(result: RenderResult, show: int) -> tuple[np.ndarray, list[str]]:
    """L_0..L_show and their sum over every bounce, with labels (stripes summed)."""
    if result.lightfields is None:
        raise ValueError(
            "plot_lightfield: the RenderResult holds no light fields; render with lightfield=True"
        )
    fields = _array(result.lightfields, (4, 5), "plot_lightfield.lightfields", "of a RenderResult")
    if fields.ndim == 5:
        fields = fields.sum(axis=0)
    n = min(check_int(show, "plot_lightfield.show", low=0), fields.shape[0] - 1)
    labels = [f"$L_{{{k}}}$" for k in range(n + 1)]
    labels.append(rf"$\Sigma_{{k=0}}^{{{fields.shape[0] - 1}}} L_k$")
    return np.concatenate([fields[: n + 1], fields.sum(axis=0)[None]]), labels


def light_path_coordinates(
    shape: tuple[int, int], illumination: Illumination | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Distance along the light from where it enters, and the pixels that show it.

    Args:
        shape: image shape (height, width).
        illumination: a :class:`~lightfield_jax.Beam` (distance along the beam from its
            entry point; the pixels whose centre lies within half the beam's width, at
            least half a pixel, of its axis), or :class:`~lightfield_jax.Stripes` /
            :class:`~lightfield_jax.Full` (distance from the entry wall along the
            light; the pixels wholly lit through the wall). ``None``: ``Full()`` (left
            wall, 0°).

    Returns:
        ``(s, mask)``: s (pixels, float64, (height, width)) for every pixel centre and
        the boolean mask of pixels on the light's path.
    """
    if not isinstance(shape, (tuple, list)) or len(shape) != 2:
        raise ValueError(
            f"light_path_coordinates.shape: must be (height, width), got {brief(shape)}"
        )
    height, width = (check_int(v, "light_path_coordinates.shape", low=1) for v in shape)
    illumination = Full() if illumination is None else illumination
    if isinstance(illumination, Beam):
        t0 = math.radians(illumination.direction_deg)
        c, s0 = math.cos(t0), math.sin(t0)
        y, x = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
        dx, dy = x - illumination.x, y - illumination.y
        along = dx * c + dy * s0
        across = -dx * s0 + dy * c
        mask = (np.abs(across) <= max(0.5 * illumination.width, 0.5)) & (along >= 0)
        return along, mask
    _illumination(illumination, "light_path_coordinates")
    entry, direction = illumination.entry, illumination.direction_deg
    s, u = entry_coordinates(height, width, entry, direction)
    across = along_x(entry)
    n_lines = height if across else width
    t0 = math.radians(direction)
    half = 0.5 * (1.0 + abs(math.tan(t0) if across else 1.0 / math.tan(t0)))
    return s, (u - half >= -1e-9) & (u + half <= n_lines + 1e-9)


def _profile(image: np.ndarray, s: np.ndarray, mask: np.ndarray, bin_width: float):
    """(bin centres, mean of image over the masked pixels in each bin of s)."""
    sv, iv = s[mask], image[mask]
    if sv.size == 0:  # no pixel on the path (light nearly along the wall): nothing to draw
        return np.zeros(0), np.zeros(0)
    edges = np.arange(np.floor(sv.min()), sv.max() + bin_width, bin_width)
    idx = np.clip(np.digitize(sv, edges) - 1, 0, len(edges) - 2)
    total = np.bincount(idx, iv, minlength=len(edges) - 1)
    count = np.bincount(idx, minlength=len(edges) - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / count, np.nan)
    return 0.5 * (edges[1:] + edges[:-1]), mean


def _visible(y: np.ndarray, dynamic_range: float) -> np.ndarray:
    """Where a profile is finite, positive and within ``dynamic_range`` of its peak.

    Below that, float32 renders show round-off (the first scatter's FFT convolution
    leaves values of about 1e-7 of the peak, of either sign), not light."""
    ok = np.isfinite(y) & (y > 0)
    if ok.any():
        ok &= y >= np.max(y[ok]) / dynamic_range
    return ok


def _mask(mask, default: np.ndarray) -> np.ndarray:
    if mask is None:
        return default
    mask = np.asarray(mask)
    if mask.dtype != bool:
        raise ValueError(f"mask: must be a boolean array, got dtype {mask.dtype}")
    if mask.shape != default.shape:
        raise ValueError(f"mask: must have the image's shape {default.shape}, got {mask.shape}")
    return mask & default


# --------------------------------------------------------------------- Fig. 11: decay


def _decay_model(fit: DecayFit, shape, entry: str, direction_deg: float) -> np.ndarray:
    """The fitted direct image c_ℓ·exp(−σt s) (NaN on lines the fit did not use)."""
    height, width = shape
    s, u = entry_coordinates(height, width, entry, direction_deg)
    n_lines = height if along_x(entry) else width
    line = np.clip(np.floor(u), 0, n_lines - 1).astype(int)
    amplitude = np.asarray(fit.amplitude, dtype=np.float64)
    return amplitude[line] * np.exp(-float(fit.sigma_t) * s)


def plot_direct_decay(
    direct,
    fit: DecayFit,
    path=None,
    *,
    unseparated=None,
    unseparated_fit: DecayFit | None = None,
    unseparated_label: str = "without separation",
    entry: str = "left",
    direction_deg: float | None = None,
    mask=None,
    true_sigma_t: float | None = None,
    bin_width: float = 1.0,
    dynamic_range: float = 1e6,
    title: str | None = None,
):
    """Fig. 11: log intensity of the direct component against the distance travelled,
    with the fitted exponential c·exp(−σt s) (a line on this plot).

    Args:
        direct: the separated direct image D, (height, width).
        fit: :func:`lightfield_jax.fit_decay` of ``direct``.
        path: PNG to write, or ``None`` to return the figure.
        unseparated: optionally the image without separation (e.g. Imax, the image
            under the pixel's own lit stripe, or a full-illumination image); it keeps
            the multiple scatter, so its decay is not one exponential.
        unseparated_fit: optionally ``fit_decay`` of ``unseparated`` (its σt is biased).
        unseparated_label: its legend entry.
        entry, direction_deg: the light's entry wall and heading (as for ``fit_decay``).
        mask: optionally restrict the pixels averaged into the profile.
        true_sigma_t: optionally the true σt (per pixel), shown for comparison.
        bin_width: profile bin width along the light (pixels).
        dynamic_range: profile points below the peak / dynamic_range are not drawn.
        title: figure title (default: the fitted values).
    """
    fn = "plot_direct_decay"
    _check_common(fn, path, bin_width=bin_width, dynamic_range=dynamic_range, title=title)
    direct = _array(direct, (2,), f"{fn}.direct", "(height, width)", finite="some")
    for key, value in (("fit", fit), ("unseparated_fit", unseparated_fit)):
        if not isinstance(value, DecayFit) and (key == "fit" or value is not None):
            raise ValueError(
                f"{fn}.{key}: must be a DecayFit (lightfield_jax.fit_decay), got "
                f"{type(value).__name__}"
            )
    if true_sigma_t is not None:
        check_number(true_sigma_t, f"{fn}.true_sigma_t", low=0.0, low_open=True, unit=" per px")
    if not isinstance(entry, str) or entry not in _INWARD_DEG:
        raise ValueError(f"{fn}.entry: must be one of {', '.join(_INWARD_DEG)}, got {brief(entry)}")
    if direction_deg is None:
        direction_deg = _INWARD_DEG[entry]
    direction_deg = _direction(direction_deg, f"{fn}.direction_deg")
    _check_direction(entry, direction_deg, fn)
    light = Full(direction_deg=direction_deg, entry=entry)
    s, on_path = light_path_coordinates(direct.shape, light)
    sel = _mask(mask, on_path)
    fig = _figure(7.5, 5.0)
    ax = fig.add_subplot()
    series = [("direct D (separated)", direct, fit, "C0", "o")]
    if unseparated is not None:
        unseparated = _array(unseparated, (2,), f"{fn}.unseparated", "(height, width)", "some")
        if unseparated.shape != direct.shape:
            raise ValueError(
                f"{fn}.unseparated: must have the direct image's shape {direct.shape}, got "
                f"{unseparated.shape}"
            )
        series.append((unseparated_label, unseparated, unseparated_fit, "C3", "s"))
    for label, image, f, colour, marker in series:
        x, y = _profile(image, s, sel, bin_width)
        ok = _visible(y, dynamic_range)
        ax.semilogy(x[ok], y[ok], marker, color=colour, ms=3.5, mfc="none", label=label)
        if f is not None:
            model = _decay_model(f, image.shape, entry, direction_deg)
            mx, my = _profile(model, s, sel & np.isfinite(model), bin_width)
            ok = _visible(my, dynamic_range) & (mx <= x[ok].max() + bin_width)
            err = float(f.sigma_t_stderr)
            ax.semilogy(
                mx[ok],
                my[ok],
                "-",
                color=colour,
                lw=1.4,
                label=f"fit: σt = {float(f.sigma_t):.4f} ± {err:.1g} px⁻¹",
            )
    ax.set_xlabel("distance from the entry wall along the light s (px)")
    ax.set_ylabel(f"mean intensity over the lit rows ({_UNITS}, log scale)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    truth = "" if true_sigma_t is None else f" (true σt = {true_sigma_t:.4f} px⁻¹)"
    ax.set_title(
        title or f"Decay of the direct component: σt = {float(fit.sigma_t):.4f} px⁻¹{truth}",
        fontsize=10,
    )
    return _finish(fig, path)


# ----------------------------------------------------------- Fig. 12: bounce profiles


def plot_bounce_profiles(
    images,
    path=None,
    *,
    illumination: Illumination | None = None,
    mask=None,
    bin_width: float = 1.0,
    total: bool = True,
    dynamic_range: float = 1e6,
    title: str | None = None,
):
    """Fig. 12: the profile of each bounce image I_k along the light.

    Left: the profiles on a log scale (with their sum). Right: each normalised to its
    peak, peaks marked: single scatter decays from the wall, light that scattered more
    often peaks deeper inside the medium.

    Args:
        images: per-bounce images, (K, height, width), index k−1 holding I_k, or a
            :class:`~lightfield_jax.RenderResult`.
        path: PNG to write, or ``None`` to return the figure.
        illumination: the light the images were rendered with; sets the path
            coordinate and the pixels averaged (see :func:`light_path_coordinates`).
            Default: full illumination through the left wall.
        mask: optionally restrict those pixels further.
        bin_width: profile bin width along the light (pixels).
        total: also plot Σ_k I_k.
        dynamic_range: each profile is drawn down to its peak / dynamic_range.
        title: figure title.
    """
    fn = "plot_bounce_profiles"
    _check_common(fn, path, bin_width=bin_width, dynamic_range=dynamic_range, title=title)
    _illumination(illumination, fn)
    check_flag(total, f"{fn}.total")
    images = _bounce_images(images, f"{fn}.images")
    s, on_path = light_path_coordinates(images.shape[1:], illumination)
    sel = _mask(mask, on_path)
    fig = _figure(12.0, 4.6)
    ax_abs, ax_norm = fig.subplots(1, 2)
    # The y range is the brightest profile's: a high order's profile sits many decades
    # below (ρ^k), and drawing each down to its own peak / dynamic_range collapsed the
    # axis to a sliver at K 238. Orders wholly below it are not drawn nor listed.
    peaks = [float(np.nanmax(_profile(im, s, sel, bin_width)[1], initial=0.0)) for im in images]
    top = max(peaks, default=0.0)
    seen = [k for k, p in enumerate(peaks, start=1) if top > 0 and p >= top / dynamic_range]
    last = seen[-1] if seen else len(images)
    drawn = shown_bounces(last)
    colours = _bounce_colours(drawn)
    for k in drawn:
        x, y = _profile(images[k - 1], s, sel, bin_width)
        ok = _visible(y, dynamic_range) & (y >= top / dynamic_range)
        colour = colours[k]
        ax_abs.semilogy(x[ok], y[ok], "-", color=colour, label=f"$I_{{{k}}}$")
        if ok.any():
            peak = x[ok][np.argmax(y[ok])]
            ax_norm.plot(
                x[ok],
                y[ok] / y[ok].max(),
                "-",
                color=colour,
                label=f"$I_{{{k}}}$: peak {peak:.0f} px",
            )
            ax_norm.axvline(peak, color=colour, ls=":", lw=0.8)
    if total:
        x, y = _profile(images.sum(axis=0), s, sel, bin_width)
        top = max(top, float(np.nanmax(y, initial=0.0)))
        ok = _visible(y, dynamic_range) & (y >= top / dynamic_range)
        label = r"$\Sigma_k I_k$" + (f" (all {len(images)})" if len(drawn) < len(images) else "")
        ax_abs.semilogy(x[ok], y[ok], "k--", lw=1.2, label=label)
    if top > 0:
        ax_abs.set_ylim(top / dynamic_range, top * 2)
    where = _where(illumination)
    ax_abs.set_xlabel("distance along the light s (px)")
    ax_abs.set_ylabel(f"mean intensity ({_UNITS}, log scale)")
    some = "" if len(drawn) == len(images) else f"; {len(drawn)} of {len(images)} bounces shown"
    if last < len(images):
        some += f",\nthose after {last} below {1 / dynamic_range:g} of the brightest"
    ax_abs.set_title(
        f"bounce profiles (mean over the pixels on the light's path{some})", fontsize=10
    )
    ax_abs.grid(True, which="both", alpha=0.3)
    ax_norm.set_xlabel("distance along the light s (px)")
    ax_norm.set_ylabel("intensity / its peak")
    ax_norm.set_title("each normalised to its peak (dotted: peak position)", fontsize=10)
    ax_norm.grid(True, alpha=0.3)
    if sel.any():
        ax_abs.legend(fontsize=8, ncol=2, title="bounce k", title_fontsize=8)
        ax_norm.legend(fontsize=8, ncol=2 if len(drawn) > 6 else 1)
    else:  # light nearly along the wall: no pixel is wholly lit through it
        ax_abs.text(
            0.5, 0.5, "no pixel on the light's path", transform=ax_abs.transAxes, ha="center"
        )
    fig.suptitle(title or f"Decay of each bounce along the light {where}", fontsize=11)
    return _finish(fig, path)


# Bounce profiles drawn at most: each has a legend entry and a colour that must stay
# readable (every bounce of a K 238 render overflowed the legend and collapsed the axes).
MAX_SHOWN_BOUNCES = 10


def shown_bounces(k: int, most: int = MAX_SHOWN_BOUNCES) -> list[int]:
    """The bounce orders 1..k to draw: all of them up to ``most``, else the first four
    and the rest spaced evenly in log k up to k (the profiles change slowly there)."""
    if k <= most:
        return list(range(1, k + 1))
    first = [1, 2, 3, 4]
    rest = np.geomspace(5, k, most - len(first))
    out = sorted(set(first) | {int(round(v)) for v in rest} | {k})
    while len(out) > most:  # rounding may add one: drop from the middle of the rest
        out.pop(len(first) + (len(out) - len(first)) // 2)
    return out


def _bounce_colours(drawn: list[int]) -> dict[int, object]:
    """One colour per drawn order: the tab10 cycle for a few, viridis in log k for more."""
    if len(drawn) <= 10 and drawn[-1] <= 10:
        return {k: f"C{(k - 1) % 10}" for k in drawn}
    from matplotlib import colormaps

    cmap = colormaps["viridis"]
    span = max(math.log(drawn[-1]), 1e-9)
    return {k: cmap(0.9 * math.log(k) / span) for k in drawn}


def _where(illumination) -> str:
    if isinstance(illumination, Beam):
        return (
            f"on the beam (entry ({illumination.x:g}, {illumination.y:g}), "
            f"{illumination.direction_deg:g}°)"
        )
    light = Full() if illumination is None else illumination
    return f"over the rows lit through the {light.entry} wall ({light.direction_deg:g}°)"


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
    _check_common(fn, path, dynamic_range=dynamic_range, title=title)
    check_flag(log, f"{fn}.log")
    if not isinstance(glyph_scale, str) or glyph_scale not in ("local", "global"):
        raise ValueError(f"{fn}.glyph_scale: must be 'local' or 'global', got {brief(glyph_scale)}")
    check_int(columns, f"{fn}.columns", low=1, high=MAX_PANELS)
    if isinstance(lightfield, RenderResult):
        lightfield, rendered = _render_fields(lightfield, show)
        labels = rendered if labels is None else labels
    what = "(height, width, n_theta) or (panels, height, width, n_theta), or a RenderResult"
    fields = _array(lightfield, (3, 4), f"{fn}.lightfield", what)
    single = fields.ndim == 3
    if single:
        fields = fields[None]
    n_panels, height, width, n_theta = fields.shape
    _panels(n_panels, fn, "light fields")
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
        fig.colorbar(im, ax=ax, shrink=0.85, label=f"fluence Σθ L Δθ ({_UNITS})")
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
    a = _array(points, (2,), f"{fn}.points", "of (x, y) pairs, shape (n, 2)")
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
    _check_common(fn, path, dynamic_range=dynamic_range, title=title)
    _illumination(illumination, fn)
    check_flag(total, f"{fn}.total")
    check_flag(log, f"{fn}.log")
    check_int(columns, f"{fn}.columns", low=1, high=MAX_PANELS)
    if show is not None:
        check_int(show, f"{fn}.show", low=1)
    images = _bounce_images(images, f"{fn}.images")
    shown = images if show is None else images[:show]
    _panels(len(shown) + bool(total), fn, "bounce images")
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
        fig.colorbar(im, ax=ax, shrink=0.85, label=f"intensity ({_UNITS})")
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
