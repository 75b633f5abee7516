"""Many fits at once on Dask (``dask.distributed``): batch fits and experiment sweeps.

:func:`run_tasks` runs a list of :class:`Task` (one fit each, or one sweep cell) on a
Dask cluster and stores each result as it completes (``save``), so that a rerun after a
crash or Ctrl-C skips what ``load`` finds and recomputes only what is missing. The
cluster (:func:`cluster`) is an embedded ``LocalCluster`` (one process per worker, one
thread each, JAX's GPU preallocation off) unless a scheduler's address is given
(``--scheduler ADDRESS`` or ``$LIGHTFIELD_JAX_SCHEDULER``).

- A task has a time limit: past it, its result is a timeout (``on_timeout``) or a
  failure, and its worker process is ended (a running XLA program cannot be
  interrupted; the nanny starts a new worker).
- A worker that dies under a task (out of its memory limit, a crash) has the task
  retried once, on the embedded cluster (``allowed-failures: 1``; an external
  scheduler applies its own setting); a second death is a failure of that task, never
  a result. Failures are not stored: the next run tries them again.
- Before any work the number of tasks and a rough time are said; more than
  :data:`MAX_TASKS` tasks are refused unless ``allow_large``.
- A task runs with the caller's precision (x64 on or off), so that its answers are the
  serial run's bit for bit where the programs are the same.

Dask is imported here only: ``import lightfield_jax`` does not import it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import math
import os
import sys
import threading
import time
import types
import uuid
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from lightfield_jax.app.experiment_scripts import SCRIPTS_PACKAGE, load_helper

SCHEDULER_ENV = "LIGHTFIELD_JAX_SCHEDULER"
MAX_TASKS = 10_000
"""A sweep or batch above this many fits is refused unless asked for explicitly."""

# Module prefix of the experiment scripts and their helpers (loaded by path, see
# lightfield_jax.app.experiment_scripts): a worker loads those a task refers to.
_SCRIPTS = f"{SCRIPTS_PACKAGE}."


@dataclasses.dataclass(frozen=True)
class Task:
    """One unit of work: ``fn(*args)`` (JSON-ready result), stored under ``key``;
    ``label`` names it in messages (a capture file, a sweep point)."""

    key: str
    label: str
    fn: Callable[..., Any]
    args: tuple = ()


@dataclasses.dataclass
class Report:
    """What :func:`run_tasks` did: ``results`` (key → value, the stored ones too),
    ``failures`` (key → reason, one line), ``computed`` (keys run this time),
    ``workers`` and ``seconds``."""

    results: dict[str, Any]
    failures: dict[str, str]
    computed: list[str]
    workers: int
    seconds: float


def scheduler_address(given: str | None = None) -> str | None:
    """The scheduler to use: ``given``, else ``$LIGHTFIELD_JAX_SCHEDULER``; ``None``
    (an empty value too): an embedded local cluster."""
    value = given if given is not None else os.environ.get(SCHEDULER_ENV)
    return value.strip() or None if value is not None else None


def default_workers() -> int:
    return max(1, os.cpu_count() or 1)


# A local worker process's own memory before any task: Python, JAX, Dask and this
# package imported (measured: 240 MB resident).
WORKER_BYTES = 256 << 20


def check_workers(workers: int | None) -> None:
    """Refuse more local worker processes than the memory holds before any task runs:
    unchecked, --workers 100000 started a process each (a machine's memory and process
    table exhausted before the first fit)."""
    from lightfield_jax.runtime.memory import check_memory, format_size

    n = workers or default_workers()
    check_memory(
        n * WORKER_BYTES,
        f"--workers {n}: {n} worker processes (about {format_size(WORKER_BYTES)} each "
        "before any task)",
    )


@contextlib.contextmanager
def cluster(
    scheduler: str | None = None,
    *,
    workers: int | None = None,
    memory_limit: int | str | None = None,
) -> Iterator[Any]:
    """A ``distributed.Client``: of the scheduler at ``scheduler`` (or
    ``$LIGHTFIELD_JAX_SCHEDULER``), else of an embedded ``LocalCluster`` with
    ``workers`` processes (default: one per core), one thread each, each with
    ``memory_limit`` bytes (default: the machine's memory shared out; its nanny restarts
    a worker past 95 % of it)."""
    import dask
    from distributed import Client, LocalCluster

    address = scheduler_address(scheduler)
    if address is not None:
        given = "--scheduler" if scheduler is not None else f"${SCHEDULER_ENV}"
        try:
            client = Client(address, timeout="10s")
        except OSError as e:  # (a TimeoutError too)
            raise ValueError(f"{given} {address}: cannot connect ({e})") from None
        except ValueError as e:  # no port, an unknown scheme: Dask's words name no option
            raise ValueError(
                f"{given} {address}: not a scheduler's address ({e}); e.g. tcp://host:8786"
            ) from None
        with client:
            yield client
        return
    check_workers(workers)
    n = workers or default_workers()
    # Each worker allocates GPU memory as it needs it (one accelerator may serve
    # several workers and the client); the user's own setting wins.
    preallocate = "XLA_PYTHON_CLIENT_PREALLOCATE"
    env = {preallocate: os.environ.get(preallocate, "false")}
    settings = {
        "distributed.scheduler.allowed-failures": 1,  # a dead worker's task: retried once
        # One task at a time per worker: a task queued on a worker that dies under
        # another's would count that death as its own.
        "distributed.scheduler.worker-saturation": 1.0,
    }
    with dask.config.set(settings):
        local = LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            memory_limit="auto" if memory_limit is None else memory_limit,
            dashboard_address=None,  # no dashboard per run ...
            # ... and the scheduler's own web server (health checks) on a free port:
            # two runs at once must not fight over the default one.
            scheduler_kwargs={"dashboard_address": ":0"},
            env=env,
            silence_logs=50,  # the workers' restarts are reported per task instead
        )
        try:
            with Client(local) as client:
                yield client
        finally:
            local.close()


def _precision_x64() -> bool:
    """Whether JAX computes in float64 here (the global flag or an ``enable_x64``
    block)."""
    import jax

    return jax.dtypes.canonicalize_dtype(np.float64) == np.float64


def describe_seconds(seconds: float) -> str:
    if seconds < 90:
        return f"{max(1, round(seconds))} s"
    if seconds < 90 * 60:
        return f"{round(seconds / 60)} min"
    return f"{seconds / 3600:.1f} h"


def check_count(n: int, allow_large: bool, what: str = "fits", flag: str = "--allow-large") -> None:
    """Refuse more than :data:`MAX_TASKS` tasks unless ``allow_large`` (before any work:
    a sweep of 10^5 fits is days, and usually a typo in a range)."""
    if n > MAX_TASKS and not allow_large:
        raise ValueError(
            f"{n} {what}: more than {MAX_TASKS} at once; give {flag} to run them anyway"
        )


# ---------------------------------------------------------------- the worker's side

_RUNAWAY = threading.Event()  # a task past its time limit still runs in this worker


def _unpickle(payload: bytes):
    """The task's ``(fn, args)``; the experiment scripts they refer to (modules
    loaded by path, which no import finds) are loaded on the way, as they are asked
    for."""
    import cloudpickle

    sys.modules.setdefault(SCRIPTS_PACKAGE, types.ModuleType(SCRIPTS_PACKAGE))
    loaded: set[str] = set()
    while True:
        try:
            return cloudpickle.loads(payload)
        except ModuleNotFoundError as e:
            name = e.name or ""
            if not name.startswith(_SCRIPTS) or name in loaded:
                raise
            loaded.add(name)
            load_helper(name.removeprefix(_SCRIPTS))


def _run_task(payload: bytes, x64: bool, timeout: float | None):
    """A task's body on a worker: ``("ok", value)`` or ``("timeout", worker address)``;
    an exception of the task is raised (the client reports it)."""
    import jax
    from distributed import Reschedule, get_worker

    if _RUNAWAY.is_set():  # until the client restarts this worker: run it elsewhere
        raise Reschedule()
    fn, args = _unpickle(payload)
    box: dict[str, Any] = {}

    def body() -> None:
        try:
            with jax.enable_x64(x64):
                box["value"] = fn(*args)
        except BaseException as e:  # raised again in the task's thread
            box["error"] = e

    if timeout is None:
        body()
    else:
        # In a thread of its own: past the limit the task's thread returns, and the
        # client restarts this worker (the runaway program stops with its process).
        thread = threading.Thread(target=body, name="lightfield-jax-task", daemon=True)
        thread.start()
        thread.join(timeout)
        if thread.is_alive():
            _RUNAWAY.set()
            return ("timeout", get_worker().address)
    if "error" in box:
        raise box["error"]
    return ("ok", box["value"])


def _end_process() -> None:
    """End this worker's process in a moment (after answering the client)."""
    threading.Timer(0.2, os._exit, (1,)).start()


