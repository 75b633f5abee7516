"""The experiment runner works from an installed package, not only from the source tree."""

import tomllib
from pathlib import Path

import pytest

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
