"""Counting the XLA programs a call builds, compiled or loaded from the persistent
compilation cache the tests keep (conftest.py): a program kept in the process is
neither."""

from __future__ import annotations

_BUILT = ("/jax/core/compile/backend_compile_duration", "/jax/compilation_cache/cache_hits")


def programs_built(fn) -> int:
    """How many XLA programs ``fn()`` compiled or loaded from the persistent cache."""
    from jax import monitoring

    count = []

    def on_duration(name, secs, **kwargs):
        if name == _BUILT[0]:
            count.append(name)

    def on_event(name, **kwargs):
        if name == _BUILT[1]:
            count.append(name)

    monitoring.register_event_duration_secs_listener(on_duration)
    monitoring.register_event_listener(on_event)
    try:
        fn()
    finally:
        monitoring.unregister_event_duration_listener(on_duration)
        monitoring.unregister_event_listener(on_event)
    return len(count)
