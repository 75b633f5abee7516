"""What loading measures from the images: the ``auto`` values (geometry detection, the
black level), and the checks that the images agree with the capture file (light, stripes)."""

from __future__ import annotations

import math

import numpy as np

from lightfield_jax.capture.calibration import BlackLevel, estimate_black_level
from lightfield_jax.capture.detect import LOW_CONFIDENCE, Geometry, detect_geometry
from lightfield_jax.capture.io import CaptureError, ImageData
from lightfield_jax.capture.keys import AUTO, dark_level_text
from lightfield_jax.capture.stripe_phase import (
    ACROSS,
    STRIPED,
    across_first,
    period_contradiction,
    stripe_coefficients,
)
from lightfield_jax.scene.illumination import Stripes, unseparated_rows
from lightfield_jax.schema import Section


def detect_capture_geometry(top, spec, roi, images, white, *, dark_subtracted: bool) -> Geometry:
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


# A dark_level above the camera's pedestal pushes the dark values below zero by more
# than their noise: refused where more than DARK_BELOW of the image values lie below
# −DARK_DEPTH × the brightest values (their 99th percentile); a right level leaves only
# the dark pixels' noise below zero.
DARK_BELOW, DARK_DEPTH = 0.05, 0.05


def check_light(
    top: Section,
    images: np.ndarray,
    dark: ImageData | None,
    dark_level: float | np.ndarray | None = None,
) -> None:
    """Refuse images without light: no value above zero (every value zero, or negative
    images), or, with a dark frame, images darker than it (99 % of the values after
    subtracting it below zero by more than 10⁻³ of the dark level: past quantisation),
    or, with a ``dark_level``, one above the pedestal (see :data:`DARK_BELOW`)."""
    finite = images[np.isfinite(images)]
    if finite.size == 0:
        return  # every value non-finite: the mask's check says so
    brightest = float(finite.max())
    if dark_level is not None:
        bright = float(np.percentile(finite, 99))
        below = float(np.mean(finite < -DARK_DEPTH * max(bright, 0.0)))
        if bright <= 0 or below > DARK_BELOW:
            top.fail(
                "dark_level",
                f"{dark_level_text(dark_level)} is above the camera's pedestal: after "
                "subtracting it, "
                f"{below:.0%} of the image values lie below zero by more than "
                f"{DARK_DEPTH:.0%} of the bright ones (their 99th percentile "
                f"{bright:.3g}); give it in image values (a 16-bit file's pedestal of C "
                "codes is C/65535), at or below the darkest pixels",
            )
        return
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


# An image whose stripe amplitude is below _UNSTRIPED times the median image's, in a
# capture with stripes (detect.STRIPED), is not a stripe image (a white or black frame
# listed among them: measured 0.003).
_UNSTRIPED = 0.1
# Declared phases are compared with measured ones only when the detector is sure of
# them: the stripes' period found within 2 % and every phase within 0.1 row of an
# integer (noise images reach neither).
_SURE_PHASES = 0.8


