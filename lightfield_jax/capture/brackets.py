"""Exposure brackets: reading them, their ``exposure_times`` and ``response``, and
merging them to linear radiance (:mod:`lightfield_jax.capture.hdr`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lightfield_jax.capture.auto import check_light
from lightfield_jax.capture.calibration import (
    check_sample_formats,
    drop_constant_alpha,
    sensor_top_code,
)
from lightfield_jax.capture.exposure_checks import (
    EXPOSURE_MISMATCH_FACTOR,
    EXPOSURE_MISMATCH_SHARE,
    EXPOSURE_RATIO_TOLERANCE,
    bracket_offset,
    mismatch_problem_of,
    pair_statistics,
    ratio_problem_of,
    ratio_within,
)
from lightfield_jax.capture.frames import (
    check_distinct_files,
    check_not_blank,
    matched_channels,
    read_aux_frame,
    read_frame,
    resolve_file,
    size_text,
)
from lightfield_jax.capture.hdr import merge_bracket, merge_capture
from lightfield_jax.capture.io import CaptureError, ImageData
from lightfield_jax.capture.keys import (
    AUX_FRAMES,
    check_integer_saturation,
    dark_level_text,
    read_dark_level,
    read_positive,
)
from lightfield_jax.capture.response import (
    CLIP,
    RESPONSES,
    calibrate_response,
    linear_response,
    load_response,
    srgb_response,
)
from lightfield_jax.schema import Section


def read_brackets(top: Section, base: Path, channel, notes: list[str]):
    """Exposure brackets merged to linear radiance (:mod:`lightfield_jax.capture.hdr`):
    ``(frames, calibration frames, Brackets)``, one merged frame per shift, the dark
    frame subtracted per exposure before merging (so the calibration frames hold no
    dark frame any more); ``None`` when the images are not brackets (lists)."""
    response = response_key = top.get("response", "linear")
    if not isinstance(response, str) or not response:
        top.fail("response", f"must be {' or '.join(RESPONSES)} or a file, got {response!r}")
    if response != response.lower() and response.lower() in RESPONSES:
        top.fail("response", f"write {response.lower()!r} in lower case, got {response!r}")
    value = top.get("images")
    rows = [isinstance(v, list) for v in value] if isinstance(value, list) else []
    if not any(rows):
        if "exposure_times" in top.data:
            top.fail(
                "exposure_times", "applies to bracketed images only (a list of exposures per shift)"
            )
        if response == "auto":
            top.fail(
                "response",
                "auto recovers the camera's response from exposure brackets; with one "
                "exposure per shift give linear, srgb or a response file (lightfield-jax "
                "inspect --response writes one from a bracketed capture)",
            )
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
            return read_aux_frame(top, key, base, channel, first, value=file)
        return read_frame(top, key, resolve_file(top, key, file, base), channel)

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
                f"{f.path.name} is {size_text(f)}, but images[0][0] ({first.path.name}) is "
                f"{size_text(first)}; every image must have the same size and channels",
            )
    # By name (one exposure saved B, G, R), as the shifts are rebuilt from listed below.
    by_index = isinstance(channel, int)
    listed = [(key, matched_channels(top, key, f, first, by_index)) for key, f in listed]
    try:
        kept = iter(drop_constant_alpha([f for _, f in listed], notes))
    except CaptureError as e:
        raise CaptureError(f"{top.source}: images: {e}") from None
    shifts = [[next(kept) for _ in row] for row in shifts]
    # As for single exposures: a corrupt or dropped exposure would merge (as 0) into its
    # shift's image without a word, near 0 where the longer exposures clipped.
    frames = [f for row in shifts for f in row]
    keys = [key for key, _ in listed]
    check_not_blank(top, [(k, f.path.name, f.pixels) for k, f in zip(keys, frames, strict=True)])
    bad = {f.path.name: int(np.sum(~np.isfinite(f.pixels))) for f in frames}
    if bad := {name: n for name, n in bad.items() if n}:
        notes.append(
            f"{sum(bad.values())} sample value(s) are NaN or Inf "
            f"({', '.join(f'{name}: {n}' for name, n in bad.items())}): left out of the "
            "merge (a pixel with no other sample is masked)"
        )
    first = shifts[0][0]
    for key in AUX_FRAMES:
        files = top.get(key, None)
        if files is not None and (not isinstance(files, list) or len(files) != len(times)):
            top.fail(
                key,
                f"with bracketed images give one file per exposure time ({len(times)}), in "
                f"their order, got {files!r}",
            )
    check_distinct_files(top, base)
    aux: dict[str, list[ImageData] | None] = {}
    for key in AUX_FRAMES:
        files = top.get(key, None)
        aux[key] = (
            None if files is None else [read(f"{key}[{j}]", f, first) for j, f in enumerate(files)]
        )
    try:
        check_sample_formats(
            listed, [(f"{k}[{j}]", f) for k, v in aux.items() if v for j, f in enumerate(v)]
        )
    except CaptureError as e:
        raise CaptureError(f"{top.source}: {e}") from None
    if response != "linear" and not first.is_integer:
        # As for single exposures (srgb would refuse them as exposures "listed out of
        # order", and auto would quantise the float values to 256 codes without a word).
        top.fail(
            "response",
            f"{response} maps a camera's integer codes (8- or 16-bit files), but "
            f"images[0][0] ({first.path.name}) holds float values, which are linear: give "
            "response: linear",
        )
    levels = (1 << first.bit_depth) if first.is_integer else None
    images = np.stack([[f.pixels for f in row] for row in shifts])  # [P, J, H, W, C]
    clip = read_positive(top, "saturation")
    check_integer_saturation(top, clip, first)
    # 10-14-bit data in 16-bit files: samples rescaled so that the sensor's top code is 1.
    sensor = None
    if clip is None:
        sensor = sensor_top_code(images.reshape(-1, *images.shape[2:]), [f for _, f in listed])
    full = 1.0 if sensor is None else sensor[0]
    if sensor is not None:
        levels = 1 << sensor[1]
        notes.append(f"{sensor[1]}-bit data in 16-bit files: samples divided by its top code")
    images = images / full
    response = read_response(top, base, first.channel_names, images, times)
    clip = clip or CLIP
    dark = None if aux["dark_frame"] is None else np.stack([f.pixels for f in aux["dark_frame"]])
    level = read_dark_level(
        top,
        first.bit_depth if first.is_integer else None,
        str(response_key),
        tuple(first.channel_names),
    )
    if level is not None:
        dark = np.full((len(times), *first.pixels.shape), level, images.dtype)
    dark = None if dark is None else dark / full
    _check_exposure_ratios(
        top, images, times, response, levels, dark, clip, shifts, aux, full, level
    )
    radiance, record = merge_capture(
        images, times, response, levels=levels, dark=dark, clip=clip,
        files=[[f.path for f in row] for row in shifts],
    )  # fmt: skip
    frames = [_merged_frame(r, row[-1]) for r, row in zip(radiance, shifts, strict=True)]
    merged: dict[str, ImageData | None] = dict.fromkeys(AUX_FRAMES)
    for key in ("black_frame", "white_frame", "flat_field"):
        if aux[key] is not None:
            stack = np.stack([f.pixels for f in aux[key]]) / full
            m = merge_bracket(stack, times, response, levels=levels, dark=dark, clip=clip)
            merged[key] = _merged_frame(m.radiance, aux[key][-1])
    if dark is not None:
        what = "dark_frame" if level is None else f"dark_level: {dark_level_text(level)}"
        notes.append(f"{what}: subtracted from every exposure before the merge")
    return frames, merged, record


def _check_exposure_ratios(
    top, images, times, response, levels, dark, clip, shifts, aux, full, level
):
    """Refuse brackets whose exposures do not scale as ``exposure_times`` say (files
    listed out of order, or wrong times), before the merge: merged, they give a capture
    the fit cannot explain (it ended not converged, sigma_t 22 % off). Then refuse
    brackets whose exposures scale as stated in their median but disagree pixel by
    pixel (an exposure of another shift, or a scene that moved): merged, they mix two
    stripe patterns into one image."""
    rows = [(f"images[{i}]", images[i], [f.path.name for f in row]) for i, row in enumerate(shifts)]
    for key in ("white_frame", "flat_field"):
        if aux[key] is not None:
            stack = np.stack([f.pixels for f in aux[key]]) / full
            rows.append((key, stack, [f.path.name for f in aux[key]]))
    kw = {"levels": levels, "dark": dark, "clip": clip}
    for key, bracket, names in rows:
        stats = pair_statistics(bracket, times, response, **kw)
        found = ratio_problem_of(stats)
        if found is not None:
            j, k, measured, stated = found
            # A pedestal left in (or a dark level above it) breaks the ratio too: said
            # where one constant in every sample makes the pair scale as stated.
            p = bracket_offset(bracket, times, response, (j, k), **kw)
            # An exposure of another shift moves the median too (where its stripes
            # leave few samples well exposed in both): said where this pair, or
            # another whose median ratio is as stated, disagrees pixel by pixel
            # (files out of order or wrong times scale alike in every pixel).
            as_stated = [s for s in stats if s[2] is not None and ratio_within(s[2], s[3])]
            mismatch = mismatch_problem_of([s for s in stats if s[:2] == (j, k)] + as_stated)
            cause = (
                "are the files listed out of order (each shift's in the order of "
                "exposure_times, shortest first), or are exposure_times wrong?"
            )
            if math.isfinite(p):
                cause = _offset_cause(p * full)
            elif mismatch is not None:
                a, b, share, _ = mismatch
                who = "they" if (a, b) == (j, k) else f"{names[b]} and {names[a]}"
                cause = (
                    f"{who} disagree pixel by pixel ({100 * share:.0f} % of the samples "
                    f"compared more than {EXPOSURE_MISMATCH_FACTOR:g}x off their median "
                    f"ratio): {_MISMATCH_CAUSE}"
                )
            top.fail(
                key,
                f"{names[k]} (listed for {times[k]:g} s) is {measured:.3g} times as bright as "
                f"{names[j]} (listed for {times[j]:g} s) where both are well exposed (median "
                f"over the pixels), but exposure_times make it {stated:.3g} (more than "
                f"{EXPOSURE_RATIO_TOLERANCE:g}x apart): {cause}",
            )
        found = mismatch_problem_of(stats)
        if found is None:
            continue
        j, k, share, compared = found
        if level is not None:
            # A dark_level above the pedestal pushes the dark values below zero, which
            # no exposure predicts: refused as for single exposures, naming dark_level.
            check_light(top, bracket - dark, None, level)
        cause = _MISMATCH_CAUSE
        p = bracket_offset(bracket, times, response, (j, k), **kw)
        if math.isfinite(p):  # one constant in every value, where it explains them
            again = pair_statistics(bracket, times, response, **kw, pairs=[(j, k)], offset=p)
            share = again[0][4]  # None: too few samples to compare with p taken out
            if share is not None and share <= EXPOSURE_MISMATCH_SHARE:
                cause = _offset_cause(p * full)
        if cause is _MISMATCH_CAUSE and response.kind != "linear":
            # A curve that does not fit the camera makes the ratio vary with the
            # code: measured on an auto curve recovered from two 8-bit exposures,
            # most of them clipped (1.3-1.8x off over the top codes), 0.27-0.34 off.
            cause = (
                "is one a file from another shift, did the scene move between exposures, "
                f"or does the response curve ({response.kind}) not fit the camera?"
            )
        top.fail(
            key,
            f"{names[k]} (listed for {times[k]:g} s) and {names[j]} (listed for "
            f"{times[j]:g} s) disagree pixel by pixel: {100 * share:.0f} % of the "
            f"{compared} samples compared differ from their median ratio by more than "
            f"{EXPOSURE_MISMATCH_FACTOR:g}x (exposures of one scene: at most "
            f"{100 * EXPOSURE_MISMATCH_SHARE:.0f} %): {cause}",
        )


_MISMATCH_CAUSE = "is one a file from another shift, or did the scene move between exposures?"


def _offset_cause(constant: float) -> str:
    """The cause of a pair that scales as stated with one constant in every image value."""
    what = (
        "a camera pedestal left in the images (give dark_level or a dark_frame)"
        if constant > 0
        else "a dark_level or dark_frame that subtracts too much"
    )
    return (
        f"they scale as exposure_times say with a constant {constant:+.4g} in every image "
        f"value: {what}?"
    )


def _merged_frame(radiance: np.ndarray, longest: ImageData) -> ImageData:
    """A merged bracket as a float frame, named after its longest exposure."""
    return dataclasses.replace(
        longest, pixels=radiance.astype(np.float32), bit_depth=32, sample_type="float"
    )


# Exposure times a camera takes, in seconds (1 ns to 11.6 days): the merge divides
# the codes by them in float32, where 1e-308 s overflows every value to Inf and
# 1e308 s underflows it to 0 (a numpy warning, then "no usable pixel" or "no light
# was captured", blaming the images).
EXPOSURE_RANGE = (1e-9, 1e6)


def _exposure_times(top: Section) -> list[float]:
    value = top.get("exposure_times", None)
    if not isinstance(value, list) or len(value) < 2:
        top.fail(
            "exposure_times",
            f"bracketed images need a list of at least two exposure times (seconds), got {value!r}",
        )
    for i, t in enumerate(value):
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not 0 < t < math.inf:
            top.fail(f"exposure_times[{i}]", f"must be a positive number of seconds, got {t!r}")
        low, high = EXPOSURE_RANGE
        if not low <= t <= high:
            top.fail(
                f"exposure_times[{i}]",
                f"must be a number of seconds in [{low:g}, {high:g}] (a camera's exposure), "
                f"got {t!r}",
            )
    if any(b <= a for a, b in zip(value, value[1:], strict=False)):
        top.fail("exposure_times", f"must increase (shortest first), got {value!r}")
    return [float(t) for t in value]


def read_response(
    top: Section,
    base: Path,
    names: Sequence[str],
    images: np.ndarray | None = None,
    times=None,
):
    """The inverse response of the ``response`` key: ``linear`` (default), ``srgb``, a
    table file (:func:`~lightfield_jax.capture.response.load_response`) or, for exposure
    brackets (``images`` [P, J, H, W, C] and their ``times``), ``auto`` (refused
    without brackets by :func:`read_brackets`)."""

    value = top.get("response", "linear")  # a string: checked by read_brackets
    try:
        if value == "linear":
            return linear_response()
        if value == "srgb":
            return srgb_response()
        if value == "auto":
            p, j, h, w, c = images.shape
            pooled = np.moveaxis(images, 1, 0).reshape(j, p * h * w, c)
            return calibrate_response(pooled, times)
        return load_response(resolve_file(top, "response", value, base), len(names), names)
    except CaptureError as e:
        raise CaptureError(f"{top.source}: response: {e}") from None
