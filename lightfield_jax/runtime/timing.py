"""Wall time split into compilation and run time, from JAX's own compile events."""

from __future__ import annotations

import contextlib
import dataclasses
import statistics
import threading
import time
from collections.abc import Iterator

# Trace, lowering and XLA compilation: the events JAX records with a time span for every
# compile (jax._src.dispatch); nested traces overlap, so their spans are merged.
_COMPILE_EVENTS = frozenset(
    {
        "/jax/core/compile/jaxpr_trace_duration",
        "/jax/core/compile/jaxpr_to_mlir_module_duration",
        "/jax/core/compile/backend_compile_duration",
    }
)


@dataclasses.dataclass
class Timing:
    """Seconds spent in a :func:`stopwatch` block: ``total``, of which ``compile`` went to
    tracing and compiling JAX functions, and ``run`` (= total − compile) to the rest."""

    total: float = 0.0
    compile: float = 0.0

    @property
    def run(self) -> float:
        return max(self.total - self.compile, 0.0)


def _union_length(spans: list[tuple[float, float]]) -> float:
    length, end = 0.0, -float("inf")
    for start, stop in sorted(spans):
        if stop > end:
            length += stop - max(start, end)
            end = stop
    return length


@contextlib.contextmanager
def stopwatch() -> Iterator[Timing]:
    """Time a block; the yielded :class:`Timing` is filled in when the block ends.

    Compile time counts the JAX compiles started by this thread inside the block (a
    function already compiled in this process costs none).
    """
    import jax.monitoring

    spans: list[tuple[float, float]] = []
    thread = threading.get_ident()

    def listener(event: str, start: float, end: float, **_kwargs) -> None:
        if event in _COMPILE_EVENTS and threading.get_ident() == thread:
            spans.append((start, end))

    timing = Timing()
    jax.monitoring.register_event_time_span_listener(listener)
    t0 = time.perf_counter()
    try:
        yield timing
    finally:
        timing.total = time.perf_counter() - t0
        jax.monitoring.unregister_event_time_span_listener(listener)
        timing.compile = min(_union_length(spans), timing.total)


def repeated_calls(call, repeats: int, long_call_s: float = 10.0) -> dict:
    """Time ``call()``: its first call (compile + run, split by :func:`stopwatch`) and the
    median of ``repeats`` steady calls; a first call that runs longer than
    ``long_call_s`` is not repeated (its run time counts). Returns ``first_call_s``,
    ``compile_s``, ``seconds`` (the median), ``fastest_s`` (the least: on a shared
    machine the call least slowed by others), ``times_s`` and the last call's ``out``."""
    with stopwatch() as first:
        out = call()
    times = [first.run] if first.run > long_call_s else []
    for _ in range(repeats if not times else 0):
        t0 = time.perf_counter()
        out = call()
        times.append(time.perf_counter() - t0)
    return {
        "first_call_s": first.total,
        "compile_s": first.compile,
        "seconds": float(statistics.median(times)),
        "fastest_s": float(min(times)),
        "times_s": times,
        "out": out,
    }
