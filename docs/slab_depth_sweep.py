"""The sweep behind default_n_z (docs/slab_depth.md): per scene, the error of the image
sums Σ I_k (k = 1..7) of the slab model at n_z = 1, 2, 4 (default angular
discretisation, resolved without the albedo) against the 3-D slab Monte Carlo
(1e6 photons, camera_sampling 0.3, seed 5), full illumination, 48×32, h 6.4 px, ω 0.9.

Run: .venv/bin/python docs/slab_depth_sweep.py [OUT.json]  (about 40 minutes on 2 cores)
"""

import dataclasses
import json
import sys

import jax
import numpy as np

import lightfield_jax as lfj
from lightfield_jax.forward.slab import SlabRenderer
from lightfield_jax.reference.montecarlo_slab import monte_carlo_slab
from lightfield_jax.scene.geometry import Slab, resolve_slab_grid

jax.config.update("jax_enable_x64", True)
W, H, h, K = 48, 32, 6.4, 7
full = lfj.Full(0.0, "left")
rows = []
for bd in ("refractive", "absorbing"):
    for tau in (0.3, 1.3, 3.0):
        for g in (0.8, 0.9, -0.3, 0.4):
            st = tau / h
            ss = 0.9 * st
            mc = monte_carlo_slab(
                W,
                H,
                h,
                st,
                ss,
                g,
                full,
                K,
                boundary=bd,
                photons=1_000_000,
                seed=5,
                camera_sampling=0.3,
            )
            ref = mc.images[0].sum((1, 2))
            grid, slab = resolve_slab_grid(lfj.Grid(W, H), Slab(h, bd), g)
            row = dict(
                boundary=bd,
                tau=tau,
                g=g,
                n_theta=grid.n_theta,
                n_mu=slab.n_mu,
                stderr=(mc.total_stderr[0] / ref).tolist(),
                errors={},
            )
            for n_z in (1, 2, 4):
                r = SlabRenderer(grid, full, K, dataclasses.replace(slab, n_z=n_z))
                sums = np.asarray(r(st, ss, g)[0], np.float64)[0].sum((1, 2))
                row["errors"][n_z] = (sums / ref - 1).tolist()
            rows.append(row)
            print(json.dumps(row), flush=True)
json.dump(rows, open(sys.argv[1] if len(sys.argv) > 1 else "slab_depth_sweep.json", "w"), indent=1)
