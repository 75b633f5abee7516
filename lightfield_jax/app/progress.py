"""A stage-by-stage progress display on stderr for long commands.

The display (a tqdm bar) appears only once the work has run for ``delay`` seconds, so
quick commands print nothing; a ticker thread keeps its elapsed time moving while one
long stage (a compile, a render) runs without reporting. tqdm is imported lazily.
"""

from __future__ import annotations

import contextlib
import sys
import threading
from collections.abc import Callable, Iterator
from typing import Any, TextIO

Stage = Callable[[str], None]
"""Called with a stage's name when it starts; the previous stage is then done."""


def quiet(_name: str) -> None:
    """A :data:`Stage` callback that shows nothing."""


@contextlib.contextmanager
def progress(
    desc: str,
    total: int | None = None,
    *,
    enabled: bool | None = None,
    delay: float = 2.0,
    file: TextIO | None = None,
) -> Iterator[Stage]:
    """Show progress through named stages; yields the :data:`Stage` callback.

    Args:
        desc: what runs (the bar's label).
        total: the number of stages, if known (a bar), else a counter.
        enabled: ``True``/``False`` forces the display on/off; ``None`` shows it only
            when ``file`` is a terminal.
        delay: seconds before the display appears.
        file: where to draw it (default ``sys.stderr``).
    """
    file = sys.stderr if file is None else file
    if enabled is None:
        enabled = bool(getattr(file, "isatty", lambda: False)())
    if not enabled:
        yield quiet
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
