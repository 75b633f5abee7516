"""The schema of an experiment's config: every script defines its config as a frozen
dataclass ``Config`` (field types with :class:`Range` bounds, ``Literal`` choices,
nested mappings as dataclass schemas); :func:`typed_config` checks a whole config
against it, and :func:`check_cells` the size of its grid, before any work, so that a
bad config is one line naming the file and the key."""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from pathlib import Path
from typing import Annotated, Any, Literal

from lightfield_jax.schema import Section


def check_choices(name: str, key: str, values, known) -> None:
    """Refuse a value of the list ``values`` (config key ``key``) outside ``known``."""
    for value in values:
        if value not in known:
            raise ValueError(
                f"{name}: {key}: unknown {value!r} (known: {', '.join(map(str, known))})"
            )


@dataclasses.dataclass(frozen=True)
class Range:
    """The interval a config number must lie in, written into its field's annotation:
    ``width: Annotated[int, Range(8, 2048)]``; ``open_low`` and ``open_high`` exclude
    the ends themselves."""

    low: float = -math.inf
    high: float = math.inf
    open_low: bool = False
    open_high: bool = False

    def __contains__(self, x) -> bool:
        above = self.low < x if self.open_low else self.low <= x
        below = x < self.high if self.open_high else x <= self.high
        return above and below

    def __str__(self) -> str:
        low, high = _number(self.low), _number(self.high)
        if self.high == math.inf:
            return f"{'>' if self.open_low else '>='} {low}"
        return f"in {'(' if self.open_low else '['}{low}, {high}{')' if self.open_high else ']'}"


def _number(x: float) -> str:
    """``x`` as a config would write it: integers in full, else ``%g``."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


# The ranges the experiments share: an image side, a count of things, a seed (numpy's
# generators take 0 .. 2**32 - 1 as 32-bit seeds), a positive number, a precision.
Pixels = Annotated[int, Range(8, 2048)]


Count = Annotated[int, Range(1, 100_000)]


Seed = Annotated[int, Range(0, 2**32 - 1)]


Positive = Annotated[float, Range(0, open_low=True)]


Dtype = Literal["float32", "float64"]


class _Invalid(ValueError):
    """A config value that does not fit its field: ``key``, the reason."""


class _WrongType(_Invalid):
    """A value of the wrong kind at ``key`` itself (not inside it)."""

    def __init__(self, key: str, annotation, value):
        super().__init__(f"{key}: expected {_type_name(annotation)}, got {value!r}")
        self.key = key


def _check_value(value, annotation, key: str):
    """``value`` (YAML) checked against a field's annotation, returned as the config
    holds it (lists become tuples); a misfit raises :class:`_Invalid`. int is accepted
    for float, bool is not a number, floats are finite; ``Annotated[dict, Schema]``
    checks a mapping against the dataclass ``Schema`` (kept as the mapping)."""
    origin = typing.get_origin(annotation)
    if origin is Annotated:
        base, *extras = typing.get_args(annotation)
        schemas = [e for e in extras if isinstance(e, type) and dataclasses.is_dataclass(e)]
        if schemas:
            if not isinstance(value, dict):
                raise _WrongType(key, dict, value)
            _build(schemas[0], value, f"{key}.")
            return value
        value = _check_value(value, base, key)
        for r in (e for e in extras if isinstance(e, Range)):
            if value not in r:
                raise _Invalid(f"{key}: must be {r}, got {value!r}")
        return value
    if origin is Literal:
        known = typing.get_args(annotation)
        if isinstance(value, bool) or value not in known:
            raise _Invalid(f"{key}: must be one of {', '.join(map(str, known))}, got {value!r}")
        return value
    if origin in (typing.Union, types.UnionType):
        errors = []
        for option in typing.get_args(annotation):
            try:
                return _check_value(value, option, key)
            except _Invalid as e:
                errors.append(e)
        # An option of the value's kind: its reason (a range, a key inside); else the
        # types expected.
        fitting = [e for e in errors if not (isinstance(e, _WrongType) and e.key == key)]
        raise fitting[0] if fitting else _WrongType(key, annotation, value)
    if annotation is Any:
        return value
    if origin in (tuple, list):
        args = typing.get_args(annotation)
        inner = args[0] if args else Any
        if not isinstance(value, (list, tuple)):
            raise _WrongType(key, annotation, value)
        items = tuple(_check_value(v, inner, f"{key}[{i}]") for i, v in enumerate(value))
        _check_names(items, key)
        return items
    if annotation is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        if ok and not math.isfinite(value):
            raise _Invalid(f"{key}: must be a finite number, got {value!r}")
    elif annotation is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif annotation is type(None):
        ok = value is None
    else:
        ok = isinstance(value, origin or annotation)
    if not ok:
        raise _WrongType(key, annotation, value)
    return value


def _check_names(items: tuple, key: str) -> None:
    """A list of named mappings (media, scenes): the names key the tables, the figures
    and some figures' file names, so they must differ and hold no path separator
    (two scenes of one name would both run, then one be kept in the results or their
    rows mixed in one figure; a name with '/' would name a file in another folder)."""
    names = [v["name"] for v in items if isinstance(v, dict) and isinstance(v.get("name"), str)]
    if len(names) != len(items):
        return
    for i, name in enumerate(names):
        if not name or "/" in name or "\\" in name or "\0" in name:
            raise _Invalid(f"{key}[{i}].name: must be a non-empty name without '/', got {name!r}")
    if len(set(names)) < len(names):
        raise _Invalid(f"{key}: names must differ, got {names}")


def _build(cls, config: dict, prefix: str = ""):
    """``cls(**config)`` with every key checked (see :func:`typed_config`); the keys
    named with ``prefix`` (``"oblique."``, ``"media[0]."``)."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(config) - set(fields) - ({"experiment"} if not prefix else set())
    if unknown:  # (YAML keys may be numbers or booleans too)
        raise _Invalid(f"unknown config keys {sorted(f'{prefix}{k}' for k in unknown)}")
    hints = typing.get_type_hints(cls, include_extras=True)
    values = {}
    for key, field in fields.items():
        if key in config:
            values[key] = _check_value(config[key], hints[key], prefix + key)
        elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            raise _Invalid(f"missing config key {prefix + key!r}")
    return cls(**values)


