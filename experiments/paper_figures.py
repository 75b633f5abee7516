"""The paper's figures 11-14 for its milk, from this project's forward model.

Mukaigawa, Raskar & Yagi (CVPR 2010) show, for milk with σt 0.2051, σs 0.0366 (per
pixel) and g 0.4:

- Fig. 11: the decay of the direct component with and without separation, and σt
  from its slope. Here: a simulated capture of period-``stripes.period`` stripes
  (``render`` with :class:`~lightfield_jax.Stripes`, every bounce summed), separated
  (:func:`~lightfield_jax.separate`, a = lit/period) into D and M; σt fitted
  (:func:`~lightfield_jax.fit_decay`) to D and, for comparison, to Imax (the image
  under the pixel's own lit stripe, i.e. without separation).
- Fig. 12: the decay of each bounce I_k along the light, under full illumination of
  the left wall and along a single beam.
- Fig. 13: the light field of each bounce L_1..L_3 of a beam, fluence with polar
  glyphs of the direction distribution.
- Fig. 14: oblique incidence: the per-bounce images of a beam entering at 30°.

Writes the PNGs and ``paper_figures.json`` (the fitted σt, peak positions of each
bounce profile, the energy of each bounce).
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Annotated

import numpy as np

import lightfield_jax as lfj
from lightfield_jax import viz
from lightfield_jax.app.experiment_config import Count, Pixels, Positive, Range, typed_config


@dataclasses.dataclass(frozen=True)
class StripesSpec:
    period: Annotated[int, Range(2, 1000)]
    lit: Count

    def __post_init__(self):
        if not self.lit < self.period:
            raise ValueError(f"paper_figures: stripes.lit: must be < period, got {self.lit}")


@dataclasses.dataclass(frozen=True)
class ObliqueSpec:
    y: float
    direction_deg: Annotated[float, Range(-89, 89)]
    show_bounces: Annotated[int, Range(1, 20)]


@dataclasses.dataclass(frozen=True)
class Config:
    """configs/paper_figures.yaml: the image size (pixels), the milk's σt, σs (per
    pixel) and g, the tail tolerance that sets the bounces, the stripes of Fig. 11
    (``period``, ``lit``), the beam's row of Figs. 12-13, the light-field bounces of
    Fig. 13 and the oblique beam of Fig. 14 (``y``, ``direction_deg``,
    ``show_bounces``)."""

    width: Pixels
    height: Pixels
    sigma_t: Positive
    sigma_s: Annotated[float, Range(0)]
    g: Annotated[float, Range(-0.99, 0.99)]
    tolerance: Annotated[float, Range(1e-12, 0.1)]
    stripes: Annotated[dict, StripesSpec]
    beam_y: float
    lightfield_bounces: Annotated[int, Range(1, 20)]
    oblique: Annotated[dict, ObliqueSpec]

    def __post_init__(self):
        if not self.sigma_s < self.sigma_t:
            raise ValueError(
                f"paper_figures: sigma_s: must be < sigma_t = {self.sigma_t:g}, got {self.sigma_s}"
            )
        for key, y in (("beam_y", self.beam_y), ("oblique.y", self.oblique["y"])):
            if not 0 < y < self.height:
                raise ValueError(
                    f"paper_figures: {key}: must be in (0, height={self.height}), got {y}"
                )


def run(raw: dict, out: Path, ctx) -> dict:
    config = typed_config(Config, raw)
    w, h = config.width, config.height
    medium = lfj.Medium(config.sigma_t, config.sigma_s, config.g)
    grid = lfj.Grid(w, h)  # n_theta and refine: the defaults for this g
    resolved = grid.resolve(float(medium.g))
    bounces = lfj.bounces_for_tolerance(float(medium.rho), config.tolerance)
    params = (
        f"σt {config.sigma_t:g}, σs {config.sigma_s:g} px⁻¹, g {config.g:g}; "
        f"{w}×{h} px, n_theta {resolved.n_theta}, refine {resolved.refine}, K = {bounces}"
    )
    summary: dict = {
        "medium": {k: getattr(config, k) for k in ("sigma_t", "sigma_s", "g")},
        "rho": float(medium.rho),
        "grid": {"width": w, "height": h, "n_theta": resolved.n_theta, "refine": resolved.refine},
        "bounces": bounces,
    }
    figures = []

    # Fig. 11: separation of a simulated stripe capture, σt from the direct decay.
    ctx.progress("Fig. 11: stripe capture, separation, decay fit")
    st = config.stripes
    stripes = lfj.Stripes.shifted(period=st["period"], lit=st["lit"])
    capture = np.asarray(lfj.render(medium, grid, stripes, bounces).images).sum(axis=1)
    sep = lfj.separate(capture, lit_fraction=stripes.lit_fraction)
    fit_d = lfj.fit_decay(sep.direct)
    fit_max = lfj.fit_decay(sep.imax)
    figures.append(
        viz.plot_direct_decay(
            sep.direct,
            fit_d,
            out / "fig11_direct_decay.png",
            unseparated=sep.imax,
            unseparated_fit=fit_max,
            unseparated_label="without separation: Imax (the pixel's own stripe lit)",
            true_sigma_t=config.sigma_t,
            title=(
                f"Fig. 11: decay of the direct component (true σt {config.sigma_t:g} px⁻¹), "
                f"period-{st['period']} stripes ({st['lit']} lit), {len(stripes.phases)} "
                f"shifts\n{params}"
            ),
        )
    )
    summary["fig11"] = {
        "sigma_t_true": config.sigma_t,
        "sigma_t_separated": float(fit_d.sigma_t),
        "sigma_t_separated_stderr": float(fit_d.sigma_t_stderr),
        "sigma_t_unseparated_imax": float(fit_max.sigma_t),
        "sigma_t_unseparated_imax_stderr": float(fit_max.sigma_t_stderr),
        "converged": [bool(fit_d.converged), bool(fit_max.converged)],
    }

    # Fig. 12: each bounce along the light, full illumination and one beam.
    ctx.progress("Fig. 12: bounce profiles")
    full = lfj.Full()
    beam = lfj.Beam(0.0, config.beam_y)
    summary["fig12"] = {}
    for name, light in (("full", full), ("beam", beam)):
        images = np.asarray(lfj.render(medium, grid, light, bounces).images)
        figures.append(
            viz.plot_bounce_profiles(
                images,
                out / f"fig12_bounce_profiles_{name}.png",
                illumination=light,
                title=f"Fig. 12: decay of each bounce I_k along the light ({name})\n{params}",
            )
        )
        s, mask = viz.light_path_coordinates(images.shape[1:], light)
        summary["fig12"][name] = {
            "peak_s_px": [float(s[mask][np.argmax(im[mask])]) for im in images],
            "energy_per_bounce": [float(im.sum()) for im in images],
        }

    # Fig. 13: light fields L_1..L_K of a beam.
    ctx.progress("Fig. 13: light fields")
    k_lf = config.lightfield_bounces
    result = lfj.render(medium, grid, beam, k_lf, lightfield=True)
    fields = np.asarray(result.lightfields[1:])
    figures.append(
        viz.plot_lightfield(
            fields,
            out / "fig13_lightfield.png",
            title=(
                f"Fig. 13: light field of each bounce, beam at y = {config.beam_y:g}, 0°; "
                "colour: fluence, cyan glyphs: L(θ) scaled to its maximum, θ from +x "
                f"toward +y\n{params.replace(f', K = {bounces}', '')}"
            ),
        )
    )

    # Fig. 14: oblique incidence.
    ctx.progress("Fig. 14: oblique beam")
    ob = config.oblique
    oblique = lfj.Beam(0.0, ob["y"], ob["direction_deg"])
    with warnings.catch_warnings():
        warnings.simplefilter("error", lfj.DivergentSeriesWarning)
        images = np.asarray(lfj.render(medium, grid, oblique, bounces).images)
    figures.append(
        viz.plot_bounce_images(
            images,
            out / "fig14_oblique_bounces.png",
            show=ob["show_bounces"],
            dynamic_range=1e5,
            illumination=oblique,
            title=(
                f"Fig. 14: oblique incidence, beam from (0, {ob['y']:g}) at "
                f"{ob['direction_deg']:g}°: images of light that scattered k times "
                f"(Σ over all {bounces} bounces)\n{params}"
            ),
        )
    )
    summary["fig14"] = {"energy_per_bounce": [float(im.sum()) for im in images]}
    summary["figures"] = [Path(p).name for p in figures]
    ctx.write_json("paper_figures.json", summary)
    return summary
