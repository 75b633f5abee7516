"""The schema every YAML file of the package is read through: a safe loader, one
:class:`Section` per mapping checked against its allowed keys, and typed values whose
errors name the file, the key's path and the offending value.

A YAML file must be a regular file of at most 16 MiB whose aliases expand to at most
:data:`MAX_YAML_VALUES` values (an "alias bomb" is refused before it is built), nested
less deeply than Python's recursion limit. Unknown keys, duplicate keys, wrong types and
out-of-range values are all errors. Float keys accept the strings YAML 1.1 leaves unread
(``1e-4``), no other string (a quoted ``'0.01'``); integer keys accept only integers.
"""

from __future__ import annotations

import difflib
import math
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from lightfield_jax.checks import shown
from lightfield_jax.files import require_regular_file

REQUIRED = object()


class ConfigError(ValueError):
    """An invalid config. The message starts with the file name and names the key."""


# --------------------------------------------------------------------------- YAML


# A config or capture file is a few hundred values; these bound what a hostile file
# (an alias bomb: a few lines whose aliases expand to billions of values) can cost.
MAX_YAML_BYTES = 1 << 24
MAX_YAML_VALUES = 100_000


class _Loader(yaml.SafeLoader):
    """Safe YAML with duplicate keys refused, YAML 1.2 floats (``1e-4`` is a float) and
    documents whose aliases expand past :data:`MAX_YAML_VALUES` values refused before
    they are built."""

    def get_single_data(self):
        node = self.get_single_node()
        if node is None:
            return None
        size, written = _expanded_size(node)
        if size > MAX_YAML_VALUES and written <= MAX_YAML_VALUES:
            raise yaml.YAMLError(
                f"its aliases expand to more than {MAX_YAML_VALUES} values (an alias "
                "bomb?); a config holds a few hundred"
            )
        if size > MAX_YAML_VALUES:  # written out: a long list, no aliases
            raise yaml.YAMLError(
                f"it holds more than {MAX_YAML_VALUES} values; a config holds a few "
                "hundred (many images: give them as one .npy stack)"
            )
        return self.construct_document(node)

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                # ``<<: *base``: merged by SafeLoader (the keys given beside it override
                # the merged ones); constructing it here would fail with "could not
                # determine a constructor for the tag 'tag:yaml.org,2002:merge'".
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                hash(key)
            except TypeError:  # a complex key ("? [a, b]"): before, a TypeError traceback
                mark = key_node.start_mark
                raise yaml.constructor.ConstructorError(
                    None,
                    None,
                    f"a key must be a string, got a {type(key).__name__} (line {mark.line + 1})",
                    mark,
                ) from None
            if key in seen:
                mark = key_node.start_mark
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {key!r} (line {mark.line + 1})", mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep)

    def construct_yaml_int(self, node):
        _refuse_yaml11_only(node)
        try:
            return super().construct_yaml_int(node)
        except ValueError:  # past Python's 4300 digits: a bare ValueError naming no file
            mark, digits = node.start_mark, len(node.value.lstrip("+-"))
            raise yaml.constructor.ConstructorError(
                None,
                None,
                f"an integer of {digits} digits (line {mark.line + 1}) is beyond any value "
                "a config takes",
                mark,
            ) from None

    def construct_yaml_float(self, node):
        _refuse_yaml11_only(node)
        return super().construct_yaml_float(node)


