"""Stop a command on Ctrl-C (SIGINT), SIGTERM or SIGHUP (a dropped ssh connection)
within a moment, whatever it computes.

Python runs a signal handler only when the main thread returns to the interpreter,
and a running XLA computation does not: after a ``KeyboardInterrupt`` the main thread
waits in the XLA client for the computation to finish, minutes for a fit. Here the
signal is seen by a watcher thread instead: Python's C-level handler writes the
signal's number to a pipe (:func:`signal.set_wakeup_fd`) at once, the thread removes
the command's unpublished temporary files and folders
(:func:`~lightfield_jax.files.remove_temporaries`) and ends the process with
:func:`os._exit` (status 130 for SIGINT, 143 for SIGTERM, 129 for SIGHUP, as shells
report them), which does not wait for the computation. Nothing was published: outputs replace their
targets only when a command succeeds, so no output is left.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator

from lightfield_jax.files import remove_temporaries

# SIGHUP: the terminal went away (an ssh connection dropped); ended like SIGTERM.
EXIT_STATUS = {signal.SIGINT: 130, signal.SIGTERM: 143, signal.SIGHUP: 129}


def _ignore(signum, frame) -> None:
    """Python-level handler: the watcher thread acts on the signal."""


def _watch(read_fd: int, prog: str) -> None:
    while True:
        data = os.read(read_fd, 1)
        if not data:  # the command ended: the pipe was closed
            return
        if data[0] in {int(s) for s in EXIT_STATUS}:
            break  # else another signal with a Python handler: not ours
    signum = signal.Signals(data[0])
    remove_temporaries()
    with contextlib.suppress(Exception):
        sys.stdout.flush()
        print(f"{prog}: interrupted ({signum.name}): nothing written", file=sys.stderr)
        sys.stderr.flush()
    os._exit(EXIT_STATUS[signum])


@contextlib.contextmanager
def stop_on_signals(prog: str) -> Iterator[None]:
    """Within the block, SIGINT, SIGTERM and SIGHUP end the process at once (see the module
    docstring); a SIGHUP ignored when the command started (``nohup``) stays ignored.
    Outside the main thread (where handlers cannot be set) it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    watched = [
        s for s in EXIT_STATUS if not (s == signal.SIGHUP and signal.getsignal(s) == signal.SIG_IGN)
    ]
    previous = {s: signal.signal(s, _ignore) for s in watched}
    old_fd = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    watcher = threading.Thread(target=_watch, args=(read_fd, prog), daemon=True)
    watcher.start()
    try:
        yield
    finally:
        signal.set_wakeup_fd(old_fd)
        for s, handler in previous.items():
            signal.signal(s, handler)
        os.close(write_fd)
        watcher.join()
        os.close(read_fd)


# The exit status of a command stopped at its time limit (as timeout(1) reports one).
TIME_LIMIT_STATUS = 124


# A limit longer than this (about 31 years) is no limit: a timer thread's wait fails
# beyond threading.TIMEOUT_MAX (9.2e9 s: "timestamp out of range", a traceback printed
# from the thread and the fit then run unbounded), so none is started.
LONGEST_LIMIT = 1e9


@contextlib.contextmanager
def stop_after(seconds: float | None, prog: str, what: str, doing=lambda: "") -> Iterator[None]:
    """Within the block, end the process once ``seconds`` have passed (``None``: no
    limit), whatever it computes (as :func:`stop_on_signals` does: a timer thread removes
    the unpublished temporaries, says so in one line naming ``what`` and ``doing()`` (the
    stage it was in), and exits with :data:`TIME_LIMIT_STATUS`). Leaving the block in
    time cancels it."""
    if seconds is None or seconds > LONGEST_LIMIT:
        yield
        return

    lock, done = threading.Lock(), []

    def stop() -> None:
        with lock:  # held until the exit: the block cannot end (and publish) meanwhile
            if done:
                return  # the block ended first: nothing to stop
            remove_temporaries()
            with contextlib.suppress(Exception):
                sys.stdout.flush()
                stage = doing()
                print(
                    ("\n" if sys.stderr.isatty() else "")  # past a progress bar's line
                    + f"{prog}: {what} ran past its time limit of {seconds:g} s"
                    + (f" (in: {stage})" if stage else "")
                    + ": stopped, nothing written",
                    file=sys.stderr,
                )
                sys.stderr.flush()
            os._exit(TIME_LIMIT_STATUS)

    timer = threading.Timer(seconds, stop)
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        with lock:
            done.append(True)
        timer.cancel()


__all__ = ["EXIT_STATUS", "TIME_LIMIT_STATUS", "stop_after", "stop_on_signals"]
