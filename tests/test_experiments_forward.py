"""The forward-model experiments (reduced configs) and the paper-figure functions."""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest

import lightfield_jax as lfj
from lightfield_jax import viz
from lightfield_jax.app.experiment import run_experiment

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def _nonempty(path: Path) -> bool:
    return path.is_file() and path.stat().st_size > 0


def test_forward_accuracy_reduced(tmp_path):
    record = run_experiment(CONFIGS / "forward_accuracy.yaml", tmp_path, reduced=True)
    summary = record["summary"]
    for name in summary["figures"] + summary["data"] + ["summary.json"]:
        assert _nonempty(tmp_path / name), name
    rows = list(csv.DictReader(io.StringIO((tmp_path / "errors.csv").read_text())))
    assert {int(r["k"]) for r in rows} == {1, 2, 3}
    for r in rows:
        err, noise = float(r["error"]), float(r["mc_noise"])
        assert 0 < noise < 0.05
        # I_1 is exact: what is left is the Monte Carlo's noise.
        limit = 0.01 if r["k"] == "1" else 0.05
        assert err < limit, r
        assert float(r["render_median_s"]) > 0
        if r["k"] == "2":  # Σ I_2 against the noise-free quadrature
            assert abs(float(r["energy_bias_exact"])) < 0.01, r
    data = json.loads((tmp_path / "forward_accuracy.json").read_text())
    milk = data["scenes"]["milk"]
    assert (milk["default_n_theta"], milk["default_refine"]) == (32, 1)
    assert milk["auto_bounces"] == 5
    assert sum(r["is_default"] == "True" for r in rows if r["k"] == "1") == 1
    # A rerun resumes from the cache: same numbers.
    again = run_experiment(CONFIGS / "forward_accuracy.yaml", tmp_path, reduced=True)
    assert json.dumps(again["summary"]["scenes"]) == json.dumps(summary["scenes"])


@pytest.mark.slow  # the default suite keeps to ~10 min on 2 cores
def test_paper_figures_reduced(tmp_path):
    record = run_experiment(CONFIGS / "paper_figures.yaml", tmp_path, reduced=True)
    summary = record["summary"]
    assert len(summary["figures"]) == 5
    for name in summary["figures"] + ["paper_figures.json"]:
        assert _nonempty(tmp_path / name), name
    fig11 = summary["fig11"]
    assert fig11["sigma_t_separated"] == pytest.approx(0.2051, rel=0.03)
    # Without separation the multiple scatter flattens the decay.
    assert fig11["sigma_t_unseparated_imax"] < fig11["sigma_t_separated"]
    peaks = summary["fig12"]["full"]["peak_s_px"]
    assert peaks[0] < 1 and all(b >= a for a, b in zip(peaks, peaks[1:], strict=False))
    energy = summary["fig14"]["energy_per_bounce"]
    assert all(b < a for a, b in zip(energy, energy[1:], strict=False))


@pytest.fixture(scope="module")
def small_render():
    medium = lfj.Medium(0.25, 0.1, 0.4)
    beam = lfj.Beam(0.0, 8.5)
    return lfj.render(medium, lfj.Grid(24, 16, 16), beam, 3, lightfield=True), beam


def test_plot_bounce_profiles_and_images_write_png(tmp_path, small_render):
    result, beam = small_render
    out = viz.plot_bounce_profiles(result.images, tmp_path / "p.png", illumination=beam)
    assert _nonempty(out)
    out = viz.plot_bounce_images(result.images, tmp_path / "i.png", illumination=beam, show=2)
    assert _nonempty(out)
    fig = viz.plot_bounce_images(np.asarray(result.images), log=False)
    assert fig.axes  # without a path: the figure, for the caller
    with pytest.raises(ValueError, match="dimensions"):
        viz.plot_bounce_profiles(result.images[0])


def test_plot_lightfield_writes_png(tmp_path, small_render):
    result, _ = small_render
    out = viz.plot_lightfield(result.lightfields[1], tmp_path / "one.png", spacing=6)
    assert _nonempty(out)
    out = viz.plot_lightfield(result.lightfields[1:], tmp_path / "stack.png", glyph_scale="global")
    assert _nonempty(out)
    with pytest.raises(ValueError, match="glyph_scale"):
        viz.plot_lightfield(result.lightfields[1], glyph_scale="big")
    with pytest.raises(ValueError, match="labels"):
        viz.plot_lightfield(result.lightfields[1:], labels=["a"])


def test_plot_direct_decay_writes_png(tmp_path):
    h, w, sigma_t = 12, 30, 0.15
    x = np.arange(w) + 0.5
    direct = np.tile(np.exp(-sigma_t * x), (h, 1))
    fit = lfj.fit_decay(direct)
    assert float(fit.sigma_t) == pytest.approx(sigma_t, rel=1e-4)
    out = viz.plot_direct_decay(
        direct,
        fit,
        tmp_path / "d.png",
        unseparated=direct * (1 + 0.1 * x / w),
        true_sigma_t=sigma_t,
    )
    assert _nonempty(out)


def test_light_path_coordinates():
    s, mask = viz.light_path_coordinates((8, 10), lfj.Beam(0.0, 4.5))
    assert mask.sum() == 10 and np.all(mask[4])
    assert s[4, 0] == pytest.approx(0.5)
    s, mask = viz.light_path_coordinates((8, 10), lfj.Full(direction_deg=30.0))
    assert s[0, 0] == pytest.approx(0.5 / math.cos(math.radians(30)))
    assert not mask[0, -1] and mask[-1, 0]
