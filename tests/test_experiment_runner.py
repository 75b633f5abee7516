"""The experiment runner works from an installed package, not only from the source tree."""

import dataclasses
import json
import re
import tomllib
import types
from pathlib import Path

import numpy as np
import pytest
import yaml

from lightfield_jax.app import experiment as _experiment
from lightfield_jax.app.experiment_config import typed_config
from lightfield_jax.app.experiment_records import write_csv
from lightfield_jax.app.experiment_scripts import load_script, tree_or_packaged

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


def test_an_empty_name_or_a_config_that_is_no_file_is_named(monkeypatch, tmp_path):
    # Before: "": ".: no such experiment config"; a folder or FIFO: "no such config".
    monkeypatch.chdir(tmp_path)
    with pytest.raises(FileNotFoundError, match="^an empty experiment name"):
        _experiment.load_experiment_config("")
    (tmp_path / "folder.yaml").mkdir()
    with pytest.raises(ValueError, match="folder.yaml: is a directory"):
        _experiment.load_experiment_config(tmp_path / "folder.yaml")


def test_packaged_copies_used_outside_a_checkout(monkeypatch, tmp_path):
    package = tmp_path / "site" / "lightfield_jax"
    (package / "_experiments").mkdir(parents=True)
    assert tree_or_packaged("experiments", "_experiments", package) == package / "_experiments"
    checkout = ROOT / "lightfield_jax"
    assert tree_or_packaged("experiments", "_experiments", checkout) == ROOT / "experiments"
    assert _experiment.EXPERIMENTS_DIR == ROOT / "experiments"  # this checkout's


def _plane_vs_slab_config():
    """plane_vs_slab's typed config class (the script loaded as the runner loads it)."""
    return load_script("plane_vs_slab").Config


@pytest.mark.parametrize(
    "change, message",
    [
        ({"widht": 32}, r"plane_vs_slab: unknown config keys \['widht'\]"),
        ({"width": "32"}, "plane_vs_slab: width: expected int, got '32'"),
        ({"albedo": [0.5, "high"]}, r"plane_vs_slab: albedo\[1\]: expected float, got .high."),
        ({"max_steps": True}, "plane_vs_slab: max_steps: expected int"),
        ({"boundary": ["mirror"]}, "plane_vs_slab: boundary: unknown 'mirror'"),
    ],
)
def test_a_typed_config_names_the_bad_key(change, message):
    raw = _experiment.load_experiment_config(ROOT / "configs" / "plane_vs_slab.yaml")
    with pytest.raises(ValueError, match=message):
        typed_config(_plane_vs_slab_config(), {**raw, **change})
    missing = {k: v for k, v in raw.items() if k != "sigma_t"}
    with pytest.raises(ValueError, match="plane_vs_slab: missing config key 'sigma_t'"):
        typed_config(_plane_vs_slab_config(), missing)


