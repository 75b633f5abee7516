"""One-line checks of the numbers the Python API takes (medium, grid, geometry,
illumination, fit options, figures).

A number is a Python ``int`` or ``float``, a NumPy integer or floating scalar, or a
0-d real array (NumPy or JAX); ``True``, strings, ``None``, complex values and arrays
of more than one value are not (``True`` is an ``int`` to Python and ``"0.2"`` a
number to ``float()``: neither is taken silently). :func:`number_problem` says what is
wrong with a value (``None``: nothing), :func:`check_number` raises it as
``ValueError("KEY: PROBLEM")`` naming the argument, the value and the allowed range.
JAX tracers (values under ``jit`` or ``grad``) are not numbers to check here: callers
that take them skip the check (see :class:`~lightfield_jax.Medium`); given to one that
does not, a tracer is named as such (not as JAX's many-line ConcretizationTypeError).
"""

from __future__ import annotations

import math
import reprlib
import sys

import numpy as np

_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxdict, _REPR.maxlist, _REPR.maxstring, _REPR.maxother = 3, 6, 8, 60, 60


def shown(value, limit: int = 80) -> str:
    """``repr(value)`` bounded in size (and in the work to build it), for an error
    message: a rejected value may be a huge array, list or string."""
    text = _REPR.repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _range(kind: str, low, high, low_open: bool, high_open: bool, unit: str) -> str:
    """``"must be a number in [0, 1)"``, ``"must be an integer >= 2"``, ..."""
    if low is not None and high is not None:
        left, right = "(" if low_open else "[", ")" if high_open else "]"
        return f"must be {kind} in {left}{low:g}, {high:g}{right}{unit}"
    if low is not None:
        return f"must be {kind} {'>' if low_open else '>='} {low:g}{unit}"
    return f"must be {kind} {'<' if high_open else '<='} {high:g}{unit}"


def _is_tracer(value) -> bool:
    jax = sys.modules.get("jax")  # no JAX imported: no tracer
    return jax is not None and isinstance(value, jax.core.Tracer)


TRACED = "a traced value (under jax.jit, grad or vmap): it must be concrete here"


def number_problem(
    value,
    *,
    integer: bool = False,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
    allow_inf: bool = False,
    unit: str = "",
) -> str | None:
    """What is wrong with ``value`` as a number (``None``: nothing).

    ``integer``: an ``int`` or NumPy integer only. ``low``/``high``: the allowed range
    (closed unless ``low_open``/``high_open``); ``allow_inf``: ±inf is a value (NaN
    never is). ``unit`` follows the range in the message (e.g. ``" px"``).
    """
    kind = "an integer" if integer else "a number"
    if isinstance(value, (bool, np.bool_, str, bytes, np.str_)) or value is None:
        return f"must be {kind}, got {shown(value)}"
    if _is_tracer(value):
        return f"must be {kind}, got {TRACED}"
    if isinstance(value, (int, np.integer)):
        v = value
    elif integer:
        if isinstance(value, (float, np.floating)) or np.ndim(value) == 0:
            return f"must be {kind}, got {shown(value)}"
        return f"must be {kind}, got {_array_words(value)}"
    elif isinstance(value, (float, np.floating)):
        v = float(value)
    else:
        dtype = getattr(value, "dtype", None)
        if dtype is None or getattr(value, "shape", None) is None:
            if isinstance(value, complex):
                return f"must be a real number, got {shown(value)}"
            if isinstance(value, (list, tuple)):
                return f"must be a single number, got {shown(value)}"
            return f"must be {kind}, got {shown(value)} ({type(value).__name__})"
        if np.ndim(value) != 0:
            return f"must be a single number, got {_array_words(value)}"
        dtype = np.dtype(dtype)
        if dtype.kind not in "iuf":
            what = "a real number" if dtype.kind == "c" else kind
            return f"must be {what}, got {shown(value)} (dtype {dtype})"
        v = float(value)
    if isinstance(v, float) or not integer:
        try:
            f = float(v)
        except OverflowError:  # an int beyond float64 (10**400): said, not a bare OverflowError
            if (low is None or v >= low) and (high is None or v <= high):
                big = sys.float_info.max
                return f"must be a number of magnitude at most {big:.3g}, got {shown(value)}"
            f = 0.0  # outside the range: said below
        if math.isnan(f) or (math.isinf(f) and not allow_inf):
            return f"must be finite, got {shown(value)}"
    if (low is not None and (v < low or (low_open and v == low))) or (
        high is not None and (v > high or (high_open and v == high))
    ):
        return f"{_range(kind, low, high, low_open, high_open, unit)}, got {shown(value)}"
    return None


