"""The capture format: shifted stripe images of a medium, and how they were taken.

A capture is a YAML file next to its images (``lightfield-jax simulate`` writes one for
stripe illumination, ``lightfield-jax pattern`` a template for a real camera; the
inverse pipeline reads it)::

    images: [shift_00.exr, shift_01.exr, shift_02.exr, shift_03.exr, shift_04.exr, shift_05.exr]
    pattern: {period: 6, lit: 3, phases: [0, 1, 2, 3, 4, 5], direction_deg: 0.0, entry: left}
    dark_frame: dark.exr         # optional
    black_frame: black.tif       # optional
    white_frame: white.tif       # optional
    flat_field: flat.tif         # optional
    black_level: 0.0             # optional (or auto)
    medium_roi: [x0, y0, x1, y1] # optional (or auto)
    pixel_size_mm: 0.05          # optional
    saturation: 0.98             # optional
    channel: all                 # optional
    geometry: {kind: plane}      # optional
    fit: {max_render_cells: 4000000, n_theta: 64}   # optional: FitOptions fields
    truth: {sigma_t: 0.2051, sigma_s: 0.0366, g: 0.4, gain: 1.0, phase: paper}  # optional

Keys:

- ``images``: a list of image files (paths relative to the capture file; OpenEXR,
  TIFF, PNG or ``.npy``, all the same size, channel count and sample format), one per
  phase; or one ``.npy`` stack of shape [P, H, W] or [P, H, W, C]. Integer samples are
  scaled to [0, 1] by their type's maximum (see :func:`~lightfield_jax.capture.io.read_image`).
  Camera files: 16-bit TIFF or PNG from a raw converter (linear, demosaiced), or float
  EXR from an HDR merge. Refused with a clear error: images of different sample
  formats (8- and 16-bit, integer and float), 1-channel images that are an
  undemosaiced Bayer mosaic, 4-channel images that are not RGB with a constant alpha
  (a constant alpha channel is dropped). 16-bit files that hold 10-, 12- or 14-bit data
  clipped at its top code (4095 for 12 bits) have those pixels masked as saturated.
  See :mod:`lightfield_jax.capture.calibration`.
- ``images`` as exposure brackets, one list per shift (``[[s0_1ms.png, s0_8ms.png],
  [s1_1ms.png, s1_8ms.png], ...]``), with ``exposure_times`` (seconds, increasing, the
  order of every list) and ``response`` (``linear``, default; ``auto``: recovered from
  the brackets; or a table file): each bracket is merged to linear radiance
  (:mod:`lightfield_jax.capture.hdr`), clipped and near-black samples dropped; a calibration
  frame is then a list of one file per exposure time too, and the dark frame is
  subtracted from every exposure before the merge. ``saturation`` is then the sample
  value at which a sample counts as clipped (default 0.98). The merged noise goes to the
  joint fit (``Capture.exposure``); ``Capture.brackets`` says what the merge did.
- ``pattern``: the projected stripes (docs/model.md section 3): ``period`` (default 6),
  ``lit`` (default 3), ``phases`` (one per image, default 0..P−1), ``direction_deg``
  (default: the entry wall's inward normal), ``entry`` (left, right, top, bottom;
  default left). Image row r (column, for the top and bottom walls) is lit in an image
  of phase φ iff (r + φ) mod period < lit, counted in the full image frame; with a
  ``medium_roi`` the loaded pattern's phases are shifted to count from the ROI's edge.
- ``dark_frame``: an image taken with the projector off, subtracted from every image
  (and from the other calibration frames) first.
- ``black_frame``, ``white_frame``: the camera's images of the projector showing all
  black and all white. The black frame measures the black level (``black_level:
  auto``); the white frame, if given, is where the medium's ROI is found.
- ``flat_field``: an image of a uniformly lit white target (the camera's vignetting),
  taken with the images' settings; the dark frame is subtracted from it, it is divided
  by its median, and every image is divided by it. Pixels where it is not positive
  are masked.
  Calibration frames (dark, black, white, flat) have the images' size and one channel
  or as many as the images, and an integer one the images' bit depth.
- ``black_level``: b in [0, 1): a dark stripe emits b times a lit one (docs/model.md
  section 5). Absent: unknown (a joint fit may estimate it).
- ``medium_roi``: [x0, y0, x1, y1] in pixels, x1 and y1 exclusive: the medium's
  rectangle. Images are cropped to it and its edges are the medium's walls.
- ``pixel_size_mm``: pixel pitch in mm (> 0), to report coefficients in mm⁻¹.
- ``saturation``: image value (after integer scaling) at or above which a raw pixel
  is saturated and masked. Absent: integer frames mask pixels at their top code (255
  or 65535, i.e. 1.0, or a 16-bit file's sensor top code, see ``images``), float
  frames mask nothing.
- ``channel``: which channel to use: a name (R, G, B, Y, ...), an index, or ``all``
  (default: every channel, fitted separately).
- ``geometry``: ``{kind: plane}``, the paper's 2-D model (default), or the tank's
  depth modelled in 3-D (docs/model.md section 7): ``{kind: slab, thickness: 6.4,
  boundary: absorbing}`` (thickness in pixels; ``boundary: refractive`` with ``n:
  1.33``; optional ``n_mu``, the elevation nodes). Every fit method uses it.
  ``{kind: auto, thickness: 6.4, ...}`` (the slab's keys): the fit uses the plane
  model where its misfit is below the capture's noise, else the slab.
- ``fit``: settings of the fit (:class:`~lightfield_jax.FitOptions` fields: the
  model's ``n_theta``, ``refine``, ``bounces``, ``tail``, ``max_cells``,
  ``max_render_cells``; the solve's ``max_steps``, ``rtol``, ``atol``, ``start``; the
  basin search's ``basin_search``, ``max_basins``; ``model_error``, ``correct``,
  ``max_chi2`` ...; see ``help(lfj.FitOptions)``), used by ``lightfield-jax fit`` and
  :func:`~lightfield_jax.fit_capture`. The method and the phase convention are the
  command's options, the geometry the key above.
- ``truth``: the true parameters of a simulated capture (``sigma_t``, ``sigma_s``,
  ``g``, ``gain``, ``phase``, ``black_level``), for reports.

Measured values (``auto``). Five keys take the value ``auto``: ``medium_roi``,
``pattern.entry``, ``pattern.direction_deg``, ``pattern.phases`` and ``black_level``.
Each is then measured from the images instead of given (a key that is given is used
as it is, and constrains the measurement of the others; a key that is absent keeps its
default above, so existing captures load unchanged):

- ``medium_roi``, ``pattern.entry``, ``pattern.direction_deg``, ``pattern.phases``:
  :func:`~lightfield_jax.capture.detect.detect_geometry` on the dark-subtracted,
  flat-fielded images over the whole frame (the ROI in the white frame when there is
  one): the lit medium's rectangle, the wall the light enters, its heading from the
  stripes' ridges (oblique stripes are modelled by ``direction_deg``), and where the
  stripes fall on the camera's rows. Its result is ``Capture.detected``. Where the
  light fades before the far wall, that edge is not taken for a wall: the ROI goes on
  through the dark frame and the fit crops where each channel's light meets its noise.
- ``black_level``: from the black frame (against the white frame or the mean of the
  shifts), or, without one, Imin/Imax at the entry wall, which is an upper bound
  (:mod:`lightfield_jax.capture.calibration`). Its result is ``Capture.black_level_estimate``.

What was measured is written to ``Capture.notes``; a detection whose confidence is
below 0.5 is also a :class:`CaptureWarning`. ``lightfield-jax inspect`` shows it all.

:func:`load_capture` validates all of it: every error is a
:class:`~lightfield_jax.capture.io.CaptureError` whose message starts with the capture file and
names the key and value (or the image file). Beyond each key's type and range (phases
in [0, period), a period no longer than the images), the images must agree with the
file: a capture too large for the memory available is refused from the image headers
before any pixel is read (:mod:`lightfield_jax.app.memory`); images without light (every
value zero or negative, or darker than the dark frame) are refused; in a capture whose
images show stripes of the period, an image without them (a white or black frame
listed among the stripes) is refused, and given phases that the stripe detector
contradicts with confidence (the period within 2 %, every phase within 0.1 row) are
refused with both lists (absent phases, whose default is contradicted, get a note).
Pixels that cannot be used (NaN or Inf in an image, the dark frame or the flat field,
saturated or clipped) are masked, with a :class:`CaptureWarning` that counts them.
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lightfield_jax.app.config import _REQUIRED, _as_float, _as_int, _Section, brief, load_yaml
from lightfield_jax.app.memory import capture_bytes, check_memory
from lightfield_jax.capture.calibration import (
    BlackLevel,
    check_not_mosaic,
    check_sample_formats,
    drop_constant_alpha,
    estimate_black_level,
    sensor_top_code,
)
from lightfield_jax.capture.detect import (
    LOW_CONFIDENCE,
    Geometry,
    _across_first,
    _coefficients,
    detect_geometry,
)
from lightfield_jax.capture.hdr import (
    CLIP,
    RESPONSES,
    Brackets,
    linear_response,
    merge_bracket,
    merge_capture,
)
from lightfield_jax.capture.io import (
    CaptureError,
    CaptureFileNotFoundError,
    ImageData,
    _channel_index,
    atomic_write_text,
    image_values,
    read_image,
    read_npy_stack,
)
from lightfield_jax.scene.geometry import parse_geometry
from lightfield_jax.scene.illumination import WALLS, Stripes
from lightfield_jax.scene.medium import PHASE_CONVENTIONS

CAPTURE_KEYS: tuple[str, ...] = (
    "images",
    "pattern",
    "dark_frame",
    "black_level",
    "medium_roi",
    "pixel_size_mm",
    "saturation",
    "channel",
    "geometry",
    "truth",
    "black_frame",
    "white_frame",
    "flat_field",
    "exposure_times",
    "response",
    "fit",
)
AUTO = "auto"
# FitOptions a capture file may set under ``fit:`` (the method and the phase convention
# are the command's flags, the geometry has its own key, a solver has no YAML form).
_FIT_INTS = (
    "max_bounces",
    "tail_bounces",
    "tail_max_steps",
    "g_grid",
    "start_grid",
    "max_cells",
    "max_steps",
    "max_basins",
    "max_render_cells",
    "correction_renders",
)
_FIT_OPTIONAL_INTS = ("n_theta", "refine")
_FIT_FLOATS = ("tolerance", "crop_fraction", "basin_tolerance", "max_chi2")
_FIT_OPTIONAL_FLOATS = ("rtol", "atol")
_FIT_BOOLS = ("crop", "basin_search", "model_error", "correct")
FIT_KEYS: tuple[str, ...] = (
    "bounces",
    "tail",
    "start",
    *_FIT_INTS,
    *_FIT_OPTIONAL_INTS,
    *_FIT_FLOATS,
    *_FIT_OPTIONAL_FLOATS,
    *_FIT_BOOLS,
)
GEOMETRY_KINDS: tuple[str, ...] = ("plane", "slab")
_AUX_FRAMES = ("dark_frame", "black_frame", "white_frame", "flat_field")
_PATTERN_KEYS = ("period", "lit", "phases", "direction_deg", "entry")
_TRUTH_FLOATS = ("sigma_t", "sigma_s", "g", "gain", "black_level")
_TRUTH_KEYS = (*_TRUTH_FLOATS, "phase")


class CaptureWarning(UserWarning):
    """Pixels of a capture were masked (non-finite, saturated or clipped)."""


@dataclasses.dataclass(frozen=True, eq=False)
class Capture:
    """A loaded, validated capture (see the module docstring).

    Attributes:
        images: float array [P, H, W, C]: the images after dark-frame subtraction and
            the ROI crop, in image units. Masked non-finite values are set to 0.
        channel_names: one name per channel.
        pattern: the stripes of each image, phases counted in the cropped frame.
        mask: bool [H, W, C], True where a pixel is valid in every image (finite in the
            images and the dark frame, and not saturated).
        black_level: b, or ``None`` when unknown.
        roi: (x0, y0, x1, y1) of the medium in the full frame, or ``None``.
        pixel_size_mm: pixel pitch, or ``None``.
        saturation: the saturation threshold used, or ``None``.
        source: the capture file.
        image_paths: the image files (one ``.npy`` stack repeated for a stack).
        dark_frame: the dark frame's file, or ``None``.
        n_masked: masked [H, W, C] entries: ``nonfinite``, ``saturated`` (finite but
            saturated or clipped) and ``total``.
        geometry: the geometry mapping (``{"kind": "plane"}``).
        truth: the true parameters of a simulated capture, or ``None``.
        warnings: the messages of the :class:`CaptureWarning` s issued while loading.
        notes: what loading measured or decided on its own (``auto`` values, a dropped
            alpha channel, the sensor's bit depth), one line each.
        detected: what :func:`~lightfield_jax.capture.detect.detect_geometry` found, when a
            key asked for ``auto``; else ``None``.
        black_level_estimate: the estimate behind ``black_level: auto``, else ``None``.
        overview: the mean of the shifts over the whole camera frame (dark frame
            subtracted, flat-fielded), [H, W, C], before the ROI crop.
        black_frame, white_frame, flat_field: the files given for these keys, or ``None``.
        brackets: what merging exposure brackets did (:mod:`lightfield_jax.capture.hdr`), or
            ``None`` for single exposures.
        exposure: the merged images' effective exposure T (seconds) [P, H, W, C] after
            the ROI crop (their noise: Var ∝ image / T), or ``None``.
        fit_options: the file's ``fit:`` settings (:class:`~lightfield_jax.FitOptions`
            fields), which :func:`~lightfield_jax.fit_capture` uses unless told otherwise.
    """

    images: np.ndarray
    channel_names: tuple[str, ...]
    pattern: Stripes
    mask: np.ndarray
    black_level: float | None
    roi: tuple[int, int, int, int] | None
    pixel_size_mm: float | None
    saturation: float | None
    source: Path
    image_paths: tuple[Path, ...]
    dark_frame: Path | None
    n_masked: dict[str, int]
    geometry: dict[str, Any]
    truth: dict[str, Any] | None
    warnings: tuple[str, ...]
    notes: tuple[str, ...] = ()
    detected: Geometry | None = None
    black_level_estimate: BlackLevel | None = None
    overview: np.ndarray | None = None
    black_frame: Path | None = None
    white_frame: Path | None = None
    flat_field: Path | None = None
    brackets: Brackets | None = None
    exposure: np.ndarray | None = None
    fit_options: dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def n_images(self) -> int:
        return self.images.shape[0]

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the (cropped) images."""
        return self.images.shape[1:3]


