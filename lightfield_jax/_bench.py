"""Forward-model benchmark: compile time, time per bounce, gradient time, peak memory,
and a hardware yardstick (one complex FFT pass over an array of the light field's size)
measured in the same run. Prints a table and writes JSON; asserts nothing."""

from __future__ import annotations

import platform
import resource
import time

import jax
import jax.numpy as jnp
import numpy as np

from ._grid import Grid
from ._illumination import Beam
from ._render import renderer_for

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