def check_stripes(
    top,
    pattern,
    images,
    roi,
    names,
    phases_from: str,
    dark_removed: bool,
    auto=(),
    notes=None,
    frames=None,
) -> str | None:
    """Refuse a capture whose images contradict its pattern: an image without stripes
    of the period in a capture that has them, or given phases that differ from those
    the stripe detector (:func:`~lightfield_jax.capture.detect.detect_geometry`) measures
    with confidence. Default phases (``pattern.phases`` absent) that differ are
    returned as a note's text instead. ``images`` and ``roi``: the full frame's;
    ``phases_from``: ``given``, ``default`` or ``auto``; ``auto``: the pattern keys
    measured (see :func:`_check_geometry_seen`, run after the period's check);
    ``frames``: ``(stripe images, calibration frames)``, the files as read (a list of
    ``ImageData``; ``{key: ImageData or None}``): a calibration frame that shows the
    stripes is refused (:func:`_check_frames_unstriped`)."""
    x0, y0, x1, y1 = roi if roi is not None else (0, 0, images.shape[2], images.shape[1])
    crop = np.where(np.isfinite(images), images, 0.0).sum(axis=-1)[:, y0:y1, x0:x1]
    stack = across_first(crop, pattern.entry)
    u0 = y0 if pattern.along_x else x0

    def amplitude(period):
        return np.abs(stripe_coefficients(stack, u0, 1.0 / period)).sum(axis=-1)

    if frames is not None:
        _check_frames_unstriped(top, *frames, (x0, y0, x1, y1), pattern, u0)
    if notes is not None and (
        rows := unseparated_rows(pattern.period, pattern.lit, pattern.phases)
    ):
        notes.append(
            f"pattern.phases {list(pattern.phases)} leave {rows} (period "
            f"{pattern.period}, lit {pattern.lit}): the direct light is not separated "
            "there (the SNR inspect measures of it is not the capture's); the joint fit "
            "models the raw images and takes them, the two-step methods (gradient, grid) "
            "need each row lit in one shift and dark in another"
        )
    _check_period(top, pattern, stack, u0)
    if len(names) >= 2:
        _check_geometry_seen(top, pattern, images, roi, dark_removed, auto, notes)
    stripes = amplitude(pattern.period)
    with np.errstate(divide="ignore", invalid="ignore"):
        contrast = np.median(stripes / amplitude(1.5 * pattern.period))
        relative = stripes / np.median(stripes)
    if not contrast >= STRIPED:
        _check_light_alike(top, stack, u0, pattern, names)
        return None  # no stripes to compare with
    for name, r in zip(names, relative, strict=True):
        if not r >= _UNSTRIPED:
            top.fail(
                "images",
                f"{name} shows no stripes of period {pattern.period} (stripe amplitude "
                f"{r:.2g} times the other images'): a white or black frame listed as a "
                "stripe image? (give it as white_frame or black_frame)",
            )
    _check_light_alike(top, stack, u0, pattern, names)
    if phases_from == "auto" or len(names) < 2:
        return None
    found = _measured(images, pattern, (x0, y0, x1, y1), dark_removed, pattern.direction_deg)
    message = _phases_contradicted(found, pattern)
    if message is None:
        return None
    message += ", or set pattern.phases: auto"
    if phases_from == "default":
        return f"pattern.phases (absent: the default) {message}"
    top.fail("pattern.phases", message)


# Shifts of one stripe pattern light the medium alike: the light summed over it differs
# between them by 1 % (renders of 32x24 media, period 6), 5 % (oblique at 20 deg), up
# to 2x where the shifts light 1 or 2 of the rows across a narrow medium. An image
# whose sum is off the shifts' median by more than LIGHT_OFF times the ratio of the
# most to the fewest rows a shift lights is refused: one taken at another exposure or
# gain (a camera's auto exposure), or with an offset left in or taken out twice.
LIGHT_OFF = 1.5


def light_contradiction(stack, u0: int, pattern: Stripes, valid=None) -> tuple[int, str] | None:
    """``(index, what to say)`` of the image of a (P, across, along) stack
    (:func:`~lightfield_jax.capture.stripe_phase.across_first` of dark-subtracted
    images, non-finite values 0; the first row across at ``u0``) whose light summed
    over the pixels ``valid`` (booleans (across, along): in every shift; ``None``: all)
    is off the shifts' median (see :data:`LIGHT_OFF`); ``None`` where none is, or with
    fewer than 3 images (two cannot say which one is off)."""
    if stack.shape[0] < 3:
        return None
    rows = u0 + np.arange(stack.shape[1])
    lit = [int(np.sum((rows + p) % pattern.period < pattern.lit)) for p in pattern.phases]
    if min(lit) < 1:
        return None  # a shift lighting no row of the medium: no sum to compare
    kept = stack if valid is None else np.where(valid, stack, 0.0)
    sums = kept.sum(axis=(1, 2), dtype=np.float64)
    median = float(np.median(sums))
    if not median > 0:
        return None
    ratio = sums / median
    tolerance = LIGHT_OFF * max(lit) / min(lit)
    off = np.abs(np.log(np.where(ratio > 0, ratio, 1e-300)))  # no light: the farthest off
    worst = int(np.argmax(off))
    if off[worst] <= math.log(tolerance):
        return None
    held = (
        f"{ratio[worst]:.3g} times the light of the shifts' median (summed over the "
        f"medium; {tolerance:.2g}x tolerated)"
        if ratio[worst] > 0
        else "no light: its values summed over the medium are at or below 0, the shifts' "
        "median above"
    )
    return worst, (
        f"holds {held}: every shift needs the same exposure and gain (the camera's auto "
        "exposure on?) and the same dark frame or offset subtracted"
    )


