"""Fits with the slab geometry (issue 7): round trips through the own slab model,
the plane-or-slab choice of ``geometry: auto``, and the capture/CLI path."""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
import yaml

import lightfield_jax as lfj
from lightfield_jax.app.experiment import load_helper, run_experiment
from lightfield_jax.forward.slab import slab_bounce_ratio
from lightfield_jax.inverse.fit import fit_images
from lightfield_jax.inverse.geometry_model import SlabModel
from lightfield_jax.inverse.model_choice import choose, misfit, relative_noise
from lightfield_jax.inverse.model_size import finer_cheap, scan_model
from lightfield_jax.inverse.options import FitOptions
from lightfield_jax.scene.geometry import AutoGeometry, Slab

PATTERN = lfj.Stripes(6, 3, tuple(range(6)))


def slab_capture(st, ss, g, slab, width=40, height=30):
    res = lfj.render(lfj.Medium(st, ss, g), lfj.Grid(width, height), PATTERN, geometry=slab)
    return np.asarray(res.total, np.float64)


def test_joint_recovers_a_slab_capture_rendered_by_the_slab_model():
    st, ss, g = 0.2051, 0.0366, 0.4
    slab = Slab(6.4, n_z=1)  # what default_n_z gives a medium this dim (ω 0.18)
    fit = fit_images(slab_capture(st, ss, g, slab), PATTERN, options=FitOptions(geometry=slab))
    assert fit.converged, fit.message
    assert fit.sigma_t == pytest.approx(st, rel=0.01)
    assert fit.sigma_s == pytest.approx(ss, rel=0.01)
    assert fit.g == pytest.approx(g, abs=0.01)
    assert fit.model["geometry"]["kind"] == "slab"
    assert fit.phase == "normalized"  # the 3-D phase function is normalised


def test_a_one_layer_model_does_not_cover_a_need_of_four():
    """The cheap slab model (8 bins, 4 nodes, 1 constant layer) stands in for the model
    the answer needs only where it is as large in every dimension: behind absorbing faces
    at ω 0.8, g 0.2 the need is 8 bins (what it has; 16 from |g| 0.3 with the margin) but
    4 layers, linear in depth."""
    from lightfield_jax.inverse.model_size import covers, size_model

    opts = FitOptions(geometry=Slab(6.4), phase="normalized")
    crop = (0, 0, 32, 24)
    cheap = dataclasses.replace(scan_model(crop, opts, 0.5), extrapolate=False)
    need = size_model(np.zeros((6, 24, 32)), PATTERN, 0.8, 0.2, opts, 1.03, 0.2, crop)
    depth = (need.grid.n_theta, need.geometry.slab.n_z, need.geometry.slab.profile)
    assert depth == (8, 4, "linear")
    assert cheap.grid.n_theta == 8 and cheap.geometry.slab.n_z == 1
    bounces = dataclasses.replace(cheap, bounces=need.bounces)
    assert not covers(bounces, need)
    layered = dataclasses.replace(bounces, geometry=need.geometry)
    assert covers(layered, need)
    # As many layers, but each one's average only: not the need either.
    constant = dataclasses.replace(need.geometry.slab, depth_profile="constant")
    assert not covers(dataclasses.replace(bounces, geometry=SlabModel(constant)), need)
    # The cheap model's one layer is its average whatever profile the user asks of the
    # answer's model (a linear one would double the cheap solve's cost).
    linear = FitOptions(geometry=Slab(6.4, depth_profile="linear"), phase="normalized")
    assert scan_model(crop, linear, 0.5).geometry.slab.profile == "constant"


@pytest.mark.slow  # a minute on 2 cores
def test_the_fit_ends_on_the_depth_layers_its_answer_needs():
    """Behind absorbing faces at ω 0.8, g 0.4 the slab needs 4 linear depth layers (the
    cheap model has one constant one) and 16 azimuth bins (it has 8): the cheap model
    does not stand in for the layered one (the depth average is off by 1 % on σs here),
    the fit corrects its answer to the layers."""
    st, ss, g = 0.2, 0.16, 0.4
    slab = Slab(6.4)  # layers and nodes from the medium, as a user gives it
    fit = fit_images(
        slab_capture(st, ss, g, slab, 32, 24), PATTERN, options=FitOptions(geometry=slab)
    )
    assert fit.model["geometry"]["n_z"] == 4
    assert fit.model["geometry"]["depth_profile"] == "linear"
    assert fit.converged, fit.message
    assert fit.sigma_t == pytest.approx(st, rel=1e-3)
    assert fit.sigma_s == pytest.approx(ss, rel=1e-3)
    assert fit.g == pytest.approx(g, abs=1e-3)


