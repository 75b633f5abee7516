"""The accuracy table of docs/slab_design.md section 6: the slab model's depth average
(n_z = 1) against the 3-D Monte Carlo (layer-averaged, its exact target, and the true
slab), per bounce. The layered model's table: experiments/slab_depth_accuracy.py.

Run: .venv/bin/python docs/slab_accuracy.py [OUT.json]  (about 2 minutes on 2 cores)
"""

import json
import sys

import numpy as np

import lightfield_jax as lfj
from lightfield_jax.forward.slab import SlabRenderer
from lightfield_jax.reference.montecarlo_slab import monte_carlo_slab
from lightfield_jax.scene.geometry import Slab, resolve_slab_grid

W, H, K = 48, 32, 5
beam = lfj.Beam(0, 16, 0.0, 1.0)


def binl1(a, b):
    a = a.reshape(K, H // 4, 4, W // 4, 4).mean((2, 4))
    b = b.reshape(K, H // 4, 4, W // 4, 4).mean((2, 4))
    return np.abs(a - b).sum((1, 2)) / b.sum((1, 2))


rows = []
for name, st, ss, g, h, bd in [
    ("milk", 0.2051, 0.0366 * 4, 0.4, 6.4, "absorbing"),
    ("backward", 0.3, 0.24, -0.3, 6.4, "absorbing"),
    ("backward", 0.3, 0.24, -0.3, 6.4, "refractive"),
    ("forward", 0.1, 0.08, 0.8, 6.4, "absorbing"),
    ("backward thick", 0.3, 0.24, -0.3, 20.0, "refractive"),
]:
    grid, slab = resolve_slab_grid(lfj.Grid(W, H), Slab(h, bd, n_z=1), g, st, ss / st)
    im = np.asarray(SlabRenderer(grid, beam, K, slab)(st, ss, g)[0], np.float64)[0]
    lay = monte_carlo_slab(
        W, H, h, st, ss, g, beam, K, boundary=bd, photons=4_000_000, depth_layers=1, seed=21
    )
    lay2 = monte_carlo_slab(
        W, H, h, st, ss, g, beam, K, boundary=bd, photons=4_000_000, depth_layers=1, seed=22
    )
    true = monte_carlo_slab(W, H, h, st, ss, g, beam, K, boundary=bd, photons=4_000_000, seed=23)
    m = lay.images[0]
    row = dict(
        scene=name,
        sigma_t=st,
        sigma_s=ss,
        g=g,
        h=h,
        boundary=bd,
        n_theta=grid.n_theta,
        n_mu=slab.n_mu,
        l1_vs_layered=binl1(im, m).tolist(),
        mc_noise_l1=binl1(lay2.images[0], m).tolist(),
        sum_vs_layered=(im.sum((1, 2)) / m.sum((1, 2)) - 1).tolist(),
        sum_vs_true_slab=(im.sum((1, 2)) / true.images[0].sum((1, 2)) - 1).tolist(),
        l1_vs_true_slab=binl1(im, true.images[0]).tolist(),
    )
    rows.append(row)
    print(json.dumps(row), flush=True)
json.dump(rows, open(sys.argv[1] if len(sys.argv) > 1 else "slab_accuracy.json", "w"), indent=1)