def pattern_contradiction(images, pattern: Stripes, valid=None) -> tuple[str, str] | None:
    """``(key, what to say after it)`` where the stripes of ``images`` (``(P, H, W)``,
    cropped to the medium, dark frame subtracted) contradict ``pattern``'s entry wall,
    heading or phases (judged as a capture file's are, :func:`_check_geometry_seen`,
    :func:`check_stripes`: only where the stripe detector is sure of what it measures),
    or its shifts lighting the medium alike (:func:`light_contradiction`); ``None``
    where they agree or the stripes are too faint to measure. ``valid``
    (booleans like ``images``): the values to trust; each image's lines along the light
    holding another are left out (a mask's zeros bend the measured heading).
    ``fit_images``' check: unchecked, a heading 30 deg off fits σt 15 % low, phases one
    shift off σs 27 % high, and images transposed (light entering the top, declared
    left) give a decay start of σt 0, without a word."""
    if len(pattern.phases) < 2:
        return None
    height, width = np.shape(images)[1:3]
    roi = (0, 0, width, height)
    seen = _measured(images, pattern, roi, True, None, entry=False, valid=valid)
    if seen is not None and seen.parts.get("period", 0.0) >= _SURE_PHASES:
        # The wall opposite is fit_images' own check (the direct light's growth).
        crossed = ACROSS[seen.entry] != ACROSS[pattern.entry]
        if crossed and _sure(seen, "orientation"):
            return "pattern.entry", f"{_entry_off(seen, pattern)}; correct it (and direction_deg)"
        if seen.entry == pattern.entry and (problem := _heading_off(seen, pattern)):
            return "pattern.direction_deg", problem
    found = _measured(images, pattern, roi, True, pattern.direction_deg, valid=valid)
    if (problem := _phases_contradicted(found, pattern)) is not None:
        return "pattern.phases", problem
    every = None if valid is None else across_first(np.all(valid, axis=0), pattern.entry)
    stack = across_first(np.where(np.isfinite(images), images, 0.0), pattern.entry)
    if (off := light_contradiction(stack, 0, pattern, every)) is not None:
        return "images", f"images[{off[0]}] {off[1]}"
    return None


def _phases_contradicted(found: Geometry | None, pattern: Stripes) -> str | None:
    """The message (up to its advice) where the detector's ``found`` stripes are sure
    of other phases than ``pattern``'s; ``None`` where they agree, or the stripes are
    too faint to measure (``found`` ``None``) or to be sure of."""
    if found is None:
        return None
    sure = min(found.parts.get("phases", 0.0), found.parts.get("period", 0.0))
    if sure < _SURE_PHASES or list(found.phases) == list(pattern.phases):
        return None
    return (
        f"{list(pattern.phases)} contradict the images, whose stripes are at phases "
        f"{list(found.phases)} (measured by the stripe detector, phase confidence "
        f"{found.parts['phases']:.2f}); correct them"
    )


