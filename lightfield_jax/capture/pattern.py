"""The projector's side of a real capture: stripe images to project, and the capture
file that will describe the camera's images of them.

:func:`stripe_patterns` makes the paper's shifted stripes (docs/model.md section 3) as
8-bit projector frames: in the image of phase φ, projector row r (column, for
``orientation="columns"``) is white iff (r + φ) mod period < lit. Phases are spread
evenly over the period (0..period−1 for as many shifts as the period has rows), and
every row must be lit in at least one shift and dark in at least one, or the direct
and multiple light cannot be separated (docs/model.md section 5).

:func:`write_patterns` writes them with the all-white and all-black frames and a
``capture.yaml`` template: one camera file name per projected image (to be replaced by
the camera's files), ``auto`` for what is measured from the images (the medium's ROI,
the entry wall, the light's direction, where the stripes fall on the camera's rows,
the projector's black level; see :mod:`lightfield_jax.capture.capture`), and a comment on
every key.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from lightfield_jax.capture.image_write import write_png
from lightfield_jax.files import atomic_write_text
from lightfield_jax.runtime.memory import check_memory
from lightfield_jax.scene.illumination import unseparated_rows

ORIENTATIONS: tuple[str, ...] = ("rows", "columns")


def pattern_phases(period: int = 6, lit: int = 3, shifts: int | None = None) -> tuple[int, ...]:
    """Phases of ``shifts`` stripe images spread evenly over the period (default: one
    per row of the period), checked so that every row is lit and dark in some shift."""
    for name, value, low in (("period", period, 2), ("lit", lit, 1)):
        if not isinstance(value, int) or isinstance(value, bool) or value < low:
            raise ValueError(f"pattern.{name}: must be an integer >= {low}, got {value!r}")
    if lit >= period:
        raise ValueError(f"pattern.lit: must be smaller than the period {period}, got {lit}")
    n = period if shifts is None else shifts
    if not isinstance(n, int) or isinstance(n, bool) or not 2 <= n <= period:
        raise ValueError(
            f"pattern.shifts: must be an integer in [2, period] = [2, {period}], got {shifts!r}"
        )
    phases = tuple(int(round(k * period / n)) % period for k in range(n))
    if (rows := unseparated_rows(period, lit, phases)) is not None:
        raise ValueError(
            f"pattern.shifts: {n} shifts of a period-{period} pattern with {lit} lit rows "
            f"leave {rows} (phases {list(phases)}): direct and multiple light cannot "
            f"be separated there; use more shifts (up to {period})"
        )
    return phases


def check_size(width: int, height: int, period: int) -> None:
    """The projector's frame holds at least one period of stripes."""
    for name, value in (("width", width), ("height", height)):
        if not isinstance(value, int) or isinstance(value, bool) or value < period:
            raise ValueError(
                f"pattern.{name}: must be an integer >= the period {period}, got {value!r}"
            )


def stripe_patterns(
    width: int,
    height: int,
    period: int = 6,
    lit: int = 3,
    shifts: int | None = None,
    orientation: str = "rows",
) -> tuple[tuple[int, ...], list[np.ndarray]]:
    """The projector frames: (phases, one uint8 (height, width) image per phase)."""
    check_size(width, height, period)
    if orientation not in ORIENTATIONS:
        raise ValueError(
            f"pattern.orientation: must be one of {', '.join(ORIENTATIONS)}, got {orientation!r}"
        )
    phases = pattern_phases(period, lit, shifts)
    # Checked first: stripe_patterns(10**6, 10**6) would ask numpy for 931 GiB (a
    # MemoryError).
    check_memory(
        pattern_memory(width, height, len(phases)),
        f"stripe_patterns: {len(phases) + 2} images of {width}x{height}",
    )
    across = height if orientation == "rows" else width
    images = []
    for phase in phases:
        line = np.where((np.arange(across) + phase) % period < lit, 255, 0).astype(np.uint8)
        if orientation == "rows":
            images.append(np.repeat(line[:, None], width, axis=1))
        else:
            images.append(np.repeat(line[None, :], height, axis=0))
    return phases, images


# How far a stripe's size on the camera may be from a whole number of camera pixels.
SCALE_TOLERANCE = 0.05


def camera_stripes(period: int, lit: int, scale: float) -> tuple[int, int]:
    """The stripes' period and lit width in camera pixels, the model's unit, for
    ``scale`` camera pixels per projector pixel (measured across the stripes, on the
    medium: e.g. the stripes' period in a camera image divided by the projector's).
    Refused where either is not a whole number of camera pixels, or where fewer than 2
    camera pixels make a period (the model lights whole camera rows)."""
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise ValueError(f"--camera-px-per-projector-px: must be a number > 0, got {scale!r}")
    out = []
    for name, value in (("period", period), ("lit", lit)):
        camera = value * scale
        if abs(camera - round(camera)) > SCALE_TOLERANCE or round(camera) < 1:
            raise ValueError(
                f"--camera-px-per-projector-px: {scale:g} puts a {name} of {value} projector "
                f"px on {camera:.3g} camera px, not a whole number: choose a --{name} "
                f"whose image is a whole number of camera pixels"
            )
        out.append(int(round(camera)))
    if out[0] < 2:
        raise ValueError(
            f"--camera-px-per-projector-px: {scale:g} puts the period of {period} projector "
            f"px on {out[0]} camera px: at least 2 are needed"
        )
    return out[0], out[1]