@pytest.mark.parametrize("method", ["grid", "gradient"])
def test_two_step_methods_with_the_slab_and_a_perfect_split(method):
    st, ss, g = 0.2051, 0.11, 0.4
    slab = Slab(6.4, n_z=1)  # the depth average: layers are tested in test_slab_depth.py
    medium = lfj.Medium(st, ss, g)
    stripes = np.asarray(lfj.render(medium, lfj.Grid(32, 24), PATTERN, 8, geometry=slab).total)
    full = lfj.render(medium, lfj.Grid(32, 24), lfj.Full(0.0, "left"), 8, geometry=slab)
    full = np.asarray(full.images)
    split = (full[0], full[1:].sum(axis=0))
    opts = FitOptions(method=method, geometry=slab, bounces=8)
    fit = fit_images(stripes, PATTERN, options=opts, split=split)
    assert fit.model["geometry"]["kind"] == "slab"
    assert fit.sigma_t == pytest.approx(st, rel=1e-3)
    assert fit.sigma_s == pytest.approx(ss, rel=0.01)
    assert fit.g == pytest.approx(g, abs=0.01)


@pytest.mark.slow  # a minute on 2 cores
def test_a_two_step_fit_is_solved_again_with_the_elevation_nodes_its_g_needs():
    """The two-step methods size their first model at g 0 (4 elevation nodes behind
    absorbing faces); at g 0.7 the slab needs 16: the fit is solved again with them."""
    st, ss, g = 0.2051, 0.11, 0.7
    slab = Slab(6.4)
    medium = lfj.Medium(st, ss, g)
    stripes = np.asarray(lfj.render(medium, lfj.Grid(32, 24), PATTERN, 8, geometry=slab).total)
    full = lfj.render(medium, lfj.Grid(32, 24), lfj.Full(0.0, "left"), 8, geometry=slab)
    full = np.asarray(full.images)
    opts = FitOptions(method="gradient", geometry=slab, bounces=8)
    fit = fit_images(stripes, PATTERN, options=opts, split=(full[0], full[1:].sum(axis=0)))
    geometry = fit.model["geometry"]
    assert (geometry["n_mu"], geometry["n_z"], geometry["depth_profile"]) == (16, 4, "linear")
    assert fit.sigma_s == pytest.approx(ss, rel=0.01)
    assert fit.g == pytest.approx(g, abs=0.01)


@pytest.mark.slow
def test_the_plane_model_is_biased_on_a_slab_capture():
    # The reason the slab exists (docs/model.md §7): with the plane model, σs or g are off.
    st, ss, g = 0.2051, 0.0366, 0.4
    fit = fit_images(slab_capture(st, ss, g, Slab(6.4)), PATTERN, options=FitOptions(max_steps=40))
    assert abs(fit.sigma_s / ss - 1) > 0.05 or abs(fit.g - g) > 0.05


def test_bounce_ratio_is_below_the_albedo_and_matches_the_render():
    slab = Slab(6.4, "refractive", n_z=2)
    r = slab_bounce_ratio(slab, 0.3, 0.7, -0.3, 48, 36)
    res = lfj.render(
        lfj.Medium(0.3, 0.21, -0.3), lfj.Grid(48, 36), lfj.Full(0.0, "left"), 16, geometry=slab
    )
    totals = np.asarray(res.images).sum((1, 2))
    assert r < 0.7
    assert r == pytest.approx(totals[-1] / totals[-2], rel=0.05)


def test_relative_noise_measures_the_noise_not_the_signal():
    img = slab_capture(0.2051, 0.0366, 0.4, Slab(6.4, n_z=1), 64, 48)
    assert relative_noise(img, PATTERN) < 2e-3  # the signal's own fourth difference
    rng = np.random.default_rng(1)
    for eps in (0.003, 0.03):
        noisy = img * (1 + eps * rng.standard_normal(img.shape))
        assert relative_noise(noisy, PATTERN) == pytest.approx(eps, rel=0.15)
    with pytest.raises(ValueError, match="expected"):
        relative_noise(img[0], PATTERN)


