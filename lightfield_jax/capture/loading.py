"""The capture format: shifted stripe images of a medium, and how they were taken.

A capture is a YAML file next to its images (``lightfield-jax simulate`` writes one for
stripe illumination, ``lightfield-jax pattern`` a template for a real camera; the
inverse pipeline reads it)::

    images: [shift_00.exr, shift_01.exr, shift_02.exr, shift_03.exr, shift_04.exr, shift_05.exr]
    pattern: {period: 6, lit: 3, phases: [0, 1, 2, 3, 4, 5], direction_deg: 0.0, entry: left}
    dark_frame: dark.exr         # optional
    dark_level: 0.03125          # optional, instead of dark_frame: a camera's pedestal
    black_frame: black.tif       # optional
    white_frame: white.tif       # optional
    flat_field: flat.tif         # optional
    black_level: 0.0             # optional (or auto)
    medium_roi: [x0, y0, x1, y1] # optional (or auto)
    pixel_size_mm: 0.05          # optional
    saturation: 0.98             # optional
    response: srgb               # optional: linear (default), srgb or a table file
    channel: all                 # optional
    geometry: {kind: plane}      # optional
    fit: {phase: normalized, n_theta: 64}   # optional: FitOptions fields
    truth: {sigma_t: 0.2051, sigma_s: 0.0366, g: 0.4, gain: 1.0, phase: paper}  # optional

Keys:

- ``images``: a list of image files (paths relative to the capture file's folder: for
  a symbolic link, the folder of the file it points to; OpenEXR, TIFF, PNG or
  ``.npy``, all the same size, channel count and sample format), one per phase; or one
  ``.npy`` stack of shape [P, H, W] or [P, H, W, C]. Integer samples are scaled to
  [0, 1] by their type's maximum (see :func:`~lightfield_jax.capture.io.read_image`).
  Camera files: 16-bit TIFF or PNG from a raw converter (linear, demosaiced), or float
  EXR from an HDR merge. Refused with a clear error: images of different sample
  formats (8- and 16-bit, integer and float), 1-channel images that are an
  undemosaiced Bayer mosaic, 4-channel images that are not RGB with a constant alpha
  (a constant alpha channel is dropped), files of several images (a multi-page TIFF,
  a multi-part EXR), signed or 32-bit integer samples (a TIFF or a ``.npy``: save
  the counts as uint16 or float32). 16-bit files that hold 10-, 12- or 14-bit data
  clipped at its top code (4095 for 12 bits) have those pixels masked as saturated.
  See :mod:`lightfield_jax.capture.calibration`.
- ``images`` as exposure brackets, one list per shift (``[[s0_1ms.png, s0_8ms.png],
  [s1_1ms.png, s1_8ms.png], ...]``), with ``exposure_times`` (seconds, increasing, the
  order of every list) and ``response`` (``linear``, default; ``srgb``; ``auto``:
  recovered from the brackets; or a table file): each bracket is merged to linear radiance
  (:mod:`lightfield_jax.capture.hdr`), clipped and near-black samples dropped; a calibration
  frame is then a list of one file per exposure time too, and the dark frame is
  subtracted from every exposure before the merge. ``saturation`` is then the sample
  value at which a sample counts as clipped (default 0.98). The merged noise goes to the
  joint fit (``Capture.exposure``); ``Capture.brackets`` says what the merge did.
- ``response`` with one exposure per shift: ``linear`` (default; a raw converter's
  output), ``srgb`` (the sRGB curve of most 8-bit camera and phone files) or a table
  file (:func:`~lightfield_jax.capture.response.load_response`, as ``lightfield-jax inspect
  --response`` writes it from brackets; columns named in its header are taken by name,
  also for one ``channel:`` chosen from them): the integer codes of the images and
  calibration frames are mapped to linear values before the dark frame and the flat
  field are applied; float calibration frames (an EXR flat field) are linear already,
  and float images with a curve are refused; saturation and clipping are judged on the
  codes.
- ``pattern``: the projected stripes (docs/model.md section 3): ``period`` (default 6),
  ``lit`` (default 3), ``phases`` (one per image, default 0..P−1), ``direction_deg``
  (default: the entry wall's inward normal), ``entry`` (left, right, top, bottom;
  default left). Image row r (column, for the top and bottom walls) is lit in an image
  of phase φ iff (r + φ) mod period < lit, counted in the full image frame; with a
  ``medium_roi`` the loaded pattern's phases are shifted to count from the ROI's edge.
- ``dark_frame``: an image taken with the projector off, subtracted from every image
  (and from the other calibration frames) first (after a ``response``'s linearisation).
- ``dark_level``: instead of a dark frame, the camera's constant black offset (its
  pedestal), in image values after integer scaling (as ``saturation``: a pedestal of
  2048 codes in 16-bit files is 2048/65535 = 0.03125), subtracted like a dark frame of
  that value; linear images only. One value, or one per channel by name
  (``dark_level: {R: 0.0312, G: 0.0310, B: 0.0316}``, every channel loaded: with
  ``channel: G``, ``{G: 0.0310}``). A
  pedestal left in the images is light the model does not have: the joint fit then
  stops or ends far above the noise and says so, with the offset it measures.
- ``black_frame``, ``white_frame``: the camera's images of the projector showing all
  black and all white. The black frame measures the black level (``black_level:
  auto``); the white frame, if given, is where the medium's ROI is found.
- ``flat_field``: an image of a uniformly lit white target (the camera's vignetting),
  taken with the images' settings; the dark frame is subtracted from it, it is divided
  by its median, and every image is divided by it. Pixels where it is not positive
  are masked.
  Calibration frames (dark, black, white, flat) have the images' size and one channel
  or as many as the images; an integer dark, black or white frame has the images'
  integer format (with float images: a float frame).
- ``black_level``: b in [0, 1): a dark stripe emits b times a lit one (docs/model.md
  section 5). Absent: unknown (a joint fit may estimate it).
- ``medium_roi``: [x0, y0, x1, y1] in pixels, x1 and y1 exclusive: the medium's
  rectangle. Images are cropped to it and its edges are the medium's walls.
- ``pixel_size_mm``: pixel pitch in mm (> 0), to report coefficients in mm⁻¹.
- ``saturation``: image value (after integer scaling: at most 1 for integer images) at
  or above which a raw pixel is saturated and masked. Absent: integer frames mask
  pixels at their top code (255 or 65535, i.e. 1.0, or a 16-bit file's sensor top
  code, see ``images``), float frames mask nothing.
- ``channel``: which channel to use: a name (R, G, B, Y, ...), an index, or ``all``
  (default: every channel, fitted separately; matched by name across files; channels
  equal in every file load as one, ``Y``).
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
  ``extrapolate``, ``stripe_cell``,
  ``max_chi2`` ...; see ``help(lfj.FitOptions)``), used by ``lightfield-jax fit`` and
  :func:`~lightfield_jax.fit_capture`; ``phase``: the model's phase convention,
  ``normalized`` (energy-conserving, for every medium) where absent, or ``paper``
  (the paper's own; no answer for forward media of high albedo such as milk). The
  method is the command's option, the geometry the key above.
- ``truth``: the true parameters of a simulated capture (``sigma_t``, ``sigma_s``,
  ``g``, ``gain``, ``phase``, ``black_level``), for reports; for several channels each
  value may be a list of one per channel, or ``truth`` a list of one mapping per
  channel.

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
before any pixel is read (:mod:`lightfield_jax.runtime.memory`); images without light (every
value zero or negative, or darker than the dark frame) are refused; in a capture whose
images show stripes of the period, an image without them (a white or black frame
listed among the stripes) is refused, and given phases that the stripe detector
contradicts with confidence (the period within 2 %, every phase within 0.1 row) are
refused with both lists (absent phases, whose default is contradicted, get a note).
Pixels that cannot be used (NaN or Inf in an image, the dark frame or the flat field;
zero or negative in the flat field; saturated or clipped) are masked, with a
:class:`CaptureWarning` that counts them (an image of nothing but NaN or Inf is refused).
"""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path