# --------------------------------------------------------------------------- loading


def load_capture(path: str | os.PathLike) -> Capture:
    """Read and validate a capture file (see the module docstring).

    Raises:
        CaptureFileNotFoundError: the capture file or an image does not exist.
        CaptureError: anything else that makes the capture unusable; the message
            starts with the capture file and names the key, value or image.
    """
    path = Path(path)
    if not path.exists():
        raise CaptureFileNotFoundError(f"{path}: file not found")
    top = _Section(str(path), "", load_yaml(path, CaptureError), CAPTURE_KEYS, error=CaptureError)
    base = path.parent
    channel = _channel(top)
    fit_options = _fit_options(top)  # before any image is read
    notes: list[str] = []  # what was measured or decided: Capture.notes
    issues: list[str] = []  # what the user must know: CaptureWarnings
    merged = _brackets(top, base, channel, notes)
    frames = _frames(top, base, channel) if merged is None else merged[0]
    try:
        frames = drop_constant_alpha(frames, notes)
    except CaptureError as e:
        raise CaptureError(f"{top.source}: images: {e}") from None
    height, width, n_channels = frames[0].pixels.shape
    spec = _pattern_spec(top, len(frames), height, width)
    if merged is None:
        aux = {key: _aux_frame(top, key, base, channel, frames[0]) for key in _AUX_FRAMES}
    else:
        aux, brackets = merged[1], merged[2]
    try:
        check_sample_formats(
            [(f"images[{i}]", f) for i, f in enumerate(frames)],
            [(k, v) for k, v in aux.items() if v is not None],
        )
        check_not_mosaic(frames)
    except CaptureError as e:
        raise CaptureError(f"{top.source}: {e}") from None
    roi = _roi(top, width, height)
    black_level = _black_level(top)
    pixel_size = _positive(top, "pixel_size_mm")
    saturation = _positive(top, "saturation") if merged is None else None
    geometry = _geometry(top)
    truth = _truth(top)

    raw = np.stack([f.pixels for f in frames])
    if frames[0].is_integer and frames[0].bit_depth == 8:
        notes.append(
            "8-bit images: 256 levels quantise the light's decay, and cameras usually "
            "write 8-bit files gamma-encoded (not linear); prefer 16-bit linear output"
        )
    sensor = None if saturation is not None else sensor_top_code(raw, frames)
    dark = aux["dark_frame"]
    dark_pixels = None if dark is None else dark.pixels
    flat_pixels = _flat(top, aux["flat_field"], dark_pixels)

    overview = _calibrate(np.mean(raw, axis=0), dark_pixels, flat_pixels)
    calibrated = _calibrate(raw, dark_pixels, flat_pixels)
    _check_light(top, calibrated, dark)
    detected = None
    if AUTO in (roi, spec["phases"], spec["entry"], spec["direction_deg"]):
        white = aux["white_frame"]
        detected = _detect(
            top,
            spec,
            roi,
            calibrated,
            None if white is None else _calibrate(white.pixels, dark_pixels, flat_pixels),
            dark_subtracted=dark is not None or bool(merged and "dark_frame" in top.data),
        )
        notes.append("detected: " + detected.summary().replace("\n", "; "))
        if detected.confidence < LOW_CONFIDENCE:
            issues.append(
                f"the detected geometry has a low confidence {detected.confidence:.2f} "
                f"({detected.summary().splitlines()[-1]}): check it with lightfield-jax "
                "inspect, or give the values"
            )
        roi = detected.roi if roi == AUTO else roi
    pattern = _stripes(top, spec, detected)
    names = [f.path.name for f in frames]
    if len(set(f.path for f in frames)) == 1 and len(frames) > 1:
        names = [f"{frames[0].path.name}[{i}]" for i in range(len(frames))]

    calibration_frames = {k: v.pixels for k, v in aux.items() if v is not None}
    full_roi, full_pattern = roi, pattern
    if roi is not None:
        x0, y0, x1, y1 = roi
        raw = raw[:, y0:y1, x0:x1]
        calibration_frames = {k: v[y0:y1, x0:x1] for k, v in calibration_frames.items()}
        dark_pixels = calibration_frames.get("dark_frame")
        if flat_pixels is not None:
            flat_pixels = flat_pixels[y0:y1, x0:x1]
        pattern = _crop_pattern(pattern, x0, y0)
    checked = [(dark, dark_pixels)] if dark is not None else []
    if flat_pixels is not None:
        checked.append((aux["flat_field"], flat_pixels))
    nonfinite = _nonfinite(raw, checked, names, issues)
    saturated = _saturated(raw, frames, names, saturation, sensor, issues) & ~nonfinite
    exposure = None
    if merged is not None:
        x0, y0, x1, y1 = roi or (0, 0, width, height)
        saturated |= brackets.clipped[y0:y1, x0:x1] & ~nonfinite
        exposure = brackets.exposure[:, y0:y1, x0:x1]
        notes.append(brackets.summary())
    mask = ~(nonfinite | saturated)
    for issue in issues:
        warnings.warn(f"{path}: {issue}", CaptureWarning, stacklevel=2)
    if not mask.any():
        top.fail("images", "no usable pixel: every pixel is non-finite or saturated in some image")
    phases_from = "auto" if spec["phases"] == AUTO else spec["phases_from"]
    contradiction = _check_stripes(
        top, full_pattern, calibrated, full_roi, names, phases_from, dark
    )
    if contradiction:
        notes.append(contradiction)
    del calibrated
    images = _calibrate(raw, dark_pixels, flat_pixels)
    images = np.where(np.isfinite(images), images, 0).astype(raw.dtype)

    estimate = None
    if black_level == AUTO:
        frames_used = {
            k: _calibrate(calibration_frames[k], dark_pixels, flat_pixels)
            for k in ("black_frame", "white_frame")
            if k in calibration_frames
        }
        estimate = _estimate_black_level(top, images, pattern, mask, frames_used)
        black_level = estimate.value
        notes.append(
            f"black_level: auto: {estimate.value:.4f}"
            + (f" ± {estimate.stderr:.4f}" if math.isfinite(estimate.stderr) else "")
            + f" ({estimate.method}; per channel "
            + ", ".join(f"{v:.4f}" for v in estimate.per_channel)
            + ")"
        )
    return Capture(
        images=images,
        channel_names=frames[0].channel_names,
        pattern=pattern,
        mask=mask,
        black_level=black_level,
        roi=roi,
        pixel_size_mm=pixel_size,
        saturation=saturation,
        source=path,
        image_paths=tuple(f.path for f in frames),
        dark_frame=None if dark is None else dark.path,
        n_masked={
            "nonfinite": int(nonfinite.sum()),
            "saturated": int(saturated.sum()),
            "total": int((~mask).sum()),
        },
        geometry=geometry,
        truth=truth,
        fit_options=fit_options,
        warnings=tuple(issues),
        notes=tuple(notes),
        detected=detected,
        black_level_estimate=estimate,
        overview=np.where(np.isfinite(overview), overview, 0.0).astype(raw.dtype),
        black_frame=None if aux["black_frame"] is None else aux["black_frame"].path,
        white_frame=None if aux["white_frame"] is None else aux["white_frame"].path,
        flat_field=None if aux["flat_field"] is None else aux["flat_field"].path,
        brackets=None if merged is None else brackets,
        exposure=exposure,
    )


