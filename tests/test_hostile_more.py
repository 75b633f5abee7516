"""More hostile inputs (after tests/test_hostile.py): values a file may hold that the
work would otherwise ignore, replace quietly, or turn into an overflow. Each is refused
with one line naming the file, the key and the value, exit status 2, before the work."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from lightfield_jax.app.cli import XLA_CACHE_ENV, main
from lightfield_jax.app.memory import MAX_MEMORY_ENV

H, W = 24, 32
SIMULATE = f"""\
grid: {{width: {W}, height: {H}, n_theta: 16, refine: 1}}
medium: {{sigma_t: 0.2051, sigma_s: 0.0366, g: 0.4}}
illumination: {{kind: stripes, period: 6, lit: 3}}
gain: 400.0
black_level: 0.02
dark_level: 0.01
noise: {{photons: 1.0e5, read: 0.0005, seed: 3}}
"""


@pytest.fixture(autouse=True)
def _environment(monkeypatch):
    monkeypatch.setenv(XLA_CACHE_ENV, "off")
    monkeypatch.delenv(MAX_MEMORY_ENV, raising=False)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """The milk as a 32x24 six-shift stripe capture with a dark frame."""
    folder = tmp_path_factory.mktemp("hostile_more")
    (folder / "sim.yaml").write_text(SIMULATE)
    assert main(["simulate", str(folder / "sim.yaml"), "--out", str(folder / "cap"), "-q"]) == 0
    return folder / "cap"


@pytest.fixture
def capture(simulated, tmp_path):
    folder = tmp_path / "cap"
    shutil.copytree(simulated, folder)
    return folder


def _refused(capsys, *argv, match: str) -> str:
    """The command exits 2 with one error line containing ``match``."""
    status = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    lines = err.splitlines()
    assert status == 2, (status, out, err)
    assert len(lines) == 1 and lines[0].startswith("lightfield-jax: error: "), err
    assert match in lines[0], lines[0]
    return lines[0]


def _edit(folder: Path, **changes) -> Path:
    path = folder / "capture.yaml"
    data = yaml.safe_load(path.read_text())
    data.update(changes)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


# ------------------------------------------------------------- a capture's fit: settings


@pytest.mark.parametrize(
    ("fit", "match"),
    [
        ({"bounces": 0}, "fit: bounces: must be an integer >= 1 or 'auto', got 0"),
        ({"bounces": -3}, "fit: bounces: must be an integer >= 1 or 'auto', got -3"),
        ({"n_theta": 1}, "fit: n_theta: must be a multiple of 8 (>= 8), got 1"),
        ({"refine": 0}, "fit: refine: must be an integer in [1, 8], got 0"),
        ({"max_cells": 0}, "fit: max_cells: must be an integer >= 1, got 0"),
        ({"max_steps": 0}, "fit: max_steps: must be an integer >= 1, got 0"),
        ({"max_bounces": 0}, "fit: max_bounces: must be an integer >= 1, got 0"),
        ({"start_grid": 0}, "fit: start_grid: must be at least 3, got 0"),
        ({"tolerance": 0.0}, "fit: tolerance: must lie in (0, 1), got 0.0"),
        ({"crop_fraction": 5.0}, "fit: crop_fraction: must lie in [0, 1)"),
        ({"rtol": -1.0}, "fit: rtol: must be a finite number >= 0 or None, got -1.0"),
        ({"max_chi2": 0.0}, "fit: max_chi2: must be > 0, got 0.0"),
    ],
)
def test_fit_settings_out_of_range_are_refused_on_loading(capture, capsys, fit, match):
    """Before: a bounce count below 1 became 2, max_cells 0 and crop_fraction 5 were
    ignored, max_steps 0 made a fit that "did not converge", all after the work."""
    _edit(capture, fit=fit)
    line = _refused(capsys, "inspect", capture / "capture.yaml", match=match)
    assert str(capture / "capture.yaml") in line


def test_fit_options_refuse_out_of_range_values():
    from lightfield_jax import FitOptions

    FitOptions(bounces=1, n_theta=8, refine=8, rtol=0.0, atol=None, crop_fraction=0.0)
    for bad in (
        {"bounces": True},
        {"phase": "nonsense"},
        {"tolerance": float("nan")},
        {"atol": float("inf")},
        {"n_theta": 12},
        {"refine": 9},
        {"max_chi2": float("nan")},
    ):
        with pytest.raises(ValueError, match=next(iter(bad))):
            FitOptions(**bad)


@pytest.mark.parametrize(
    "fit", [{"n_theta": 2**30}, {"n_theta": 2**16}, {"refine": 8, "n_theta": 4096}]
)
def test_fixed_model_sizes_count_in_the_fits_memory_estimate(capture, capsys, tmp_path, fit):
    """θ bins and a refinement the capture fixes are not lowered to max_cells: before,
    the estimate ignored them and the fit ran out of memory (or was killed)."""
    _edit(capture, fit=fit)
    out = tmp_path / "r.json"
    argv = ("fit", capture / "capture.yaml", "--out", out, "--max-memory", "8G")
    _refused(capsys, *argv, match="the fit needs about")
    assert not out.exists()


# ------------------------------------------------------------------ simulate: float32


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"gain": 1e39}, "gain: must be at most 1e+30 (images are float32), got 1e+39"),
        ({"dark_level": 1e300}, "dark_level: must be at most 1e+30"),
        ({"noise": {"read": 1e300}}, "noise.read: must be at most 1e+30"),
        ({"noise": {"photons": 1e300}}, "noise.photons: 1e+300 photons at image value 1.0"),
        ({"dark_level": 1e12}, "noise.photons: 100000.0 photons"),
        ({"medium": {"sigma_t": 1e39, "sigma_s": 1e38, "g": 0.4}}, "medium.sigma_t: must lie in"),
        ({"medium": {"sigma_t": 1e-40, "sigma_s": 1e-41, "g": 0.4}}, "medium.sigma_t: must lie"),
    ],
)
def test_simulate_values_beyond_float32_are_refused(tmp_path, capsys, change, match):
    """Before: a gain of 1e39 wrote NaN images with exit status 0; a huge photon count,
    gain or dark level ended in numpy's 'lam value too large' after the render; σt of
    1e-40 (0 in float32) in 'bounces: cannot convert float NaN to integer'."""
    config = yaml.safe_load(SIMULATE)
    config.update(change)
    path = tmp_path / "sim.yaml"
    path.write_text(yaml.safe_dump(config))
    line = _refused(capsys, "simulate", path, "--out", tmp_path / "o", match=match)
    assert str(path) in line and not (tmp_path / "o").exists()


# ------------------------------------------------------------------ render: results


def _results(capture: Path, tmp_path: Path, **changes) -> Path:
    """A results file as lightfield-jax fit writes it (the keys render reads)."""
    model = {"width": W, "height": H, "n_theta": 16, "refine": 1, "bounces": 4}
    model.update(changes.pop("model", {}))
    data = {"sigma_t": 0.2051, "sigma_s": 0.0366, "g": 0.4, "gain": 400.0, "phase": "paper"}
    data.update(changes)
    data["model"] = {**model, "crop": [0, 0, W, H], "geometry": {"kind": "plane"}}
    data["capture"] = str(capture / "capture.yaml")
    path = tmp_path / "results.json"
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"model": {"bounces": 10**9}}, "channel Y: the render needs about"),
        ({"model": {"width": 10**7}}, "channel Y: the render needs about"),
        ({"sigma_t": -1.0}, "channel Y: medium.sigma_t: must be > 0"),
        ({"g": 1.0}, "channel Y: medium.g: must satisfy -1 < g < 1, got 1.0"),
        ({"model": {"n_theta": 7}}, "channel Y: grid.n_theta: must be a multiple of 8"),
        ({"model": {"bounces": 0}}, "channel Y: bounces: must be a positive integer"),
        ({"gain": -5.0}, "channel Y: gain: must be a number in (0, 1e+30], got -5.0"),
        ({"gain": 1e39}, "channel Y: gain: must be a number in (0, 1e+30], got 1e+39"),
        ({"gain": True}, "channel Y: gain: must be a number in (0, 1e+30], got True"),
        ({"gain": "400"}, "channel Y: no usable gain"),
    ],
)
def test_impossible_results_are_refused_by_render(capture, capsys, tmp_path, changes, match):
    """Before: a bounce count of 1e9 ended in XLA's RESOURCE_EXHAUSTED traceback, a
    width of 1e7 in a MemoryError after 40 s, a negative or huge gain rendered negative
    or non-finite images, and the model's errors did not name the results file."""
    results = _results(capture, tmp_path, **changes)
    line = _refused(
        capsys, "render", results, "--out", tmp_path / "r", "--max-memory", "8G", match=match
    )
    assert line.startswith(f"lightfield-jax: error: {results}: ")
    assert not (tmp_path / "r").exists()


