"""Shared plumbing of the figure functions (matplotlib imported lazily): the checks of
the arguments most figures share, bounce images and light fields taken from a render,
profiles along the light, and writing a figure."""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path

import numpy as np

from lightfield_jax.checks import check_int, check_number, real_array
from lightfield_jax.checks import shown as brief
from lightfield_jax.files import atomic_path
from lightfield_jax.forward.render import RenderResult
from lightfield_jax.inverse.decay import entry_coordinates
from lightfield_jax.scene.illumination import (
    Beam,
    Full,
    Illumination,
    Stripes,
    along_x,
)


def new_figure(width: float, height: float):
    """A matplotlib Figure without pyplot (no global state, no display)."""
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), layout="constrained")


def finish(fig, path):
    """Write ``fig`` to ``path`` atomically (returning the path), or return ``fig``."""
    if path is None:
        return fig
    path = Path(path)
    with atomic_path(path) as tmp, warnings.catch_warnings():
        # matplotlib's layout notes (a legend or a title that leaves an axis no room)
        # are about drawing, not the user's data; the figure is written regardless.
        warnings.filterwarnings("ignore", category=UserWarning, module=r"matplotlib(\.|$)")
        fig.savefig(tmp, dpi=110)
    return path


UNITS = "source units"


# ---------------------------------------------------------------------------- helpers


# The most panels a figure draws and glyphs a light-field panel draws: beyond them a
# figure takes minutes (plot_lightfield(spacing=1e-3) asked for 7.7e8 glyphs).
MAX_PANELS = 48
MAX_GLYPHS = 1024
# The finest profile bin along the light (pixels).
MIN_BIN_WIDTH = 0.01


def checked_array(
    a, ndim: tuple[int, ...], name: str, what: str, finite: str = "all"
) -> np.ndarray:
    return real_array(a, name, ndim, what, finite=finite)


def check_common(fn: str, path, *, bin_width=None, dynamic_range=None, title=None) -> None:
    """The arguments most figures share, checked before any work."""
    if path is not None and not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"{fn}.path: must be a file path or None, got {brief(path)}")
    if bin_width is not None:
        check_number(bin_width, f"{fn}.bin_width", low=MIN_BIN_WIDTH, unit=" px")
    if dynamic_range is not None:
        check_number(dynamic_range, f"{fn}.dynamic_range", low=1.0, low_open=True)
    if title is not None and not isinstance(title, str):
        raise ValueError(f"{fn}.title: must be a string or None, got {brief(title)}")


def check_illumination(illumination, fn: str) -> None:
    if illumination is not None and not isinstance(illumination, (Beam, Stripes, Full)):
        raise ValueError(
            f"{fn}.illumination: must be a Beam, Stripes, Full or None, got "
            f"{type(illumination).__name__}"
        )


def check_panels(n: int, fn: str, what: str) -> None:
    if n > MAX_PANELS:
        raise ValueError(
            f"{fn}: {n} panels ({what}) are more than the {MAX_PANELS} a figure draws; "
            "select some (e.g. show=6, or a slice of the array)"
        )


def bounce_images(images, name: str) -> np.ndarray:
    """(K, H, W) per-bounce images from an array or a RenderResult (stripes summed)."""
    if not isinstance(images, RenderResult):
        return checked_array(images, (3,), name, "(K, height, width) or a RenderResult")
    a = checked_array(images.images, (3, 4), f"{name}.images", "of a RenderResult")
    return a.sum(axis=0) if a.ndim == 4 else a


def render_fields(result: RenderResult, show: int) -> tuple[np.ndarray, list[str]]:
    """L_0..L_show and their sum over every bounce, with labels (stripes summed)."""
    if result.lightfields is None:
        raise ValueError(
            "plot_lightfield: the RenderResult holds no light fields; render with lightfield=True"
        )
    fields = checked_array(
        result.lightfields, (4, 5), "plot_lightfield.lightfields", "of a RenderResult"
    )
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
    check_illumination(illumination, "light_path_coordinates")
    entry, direction = illumination.entry, illumination.direction_deg
    s, u = entry_coordinates(height, width, entry, direction)
    across = along_x(entry)
    n_lines = height if across else width
    t0 = math.radians(direction)
    half = 0.5 * (1.0 + abs(math.tan(t0) if across else 1.0 / math.tan(t0)))
    return s, (u - half >= -1e-9) & (u + half <= n_lines + 1e-9)


def binned_profile(image: np.ndarray, s: np.ndarray, mask: np.ndarray, bin_width: float):
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


def visible_range(y: np.ndarray, dynamic_range: float) -> np.ndarray:
    """Where a profile is finite, positive and within ``dynamic_range`` of its peak.

    Below that, float32 renders show round-off (the first scatter's FFT convolution
    leaves values of about 1e-7 of the peak, of either sign), not light."""
    ok = np.isfinite(y) & (y > 0)
    if ok.any():
        ok &= y >= np.max(y[ok]) / dynamic_range
    return ok


def checked_mask(mask, default: np.ndarray) -> np.ndarray:
    if mask is None:
        return default
    mask = np.asarray(mask)
    if mask.dtype != bool:
        raise ValueError(f"mask: must be a boolean array, got dtype {mask.dtype}")
    if mask.shape != default.shape:
        raise ValueError(f"mask: must have the image's shape {default.shape}, got {mask.shape}")
    return mask & default