def capture_files(path: str | os.PathLike) -> list[Path]:
    """The capture file and every file it lists (images, calibration frames), from the
    YAML alone: the inputs an output must not replace. Values that are not file names
    are skipped (:func:`load_capture` reports them)."""
    path = Path(path)
    data = load_yaml(path, CaptureError)
    if not isinstance(data, dict):
        return [path]

    def names(value) -> list:  # a file, a list of files, or brackets (lists of lists)
        if isinstance(value, list):
            return [name for v in value for name in names(v)]
        return [value]

    listed = names(data.get("images")) + names([data.get(key) for key in _AUX_FRAMES])
    if data.get("response") not in RESPONSES:
        listed.append(data.get("response"))
    return [path] + [path.parent / v for v in listed if isinstance(v, str) and v]


def _check_capture_memory(top: _Section, files: Sequence[Path]) -> None:
    """Refuse, from the first file's header, a capture too large to load (a file that
    cannot be read is left to the read, which names its key)."""
    try:
        samples = image_values(files[0]) * len(files)
    except CaptureError:
        return
    check_memory(
        capture_bytes(samples), f"{top.source}: images ({len(files)} file(s), {samples} samples)"
    )


def _channel(top: _Section) -> str | int | None:
    """The channel selection for read_image: a name, an index, or None for all."""
    value = top.get("channel", "all")
    if isinstance(value, bool) or not isinstance(value, (str, int)) or value == "":
        top.fail("channel", f"must be a channel name, an index or 'all', got {brief(value)}")
    if isinstance(value, int) and value < 0:
        top.fail("channel", f"must be a non-negative index, got {brief(value)}")
    return None if value == "all" else value