# ---------------------------------------------------------------- the client's side


def run_tasks(
    tasks: Sequence[Task],
    *,
    load: Callable[[Task], Any],
    save: Callable[[Task, Any], None],
    client=None,
    scheduler: str | None = None,
    workers: int | None = None,
    memory_limit: int | str | None = None,
    timeout: float | None = None,
    on_timeout: Callable[[Task, float], Any] | None = None,
    seconds_per_task: float = 30.0,
    allow_large: bool = False,
    what: str = "fits",
    say: Callable[[str], None] = lambda _m: None,
    show_progress: bool | None = None,
    desc: str = "fits",
) -> Report:
    """Run ``tasks`` on a Dask cluster (``client``, else :func:`cluster`) and store each
    result with ``save(task, value)`` as it completes; ``load(task)`` gives a stored
    result (``None``: none), which is not computed again.

    ``timeout`` (s) bounds each task: its result is then ``on_timeout(task, timeout)``
    (stored like a result: a timeout is data to an experiment), or, without
    ``on_timeout``, a failure. A task whose worker died twice, or which raised, is a
    failure (``Report.failures``, one line each), not stored."""

    check_count(len(tasks), allow_large, what)
    keys = [t.key for t in tasks]
    if len(set(keys)) != len(keys):
        raise ValueError("run_tasks: two tasks share a key")
    started = time.perf_counter()
    results: dict[str, Any] = {}
    pending = []
    for task in tasks:
        stored = load(task)
        if stored is None:
            pending.append(task)
        else:
            results[task.key] = stored
    failures: dict[str, str] = {}
    if not pending:
        say(f"{len(tasks)} {what}: all done already (stored)")
        return Report(results, failures, [], 0, time.perf_counter() - started)
    with contextlib.ExitStack() as stack:
        if client is None:
            client = stack.enter_context(
                cluster(scheduler, workers=workers, memory_limit=memory_limit)
            )
        n_workers = max(1, len(client.scheduler_info(n_workers=-1)["workers"]))
        waves = math.ceil(len(pending) / n_workers)
        done_before = f" ({len(results)} stored, {len(pending)} to run)" if results else ""
        say(
            f"{len(tasks)} {what}{done_before} on {n_workers} worker(s): roughly "
            f"{describe_seconds(waves * seconds_per_task)} (a guess of "
            f"{describe_seconds(seconds_per_task)} per fit; the progress bar measures)"
        )
        computed = _run_pending(
            client, pending, save, timeout, on_timeout, results, failures, show_progress, desc
        )
    return Report(results, failures, computed, n_workers, time.perf_counter() - started)