def test_choice_rule():
    # The misfit holds the noise: the plane's own error is √(misfit² − noise²).
    assert choose(0.004, 0.01).chosen == "plane"
    assert choose(0.0141, 0.01).chosen == "plane"
    assert choose(0.0142, 0.01).chosen == "slab"
    assert choose(0.02, 0.01).plane_error == pytest.approx(math.sqrt(3) * 0.01)
    assert choose(0.02, 0.01, threshold=2.0).chosen == "plane"
    assert misfit(np.ones(4) * 1.1, np.ones(4)) == pytest.approx(0.1)


@pytest.mark.slow  # minutes on 2 cores; run with -m slow
def test_auto_keeps_the_plane_under_heavy_noise_and_picks_the_slab_without():
    st, ss, g = 0.2, 0.1, 0.4
    slab = Slab(6.4, n_z=1)
    clean = slab_capture(st, ss, g, slab, 32, 24)
    rng = np.random.default_rng(0)
    noisy = clean * (1 + 0.2 * rng.standard_normal(clean.shape))
    opts = FitOptions(geometry=AutoGeometry(slab), max_steps=30)
    heavy = fit_images(noisy, PATTERN, options=opts)
    choice = heavy.model["geometry_choice"]
    assert choice["chosen"] == "plane", choice
    assert heavy.model["geometry"]["kind"] == "plane"
    exact = fit_images(clean, PATTERN, options=opts)
    choice = exact.model["geometry_choice"]
    assert choice["chosen"] == "slab", choice
    assert choice["plane_error"] > choice["noise"]
    assert exact.sigma_s == pytest.approx(ss, rel=0.02)


def test_cli_fit_uses_the_capture_geometry(tmp_path):
    cfg = {
        "grid": {"width": 32, "height": 24},
        "medium": {"sigma_t": 0.2051, "sigma_s": 0.0366, "g": 0.4, "phase": "paper"},
        "illumination": {"kind": "stripes", "period": 6, "lit": 3, "shifts": 6},
        "geometry": {
            "kind": "slab",
            "thickness": 6.4,
            "boundary": "refractive",
            "n": 1.33,
            "n_z": 1,
        },
    }
    (tmp_path / "sim.yaml").write_text(yaml.safe_dump(cfg))
    run = [sys.executable, "-m", "lightfield_jax"]
    out = tmp_path / "cap"
    subprocess.run([*run, "simulate", str(tmp_path / "sim.yaml"), "--out", str(out)], check=True)
    capture = yaml.safe_load((out / "capture.yaml").read_text())
    # The capture records the geometry it was rendered with, the depth profile in effect
    # included (one layer: its average).
    assert capture["geometry"] == {**cfg["geometry"], "depth_profile": "constant"}
    result = tmp_path / "fit.json"
    subprocess.run(
        [*run, "fit", str(out / "capture.yaml"), "--out", str(result)], check=True, timeout=600
    )
    data = json.loads(result.read_text())
    entry = data if "model" in data else next(iter(data["channels"].values()))
    assert entry["model"]["geometry"]["kind"] == "slab"
    assert entry["model"]["geometry"]["boundary"] == "refractive"
    assert entry["sigma_s"] == pytest.approx(0.0366, rel=0.02)


@pytest.mark.slow  # minutes on 2 cores; run with -m slow
def test_plane_vs_slab_experiment_reduced(tmp_path):
    from pathlib import Path

    from lightfield_jax.app.experiment import run_experiment

    config = Path(__file__).resolve().parent.parent / "configs" / "plane_vs_slab.yaml"
    summary = run_experiment(config, tmp_path, reduced=True)["summary"]
    for name in summary["figures"] + ["plane_vs_slab.json", "summary.json"]:
        assert (tmp_path / name).stat().st_size > 0, name
    rows = json.loads((tmp_path / "plane_vs_slab.json").read_text())["rows"]
    assert len(rows) == 1
    # Noiseless slab capture, plane model: a misfit well above float32 round-off.
    assert 1e-3 < rows[0]["misfit"] < 0.5
    assert set(rows[0]["errors"]) == {"sigma_t", "sigma_s", "g"}


