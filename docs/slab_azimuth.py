"""The tables of docs/slab_depth.md section 8 ("Angles far from the entry wall"): how many
azimuth bins and elevation nodes the slab's later bounces need.

A 48×36 refractive slab (h 6.4 px, n 1.33, σt 0.2), full illumination from the left
wall, elevation nodes and depth layers from g and the albedo (``Slab.resolve``), 24
orders and the rest of the series by a GMRES tail, float32. Per medium (g, ω) and
azimuth bins: the image's total, its far half (columns 24–47) and its worst column
against the finest count's (64 bins), in per cent. Then, at g 0.8 and ω 0.95, pairs of
(azimuth bins, elevation nodes) against 64 bins and 16 nodes.

Run: .venv/bin/python docs/slab_azimuth.py  (about half an hour on 2 cores); writes
docs/data/slab_azimuth.json and prints the table.
"""

import json
import os
import time
from pathlib import Path

import jax
import numpy as np

from lightfield_jax.app.experiment_records import provenance
from lightfield_jax.forward.slab import SlabRenderer
from lightfield_jax.scene.geometry import Slab
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import Full

WIDTH, HEIGHT, SIGMA_T, BOUNCES = 48, 36, 0.2, 24
MEDIA = [(0.3, 0.95), (0.5, 0.95), (0.7, 0.8), (0.7, 0.95), (0.8, 0.8), (0.8, 0.95), (0.8, 0.99)]
BINS = [8, 16, 32, 64]
PAIRS = [(64, 16), (32, 24), (32, 16), (32, 8), (32, 4), (16, 16), (16, 8)]


def render(
    g: float, albedo: float, n_theta: int, n_mu: int | None = None
) -> tuple[np.ndarray, float, Slab]:
    slab = Slab(6.4, "refractive", n=1.33, n_mu=n_mu).resolve(g, sigma_t=SIGMA_T, albedo=albedo)
    renderer = SlabRenderer(
        Grid(WIDTH, HEIGHT, n_theta, 1), Full(entry="left"), BOUNCES, slab, tail="gmres"
    )
    t = time.perf_counter()
    out = renderer(SIGMA_T, SIGMA_T * albedo, g)
    image = np.asarray(jax.block_until_ready(out[0]), np.float64).sum(axis=(0, 1))
    image = image + np.asarray(out[2].image, np.float64)[0]
    return image, time.perf_counter() - t, slab


def compared(image: np.ndarray, reference: np.ndarray) -> dict:
    """Total, far half and worst column of ``image`` against ``reference`` (fractions)."""
    far = slice(WIDTH // 2, None)
    column = np.abs(image.sum(0) / reference.sum(0) - 1)
    return {
        "total": float(image.sum() / reference.sum() - 1),
        "far_half": float(image[:, far].sum() / reference[:, far].sum() - 1),
        "worst_column": float(column.max()),
        "load_avg": os.getloadavg()[0],
    }


def main() -> None:
    rows, pairs = [], []
    for g, albedo in MEDIA:
        images = {}
        for n_theta in BINS:
            images[n_theta], seconds, slab = render(g, albedo, n_theta)
            print(f"g {g} ω {albedo} {n_theta} bins: {seconds:.1f} s", flush=True)
        for n_theta in BINS[:-1]:
            rows.append(
                {
                    "g": g,
                    "albedo": albedo,
                    "n_theta": n_theta,
                    "reference_n_theta": BINS[-1],
                    "n_mu": slab.n_mu,
                    "n_z": slab.n_z,
                    **compared(images[n_theta], images[BINS[-1]]),
                }
            )
    reference = None
    for n_theta, n_mu in PAIRS:
        image, seconds, slab = render(0.8, 0.95, n_theta, n_mu)
        print(f"g 0.8 ω 0.95 {n_theta} bins, {n_mu} nodes: {seconds:.1f} s", flush=True)
        if reference is None:
            reference = image
            continue
        pairs.append(
            {"n_theta": n_theta, "n_mu": n_mu, "n_z": slab.n_z, **compared(image, reference)}
        )
    out = {
        "rows": rows,
        "angle_pairs": {"g": 0.8, "albedo": 0.95, "reference": list(PAIRS[0]), "rows": pairs},
        "setup": {
            "width": WIDTH,
            "height": HEIGHT,
            "sigma_t": SIGMA_T,
            "bounces": BOUNCES,
            "tail": "gmres",
            "slab": "refractive, h 6.4, n 1.33",
            "dtype": "float32",
        },
        **provenance(),
    }
    path = Path(__file__).parent / "data" / "slab_azimuth.json"
    path.write_text(json.dumps(out, indent=1))
    print("| g | ω | μ nodes | bins | total | far half | worst column |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['g']} | {r['albedo']} | {r['n_mu']} | {r['n_theta']} | "
            f"{100 * r['total']:+.2f} % | {100 * r['far_half']:+.2f} % | "
            f"{100 * r['worst_column']:.2f} % |"
        )
    print("| bins × nodes | total | far half | worst column |")
    print("|---|---|---|---|")
    for r in pairs:
        print(
            f"| {r['n_theta']} × {r['n_mu']} | {100 * r['total']:+.2f} % | "
            f"{100 * r['far_half']:+.2f} % | {100 * r['worst_column']:.2f} % |"
        )


if __name__ == "__main__":
    main()
