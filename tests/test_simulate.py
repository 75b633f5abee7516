"""simulate_capture: black level (both ways of getting R_full agree), camera noise."""

import numpy as np

from lightfield_jax import Full, Grid, Medium, render
from lightfield_jax.forward.simulate import simulate_capture
from lightfield_jax.forward.simulate_config import parse_simulation_config

BASE = {
    "grid": {"width": 24, "height": 18, "n_theta": 16, "refine": 1},
    "medium": {"sigma_t": 0.25, "sigma_s": 0.15, "g": 0.3, "phase": "paper"},
    "bounces": 3,
}


def _config(**extra):
    return parse_simulation_config({**BASE, **extra})


def test_black_level_full_from_shifts_equals_a_rendered_full():
    b = 0.2
    stripes = {"kind": "stripes", "period": 6, "lit": 3}
    every = simulate_capture(
        _config(illumination=stripes, black_level=b, gain=1.5), lightfield=True
    )
    some = simulate_capture(
        _config(illumination={**stripes, "phases": [0, 2, 4]}, black_level=b, gain=1.5),
        lightfield=True,
    )
    assert every.full_illumination == "sum of shifts / lit"
    assert some.full_illumination == "rendered"
    np.testing.assert_allclose(some.bounces, every.bounces[[0, 2, 4]], rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(some.lightfields, every.lightfields[[0, 2, 4]], rtol=1e-5, atol=1e-9)
    # (1 − b)·R_pattern + b·R_full: the dark rows of a shift see b times the full render.
    full = render(Medium(0.25, 0.15, 0.3), Grid(24, 18, 16, 1), Full(), 3, gain=1.5)
    plain = simulate_capture(_config(illumination=stripes, gain=1.5))
    np.testing.assert_allclose(
        every.bounces, (1 - b) * plain.bounces + b * np.asarray(full.images)[None], rtol=1e-5
    )
    np.testing.assert_allclose(every.images, every.bounces.sum(1), rtol=1e-6)


def test_noise_is_seeded_poisson_plus_read_noise():
    photons, read, dark = 2e4, 0.002, 0.5
    noise = {"photons": photons, "read": read, "seed": 7}
    extra = {"illumination": {"kind": "full"}, "dark_level": dark, "noise": noise}
    sim = simulate_capture(_config(**extra))
    clean = sim.bounces.sum(0) + dark
    z = (sim.images - clean) / np.sqrt(clean / photons + read**2)
    assert abs(z.mean()) < 0.2 and 0.85 < z.std() < 1.15
    zd = (sim.dark - dark) / np.sqrt(dark / photons + read**2)
    assert abs(zd.mean()) < 0.2 and 0.85 < zd.std() < 1.15
    again = simulate_capture(_config(**extra))
    np.testing.assert_array_equal(again.images, sim.images)
    other = simulate_capture(_config(**{**extra, "noise": {**noise, "seed": 8}}))
    assert not np.array_equal(other.images, sim.images)


def test_accepts_a_config_path(tmp_path):
    path = tmp_path / "sim.yaml"
    path.write_text(
        "grid: {width: 24, height: 18, n_theta: 16, refine: 1}\n"
        "medium: {sigma_t: 0.25, sigma_s: 0.15, g: 0.3, phase: paper}\n"
        "illumination: {kind: full}\nbounces: 3\n"
    )
    sim = simulate_capture(path)
    assert sim.bounces.shape == (3, 18, 24) and sim.dark is None and sim.lightfields is None
    assert sim.images.dtype == np.float32
    np.testing.assert_allclose(sim.images, sim.bounces.sum(0), rtol=1e-6)
    assert sim.truth() == {
        "sigma_t": 0.25,
        "sigma_s": 0.15,
        "g": 0.3,
        "gain": 1.0,
        "phase": "paper",
    }
    meta = sim.metadata()
    assert meta["illumination"] == "full" and meta["bounces"] == 3
    assert meta["timings"]["total_s"] >= meta["timings"]["compile_s"] >= 0


def test_stages_are_reported():
    stages = []
    simulate_capture(_config(illumination={"kind": "full"}), stage=stages.append)
    assert stages == ["render full (3 bounces)", "camera"]


def test_a_tail_solve_sums_the_bounces_a_march_would(tmp_path):
    # Albedo .95 marches 200+ bounces; with tail: gmres, 4 explicit ones and the solve's
    # sum as the last slice give the same captured images, light fields and files.
    import json

    import pytest

    from lightfield_jax.forward.simulate import write_simulation
    from lightfield_jax.schema import ConfigError

    dense = {
        "grid": {"width": 20, "height": 12, "n_theta": 16, "refine": 1},
        "medium": {"sigma_t": 0.3, "sigma_s": 0.285, "g": 0.5, "phase": "normalized"},
        "illumination": {"kind": "stripes", "period": 4, "lit": 2},
        "black_level": 0.1,
    }
    marched = simulate_capture(parse_simulation_config(dense), lightfield=True)
    solved = simulate_capture(parse_simulation_config({**dense, "tail": "gmres"}), lightfield=True)
    assert marched.n_bounces > 100 and marched.tail is None
    assert solved.n_bounces == 4 and solved.tail["method"] == "gmres"
    assert solved.bounces.shape[1] == 5 and solved.lightfields.shape[1] == 6
    np.testing.assert_allclose(solved.bounces[:, :4], marched.bounces[:, :4], rtol=1e-5)
    np.testing.assert_allclose(solved.images, marched.images, rtol=1e-4)
    np.testing.assert_allclose(
        solved.lightfields.sum(1), marched.lightfields.sum(1), rtol=1e-3, atol=1e-7
    )
    write_simulation(solved, tmp_path)
    meta = json.loads((tmp_path / "metadata.json").read_text())
    assert meta["bounces"] == 4 and meta["tail"]["method"] == "gmres"
    assert "I4, tail" in meta["files"]["bounces_00.exr"]
    # A tail is refused where nothing converges, and named in one line otherwise.
    for bad, words in (
        ({"tail": "cg"}, "tail: must be one of gmres, bicgstab"),
        ({"tail": "gmres", "medium": {**dense["medium"], "phase": "paper", "g": 0.8}}, "phase: n"),
        ({"tail": "gmres", "medium": {**dense["medium"], "sigma_s": 0.3}}, "absorbs nothing"),
    ):
        with pytest.raises(ConfigError, match=words):
            parse_simulation_config({**dense, **bad})
