"""The tables of docs/slab_depth.md section 7: the linear depth profile against the layer
average.

1. Convergence in depth (no Monte Carlo: the converged depth is 8 linear layers). A
   1-px beam entering at the left wall (y = 8.5 of 24×17), 16 azimuth bins × 8 μ nodes,
   6 orders, float64; per scene the largest error of orders 3–6 in the image sum and in
   the off-beam rows next to the wall (rows 0–6 and 10–16, columns 0–5).
2. Cost: one render of 48×32, full illumination, refractive, g 0.8, 16 × 16 angles,
   10 bounces, float32 (compile, then the fastest of 3 calls).
3. With ``--mc``: the same beam against the 3-D slab Monte Carlo (g 0.9, ω 0.99,
   refractive, 32 × 24 angles, 2 × 1e6 photons), per depth model; then, at 2 linear
   layers, per in-plane discretisation (azimuth bins, μ nodes, spatial refinement).

4. With ``--near-wall`` (alone: the other tables are skipped): the in-plane grid next
   to the entry wall, the same beam against the 3-D slab Monte Carlo at g 0.9, ω 0.99
   (8 × 5e6 photons) and at g 0.8, ω 0.95 (4 × 5e6), per (azimuth bins, μ nodes,
   refinement), 2 linear layers, float32: the errors of orders 2–6 in the image sums,
   the off-beam rows next to the wall (rows 0–6 and 10–16, columns 0–5) and the beam's
   rows there (7–9, columns 0–5), the Monte Carlo's σ of the mean from the spread of its
   runs; the settings, errors, times and the machine's load go to
   docs/slab_near_wall.json.

Run: .venv/bin/python docs/slab_depth_profile.py [--mc | --near-wall]  (about 2 minutes
on 2 cores; 4 more with --mc; about 8 on a shared 2-core machine with --near-wall)
"""

import json
import os
import platform
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import lightfield_jax as lfj
from lightfield_jax.forward.slab import SlabRenderer
from lightfield_jax.reference.montecarlo_slab import monte_carlo_slab
from lightfield_jax.scene.geometry import Slab

W, H, K = 24, 17, 6
BEAM = lfj.Beam(0, 8.5, 0.0, 1.0)
OFF = np.r_[0:7, 10:17]
MODELS = [("constant", n) for n in (1, 2, 4, 8)] + [("linear", n) for n in (1, 2, 4)]


def beam_render(boundary, sigma_t, sigma_s, g, profile, n_z, n_theta=16, n_mu=8):
    slab = Slab(6.4, boundary, n=1.33, n_mu=n_mu, n_z=n_z, depth_profile=profile)
    renderer = SlabRenderer(lfj.Grid(W, H, n_theta, 1), BEAM, K, slab)
    return np.asarray(renderer(sigma_t, sigma_s, g)[0], np.float64)[0]


def orders(image, first=3):
    """Orders ``first``–6: image sums, then the off-beam rows next to the wall."""
    k = first - 1
    return np.concatenate([image[k:].sum((1, 2)), image[k:, OFF, 0:6].sum((1, 2))])


def convergence():
    print("| faces | σt·h | ω | g | " + " | ".join(f"{p} {n}" for p, n in MODELS) + " |")
    scenes = [
        ("absorbing", 1.3, 0.95, 0.8),
        ("absorbing", 0.3, 0.9, -0.3),
        ("absorbing", 3.0, 0.95, 0.4),
        ("refractive", 1.3, 0.99, 0.9),
        ("refractive", 3.0, 0.95, 0.8),
        ("refractive", 0.3, 0.95, -0.3),
    ]
    for boundary, tau, albedo, g in scenes:
        st = tau / 6.4
        ref = orders(beam_render(boundary, st, albedo * st, g, "linear", 8))
        cells = []
        for profile, n_z in MODELS:
            err = 100 * np.abs(
                orders(beam_render(boundary, st, albedo * st, g, profile, n_z)) / ref - 1
            )
            cells.append(f"{err[:4].max():.2f} / {err[4:].max():.2f}")
        print(
            f"| {boundary} | {tau:g} | {albedo:g} | {g:g} | " + " | ".join(cells) + " |", flush=True
        )


def cost():
    print("| profile | n_z | compile s | render s |")
    full = lfj.Full(0.0, "left")
    render = eqx.filter_jit(lambda r, a, b, c: r(a, b, c)[0])
    for profile, n_z in MODELS:
        slab = Slab(6.4, "refractive", n_mu=16, n_z=n_z, depth_profile=profile)
        renderer = SlabRenderer(lfj.Grid(48, 32, 16, 1), full, 10, slab)
        values = [jnp.float32(v) for v in (0.2, 0.19, 0.8)]
        start = time.perf_counter()
        jax.block_until_ready(render(renderer, *values))
        first = time.perf_counter() - start
        runs = []
        for _ in range(3):
            start = time.perf_counter()
            jax.block_until_ready(render(renderer, *values))
            runs.append(time.perf_counter() - start)
        print(f"| {profile} | {n_z} | {first - min(runs):.1f} | {min(runs):.2f} |", flush=True)