DATA = Path(__file__).resolve().parent / "data"
CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def test_slab_recovery_experiment_reduced(tmp_path):
    """The experiment that renders the stored Monte Carlo captures (reduced: a small
    capture, no fit) writes a capture the fit can read, with its noise."""
    record = run_experiment(CONFIGS / "slab_recovery.yaml", tmp_path, reduced=True)
    (row,) = record["summary"]["rows"]
    with np.load(tmp_path / "capture_w0.95_g0.8.npz") as data:
        images, variance = data["images"], data["variance"]
        assert images.shape == (6, 12, 24) and variance.shape == images.shape
        assert float(data["g"]) == 0.8 and float(data["albedo"]) == 0.95
    assert np.all(images >= 0) and np.all(variance >= 0)
    assert 0 < row["relative_noise_median"] < 1
    assert row["untraced"] < 1e-3
    # A lit row (phase 0 lights rows 0-2) outshines a dark one near the entry wall.
    assert images[0, 1, :4].sum() > 3 * images[0, 4, :4].sum()


@functools.cache
def _true_slab_fit(medium: str):
    """The experiment's own fit (``fit_capture``) of a stored Monte Carlo capture, in
    float32 as a user runs it; its errors against the truth. Shared by the tests below."""
    recovery = load_helper("slab_recovery")
    config = yaml.safe_load((CONFIGS / "slab_recovery.yaml").read_text())
    with np.load(DATA / f"slab_recovery_{medium}.npz") as data:
        images, variance = data["images"], data["variance"]
        truth = {"albedo": float(data["albedo"]), "g": float(data["g"])}
        assert float(data["sigma_t"]) == config["sigma_t"]
    with jax.enable_x64(False):  # the fit's default precision, as a user runs it
        fit = recovery.fit_capture(config, images.astype(np.float32), variance, None)
    truth_values = {
        "sigma_t": config["sigma_t"],
        "sigma_s": truth["albedo"] * config["sigma_t"],
        "g": truth["g"],
    }
    err = recovery.errors(fit, config, truth)
    d = fit.to_dict()
    print(  # the measurement (pytest -s): docs/slab_depth.md section 6
        medium,
        {k: err[k] for k in truth_values},
        {k: d[k] for k in ("uncertainty", "uncertainty_statistical", "consistency")},
        {k: d[k] for k in ("model_limited", "converged", "reasons", "chi2_dof", "seconds")},
        {k: d["model"].get(k) for k in ("n_theta", "bounces", "geometry", "correction")},
    )
    return fit, err, truth_values


NEAR_WALL_MISS = pytest.mark.xfail(
    strict=True,
    reason="σt +3.8 % (+3.5 % without the stripe cell): the default max_render_cells drops the "
    "near-wall grid's refinement (64 bins at refine 1); with max_render_cells 4.8e7 (refine 2) "
    "σt −0.28 % in 9× the time (docs/slab_depth.md section 7); the fit reports model_limited",
)


@pytest.mark.slow  # minutes on 2 cores; run with -m slow
@pytest.mark.parametrize("medium", ["w0.95_g0.8", pytest.param("w0.99_g0.9", marks=NEAR_WALL_MISS)])
def test_fit_recovers_milk_like_media_rendered_by_the_3d_monte_carlo(medium):
    """Stripe captures of milk-like media behind refractive faces rendered by the 3-D
    slab Monte Carlo (true depth, not the layered model; tests/data, made by
    ``lightfield-jax experiment configs/slab_recovery.yaml``), fitted with the slab
    geometry and weighted by their own Monte Carlo noise: σt within 1 %, σs within
    3 %, g within 0.02 (issue 18)."""
    fit, err, _ = _true_slab_fit(medium)
    assert abs(err["sigma_t"]) < 0.01, (err, fit)
    assert abs(err["sigma_s"]) < 0.03, (err, fit)
    assert abs(err["g"]) < 0.02, (err, fit)


@pytest.mark.slow  # minutes on 2 cores; run with -m slow
@pytest.mark.parametrize("medium", ["w0.95_g0.8", "w0.99_g0.9"])
def test_a_fit_of_the_true_slab_is_honest_about_its_error(medium):
    """Where the slab model misses the true slab, the fit says so: the truth is inside
    its total 2σ, or it is not reported as converged; and a miss beyond the issue's
    bounds comes with ``model_limited``."""
    fit, err, truth = _true_slab_fit(medium)
    if not fit.converged:
        return
    for key, value in truth.items():
        assert abs(getattr(fit, key) - value) < 2 * fit.uncertainty[key], (key, err, fit)
    if abs(err["sigma_t"]) > 0.01 or abs(err["sigma_s"]) > 0.03 or abs(err["g"]) > 0.02:
        assert fit.model_limited, (err, fit)