def _run_pending(client, pending, save, timeout, on_timeout, results, failures, show, desc):
    import cloudpickle
    from distributed import as_completed
    from distributed.client import FutureCancelledError
    from distributed.scheduler import KilledWorker

    from lightfield_jax.runtime.progress import progress_bar

    x64 = _precision_x64()
    futures = {}
    for task in pending:
        payload = cloudpickle.dumps((task.fn, task.args))
        name = hashlib.sha1(task.key.encode()).hexdigest()[:16]
        future = client.submit(
            _run_task, payload, x64, timeout, key=f"lfj-{name}-{uuid.uuid4().hex[:8]}"
        )
        futures[future] = task
    computed = []
    with progress_bar(desc, total=len(pending), enabled=show) as bar:
        try:
            for future in as_completed(list(futures)):
                task = futures[future]
                bar.update(1)
                try:
                    kind, value = future.result()
                except KilledWorker:
                    failures[task.key] = (
                        f"{task.label}: its worker died twice (out of its memory limit, or a "
                        "crash): no result"
                    )
                    continue
                except FutureCancelledError:
                    failures[task.key] = f"{task.label}: cancelled"
                    continue
                except Exception as e:
                    text = " ".join(str(e).split())[:300]
                    failures[task.key] = f"{task.label}: {type(e).__name__}: {text}"
                    continue
                finally:
                    future.release()
                if kind == "timeout":
                    # Its program still runs there: stop it with its process (the
                    # nanny starts a new one), without waiting for that.
                    with contextlib.suppress(Exception):
                        client.run(_end_process, workers=[value])
                    if on_timeout is None:
                        failures[task.key] = f"{task.label}: no result within {timeout:g} s"
                        continue
                    value = on_timeout(task, timeout)
                save(task, value)
                results[task.key] = value
                computed.append(task.key)
        finally:
            for future in futures:
                future.cancel()
    return computed