def against_monte_carlo():
    st, albedo, g = 0.2, 0.99, 0.9
    mc = np.stack(
        [
            np.asarray(
                monte_carlo_slab(
                    W,
                    H,
                    6.4,
                    st,
                    albedo * st,
                    g,
                    BEAM,
                    K,
                    boundary="refractive",
                    photons=1_000_000,
                    seed=seed,
                    camera_sampling=0.3,
                ).images[0]
            )
            for seed in (31, 32)
        ]
    )
    ref = orders(mc.mean(0))
    half = 100 * np.abs(orders(mc[0]) - orders(mc[1])) / ref / 2
    print(f"Monte Carlo σ of the mean, % (orders 3–6; off-beam rows): {np.round(half, 2)}")
    for profile, n_z in MODELS:
        image = beam_render("refractive", st, albedo * st, g, profile, n_z, 32, 24)
        err = 100 * (orders(image) / ref - 1)
        print(f"{profile} {n_z}: sums {np.round(err[:4], 2)}, off-beam rows {np.round(err[4:], 2)}")
    for n_theta, n_mu, refine in ((32, 24, 1), (64, 24, 1), (128, 24, 1), (32, 48, 1), (32, 24, 2)):
        slab = Slab(6.4, "refractive", n=1.33, n_mu=n_mu, n_z=2)
        renderer = SlabRenderer(lfj.Grid(W, H, n_theta, refine), BEAM, K, slab)
        image = np.asarray(renderer(st, albedo * st, g)[0], np.float64)[0]
        err = 100 * (orders(image, 2) / orders(mc.mean(0), 2) - 1)
        print(
            f"{n_theta} bins × {n_mu} μ, refine {refine} (orders 2–6): sums "
            f"{np.round(err[:5], 2)}, off-beam rows {np.round(err[5:], 1)}"
        )


NEAR_WALL = {
    (0.99, 0.9): (8, ["32x24x1", "32x48x1", "32x24x2", "32x48x2", "32x24x3", "32x48x3",
                      "64x24x2", "32x24x4", "64x24x3", "64x48x3", "64x24x4"]),
    (0.95, 0.8): (4, ["16x16x1", "32x16x2", "64x24x3", "64x48x3"]),
}  # fmt: skip
ON = np.r_[7:10]


def near_wall_groups(image):
    """Orders 2–6: image sums, off-beam rows next to the wall, the beam's rows there."""
    return np.stack(
        [image[1:].sum((1, 2)), image[1:, OFF, 0:6].sum((1, 2)), image[1:, ON, 0:6].sum((1, 2))]
    )


def near_wall():
    st, record = 0.2, {"scenes": [], "load_before": os.getloadavg()}
    record["machine"] = {"cpus": os.cpu_count(), "platform": platform.platform()}
    for (albedo, g), (runs, settings) in NEAR_WALL.items():
        start = time.perf_counter()
        images = np.stack(
            [
                np.asarray(
                    monte_carlo_slab(
                        W, H, 6.4, st, albedo * st, g, BEAM, K, boundary="refractive",
                        photons=5_000_000, seed=seed, camera_sampling=0.3,
                    ).images[0]
                )
                for seed in range(31, 31 + runs)
            ]
        )  # fmt: skip
        mc = np.stack([near_wall_groups(image) for image in images])
        ref = mc.mean(0)
        mc_columns = images.mean(0)[3, OFF, :12].sum(0)
        sigma = 100 * mc.std(0, ddof=1) / np.sqrt(runs) / ref
        scene = {"albedo": albedo, "g": g, "photons": 5_000_000 * runs, "rows": []}
        scene["mc_seconds"] = time.perf_counter() - start
        scene["mc_sigma_percent"] = np.round(sigma, 3).tolist()
        print(f"\nω {albedo}, g {g}: Monte Carlo σ % (sums; off-beam; beam rows, k 2–6):")
        print("  " + " | ".join(" / ".join(f"{v:.2f}" for v in row) for row in sigma))
        print("| θ × μ × refine | image sums | off-beam rows | beam rows | s |")
        for setting in settings:
            n_theta, n_mu, refine = map(int, setting.split("x"))
            start = time.perf_counter()
            slab = Slab(6.4, "refractive", n=1.33, n_mu=n_mu, n_z=2)
            renderer = SlabRenderer(lfj.Grid(W, H, n_theta, refine), BEAM, K, slab)
            image = np.asarray(renderer(st, albedo * st, g)[0], np.float64)[0]
            seconds = time.perf_counter() - start
            err = 100 * (near_wall_groups(image) / ref - 1)
            cells = " | ".join(" / ".join(f"{v:+.1f}" for v in row) for row in err)
            print(f"| {n_theta} × {n_mu} × {refine} | {cells} | {seconds:.0f} |", flush=True)
            columns = 100 * (image[3, OFF, :12].sum(0) / mc_columns - 1)
            scene["rows"].append(
                {
                    "n_theta": n_theta,
                    "n_mu": n_mu,
                    "refine": refine,
                    "error_percent": np.round(err, 3).tolist(),
                    "seconds": seconds,
                    "off_beam_k4_error_percent_by_column": np.round(columns, 2).tolist(),
                }
            )
        record["scenes"].append(scene)
    record["load_after"] = os.getloadavg()
    record["groups"] = "image sums; off-beam rows 0-6, 10-16 x columns 0-5; rows 7-9 x 0-5"
    record["orders"] = [2, 3, 4, 5, 6]
    out = Path(__file__).with_name("slab_near_wall.json")
    out.write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    if "--near-wall" in sys.argv:
        near_wall()
        sys.exit()
    with jax.enable_x64(True):
        convergence()
        if "--mc" in sys.argv:
            against_monte_carlo()
    cost()
