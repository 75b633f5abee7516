"""The inverse-problem experiments (reduced configs) and the batched, sharded render."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import lightfield_jax as lfj
from lightfield_jax.app.experiment import load_experiment_config, load_helper, run_experiment
from lightfield_jax.app.experiment_config import typed_config

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"
FAILURES = {
    "ok",
    "biased",
    "ill-conditioned",
    "not converged",
    "divergent",
    "non-finite",
    "exception",
    "timeout",  # the reduced config's joint_timeout exercises the child-process limit
}


def _files(out: Path, summary: dict) -> None:
    for name in summary["figures"] + summary["data"] + ["summary.json"]:
        path = out / name
        assert path.is_file() and path.stat().st_size > 0, name


@pytest.mark.slow  # minutes on 2 cores; run with -m slow
def test_inverse_speed_accuracy_reduced(tmp_path):
    summary = run_experiment(CONFIGS / "inverse_speed_accuracy.yaml", tmp_path, reduced=True)[
        "summary"
    ]
    _files(tmp_path, summary)
    methods = summary["captures"]["perfect_split"]["methods"]
    assert set(methods) == {"grid-5", "gradient", "jaxopt-lm"}
    # Fed the true split, both gradient solvers recover the medium; the 5-value grid
    # is limited by its spacing in g.
    for name in ("gradient", "jaxopt-lm"):
        assert methods[name]["error"] < 1e-3, (name, methods[name])
        assert methods[name]["converged"] == "1/1"
    assert methods["grid-5"]["error"] > 10 * methods["gradient"]["error"]
    for m in methods.values():
        assert m["total_s"] >= m["compile_s"] > 0
        assert 0 < m["warm_s"] < m["total_s"]  # the second fit reuses the compiled programs
    data = json.loads((tmp_path / "speed_accuracy.json").read_text())
    assert all(r["warm_same"] for r in data["records"])
    speedup = data["aggregate"]["perfect_split"]["speedup_vs_grid"]["gradient"]["total"]
    assert speedup["how"] == "bound" and speedup["speedup"] > 0


def test_inverse_speed_accuracy_dense_grids_repeat_less():
    script = load_helper("inverse_speed_accuracy")
    raw = load_experiment_config(CONFIGS / "inverse_speed_accuracy.yaml")
    dense = {"repeats": 3, "g_grids": [9, 19], "dense_g_grids": [19, 321], "dense_repeats": 1}
    config = typed_config(script.Config, {**raw, **dense})
    assert script._repeats(config, "perfect_split", "grid-321") == 1
    assert script._repeats(config, "perfect_split", "grid-19") == 3  # also a plain grid
    assert script._repeats(config, "perfect_split", "gradient") == 3
    assert script._repeats(config, "noisy", "grid-9") == 3
    grid_only = dataclasses.replace(config, methods=("grid",))
    assert "grid-321" in script._labels(grid_only, "perfect_split")
    assert "grid-321" not in script._labels(grid_only, "noisy")
    # Without dense_repeats the dense grids run as often as the others.
    unset = {k: v for k, v in {**raw, **dense}.items() if k != "dense_repeats"}
    assert script._repeats(typed_config(script.Config, unset), "perfect_split", "grid-321") == 3
    # Without dense_g_grids there are none.
    plain = {k: v for k, v in unset.items() if k != "dense_g_grids"}
    labels = script._labels(
        dataclasses.replace(typed_config(script.Config, plain), methods=("grid",)), "perfect_split"
    )
    assert labels == ["grid-9", "grid-19"]


@pytest.mark.slow  # minutes on 2 cores; run with -m slow
def test_stability_maps_reduced(tmp_path):
    config = CONFIGS / "stability_maps.yaml"
    summary = run_experiment(config, tmp_path, reduced=True)["summary"]
    _files(tmp_path, summary)
    fits = json.loads((tmp_path / "stability.json").read_text())
    for row in fits["fits"] + fits["starts"]:
        assert row["failure"] in FAILURES
    # The reduced map's one cell has rho = omega*A(g) >= 1 under phase: paper: no
    # method may call that a success.
    cells = [r for r in fits["fits"] if r["sweep"] == "albedo_g"]
    assert {r["method"] for r in cells} == {"grid", "joint"}
    for cell in cells:
        assert cell["truth"]["rho"] >= 1 and cell["failure"] != "ok", cell["method"]
    (start,) = fits["starts"]
    assert start["converged"] and start["failure"] == "ok"
    # The rows with their own captures and time limit: every fit ends and is timed.
    for name, methods in (("high_albedo", {"grid", "joint"}), ("refractive_slab", {"joint"})):
        rows = [r for r in fits["fits"] if r["sweep"] == name]
        assert {r["method"] for r in rows} == methods, name
        assert f"{name}.png" in summary["figures"]
        assert len(summary[name]) == len(rows)
        for r in rows:
            assert r["setting"]["medium"]["phase"] == "normalized"
            assert r["truth"]["rho"] < 1 and r["failure"] != "timeout", (name, r["method"])
            assert r["seconds"]["total"] > 0
    # albedo 0.99: capped at 100 bounces; the a-priori bound is above 1, the tail measured
    # on the render (light leaves the small capture) far below it.
    high = [r for r in fits["fits"] if r["sweep"] == "high_albedo"]
    truth = high[0]["truth"]
    assert truth["bounces"] == 100 and truth["bounces_how"] == "capped"
    assert truth["tail_bound"] > 1 and 0 <= truth["tail_measured"] < truth["tail_bound"]
    (slab,) = [r for r in fits["fits"] if r["sweep"] == "refractive_slab"]
    assert slab["setting"]["geometry"]["boundary"] == "refractive"
    assert slab["model"]["geometry"]["kind"] == "slab"
    # A rerun resumes from the cache: same numbers.
    again = run_experiment(config, tmp_path, reduced=True)["summary"]
    assert json.dumps(again) == json.dumps(summary)


def test_stability_maps_rows_config():
    script = load_helper("stability_maps")
    raw = load_experiment_config(CONFIGS / "stability_maps.yaml")
    config = typed_config(script.Config, raw)
    high = script._row_cells("high_albedo", config)
    assert len(high) == len(raw["high_albedo"]["albedo"]) * len(raw["high_albedo"]["g"])
    assert all(c["medium"]["phase"] == "normalized" for c in high)
    w99 = next(c for c in high if c["medium"]["sigma_s"] / c["medium"]["sigma_t"] > 0.985)
    assert script._rho(w99["medium"]) == pytest.approx(0.99)
    assert script._truth_bounces(w99["medium"], config, 400) == (400, "capped")
    slab = script._row_cells("refractive_slab", config)
    assert [c["name"] for c in slab] == [m["name"] for m in raw["refractive_slab"]["media"]]
    assert all(c["geometry"]["boundary"] == "refractive" for c in slab)
    # The slab's geometry is in the cache key: the plane and the slab are two fits.
    plane = {k: v for k, v in slab[0].items() if k != "geometry"}
    assert script._key(plane, "joint", config) != script._key(slab[0], "joint", config)
    assert script._row(config, "refractive_slab")["methods"] == ("joint",)
    assert script._row(config, "high_albedo")["methods"] == config.methods
    # A geometric series: the measured tail is its exact tail.
    tail, ratio = script._measured_tail(0.8 ** np.arange(10))
    assert ratio == pytest.approx(0.8)
    assert tail == pytest.approx(0.8**10 / (1 - 0.8**10))
    # Bounces that underflowed to 0 at the end: estimated from the last nonzero ones.
    tail0, ratio0 = script._measured_tail(np.r_[0.8 ** np.arange(10), 0.0, 0.0])
    assert (tail0, ratio0) == pytest.approx((tail, ratio))
    for bad, match in (
        ({"high_albedo": {**raw["high_albedo"], "albedos": [0.9]}}, "unknown config keys"),
        ({"refractive_slab": {**raw["refractive_slab"], "geometry": {"kind": "plane"}}}, "slab"),
        ({"refractive_slab": {**raw["refractive_slab"], "methods": ["nope"]}}, "nope"),
    ):
        with pytest.raises(ValueError, match=match):
            typed_config(script.Config, {**raw, **bad})


@pytest.mark.slow  # minutes on 2 cores; run with -m slow
def test_model_size_reduced(tmp_path):
    summary = run_experiment(CONFIGS / "model_size.yaml", tmp_path, reduced=True)["summary"]
    _files(tmp_path, summary)
    milk = summary["per_scene"]["gradient_split"]["milk"]
    assert milk["converged"] == {"auto": True, "large": True}
    assert isinstance(summary["auto_safe"], bool) and milk["speedup"] > 0
    for errors in milk["errors"].values():
        assert abs(errors["sigma_s"]) < 0.02 and abs(errors["g"]) < 0.02


@pytest.mark.slow  # half a minute on 2 cores (two cold fits); run with -m slow
def test_clipped_captures_reduced(tmp_path):
    summary = run_experiment(CONFIGS / "clipped_captures.yaml", tmp_path, reduced=True)["summary"]
    _files(tmp_path, summary)
    rows = {r["mask"]: r for r in summary["rows"]}
    assert set(rows) == {"pixel", "value", "floor"}
    for row in rows.values():
        assert row["converged"] == row["fits"] == 1
        assert row["values_clipped"] > row["pixels_clipped"] > 0
    # Per value: the clipped pixels' dark shifts fitted too, the truth inside 2σ.
    assert rows["value"]["inside_2sigma"] == 1.0


def test_clipped_captures_config():
    script = load_helper("clipped_captures")
    raw = load_experiment_config(CONFIGS / "clipped_captures.yaml")
    typed_config(script.Config, raw)
    for bad, match in (
        ({"clips": [0.0]}, r"clips\[0\]: must be in \(0, 1\]"),
        ({"seeds": []}, "seeds: at least one"),
        ({"medium": {"sigma_t": 0.2}}, "missing config key 'medium.sigma_s'"),
        ({"width": 4}, r"width: must be in \[8, 2048\]"),
    ):
        with pytest.raises(ValueError, match=match):
            typed_config(script.Config, {**raw, **bad})


@pytest.mark.slow  # 20 s on 2 cores (one cold fit); run with -m slow
def test_coverage_reduced(tmp_path):
    summary = run_experiment(CONFIGS / "coverage.yaml", tmp_path, reduced=True)["summary"]
    _files(tmp_path, summary)
    (row,) = summary["rows"]
    assert row["medium"] == "milk" and row["converged"] == row["fits"] == 2
    assert set(row["rms_z"]) == {"sigma_t", "sigma_s", "g"} and row["mean_m2"] > 0
    data = json.loads((tmp_path / "coverage.json").read_text())
    for fit in data["records"]["milk"]:
        z = np.array([fit["z"][k] for k in ("sigma_t", "sigma_s", "g")])
        assert np.all(np.isfinite(z)) and fit["m2"] >= 0


def test_coverage_config():
    script = load_helper("coverage")
    raw = load_experiment_config(CONFIGS / "coverage.yaml")
    typed_config(script.Config, raw)
    milk = raw["media"][0]
    for bad, match in (
        ({"media": []}, "media: at least one"),
        ({"media": [milk, milk]}, "names must differ"),
        ({"media": [{**milk, "g": 1.5}]}, "g"),
        ({"seeds": 0}, r"seeds: must be in \[1, 100000\]"),
        ({"photons": -1}, "photons: must be > 0"),
    ):
        with pytest.raises(ValueError, match=match):
            typed_config(script.Config, {**raw, **bad})


def test_load_helper_shares_one_module():
    inv = load_helper("_inverse")
    assert load_helper("_inverse") is inv and inv.__name__ == "lightfield_jax_experiments._inverse"
    assert callable(inv.fit_record)
    try:
        load_helper("_no_such_helper")
    except ValueError as e:
        assert "_no_such_helper" in str(e)
    else:
        raise AssertionError("an unknown helper must raise")


def _batch_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location("_batch_test", ROOT / "experiments" / "_batch.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_batched_render_matches_single_renders():
    batch = _batch_module()
    renderer = lfj.Renderer(lfj.Grid(12, 8, 16, 1), lfj.Stripes(4, 2, (0, 1, 2, 3)), 3)
    params = np.array([[0.2, 0.05, 0.4], [0.3, 0.2, -0.3]])
    out = np.asarray(batch.batched_render(renderer, params, shard=False))
    assert out.shape == (2, 4, 3, 8, 12)
    for row, p in zip(out, params, strict=True):
        np.testing.assert_allclose(row, np.asarray(renderer(*p)[0]), rtol=1e-12)
    chunked = np.asarray(batch.batched_render(renderer, params, shard=False, chunk=1))
    np.testing.assert_allclose(chunked, out, rtol=1e-12)


_SHARDED = """
import importlib.util, sys
import jax
import numpy as np
import pytest
import lightfield_jax as lfj

