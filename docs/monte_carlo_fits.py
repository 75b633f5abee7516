"""The table of docs/model.md section 6, "The continuum step": forward media fitted on
Monte Carlo captures, the default joint fit (the answer extrapolated to the continuum)
against the model's own answer (``extrapolate: false``).

Each medium is rendered by the package's plane Monte Carlo
(:func:`lightfield_jax.reference.montecarlo.monte_carlo_render`, independent of the grid model) as
six period-6 stripe shifts entering the left wall, 48×36 pixels, normalized phase, two
seeds of ``PHOTONS`` photons averaged, scaled to peak 1, no added noise (the Monte
Carlo's own noise stays). Each capture is fitted by ``fit_images`` (black level 0) both
ways; per fit: the errors (σt and σs relative, g absolute), the reported total 1σ, the
model (θ bins, refinement, the finer model's refinement and the factor κ) and the
seconds. Results, the machine and its load go to docs/data/monte_carlo_fits.json.

Run: .venv/bin/python docs/monte_carlo_fits.py  (about 20 minutes on 2 cores)
"""

import json
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import jax
import numpy as np

import lightfield_jax as lfj
from lightfield_jax.reference.montecarlo import monte_carlo_render

WIDTH, HEIGHT, PHOTONS, SEEDS = 48, 36, 600_000, (21, 22)
MEDIA = [  # name, σt, σs, g, the Monte Carlo's bounces
    ("dense forward", 0.2, 0.16, 0.7, 60),
    ("milk-like", 0.2, 0.19, 0.8, 150),
    ("forward, albedo .99", 0.15, 0.1485, 0.8, 800),
]
WAYS = {"default (extrapolated)": {}, "extrapolate: false": {"extrapolate": False}}
OUT = Path(__file__).parent / "data" / "monte_carlo_fits.json"


def capture(sigma_t, sigma_s, g, bounces):
    images = []
    for seed in SEEDS:
        r = monte_carlo_render(
            WIDTH, HEIGHT, sigma_t, sigma_s, g, lfj.Stripes(), bounces,
            phase="normalized", photons=PHOTONS, seed=seed, batch=100_000,
        )  # fmt: skip
        images.append(np.asarray(r.images, np.float64).sum(axis=1))
    mean = np.mean(images, axis=0)
    return (mean / mean.max()).astype(np.float32)


def fit(images, truth, options):
    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = lfj.fit_images(images, lfj.Stripes(), phase="normalized", black_level=0.0, **options)
    values = {k: getattr(res, k) for k in truth}
    finer = res.model.get("finer_model") or {}
    return {
        "values": values,
        "errors": {k: (values[k] - v) / (v if k != "g" else 1.0) for k, v in truth.items()},
        "sigma": {k: res.uncertainty[k] for k in truth},
        "converged": res.converged,
        "reasons": list(res.reasons),
        "model": {
            "n_theta": res.model.get("n_theta"),
            "refine": res.model.get("refine"),
            "finer_refine": finer.get("refine"),
            "kappa": (finer.get("extrapolation") or {}).get("factor"),
        },
        "seconds": time.perf_counter() - t,
        "load_average_1min": os.getloadavg()[0],
    }


def main():
    rows = []
    for name, st, ss, g, bounces in MEDIA:
        truth = {"sigma_t": st, "sigma_s": ss, "g": g}
        print(f"{name}: Monte Carlo capture ({bounces} bounces)", flush=True)
        images = capture(st, ss, g, bounces)
        for way, options in WAYS.items():
            rec = {"medium": name, **truth, "fit": way, **fit(images, truth, options)}
            rows.append(rec)
            e, s = rec["errors"], rec["sigma"]
            print(
                f"  {way}: σt {100 * e['sigma_t']:+.2f} % (1σ {100 * s['sigma_t'] / st:.2f} %), "
                f"σs {100 * e['sigma_s']:+.2f} % (1σ {100 * s['sigma_s'] / ss:.2f} %), "
                f"g {e['g']:+.4f} (1σ {s['g']:.4f}), converged {rec['converged']}, "
                f"{rec['seconds']:.0f} s",
                flush=True,
            )
    OUT.parent.mkdir(exist_ok=True)
    OUT.write_text(
        json.dumps(
            {
                "width": WIDTH,
                "height": HEIGHT,
                "photons": PHOTONS,
                "seeds": SEEDS,
                "rows": rows,
                "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
                "versions": {"python": sys.version.split()[0], "jax": jax.__version__},
                "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            },
            indent=1,
            default=str,
        )
    )


if __name__ == "__main__":
    main()
