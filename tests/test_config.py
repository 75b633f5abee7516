"""The simulate config: parsing into typed objects, and every documented error."""

import copy
import dataclasses
import re

import numpy as np
import pytest

from lightfield_jax import Beam, Full, Grid, Medium, Stripes
from lightfield_jax.forward.simulate_config import (
    MediumConfig,
    SimulationConfig,
    load_simulation_config,
    parse_simulation_config,
)
from lightfield_jax.schema import ConfigError, load_yaml

PAPER_YAML = """\
grid: {width: 128, height: 96, n_theta: 64}
medium: {sigma_t: 0.2051, sigma_s: 0.0366, g: 0.4, phase: paper}
illumination: {kind: beam, x: 0.0, y: 48.5, direction_deg: 0.0, width: 1.0}
bounces: 10
"""

BASE = {
    "grid": {"width": 32, "height": 24},
    "medium": {"sigma_t": 0.2051, "sigma_s": 0.0366, "g": 0.4, "phase": "paper"},
    "illumination": {"kind": "stripes"},
}


def _with(**changes):
    """BASE with dotted keys set (value ``...`` deletes the key)."""
    data = copy.deepcopy(BASE)
    for dotted, value in changes.items():
        *parents, last = dotted.split("__")
        node = data
        for p in parents:
            node = node[p]
        if value is ...:
            del node[last]
        else:
            node[last] = value
    return data


def _error(data, source="sim.yaml"):
    with pytest.raises(ConfigError) as info:
        parse_simulation_config(data, source=source)
    message = str(info.value)
    assert message.startswith(f"{source}: "), message
    return message


def test_a_simulate_config_without_a_phase_is_in_the_energy_conserving_convention():
    """Milk (σt 0.2, σs 0.19, g 0.8) was refused without a phase: ρ = ω·A(g) 1.54 under
    the paper's convention, the default then."""
    milk = {"sigma_t": 0.2, "sigma_s": 0.19, "g": 0.8}
    config = parse_simulation_config(_with(medium=milk))
    assert config.medium.phase == "normalized"
    assert config.medium.medium().rho == pytest.approx(0.95)
    with pytest.raises(ConfigError, match="rho = albedo"):
        parse_simulation_config(_with(medium={**milk, "phase": "paper"}))


def test_load_paper_beam_config(tmp_path):
    path = tmp_path / "sim.yaml"
    path.write_text(PAPER_YAML)
    config = load_simulation_config(path)
    assert isinstance(config, SimulationConfig)
    assert config.grid == Grid(128, 96, 64)
    assert config.medium == MediumConfig(0.2051, 0.0366, 0.4, "paper")
    assert config.illumination == Beam(x=0.0, y=48.5, direction_deg=0.0, width=1.0)
    assert config.bounces == 10 and config.n_bounces() == 10
    assert config.source == str(path)
    assert config.raw["medium"]["sigma_t"] == 0.2051
    medium = config.medium.medium()
    assert isinstance(medium, Medium) and medium.phase == "paper"
    np.testing.assert_allclose(float(medium.sigma_s), 0.0366)
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.bounces = 3


def test_defaults_auto_bounces_and_yaml11_float_strings(tmp_path):
    path = tmp_path / "sim.yaml"
    path.write_text(
        "grid: {width: 32, height: 24}\n"
        "medium: {sigma_t: 2e-1, sigma_s: 0.0366, g: 0.4, phase: normalized}\n"
        "illumination: {kind: full}\n"
        "bounces: auto\n"
        "tolerance: 1e-4\n"
    )
    config = load_simulation_config(path)
    assert config.grid.n_theta is None
    assert config.medium.sigma_t == 0.2 and config.medium.phase == "normalized"
    assert config.illumination == Full(direction_deg=0.0, entry="left")
    assert config.bounces == "auto" and config.tolerance == 1e-4
    assert config.raw["tolerance"] == 1e-4  # a float, not YAML 1.1's string
    assert config.n_bounces() >= 1
    # A numeric string (as PyYAML's default loader gives for 1e-4) is accepted too.
    assert parse_simulation_config(_with(tolerance="1e-3")).tolerance == 1e-3


