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
- Results and summaries go to stdout through :func:`_say` (a stdout that fails is said
  once, at the end, exit status 2); paths printed go through :func:`_path`.
- Warnings print as ``lightfield-jax: warning: ...`` and are collected in
  ``args.warnings`` (e.g. for a metadata file).
- Long work reports its stages through :func:`_progress`: on stderr, a display that
  appears when stderr is a terminal and the work takes more than two seconds, else
  one plain line per stage with the elapsed time (``--progress``, ``--quiet``).
- Results and summaries go to stdout (silenced by ``--quiet``).

This module holds the parser, :func:`main` and the helpers the commands share; the
commands live in ``cmd_simulate`` (simulate, bench), ``cmd_fit`` (fit, demo),
``cmd_capture`` (pattern, inspect) and ``cmd_render`` (render, experiment), imported at
the end of this module.
"""

from __future__ import annotations

import argparse
import contextlib
import inspect
import math
import sys
import unicodedata
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

from lightfield_jax.runtime.progress import MODES, progress

PROG = "lightfield-jax"
PROGRESS_ENV = "LIGHTFIELD_JAX_PROGRESS"
USER_ERRORS: tuple[type[BaseException], ...] = (
    ValueError,  # ConfigError, CaptureError and every validation error are ValueErrors
    FileNotFoundError,
    NotADirectoryError,
    IsADirectoryError,
    PermissionError,
)

Handler = Callable[[argparse.Namespace], "int | None"]
_COMMANDS: dict[str, tuple[str, tuple, Handler]] = {}


def arg(*flags: str, **options: Any) -> tuple[tuple[str, ...], dict[str, Any]]:
    """One argument of a subcommand, as :meth:`argparse.ArgumentParser.add_argument`
    takes it."""
    return flags, options


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
        self.exit(2, f"{self.prog}: error: {_one_line(message)} (see {self.prog} --help)\n")


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
        type=_memory_size,
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


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 success, 1 a result that
    cannot be trusted or an experiment that failed while it ran, 2 bad input or an
    output that could not be written: a full disk)."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:  # --help, --version, syntax errors
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
    from lightfield_jax.app.signals import stop_on_signals
    from lightfield_jax.runtime.memory import memory_limit

    args.warnings = []
    try:
        with (
            _warnings_to_stderr(args.warnings),
            stop_on_signals(PROG),
            memory_limit(args.max_memory),
        ):
            _refuse_empty_paths(args)
            status = args.handler(args)
    except USER_ERRORS as e:
        if args.debug:
            raise
        print(f"{PROG}: error: {_describe(e)}", file=sys.stderr)
        return 2
    except (RecursionError, OverflowError, MemoryError) as e:
        if args.debug:
            raise
        print(f"{PROG}: error: {_describe_limit(e)}", file=sys.stderr)
        return 2
    except OSError as e:  # writing an output failed: a full disk, an I/O error
        if args.debug:
            raise
        print(f"{PROG}: error: {_describe(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # XLA's allocation failure past the memory estimate
        if args.debug or "RESOURCE_EXHAUSTED" not in str(e):
            raise
        print(f"{PROG}: error: {_describe_limit(MemoryError())}", file=sys.stderr)
        return 2
    failed = getattr(args, "stdout_failed", None)
    if failed is not None:
        why = failed.strerror or type(failed).__name__
        print(
            f"{PROG}: error: standard output: {_one_line(why)}: the command finished (its "
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


# Escaped in a message line: control characters, format characters (a right-to-left
# override reorders what the terminal shows), and the surrogates a file name in another
# encoding than UTF-8 holds (which a strict stream cannot print).
CONTROLS = ("Cc", "Cf", "Cs")


def _one_line(text: str) -> str:
    """``text`` on one line: whitespace runs (newlines too) as one space, and other
    control characters and surrogates escaped (``\\x1b``, ``\\udcff``): a file name in a
    capture file holding a terminal escape sequence printed it raw, recolouring or
    rewriting the terminal."""
    flat = " ".join(str(text).split())
    if flat.isprintable():
        return flat
    return "".join(
        c.encode("unicode_escape").decode("ascii") if unicodedata.category(c) in CONTROLS else c
        for c in flat
    )


def _path(path) -> str:
    """A path as a message prints it: as given, its control characters escaped (a
    newline in a file name would split the line, an escape sequence recolour the
    terminal)."""
    text = str(path)
    if text.isprintable():
        return text
    return "".join(
        c.encode("unicode_escape").decode("ascii") if unicodedata.category(c) in CONTROLS else c
        for c in text
    )


def _memory_size(text: str) -> int:
    from lightfield_jax.runtime.memory import parse_size

    try:
        return parse_size(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _describe_limit(error: BaseException) -> str:
    """A resource limit met despite the checks, as one line (no traceback)."""
    if isinstance(error, RecursionError):
        return "an input is nested too deeply to process (RecursionError)"
    if isinstance(error, OverflowError):
        return f"a value in the input is too large ({_one_line(error)[:200]})"
    return "out of memory (MemoryError): reduce the input's size, or free memory"


def _describe(error: BaseException) -> str:
    if isinstance(error, OSError) and error.filename is not None and error.strerror:
        return _one_line(f"{error.filename}: {error.strerror}")
    return _one_line(str(error)) or type(error).__name__


@contextlib.contextmanager
def _warnings_to_stderr(collected: list[str]) -> Iterator[None]:
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
        text = _one_line(str(message))
        collected.append(text)
        print(f"{PROG}: warning: {text}", file=sys.stderr)

    with warnings.catch_warnings():
        for category in (DivergentSeriesWarning, CaptureWarning, CompilationCacheWarning):
            warnings.simplefilter("always", category)
        warnings.showwarning = show
        with repairing_compilation_cache():
            yield


def _warn(args: argparse.Namespace, text: str) -> None:
    """A warning of the command itself: one line on stderr, collected like the
    package's, whatever the Python warning filters are (``-W error`` must not turn an
    exit status 1 into a traceback)."""
    text = _one_line(text)
    args.warnings.append(text)
    print(f"{PROG}: warning: {text}", file=sys.stderr)


def _progress(args: argparse.Namespace, desc: str, total: int | None = None):
    """The stage display of a command: ``--progress MODE``, else ``$LIGHTFIELD_JAX_PROGRESS``,
    else ``auto``; off with ``--quiet`` unless ``--progress`` is given."""
    import os

    given = getattr(args, "progress", None)
    mode = given or os.environ.get(PROGRESS_ENV) or "auto"
    if mode not in MODES:
        raise ValueError(f"{PROGRESS_ENV}: must be one of {', '.join(MODES)}, got {mode!r}")
    if args.quiet and not given:  # --quiet --progress lines: a log's stages, no summary
        mode = "none"
    return progress(desc, total, mode=mode, prefix=f"{PROG}: ")


def _say(args: argparse.Namespace, text: str, always: bool = False) -> None:
    """``text`` on stdout (silenced by ``--quiet`` unless ``always``). A stdout that
    cannot take it (a full disk, a closed pipe) is noted in ``args.stdout_failed`` and
    not written to again: the command finishes its files, and :func:`main` says it."""
    if (args.quiet and not always) or getattr(args, "stdout_failed", None) is not None:
        return
    try:
        print(text)
        sys.stdout.flush()
    except OSError as e:
        args.stdout_failed = e
        _drop_stdout()


def _drop_stdout() -> None:
    """Send what is left in stdout's buffer to /dev/null: the interpreter's flush at
    exit would fail again ("Exception ignored ... BrokenPipeError")."""
    import os

    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # not a file (a test's capture)
        return
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, fd)
    finally:
        os.close(null)


# ------------------------------------------------------------------ compilation cache

XLA_CACHE_ENV = "LIGHTFIELD_JAX_XLA_CACHE"
_XLA_CACHE_HELP = (
    "do not use the persistent XLA compilation cache (also: "
    f"{XLA_CACHE_ENV}=off; {XLA_CACHE_ENV}=DIR moves it)"
)


def xla_cache_folder(environ=None) -> Path | None:
    """Where ``fit`` and ``demo`` keep compiled XLA programs: ``$LIGHTFIELD_JAX_XLA_CACHE``,
    else ``$XDG_CACHE_HOME/lightfield_jax/xla`` (``~/.cache/lightfield_jax/xla``);
    ``None`` when that variable is ``off``, ``0`` or empty."""
    import os

    env = os.environ if environ is None else environ
    value = env.get(XLA_CACHE_ENV)
    if value is not None:
        return None if value.strip().lower() in ("", "0", "off", "no", "false") else Path(value)
    base = env.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "lightfield_jax" / "xla"


def _use_xla_cache(args: argparse.Namespace) -> None:
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
        _warn(args, f"XLA compilation cache off: cannot create {folder} ({e.strerror})")
        return
    import jax
    from jax.experimental.compilation_cache import compilation_cache

    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    compilation_cache.reset_cache()  # set up once per process, at the first compilation


def _outputs(
    files=(),
    folders=(),
    inputs=(),
    plots=(),
    folder_names=(),
    marker=None,
    writer=None,
    json=(),
) -> None:
    """Check every output of a command before its work (see
    :func:`~lightfield_jax.app.outputs.check_outputs`); ``plots`` are figures among
    ``files``, whose format is checked too; ``json``: (option, file, hint) of the JSON
    files among them, whose names must not be an image's or a figure's;
    ``folder_names``: the names written into ``folders``; ``marker``: the command's own
    file (its folders are its own); ``writer``: the command's name where a folder
    without ``marker`` is the user's."""
    from lightfield_jax.app.outputs import check_json_name, check_outputs, check_plot_format

    for plot in plots:
        check_plot_format(plot)
    files, folders = [f for f in files if f], [d for d in folders if d]
    check_outputs(files, folders, inputs, folder_names, marker, writer)
    for option, given, hint in json:
        if given:
            check_json_name(given, option, hint)


