"""Memory a command will need, estimated before it allocates, against what the machine has.

The estimates are upper bounds of the working set from the sizes alone (a config, the
headers of image files), with the copies the pipeline makes counted, so that a request
that cannot fit is refused in a second instead of growing until the machine swaps or
the process ends in a ``MemoryError``. They are not measurements: normal sizes
(a 128×96 capture of 6 shifts, 64 directions) stay far below any machine's memory.

The limit is the memory available now (``MemAvailable`` in ``/proc/meminfo``, else the
free physical pages), or what :func:`memory_limit` / ``$LIGHTFIELD_JAX_MAX_MEMORY``
(and the command line's ``--max-memory``) set, for users who know better.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
from collections.abc import Iterator

from lightfield_jax.checks import shown

MAX_MEMORY_ENV = "LIGHTFIELD_JAX_MAX_MEMORY"
_UNITS = {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}
_override: list[int] = []


class MemoryLimitError(ValueError):
    """A request whose estimated memory exceeds the limit; says both numbers."""


def parse_size(text: str) -> int:
    """``"8G"``, ``"512M"``, ``"2.5GiB"``, ``"1000000"`` (bytes) → bytes."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([KMGT]?)(?:I?B)?\s*", str(text).upper())
    size = 0.0 if m is None else float(m.group(1)) * _UNITS[m.group(2)]
    # past float64 (400 digits) the size is inf, which int() raises as an OverflowError
    nbytes = int(size) if math.isfinite(size) else 0
    if nbytes < 1:  # also a fraction of a byte
        raise ValueError(f"memory size: expected a size such as 8G or 512M, got {shown(text)}")
    return nbytes


def format_size(nbytes: float) -> str:
    """Bytes as a short human-readable size (binary units)."""
    for unit in ("B", "KiB", "MiB", "GiB"):
        if abs(nbytes) < 1024:
            return f"{nbytes:.0f} {unit}" if unit == "B" else f"{nbytes:.1f} {unit}"
        nbytes /= 1024
    return f"{nbytes:.1f} TiB"


def available_bytes() -> int:
    """The memory the machine can give now, in bytes (``MemAvailable``)."""
    with contextlib.suppress(OSError, ValueError):
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def current_limit() -> tuple[int, str]:
    """(bytes, where the number comes from)."""
    if _override:
        return _override[-1], "--max-memory"
    if os.environ.get(MAX_MEMORY_ENV):
        try:
            return parse_size(os.environ[MAX_MEMORY_ENV]), f"${MAX_MEMORY_ENV}"
        except ValueError as e:
            raise ValueError(f"${MAX_MEMORY_ENV}: {e}") from None
    return available_bytes(), "available memory"


@contextlib.contextmanager
def memory_limit(nbytes: int | None) -> Iterator[None]:
    """Within the block, requests up to ``nbytes`` pass (``None``: no change)."""
    if nbytes is None:
        yield
        return
    _override.append(int(nbytes))
    try:
        yield
    finally:
        _override.pop()


def check_memory(nbytes: float, what: str) -> None:
    """Refuse ``what`` (e.g. ``"images[0] (a.png, 30000x30000x3)"``) when its estimate
    ``nbytes`` exceeds the limit."""
    limit, origin = current_limit()
    if not math.isfinite(nbytes) or nbytes > limit:
        raise MemoryLimitError(
            f"{what} needs about {format_size(nbytes)} of memory, more than the "
            f"{format_size(limit)} of the {origin}; reduce the size, or raise the limit "
            f"with --max-memory SIZE (or ${MAX_MEMORY_ENV})"
        )


# Working copies of an image read (the library's buffer, the float array, a selection).
IMAGE_COPIES = 3
# Working copies of a capture's stack of images while loading (raw, calibrated, the
# detector's float64 copy, masks) in float64. Measured: loading six 1000x800 RGB float
# EXR stripe images peaks at 32 bytes per sample above the imports (4 such copies).
CAPTURE_COPIES = 6
# Light-field sized arrays alive at once in a render per pattern (L_k, the scattered
# and transported fields, the accumulators and XLA's temporaries). Measured: peak
# resident memory above the imports of `simulate` (6 stripes, n_theta 64, 8 bounces)
# is 15-16 such fields at 256x192 and 512x384.
RENDER_FIELDS = 20
# Derivative columns and their light fields in a fit (σt, σs, g, gain, black level).
# Measured: a joint fit of the 128x96 six-shift demo capture (cropped to 46x96, n_theta
# 32) peaks at 0.63 GB above the imports, compilation included; this estimate says
# 1.1 GB for it (computed on the uncropped frame).
FIT_FIELDS = 6 * RENDER_FIELDS


def image_bytes(height: int, width: int, channels: int, itemsize: int = 4) -> int:
    """An image read as floats, with its working copies."""
    return IMAGE_COPIES * height * width * channels * max(itemsize, 4)