def capture_template(
    phases: tuple[int, ...],
    period: int,
    lit: int,
    orientation: str,
    pattern_names: list[str],
    camera_names: list[str],
    scale: float = 1.0,
) -> str:
    """The text of ``capture.yaml`` for camera images of the projected frames, whose
    stripes are ``scale`` camera pixels per projector pixel on the medium."""
    camera_period, camera_lit = camera_stripes(period, lit, scale)
    if scale == 1:
        unit = "camera pixels (= projector pixels: one camera pixel per projector pixel)"
    else:
        unit = f"camera pixels ({period} projector px x {scale:g} camera px per projector px)"
    images = "\n".join(
        f"  - {c}  # camera image of {p} (projector phase {ph})"
        for c, p, ph in zip(camera_names, pattern_names, phases, strict=True)
    )
    return f"""\
# lightfield_jax capture file: a template written by `lightfield-jax pattern`
# (format: lightfield_jax.capture.capture).
#
# Project each image in turn and take one camera image of the medium for each,
# all with the same exposure, gain and white balance, in a linear format: 16-bit
# TIFF or PNG from the camera's raw files (demosaiced, no gamma, no auto exposure),
# or float EXR from an HDR merge. Replace the camera_*.tif names below by your
# camera's files (paths relative to this file). The stripes must run along the
# camera's rows (or columns). The model counts lengths in camera pixels: period and
# lit below are the stripes' size on the camera image, which is the projector's size
# times the camera pixels per projector pixel (measure it: the stripes' period in a
# camera image over the projector's; `pattern --camera-px-per-projector-px` writes
# it here, and loading refuses a period the images clearly do not have).
# Then check what the pipeline sees with `lightfield-jax inspect capture.yaml`
# and fit with `lightfield-jax fit capture.yaml`.

# One camera image per projected stripe image, in this order.
images:
{images}

pattern:
  period: {camera_period}          # stripe period in {unit}
  lit: {camera_lit}             # lit rows per period, in camera pixels
  # `auto` measures a value from the images; give a value to override it.
  phases: auto       # where the stripes fall on the camera's rows, one per image
  entry: auto        # the wall the light enters through: left, right, top or bottom
  direction_deg: auto  # heading of the light, degrees from +x toward +y

medium_roi: auto     # the medium's rectangle [x0, y0, x1, y1] in camera pixels (x1, y1 exclusive)

# Camera images of the projector showing all white and all black: the white frame
# is where the medium's ROI is found; the black frame measures the projector's
# black level (the light a dark stripe still emits, relative to a lit one).
white_frame: camera_white.tif   # camera image of white.png
black_frame: camera_black.tif   # camera image of black.png
black_level: auto    # or a number in [0, 1)

# Optional calibration (uncomment to use):
# dark_frame: camera_dark.tif   # lens capped or projector off, same exposure; subtracted first
# flat_field: camera_flat.tif   # a uniformly lit white target; divides every image
# saturation: 0.98              # value (scaled to [0, 1]) at or above which a pixel is clipped
# pixel_size_mm: 0.05           # camera pixel pitch on the medium, to report per-mm coefficients
channel: all         # R, G, B, an index, or all (each channel is fitted on its own)

# The model's phase convention: normalized (the default) conserves energy in the
# plane and fits every medium; paper is the paper's own, with no answer for forward
# media of high albedo such as milk (rho = albedo x A(g) >= 1).
# fit: {{phase: normalized}}
"""


def pattern_memory(width: int, height: int, shifts: int) -> int:
    """Bytes :func:`write_patterns` needs: the stripe, white and black frames (8-bit),
    each with the writer's copy."""
    return 2 * (shifts + 2) * width * height


def write_patterns(
    out: str | os.PathLike,
    width: int,
    height: int,
    period: int = 6,
    lit: int = 3,
    shifts: int | None = None,
    orientation: str = "rows",
    scale: float = 1.0,
) -> list[Path]:
    """Write ``stripe_XX.png`` (one per phase), ``white.png``, ``black.png`` (8-bit,
    width × height) and ``capture.yaml`` into the folder ``out``; returns the files.
    ``period`` and ``lit`` are projector pixels; the capture file's are camera pixels,
    ``scale`` camera pixels per projector pixel (:func:`camera_stripes`)."""
    camera_stripes(period, lit, scale)  # before any file
    phases, images = stripe_patterns(width, height, period, lit, shifts, orientation)
    out = Path(out)
    files = []
    names = [f"stripe_{i:02d}.png" for i in range(len(images))]
    for name, image in zip(names, images, strict=True):
        files.append(write_png(out / name, image))
    files.append(write_png(out / "white.png", np.full((height, width), 255, np.uint8)))
    files.append(write_png(out / "black.png", np.zeros((height, width), np.uint8)))
    camera = [f"camera_{Path(n).stem}.tif" for n in names]
    text = capture_template(phases, period, lit, orientation, names, camera, scale)
    files.append(atomic_write_text(out / "capture.yaml", text))
    return files


__all__ = [
    "ORIENTATIONS",
    "camera_stripes",
    "capture_template",
    "check_size",
    "pattern_memory",
    "pattern_phases",
    "stripe_patterns",
    "write_patterns",
]