def _read(top: _Section, key: str, file: Path, channel) -> ImageData:
    try:
        return read_image(file, channel)
    except CaptureFileNotFoundError as e:
        raise CaptureFileNotFoundError(f"{top.source}: {key}: {e}") from None
    except CaptureError as e:
        raise CaptureError(f"{top.source}: {key}: {e}") from None


def _file(top: _Section, key: str, value: Any, base: Path) -> Path:
    if not isinstance(value, str) or not value:
        top.fail(key, f"must be a file path, got {brief(value)}")
    return base / value


def _frames(top: _Section, base: Path, channel) -> list[ImageData]:
    value = top.get("images")
    if isinstance(value, str):
        file = _file(top, "images", value, base)
        if file.suffix.lower() != ".npy":
            top.fail(
                "images",
                f"a single file must be a .npy stack [P, H, W(, C)], got {brief(value)}; "
                "list the image files otherwise",
            )
        _check_capture_memory(top, [file])
        try:
            frames = read_npy_stack(file)
            if channel is not None:
                index = _channel_index(frames[0].channel_names, channel, file)
                frames = [
                    dataclasses.replace(
                        f, pixels=f.pixels[..., [index]], channel_names=(f.channel_names[index],)
                    )
                    for f in frames
                ]
        except CaptureFileNotFoundError as e:
            raise CaptureFileNotFoundError(f"{top.source}: images: {e}") from None
        except CaptureError as e:
            raise CaptureError(f"{top.source}: images: {e}") from None
        return frames
    if not isinstance(value, list):
        top.fail("images", f"must be a list of image files or one .npy stack, got {brief(value)}")
    if not value:
        top.fail("images", "the list is empty: give one image per phase")
    files = [_file(top, f"images[{i}]", v, base) for i, v in enumerate(value)]
    _check_capture_memory(top, files)
    frames = [_read(top, f"images[{i}]", file, channel) for i, file in enumerate(files)]
    first = frames[0]
    for i, f in enumerate(frames[1:], start=1):
        if f.pixels.shape != first.pixels.shape:
            top.fail(
                f"images[{i}]",
                f"{f.path.name} is {_size(f)}, but images[0] ({first.path.name}) is "
                f"{_size(first)}; every image must have the same size and channels",
            )
    return frames


def _size(image: ImageData) -> str:
    h, w, c = image.pixels.shape
    return f"{w}x{h} pixels with {c} channel(s)"


# --------------------------------------------------------------------------- brackets