def typed_config(cls, config: dict):
    """The frozen dataclass ``cls`` built from an experiment config (its ``experiment``
    key aside). An unknown key (a typo), a missing one, a value of the wrong type (a
    string or a bool for a number), a number outside its field's :class:`Range`, or a
    mapping (``Annotated[dict, Schema]``) that does not fit its schema is a one-line
    ``ValueError`` naming the experiment and the key's path (``oblique.y``,
    ``media[1].g``), as are the checks of ``cls.__post_init__``. Lists become tuples."""
    name = config.get("experiment", cls.__name__)
    try:
        return _build(cls, config)
    except _Invalid as e:
        raise ValueError(f"{name}: {e}") from None


def fit_keywords(where: str, key: str, value) -> dict:
    """``value``, extra :func:`~lightfield_jax.fit_images` keywords of a config's ``key``,
    checked as a capture file's ``fit:`` section is (the FitOptions fields, their types,
    then FitOptions' own checks): one-line errors naming ``where`` and ``key.FIELD``."""
    from lightfield_jax.capture.keys import read_fit_options

    return read_fit_options(Section(where, "", {key: value}, None), key)


def _type_name(annotation) -> str:
    origin = typing.get_origin(annotation)
    if origin is Annotated:
        return _type_name(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(annotation))
    if annotation is type(None):
        return "null"
    if origin in (tuple, list):
        return "a list"
    if annotation is dict:
        return "a mapping"
    return getattr(annotation, "__name__", None) or str(annotation).replace("typing.", "")


# A sweep larger than this is refused unless allowed (run_experiment's max_cells,
# ``experiment --max-cells``): a config of 10**6 cells would start days of work
# without a word. The shipped full configs count at most a few thousand.
MAX_CELLS = 10_000


# Integer keys that count repetitions of the whole experiment (one cell each).
_COUNT_KEYS = ("seeds",)


def count_cells(config: dict) -> int:
    """An upper estimate of the units of work (cells) an experiment config sweeps,
    from its shape alone (no script loaded): in each mapping, the product of the
    lengths of its lists (each a sweep axis) and of its ``seeds`` count, times the sum
    of the cells of its sub-mappings that sweep something (each a sweep of its own).
    ``experiment`` and ``reduced`` are not counted. Any runner can call it before the
    work starts."""
    return _cells(config, top=True)[0]


def _cells(value: dict, top: bool = False) -> tuple[int, bool]:
    """(cells, whether ``value`` sweeps anything) of one mapping of a config."""
    product, sections, sweeps = 1, 0, False
    for key, item in value.items():
        if top and key in ("experiment", "reduced"):
            continue
        if isinstance(item, list):
            product *= max(1, len(item))
            sweeps = True
        elif key in _COUNT_KEYS and isinstance(item, int) and not isinstance(item, bool):
            product *= max(1, item)
            sweeps = True
        elif isinstance(item, dict):
            cells, inner = _cells(item)
            if inner:
                sections += cells
                sweeps = True
    return product * max(1, sections), sweeps


def check_cells(config: dict, source: str | Path, limit: int | None = MAX_CELLS) -> int:
    """The cells of ``config`` (:func:`count_cells`), refused (a ``ValueError`` naming
    ``source`` and the count) above ``limit`` (``None``: no limit)."""
    cells = count_cells(config)
    if limit is not None and cells > limit:
        raise ValueError(
            f"{source}: sweeps about {cells} cells (the product of its lists' lengths), "
            f"more than the limit of {limit}; a run of that size is meant: give "
            f"--max-cells {cells} (run_experiment(..., max_cells={cells}))"
        )
    return cells
