"""Batch fits and sweeps on Dask (issue 48), on a 2-worker local cluster: a batch of
captures (the serial answers, bit for bit), a small sweep, a killed worker, a timeout,
resuming, and the refusals before any work."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from lightfield_jax.app import distributed as dist
from lightfield_jax.app import experiment as _experiment
from lightfield_jax.app.arguments import XLA_CACHE_ENV
from lightfield_jax.app.cli import main

SIMULATE = """\
grid: {{width: 32, height: 24, n_theta: 16, refine: 1}}
medium: {{sigma_t: {sigma_t}, sigma_s: 0.0366, g: 0.4}}
illumination: {{kind: stripes, period: 6, lit: 3}}
gain: 400.0
black_level: 0.02
noise: {{photons: 1.0e5, read: 0.0005, seed: {seed}}}
"""
# No test here may take this long: past it, it fails instead of hanging the suite.
DEADLINE_S = 420


@pytest.fixture(autouse=True)
def _deadline():
    def expired(_signum, _frame):
        raise TimeoutError(f"a Dask test ran past {DEADLINE_S} s")

    before = signal.signal(signal.SIGALRM, expired)
    signal.alarm(DEADLINE_S)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, before)


@pytest.fixture(scope="module")
def client():
    """One local cluster of 2 workers for the module (its start costs seconds)."""
    import cloudpickle

    # The tasks below are this module's functions: sent by value (the workers do not
    # import the test modules).
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    os.environ[XLA_CACHE_ENV] = "off"  # (the workers inherit it)
    try:
        with dist.cluster(workers=2) as c:
            c.wait_for_workers(2, timeout=120)
            yield c
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])


@pytest.fixture
def captures(tmp_path_factory):
    folder = tmp_path_factory.mktemp("captures")
    for name, sigma_t, seed in (("a", 0.2051, 3), ("b", 0.25, 4)):
        config = folder / f"{name}.sim.yaml"
        config.write_text(SIMULATE.format(sigma_t=sigma_t, seed=seed))
        assert main(["simulate", str(config), "--out", str(folder / name), "-q"]) == 0
        config.unlink()
    return folder


def _without_timings(record):
    if isinstance(record, dict):
        return {k: _without_timings(v) for k, v in record.items() if k not in ("seconds", "batch")}
    if isinstance(record, list):
        return [_without_timings(v) for v in record]
    return record


def _context(tmp_path, client, **options):
    ctx = _experiment.Context(
        out=tmp_path, progress=lambda _m: None, reduced=True, keep=tmp_path, **options
    )
    ctx._client = client  # the module's cluster
    return ctx


# ------------------------------------------------------------------------ batch fits


def test_a_batch_of_captures_is_the_serial_fit_and_resumes(captures, tmp_path, client, capsys):
    address = client.scheduler.address
    out = tmp_path / "results"
    argv = ["fit", str(captures), "--out", str(out), "--method", "gradient", "--scheduler"]
    assert main([*argv, address]) == 0, capsys.readouterr().err
    said = capsys.readouterr().out
    assert "2 captures on 2 worker(s): roughly" in said
    assert sorted(p.name for p in out.iterdir()) == [
        "a_capture.json",
        "b_capture.json",
        "summary.csv",
        "summary.json",
    ]
    summary = json.loads((out / "summary.json").read_text())
    assert [c["status"] for c in summary["captures"]] == ["ok", "ok"]
    assert summary["computed"] == 2 and summary["failed"] == 0
    assert {"versions", "machine", "date_utc"} <= set(summary)
    rows = (out / "summary.csv").read_text().splitlines()
    assert rows[0].startswith("name,capture,channel,status,sigma_t") and len(rows) == 3
    # The serial fit of one capture (this process): the same results, bit for bit.
    single = tmp_path / "single.json"
    capture = captures / "a" / "capture.yaml"
    assert main(["fit", str(capture), "--out", str(single), "--method", "gradient", "-q"]) == 0
    serial = json.loads(single.read_text())
    batch = json.loads((out / "a_capture.json").read_text())
    assert _without_timings(batch) == _without_timings(serial)
    assert batch["sigma_t"] == serial["sigma_t"] and batch["g"] == serial["g"]
    # A rerun fits nothing again; one result gone, it fits that capture only.
    stamp = (out / "b_capture.json").stat().st_mtime_ns
    (out / "a_capture.json").unlink()
    assert main([*argv, address, "-q"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert [c["computed"] for c in summary["captures"]] == [True, False]
    assert (out / "b_capture.json").stat().st_mtime_ns == stamp
    assert _without_timings(json.loads((out / "a_capture.json").read_text())) == _without_timings(
        batch
    )


def test_bad_batches_are_refused_in_one_line_before_any_fit(
    captures, tmp_path, capsys, monkeypatch
):
    a, b = captures / "a" / "capture.yaml", captures / "b" / "capture.yaml"
    out = tmp_path / "out"
    cases = [
        ([a, tmp_path / "missing.yaml"], "missing.yaml"),
        ([a, b, "--plot", tmp_path / "f.png"], "--plot: one capture at a time"),
        ([a, a], "given twice"),
        ([a, b, "--channel", "R"], "--channel R: not among its channels"),
        ([a, "--workers", "2"], "--workers: for several captures"),
        ([tmp_path], "a folder without capture files"),
        (
            [a, b, "--scheduler", "tcp://127.0.0.1:9"],
            "--scheduler tcp://127.0.0.1:9: cannot connect",
        ),
    ]
    for args, message in cases:
        status = main(["fit", *map(str, args), "--out", str(out), "-q"])
        err = capsys.readouterr().err.strip()
        assert status == 2 and "\n" not in err and message in err, (args, err)
        assert not out.exists() or not any(out.iterdir()), args
    monkeypatch.setattr(dist, "MAX_TASKS", 1)
    assert main(["fit", str(a), str(b), "--out", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert "2 captures: more than 1 at once; give --allow-large" in err


# ------------------------------------------------------------------------ sweeps


def _cell(a, b):
    import jax.numpy as jnp

    x = jnp.linspace(0.0, 1.0, 1000) * a + b
    return {"a": a, "b": b, "sum": float(jnp.sum(jnp.sin(x) ** 2)), "pid": os.getpid()}


def test_a_small_sweep_is_the_serial_one_and_resumes(tmp_path, client):
    axes = [("a", [0.5, 1.5, 2.5]), ("b", [0.1, 0.2])]

    def key(a, b):
        return f"a{a}|b{b}"

    rows = _context(tmp_path / "dask", client).parallel_sweep(axes, key, _cell)
    serial = _context(tmp_path / "serial", client).sweep(axes, key, _cell)
    strip = [{k: v for k, v in r.items() if k != "pid"} for r in rows]
    assert strip == [{k: v for k, v in r.items() if k != "pid"} for r in serial]  # bit for bit
    assert [(r["a"], r["b"]) for r in rows] == [(a, b) for a in (0.5, 1.5, 2.5) for b in (0.1, 0.2)]
    assert all(r["pid"] != os.getpid() for r in rows)
    # Stored as they completed: a rerun computes nothing (this compute would fail) ...
    ctx = _context(tmp_path / "dask", client)
    assert ctx.parallel_sweep(axes, key, _fails) == rows
    # ... and, one entry gone, only that point.
    entry = ctx._entry(key(a=1.5, b=0.2))
    entry.unlink()
    with pytest.raises(_experiment.ExperimentError, match=r"^1 of 6 sweep points failed"):
        ctx.parallel_sweep(axes, key, _fails)
    assert len(list((tmp_path / "dask" / "cache").iterdir())) == 5


def _fails(a, b):
    raise RuntimeError(f"computed again: {a}, {b}")


def _dies(a, marker_dir):
    """Point 0 works; point 1 kills its worker once (then works); point 2 always does."""
    marker = os.path.join(marker_dir, f"died_{a}")
    if a == 2 or (a == 1 and not os.path.exists(marker)):
        with open(marker, "a") as f:
            f.write("x")
        os._exit(3)
    return {"a": a}


def test_a_killed_worker_is_retried_once_then_a_failure(tmp_path, client):
    ctx = _context(tmp_path, client)
    axes = [("a", [0, 1, 2]), ("marker_dir", [str(tmp_path)])]

    def key(a, marker_dir):
        return f"a{a}"

    with pytest.raises(_experiment.ExperimentError) as info:
        ctx.parallel_sweep(axes, key, _dies)
    message = str(info.value)
    assert message.startswith("1 of 3 sweep points failed (first: a 2, marker_dir ")
    assert "its worker died twice" in message
    assert (tmp_path / "died_1").read_text() == "x"  # died once, then computed
    assert (tmp_path / "died_2").read_text() == "xx"  # retried once, not more
    assert ctx.stored("a0") == {"a": 0} and ctx.stored("a1") == {"a": 1}
    assert ctx.stored("a2") is None  # a failure is never stored as a result
    client.wait_for_workers(2, timeout=300)  # the nannies restart the dead ones (slow when loaded)


def _sleeps(seconds):
    time.sleep(seconds)
    return {"slept": seconds}


def test_a_task_past_its_time_limit_is_a_timeout_record(tmp_path, client):
    ctx = _context(tmp_path, client)
    rows = ctx.parallel_sweep(
        [("seconds", [0.0, 600.0])],
        lambda seconds: f"s{seconds}",
        _sleeps,
        timeout=3.0,
        on_timeout=lambda point, limit: {"timeout_s": limit, **point},
    )
    assert rows == [{"slept": 0.0}, {"timeout_s": 3.0, "seconds": 600.0}]
    assert ctx.stored("s600.0") == {"timeout_s": 3.0, "seconds": 600.0}
    # Without on_timeout it is a failure; the worker that ran it is free again.
    with pytest.raises(_experiment.ExperimentError, match=r"no result within 3 s"):
        ctx.parallel_sweep(
            [("seconds", [600.0])], lambda seconds: f"t{seconds}", _sleeps, timeout=3.0
        )
    client.wait_for_workers(2, timeout=300)  # a restarted worker, on a loaded machine
    again = ctx.parallel_sweep([("a", [1.0, 2.0]), ("b", [0.0])], lambda a, b: f"c{a}{b}", _cell)
    assert [r["a"] for r in again] == [1.0, 2.0]


def test_a_sweep_past_the_limit_is_refused_before_any_work(tmp_path, monkeypatch):
    monkeypatch.setattr(dist, "MAX_TASKS", 3)
    ctx = _experiment.Context(out=tmp_path, progress=lambda _m: None, reduced=True)
    axes = [("a", [1, 2]), ("b", [1, 2])]
    for sweep in (ctx.sweep, ctx.parallel_sweep):
        with pytest.raises(ValueError, match="^4 sweep points: more than 3 at once; give --allow"):
            sweep(axes, lambda a, b: f"{a}{b}", _fails)
    assert ctx._client is None and not any(tmp_path.iterdir())


def test_the_scheduler_comes_from_the_environment(monkeypatch):
    monkeypatch.setenv(dist.SCHEDULER_ENV, "tcp://10.0.0.1:8786")
    assert dist.scheduler_address() == "tcp://10.0.0.1:8786"
    assert dist.scheduler_address("tcp://other:1") == "tcp://other:1"
    monkeypatch.setenv(dist.SCHEDULER_ENV, " ")
    assert dist.scheduler_address() is None


def test_importing_the_package_does_not_import_dask():
    code = (
        "import sys, lightfield_jax, lightfield_jax.app.cli, lightfield_jax.app.experiment\n"
        "bad = [m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed')]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_the_precision_travels_with_the_task(client):
    """A worker computes in the caller's precision (x64 here, float32 in a block)."""
    import jax

    def run(key):
        report = dist.run_tasks(
            [dist.Task(key, key, _dtype)], load=lambda _t: None, save=lambda *_: None, client=client
        )
        return report.results[key]

    wide = run("x")
    with jax.enable_x64(False):
        narrow = run("y")
    assert wide == "float64" and narrow == "float32"


def _dtype():
    import jax.numpy as jnp

    return str(np.asarray(jnp.zeros(1) + 1.0).dtype)
