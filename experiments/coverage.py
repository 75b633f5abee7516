"""Are the reported uncertainties honest? The truth against the reported 1σ over noise seeds.

For each medium of ``media`` a six-shift stripe capture of ``width`` × ``height``
pixels is rendered, scaled to peak 1 and given the package's camera noise (``photons``
at 1, ``read`` σ), one realisation per seed ``seed0 .. seed0 + seeds − 1``, and fitted
by the default joint fit. Per fit: each parameter's error in its reported total 1σ,
z = (fitted − true)/σ, and the Mahalanobis distance of the three errors with the
reported correlations, M² = zᵀ R⁻¹ z, which follows χ² with 3 degrees of freedom where
the errors are Gaussian with the reported covariance.

Per medium: the converged fits, the share of (seed, parameter) pairs with the truth
inside the reported 2σ (0.954 for honest Gaussian errors), the RMS of z per parameter
(1 for honest errors), the mean of M² (3) and its share above χ²₃'s 95 % point 7.81
(0.05), the largest |z| and the median seconds; written to ``coverage.json`` with the
machine and versions, and drawn in ``coverage.png`` (the z's against the unit normal,
M² against χ²₃). A fit that says it did not converge is counted apart: it claims no
uncertainty to check.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
import warnings
from pathlib import Path
from typing import Annotated

import numpy as np

import lightfield_jax as lfj
from lightfield_jax.app.experiment import load_helper
from lightfield_jax.app.experiment_config import (
    Count,
    Pixels,
    Positive,
    Range,
    Seed,
    fit_keywords,
    typed_config,
)
from lightfield_jax.app.experiment_records import provenance, pyplot, save_figure

inv = load_helper("_inverse")

PARAMS = ("sigma_t", "sigma_s", "g")
CHI2_3_95 = 7.814727903251178  # χ²₃'s 95 % point


@dataclasses.dataclass(frozen=True)
class Config:
    """configs/coverage.yaml: the media (name, sigma_t, sigma_s, g, phase), the
    capture's size (pixels), its noise (photons at the peak, read σ), the seeds and
    extra :func:`~lightfield_jax.fit_images` keywords (a capture file's ``fit:`` keys)."""

    media: tuple[Annotated[dict, inv.NamedMedium], ...]
    width: Pixels
    height: Pixels
    photons: Positive
    read: Annotated[float, Range(0)]
    seeds: Count
    seed0: Seed = 0
    fit: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        fit_keywords("coverage", "fit", self.fit)
        if not self.media:
            raise ValueError("coverage: media: at least one")
        names = [m["name"] for m in self.media]
        if len(set(names)) != len(names):
            raise ValueError(f"coverage: media: names must differ, got {names}")
        for m in self.media:
            cfg = inv.capture_config(m, self.width, self.height)
            inv.check_simulation_config(cfg, f"coverage: media {m['name']}")


def _fit(images: np.ndarray, medium: dict, truth: dict, fit: dict) -> dict:
    t = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", lfj.DivergentSeriesWarning)
            # The captures are the model's own renders (inv.OWN_MODEL), unless fit says.
            kwargs = {"phase": medium.get("phase", "paper"), **inv.OWN_MODEL, **fit}
            res = lfj.fit_images(images, lfj.Stripes(), **kwargs)
    except (ValueError, FloatingPointError, RuntimeError) as e:  # data, not a crash
        return {"error_message": f"{type(e).__name__}: {e}", "converged": False}
    sigma = np.array([res.uncertainty[k] for k in PARAMS])
    z = np.array([getattr(res, k) - truth[k] for k in PARAMS]) / sigma
    corr = np.eye(3)
    for i, a in enumerate(PARAMS):
        for j, b in enumerate(PARAMS[i + 1 :], i + 1):
            corr[i, j] = corr[j, i] = res.correlation.get(f"{a},{b}", math.nan)
    try:
        m2 = float(z @ np.linalg.solve(corr, z))
    except np.linalg.LinAlgError:
        m2 = math.nan
    return {
        "values": {k: float(getattr(res, k)) for k in PARAMS},
        "uncertainty": {k: float(s) for k, s in zip(PARAMS, sigma, strict=True)},
        "z": {k: float(v) for k, v in zip(PARAMS, z, strict=True)},
        "m2": m2,
        "chi2_dof": float(res.chi2_dof),
        "model_limited": bool(res.model_limited),
        "converged": bool(res.converged),
        "reasons": list(res.reasons),
        "seconds": time.perf_counter() - t,
    }


def _summary(fits: list[dict]) -> dict:
    ok = [f for f in fits if f["converged"]]
    z = np.array([[f["z"][k] for k in PARAMS] for f in ok]).reshape(-1, 3)
    m2 = np.array([f["m2"] for f in ok])
    return {
        "fits": len(fits),
        "converged": len(ok),
        "inside_2sigma": float(np.mean(np.abs(z) <= 2)) if len(ok) else None,
        "rms_z": {k: float(np.sqrt(np.mean(z[:, i] ** 2))) for i, k in enumerate(PARAMS)}
        if len(ok)
        else None,
        "mean_m2": float(np.mean(m2)) if len(ok) else None,
        "m2_above_95": float(np.mean(m2 > CHI2_3_95)) if len(ok) else None,
        "largest_z": float(np.max(np.abs(z))) if len(ok) else None,
        "median_seconds": float(np.median([f.get("seconds", math.nan) for f in fits])),
    }


def _figure(cfg: Config, records: dict, out: Path) -> Path:
    plt = pyplot()
    fig, axes = plt.subplots(2, len(cfg.media), figsize=(4 * len(cfg.media), 6.4), squeeze=False)
    u = np.linspace(-4, 4, 200)
    x = np.linspace(0, 16, 200)
    for col, m in enumerate(cfg.media):
        ok = [f for f in records[m["name"]] if f["converged"]]
        z = [f["z"][k] for f in ok for k in PARAMS]
        ax = axes[0, col]
        ax.hist(np.clip(z, -4, 4), bins=np.linspace(-4, 4, 17), density=True, alpha=0.6)
        ax.plot(u, np.exp(-(u**2) / 2) / math.sqrt(2 * math.pi), "k-", lw=1)
        ax.set_title(f"{m['name']}: z of σt, σs, g ({len(ok)} fits)", fontsize=9)
        ax.set_xlabel("(fitted − true) / reported 1σ")
        ax = axes[1, col]
        m2 = [f["m2"] for f in ok]
        ax.hist(np.clip(m2, 0, 16), bins=np.linspace(0, 16, 17), density=True, alpha=0.6)
        ax.plot(x, np.sqrt(x / (2 * math.pi)) * np.exp(-x / 2), "k-", lw=1)
        ax.axvline(CHI2_3_95, color="r", lw=0.8)
        ax.set_xlabel("M² (χ²₃ for honest errors; red: 95 %)")
    fig.tight_layout()
    return save_figure(fig, out / "coverage.png")


def run(config: dict, out: Path, ctx) -> dict:
    cfg = typed_config(Config, config)
    records, rows = {}, []
    for m in cfg.media:
        truth = inv.truth_of(m)
        clean = np.asarray(inv.simulate(inv.capture_config(m, cfg.width, cfg.height)).images)
        fits = []
        for seed in range(cfg.seed0, cfg.seed0 + cfg.seeds):
            ctx.progress(f"{m['name']}: seed {seed}")
            key = f"coverage {m} {cfg.width}x{cfg.height} {cfg.photons} {cfg.read} {seed}"
            if cfg.fit:
                key += f" {json.dumps(cfg.fit, sort_keys=True)}"

            def compute(seed=seed, m=m, truth=truth, clean=clean):
                images = inv.camera(clean, (cfg.photons, cfg.read), seed)
                return {"seed": seed, **_fit(images, m, truth, cfg.fit)}

            fits.append(ctx.cached(key, compute))
        records[m["name"]] = fits
        rows.append({"medium": m["name"], **_summary(fits)})
        r = rows[-1]
        ctx.progress(
            f"{m['name']}: {r['converged']}/{r['fits']} converged, truth inside 2 sigma "
            f"{r['inside_2sigma']}, RMS z {r['rms_z']}, mean M2 {r['mean_m2']}"
        )
    figure = _figure(cfg, records, out)
    data = {"config": config, "rows": rows, "records": records, **provenance()}
    ctx.write_json("coverage.json", inv.jsonable(data))
    return {"rows": inv.jsonable(rows), "figures": [figure.name], "data": ["coverage.json"]}