def _array_words(value) -> str:
    shape = getattr(value, "shape", None)
    if shape is None:
        return shown(value)
    return f"an array of shape {tuple(shape)}"


def check_number(value, key: str, **limits) -> float:
    """``value`` as a float, or ``ValueError("KEY: ...")`` (see :func:`number_problem`)."""
    problem = number_problem(value, **limits)
    if problem is not None:
        raise ValueError(f"{key}: {problem}")
    return float(value)


def check_int(value, key: str, **limits) -> int:
    """``value`` as an int, or ``ValueError("KEY: ...")`` (an ``int`` or NumPy integer
    only: see :func:`number_problem`)."""
    problem = number_problem(value, integer=True, **limits)
    if problem is not None:
        raise ValueError(f"{key}: {problem}")
    return int(value)


def check_flag(value, key: str) -> bool:
    """``value`` if it is a ``bool`` (or NumPy bool), else ``ValueError("KEY: ...")``:
    ``"no"`` or ``0`` for a switch is a slip (``"no"`` is true)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{key}: must be True or False, got {shown(value)}")
    return bool(value)


# The gain (image units per unit source irradiance) a render takes: images are float32,
# whose normal numbers span 1.2e-38 to 3.4e38. A larger gain overflows the brightest
# images, a smaller one underflows every image to zero (gain 1e-40 would render
# all-zero images, silently): per unit irradiance the single scatter is at most about 1.
GAIN_RANGE = (1e-30, 1e30)


def gain_problem(value) -> str | None:
    """What is wrong with a render's gain (``None``: nothing); see :data:`GAIN_RANGE`."""
    low, high = GAIN_RANGE
    if number_problem(value, low=low, high=high) is None:
        return None
    return f"must be a number in [{low:g}, {high:g}] (images are float32), got {shown(value)}"


def real_array(value, key: str, ndim: tuple[int, ...], what: str, *, finite: str = "all"):
    """``value`` as a float64 NumPy array, or ``ValueError("KEY: ...")``: real numbers
    (not bool, strings or objects such as a result of another kind), ``ndim``
    dimensions, none of them empty, and finite: every value (``finite="all"``), at
    least one (``"some"``: masked pixels may be NaN) or not checked (``"any"``).
    ``what`` names the expected array in the message (e.g. ``"(K, height, width)"``)."""
    try:
        a = np.asarray(value)
    except (TypeError, ValueError):
        raise ValueError(f"{key}: must be an array {what}, got {type(value).__name__}") from None
    if a.dtype == object or a.dtype.kind not in "iuf":
        got = type(value).__name__ if a.dtype == object else f"dtype {a.dtype}"
        raise ValueError(f"{key}: must be an array of real numbers {what}, got {got}")
    if a.ndim not in ndim:
        dims = " or ".join(map(str, ndim))
        raise ValueError(f"{key}: must have {dims} dimensions {what}, got shape {a.shape}")
    if a.size == 0:
        raise ValueError(f"{key}: must not be empty {what}, got shape {a.shape}")
    a = a.astype(np.float64)
    ok = np.isfinite(a)
    if finite == "all" and not ok.all():
        raise ValueError(
            f"{key}: must be finite, got {a.size - int(ok.sum())} of {a.size} values NaN or inf"
        )
    if finite == "some" and not ok.any():
        raise ValueError(f"{key}: has no finite value (all {a.size} NaN or inf)")
    return a


def unmasked(values, key: str = "values") -> tuple[np.ndarray, np.ndarray]:
    """``(data, masked)``: a numpy masked array's data and mask (``masked`` all false
    for any other array), so that its fill values are never used as values. A ragged
    list is ``ValueError("KEY: ...")`` (not numpy's "inhomogeneous shape")."""
    if isinstance(values, np.ma.MaskedArray):
        return np.ma.getdata(values), np.ma.getmaskarray(values)
    data = as_array(values, key)
    return data, np.zeros(data.shape, bool)


