"""The paper's profile figures (Mukaigawa, Raskar & Yagi 2010, Figs. 11-12) for any result.

Every function takes arrays (numpy or JAX) in the image frame of docs/model.md section 1
(x = column to the right, y = row downward, θ from +x toward +y, lengths in pixels,
images in source units: unit irradiance times the gain). With ``path`` it writes a PNG
atomically and returns the path; without, it returns the matplotlib ``Figure`` (built
without pyplot, so it changes no backend and needs no closing).

- :func:`plot_direct_decay` (Fig. 11): the direct component's decay along the light,
  log intensity against distance, with and without separation, and the σt fit.
- :func:`plot_bounce_profiles` (Fig. 12): the profile of each bounce image I_k along
  the light; single scatter decays from the wall, higher bounces peak inside. It also
  takes a :class:`~lightfield_jax.RenderResult` itself (its ``images``; of a stripe
  render, the sum over the shifted patterns).

Figs. 13 and 14 are :mod:`lightfield_jax.viz._fields`.
"""

from __future__ import annotations

import math

import numpy as np

from lightfield_jax.checks import check_flag, check_number
from lightfield_jax.checks import shown as brief
from lightfield_jax.inverse.decay import DecayFit, entry_coordinates
from lightfield_jax.scene.illumination import (
    INWARD_DEG,
    Beam,
    Full,
    Illumination,
    along_x,
    check_direction,
    checked_direction,
)

from ._common import (
    UNITS,
    binned_profile,
    bounce_images,
    check_common,
    check_illumination,
    checked_array,
    checked_mask,
    light_path_coordinates,
    visible_range,
)
from ._common import finish as _finish
from ._common import new_figure as _figure

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
    check_common(fn, path, bin_width=bin_width, dynamic_range=dynamic_range, title=title)
    direct = checked_array(direct, (2,), f"{fn}.direct", "(height, width)", finite="some")
    for key, value in (("fit", fit), ("unseparated_fit", unseparated_fit)):
        if not isinstance(value, DecayFit) and (key == "fit" or value is not None):
            raise ValueError(
                f"{fn}.{key}: must be a DecayFit (lightfield_jax.fit_decay), got "
                f"{type(value).__name__}"
            )
    if true_sigma_t is not None:
        check_number(true_sigma_t, f"{fn}.true_sigma_t", low=0.0, low_open=True, unit=" per px")
    if not isinstance(entry, str) or entry not in INWARD_DEG:
        raise ValueError(f"{fn}.entry: must be one of {', '.join(INWARD_DEG)}, got {brief(entry)}")
    if direction_deg is None:
        direction_deg = INWARD_DEG[entry]
    direction_deg = checked_direction(direction_deg, f"{fn}.direction_deg")
    check_direction(entry, direction_deg, fn)
    light = Full(direction_deg=direction_deg, entry=entry)
    s, on_path = light_path_coordinates(direct.shape, light)
    sel = checked_mask(mask, on_path)
    fig = _figure(7.5, 5.0)
    ax = fig.add_subplot()
    series = [("direct D (separated)", direct, fit, "C0", "o")]
    if unseparated is not None:
        unseparated = checked_array(
            unseparated, (2,), f"{fn}.unseparated", "(height, width)", "some"
        )
        if unseparated.shape != direct.shape:
            raise ValueError(
                f"{fn}.unseparated: must have the direct image's shape {direct.shape}, got "
                f"{unseparated.shape}"
            )
        series.append((unseparated_label, unseparated, unseparated_fit, "C3", "s"))
    for label, image, f, colour, marker in series:
        x, y = binned_profile(image, s, sel, bin_width)
        ok = visible_range(y, dynamic_range)
        ax.semilogy(x[ok], y[ok], marker, color=colour, ms=3.5, mfc="none", label=label)
        if f is not None:
            model = _decay_model(f, image.shape, entry, direction_deg)
            mx, my = binned_profile(model, s, sel & np.isfinite(model), bin_width)
            ok = visible_range(my, dynamic_range) & (mx <= x[ok].max() + bin_width)
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
    ax.set_ylabel(f"mean intensity over the lit rows ({UNITS}, log scale)")
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
    check_common(fn, path, bin_width=bin_width, dynamic_range=dynamic_range, title=title)
    check_illumination(illumination, fn)
    check_flag(total, f"{fn}.total")
    images = bounce_images(images, f"{fn}.images")
    s, on_path = light_path_coordinates(images.shape[1:], illumination)
    sel = checked_mask(mask, on_path)
    fig = _figure(12.0, 4.6)
    ax_abs, ax_norm = fig.subplots(1, 2)
    # The y range is the brightest profile's: a high order's profile sits many decades
    # below (ρ^k), and drawing each down to its own peak / dynamic_range collapsed the
    # axis to a sliver at K 238. Orders wholly below it are not drawn nor listed.
    peaks = [
        float(np.nanmax(binned_profile(im, s, sel, bin_width)[1], initial=0.0)) for im in images
    ]
    top = max(peaks, default=0.0)
    seen = [k for k, p in enumerate(peaks, start=1) if top > 0 and p >= top / dynamic_range]
    last = seen[-1] if seen else len(images)
    drawn = shown_bounces(last)
    colours = _bounce_colours(drawn)
    for k in drawn:
        x, y = binned_profile(images[k - 1], s, sel, bin_width)
        ok = visible_range(y, dynamic_range) & (y >= top / dynamic_range)
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
        x, y = binned_profile(images.sum(axis=0), s, sel, bin_width)
        top = max(top, float(np.nanmax(y, initial=0.0)))
        ok = visible_range(y, dynamic_range) & (y >= top / dynamic_range)
        label = r"$\Sigma_k I_k$" + (f" (all {len(images)})" if len(drawn) < len(images) else "")
        ax_abs.semilogy(x[ok], y[ok], "k--", lw=1.2, label=label)
    if top > 0:
        ax_abs.set_ylim(top / dynamic_range, top * 2)
    where = _where(illumination)
    ax_abs.set_xlabel("distance along the light s (px)")
    ax_abs.set_ylabel(f"mean intensity ({UNITS}, log scale)")
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