def _brackets(top: _Section, base: Path, channel, notes: list[str]):
    """Exposure brackets merged to linear radiance (:mod:`lightfield_jax.capture.hdr`):
    ``(frames, calibration frames, Brackets)``, one merged frame per shift, the dark
    frame subtracted per exposure before merging (so the calibration frames hold no
    dark frame any more); ``None`` when the images are not brackets (lists)."""
    value = top.get("images")
    rows = [isinstance(v, list) for v in value] if isinstance(value, list) else []
    if not any(rows):
        for key in ("exposure_times", "response"):
            if key in top.data:
                top.fail(key, "applies to bracketed images only (a list of exposures per shift)")
        return None
    if not all(rows):
        top.fail(
            "images",
            "mixes files and brackets: give every shift as a list of exposures, or every "
            "shift as one file",
        )
    times = _exposure_times(top)

    def read(key, file, first=None):
        if first is not None:
            return _aux_frame(top, key, base, channel, first, value=file)
        return _read(top, key, _file(top, key, file, base), channel)

    shifts = []
    for i, row in enumerate(value):
        if len(row) != len(times):
            top.fail(
                f"images[{i}]",
                f"lists {len(row)} exposure(s) for {len(times)} exposure_times; give one file "
                "per exposure time, in the same order",
            )
        shifts.append([read(f"images[{i}][{j}]", v) for j, v in enumerate(row)])
    listed = [(f"images[{i}][{j}]", f) for i, row in enumerate(shifts) for j, f in enumerate(row)]
    first = listed[0][1]
    for key, f in listed[1:]:
        if f.pixels.shape != first.pixels.shape:
            top.fail(
                key,
                f"{f.path.name} is {_size(f)}, but images[0][0] ({first.path.name}) is "
                f"{_size(first)}; every image must have the same size and channels",
            )
    try:
        kept = iter(drop_constant_alpha([f for _, f in listed], notes))
    except CaptureError as e:
        raise CaptureError(f"{top.source}: images: {e}") from None
    shifts = [[next(kept) for _ in row] for row in shifts]
    first = shifts[0][0]
    aux: dict[str, list[ImageData] | None] = {}
    for key in _AUX_FRAMES:
        files = top.get(key, None)
        if files is not None and (not isinstance(files, list) or len(files) != len(times)):
            top.fail(
                key,
                f"with bracketed images give one file per exposure time ({len(times)}), in "
                f"their order, got {files!r}",
            )
        aux[key] = (
            None if files is None else [read(f"{key}[{j}]", f, first) for j, f in enumerate(files)]
        )
    try:
        check_sample_formats(
            listed, [(f"{k}[{j}]", f) for k, v in aux.items() if v for j, f in enumerate(v)]
        )
    except CaptureError as e:
        raise CaptureError(f"{top.source}: {e}") from None
    levels = (1 << first.bit_depth) if first.is_integer else None
    images = np.stack([[f.pixels for f in row] for row in shifts])  # [P, J, H, W, C]
    clip = _positive(top, "saturation")
    # 10-14-bit data in 16-bit files: samples rescaled so that the sensor's top code is 1.
    sensor = None
    if clip is None:
        sensor = sensor_top_code(images.reshape(-1, *images.shape[2:]), [f for _, f in listed])
    full = 1.0 if sensor is None else sensor[0]
    if sensor is not None:
        levels = 1 << sensor[1]
        notes.append(f"{sensor[1]}-bit data in 16-bit files: samples divided by its top code")
    images = images / full
    response = _response(top, base, images, times, first.pixels.shape[-1])
    clip = clip or CLIP
    dark = None if aux["dark_frame"] is None else np.stack([f.pixels for f in aux["dark_frame"]])
    dark = None if dark is None else dark / full
    radiance, record = merge_capture(
        images, times, response, levels=levels, dark=dark, clip=clip,
        files=[[f.path for f in row] for row in shifts],
    )  # fmt: skip
    frames = [_merged_frame(r, row[-1]) for r, row in zip(radiance, shifts, strict=True)]
    merged: dict[str, ImageData | None] = dict.fromkeys(_AUX_FRAMES)
    for key in ("black_frame", "white_frame", "flat_field"):
        if aux[key] is not None:
            stack = np.stack([f.pixels for f in aux[key]]) / full
            m = merge_bracket(stack, times, response, levels=levels, dark=dark, clip=clip)
            merged[key] = _merged_frame(m.radiance, aux[key][-1])
    if dark is not None:
        notes.append("dark_frame: subtracted from every exposure before the merge")
    return frames, merged, record


def _merged_frame(radiance: np.ndarray, longest: ImageData) -> ImageData:
    """A merged bracket as a float frame, named after its longest exposure."""
    return dataclasses.replace(
        longest, pixels=radiance.astype(np.float32), bit_depth=32, sample_type="float"
    )


def _exposure_times(top: _Section) -> list[float]:
    value = top.get("exposure_times", None)
    if not isinstance(value, list) or len(value) < 2:
        top.fail(
            "exposure_times",
            f"bracketed images need a list of at least two exposure times (seconds), got {value!r}",
        )
    for i, t in enumerate(value):
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not 0 < t < math.inf:
            top.fail(f"exposure_times[{i}]", f"must be a positive number of seconds, got {t!r}")
    if any(b <= a for a, b in zip(value, value[1:], strict=False)):
        top.fail("exposure_times", f"must increase (shortest first), got {value!r}")
    return [float(t) for t in value]


def _response(top: _Section, base: Path, images: np.ndarray, times, n_channels: int):
    """The inverse response: ``linear`` (default), ``auto`` (from the brackets) or a
    table file (:func:`~lightfield_jax.capture.hdr.load_response`)."""
    from lightfield_jax.capture.hdr import calibrate_response, load_response

    value = top.get("response", "linear")
    if not isinstance(value, str) or not value:
        top.fail("response", f"must be {' or '.join(RESPONSES)} or a file, got {value!r}")
    try:
        if value == "linear":
            return linear_response()
        if value == "auto":
            p, j, h, w, c = images.shape
            pooled = np.moveaxis(images, 1, 0).reshape(j, p * h * w, c)
            return calibrate_response(pooled, times)
        return load_response(_file(top, "response", value, base), n_channels)
    except CaptureError as e:
        raise CaptureError(f"{top.source}: response: {e}") from None