# A given entry wall, direction or lit width is compared with what the stripe detector
# measures (every part measured: the wall, the heading, the lit width next to the wall)
# only where it is sure of the stripes (their period found within 2 %, _SURE_PHASES:
# noise can fit a heading too; a capture whose stripes are not seen got a heading of
# 71 deg ± 0.01 with confidence 0.62). A given entry wall contradicts the images where
# the detector finds the light entering another wall with the entry and orientation
# parts of its confidence at least GEOMETRY_SURE (the detector's own LOW_CONFIDENCE:
# below it a detection deserves a look, not a verdict).
GEOMETRY_SURE = LOW_CONFIDENCE
# A given direction contradicts the images where the stripes' measured heading differs
# from it by more than DIRECTION_OFF degrees and DIRECTION_SIGMAS standard errors, the
# heading measured with a direction confidence of at least GEOMETRY_SURE. The detector
# is accurate to 0.09 deg on renders (rms 0.04; its standard error, 0.005-0.05 deg, is
# the statistical part only, and a dense oblique medium measures 0.21 deg off):
# 2 deg leaves that bias and a real capture's lens distortion and keystone room, while a
# stripe tilt the fit cannot absorb (4 deg: not identifiable after 30 s) is refused.
DIRECTION_OFF, DIRECTION_SIGMAS = 2.0, 5.0
# A given lit width contradicts the images where the stripes' lit width measured next to
# the entry wall (Geometry.lit_px: rows above the local midpoint, per period) differs
# from it by more than LIT_OFF rows: another integer width differs by 1 or more, and a
# renders' measure is within 0.15 row (partial pixels of oblique stripes).
LIT_OFF = 0.6


# A calibration frame (dark, black, white, flat) shows no projected stripes: one whose
# stripe contrast (its Fourier amplitude at the period over its total, against that at
# 1.5 times the period: STRIPED) is clear and at least FRAME_STRIPED of the stripe
# images' is a stripe image listed in its place (a copy of one: 1.0; a dark frame's
# noise has no contrast at the period).
FRAME_STRIPED = 0.25


def _stripe_share(frame, roi, pattern: Stripes, u0: int, period: float) -> float:
    """A file's stripes (channels summed, inside ``roi``): their Fourier amplitude at
    ``period`` over the sum of the absolute values."""
    x0, y0, x1, y1 = roi
    pixels = frame.pixels[y0:y1, x0:x1]
    pixels = np.where(np.isfinite(pixels), pixels, 0.0).sum(axis=-1, dtype=np.float64)
    one = across_first(pixels[None], pattern.entry)
    amplitude = float(np.abs(stripe_coefficients(one, u0, 1.0 / period)).sum())
    return amplitude / max(float(np.abs(one).sum()), np.finfo(float).tiny)


def _check_frames_unstriped(top, images, frames, roi, pattern: Stripes, u0: int) -> None:
    period = pattern.period
    shares = [_stripe_share(f, roi, pattern, u0, period) for f in images]
    reference = float(np.median(shares))
    for key, frame in frames.items():
        if frame is None:
            continue
        share = _stripe_share(frame, roi, pattern, u0, period)
        elsewhere = _stripe_share(frame, roi, pattern, u0, 1.5 * period)
        if share >= STRIPED * elsewhere and share >= FRAME_STRIPED * reference > 0:
            top.fail(
                key,
                f"{frame.path.name} shows the stripes of period {period} ({share / reference:.2g} "
                "times the stripe images' contrast): a stripe image listed as the "
                f"{key.replace('_', ' ')}? (it is taken without stripes)",
            )


def _check_light_alike(top, stack, u0: int, pattern: Stripes, names) -> None:
    if (problem := light_contradiction(stack, u0, pattern)) is not None:
        top.fail("images", f"{names[problem[0]]} {problem[1]}")


def _check_period(top, pattern: Stripes, stack, u0: int) -> None:
    """Refuse a ``pattern.period`` the images' stripes do not have, where they show
    clear stripes of another period (:func:`~lightfield_jax.capture.stripe_phase.other_period`)."""
    if (problem := period_contradiction(stack, u0, pattern.period, pattern.entry)) is not None:
        top.fail("pattern.period", problem)