def _refuse_yaml11_only(node) -> None:
    """Refuse the numbers YAML 1.1 (PyYAML) reads otherwise than YAML 1.2 and people
    do: base 60 (``1:30`` is 90, ``1:30.5`` 90.5) and a leading zero that makes another
    octal number (``010`` is 8; ``07`` is 7 either way and kept): a ROI written
    ``[010, 020, 310, 220]`` would be read as ``[8, 16, 310, 220]`` without a word."""
    text = str(node.value).replace("_", "")
    digits = text.lstrip("+-")
    mark = node.start_mark
    where = f"{node.value} (line {mark.line + 1})"
    if ":" in text:
        raise yaml.constructor.ConstructorError(
            None,
            None,
            f"{where} is read by YAML 1.1 as a base-60 number: write it in decimal (or "
            "quote it for a name)",
            mark,
        )
    octal = len(digits) > 1 and digits.startswith("0") and digits.isdigit()
    if octal and set(digits) <= set("01234567") and int(digits, 8) != int(digits, 10):
        raise yaml.constructor.ConstructorError(
            None,
            None,
            f"{where} is read by YAML 1.1 as the octal number {int(text, 8)}: write "
            f"{int(text, 10)} without its leading zero (or quote it for a name)",
            mark,
        )


def _expanded_size(root: yaml.Node) -> tuple[int, int]:
    """The number of values ``root`` holds with every alias expanded, counted once per
    distinct node (memoised, without recursion) and capped just past the limit; and the
    number of distinct nodes (as written, without the aliases' expansion)."""
    sizes: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, finished = stack.pop()
        key = id(node)
        children = _children(node)
        if finished:
            on_path.discard(key)
            sizes[key] = min(1 + sum(sizes[id(c)] for c in children), MAX_YAML_VALUES + 1)
        elif key in on_path:
            raise yaml.YAMLError("an alias refers to a value that contains it (a cycle)")
        elif key not in sizes:
            on_path.add(key)
            stack.append((node, True))
            stack.extend((c, False) for c in children if id(c) not in sizes)
    return sizes[id(root)], len(sizes)


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    return []


# The floats YAML 1.1 (PyYAML's default loader) reads as strings: 1e-4, 2E5.
_YAML11_FLOAT = re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$")
_Loader.add_implicit_resolver("tag:yaml.org,2002:float", _YAML11_FLOAT, list("-+0123456789"))
_Loader.add_constructor("tag:yaml.org,2002:int", _Loader.construct_yaml_int)
_Loader.add_constructor("tag:yaml.org,2002:float", _Loader.construct_yaml_float)


def load_yaml(
    path: str | os.PathLike,
    error: type[ValueError] = ConfigError,
    missing: type[ValueError] | None = None,
) -> dict:
    """Parse a YAML file whose top level is a mapping; errors are ``error`` (a
    :class:`ConfigError` unless the caller reads another kind of file), a missing file
    ``missing`` (default ``error``)."""
    path = Path(path)
    require_regular_file(path, "a YAML file", error, missing)
    if os.path.getsize(path) > MAX_YAML_BYTES:
        raise error(
            f"{path}: {os.path.getsize(path)} bytes is too large for a YAML config "
            f"(at most {MAX_YAML_BYTES})"
        )
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise error(f"{path}: cannot read ({e})") from None
    try:
        data = yaml.load(text, Loader=_Loader)  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError as e:
        raise error(f"{path}: invalid YAML: {' '.join(str(e).split())[:300]}") from None
    except RecursionError:
        raise error(f"{path}: invalid YAML: nested too deeply") from None
    if not isinstance(data, dict):
        raise error(f"{path}: the top level must be a mapping of keys, got {type(data).__name__}")
    return data


# --------------------------------------------------------------------------- typed values


