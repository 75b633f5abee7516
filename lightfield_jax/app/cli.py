"""The ``lightfield-jax`` command line.

Each subcommand is one function decorated with :func:`command`, which registers its
name, one-line help and arguments; its docstring is the command's ``--help`` text. The
function receives the parsed arguments (with the common options ``quiet``, ``debug``
and a ``warnings`` list of the warnings issued so far) and returns an exit status
(``None`` for 0). Adding a subcommand is that one function::

    @command("inspect", "summarise a capture file", arg("capture", metavar="CAPTURE.yaml"))
    def _inspect(args: argparse.Namespace) -> int | None:
        \"\"\"Print what a capture holds.\"\"\"
        ...

Conventions every command keeps:

- Errors in the user's input (a bad config or capture, a missing file, an invalid
  value: the :data:`USER_ERRORS`) print one line, ``lightfield-jax: error: ...``, on
  stderr and exit with status 2, without a traceback (``--debug`` shows it). Command
  line syntax errors exit 2 the same way.
- Validate every input before the long work starts: check every output path against
  the inputs and each other with :func:`~lightfield_jax.app.outputs.check_outputs`, and
  the memory the work needs with :func:`~lightfield_jax.runtime.memory.check_memory`. Write
  output folders through :func:`~lightfield_jax.files.atomic_directory` and single files
  through :func:`~lightfield_jax.app.outputs.staged_files`, so a failure leaves no
  partial output and replaces no existing file.
- SIGINT (Ctrl-C), SIGTERM and SIGHUP end a command within a moment, with status 130,
  143 or 129 and nothing written (:mod:`lightfield_jax.app.signals`).
- Results and summaries go to stdout through :func:`~lightfield_jax.app.messages.say`
  (a stdout that fails is said once, at the end, exit status 2); paths printed go
  through :func:`~lightfield_jax.app.messages.shown_path`.
- Warnings print as ``lightfield-jax: warning: ...`` and are collected in
  ``args.warnings`` (e.g. for a metadata file).
- Long work reports its stages through
  :func:`~lightfield_jax.app.messages.command_progress`: on stderr, a display that
  appears when stderr is a terminal and the work takes more than two seconds, else
  one plain line per stage with the elapsed time (``--progress``, ``--quiet``).
- Results and summaries go to stdout (silenced by ``--quiet``).

This module holds the parser and :func:`main`; the helpers the commands share are in
:mod:`~lightfield_jax.app.messages` (what they print) and
:mod:`~lightfield_jax.app.arguments` (argument types, the XLA cache); the
commands live in ``cmd_simulate`` (simulate, bench), ``cmd_fit`` (fit), ``cmd_demo`` (demo),
``cmd_capture`` (pattern, inspect) and ``cmd_render`` (render, experiment), imported at
the end of this module.
"""

from __future__ import annotations

import argparse
import contextlib
import inspect
import sys
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

from lightfield_jax.app.arguments import memory_size
from lightfield_jax.app.messages import PROG, PROGRESS_ENV, one_line
from lightfield_jax.runtime.memory import memory_limit
from lightfield_jax.runtime.progress import MODES

USER_ERRORS: tuple[type[BaseException], ...] = (
    ValueError,  # ConfigError, CaptureError and every validation error are ValueErrors
    FileNotFoundError,
    NotADirectoryError,
    IsADirectoryError,
    PermissionError,
)

Handler = Callable[[argparse.Namespace], "int | None"]
_COMMANDS: dict[str, tuple[str, tuple, Handler]] = {}


def command(name: str, help: str, *arguments: tuple[tuple[str, ...], dict[str, Any]]):
    """Register the decorated function as subcommand ``name`` (see the module docstring)."""

    def register(handler: Handler) -> Handler:
        if name in _COMMANDS:
            raise ValueError(f"subcommand {name!r} is registered twice")
        _COMMANDS[name] = (help, arguments, handler)
        return handler

    return register


