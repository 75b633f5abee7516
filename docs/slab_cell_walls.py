"""The table of docs/slab_memory.md "The slab's stripe cell": a slab's six-shift stripe
render from one period (SlabCellRenderer: the first ``shift_orders`` orders of every
shift exact, the later ones from the cell with the walls' term of the shifts' mean and,
with ``deviation``, each shift's deviation from it on a coarse discretisation) against
the full slab render.

A 48×36 refractive slab (h 6.4 px, n 1.33, 2 depth layers), six shifts of period-6
stripes from the left wall, ``bounces`` orders, float32. Per medium and scheme: the
worst row of the image of all orders (the largest |Δ| over shifts and columns, as a
fraction of the row's largest value), the worst of the two rows next to the walls and of
the middle half, and the seconds of one warm render of each (the median of 3 calls).

Run: .venv/bin/python docs/slab_cell_walls.py [N_THETA N_MU BOUNCES]  (default 32 16 24;
tens of minutes on 2 cores); writes docs/data/slab_cell_walls.json and prints the table.
"""

import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

import lightfield_jax as lfj
from lightfield_jax.forward.slab import SlabRenderer
from lightfield_jax.forward.slab_cell import SlabCellRenderer
from lightfield_jax.scene.geometry import Slab
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import Stripes

WIDTH, HEIGHT = 48, 36
MEDIA = {  # σt, σs, g (per pixel)
    "milk (ω .18, g .4)": (0.2051, 0.0366, 0.4),
    "ω .95, g .8": (0.2, 0.19, 0.8),
    "ω .99, g .85": (0.2, 0.198, 0.85),
}
SCHEMES = [(3, None), (3, (16, 8)), (3, (32, 8))]


def seconds(renderer, values) -> tuple[np.ndarray, float]:
    images = np.asarray(jax.block_until_ready(renderer(*values)[0]))
    times = []
    for _ in range(3):
        t = time.perf_counter()
        jax.block_until_ready(renderer(*values)[0])
        times.append(time.perf_counter() - t)
    return images, float(np.median(times))


def main(n_theta: int, n_mu: int, bounces: int) -> None:
    slab = Slab(6.4, "refractive", n=1.33, n_mu=n_mu, n_z=2)
    stripes, grid = Stripes(6, 3), Grid(WIDTH, HEIGHT, n_theta, 1)
    full = SlabRenderer(grid, stripes, bounces, slab)
    rows = []
    for name, values in MEDIA.items():
        reference, t_full = seconds(full, values)
        series = reference.sum(1)
        for orders, deviation in SCHEMES:
            cell = SlabCellRenderer(
                grid, stripes, bounces, slab, shift_orders=orders, deviation=deviation
            )
            images, t_cell = seconds(cell, values)
            row = np.max(np.abs(images.sum(1) - series), axis=(0, 2))
            row = row / np.max(series, axis=(0, 2))
            rows.append(
                {
                    "medium": name,
                    "shift_orders": orders,
                    "deviation": deviation,
                    "worst_row": float(row.max()),
                    "walls": float(max(row[0], row[-1])),
                    "middle": float(row[HEIGHT // 4 : 3 * HEIGHT // 4].max()),
                    "full_seconds": t_full,
                    "cell_seconds": t_cell,
                    "load_avg": os.getloadavg()[0],
                }
            )
            r = rows[-1]
            print(
                f"| {name} | {orders} | {deviation or 'none'} | {100 * r['worst_row']:.2f} % "
                f"| {100 * r['walls']:.2f} % | {100 * r['middle']:.3f} % | {t_full:.1f} "
                f"| {t_cell:.1f} | {t_full / t_cell:.1f}× | {r['load_avg']:.1f} |",
                flush=True,
            )
    out = Path(__file__).parent / "data" / "slab_cell_walls.json"
    data = {
        "width": WIDTH,
        "height": HEIGHT,
        "n_theta": n_theta,
        "n_mu": n_mu,
        "n_z": 2,
        "bounces": bounces,
        "rows": rows,
        "machine": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "versions": {"lightfield_jax": lfj.__version__, "jax": jax.__version__},
        "date": time.strftime("%Y-%m-%d"),
    }
    out.write_text(json.dumps(data, indent=1))


if __name__ == "__main__":
    args = [int(a) for a in sys.argv[1:4]] or [32, 16, 24]
    main(*args)