jax.config.update("jax_enable_x64", True)
assert len(jax.devices()) == 2, jax.devices()
spec = importlib.util.spec_from_file_location("_batch", sys.argv[1])
batch = importlib.util.module_from_spec(spec)
spec.loader.exec_module(batch)
renderer = lfj.Renderer(lfj.Grid(12, 8, 16, 1), lfj.Stripes(4, 2, (0, 1, 2, 3)), 3)
params = np.array([[0.2, 0.05, 0.4], [0.3, 0.2, -0.3], [0.1, 0.05, 0.7], [0.25, 0.1, 0.0]])
plain = np.asarray(batch.batched_render(renderer, params, shard=False))
sharded = batch.batched_render(renderer, params)  # two devices: sharded by default
assert len(sharded.sharding.device_set) == 2, sharded.sharding
assert [s.data.shape[0] for s in sharded.addressable_shards] == [2, 2]
np.testing.assert_allclose(np.asarray(sharded), plain, rtol=1e-12, atol=0)
odd = np.asarray(batch.batched_render(renderer, params[:3]))  # padded to 4, then cut
np.testing.assert_allclose(odd, plain[:3], rtol=1e-12, atol=0)
print("sharded ok")
"""


def test_batched_render_sharded_equals_unsharded():
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    env.pop("JAX_PLATFORMS", None)
    done = subprocess.run(
        [sys.executable, "-c", _SHARDED, str(ROOT / "experiments" / "_batch.py")],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert "sharded ok" in done.stdout
