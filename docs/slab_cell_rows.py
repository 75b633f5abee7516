"""The table of docs/slab_memory.md "The slab on one period": the slab on one stripe
period (SlabPeriodicCell), rolled to each shift, against the full slab render, per
order and row.

A 20×48 refractive slab (h 3 px, 8 θ bins × 4 μ nodes × 2 linear layers), σt 0.6,
σs 0.55, g 0.6, six shifts of period-6 stripes from the left wall, 5 orders, float32;
per order the largest difference over the shifts and columns, as a fraction of that
order's peak, in rows 0, 6, …, 42.

Run: .venv/bin/python docs/slab_cell_rows.py DIRECTION_DEG  (about a minute on 2 cores)
"""

import dataclasses
import sys

import numpy as np

from lightfield_jax.forward.slab import SlabRenderer
from lightfield_jax.forward.slab_cell import SlabPeriodicCell, shift_rows
from lightfield_jax.scene.geometry import Slab
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import Stripes

HEIGHT, WIDTH, K = 48, 20, 5
direction = float(sys.argv[1]) if len(sys.argv) > 1 else 0.0
slab = Slab(3.0, "refractive", n_mu=4, n_z=2)
stripes = Stripes(6, 3, direction_deg=direction)
full = np.asarray(SlabRenderer(Grid(WIDTH, HEIGHT, 8, 1), stripes, K, slab)(0.6, 0.55, 0.6)[0])
one = dataclasses.replace(stripes, phases=(0,))
cell = SlabPeriodicCell(Grid(WIDTH, 6, 8, 1), one, K, slab, tank_height=HEIGHT)
images = np.asarray(cell(0.6, 0.55, 0.6)[0])[0]
tiled = np.moveaxis(images[:, shift_rows(stripes, HEIGHT)], 0, 1)
print("| k | " + " | ".join(f"row {r}" for r in range(0, HEIGHT, 6)) + " |")
print("|---" * (HEIGHT // 6 + 1) + "|")
for k in range(K):
    error = np.abs(tiled[:, k] - full[:, k]).max(axis=(0, 2)) / full[:, k].max()
    print(f"| {k + 1} | " + " | ".join(f"{e:.1e}" for e in error[::6]) + " |")