def _pattern_spec(top: _Section, n_images: int, height: int, width: int) -> dict[str, Any]:
    """The pattern's keys, validated; ``phases``, ``entry`` and ``direction_deg`` may be
    ``"auto"`` (measured from the images)."""
    s = top.section("pattern", _PATTERN_KEYS)
    spec: dict[str, Any] = {"period": s.int("period", 6), "lit": s.int("lit", 3)}
    if spec["period"] > max(height, width):
        s.fail(
            s.key("period"),
            f"{spec['period']} rows is longer than the {width}x{height} images: a stripe "
            "period is a few rows",
        )
    phases = s.get("phases", None)
    spec["phases_from"] = "default" if phases is None else "given"
    if phases is None:
        phases = list(range(n_images))
    elif phases == AUTO:
        pass
    elif not isinstance(phases, list) or not phases:
        s.fail(
            s.key("phases"), f"must be a non-empty list of integers or 'auto', got {brief(phases)}"
        )
    else:
        phases = [_as_int(s, f"{s.key('phases')}[{i}]", p) for i, p in enumerate(phases)]
        outside = [p for p in phases if not 0 <= p < spec["period"]]
        if outside:
            s.fail(
                s.key("phases"),
                f"{brief(outside)} outside [0, period) = [0, {spec['period']}); a phase "
                "counts rows modulo the period",
            )
    if phases != AUTO and len(phases) != n_images:
        s.fail(
            s.key("phases"),
            f"lists {len(phases)} phase(s) for {n_images} image(s); give one phase per image",
        )
    spec["phases"] = phases
    spec["direction_deg"] = (
        AUTO if s.get("direction_deg", None) == AUTO else (s.float("direction_deg", None))
    )
    spec["entry"] = s.choice("entry", (*WALLS, AUTO), "left")
    # Validate what is given now, before any detection.
    _stripes(top, {**spec, "phases": phases if phases != AUTO else [0]}, None, check=True)
    return spec


def _stripes(top: _Section, spec: dict[str, Any], detected: Geometry | None, check=False):
    """The Stripes of a pattern spec, ``auto`` values taken from ``detected``."""

    def pick(key, measured):
        value = spec[key]
        if value != AUTO:
            return value
        return None if detected is None else measured

    entry = pick("entry", detected and detected.entry)
    direction = pick("direction_deg", detected and detected.direction_deg)
    phases = pick("phases", detected and detected.phases)
    if check and entry is None:
        entry = "left" if direction is None else _any_wall(direction)
    try:
        return Stripes(
            spec["period"], spec["lit"], tuple(phases), direction_deg=direction, entry=entry
        )
    except ValueError as e:
        message = str(e).replace("illumination.", "pattern.").replace("illumination:", "pattern:")
        raise CaptureError(f"{top.source}: {message}") from None


def _any_wall(direction_deg: float) -> str:
    """A wall that light heading ``direction_deg`` can enter (for validation only)."""
    t = math.radians(direction_deg)
    c, s = math.cos(t), math.sin(t)
    if abs(c) >= abs(s):
        return "left" if c > 0 else "right"
    return "top" if s > 0 else "bottom"


def _crop_pattern(pattern: Stripes, x0: int, y0: int) -> Stripes:
    """The pattern with wall cells counted from the ROI's edge instead of the frame's."""
    offset = y0 if pattern.entry in ("left", "right") else x0
    phases = tuple((p + offset) % pattern.period for p in pattern.phases)
    return dataclasses.replace(pattern, phases=phases)


def _aux_frame(top: _Section, key: str, base: Path, channel, first: ImageData, value=None):
    """A calibration frame (dark, black, white, flat; ``value``: its file, default the
    key's): the images' size, and one channel or as many as they have."""
    value = top.get(key, None) if value is None else value
    if value is None:
        return None
    frame = _read(top, key, _file(top, key, value, base), channel)
    h, w, c = first.pixels.shape
    fh, fw, fc = frame.pixels.shape
    if fc == c + 1 and frame.channel_names[-1] == "A":
        frame = dataclasses.replace(
            frame, pixels=frame.pixels[..., :c], channel_names=frame.channel_names[:c]
        )
        fc = c
    if (fh, fw) != (h, w) or fc not in (1, c):
        top.fail(
            key,
            f"{value} is {_size(frame)}, but the images are {_size(first)} (a "
            f"{key.replace('_', ' ')} has the images' size and one channel or as many as "
            "they have)",
        )
    return frame


def _flat(top: _Section, flat: ImageData | None, dark: np.ndarray | None):
    """The flat field, dark frame subtracted, divided by its median: NaN where it is
    not positive (those pixels are masked)."""
    if flat is None:
        return None
    f = flat.pixels if dark is None else flat.pixels - dark
    good = np.isfinite(f) & (f > 0)
    if good.mean() < 0.5:
        top.fail(
            "flat_field",
            f"{flat.path.name} is not positive in {100 * (1 - good.mean()):.0f}% of its "
            "pixels (after the dark frame): not a flat field",
        )
    return np.where(good, f / np.median(f[good]), np.nan)


def _black_level(top: _Section) -> float | str | None:
    if top.get("black_level", None) == AUTO:
        return AUTO
    value = top.float("black_level", None)
    if value is not None and not 0.0 <= value < 1.0:
        top.fail("black_level", f"must lie in [0, 1), got {brief(value)} (or 'auto': measured)")
    return value


def _calibrate(a: np.ndarray, dark: np.ndarray | None, flat: np.ndarray | None) -> np.ndarray:
    """(a − dark) / flat: the images (or a calibration frame) in linear units."""
    if dark is not None:
        a = a - dark
    return a if flat is None else a / flat


def _detect(top, spec, roi, images, white, *, dark_subtracted: bool) -> Geometry:
    """Measure what the capture leaves ``auto`` (see :mod:`lightfield_jax.capture.detect`)."""
    asked = [k for k in ("phases", "entry", "direction_deg") if spec[k] == AUTO]
    asked = (["medium_roi"] if roi == AUTO else []) + [f"pattern.{k}" for k in asked]
    try:
        return detect_geometry(
            images,
            period=spec["period"],
            lit=spec["lit"],
            reference=white,
            floor=0.0 if dark_subtracted else None,
            roi=None if roi == AUTO else roi,
            entry=None if spec["entry"] == AUTO else spec["entry"],
            direction_deg=None if spec["direction_deg"] == AUTO else spec["direction_deg"],
        )
    except ValueError as e:
        raise CaptureError(f"{top.source}: {', '.join(asked)}: auto: {e}") from None


def _check_light(top: _Section, images: np.ndarray, dark: ImageData | None) -> None:
    """Refuse images without light: no value above zero (every value zero, or negative
    images), or, with a dark frame, images darker than it (99 % of the values after
    subtracting it below zero by more than 10⁻³ of the dark level: past quantisation)."""
    finite = images[np.isfinite(images)]
    if finite.size == 0:
        return  # every value non-finite: the mask's check says so
    brightest = float(finite.max())
    if dark is not None:
        level = float(np.percentile(finite, 99))
        dark_level = float(np.nanmedian(np.abs(dark.pixels)))
        if level < -1e-3 * dark_level:
            top.fail(
                "dark_frame",
                f"{dark.path.name} is brighter than the images (after subtracting it, 99% "
                f"of the image values are <= {level:.3g}): a dark frame is taken with the "
                "projector off, darker than every image",
            )
        return
    if brightest == 0:
        top.fail("images", "every pixel of every image is 0: no light was captured")
    if brightest < 0:
        top.fail(
            "images",
            f"every image value is negative (the largest is {brightest:.3g}): images of "
            "light are not negative (values must be linear, black at 0)",
        )