def test_a_valid_handmade_results_file_renders(capture, capsys, tmp_path):
    results = _results(capture, tmp_path)
    assert main(["render", str(results), "--out", str(tmp_path / "r"), "-q"]) == 0
    assert np.load(tmp_path / "r" / "bounces.npy").shape == (4, H, W)


# ------------------------------------------------------------------ smaller


def test_a_saturation_beyond_float32_is_refused(capture, capsys):
    """Before: inspect went on with numpy's 'overflow encountered in cast' warning."""
    _edit(capture, saturation=1.0e300)
    _refused(
        capsys,
        *("inspect", capture / "capture.yaml"),
        match="saturation: must be at most 3.4e+38 (float32), got 1e+300",
    )


def test_a_period_below_2_is_named_before_the_phases(capture, capsys, tmp_path):
    """Before: 'pattern.phases: [0, 1, ...] outside [0, period) = [0, 0)' (and
    'illumination.shifts: must be an integer in [1, period] = [1, 0]')."""
    pattern = yaml.safe_load((capture / "capture.yaml").read_text())["pattern"]
    for period in (0, -6, 1):
        _edit(capture, pattern={**pattern, "period": period})
        _refused(
            capsys,
            *("inspect", capture / "capture.yaml"),
            match=f"pattern.period: must be an integer >= 2, got {period}",
        )
    config = yaml.safe_load(SIMULATE)
    config["illumination"]["period"] = 0
    path = tmp_path / "sim.yaml"
    path.write_text(yaml.safe_dump(config))
    _refused(
        capsys,
        *("simulate", path, "--out", tmp_path / "o"),
        match="illumination.period: must be an integer >= 2, got 0",
    )