class _Parser(argparse.ArgumentParser):
    """An argument parser whose syntax errors are one line on stderr, status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {one_line(message)} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The parser of every registered subcommand."""
    from lightfield_jax import __version__

    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        help="no summary, and no progress display unless --progress is given",
    )
    common.add_argument(
        "--progress",
        choices=MODES,
        metavar="MODE",
        help="how stages are shown on stderr: auto (a bar on a terminal, else one line "
        "per stage with the elapsed time), bar, lines, none (default: "
        f"${PROGRESS_ENV}, else auto; none with --quiet unless given)",
    )
    common.add_argument(
        "--debug", action="store_true", help="show a traceback for errors in the input"
    )
    common.add_argument(
        "--max-memory",
        type=memory_size,
        metavar="SIZE",
        help="memory the command may use (e.g. 16G; default: the machine's available "
        "memory); work estimated to need more is refused before it starts",
    )
    parser = _Parser(
        prog=PROG,
        description="Light transport in thin scattering media (Mukaigawa, Raskar & Yagi, "
        "CVPR 2010): simulate, separate and fit.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (help_text, arguments, handler) in _COMMANDS.items():
        p = sub.add_parser(
            name,
            help=help_text,
            description=inspect.cleandoc(handler.__doc__ or ""),
            parents=[common],
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        for flags, options in arguments:
            p.add_argument(*flags, **options)
        p.set_defaults(handler=handler)
    return parser


# JAX's error for a backend it cannot start (JAX_PLATFORMS=tpu on a machine without one).
_BACKEND_FAILED = "Unable to initialize backend"


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 success, 1 a result that
    cannot be trusted or an experiment that failed while it ran, 2 bad input or an
    output that could not be written: a full disk)."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:  # --help, --version, syntax errors
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
    from lightfield_jax.app.signals import stop_on_signals

    args.warnings = []
    try:
        with (
            warnings_to_stderr(args.warnings),
            stop_on_signals(PROG),
            memory_limit(args.max_memory),
        ):
            _refuse_empty_paths(args)
            status = args.handler(args)
    except USER_ERRORS as e:
        if args.debug:
            raise
        print(f"{PROG}: error: {describe_error(e)}", file=sys.stderr)
        return 2
    except (RecursionError, OverflowError, MemoryError) as e:
        if args.debug:
            raise
        print(f"{PROG}: error: {_describe_limit(e)}", file=sys.stderr)
        return 2
    except OSError as e:  # writing an output failed: a full disk, an I/O error
        if args.debug:
            raise
        print(f"{PROG}: error: {describe_error(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # XLA's allocation failure past the memory estimate
        if not args.debug and _BACKEND_FAILED in str(e):  # JAX_PLATFORMS naming none here
            print(f"{PROG}: error: JAX cannot start: {one_line(str(e))}", file=sys.stderr)
            return 2
        if args.debug or "RESOURCE_EXHAUSTED" not in str(e):
            raise
        print(f"{PROG}: error: {_describe_limit(MemoryError())}", file=sys.stderr)
        return 2
    failed = getattr(args, "stdout_failed", None)
    if failed is not None:
        why = failed.strerror or type(failed).__name__
        print(
            f"{PROG}: error: standard output: {one_line(why)}: the command finished (its "
            "files written), but its report there is incomplete",
            file=sys.stderr,
        )
        return 2
    return 0 if status is None else int(status)


# The options naming an output path (each command has some of them).
PATH_OPTIONS = ("out", "plot", "json", "response")


def _refuse_empty_paths(args: argparse.Namespace) -> None:
    """An empty output path (``--out ''``) is a mistake, not "no output" nor ".": refuse
    it by the option's name; so is ``-``, which means standard output to most tools
    (``--json -`` would write a file named ``-``)."""
    for name in PATH_OPTIONS:
        if getattr(args, name, None) == "":
            raise ValueError(f"--{name}: an empty path")
        if getattr(args, name, None) == "-":
            raise ValueError(
                f"--{name}: '-' (standard output) is not supported; give a file name "
                "(./- for a file named -)"
            )


def _describe_limit(error: BaseException) -> str:
    """A resource limit met despite the checks, as one line (no traceback)."""
    if isinstance(error, RecursionError):
        return "an input is nested too deeply to process (RecursionError)"
    if isinstance(error, OverflowError):
        return f"a value in the input is too large ({one_line(error)[:200]})"
    return "out of memory (MemoryError): reduce the input's size, or free memory"


def describe_error(error: BaseException) -> str:
    if isinstance(error, OSError) and error.filename is not None and error.strerror:
        return one_line(f"{error.filename}: {error.strerror}")
    return one_line(str(error)) or type(error).__name__


@contextlib.contextmanager
def warnings_to_stderr(collected: list[str]) -> Iterator[None]:
    """Show the package's warnings as one line each on stderr, every time, and collect
    them; other warnings keep the filters in force."""
    from lightfield_jax.capture.capture import CaptureWarning
    from lightfield_jax.forward.render import DivergentSeriesWarning
    from lightfield_jax.inverse.programs import (
        CompilationCacheWarning,
        repairing_compilation_cache,
    )

    original = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        if "matplotlib" in Path(str(filename)).parts:  # its own, not the package's
            original(message, category, filename, lineno, file, line)
            return
        text = one_line(str(message))
        collected.append(text)
        print(f"{PROG}: warning: {text}", file=sys.stderr)

    with warnings.catch_warnings():
        for category in (DivergentSeriesWarning, CaptureWarning, CompilationCacheWarning):
            warnings.simplefilter("always", category)
        warnings.showwarning = show
        with repairing_compilation_cache():
            yield


# The demo's capture (the paper's milk); bench --fits times the fits of it too.
DEMO_CONFIG = {
    "grid": {"width": 128, "height": 96},
    "medium": {"sigma_t": 0.2051, "sigma_s": 0.0366, "g": 0.4, "phase": "paper"},
    "illumination": {"kind": "stripes", "period": 6, "lit": 3, "shifts": 6},
    "bounces": "auto",
    "gain": 400.0,
    "black_level": 0.01,
    "noise": {"photons": 20000.0, "read": 0.0005, "seed": 0},
}


# ------------------------------------------------------------------ subcommands

# Each module registers its subcommands on import; --help lists them in this order.
# (Run as ``python -m lightfield_jax.app.cli``, this file is ``__main__``: the
# commands register in lightfield_jax.app.cli, whose main the block below runs.)
if __name__ != "__main__":
    import importlib

    for _module in ("cmd_simulate", "cmd_fit", "cmd_demo", "cmd_capture", "cmd_render"):
        importlib.import_module(f"lightfield_jax.app.{_module}")


if __name__ == "__main__":  # pragma: no cover
    from lightfield_jax.app.cli import main as _main

    sys.exit(_main())