# Stripe contrast of an image: its Fourier amplitude across the stripes at the period
# against that at 2/3 of it (not a harmonic of the stripes: noise alone gives about 1,
# a 24-row crop of rendered stripes about 4, the window's leakage included). A capture
# whose median contrast reaches _STRIPED has stripes; an image of it whose amplitude is
# below _UNSTRIPED times the median image's is not a stripe image (a white or black
# frame listed among them: measured 0.003).
_STRIPED, _UNSTRIPED = 2.5, 0.1
# Declared phases are compared with measured ones only when the detector is sure of
# them: the stripes' period found within 2 % and every phase within 0.1 row of an
# integer (noise images reach neither).
_SURE_PHASES = 0.8


def _check_stripes(top, pattern, images, roi, names, phases_from: str, dark) -> str | None:
    """Refuse a capture whose images contradict its pattern: an image without stripes
    of the period in a capture that has them, or given phases that differ from those
    the stripe detector (:func:`~lightfield_jax.capture.detect.detect_geometry`) measures
    with confidence. Default phases (``pattern.phases`` absent) that differ are
    returned as a note's text instead. ``images`` and ``roi``: the full frame's;
    ``phases_from``: ``given``, ``default`` or ``auto``."""
    x0, y0, x1, y1 = roi if roi is not None else (0, 0, images.shape[2], images.shape[1])
    crop = np.where(np.isfinite(images), images, 0.0).sum(axis=-1)[:, y0:y1, x0:x1]
    stack = _across_first(crop, pattern.entry)
    u0 = y0 if pattern.entry in ("left", "right") else x0

    def amplitude(period):
        return np.abs(_coefficients(stack, u0, 1.0 / period)).sum(axis=-1)

    stripes = amplitude(pattern.period)
    with np.errstate(divide="ignore", invalid="ignore"):
        contrast = np.median(stripes / amplitude(1.5 * pattern.period))
        relative = stripes / np.median(stripes)
    if not contrast >= _STRIPED:
        return None  # no stripes to compare with
    for name, r in zip(names, relative, strict=True):
        if not r >= _UNSTRIPED:
            top.fail(
                "images",
                f"{name} shows no stripes of period {pattern.period} (stripe amplitude "
                f"{r:.2g} times the other images'): a white or black frame listed as a "
                "stripe image? (give it as white_frame or black_frame)",
            )
    if phases_from == "auto" or len(names) < 2:
        return None
    try:
        found = detect_geometry(
            images,
            period=pattern.period,
            lit=pattern.lit,
            floor=None if dark is None else 0.0,
            roi=(x0, y0, x1, y1),
            entry=pattern.entry,
            direction_deg=pattern.direction_deg,
        )
    except ValueError:
        return None  # stripes too faint to measure: nothing to compare
    sure = min(found.parts.get("phases", 0.0), found.parts.get("period", 0.0))
    if sure < _SURE_PHASES or list(found.phases) == list(pattern.phases):
        return None
    message = (
        f"{list(pattern.phases)} contradict the images, whose stripes are at phases "
        f"{list(found.phases)} (measured by the stripe detector, phase confidence "
        f"{found.parts['phases']:.2f}); correct them, or set pattern.phases: auto"
    )
    if phases_from == "default":
        return f"pattern.phases (absent: the default) {message}"
    top.fail("pattern.phases", message)


def _estimate_black_level(top, images, pattern: Stripes, mask, frames) -> BlackLevel:
    black, white = frames.get("black_frame"), frames.get("white_frame")
    tiles = sorted(p % pattern.period for p in pattern.phases) == list(range(pattern.period))
    try:
        return estimate_black_level(
            images,
            pattern.lit_fraction,
            tiles_period=tiles,
            mask=mask,
            entry=pattern.entry,
            direction_deg=pattern.direction_deg,
            black=None if black is None else _broadcast(black, images),
            white=None if white is None else _broadcast(white, images),
        )
    except ValueError as e:
        raise CaptureError(f"{top.source}: {e}") from None


def _broadcast(frame: np.ndarray, images: np.ndarray) -> np.ndarray:
    return np.broadcast_to(frame, images.shape[1:])


def _roi(top: _Section, width: int, height: int) -> tuple[int, int, int, int] | str | None:
    value = top.get("medium_roi", None)
    if value is None or value == AUTO:
        return value
    if (
        not isinstance(value, list)
        or len(value) != 4
        or any(isinstance(v, bool) or not isinstance(v, int) for v in value)
    ):
        top.fail(
            "medium_roi",
            f"must be a list of 4 integers [x0, y0, x1, y1] or 'auto', got {brief(value)}",
        )
    x0, y0, x1, y1 = value
    if not (0 <= x0 and x0 + 2 <= x1 <= width and 0 <= y0 and y0 + 2 <= y1 <= height):
        top.fail(
            "medium_roi",
            f"{value} does not fit the {width}x{height} image: need 0 <= x0, x0 + 2 <= x1 <= "
            f"{width}, 0 <= y0, y0 + 2 <= y1 <= {height} (x1, y1 exclusive)",
        )
    return (x0, y0, x1, y1)


def _positive(top: _Section, key: str) -> float | None:
    value = top.float(key, None)
    if value is not None and value <= 0:
        top.fail(key, f"must be > 0, got {brief(value)}")
    return value


def _geometry(top: _Section) -> dict[str, Any]:
    """The model geometry: ``{kind: plane}`` (default) or a slab (docs/model.md §7)."""
    if "geometry" not in top.data:
        return {"kind": "plane"}
    try:
        return parse_geometry(top.data["geometry"], top.key("geometry"), allow_auto=True).as_dict()
    except ValueError as err:
        raise top.error(f"{top.source}: {err}") from None