def test_stripes_shifts_phases_and_entry():
    config = parse_simulation_config(_with(illumination={"kind": "stripes"}))
    assert config.illumination == Stripes(6, 3, (0, 1, 2, 3, 4, 5), 0.0, "left")
    shifted = parse_simulation_config(
        _with(illumination={"kind": "stripes", "period": 8, "lit": 2, "shifts": 4})
    )
    assert shifted.illumination.phases == (0, 1, 2, 3)
    top = parse_simulation_config(
        _with(illumination={"kind": "stripes", "phases": [0, 3], "entry": "top"})
    )
    assert top.illumination == Stripes(6, 3, (0, 3), 90.0, "top")


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        (_with(extra=1), "extra: unknown key; allowed keys: grid, medium"),
        (_with(medium__sigmat=0.2), "medium.sigmat: unknown key (did you mean 'sigma_t'?)"),
        (_with(grid__depth=3), "grid.depth: unknown key"),
        (
            _with(illumination={"kind": "beam", "x": 0, "y": 3, "entry": "left"}),
            "illumination.entry: unknown key; allowed keys for kind beam: kind, x, y",
        ),
        (
            _with(illumination={"kind": "full", "shift": 2}),
            "illumination.shift: unknown key",
        ),
        (_with(medium__g=...), "medium.g: required key is missing"),
        (_with(grid=...), "grid: required key is missing"),
        (
            _with(illumination={"period": 6}),
            "illumination.kind: required key is missing; one of beam, stripes, full",
        ),
    ],
)
def test_unknown_and_missing_keys(data, expected):
    assert expected in _error(data)


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        (_with(grid=[32, 24]), "grid: must be a mapping of keys, got [32, 24] (list)"),
        (_with(illumination="beam"), "illumination: must be a mapping of keys, got 'beam'"),
        (_with(grid__width=128.5), "grid.width: must be an integer, got 128.5 (float)"),
        (_with(grid__width="128"), "grid.width: must be an integer, got '128' (str)"),
        (_with(grid__height=True), "grid.height: must be an integer, got True (bool)"),
        (_with(medium__sigma_t="thin"), "medium.sigma_t: must be a number, got 'thin' (str)"),
        (_with(medium__g=None), "medium.g: must be a number, got None (NoneType)"),
        (_with(medium__sigma_s=[0.1]), "medium.sigma_s: must be a number, got [0.1] (list)"),
        (_with(medium__sigma_t=float("inf")), "medium.sigma_t: must be finite, got inf"),
        (_with(medium__phase="flatland"), "medium.phase: must be one of paper, normalized"),
        (
            _with(illumination={"kind": "stripes", "phases": [0, 1.5]}),
            "illumination.phases[1]: must be an integer, got 1.5 (float)",
        ),
        (
            _with(illumination={"kind": "stripes", "phases": 3}),
            "illumination.phases: must be a non-empty list of integers, got 3 (int)",
        ),
        (_with(bounces="many"), "bounces: must be a positive integer or 'auto', got 'many'"),
        (_with(bounces=2.0), "bounces: must be an integer, got 2.0 (float)"),
        (_with(tolerance="small"), "tolerance: must be a number, got 'small' (str)"),
    ],
)
def test_wrong_types(data, expected):
    assert expected in _error(data)


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        (_with(grid__width=1), "grid.width: must be an integer >= 2, got 1"),
        (_with(grid__n_theta=60), "grid.n_theta: must be a multiple of 8 (>= 8), got 60"),
        (_with(medium__sigma_t=0.0), "medium.sigma_t: must be > 0 (per pixel), got 0.0"),
        (_with(medium__sigma_s=0.3), "medium.sigma_s: must satisfy 0 <= sigma_s <= sigma_t"),
        (_with(medium__sigma_s=-0.01), "medium.sigma_s: must satisfy 0 <= sigma_s"),
        (_with(medium__g=1.0), "medium.g: must satisfy -1 < g < 1, got 1.0"),
        (_with(bounces=0), "bounces: must be a positive integer or 'auto', got 0"),
        # Refused before by the renderer, in a message that did not name the file.
        (_with(bounces=100_000), "bounces: at most 10000 bounces are marched"),
        (_with(tolerance=1.5), "tolerance: must lie in (0, 1), got 1.5"),
        (_with(bounces=5, tolerance=1e-3), "tolerance: is used only with bounces: auto"),
        (
            _with(illumination={"kind": "stripes", "period": 6, "lit": 6}),
            "illumination.lit: must be an integer in [1, period-1] = [1, 5], got 6",
        ),
        (
            _with(illumination={"kind": "stripes", "period": 1}),
            "illumination.period: must be an integer >= 2, got 1",
        ),
        (
            _with(illumination={"kind": "stripes", "shifts": 0}),
            "illumination.shifts: must be an integer in [1, period] = [1, 6], got 0",
        ),
        (
            _with(illumination={"kind": "beam", "x": 0.0, "y": 3.0, "width": 0.0}),
            "illumination.width: must be > 0 pixels, got 0.0",
        ),
        (
            _with(illumination={"kind": "beam", "x": 5.0, "y": 3.0}),
            "illumination: beam entry point (5, 3) heading 0 deg must lie on a wall",
        ),
        (
            _with(illumination={"kind": "full", "direction_deg": 180.0}),
            "illumination.direction_deg: 180.0 degrees does not point into the medium",
        ),
    ],
)
def test_out_of_range_values(data, expected):
    assert expected in _error(data)