import numpy as np

from lightfield_jax.capture.auto import (
    check_light,
    check_stripes,
    detect_capture_geometry,
    estimate_capture_black_level,
)
from lightfield_jax.capture.brackets import read_brackets, read_response
from lightfield_jax.capture.calibration import (
    check_not_mosaic,
    check_sample_formats,
    drop_constant_alpha,
    sensor_top_code,
)
from lightfield_jax.capture.capture import (
    MIN_SIDE,
    Capture,
    CaptureWarning,
)
from lightfield_jax.capture.detect import LOW_CONFIDENCE
from lightfield_jax.capture.frames import (
    check_not_blank,
    check_projector_frames,
    images_listed_twice,
    read_calibration_frames,
    read_frames,
)
from lightfield_jax.capture.io import CaptureError, CaptureFileNotFoundError
from lightfield_jax.capture.keys import (
    AUTO,
    CAPTURE_KEYS,
    check_integer_saturation,
    crop_pattern,
    dark_level_text,
    pixel_size_problem,
    read_black_level,
    read_channel,
    read_dark_level,
    read_fit_options,
    read_geometry,
    read_pattern_spec,
    read_positive,
    read_roi,
    read_stripes,
    read_truth,
)
from lightfield_jax.capture.keys import FIT_KEYS as FIT_KEYS
from lightfield_jax.capture.keys import GEOMETRY_KINDS as GEOMETRY_KINDS
from lightfield_jax.capture.paths import capture_folder, check_link_folder, listed_files
from lightfield_jax.capture.pixels import (
    calibrate,
    corrupt_to_nan,
    floored_mask,
    inf_to_nan,
    nonfinite_mask,
    normalized_flat,
    saturated_mask,
)
from lightfield_jax.capture.response import frame_linearizer
from lightfield_jax.inverse.noise import MIN_ALONG
from lightfield_jax.schema import Section, load_yaml


