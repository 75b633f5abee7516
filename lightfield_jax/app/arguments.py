"""The argument types and options the commands share: positive numbers, memory sizes,
the Dask options, and the persistent XLA compilation cache (``--no-xla-cache``)."""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import Any

from lightfield_jax.app.messages import warn
from lightfield_jax.runtime.memory import parse_size


def arg(*flags: str, **options: Any) -> tuple[tuple[str, ...], dict[str, Any]]:
    """One argument of a subcommand, as :meth:`argparse.ArgumentParser.add_argument`
    takes it."""
    return flags, options


def memory_size(text: str) -> int:

    try:
        return parse_size(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}")
    return value


def _positive_number(what: str):
    """An argparse type: a finite number > 0, refused as "must be WHAT, got ..."."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value > 0):
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
        return value

    return parse


positive_scale = _positive_number("a number > 0")
positive_seconds = _positive_number("a positive number of seconds")


def dask_arguments(what: str) -> tuple:
    """The options of work run on Dask (``what``: where they apply)."""
    return (
        arg(
            "--scheduler",
            metavar="ADDRESS",
            help=f"{what}: the Dask scheduler to run on (e.g. tcp://host:8786; also "
            "$LIGHTFIELD_JAX_SCHEDULER; default: a local cluster of --workers processes)",
        ),
        arg(
            "--workers",
            type=positive_int,
            metavar="N",
            help=f"{what}: worker processes of the local cluster (default: one per core)",
        ),
        arg(
            "--allow-large",
            action="store_true",
            help=f"{what}: run more than 10000 fits at once",
        ),
    )


# ------------------------------------------------------------------ compilation cache

XLA_CACHE_ENV = "LIGHTFIELD_JAX_XLA_CACHE"
XLA_CACHE_HELP = (
    "do not use the persistent XLA compilation cache (also: "
    f"{XLA_CACHE_ENV}=off; {XLA_CACHE_ENV}=DIR moves it)"
)


def xla_cache_folder(environ=None) -> Path | None:
    """Where ``fit`` and ``demo`` keep compiled XLA programs: ``$LIGHTFIELD_JAX_XLA_CACHE``,
    else ``$XDG_CACHE_HOME/lightfield_jax/xla`` (``~/.cache/lightfield_jax/xla``);
    ``None`` when that variable is ``off``, ``0`` or empty."""

    env = os.environ if environ is None else environ
    value = env.get(XLA_CACHE_ENV)
    if value is not None:
        off = value.strip().lower() in ("", "0", "off", "no", "false")
        return None if off else Path(value).expanduser()
    base = env.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "lightfield_jax" / "xla"


def use_xla_cache(args: argparse.Namespace) -> None:
    """Turn on JAX's persistent compilation cache (every program, however small or
    quick to compile) unless ``--no-xla-cache`` or the environment turns it off. A fit
    spends most of its time on a CPU compiling; a later fit of a capture of the same
    shape and model size loads the programs instead (a warm start). A folder that cannot
    be created leaves the cache off, with a warning."""
    folder = None if args.no_xla_cache else xla_cache_folder()
    if folder is None:
        return
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        warn(args, f"XLA compilation cache off: cannot create {folder} ({e.strerror})")
        return
    from lightfield_jax.inverse.programs import use_compilation_cache

    use_compilation_cache(folder)


__all__ = [
    "XLA_CACHE_ENV",
    "XLA_CACHE_HELP",
    "arg",
    "dask_arguments",
    "memory_size",
    "positive_int",
    "positive_scale",
    "positive_seconds",
    "use_xla_cache",
    "xla_cache_folder",
]