def _measured(
    images, pattern: Stripes, roi, dark_removed: bool, direction_deg, entry=True, valid=None
) -> Geometry | None:
    """What the stripe detector measures in the full-frame ``images`` inside ``roi``
    (``None``: the lit region it finds), for the pattern's period, lit rows and entry
    wall (``entry`` ``None``: measured) and ``direction_deg`` (given, or ``None``:
    measured); ``None`` where the stripes are too faint to measure."""
    try:
        return detect_geometry(
            images,
            period=pattern.period,
            lit=pattern.lit,
            floor=0.0 if dark_removed else None,
            roi=roi,
            entry=pattern.entry if entry else None,
            direction_deg=direction_deg,
            valid=valid,
        )
    except ValueError:
        return None


def _entry_off(found: Geometry, pattern: Stripes) -> str:
    return (
        f"{pattern.entry} contradicts the images, whose light enters through the "
        f"{found.entry} wall heading {found.direction_deg:.1f} deg (measured by the "
        f"stripe detector, confidence {found.confidence:.2f})"
    )


def _heading_off(found: Geometry, pattern: Stripes) -> str | None:
    """What to say of ``pattern.direction_deg`` (after its key, up to the advice) where
    the heading ``found`` is sure of differs from it (see DIRECTION_OFF); else ``None``."""
    off = abs((found.direction_deg - pattern.direction_deg + 180.0) % 360.0 - 180.0)
    tolerance = max(DIRECTION_OFF, DIRECTION_SIGMAS * found.direction_stderr_deg)
    if not (_sure(found, "direction") and off > tolerance):
        return None
    return (
        f"{pattern.direction_deg:g} contradicts the images, whose stripes run at "
        f"{found.direction_deg:.2f} ± {found.direction_stderr_deg:.2f} deg from the "
        f"{pattern.entry} wall (measured by the stripe detector; {tolerance:.1f} deg "
        "tolerated); correct it"
    )


def _sure(found: Geometry, *parts: str) -> bool:
    return all(found.parts.get(p, 1.0) >= GEOMETRY_SURE for p in parts)


def _check_geometry_seen(
    top, pattern: Stripes, images, roi, dark_removed: bool, auto, notes=None
) -> None:
    """Refuse a ``pattern.entry`` or ``pattern.direction_deg`` the stripes in the images
    contradict, where the stripe detector is sure of what it measures (see
    GEOMETRY_SURE); a ``pattern.lit`` they seem to contradict is a note (appended to
    ``notes``): the measured width moves by a row or two with the stripes' offset from
    the pixel grid and the camera's blur. ``roi``: the capture's (``None``: the whole
    frame, where the detector looks for the lit region itself); ``auto``: the keys
    measured."""
    found = _measured(images, pattern, roi, dark_removed, None, entry=False)
    if found is None or found.parts.get("period", 0.0) < _SURE_PHASES:
        return  # stripes too faint to measure: nothing to compare
    if found.entry != pattern.entry:
        if "entry" not in auto and _sure(found, "entry", "orientation", "roi"):
            top.fail(
                "pattern.entry",
                f"{_entry_off(found, pattern)}; correct it (and pattern.direction_deg), or "
                "set both to auto",
            )
        found = _measured(images, pattern, roi, dark_removed, None)
        if found is None or found.parts.get("period", 0.0) < _SURE_PHASES:
            return
    if "direction_deg" not in auto and (problem := _heading_off(found, pattern)):
        top.fail("pattern.direction_deg", f"{problem}, or set it to auto")
    off_lit = math.isfinite(found.lit_px) and abs(found.lit_px - pattern.lit) > LIT_OFF
    if off_lit and notes is not None:
        notes.append(
            f"pattern.lit: {pattern.lit}, but the stripes look lit {found.lit_px:.2f} of "
            f"every {pattern.period} rows at the {pattern.entry} wall (the stripe detector; "
            "a row or two off where the stripes are blurred or not aligned with the "
            "pixels): check it, a wrong lit makes the fit slow and wrong"
        )


def estimate_capture_black_level(top, images, pattern: Stripes, mask, frames) -> BlackLevel:
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
