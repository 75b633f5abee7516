"""Benchmarks. The forward model: compile time, time per bounce, gradient time, peak
memory, and a hardware yardstick (one complex FFT pass over an array of the light
field's size) measured in the same run; the slab against the plane; and the fit
methods, each in a fresh process. Each prints a table and writes JSON; asserts
nothing."""

from __future__ import annotations

import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from lightfield_jax.app.experiment import child_env
from lightfield_jax.forward.render import renderer_for
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import Beam

DEFAULT_SIZES = ((64, 64, 32), (128, 128, 64), (256, 256, 128))
_MILK = (0.2051, 0.0366, 0.4)


def _median_time(fn, repeats: int) -> float:
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def bench_size(width: int, height: int, n_theta: int, repeats: int = 5, bounces: int = 12) -> dict:
    """Measure one grid size (a single beam, float32, the paper's milk)."""
    grid = Grid(width, height, n_theta)
    beam = Beam(0.0, height / 2)
    dtype = jnp.float32
    params = [jnp.asarray(v, dtype) for v in _MILK]

    fft = jax.jit(jnp.fft.fft2)
    field = jnp.ones((n_theta, height, width), jnp.complex64)
    t_fft = _median_time(lambda: fft(field), repeats * 4)

    short = renderer_for(grid, beam, 2, "paper")
    long = renderer_for(grid, beam, bounces, "paper")
    t0 = time.perf_counter()
    jax.block_until_ready(long(*params)[0])
    compile_s = time.perf_counter() - t0
    t_short = _median_time(lambda: short(*params)[0], repeats)
    t_long = _median_time(lambda: long(*params)[0], repeats)
    per_bounce = (t_long - t_short) / (bounces - 2)

    grad_renderer = renderer_for(grid, beam, 10, "paper")

    def loss(p):
        images, _ = grad_renderer(p[0], p[1], p[2])
        return jnp.sum(images**2)

    vg = jax.jit(jax.value_and_grad(loss))
    p0 = jnp.asarray(_MILK, dtype)
    t0 = time.perf_counter()
    jax.block_until_ready(vg(p0))
    grad_compile_s = time.perf_counter() - t0
    t_grad = _median_time(lambda: vg(p0), max(2, repeats // 2))
    t_forward10 = _median_time(lambda: grad_renderer(*params)[0], repeats)
    return {
        "grid": [width, height, n_theta],
        "compile_s": compile_s,
        "first_scatter_s": t_short,
        "per_bounce_s": per_bounce,
        "forward_10_bounces_s": t_forward10,
        "fft_pass_s": t_fft,
        "per_bounce_over_fft": per_bounce / t_fft,
        "grad_compile_s": grad_compile_s,
        "value_and_grad_10_bounces_s": t_grad,
        "grad_over_forward": t_grad / t_forward10,
        "lightfield_mib": width * height * n_theta * 4 / 2**20,
        "peak_rss_mib_so_far": _peak_rss_mib(),
    }


def run_benchmark(sizes=DEFAULT_SIZES, repeats: int = 5, progress=print) -> dict:
    results = []
    for w, h, n in sizes:
        r = bench_size(w, h, n, repeats)
        results.append(r)
        progress(
            f"{w}x{h}x{n}: compile {r['compile_s']:.2f} s | first scatter "
            f"{r['first_scatter_s'] * 1e3:.1f} ms | per bounce {r['per_bounce_s'] * 1e3:.2f} ms "
            f"= {r['per_bounce_over_fft']:.2f}x FFT pass ({r['fft_pass_s'] * 1e3:.2f} ms) | "
            f"10 bounces {r['forward_10_bounces_s'] * 1e3:.1f} ms, value_and_grad "
            f"{r['value_and_grad_10_bounces_s'] * 1e3:.1f} ms ({r['grad_over_forward']:.1f}x) | "
            f"peak RSS {r['peak_rss_mib_so_far']:.0f} MiB"
        )
    return {
        "benchmark": "forward",
        "device": str(jax.devices()[0]),
        "platform": platform.platform(),
        "processor": platform.processor(),
        "jax": jax.__version__,
        "results": results,
    }


def bench_slab(
    width: int = 128,
    height: int = 128,
    thickness: float = 6.4,
    repeats: int = 3,
    fits: bool = True,
    progress=print,
) -> dict:
    """Slab against plane on a 6-phase stripe capture of the paper's milk (issue 7):
    a forward render (compile, run), one forward-mode derivative column (what each
    Levenberg–Marquardt step needs per parameter) and, with ``fits``, a noiseless joint
    fit of each model to its own render (wall time, compile included)."""
    from lightfield_jax.forward.render import make_renderer, resolve_model
    from lightfield_jax.inverse.fit import fit_images
    from lightfield_jax.inverse.options import FitOptions
    from lightfield_jax.scene.geometry import Slab
    from lightfield_jax.scene.illumination import Stripes
    from lightfield_jax.scene.medium import Medium

    stripes = Stripes(6, 3, tuple(range(6)))
    medium = Medium(*_MILK)
    dtype = jnp.float32
    params = [jnp.asarray(v, dtype) for v in _MILK]
    rows = []
    for name, geometry in (
        ("plane", None),
        ("slab absorbing", Slab(thickness)),
        ("slab refractive", Slab(thickness, "refractive")),
    ):
        grid, geo, rho = resolve_model(medium, Grid(width, height), geometry)
        k = 6
        r = make_renderer(grid, stripes, k, "paper", geo)
        t0 = time.perf_counter()
        images = jax.block_until_ready(r(*params)[0])
        compile_s = time.perf_counter() - t0
        run_s = _median_time(lambda r=r: r(*params)[0], repeats)
        column = jax.jit(lambda p, v, r=r: jax.jvp(lambda q: r(q[0], q[1], q[2])[0], (p,), (v,))[1])
        p0 = jnp.asarray(_MILK, dtype)
        e = jnp.asarray([0.0, 0.0, 1.0], dtype)
        t0 = time.perf_counter()
        jax.block_until_ready(column(p0, e))
        column_compile_s = time.perf_counter() - t0
        column_s = _median_time(lambda column=column, p0=p0, e=e: column(p0, e), repeats)
        row = {
            "model": name,
            "grid": [width, height, grid.n_theta],
            "n_mu": getattr(geo, "n_mu", None),
            "bounces": k,
            "patterns": 6,
            "compile_s": compile_s,
            "forward_s": run_s,
            "jvp_column_compile_s": column_compile_s,
            "jvp_column_s": column_s,
        }
        if fits:
            captured = np.asarray(images).sum(axis=1)
            t0 = time.perf_counter()
            fit = fit_images(captured, stripes, options=FitOptions(method="joint", geometry=geo))
            row["joint_fit_s"] = time.perf_counter() - t0
            row["joint_fit_errors"] = {
                "sigma_t": fit.sigma_t / _MILK[0] - 1,
                "sigma_s": fit.sigma_s / _MILK[1] - 1,
                "g": fit.g - _MILK[2],
            }
            row["joint_fit_converged"] = bool(fit.converged)
            row["joint_fit_iterations"] = fit.iterations
        rows.append(row)
        progress(
            f"{name}: {width}x{height}, n_theta {grid.n_theta}"
            + (f", n_mu {row['n_mu']}" if row["n_mu"] else "")
            + f", 6 patterns, {k} bounces: compile {compile_s:.2f} s, forward {run_s:.3f} s, "
            f"one derivative column {column_s:.3f} s"
            + (
                f", joint fit {row['joint_fit_s']:.1f} s ({row['joint_fit_iterations']} steps)"
                if fits
                else ""
            )
        )
    return {
        "benchmark": "slab vs plane",
        "device": str(jax.devices()[0]),
        "platform": platform.platform(),
        "jax": jax.__version__,
        "load_avg": list(os.getloadavg()),
        "results": rows,
    }


# ------------------------------------------------------------------- fit benchmark

# One fit in a fresh process: nothing compiled, no persistent compilation cache.
_FIT_CHILD = r"""
import json, sys, time
t0 = time.perf_counter()
import lightfield_jax
from lightfield_jax.capture.loading import load_capture
from lightfield_jax.inverse.capture_fit import fit_capture
import_s = time.perf_counter() - t0
capture = load_capture(sys.argv[1])
out = {"import_s": import_s}
for name in ("cold", "warm"):
    t, cpu = time.perf_counter(), time.process_time()
    r = fit_capture(capture, sys.argv[2]).results[0]
    out[name] = dict(r.seconds, wall=time.perf_counter() - t, cpu=time.process_time() - cpu)
out["values"] = {k: getattr(r, k) for k in ("sigma_t", "sigma_s", "g")}
out["converged"], out["iterations"] = bool(r.converged), r.iterations
print("RESULT " + json.dumps(out))
"""


def bench_fits(
    config: dict,
    methods: tuple[str, ...] = ("grid", "gradient", "joint"),
    repeats: int = 3,
    progress=print,
) -> dict:
    """Wall time of each fit method on a simulated capture (the demo's by default), each
    fit in a fresh Python process with no compilation cache (what a first fit costs:
    tracing, XLA compilation and the run), then once more in that process (``warm``:
    its compiled programs reused, as for a second channel or the next capture of the
    size). The methods take turns (one process of each, ``repeats`` times), so a change
    in the machine's load falls on all of them alike. Medians over ``repeats``
    processes; errors against the simulated truth; each process's 1-minute load average
    at its start is in its run's record."""

    from lightfield_jax.forward.simulate import simulate_capture, write_simulation
    from lightfield_jax.forward.simulate_config import parse_simulation_config

    sim = simulate_capture(parse_simulation_config(config, source="bench config"))
    truth = sim.truth()
    env = dict(child_env(), JAX_ENABLE_COMPILATION_CACHE="false", LIGHTFIELD_JAX_XLA_CACHE="off")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        write_simulation(sim, Path(tmp))
        capture = str(Path(tmp) / "capture.yaml")
        all_runs: dict[str, list] = {method: [] for method in methods}
        for _ in range(repeats):
            for method in methods:
                load = os.getloadavg()[0]
                done = subprocess.run(
                    [sys.executable, "-c", _FIT_CHILD, capture, method],
                    capture_output=True,
                    text=True,
                    env=env,
                )
                lines = [x for x in done.stdout.splitlines() if x.startswith("RESULT ")]
                if done.returncode or not lines:
                    raise RuntimeError(
                        f"bench --fits: the {method} fit failed: {done.stderr.strip()[-2000:]}"
                    )
                result = json.loads(lines[-1][len("RESULT ") :])
                all_runs[method].append({**result, "load_avg": load})
        first = all_runs[methods[0]]
        for method, runs in all_runs.items():

            def median(get, runs=runs):
                return float(statistics.median(get(r) for r in runs))

            def vs_first(get, runs=runs):  # over the first method's in the same round
                return float(
                    statistics.median(get(r) / get(f) for r, f in zip(runs, first, strict=True))
                )

            values = runs[0]["values"]
            row = {
                "method": method,
                "cold_s": median(lambda r: r["cold"]["total"]),
                "cold_compile_s": median(lambda r: r["cold"]["compile"]),
                "cold_run_s": median(lambda r: r["cold"]["run"]),
                # (the same round: the same load)
                "cold_vs_first": vs_first(lambda r: r["cold"]["total"]),
                # the process's CPU seconds (all its threads): on a machine shared with
                # other work they change less with the load than the wall time does
                "cold_cpu_s": median(lambda r: r["cold"]["cpu"]),
                "cold_cpu_vs_first": vs_first(lambda r: r["cold"]["cpu"]),
                "warm_s": median(lambda r: r["warm"]["total"]),
                "import_s": median(lambda r: r["import_s"]),
                "load_avg": median(lambda r: r["load_avg"]),
                "values": values,
                "errors": {
                    "sigma_t": values["sigma_t"] / truth["sigma_t"] - 1,
                    "sigma_s": values["sigma_s"] / truth["sigma_s"] - 1,
                    "g": values["g"] - truth["g"],
                },
                "converged": runs[0]["converged"],
                "iterations": runs[0]["iterations"],
                "runs": runs,
            }
            rows.append(row)
            e = row["errors"]
            progress(
                f"{method:<9} cold {row['cold_s']:6.2f} s (compile {row['cold_compile_s']:5.2f} s, "
                f"run {row['cold_run_s']:5.2f} s), warm {row['warm_s']:5.2f} s; sigma_t "
                f"{100 * e['sigma_t']:+.2f} %, sigma_s {100 * e['sigma_s']:+.1f} %, g "
                f"{e['g']:+.3f}; cold {row['cold_vs_first']:.2f}x {methods[0]}'s (CPU seconds "
                f"{row['cold_cpu_vs_first']:.2f}x); load "
                f"{row['load_avg']:.1f}"
            )
    return {
        "benchmark": "fit methods, each in a fresh process (no compilation cache)",
        "capture": config,
        "truth": truth,
        "repeats": repeats,
        "device": str(jax.devices()[0]),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "jax": jax.__version__,
        "results": rows,
    }
