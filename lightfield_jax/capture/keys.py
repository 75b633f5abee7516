"""The capture file's keys: their tables, and the parsers of the keys that need no image
(``channel``, ``pattern``, ``medium_roi``, ``black_level``, ``pixel_size_mm``,
``saturation``, ``geometry``, ``fit``, ``truth``).
The format: :mod:`lightfield_jax.capture.capture`."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from lightfield_jax.capture.detect import Geometry
from lightfield_jax.capture.io import CaptureError
from lightfield_jax.scene.geometry_spec import parse_geometry
from lightfield_jax.scene.illumination import WALLS, Stripes
from lightfield_jax.scene.medium import FILE_PHASE, PHASE_CONVENTIONS
from lightfield_jax.schema import REQUIRED, Section, as_float, as_int, at_most, brief

CAPTURE_KEYS: tuple[str, ...] = (
    "images",
    "pattern",
    "dark_frame",
    "dark_level",
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
# FitOptions a capture file may set under ``fit:`` (the method is the command's flag, the
# geometry has its own key, a solver has no YAML form).
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
_FIT_OPTIONAL_INTS = ("n_theta", "refine", "coarse_after")
_FIT_FLOATS = ("tolerance", "crop_fraction", "basin_tolerance", "max_chi2", "offset_stop")
_FIT_OPTIONAL_FLOATS = ("rtol", "atol")
_FIT_BOOLS = ("crop", "basin_search", "model_error", "correct", "extrapolate", "stripe_cell")
FIT_KEYS: tuple[str, ...] = (
    "phase",
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
AUX_FRAMES = ("dark_frame", "black_frame", "white_frame", "flat_field")
_PATTERN_KEYS = ("period", "lit", "phases", "direction_deg", "entry")
_TRUTH_FLOATS = ("sigma_t", "sigma_s", "g", "gain", "black_level")
_TRUTH_KEYS = (*_TRUTH_FLOATS, "phase")


def read_channel(top: Section) -> str | int | None:
    """The channel selection for read_image: a name, an index, or None for all."""
    value = top.get("channel", "all")
    if isinstance(value, bool) or not isinstance(value, (str, int)) or value == "":
        top.fail("channel", f"must be a channel name, an index or 'all', got {brief(value)}")
    if isinstance(value, int) and value < 0:
        top.fail("channel", f"must be a non-negative index, got {brief(value)}")
    return None if value == "all" else value


def read_pattern_spec(top: Section, n_images: int, height: int, width: int) -> dict[str, Any]:
    """The pattern's keys, validated; ``phases``, ``entry`` and ``direction_deg`` may be
    ``"auto"`` (measured from the images)."""
    s = top.section("pattern", _PATTERN_KEYS)
    spec: dict[str, Any] = {"period": s.int("period", 6), "lit": s.int("lit", 3)}
    if spec["period"] < 2:  # before the phases, which count rows modulo it
        s.fail(s.key("period"), f"must be an integer >= 2, got {spec['period']}")
    if spec["period"] > max(height, width):
        s.fail(
            s.key("period"),
            f"{spec['period']} rows is longer than the {width}x{height} images: a stripe "
            "period is a few rows",
        )
    phases = s.get("phases", None)
    spec["phases_from"] = "default" if phases is None else "given"
    if phases is None:
        if n_images > spec["period"]:  # not "each phase must lie in [0, 6)": none are given
            s.fail(
                s.key("phases"),
                f"not given, so the {n_images} images take the phases 0..{n_images - 1}, "
                f"beyond the period {spec['period']}: give one phase per image in [0, "
                f"{spec['period']}) (or phases: auto)",
            )
        phases = list(range(n_images))
    elif phases == AUTO:
        pass
    elif not isinstance(phases, list) or not phases:
        s.fail(
            s.key("phases"), f"must be a non-empty list of integers or 'auto', got {brief(phases)}"
        )
    else:
        phases = [as_int(s, f"{s.key('phases')}[{i}]", p) for i, p in enumerate(phases)]
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
    read_stripes(top, {**spec, "phases": phases if phases != AUTO else [0]}, None, check=True)
    return spec


def read_stripes(top: Section, spec: dict[str, Any], detected: Geometry | None, check=False):
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


def crop_pattern(pattern: Stripes, x0: int, y0: int) -> Stripes:
    """The pattern with wall cells counted from the ROI's edge instead of the frame's."""
    offset = y0 if pattern.along_x else x0
    phases = tuple((p + offset) % pattern.period for p in pattern.phases)
    return dataclasses.replace(pattern, phases=phases)


def read_black_level(top: Section) -> float | str | None:
    given = top.get("black_level", None)
    if given == AUTO:
        return AUTO
    if isinstance(given, str) and given.strip().lower() == AUTO:  # else "must be a number"
        top.fail("black_level", f"must be a number in [0, 1) or 'auto', got {brief(given)}")
    value = top.float("black_level", None)
    if value is not None and not 0.0 <= value < 1.0:
        top.fail("black_level", f"must lie in [0, 1), got {brief(value)} (or 'auto': measured)")
    return value


def read_dark_level(
    top: Section, integer_bits: int | None, response: str, channels: tuple[str, ...] = ()
) -> float | np.ndarray | None:
    """``dark_level``: the camera's constant black offset (a pedestal), in the images'
    values after integer scaling (``integer_bits``: the files' bits, ``None`` for float
    files), subtracted from every image like a dark frame of that value: one value, or
    one per channel by name (``{R: 0.0312, G: 0.0310, B: 0.0316}``; ``channels``: the
    images' channels), returned in the channels' order. ``None``: no pedestal."""
    given = top.get("dark_level", None)
    if given is None:
        return None
    if "dark_frame" in top.data and top.get("dark_frame", None) is not None:
        top.fail("dark_level", "give a dark_frame or a dark_level, not both")
    if isinstance(given, dict):
        given = {str(k): v for k, v in given.items()}  # a YAML key 0 names channel "0"
        names = list(given)
        for name in names:
            if name not in channels:
                top.fail(
                    f"dark_level.{name}",
                    f"no channel named {name!r} in the images; channels: {', '.join(channels)}",
                )
        missing = [c for c in channels if c not in names]
        if missing:
            top.fail(
                "dark_level",
                f"no value for channel {missing[0]} (one value per channel of the images: "
                f"{', '.join(channels)}, or one value for all)",
            )
        keys = [f"dark_level.{c}" for c in channels]
        levels = [as_float(top, k, given[c]) for k, c in zip(keys, channels, strict=True)]
    elif isinstance(given, list):
        top.fail(
            "dark_level",
            "one value, or one per channel by name (e.g. {R: 0.0312, G: 0.031, B: 0.0316}), "
            f"not a list: {brief(given)}",
        )
    else:
        keys, levels = ["dark_level"], [top.float("dark_level", None)]
    for key, value in zip(keys, levels, strict=True):
        if not math.isfinite(value) or value < 0:
            top.fail(key, f"must be a finite value >= 0, got {brief(value)}")
        # Bounded: 1e300 would overflow the float32 images to -Inf (a numpy warning and
        # "no direct light at the entry wall", exit 1), past the pedestal check.
        at_most(top, key, value)
        if integer_bits is not None and value >= 1:
            top_code = (1 << integer_bits) - 1
            top.fail(
                key,
                f"{value:g} is not an image value of these {integer_bits}-bit files (scaled "
                f"to [0, 1]): a pedestal of {value:g} codes is {key}: "
                f"{value / top_code:.6g} ({value:g}/{top_code})",
            )
    if response != "linear":
        top.fail(
            "dark_level",
            f"applies to linear images, not with response: {response} (a camera that "
            "encodes its files subtracts its pedestal first; take a dark_frame otherwise)",
        )
    if not any(levels):
        return None  # no pedestal: nothing to subtract
    return levels[0] if len(levels) == 1 and not isinstance(given, dict) else np.array(levels)


def dark_level_text(level: float | np.ndarray) -> str:
    """A ``dark_level`` as a message shows it: ``0.0312`` or ``[0.0312, 0.031, 0.0316]``."""
    if np.ndim(level) == 0:
        return f"{float(level):.6g}"
    return "[" + ", ".join(f"{float(v):.6g}" for v in level) + "]"


def read_roi(top: Section, width: int, height: int) -> tuple[int, int, int, int] | str | None:
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


# A pixel's pitch in mm, from 1 nm to 1 m: outside it, a slip (a value in m or µm
# given as mm) or a value that overflows the per-mm coefficients.
PIXEL_SIZE_MM = (1e-6, 1e3)


def pixel_size_problem(value) -> str | None:
    """What is wrong with a pixel pitch (``None``: nothing, or none given)."""
    lo, hi = PIXEL_SIZE_MM
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
        return f"must be a number of mm, got {value!r}"
    if not lo <= value <= hi:
        return f"must lie in [{lo:g}, {hi:g}] mm, got {value!r}"
    return None


def check_pixel_size(value, key: str = "pixel_size_mm") -> None:
    """Refuse a pixel pitch outside :data:`PIXEL_SIZE_MM` (``None``: none given)."""
    problem = pixel_size_problem(value)
    if problem is not None:
        raise ValueError(f"{key}: {problem}")


def read_positive(top: Section, key: str) -> float | None:
    value = top.float(key, None)
    if value is not None and value <= 0:
        top.fail(key, f"must be > 0, got {brief(value)}")
    if value is not None:
        at_most(top, key, value)
    return value


def check_integer_saturation(top: Section, value: float | None, frame) -> None:
    """``saturation`` above 1 with integer images (``frame``), whose samples are scaled
    to [0, 1], would mask nothing: a threshold given in codes (65000 of 65535) kept
    every clipped value in the fit, without a word."""
    if value is not None and value > 1 and frame.is_integer:
        top_code = (1 << frame.bit_depth) - 1
        codes = (
            f": a threshold of {value:g} codes is saturation: {value / top_code:.6g} "
            f"({value:g}/{top_code})"
            if value <= top_code
            else ""
        )
        top.fail(
            "saturation",
            f"must be at most 1 with integer images ({frame.path.name} is {frame.bit_depth}-bit, "
            f"scaled to [0, 1]: its top code is 1), got {value:g}{codes}",
        )


def read_geometry(top: Section) -> dict[str, Any]:
    """The model geometry: ``{kind: plane}`` (default) or a slab (docs/model.md §7)."""
    if "geometry" not in top.data:
        return {"kind": "plane"}
    try:
        return parse_geometry(top.data["geometry"], top.key("geometry"), allow_auto=True).as_dict()
    except ValueError as err:
        raise top.error(f"{top.source}: {err}") from None


def read_fit_options(top: Section, key: str = "fit") -> dict[str, Any]:
    """The ``fit:`` mapping (at ``key``): FitOptions settings (:data:`FIT_KEYS`), each
    checked for its type, then as FitOptions checks them (ranges: each group of
    settings, :mod:`lightfield_jax.inverse.settings`, and the methods' own), before any
    image is read and before the command chooses the method."""
    from lightfield_jax.forward.tail import TAIL_METHODS
    from lightfield_jax.inverse.method_base import METHOD_KEYS, check_method_setting
    from lightfield_jax.inverse.settings import grouped

    if key not in top.data or top.data[key] is None:
        return {}
    s = top.section(key, FIT_KEYS)
    out: dict[str, Any] = {}
    for k in s.data:
        value = s.data[k]
        if k in _FIT_INTS or k in _FIT_OPTIONAL_INTS:
            out[k] = s.int(k, None if k in _FIT_OPTIONAL_INTS else REQUIRED)
        elif k in _FIT_FLOATS or k in _FIT_OPTIONAL_FLOATS:
            out[k] = s.float(k, None if k in _FIT_OPTIONAL_FLOATS else REQUIRED)
        elif k in _FIT_BOOLS:
            if not isinstance(value, bool):
                s.fail(s.key(k), f"must be true or false, got {brief(value)}")
            out[k] = value
        elif k == "bounces":
            out[k] = AUTO if value == AUTO else s.int(k)
        elif k == "tail":
            out[k] = None if value is None else s.choice(k, (AUTO, *TAIL_METHODS))
        elif k == "phase":
            out[k] = s.choice(k, PHASE_CONVENTIONS)
        else:  # start: [sigma_s, g]
            if not (isinstance(value, list) and len(value) == 2):
                s.fail(s.key(k), f"must be [sigma_s, g], got {brief(value)}")
            out[k] = tuple(as_float(s, s.key(k), v) for v in value)
    try:
        grouped({k: v for k, v in out.items() if k not in METHOD_KEYS})
        for k in METHOD_KEYS:
            if k in out:
                check_method_setting(k, out[k])
    except ValueError as err:
        s.fail(key, str(err))
    return out


def fit_phase(capture) -> str:
    """The phase convention a capture is fitted with: its file's ``fit.phase``, else
    :data:`~lightfield_jax.scene.medium.FILE_PHASE` (``normalized``)."""
    return (getattr(capture, "fit_options", None) or {}).get("phase", FILE_PHASE)


def read_truth(top: Section, n_channels: int = 1) -> dict[str, Any] | None:
    """The ``truth`` section: each number, or a list of one per channel (an RGB
    capture's media differ by channel), checked in its range."""
    if "truth" not in top.data:
        return None
    if isinstance(top.data["truth"], list):
        data = {**top.data, "truth": _by_key(top, n_channels)}
        top = Section(top.source, top.path, data, None, error=top.error)
    s = top.section("truth", _TRUTH_KEYS)
    truth: dict[str, Any] = {}
    for k in _TRUTH_FLOATS:
        if k not in s.data:
            continue
        value = s.data[k]
        if isinstance(value, list):
            if len(value) != n_channels:
                s.fail(
                    s.key(k),
                    f"a list gives one value per channel: {n_channels} here, got {len(value)}",
                )
            truth[k] = [as_float(s, f"{s.key(k)}[{i}]", v) for i, v in enumerate(value)]
        else:
            truth[k] = s.float(k)
    for c in range(n_channels):
        _check_truth(s, truth_for(truth, c))
    if "phase" in s.data:
        truth["phase"] = s.choice("phase", PHASE_CONVENTIONS)
    return truth


def _by_key(top: Section, n_channels: int) -> dict[str, Any]:
    """``truth`` given as a list of one mapping per channel, as the mapping of lists
    :func:`read_truth` reads (``truth: [{sigma_t: .2, g: .8}, ...]`` for R, G, B)."""
    given = top.data["truth"]
    key = top.key("truth")
    if len(given) != n_channels:
        top.fail(key, f"a list gives one mapping per channel: {n_channels} here, got {len(given)}")
    for i, item in enumerate(given):
        if not isinstance(item, dict):
            top.fail(
                f"{key}[{i}]", f"must be a mapping (sigma_t, sigma_s, g, ...), got {brief(item)}"
            )
    keys = list(dict.fromkeys(k for item in given for k in item))
    for k in keys:
        missing = [i for i, item in enumerate(given) if k not in item]
        if missing:
            top.fail(f"{key}[{missing[0]}]", f"{k}: given for another channel but not this one")
    out: dict[str, Any] = {k: [item[k] for item in given] for k in keys}
    if "phase" in out:
        if len(set(map(str, out["phase"]))) > 1:
            top.fail(key, f"phase: one convention for every channel, got {out['phase']}")
        out["phase"] = out["phase"][0]
    return out


def truth_for(truth: dict[str, Any] | None, channel: int) -> dict[str, Any] | None:
    """Channel ``channel``'s truth: per-channel lists picked, numbers as they are."""
    if truth is None:
        return None
    return {k: v[channel] if isinstance(v, list) else v for k, v in truth.items()}


def _check_truth(s: Section, truth: dict[str, Any]) -> None:
    """The ranges of a medium (a report compares the fit with these)."""
    t, v = truth.get("sigma_t"), truth.get("sigma_s")
    if t is not None and t <= 0:
        s.fail(s.key("sigma_t"), f"must be > 0 (per pixel), got {t!r}")
    if v is not None and not 0 <= v <= (math.inf if t is None else t * (1 + 1e-6)):
        bound = "" if t is None else f" <= sigma_t = {t!r}"
        s.fail(s.key("sigma_s"), f"must satisfy 0 <= sigma_s{bound}, got {v!r}")
    if "g" in truth and not -1 < truth["g"] < 1:
        s.fail(s.key("g"), f"must satisfy -1 < g < 1, got {truth['g']!r}")
    if "gain" in truth and truth["gain"] <= 0:
        s.fail(s.key("gain"), f"must be > 0, got {truth['gain']!r}")
    if "black_level" in truth and not 0 <= truth["black_level"] < 1:
        s.fail(s.key("black_level"), f"must lie in [0, 1), got {truth['black_level']!r}")