def as_array(values, key: str, what: str = "an array of real numbers", items: str = ""):
    """``np.asarray(values)``, or ``ValueError("KEY: must be WHAT, got ...")`` naming a
    ragged list (``list of ITEMSdifferent shapes``; not numpy's "inhomogeneous shape")
    or a traced value (not JAX's many-line TracerArrayConversionError)."""
    try:
        return np.asarray(values)
    except (TypeError, ValueError):
        got = (
            TRACED if _is_tracer(values) else f"{type(values).__name__} of {items}different shapes"
        )
        raise ValueError(f"{key}: must be {what}, got {got}") from None


def check_mask(mask, key: str = "mask"):
    """``mask`` as a bool array (``None`` as given), or ``ValueError("KEY: ...")``: flags
    are bools, or numbers that are 0 or 1 (so that a NaN, a 2 or a string is not taken
    as true, nor an object array of ``None`` as false)."""
    if mask is None:
        return None
    try:
        flags = np.asarray(mask)
    except (TypeError, ValueError):
        raise ValueError(f"{key}: must be an array of flags, got {type(mask).__name__}") from None
    if flags.dtype.kind == "b":
        return flags
    if flags.dtype.kind not in "iuf":
        raise ValueError(f"{key}: must be flags (bool, or 0 and 1), got dtype {flags.dtype}")
    other = ~((flags == 0) | (flags == 1))
    if other.any():
        raise ValueError(
            f"{key}: must be flags (bool, or 0 and 1), got {int(other.sum())} of "
            f"{flags.size} values that are neither, e.g. {flags[other].flat[0].item()!r}"
        )
    return flags.astype(bool)


def unmask(images, mask=None):
    """``(images, mask)`` with a numpy masked array's mask honoured: its masked values
    are excluded, combined with ``mask`` (``True`` where valid, per pixel ``(height,
    width)`` or per value like ``images``) into a per-value mask. Anything else is
    returned as given (``np.asarray`` would drop the mask silently). ``mask`` is checked
    (:func:`check_mask`) and returned as a bool array."""
    mask = check_mask(mask)
    if not isinstance(images, np.ma.MaskedArray):
        return images, mask
    data, masked = unmasked(images)
    valid = ~masked
    if valid.all():
        return data, mask
    if mask is None:
        return data, valid
    given = np.asarray(mask)
    if given.shape not in (data.shape, data.shape[-2:]):
        return data, mask  # refused as it would be without the masked array
    return data, given & valid


def check_float_range(values, key: str) -> None:
    """Refuse concrete float values that JAX's default float (float32 unless x64 is on)
    cannot hold: whose largest magnitude overflows it, or underflows below its smallest
    normal number (``ValueError("KEY: ...")``). Unchecked, a float64 image of 1e300
    becomes inf (1e-300 zero) in float32 and a later step fails naming another cause."""
    jax = sys.modules.get("jax")
    if jax is None or _is_tracer(values):
        return
    a = np.asarray(values)
    if a.dtype.kind != "f":
        return
    work = np.dtype(jax.dtypes.canonicalize_dtype(a.dtype))
    if a.dtype.itemsize <= work.itemsize:
        return
    finite = np.abs(a[np.isfinite(a)])
    peak = float(finite.max()) if finite.size else 0.0
    info = np.finfo(work)
    if peak > float(info.max) or 0.0 < peak < float(info.tiny):
        raise ValueError(
            f"{key}: its largest value {peak:.3g} lies outside {work}'s range "
            f"[{info.tiny:.3g}, {info.max:.3g}] (JAX's default float): scale the values by "
            "a constant"
        )


def masked_to_nan(images):
    """A numpy masked array as a float array with NaN at its masked values (for the
    functions that skip NaN values); anything else as given."""
    if not isinstance(images, np.ma.MaskedArray):
        return images
    data, masked = unmasked(images)
    if data.dtype.kind not in "f":
        data = data.astype(np.float64)
    return np.where(masked, np.nan, data)


def repeated(items) -> list:
    """The items listed more than once, sorted (for a refusal that names them)."""
    items = list(items)
    return sorted({i for i in items if items.count(i) > 1})


def one_path_part(name: str) -> bool:
    """Whether ``name`` holds no path separator (nor NUL): it names one file or folder
    inside another, not a path through or out of it."""
    return not any(c in name for c in "/\\\0")
