"""A stage-by-stage progress display on stderr for long commands.

On a terminal the display (a tqdm bar) appears only once the work has run for ``delay``
seconds, so quick commands print nothing; a ticker thread keeps its elapsed time moving
while one long stage (a compile, a render) runs without reporting. Elsewhere (a log
file, a pipe, where a redrawn bar is unreadable) each stage is one plain line with the
elapsed time. tqdm is imported lazily.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any, TextIO

Stage = Callable[[str], None]
"""Called with a stage's name when it starts; the previous stage is then done."""


def quiet(_name: str) -> None:
    """A :data:`Stage` callback that shows nothing."""


MODES: tuple[str, ...] = ("auto", "bar", "lines", "none")
"""How :func:`progress` shows the stages: ``bar`` (a display redrawn in place, for a
terminal), ``lines`` (one plain line per stage with the elapsed time, for a log file or
a pipe), ``none``; ``auto``: ``bar`` on a terminal, else ``lines``."""


def elapsed_text(seconds: float) -> str:
    """``12.3 s`` under a minute, else ``m:ss`` or ``h:mm:ss``."""
    if seconds < 60:
        return f"{seconds:.1f} s"
    m, s = divmod(int(seconds), 60)
    h, m = divmod(m, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


@contextlib.contextmanager
def _lines(desc: str, file: TextIO, prefix: str, heartbeat: float) -> Iterator[Stage]:
    """One line per stage, ``PREFIXdesc: stage [elapsed]``; a stage still running after
    ``heartbeat`` seconds says so again (a solve can run for an hour without a stage)."""
    start = time.monotonic()
    lock = threading.Lock()
    stop = threading.Event()
    current = [None, start]  # the stage, when it was last said

    def say(text: str) -> None:
        print(f"{prefix}{desc}: {text} [{elapsed_text(time.monotonic() - start)}]", file=file)
        file.flush()

    def stage(name: str) -> None:
        with lock:
            current[0], current[1] = name.strip(), time.monotonic()
            say(current[0])

    def beat() -> None:
        while not stop.wait(min(heartbeat, 1.0)):
            with lock:
                if current[0] is not None and time.monotonic() - current[1] >= heartbeat:
                    current[1] = time.monotonic()
                    say(f"still: {current[0]}")

    ticker = threading.Thread(target=beat, name="lightfield-jax-progress", daemon=True)
    ticker.start()
    try:
        yield stage
        with lock:
            say("done")
    finally:
        stop.set()
        ticker.join()


@contextlib.contextmanager
def progress(
    desc: str,
    total: int | None = None,
    *,
    enabled: bool | None = None,
    delay: float = 2.0,
    file: TextIO | None = None,
    mode: str | None = None,
    prefix: str = "",
    heartbeat: float = 60.0,
) -> Iterator[Stage]:
    """Show progress through named stages; yields the :data:`Stage` callback.

    Args:
        desc: what runs (the bar's label).
        total: the number of stages, if known (a bar), else a counter.
        enabled: ``True``/``False`` forces the bar on / the display off; ``None``
            leaves it to ``mode``.
        delay: seconds before the bar appears.
        file: where to draw it (default ``sys.stderr``).
        mode: one of :data:`MODES` (``None``: ``auto``).
        prefix: put before each plain line (``lines``).
        heartbeat: seconds after which a running stage is said again (``lines``).
    """
    file = sys.stderr if file is None else file
    if mode is not None and mode not in MODES:
        raise ValueError(f"progress: mode must be one of {', '.join(MODES)}, got {mode!r}")
    if enabled is not None:
        mode = "bar" if enabled else "none"
    if mode in (None, "auto"):
        mode = "bar" if getattr(file, "isatty", lambda: False)() else "lines"
    if mode == "none":
        yield quiet
        return
    if mode == "lines":
        with _lines(desc, file, prefix, heartbeat) as stage:
            yield stage
        return
    from tqdm import tqdm

    count = "" if total is None else " ({n_fmt}/{total_fmt} done)"
    bar = tqdm(
        desc=desc,
        total=total,
        delay=delay,
        file=file,
        leave=False,
        mininterval=0.0,  # the ticker sets the pace; every stage change redraws
        miniters=0,
        bar_format="{desc}" + count + " [{elapsed}]",
    )
    lock = threading.Lock()
    stop = threading.Event()
    started = [False]

    def stage(name: str) -> None:
        with lock:
            bar.set_description_str(f"{desc}: {name}", refresh=False)
            bar.update(1 if started[0] else 0)
            started[0] = True

    def tick() -> None:
        while not stop.wait(0.25):
            with lock:
                bar.update(0)  # redraws (elapsed time) once the delay has passed

    ticker = threading.Thread(target=tick, name="lightfield-jax-progress", daemon=True)
    ticker.start()
    try:
        yield stage
        with lock:
            if started[0]:
                bar.update(1)
    finally:
        stop.set()
        ticker.join()
        bar.close()


@contextlib.contextmanager
def progress_bar(
    desc: str,
    total: int,
    *,
    enabled: bool | None = None,
    file: TextIO | None = None,
) -> Iterator[Any]:
    """A bar over ``total`` units of work (captures, sweep cells) on stderr: yields an
    object with ``update(n)``; ``enabled`` as in :func:`progress`."""
    file = sys.stderr if file is None else file
    if enabled is None:
        enabled = bool(getattr(file, "isatty", lambda: False)())
    if not enabled:
        yield _NoBar()
        return
    from tqdm import tqdm

    bar = tqdm(desc=desc, total=total, file=file, leave=False, unit="fit")
    try:
        yield bar
    finally:
        bar.close()


class _NoBar:
    def update(self, _n: int = 1) -> None:
        pass