def capture_bytes(samples: int) -> int:
    """A capture of ``samples`` values (images × H × W × C) loaded (see
    :data:`CAPTURE_COPIES`)."""
    return CAPTURE_COPIES * samples * 8


def render_bytes(
    n_patterns: int,
    height: int,
    width: int,
    n_theta: int,
    *,
    refine: int = 1,
    n_mu: int = 1,
    bounces: int = 1,
    lightfield: bool = False,
) -> int:
    """A render of ``n_patterns`` illuminations: the light fields (float32, at the
    refined grid, × n_mu elevations for a slab), the per-bounce images (float64,
    bounces × patterns × H × W, three copies) and, with ``lightfield``, the stored
    fields ((K+1) × P × H × W × n_theta float32, two copies), and the direction
    tables of n_theta² entries (the circulant index, built in int64: Grid(2, 2, 80000)
    allocated 47.7 GiB for it, unestimated)."""
    cells = height * width * n_theta * n_mu
    fields = RENDER_FIELDS * n_patterns * cells * refine**2 * 4
    images = 3 * bounces * n_patterns * height * width * 8
    stored = 2 * (bounces + 1) * n_patterns * cells * 4 if lightfield else 0
    tables = 24 * n_theta**2
    return fields + images + stored + tables


def fit_bytes(samples: int, n_images: int, cells: int) -> int:
    """A fit: the capture's ``samples`` loaded, and per image the model's ``cells``
    (W·H·n_theta·refine², capped by the fit's ``max_cells``) for the fields and the
    derivative columns."""
    return capture_bytes(samples) + FIT_FIELDS * n_images * cells * 4


def series_bytes(n_images: int, cells: int, bounces: int) -> int:
    """A bounce series of a fixed ``bounces`` (a fit's ``bounces: K``): the field of
    every bounce and its two tangents, which a linearised march keeps, per image of
    ``cells`` (measured: 1.6 MB per bounce for six 32×24 images at 32 θ bins)."""
    return 3 * n_images * cells * 4 * bounces


def correction_bytes(samples: int, n_images: int, cells: int) -> int:
    """A fit's primal renders (its defect correction and error term) of ``cells``
    (W·H·n_theta·refine², at most twice the fit's ``max_render_cells``) per image, with
    the capture loaded."""
    return capture_bytes(samples) + RENDER_FIELDS * n_images * cells * 4


# Direction bins assumed for a fit's memory estimate: the fewest the fit chooses
# (g <= 0.5); more are capped by the fit option max_cells.
FIT_N_THETA = 32
# Cells per pixel of the largest primal render a fit may make (a forward medium's
# error-term model: 128 θ bins at refinement 2); more are capped at twice
# the fit option max_render_cells.
RENDER_CELLS_PER_PIXEL = 128 * 2**2


def fit_memory(samples: int, n_images: int, height: int, width: int, model) -> int:
    """The memory a fit of ``n_images`` images of ``height`` × ``width`` (``samples``
    values loaded, every channel) needs under the fit's ``model`` settings (a
    :class:`~lightfield_jax.ModelOptions`): the larger of the solve (:func:`fit_bytes`
    and a fixed series' :func:`series_bytes`) and the primal renders
    (:func:`correction_bytes`)."""
    # θ bins or a refinement fixed by the options are never lowered to max_cells, so
    # they bound the model from below.
    h, w = height, width
    fixed = 0
    if model.n_theta is not None or model.refine is not None:
        fixed = h * w * (model.n_theta or FIT_N_THETA) * (model.refine or 1) ** 2
    cells = max(min(h * w * FIT_N_THETA, model.max_cells), fixed)
    rendered = max(min(h * w * RENDER_CELLS_PER_PIXEL, 2 * model.max_render_cells), fixed)
    # A fixed bounce count keeps every bounce's field, as does a march capped by a
    # max_bounces raised above its default (the default cap is within the estimates).
    fixed_series = model.bounces if isinstance(model.bounces, int) else 0
    if model.max_bounces > type(model)().max_bounces:
        fixed_series = max(fixed_series, model.max_bounces)
    return max(
        fit_bytes(samples, n_images, cells) + series_bytes(n_images, cells, fixed_series),
        correction_bytes(samples, n_images, rendered),
    )


__all__ = [
    "FIT_N_THETA",
    "MAX_MEMORY_ENV",
    "RENDER_CELLS_PER_PIXEL",
    "MemoryLimitError",
    "available_bytes",
    "capture_bytes",
    "check_memory",
    "correction_bytes",
    "fit_bytes",
    "fit_memory",
    "format_size",
    "image_bytes",
    "memory_limit",
    "parse_size",
    "render_bytes",
    "series_bytes",
]
