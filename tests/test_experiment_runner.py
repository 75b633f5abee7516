"""The experiment runner works from an installed package, not only from the source tree."""

import dataclasses
import tomllib
from pathlib import Path

import pytest
import yaml

from lightfield_jax.app import experiment as _experiment

ROOT = Path(__file__).resolve().parent.parent


def test_wheel_ships_experiments_and_configs():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    shipped = project["tool"]["hatch"]["build"]["targets"]["wheel"]["force-include"]
    assert shipped["experiments"] == "lightfield_jax/_experiments"
    assert shipped["configs"] == "lightfield_jax/_configs"


def test_config_by_name(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)  # no configs/ folder here: the shipped one is found
    config = _experiment.load_experiment_config("paper_figures", reduced=True)
    assert config["experiment"] == "paper_figures"
    with pytest.raises(FileNotFoundError, match="shipped: .*paper_figures"):
        _experiment.load_experiment_config("no_such_experiment")


def test_packaged_copies_used_outside_a_checkout(monkeypatch, tmp_path):
    package = tmp_path / "site" / "lightfield_jax"
    (package / "_experiments").mkdir(parents=True)
    monkeypatch.setattr(_experiment, "_HERE", package)
    assert _experiment._tree_or_packaged("experiments", "_experiments") == package / "_experiments"
    monkeypatch.setattr(_experiment, "_HERE", ROOT / "lightfield_jax")
    assert _experiment._tree_or_packaged("experiments", "_experiments") == ROOT / "experiments"


def _plane_vs_slab_config():
    """plane_vs_slab's typed config class (the script loaded as the runner loads it)."""
    return _experiment._load_script("plane_vs_slab").Config


@pytest.mark.parametrize(
    "change, message",
    [
        ({"widht": 32}, r"plane_vs_slab: unknown config keys \['widht'\]"),
        ({"width": "32"}, "plane_vs_slab: width: expected int, got '32'"),
        ({"albedo": [0.5, "high"]}, "plane_vs_slab: albedo: expected"),
        ({"max_steps": True}, "plane_vs_slab: max_steps: expected int"),
        ({"boundary": ["mirror"]}, "plane_vs_slab: boundary: unknown 'mirror'"),
    ],
)
def test_a_typed_config_names_the_bad_key(change, message):
    raw = _experiment.load_experiment_config(ROOT / "configs" / "plane_vs_slab.yaml")
    with pytest.raises(ValueError, match=message):
        _experiment.typed_config(_plane_vs_slab_config(), {**raw, **change})
    missing = {k: v for k, v in raw.items() if k != "sigma_t"}
    with pytest.raises(ValueError, match="plane_vs_slab: missing config key 'sigma_t'"):
        _experiment.typed_config(_plane_vs_slab_config(), missing)