def test_a_typed_config_is_frozen_with_tuples():
    import dataclasses

    raw = _experiment.load_experiment_config(ROOT / "configs" / "plane_vs_slab.yaml")
    config = typed_config(_plane_vs_slab_config(), raw)
    assert config.albedo == tuple(raw["albedo"]) and config.width == raw["width"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.width = 1


@pytest.mark.parametrize(
    "name", ["inverse_speed_accuracy", "stability_maps", "forward_accuracy", "fit_speed"]
)
def test_an_experiment_refuses_an_unknown_config_key(name, tmp_path):
    script = load_script(name)
    ctx = _experiment.Context(out=tmp_path, progress=lambda _m: None, reduced=False)
    for reduced in (False, True):  # the shipped config, full and reduced, is valid
        raw = _experiment.load_experiment_config(ROOT / "configs" / f"{name}.yaml", reduced)
        config = typed_config(script.Config, raw)
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


def test_an_unreadable_cache_entry_is_computed_again(tmp_path):
    """Before: a truncated cache file stopped the run with a JSON error blamed on the
    config (a ValueError)."""
    ctx = _experiment.Context(out=tmp_path, progress=lambda _m: None, reduced=True)
    assert ctx.cached("unit", lambda: 1) == 1
    (entry,) = (tmp_path / "cache").iterdir()
    for text in ('{"key": "unit", "val', "[1, 2]", '{"key": "unit"}'):
        entry.write_text(text)
        assert ctx.cached("unit", lambda: 2) == 2
    assert ctx.cached("unit", lambda: 3) == 2  # stored again


def test_write_csv_is_one_table(tmp_path):
    import csv

    path = write_csv(tmp_path / "t.csv", ["x", "y"], ([i, i * i] for i in range(3)))
    with open(path, newline="") as f:
        assert list(csv.reader(f)) == [["x", "y"], ["0", "0"], ["1", "1"], ["2", "4"]]


def test_every_experiment_script_loads_and_every_config_names_one():
    """Each script under experiments/ imports (a stale import fails here, not in a
    long run) and each shipped config names a script that exists."""
    names = sorted(p.stem for p in _experiment.EXPERIMENTS_DIR.glob("*.py") if p.stem[0] != "_")
    for name in names:
        assert callable(load_script(name).run), name
    configs = _experiment.EXPERIMENTS_DIR.parent / "configs"
    for path in sorted(configs.glob("*.yaml")):
        experiment = yaml.safe_load(path.read_text()).get("experiment")
        if experiment is not None:  # the others are simulate configs
            assert experiment in names, (path.name, experiment)


def test_every_shipped_experiment_config_is_valid_in_full_and_reduced():
    """Each experiment config (and its ``reduced:`` form) passes its script's own
    checks, its typed ``Config``; a typo in a config fails here, not after hours of a
    run."""
    configs = _experiment.EXPERIMENTS_DIR.parent / "configs"
    checked = 0
    for path in sorted(configs.glob("*.yaml")):
        data = yaml.safe_load(path.read_text())
        name = data.get("experiment")
        if name is None:
            continue
        script = load_script(name)
        for reduced in (False, True) if data.get("reduced") else (False,):
            raw = _experiment.load_experiment_config(path, reduced)
            _experiment.check_experiment_config(script, raw)  # every script has a Config
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


# --------------------------------------------------------------------------- hostile configs


@pytest.fixture
def no_work(monkeypatch):
    """A script's run() fails the test: a bad config must be refused before it starts."""
    load = load_script

    def guarded(name):
        module = load(name)

        def run(*_args, **_kwargs):
            raise AssertionError(f"{name}: run() reached with a bad config")

        module.run = run
        return module

    monkeypatch.setattr(_experiment, "load_script", guarded)


def _shipped(name: str, reduced: bool = True) -> dict:
    return _experiment.load_experiment_config(ROOT / "configs" / f"{name}.yaml", reduced)


def _write(tmp_path, data, name="bad.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


def _refused(tmp_path, data, message, prefix=""):
    """``data`` run as a config: one-line ValueError naming its file (then ``prefix``),
    no output folder."""
    path, out = _write(tmp_path, data), tmp_path / "out"
    with pytest.raises(ValueError) as info:
        _experiment.run_experiment(path, out)
    text = str(info.value)
    assert text.startswith(f"{path}: {prefix}") and "\n" not in text, text
    assert re.search(message, text), text
    assert not out.exists()


@pytest.mark.parametrize(
    "name, key",
    [
        ("slab_recovery", "thickness"),  # before: KeyError traceback after the folder was made
        ("paper_figures", "oblique.y"),  # before: KeyError after figures 11-13 were drawn
        ("forward_accuracy", "scenes[0].beam.y"),  # before: TypeError in Beam()
        ("tail_acceleration", "slab.rho"),
        ("coarse_tail", "media[0].bounces"),
        ("stability_maps", "start.media[0].g"),
        ("model_size", "truth.tolerance"),
        ("inverse_speed_accuracy", "medium.g"),
    ],
)
def test_a_missing_key_is_named_with_its_path_before_any_work(tmp_path, no_work, name, key):
    data = {**_shipped(name, reduced=False)}
    data = json.loads(json.dumps(data))  # a deep copy
    *parents, last = re.split(r"\.|(?=\[)", key)
    node = data
    for part in parents:
        node = node[int(part[1:-1])] if part.startswith("[") else node[part]
    del node[last]
    _refused(tmp_path, data, rf"{name}: missing config key {re.escape(repr(key))}$")


def test_every_required_key_of_every_experiment_is_checked(tmp_path):
    """Each top-level key of each shipped config left out: refused with its name, or
    (a key with a default) accepted."""
    for path in sorted((ROOT / "configs").glob("*.yaml")):
        raw = yaml.safe_load(path.read_text())
        if "experiment" not in raw:
            continue
        raw.pop("reduced", None)
        script = load_script(raw["experiment"])
        fields = {f.name: f for f in dataclasses.fields(script.Config)}
        for key in set(raw) - {"experiment"}:
            partial = {k: v for k, v in raw.items() if k != key}
            field = fields[key]
            if (
                field.default is dataclasses.MISSING
                and field.default_factory is dataclasses.MISSING
            ):
                with pytest.raises(ValueError, match=rf"missing config key '{key}'$"):
                    _experiment.check_experiment_config(script, partial)
            else:
                _experiment.check_experiment_config(script, partial)


@pytest.mark.parametrize(
    "name, change, message",
    [
        ("paper_figures", {"width": "128"}, r"paper_figures: width: expected int, got '128'$"),
        (
            "paper_figures",
            {"lightfield_bounces": True},
            "lightfield_bounces: expected int, got True",
        ),
        ("paper_figures", {"width": 100_000}, r"width: must be in \[8, 2048\], got 100000$"),
        ("paper_figures", {"oblique": {"y": 4.5, "direction_deg": 30, "show": 3}}, "oblique.show"),
        (
            "paper_figures",
            {"oblique": {3: 1, "y": 4.5, "direction_deg": 30, "show_bounces": 3}},
            r"unknown config keys \['oblique.3'\]$",  # before: a TypeError
        ),
        ("paper_figures", {"beam_y": -3.0}, r"beam_y: must be in \(0, height=96\)"),
        ("forward_accuracy", {"seed": -5}, r"seed: must be in \[0, 4294967295\], got -5$"),
        ("forward_accuracy", {"n_theta": [12]}, "grid.n_theta: must be a multiple of 8"),
        ("slab_recovery", {"photons": float("nan")}, "photons: expected int, got nan"),
        ("slab_recovery", {"sigma_t": float("inf")}, "sigma_t: must be a finite number"),
        (
            "slab_recovery",
            {"media": [{"albedo": 0.9, "g": 0.8, "colour": 1}]},
            r"media\[0\].colour",
        ),
        ("slab_recovery", {"n_z": 1.5}, "n_z: expected int or null, got 1.5"),
        ("tail_acceleration", {"rho": [0.9, 1.0]}, r"rho\[1\]: must be in \(0, 1\), got 1.0$"),
        ("tail_acceleration", {"methods": ["cg"]}, r"methods\[0\]: must be one of series_auto"),
        ("tail_acceleration", {"methods": []}, "methods: at least one each"),  # max() of []
        ("coarse_tail", {"coarse_after": [4, 1]}, r"coarse_after\[1\]: must be in \[2, 1000\]"),
        ("coarse_tail", {"coarse_after": [32]}, r"media\[0\].bounces: must exceed every"),
        ("coarse_tail", {"refine": 1}, r"refine: must be in \[2, 4\], got 1$"),
        (
            "coarse_tail",
            {"media": [{"name": "m", "sigma_t": 0.1, "sigma_s": 0.2, "g": 0.5, "bounces": 32}]},
            r"media\[0\]: medium.sigma_s: must satisfy",
        ),
        (
            "stability_maps",
            {"albedo_g": {"sigma_t": "x", "albedo": [0.5], "g": [0]}},
            r"albedo_g.sigma_t: expected float",
        ),
        (
            "stability_maps",
            {"high_albedo": {"sigma_t": 0.2, "albedo": [0.9], "g": [0.5], "joint_timeout": -1}},
            r"high_albedo.joint_timeout: must be in \(0, 86400\]",
        ),
        ("stability_maps", {"noise": {"levels": [[1000.0]]}}, "noise.levels"),
        # Before: run, then one of the two kept (model_size.json, forward_accuracy's
        # scene table) or their rows mixed in one figure (stability_maps' start map).
        (
            "model_size",
            {
                "scenes": [
                    {"name": "m", "sigma_t": 0.2, "sigma_s": s, "g": 0.4} for s in (0.03, 0.1)
                ]
            },
            r"scenes: names must differ, got \['m', 'm'\]",
        ),
        (
            "forward_accuracy",
            {
                "scenes": [
                    {"name": "a/b", "sigma_t": 0.2, "sigma_s": 0.03, "g": 0.4, "beam": {"y": 8}}
                ]
            },
            r"scenes\[0\].name: must be a non-empty name without '/', got 'a/b'",
        ),
        # Before: scipy's "array of sample points is empty" naming no key; an empty
        # shifts/noise/period/black_level/start list published empty results (exit 0);
        # a row's methods: [] ran the top level's methods.
        (
            "stability_maps",
            {"albedo_g": {"sigma_t": 0.2, "albedo": [], "g": [0.4]}},
            r"albedo_g.albedo: at least one value, got \[\]$",
        ),
        ("stability_maps", {"shifts": {"phases": [[0, 3], []]}}, r"shifts.phases\[1\]: at least"),
        ("stability_maps", {"noise": {"levels": []}}, "noise.levels: at least one value"),
        (
            "stability_maps",
            {"high_albedo": {"sigma_t": 0.2, "albedo": [0.9], "g": [0.5], "methods": []}},
            "high_albedo.methods: at least one value",
        ),
        (
            "fit_speed",
            {"fit": {"tial": None}},
            r"fit_speed: fit.tial: unknown key \(did you mean 'tail'\?\)",
        ),
        ("fit_speed", {"fit": {"max_steps": "many"}}, "fit.max_steps: must be an integer"),
        (
            "fit_speed",
            {"media": [{"name": "m", "sigma_t": -1, "sigma_s": 0.1, "g": 0.4}]},
            r"media\[0\]: medium.sigma_t: must be > 0",
        ),
        ("model_size", {"large": {"n_thetaa": 64}}, "large.n_thetaa: unknown key"),
        ("clipped_captures", {"seeds": [0, -1]}, r"seeds\[1\]: must be in \[0, "),
        ("inverse_speed_accuracy", {"noise": {"photon": 5}}, "noise.photon: unknown key"),
        (
            "plane_vs_slab",
            {"optical_thickness": [1e9]},
            r"optical_thickness\[0\]: must be in \(0, 1000\]",
        ),
        ("slab_depth_accuracy", {"n": 0.5}, r"geometry.n: must lie in \[1, 4\]"),
    ],
)
def test_a_bad_value_is_named_before_any_work(tmp_path, no_work, name, change, message):
    """Strings and bools for numbers, out-of-range, non-finite and unknown nested
    values: before, run into the script (a traceback, a hang, or a silent answer)."""
    _refused(tmp_path, {**_shipped(name, reduced=False), **change}, message, f"{name}: ")


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "the top level must be a mapping"),
        ("- experiment\n- paper_figures\n", "the top level must be a mapping"),
        ("experiment: paper_figures\nreduced: [1]\n", "reduced: must be a mapping"),
        ("experiment: 3\n", "unknown experiment 3"),
        ("experiment: paper_figures\n2: 3\nwidth: 32\n", r"unknown config keys \['2'\]"),
    ],
)
def test_a_config_of_the_wrong_shape_is_one_line(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        _experiment.run_experiment(path, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_reduced_cannot_name_another_experiment(tmp_path, no_work):
    """Before: ``reduced: {experiment: OTHER}`` ran another script with --reduced."""
    path = _write(tmp_path, {**_shipped("paper_figures", False), "reduced": {"experiment": "x"}})
    with pytest.raises(ValueError, match=r"reduced: overrides unknown keys \['experiment'\]"):
        _experiment.run_experiment(path, tmp_path / "out", reduced=True)


def test_a_typo_in_reduced_is_refused_in_a_full_run_too(tmp_path, no_work):
    """Before: found only by a --reduced run (the test suite's), after the full run."""
    path = _write(tmp_path, {**_shipped("paper_figures", False), "reduced": {"widht": 32}})
    with pytest.raises(ValueError, match=r"reduced: overrides unknown keys \['widht'\]"):
        _experiment.run_experiment(path, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_a_reduced_run_checks_the_values_its_overrides_replace(tmp_path, no_work):
    """Before: a bad top-level width under reduced: {width: 32} passed the --reduced
    trial run and failed only the full run."""
    full = _shipped("paper_figures", False)
    path = _write(tmp_path, {**full, "width": -5, "reduced": {"width": 32}})
    with pytest.raises(ValueError, match=r"bad\.yaml: .*width"):
        _experiment.run_experiment(path, tmp_path / "out", reduced=True)
    assert not (tmp_path / "out").exists()


def test_a_grid_past_the_memory_is_refused_before_any_work(tmp_path, no_work):
    from lightfield_jax.runtime.memory import MemoryLimitError, memory_limit

    path = _write(tmp_path, {**_shipped("paper_figures"), "width": 2048, "height": 2048})
    with memory_limit(1 << 30), pytest.raises(MemoryLimitError, match="2048x2048 pixels needs"):
        _experiment.run_experiment(path, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_a_failed_run_publishes_nothing_but_its_cache(tmp_path, monkeypatch):
    """Before: the script wrote into OUT directly: a run failing after its first figures
    left them there (and a stale summary.json of an earlier run beside them)."""
    calls = []

    def run(config, out, ctx):
        value = ctx.cached("unit", lambda: calls.append(1) or 42)
        (out / "figure.png").write_text("half")
        if len(calls) == 1:
            raise RuntimeError("failed after its first figure")
        return {"value": value}

    script = types.SimpleNamespace(Config=load_script("paper_figures").Config, run=run)
    monkeypatch.setattr(_experiment, "load_script", lambda _name: script)
    path, out = _write(tmp_path, _shipped("paper_figures")), tmp_path / "out"
    with pytest.raises(RuntimeError, match="first figure"):
        _experiment.run_experiment(path, out)
    assert sorted(p.name for p in out.iterdir()) == ["cache"]  # only the finished unit
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    calls.append(1)  # the rerun succeeds: it resumes from the cache, then publishes
    record = _experiment.run_experiment(path, out)
    assert record["summary"] == {"value": 42} and len(calls) == 2
    assert sorted(p.name for p in out.iterdir()) == ["cache", "figure.png", "summary.json"]


def test_an_unknown_fit_key_of_fit_speed_exits_2_in_one_line(tmp_path, no_work, capsys):
    """Before: exit 0, each medium's fit 'recorded' as a child process's traceback."""
    from lightfield_jax.app.cli import main

    path = _write(tmp_path, {**_shipped("fit_speed", reduced=False), "fit": {"tial": None}})
    assert main(["experiment", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    assert err.startswith(f"lightfield-jax: error: {path}: fit_speed: fit.tial: unknown key")
    assert not (tmp_path / "out").exists()


def test_a_failed_fit_speed_child_fails_the_experiment(tmp_path, monkeypatch, capsys):
    """A child process whose fit raises: before, recorded as the medium's result (its
    traceback as 'error_message') and exit 0; now exit 1 with its last line."""
    from lightfield_jax.app.cli import main

    load = load_script

    def broken(name):
        module = load(name)
        module._capture = lambda cfg, medium, height: np.ones((6, 8, 8), np.float32)
        module._fit_kwargs = lambda cfg, medium: {"no_such_option": 1}
        return module

    monkeypatch.setattr(_experiment, "load_script", broken)
    path, out = _write(tmp_path, _shipped("fit_speed")), tmp_path / "out"
    assert main(["experiment", str(path), "--out", str(out), "-q"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    assert "fit_speed: media milk: the fit's child process failed: TypeError" in err, err
    assert not out.exists() or sorted(p.name for p in out.iterdir()) == []


def test_a_crashed_fit_child_is_one_line():
    """stability_maps and model_size fit on Dask workers: a fit that crashes (not one
    that fails, which is recorded) stops the run with an ExperimentError of one line
    (exit 1), not the worker's whole traceback."""
    import lightfield_jax as lfj

    inv = _experiment.load_helper("_inverse")
    truth = {"sigma_t": 0.2, "sigma_s": 0.04, "g": 0.4}
    with pytest.raises(_experiment.ExperimentError) as info:
        inv.fit_record_limited(
            np.ones((6, 8, 8)),
            lfj.Stripes(),
            truth,
            timeout=300,
            dtype="float16",
            xla_cache_dir=None,
        )
    assert str(info.value) == (
        "a fit on a Dask worker failed: ValueError: dtype: must be float32 or float64, "
        "got 'float16'"
    )


def test_an_experiment_does_not_replace_its_own_config(tmp_path, no_work, capsys):
    """A config inside --out named like an output (summary.json): before, replaced by
    the run's summary."""
    from lightfield_jax.app.cli import main

    config = tmp_path / "summary.json"
    config.write_text(yaml.safe_dump(_shipped("paper_figures", reduced=False)))
    before = config.read_text()
    assert main(["experiment", str(config), "--out", str(tmp_path)]) == 2
    assert "holds an input of this command" in capsys.readouterr().err
    assert config.read_text() == before