@contextlib.contextmanager
def _about(capture) -> Iterator[None]:
    """Errors of the work on ``capture`` name its file, and a numerical library's
    failure (a singular or non-finite solve) is said in the user's terms."""
    import equinox as eqx
    import numpy as np

    from lightfield_jax.capture.io import CaptureError

    source = str(capture.source)
    try:
        with np.errstate(all="ignore"):
            yield
    except (eqx.EquinoxRuntimeError, np.linalg.LinAlgError, FloatingPointError) as e:
        raise CaptureError(
            f"{source}: the solve met a singular or non-finite system: the images do not "
            "determine sigma_t, sigma_s and g (check the capture with lightfield-jax "
            "inspect; --debug shows the library's message)"
        ) from e
    except ValueError as e:
        if source in str(e):
            raise
        raise CaptureError(f"{source}: {_one_line(e)}") from e


# --------------------------------------------------------------------------- shared


def _positive_int(text: str) -> int:
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


_positive_scale = _positive_number("a number > 0")
_positive_seconds = _positive_number("a positive number of seconds")


def _dask_arguments(what: str) -> tuple:
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
            type=_positive_int,
            metavar="N",
            help=f"{what}: worker processes of the local cluster (default: one per core)",
        ),
        arg(
            "--allow-large",
            action="store_true",
            help=f"{what}: run more than 10000 fits at once",
        ),
    )


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

    for _module in ("cmd_simulate", "cmd_fit", "cmd_capture", "cmd_render"):
        importlib.import_module(f"lightfield_jax.app.{_module}")


if __name__ == "__main__":  # pragma: no cover
    from lightfield_jax.app.cli import main as _main

    sys.exit(_main())