def test_a_typed_config_is_frozen_with_tuples():
    import dataclasses

    raw = _experiment.load_experiment_config(ROOT / "configs" / "plane_vs_slab.yaml")
    config = _experiment.typed_config(_plane_vs_slab_config(), raw)
    assert config.albedo == tuple(raw["albedo"]) and config.width == raw["width"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.width = 1


@pytest.mark.parametrize(
    "name", ["inverse_speed_accuracy", "stability_maps", "forward_accuracy", "fit_speed"]
)
def test_an_experiment_refuses_an_unknown_config_key(name, tmp_path):
    script = _experiment._load_script(name)
    ctx = _experiment.Context(out=tmp_path, progress=lambda _m: None, reduced=False)
    for reduced in (False, True):  # the shipped config, full and reduced, is valid
        raw = _experiment.load_experiment_config(ROOT / "configs" / f"{name}.yaml", reduced)
        config = _experiment.typed_config(script.Config, raw)
        assert config.width == raw["width"]
    with pytest.raises(ValueError, match=rf"^{name}: unknown config keys \['widht'\]$"):
        script.run({**raw, "widht": 32}, tmp_path, ctx)  # refused before any work
    missing = {k: v for k, v in raw.items() if k != "width"}
    with pytest.raises(ValueError, match=rf"^{name}: missing config key 'width'$"):
        script.run(missing, tmp_path, ctx)
    assert not any(tmp_path.iterdir())
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.width = 1


def test_a_sweep_resumes_from_its_cache(tmp_path):
    said, calls = [], []
    ctx = _experiment.Context(out=tmp_path, progress=said.append, reduced=True)

    def compute(a, b):
        calls.append((a, b))
        return {"a": a, "b": b, "product": a * b}

    axes = [("a", [1, 2]), ("b", [10, 20, 30])]
    rows = ctx.sweep(axes, lambda a, b: f"a{a}|b{b}", compute)
    assert [(r["a"], r["b"]) for r in rows] == [
        (1, 10),
        (1, 20),
        (1, 30),
        (2, 10),
        (2, 20),
        (2, 30),
    ]
    assert said[0] == "a 1, b 10" and len(calls) == 6
    again = ctx.sweep(axes, lambda a, b: f"a{a}|b{b}", compute)
    assert again == rows and len(calls) == 6  # every point from the cache


def test_write_csv_is_one_table(tmp_path):
    import csv

    path = _experiment.write_csv(tmp_path / "t.csv", ["x", "y"], ([i, i * i] for i in range(3)))
    with open(path, newline="") as f:
        assert list(csv.reader(f)) == [["x", "y"], ["0", "0"], ["1", "1"], ["2", "4"]]


def test_every_experiment_script_loads_and_every_config_names_one():
    """Each script under experiments/ imports (a stale import fails here, not in a
    long run) and each shipped config names a script that exists."""
    names = sorted(p.stem for p in _experiment.EXPERIMENTS_DIR.glob("*.py") if p.stem[0] != "_")
    for name in names:
        assert callable(_experiment._load_script(name).run), name
    configs = _experiment.EXPERIMENTS_DIR.parent / "configs"
    for path in sorted(configs.glob("*.yaml")):
        experiment = yaml.safe_load(path.read_text()).get("experiment")
        if experiment is not None:  # the others are simulate configs
            assert experiment in names, (path.name, experiment)


def test_every_shipped_experiment_config_is_valid_in_full_and_reduced():
    """Each experiment config (and its ``reduced:`` form) passes its script's own
    checks: its typed ``Config``, or its ``_check``; a typo in a config fails here, not
    after hours of a run."""
    configs = _experiment.EXPERIMENTS_DIR.parent / "configs"
    checked = 0
    for path in sorted(configs.glob("*.yaml")):
        data = yaml.safe_load(path.read_text())
        name = data.get("experiment")
        if name is None:
            continue
        script = _experiment._load_script(name)
        for reduced in (False, True) if data.get("reduced") else (False,):
            raw = _experiment.load_experiment_config(path, reduced)
            if hasattr(script, "Config"):
                _experiment.typed_config(script.Config, raw)
            else:
                script._check(raw)
            checked += 1
    assert checked >= 2 * 10 - 1


@pytest.mark.parametrize("name", ["../../tmp/evil", "/tmp/evil", "_inverse", ["a", "b"]])
def test_a_config_names_only_a_shipped_experiment(tmp_path, name):
    """A config is data: it never names a file to run (a path, a helper, a list), and
    a refused config leaves no output folder behind."""
    (tmp_path / "evil.py").write_text("raise SystemExit('ran')\n")
    config = tmp_path / "bad.yaml"
    config.write_text(yaml.safe_dump({"experiment": name}))
    out = tmp_path / "out"
    with pytest.raises(ValueError, match=r"bad\.yaml: experiment: unknown experiment"):
        _experiment.run_experiment(config, out)
    assert not out.exists()


def test_a_config_the_script_refuses_is_named_and_leaves_no_folder(tmp_path):
    config = tmp_path / "typo.yaml"
    config.write_text(yaml.safe_dump({"experiment": "inverse_speed_accuracy", "widht": 32}))
    out = tmp_path / "out"
    with pytest.raises(ValueError, match=r"typo\.yaml: .*widht"):
        _experiment.run_experiment(config, out)
    assert not out.exists()


def test_reduced_needs_a_reduced_section(tmp_path):
    """Before: ignored where the config had none; the full run was recorded as reduced."""
    config = tmp_path / "plain.yaml"
    config.write_text("experiment: clipped_captures\nwidth: 16\n")
    with pytest.raises(ValueError, match="--reduced: this config has no reduced: section"):
        _experiment.load_experiment_config(config, reduced=True)
