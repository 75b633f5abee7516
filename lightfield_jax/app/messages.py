"""What a command prints: results on stdout (:func:`say`), its own warnings and errors on
stderr as one escaped line each (:func:`warn`, :func:`one_line`), paths as given but
escaped (:func:`shown_path`), the stage display (:func:`command_progress`), and a
capture's errors named by its file (:func:`about_capture`)."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import unicodedata
from collections.abc import Iterator

from lightfield_jax.runtime.progress import MODES, progress

PROG = "lightfield-jax"
PROGRESS_ENV = "LIGHTFIELD_JAX_PROGRESS"

# Escaped in a message line: control characters, format characters (a right-to-left
# override reorders what the terminal shows), and the surrogates a file name in another
# encoding than UTF-8 holds (which a strict stream cannot print).
CONTROLS = ("Cc", "Cf", "Cs")


def one_line(text: str) -> str:
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


def shown_path(path) -> str:
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


def warn(args: argparse.Namespace, text: str) -> None:
    """A warning of the command itself: one line on stderr, collected like the
    package's, whatever the Python warning filters are (``-W error`` must not turn an
    exit status 1 into a traceback)."""
    text = one_line(text)
    args.warnings.append(text)
    print(f"{PROG}: warning: {text}", file=sys.stderr)


def command_progress(args: argparse.Namespace, desc: str, total: int | None = None):
    """The stage display of a command: ``--progress MODE``, else ``$LIGHTFIELD_JAX_PROGRESS``,
    else ``auto``; off with ``--quiet`` unless ``--progress`` is given."""

    given = getattr(args, "progress", None)
    mode = given or os.environ.get(PROGRESS_ENV) or "auto"
    if mode not in MODES:
        raise ValueError(f"{PROGRESS_ENV}: must be one of {', '.join(MODES)}, got {mode!r}")
    if args.quiet and not given:  # --quiet --progress lines: a log's stages, no summary
        mode = "none"
    return progress(desc, total, mode=mode, prefix=f"{PROG}: ")


def say(args: argparse.Namespace, text: str, always: bool = False) -> None:
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

    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # not a file (a test's capture)
        return
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, fd)
    finally:
        os.close(null)


@contextlib.contextmanager
def about_capture(capture) -> Iterator[None]:
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
        raise CaptureError(f"{source}: {one_line(e)}") from e


__all__ = [
    "CONTROLS",
    "PROG",
    "PROGRESS_ENV",
    "about_capture",
    "command_progress",
    "one_line",
    "say",
    "shown_path",
    "warn",
]