class Section:
    """One mapping of a config, at a key path, checked against its allowed keys.

    Failures raise ``error`` (:class:`ConfigError` unless the file is of another kind,
    e.g. a capture file's ``CaptureError``)."""

    def __init__(
        self,
        source: str,
        path: str,
        value: Any,
        allowed: tuple[str, ...] | None,
        label: str = "",
        error: type[ValueError] = ConfigError,
    ):
        self.source = source
        self.path = path
        self.error = error
        if not isinstance(value, Mapping):
            self.fail(path, f"must be a mapping of keys, got {show(value)}")
        self.data = dict(value)
        for key in self.data:
            if not isinstance(key, str):
                self.fail(self.key(str(key)), f"keys must be strings, got {brief(key)}")
            if allowed is not None and key not in allowed:
                near = difflib.get_close_matches(key, allowed, n=1)
                hint = f" (did you mean {near[0]!r}?)" if near else ""
                self.fail(
                    self.key(key),
                    f"unknown key{hint}; allowed keys{label}: {', '.join(allowed)}",
                )

    def key(self, name: str) -> str:
        return f"{self.path}.{name}" if self.path else name

    def section(self, name: str, allowed: tuple[str, ...] | None, label: str = "") -> Section:
        """The mapping under key ``name`` (required), checked against ``allowed``."""
        return Section(self.source, self.key(name), self.get(name), allowed, label, self.error)

    def fail(self, where: str, message: str):
        raise self.error(f"{self.source}: {where}: {message}")

    def get(self, name: str, default: Any = REQUIRED) -> Any:
        if name not in self.data:
            if default is REQUIRED:
                self.fail(self.key(name), "required key is missing")
            return default
        return self.data[name]

    def float(self, name: str, default: Any = REQUIRED) -> float | None:
        """A number; a null value only where the default is None."""
        if name not in self.data or (self.data[name] is None and default is None):
            return self.get(name, default)
        return as_float(self, self.key(name), self.data[name])

    def int(self, name: str, default: Any = REQUIRED) -> int | None:
        """An integer; a null value only where the default is None."""
        if name not in self.data or (self.data[name] is None and default is None):
            return self.get(name, default)
        return as_int(self, self.key(name), self.data[name])

    def choice(self, name: str, choices: tuple[str, ...], default: Any = REQUIRED) -> str:
        if name not in self.data and default is REQUIRED:
            self.fail(self.key(name), f"required key is missing; one of {', '.join(choices)}")
        value = self.get(name, default)
        if value not in choices:
            self.fail(self.key(name), f"must be one of {', '.join(choices)}, got {show(value)}")
        return value


def brief(value: Any, limit: int = 80) -> str:
    """``repr(value)`` bounded in size (and in the work to build it) for an error
    message: a rejected value may be huge (:func:`lightfield_jax.checks.shown`)."""
    return shown(value, limit)


def show(value: Any) -> str:
    return f"{brief(value)} ({type(value).__name__})"


def _is_float_text(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def as_float(section: Section, where: str, value: Any) -> float:
    # A string is a number only in the form YAML 1.1 leaves unread (a config parsed by
    # PyYAML's default loader); a quoted '0.01' is a string, refused as integer keys
    # refuse a quoted '6'.
    if isinstance(value, str) and not _YAML11_FLOAT.match(value):
        quoted = " (a quoted number: remove the quotes)" if _is_float_text(value) else ""
        section.fail(where, f"must be a number, got {show(value)}{quoted}")
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        section.fail(where, f"must be a number, got {show(value)}")
    try:
        v = float(value)
    except ValueError:
        section.fail(where, f"must be a number, got {show(value)}")
    if not math.isfinite(v):
        section.fail(where, f"must be finite, got {brief(value)}")
    return v


def as_int(section: Section, where: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        section.fail(where, f"must be an integer, got {show(value)}")
    return value


# Images are rendered and written in float32 (at most 3.4e38): image-unit values (gain,
# dark level, read noise) and σt are kept far inside its range.
MAX_VALUE = 1e30


def at_most(s: Section, key: str, value: float, limit: float = MAX_VALUE) -> None:
    if value > limit:
        s.fail(key, f"must be at most {limit:g} (images are float32), got {value!r}")


__all__ = [
    "MAX_VALUE",
    "MAX_YAML_BYTES",
    "MAX_YAML_VALUES",
    "REQUIRED",
    "ConfigError",
    "Section",
    "as_float",
    "as_int",
    "at_most",
    "brief",
    "load_yaml",
    "show",
]