def test_the_second_cheap_slab_model_is_finer_and_within_the_users_settings():
    """A slab's cheap solve that runs away is solved again on 16 azimuth bins × 8 μ
    nodes, never on the plane, and not against the user's fixed bins, nodes or cell cap."""
    crop = (0, 0, 32, 24)
    slab = Slab(6.4, "refractive", 1.33)
    cheap = scan_model(crop, FitOptions(geometry=slab), 0.5)
    assert (cheap.grid.n_theta, cheap.geometry.slab.n_mu) == (8, 4)
    finer = finer_cheap(cheap, FitOptions(geometry=slab))
    assert (finer.grid.n_theta, finer.geometry.slab.n_mu) == (16, 8)
    assert finer.geometry.slab.n_z == cheap.geometry.slab.n_z and finer.bounces == cheap.bounces
    assert finer_cheap(finer, FitOptions(geometry=slab)) is None
    assert finer_cheap(scan_model(crop, FitOptions(), 0.5), FitOptions()) is None
    assert finer_cheap(cheap, FitOptions(geometry=slab, n_theta=8)) is None
    fixed = Slab(6.4, "refractive", 1.33, n_mu=4)
    assert finer_cheap(cheap, FitOptions(geometry=fixed)) is None
    assert finer_cheap(cheap, FitOptions(geometry=slab, max_cells=32 * 24 * 16)) is None


def test_the_cell_cap_leaves_a_refractive_slab_its_four_elevation_nodes():
    """A 128×96 capture of a g 0.9 medium behind refractive faces passes the cell cap at
    its elevation nodes: the cap lowers them and the azimuth bins in turn, and stops at 4
    nodes (refractive faces need 4: it used to go to 3 and raise). The depth keeps its 2
    linear layers."""
    from lightfield_jax.inverse.model_size import size_model

    opts = FitOptions(geometry=Slab(6.4, "refractive", 1.33), phase="normalized")
    crop = (0, 0, 128, 96)
    model = size_model(np.zeros((6, 96, 128)), PATTERN, 0.98, 0.9, opts, 1.03, 0.2, crop)
    assert model.geometry.slab.n_mu == 4 and model.geometry.slab.n_z == 2


@pytest.mark.parametrize(
    "slab, n_theta, finer",
    [
        # Absorbing: the cap left 16 bins, 12 nodes, 4 linear layers; the bins and the
        # nodes are below what g 0.9 asks for, so they are doubled first, then the layers.
        (Slab(6.4), None, (32, 24, 8)),
        # The user's 16 layers stay (linear: the cap left the model 8 bins, 8 nodes).
        (Slab(6.4, n_z=16), None, (16, 16, 16)),
        # Already past the cap: nothing finer fits, and nothing coarser is taken.
        (Slab(6.4, "refractive", 1.33, n_mu=64), 128, (128, 64, 2)),
    ],
)
def test_the_error_terms_slab_model_is_finer_and_never_coarser(slab, n_theta, finer):
    """The model error term's model doubles the layers, then the nodes, then the bins (the
    bins first where the cap left fewer than the answer's g asks for), each within the
    memory cap, and never goes below the fit's model (it capped layers at 8 and nodes at
    32: the depth error of an 8-layer model went unseen)."""
    from lightfield_jax.inverse.joint_fit import finer as error_term
    from lightfield_jax.inverse.model_size import size_model

    opts = FitOptions(geometry=slab, phase="normalized", n_theta=n_theta)
    model = size_model(np.zeros((6, 24, 32)), PATTERN, 0.98, 0.9, opts, 1.03, 0.2, (0, 0, 32, 24))
    fine = error_term.finer(model, opts, 0.9)
    assert (fine.grid.n_theta, fine.geometry.slab.n_mu, fine.geometry.slab.n_z) == finer
    assert fine.grid.n_theta >= model.grid.n_theta
    assert fine.geometry.slab.n_mu >= model.geometry.slab.n_mu
    assert fine.geometry.slab.n_z >= model.geometry.slab.n_z