def _fit_options(top: _Section) -> dict[str, Any]:
    """The ``fit:`` mapping: FitOptions fields (:data:`FIT_KEYS`), each checked for its
    type, then together by FitOptions itself (ranges), before any image is read."""
    from lightfield_jax.forward.tail import TAIL_METHODS
    from lightfield_jax.inverse.options import FitOptions

    if "fit" not in top.data or top.data["fit"] is None:
        return {}
    s = top.section("fit", FIT_KEYS)
    out: dict[str, Any] = {}
    for k in s.data:
        value = s.data[k]
        if k in _FIT_INTS or k in _FIT_OPTIONAL_INTS:
            out[k] = s.int(k, None if k in _FIT_OPTIONAL_INTS else _REQUIRED)
        elif k in _FIT_FLOATS or k in _FIT_OPTIONAL_FLOATS:
            out[k] = s.float(k, None if k in _FIT_OPTIONAL_FLOATS else _REQUIRED)
        elif k in _FIT_BOOLS:
            if not isinstance(value, bool):
                s.fail(s.key(k), f"must be true or false, got {brief(value)}")
            out[k] = value
        elif k == "bounces":
            out[k] = AUTO if value == AUTO else s.int(k)
        elif k == "tail":
            out[k] = None if value is None else s.choice(k, (AUTO, *TAIL_METHODS))
        else:  # start: [sigma_s, g]
            if not (isinstance(value, list) and len(value) == 2):
                s.fail(s.key(k), f"must be [sigma_s, g], got {brief(value)}")
            out[k] = tuple(_as_float(s, s.key(k), v) for v in value)
    try:
        FitOptions(**out)
    except ValueError as err:
        s.fail("fit", str(err))
    return out


def _truth(top: _Section) -> dict[str, Any] | None:
    if "truth" not in top.data:
        return None
    s = top.section("truth", _TRUTH_KEYS)
    truth: dict[str, Any] = {k: s.float(k) for k in _TRUTH_FLOATS if k in s.data}
    if "phase" in s.data:
        truth["phase"] = s.choice("phase", PHASE_CONVENTIONS)
    return truth


def _nonfinite(
    raw: np.ndarray,
    frames: Sequence[tuple[ImageData, np.ndarray]],
    names: Sequence[str],
    notes: list[str],
) -> np.ndarray:
    """[H, W, C] True where an image or a calibration frame (dark, flat: each with its
    cropped pixels; a flat field is NaN where not positive) is NaN or Inf; notes the
    counts."""
    bad = ~np.isfinite(raw)
    counts = {n: int(c) for n, c in zip(names, bad.sum(axis=(1, 2, 3)), strict=True) if c}
    out = bad.any(axis=0)
    for image, pixels in frames:
        frame_bad = ~np.isfinite(pixels)
        if frame_bad.any():
            counts[image.path.name] = int(frame_bad.sum())
        out = out | np.broadcast_to(frame_bad, out.shape)
    if counts:
        listed = ", ".join(f"{n}: {c}" for n, c in counts.items())
        notes.append(
            f"{sum(counts.values())} pixel value(s) are NaN or Inf ({listed}); "
            f"{int(out.sum())} pixel(s) masked"
        )
    return out


def _saturated(
    raw: np.ndarray,
    frames: Sequence[ImageData],
    names: Sequence[str],
    saturation: float | None,
    sensor: tuple[float, int] | None,
    notes: list[str],
) -> np.ndarray:
    """[H, W, C] True where a raw image is saturated (>= saturation) or clipped (at the
    top code of an integer frame, or of the sensor's bits in a 16-bit file, when no
    saturation is given); notes what was found."""
    with np.errstate(invalid="ignore"):
        if saturation is not None:
            hit = raw >= saturation
        else:
            integer = np.array([f.is_integer for f in frames])[:, None, None, None]
            hit = integer & (raw >= (1.0 if sensor is None else sensor[0]))
    per_frame = hit.sum(axis=(1, 2, 3))
    finite = np.isfinite(raw).sum(axis=(1, 2, 3))
    full = [n for n, h, f in zip(names, per_frame, finite, strict=True) if f and h == f]
    if full:
        notes.append(f"every pixel is saturated in {', '.join(full)}")
    listed = ", ".join(f"{n}: {int(h)}" for n, h in zip(names, per_frame, strict=True) if h)
    out = hit.any(axis=0)
    if listed and saturation is not None:
        notes.append(
            f"pixel values at or above saturation {saturation:g} ({listed}); "
            f"{int(out.sum())} pixel(s) masked"
        )
    elif listed:
        bits = sorted({f.bit_depth for f, h in zip(frames, per_frame, strict=True) if h})
        codes = ", ".join(f"{(1 << b) - 1} ({b}-bit)" for b in bits)
        if sensor is not None:
            codes = f"{(1 << sensor[1]) - 1} ({sensor[1]}-bit data in 16-bit files)"
        notes.append(
            f"integer frames clipped at their top code {codes} ({listed}); "
            f"{int(out.sum())} pixel(s) masked (set saturation: to change the threshold)"
        )
    return out


# --------------------------------------------------------------------------- writing


def write_capture_yaml(
    path: str | os.PathLike,
    *,
    images: Sequence[str | os.PathLike] | str | os.PathLike,
    pattern: Stripes,
    dark_frame: str | os.PathLike | None = None,
    black_level: float | str | None = None,
    medium_roi: Sequence[int] | str | None = None,
    pixel_size_mm: float | None = None,
    saturation: float | None = None,
    channel: str | int | None = None,
    geometry: dict[str, Any] | None = None,
    truth: dict[str, Any] | None = None,
    black_frame: str | os.PathLike | None = None,
    white_frame: str | os.PathLike | None = None,
    flat_field: str | os.PathLike | None = None,
) -> Path:
    """Write a capture file (atomically); keys left ``None`` are omitted.

    ``images`` is a list of image files or one ``.npy`` stack, and ``dark_frame``,
    ``black_frame``, ``white_frame`` and ``flat_field`` files, all given relative to the
    capture file's folder. ``medium_roi`` and ``black_level`` may be ``"auto"``.
    """

    def plain(value):
        if isinstance(value, np.generic):
            return value.item()
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        if isinstance(value, os.PathLike):
            return os.fspath(value)
        return value

    data = {
        "images": images if isinstance(images, (str, os.PathLike)) else list(images),
        "pattern": {
            "period": pattern.period,
            "lit": pattern.lit,
            "phases": list(pattern.phases),
            "direction_deg": pattern.direction_deg,
            "entry": pattern.entry,
        },
        "dark_frame": dark_frame,
        "black_level": black_level,
        "medium_roi": medium_roi,
        "pixel_size_mm": pixel_size_mm,
        "saturation": saturation,
        "channel": channel,
        "geometry": geometry,
        "truth": truth,
        "black_frame": black_frame,
        "white_frame": white_frame,
        "flat_field": flat_field,
    }
    data = plain({k: v for k, v in data.items() if v is not None})
    text = yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=100)
    header = "# lightfield_jax capture file (format: lightfield_jax.capture.capture)\n"
    return atomic_write_text(path, header + text)


__all__ = [
    "CAPTURE_KEYS",
    "Capture",
    "CaptureWarning",
    "capture_files",
    "load_capture",
    "write_capture_yaml",
]