@pytest.mark.parametrize(
    ("truth", "match"),
    [
        ({"sigma_t": -1.0}, "truth.sigma_t: must be > 0"),
        ({"sigma_t": 0.2, "sigma_s": 5.0}, "truth.sigma_s: must satisfy 0 <= sigma_s <= sigma_t"),
        ({"g": 3.0}, "truth.g: must satisfy -1 < g < 1, got 3.0"),
        ({"gain": 0.0}, "truth.gain: must be > 0"),
        ({"black_level": 1.5}, "truth.black_level: must lie in [0, 1)"),
    ],
)
def test_an_impossible_truth_is_refused(capture, capsys, truth, match):
    """Before: accepted, and the fit's report compared its answer with it."""
    _edit(capture, truth=truth)
    _refused(capsys, "inspect", capture / "capture.yaml", match=match)


def test_memory_sizes_below_a_byte_and_empty_demo_methods_are_refused(capture, capsys, tmp_path):
    """Before: --max-memory 0.0001 was a limit of 0 B; demo --methods ',' simulated the
    milk and wrote a folder without a fit."""
    status = main(["inspect", str(capture / "capture.yaml"), "--max-memory", "0.0001"])
    assert status == 2 and "memory size: expected a size" in capsys.readouterr().err
    _refused(capsys, "demo", "--out", tmp_path / "d", "--methods", " , ", match="names no method")
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize(
    ("images", "pattern", "match"),
    [
        (np.ones((6, H, W), np.complex64), "stripes", "images: must be real numbers, got dtype"),
        (np.zeros((6, 0, 0), np.float32), "stripes", r"height and width >= 2\), got shape"),
        (np.ones((6, 1, 1), np.float32), "stripes", r"height and width >= 2\), got shape"),
        (np.ones((6, H, W), np.float32), None, "pattern: must be a Stripes, got NoneType"),
    ],
)
def test_fit_images_refuses_arrays_that_are_not_images(images, pattern, match):
    """Before: complex images lost their imaginary part with a numpy warning and were
    fitted; (6, 0, 0) ended in 'zero-size array to reduction operation max'; a pattern
    of None in an AttributeError."""
    import lightfield_jax as lfj

    with pytest.raises(ValueError, match=match):
        lfj.fit_images(images, lfj.Stripes() if pattern == "stripes" else pattern)