def load_capture(path: str | os.PathLike) -> Capture:
    """Read and validate a capture file: its images, calibration frames and keys,
    measured where they say ``auto``; returns a :class:`Capture` (images dark-subtracted,
    linear, cropped to the medium) for :func:`~lightfield_jax.fit_capture`. Every key of
    the file is described below.

    Raises:
        CaptureFileNotFoundError: the capture file or an image does not exist.
        CaptureError: anything else that makes the capture unusable; the message
            starts with the capture file and names the key, value or image.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise CaptureError(f"load_capture: expected a capture file's path, got {path!r}")
    path = Path(path)
    if not path.exists():
        raise CaptureFileNotFoundError(f"{path}: file not found")
    top = Section(
        str(path),
        "",
        load_yaml(path, CaptureError, CaptureFileNotFoundError),
        CAPTURE_KEYS,
        error=CaptureError,
    )
    base = capture_folder(path)  # after links: where the file was written, beside its images
    check_link_folder(path, listed_files(top.data), CaptureError)
    channel = read_channel(top)
    fit_options = read_fit_options(top)  # before any image is read
    notes: list[str] = []  # what was measured or decided: Capture.notes
    issues: list[str] = []  # what the user must know: CaptureWarnings
    merged = read_brackets(top, base, channel, notes)
    frames = read_frames(top, base, channel) if merged is None else merged[0]
    try:
        frames = drop_constant_alpha(frames, notes)
    except CaptureError as e:
        raise CaptureError(f"{top.source}: images: {e}") from None
    height, width, _ = frames[0].pixels.shape
    spec = read_pattern_spec(top, len(frames), height, width)
    if merged is None:
        frames, aux = read_calibration_frames(top, base, channel, frames, notes)
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
    check_projector_frames(top, aux, merged is not None)
    roi = read_roi(top, width, height)
    black_level = read_black_level(top)
    pixel_size = read_positive(top, "pixel_size_mm")
    if (problem := pixel_size_problem(pixel_size)) is not None:
        top.fail("pixel_size_mm", problem)
    saturation = read_positive(top, "saturation") if merged is None else None
    check_integer_saturation(top, saturation, frames[0])
    geometry = read_geometry(top)
    truth = read_truth(top, frames[0].pixels.shape[2])  # after a grey image's merge

    names = [f.path.name for f in frames]
    if len(set(f.path for f in frames)) == 1 and len(frames) > 1:
        names = [f"{frames[0].path.name}[{i}]" for i in range(len(frames))]
    raw = np.stack([f.pixels for f in frames])
    if merged is None:  # (brackets: each exposure, by read_brackets)
        check_not_blank(top, [("images", name, raw[i]) for i, name in enumerate(names)])
    raw = inf_to_nan(corrupt_to_nan(raw, names, issues))
    response = None if merged is not None else read_response(top, base, frames[0].channel_names)
    sensor = None if saturation is not None else sensor_top_code(raw, frames)
    # 10-14-bit data in 16-bit files: codes counted to the sensor's top code, as the
    # brackets' merge (and the response tables it writes) counts them.
    top_code = 1.0 if sensor is None else sensor[0]
    linear = frame_linearizer(top, response, frames, names, top_code)

    def in_linear(frame):
        """A calibration frame's values: integer codes mapped by the response; float
        frames (an EXR flat field normalised to 1, a float dark) are linear already."""
        if frame is None:
            return None
        return linear(frame.pixels) if linear is not None and frame.is_integer else frame.pixels

    aux_linear = {k: inf_to_nan(in_linear(f)) for k, f in aux.items()}
    if frames[0].is_integer and frames[0].bit_depth == 8:
        notes.append(
            "8-bit images: 256 levels quantise the light's decay; prefer 16-bit linear output"
            + (
                " (cameras usually write 8-bit files sRGB-encoded: give response: srgb if "
                "these are)"
                if "response" not in top.data and merged is None
                else ""
            )
        )
    if linear is not None:
        notes.append(
            f"response: {top.get('response')}: the codes of the images and calibration "
            "frames linearised with it (before a dark frame or flat field is applied)"
        )
    dark = aux["dark_frame"]
    dark_pixels = aux_linear["dark_frame"]
    bits = frames[0].bit_depth if frames[0].is_integer else None  # a merged frame: float
    channels = tuple(frames[0].channel_names)
    dark_level = read_dark_level(top, bits, str(top.get("response", "linear")), channels)
    if dark_level is not None and merged is None:  # brackets: the merge subtracted it
        dark_pixels = np.full(raw.shape[1:], dark_level, raw.dtype)  # per channel: last axis
        notes.append(f"dark_level: {dark_level_text(dark_level)} subtracted from every image")
    dark_removed = (
        dark is not None
        or dark_level is not None
        or bool(merged and top.get("dark_frame", None) is not None)
    )
    flat_pixels = normalized_flat(
        top, aux["flat_field"], dark_pixels, issues, aux_linear["flat_field"]
    )

    calibrated = calibrate(raw, dark_pixels, flat_pixels, linear)
    overview = np.mean(calibrated, axis=0)
    check_light(top, calibrated, dark, dark_level)
    detected = None
    if AUTO in (roi, spec["phases"], spec["entry"], spec["direction_deg"]):
        white = aux["white_frame"]
        detected = detect_capture_geometry(
            top,
            spec,
            roi,
            calibrated,
            None
            if white is None
            else calibrate(aux_linear["white_frame"], dark_pixels, flat_pixels),
            dark_subtracted=dark_removed,
        )
        notes.append("detected: " + detected.summary().replace("\n", "; "))
        if detected.confidence < LOW_CONFIDENCE:
            issues.append(
                f"the detected geometry has a low confidence {detected.confidence:.2f} "
                f"({detected.summary().splitlines()[-1]}): check it with lightfield-jax "
                "inspect, or give the values"
            )
        roi = detected.roi if roi == AUTO else roi
    pattern = read_stripes(top, spec, detected)

    calibration_frames = {k: v for k, v in aux_linear.items() if v is not None}
    full_roi, full_pattern = roi, pattern
    if roi is not None:
        x0, y0, x1, y1 = roi
        raw = raw[:, y0:y1, x0:x1]
        calibration_frames = {k: v[y0:y1, x0:x1] for k, v in calibration_frames.items()}
        dark_pixels = None if dark_pixels is None else dark_pixels[y0:y1, x0:x1]
        if flat_pixels is not None:
            flat_pixels = flat_pixels[y0:y1, x0:x1]
        pattern = crop_pattern(pattern, x0, y0)
    if min(raw.shape[1:3]) < MIN_SIDE:
        top.fail(
            "images" if roi is None else "medium_roi",
            f"the medium is {raw.shape[2]}x{raw.shape[1]} px: at least {MIN_SIDE}x{MIN_SIDE} "
            f"px are needed (a fit: {MIN_ALONG} along the light)",
        )
    checked = [(dark, dark_pixels, dark_pixels)] if dark is not None else []
    if flat_pixels is not None:
        checked.append((aux["flat_field"], flat_pixels, calibration_frames["flat_field"]))
    first_mask_issue = len(issues)
    nonfinite = nonfinite_mask(raw, checked, names, issues)
    saturated = saturated_mask(raw, frames, names, saturation, sensor, issues, merged is None)
    saturated &= ~nonfinite
    exposure = None
    if merged is not None:
        x0, y0, x1, y1 = roi or (0, 0, width, height)
        clipped = brackets.clipped_shifts[:, y0:y1, x0:x1] & ~nonfinite
        saturated |= clipped
        whole = [i for i in range(len(frames)) if np.all(clipped[i] | nonfinite[i])]
        if whole:
            issues.append(
                "every pixel is clipped in every exposure of "
                + ", ".join(f"images[{i}] ({names[i]})" for i in whole)
                + ": take shorter exposures"
            )
        exposure = brackets.exposure[:, y0:y1, x0:x1]
        notes.append(brackets.summary())
    samples = ~(nonfinite | saturated)
    mask = np.all(samples, axis=0)
    if not mask.any():  # an error, not warnings and then an error: the cause goes with it
        masked = issues[first_mask_issue:]
        cause = f" ({masked[0]})" if masked else ""
        top.fail(
            "images",
            f"no usable pixel: every pixel is non-finite or saturated in some image{cause}",
        )
    phases_from = "auto" if spec["phases"] == AUTO else spec["phases_from"]
    auto = [k for k in ("entry", "direction_deg") if spec[k] == AUTO]
    contradiction = check_stripes(
        top, full_pattern, calibrated, full_roi, names, phases_from, dark_removed, auto, notes,
        (frames, aux),
    )  # fmt: skip
    if contradiction:
        notes.append(contradiction)
    # After the pattern's checks: a refusal there is the one line said (not a warning of
    # the detector's low confidence for a wrong period first).
    for issue in issues:
        warnings.warn(f"{path}: {issue}", CaptureWarning, stacklevel=2)
    # After the phases' checks, which refuse a repeated image where phases are given
    # (a copy's pixels are compared where the phases are not given: measured or the
    # default, where a copy only makes the measured phases differ, a note).
    copies = frames if phases_from != "given" else ()
    if (again := images_listed_twice(top, base, copies, names)) is not None:
        issues.append(again)
        warnings.warn(f"{path}: {again}", CaptureWarning, stacklevel=2)
    del calibrated
    images = calibrate(raw, dark_pixels, flat_pixels, linear)
    images = np.where(np.isfinite(images), images, 0).astype(raw.dtype)
    floored = floored_mask(raw, samples, frames, names, notes, images, pattern)

    estimate = None
    if black_level == AUTO:
        frames_used = {
            k: calibrate(calibration_frames[k], dark_pixels, flat_pixels)
            for k in ("black_frame", "white_frame")
            if k in calibration_frames
        }
        estimate = estimate_capture_black_level(top, images, pattern, mask, frames_used)
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
        sample_mask=samples,
        clipped=saturated,
        floored=floored,
        black_level=black_level,
        roi=roi,
        pixel_size_mm=pixel_size,
        saturation=saturation,
        source=path,
        image_paths=tuple(f.path for f in frames),
        dark_frame=None if dark is None else dark.path,
        dark_level=dark_level,
        n_masked={
            "nonfinite": int(nonfinite.any(axis=0).sum()),
            "saturated": int((saturated.any(axis=0) & ~nonfinite.any(axis=0)).sum()),
            "total": int((~mask).sum()),
            "values": int((~samples).sum()),
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
        response=response,
    )


if load_capture.__doc__ and __doc__:  # None under python -OO
    # help(lfj.load_capture) is where a user looks for the file's keys.
    import inspect as _inspect

    load_capture.__doc__ = (
        _inspect.cleandoc(load_capture.__doc__) + "\n\nThe capture file\n\n" + __doc__
    )


__all__ = [
    "load_capture",
]
