"""How well is a clipped capture fitted, masked per pixel or per value?

A camera clips the brightest values of a stripe capture: the lit stripes near the
entry wall. The paper's milk (``medium``) as a six-shift stripe capture of
``width`` × ``height`` pixels, scaled to peak 1 with camera noise (``photons`` at 1,
``read`` σ, one realisation per seed of ``seeds``), is clipped at each level of
``clips`` (a fraction of the peak; 1: not clipped) and fitted by the default joint
fit twice:

- ``pixel``: ``fit_images(mask=...)`` with every pixel clipped in some shift masked in
  all of them (what a per-pixel mask leaves the fit: the far field);
- ``value``: ``fit_images(saturation=...)``, the clipped values masked one at a time
  (a pixel keeps its dark shifts) and the values the answer puts within 3σ of the clip
  masked too (the clip's censoring; docs/model.md §6).

With ``clamp_zero``, each seed's capture is also fitted with its values clamped at 0
(what a 16-bit file or a camera's black subtraction writes: the read noise of the dark
far field cut at 0), unclipped above: mask ``floor``, the package's default fit (the
pile-up at 0 found, masked, and the values the answer puts within 3σ of it masked too).

Per fit: the errors (σt and σs relative, g absolute), the reported total 1σ, each
error in those 1σ, converged or not, seconds. Per (clip, mask): the share of
(seed, parameter) pairs with the truth inside the reported total 2σ among the
converged fits, the largest |error| in σ, the converged count and the median seconds;
written to ``clipped_captures.json`` with the machine and versions.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Annotated

import numpy as np

import lightfield_jax as lfj
from lightfield_jax.app.experiment import load_helper
from lightfield_jax.app.experiment_config import Pixels, Positive, Range, Seed, typed_config
from lightfield_jax.app.experiment_records import provenance

inv = load_helper("_inverse")

MASKS = ("pixel", "value")
PARAMS = ("sigma_t", "sigma_s", "g")


@dataclasses.dataclass(frozen=True)
class Config:
    """configs/clipped_captures.yaml: the medium (sigma_t, sigma_s, g, phase), the
    capture's size (pixels), its noise (photons at the peak, read σ), the clip levels
    (fractions of the peak) and the noise seeds."""

    medium: Annotated[dict, inv.MediumSpec]
    width: Pixels
    height: Pixels
    photons: Positive
    read: Annotated[float, Range(0)]
    clips: tuple[Annotated[float, Range(0, 1, open_low=True)], ...]
    seeds: tuple[Seed, ...]
    clamp_zero: bool = False

    def __post_init__(self):
        if not self.clips:
            raise ValueError("clipped_captures: clips: at least one")
        if not self.seeds:
            raise ValueError("clipped_captures: seeds: at least one")
        if self.width < 16:
            raise ValueError(f"clipped_captures: width: at least 16, got {self.width}")
        capture = inv.capture_config(self.medium, self.width, self.height)
        inv.check_simulation_config(capture, "clipped_captures")  # the medium's ranges


def _fit(images: np.ndarray, level: float, mask: str, cfg: Config, truth: dict) -> dict:
    clipped = np.minimum(images, level)
    hit = images >= level
    kwargs = {"black_level": 0.0, "phase": cfg.medium.get("phase", "paper")}
    if mask == "pixel":
        kwargs["mask"] = ~hit.any(axis=0)
    elif mask == "value":
        kwargs["saturation"] = level
    else:  # floor: clamped at 0 below, not clipped above
        clipped = np.clip(images, 0.0, None)
        hit = clipped == 0.0
    t = time.perf_counter()
    try:
        res = lfj.fit_images(clipped, lfj.Stripes(), **kwargs)
    except ValueError as e:  # e.g. no pixel valid in every shift: data, not a crash
        return {"error_message": str(e), "converged": False, "seconds": time.perf_counter() - t}
    errors, sigmas = {}, {}
    for k in PARAMS:
        value, one = getattr(res, k), res.uncertainty[k]
        err = value - truth[k] if k == "g" else value / truth[k] - 1.0
        errors[k] = err
        sigmas[k] = (value - truth[k]) / one if one > 0 else math.inf
    return {
        "values": {k: getattr(res, k) for k in PARAMS},
        "errors": errors,
        "uncertainty": {k: res.uncertainty[k] for k in PARAMS},
        "sigmas": sigmas,
        "converged": bool(res.converged),
        "reasons": list(res.reasons),
        "censoring": res.model.get("censoring"),
        "seconds": time.perf_counter() - t,
        "values_clipped": int(hit.sum()),
        "pixels_clipped": int(hit.any(axis=0).sum()),
    }


def _summary(fits: list[dict]) -> dict:
    ok = [f for f in fits if f["converged"]]
    z = [abs(f["sigmas"][k]) for f in ok for k in PARAMS]
    return {
        "fits": len(fits),
        "converged": len(ok),
        "inside_2sigma": sum(v <= 2 for v in z) / len(z) if z else None,
        "largest_sigmas": max(z) if z else None,
        "largest_errors": {k: max((abs(f["errors"][k]) for f in ok), default=None) for k in PARAMS},
        "median_seconds": float(np.median([f["seconds"] for f in fits])),
        "values_clipped": fits[0].get("values_clipped"),
        "pixels_clipped": fits[0].get("pixels_clipped"),
    }


def run(config: dict, out: Path, ctx) -> dict:
    cfg = typed_config(Config, config)
    truth = inv.truth_of(cfg.medium)
    sim = inv.simulate(inv.capture_config(cfg.medium, cfg.width, cfg.height))
    clean = np.asarray(sim.images, np.float64)
    records, rows = [], []
    for seed in cfg.seeds:
        images = np.asarray(inv.camera(clean, (cfg.photons, cfg.read), seed), np.float64)
        peak = float(images.max())
        for clip in cfg.clips:
            level = clip * peak * (1.0 + 1e-6 if clip == 1 else 1.0)  # 1: nothing clipped
            for mask in MASKS:
                ctx.progress(f"seed {seed}, clip {clip:g}, mask per {mask}")
                records.append(
                    {
                        "seed": seed,
                        "clip": clip,
                        "mask": mask,
                        **_fit(images, level, mask, cfg, truth),
                    }
                )
        if cfg.clamp_zero:
            ctx.progress(f"seed {seed}, clamped at 0")
            fit = _fit(images, math.inf, "floor", cfg, truth)
            records.append({"seed": seed, "clip": 1.0, "mask": "floor", **fit})
    variants = [(clip, mask) for clip in cfg.clips for mask in MASKS]
    for clip, mask in variants + ([(1.0, "floor")] if cfg.clamp_zero else []):
        fits = [r for r in records if r["clip"] == clip and r["mask"] == mask]
        rows.append({"clip": clip, "mask": mask, **_summary(fits)})
    data = {
        "config": config,
        "truth": truth,
        "rows": rows,
        "records": records,
        **provenance(),
    }
    ctx.write_json("clipped_captures.json", inv.jsonable(data))
    for r in rows:
        ctx.progress(
            f"clip {r['clip']:g} per {r['mask']}: {r['converged']}/{r['fits']} converged, "
            f"truth inside 2 sigma {r['inside_2sigma']}, largest {r['largest_sigmas']} sigma"
        )
    return {"rows": inv.jsonable(rows), "figures": [], "data": ["clipped_captures.json"]}