def test_auto_bounces_refused_when_the_paper_series_diverges():
    # omega = 0.95, A(0.9) ~ 3.2: rho > 1 under phase: paper.
    data = _with(medium={"sigma_t": 0.2, "sigma_s": 0.19, "g": 0.9, "phase": "paper"})
    assert "bounces: auto is impossible: rho = albedo*A(g)" in _error(data)
    explicit = parse_simulation_config({**data, "bounces": 4})
    assert explicit.bounces == 4


def test_shifts_and_phases_together_are_refused():
    data = _with(illumination={"kind": "stripes", "shifts": 6, "phases": [0, 1]})
    assert "illumination: give either shifts or phases, not both" in _error(data)


@pytest.mark.parametrize("wall", ["north", "Left", 0])
def test_bad_entry_wall(wall):
    data = _with(illumination={"kind": "stripes", "entry": wall})
    message = _error(data)
    assert re.search(r"illumination\.entry: must be one of left, right, top, bottom, got", message)


@pytest.mark.parametrize("kind", ["laser", None, 3])
def test_bad_illumination_kind(kind):
    message = _error(_with(illumination={"kind": kind}))
    assert f"illumination.kind: must be one of beam, stripes, full, got {kind!r}" in message


def test_yaml_merge_keys_are_merged_and_duplicates_beside_them_refused(tmp_path):
    """Before: any ``<<: *anchor`` was "could not determine a constructor for the tag
    'tag:yaml.org,2002:merge'"."""
    merged = tmp_path / "merged.yaml"
    text = "a: &a {x: 1, y: 2}\nb: {<<: *a, y: 3}\n"
    merged.write_text(text)
    assert load_yaml(merged)["b"] == {"x": 1, "y": 3}  # the given key overrides
    merged.write_text(text.replace("y: 3}", "y: 3, y: 4}"))
    with pytest.raises(ConfigError, match="duplicate key 'y'"):
        load_yaml(merged)
    merged.write_text("b: {<<: 5}\n")
    with pytest.raises(ConfigError, match="expected a mapping or list of mappings for merging"):
        load_yaml(merged)


def test_file_errors(tmp_path):
    with pytest.raises(ConfigError, match=r"^.*missing\.yaml: file not found$"):
        load_simulation_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("grid: {width: 32\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: invalid YAML"):
        load_simulation_config(bad)
    dup = tmp_path / "dup.yaml"
    dup.write_text(PAPER_YAML + "bounces: 3\n")
    with pytest.raises(ConfigError, match=r"dup\.yaml: invalid YAML: .*duplicate key 'bounces'"):
        load_simulation_config(dup)
    listy = tmp_path / "list.yaml"
    listy.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match=r"list\.yaml: the top level must be a mapping"):
        load_simulation_config(listy)
    typo = tmp_path / "typo.yaml"
    typo.write_text(PAPER_YAML.replace("sigma_t", "sigmat"))
    with pytest.raises(ConfigError, match=rf"^{re.escape(str(typo))}: medium\.sigmat: unknown"):
        load_simulation_config(typo)
