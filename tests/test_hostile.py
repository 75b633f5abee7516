"""Hostile inputs and faults (issue: never destroy a file, never hang, never run out of
memory, stop on Ctrl-C): each case exits 2 with one line naming what is wrong, before
the work, and leaves every file as it was."""

import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
import yaml
from cli_support import SIMULATE, H, W
from cli_support import refused as _refused
from cli_support import run as _run

import lightfield_jax as lfj
from lightfield_jax.app.arguments import XLA_CACHE_ENV
from lightfield_jax.app.cli import main
from lightfield_jax.capture.image_write import write_exr, write_png
from lightfield_jax.capture.io import read_image
from lightfield_jax.runtime.memory import MAX_MEMORY_ENV

P = 6
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _environment(monkeypatch):
    monkeypatch.setenv(XLA_CACHE_ENV, "off")
    monkeypatch.delenv(MAX_MEMORY_ENV, raising=False)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """The milk as a 32x24 six-shift stripe capture with a dark frame."""
    folder = tmp_path_factory.mktemp("hostile")
    (folder / "sim.yaml").write_text(SIMULATE)
    assert main(["simulate", str(folder / "sim.yaml"), "--out", str(folder / "cap"), "-q"]) == 0
    return folder / "cap"


@pytest.fixture
def capture(simulated, tmp_path):
    """A fresh copy of the simulated capture folder."""
    folder = tmp_path / "cap"
    shutil.copytree(simulated, folder)
    return folder


def _edit(folder: Path, **changes) -> Path:
    path = folder / "capture.yaml"
    data = yaml.safe_load(path.read_text())
    phase = (data.get("fit") or {}).get("phase")
    if isinstance(changes.get("fit"), dict) and phase is not None:
        # New fit settings keep the convention the capture was simulated in.
        changes["fit"] = {"phase": phase, **changes["fit"]}
    data.update(changes)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


# ------------------------------------------------------------- 1. outputs and inputs


def test_an_output_that_is_an_input_is_refused(capture, capsys):
    before = _snapshot(capture)
    yaml_file = capture / "capture.yaml"
    _refused(capsys, "fit", yaml_file, "--out", capture / "shift_00.exr", match="is an input")
    _refused(capsys, "fit", yaml_file, "--out", capture / "dark.exr", match="is an input")
    # The same file through another path (a symlink) is still the input.
    (capture.parent / "link.exr").symlink_to(capture / "shift_03.exr")
    _refused(capsys, "fit", yaml_file, "--out", capture.parent / "link.exr", match="is an input")
    _refused(capsys, "inspect", "--json", yaml_file, yaml_file, match="is an input")
    _refused(capsys, "inspect", yaml_file, "--plot", capture / "shift_01.exr", match="extension")
    cfg = capture.parent / "sim.yaml"
    cfg.write_text(SIMULATE)
    _refused(capsys, "simulate", cfg, "--out", cfg, match="not a directory")
    assert _snapshot(capture) == before
    # A config named like a file simulate writes, in its output folder.
    (capture / "capture.yaml").write_text(SIMULATE)
    before = _snapshot(capture)
    _refused(capsys, "simulate", capture / "capture.yaml", "--out", capture, match="holds an input")
    assert _snapshot(capture) == before


def test_a_file_output_ending_in_a_separator_is_refused(capture, capsys, tmp_path):
    """Before: ``fit --out results/`` (a folder meant, none there yet) wrote the results
    as a file named ``results``, and ``--plot fit.png/`` a figure ``fit.png``."""
    out = tmp_path / "results"
    _refused(capsys, "fit", capture / "capture.yaml", "--out", f"{out}/", match="ends in '/'")
    json_out = tmp_path / "r.json"
    plot = f"{tmp_path / 'fit.png'}/"
    _refused(capsys, "fit", capture / "capture.yaml", "--out", json_out, "--plot", plot, match=plot)
    _refused(capsys, "inspect", capture / "capture.yaml", "--json", f"{out}/", match="a folder")
    assert sorted(tmp_path.iterdir()) == [capture]


def test_a_json_output_named_like_an_image_or_a_figure_is_refused(capture, capsys, tmp_path):
    """Before: ``fit --out results.png`` (the figure meant) wrote the JSON results into
    a file named results.png, exit 0; ``inspect --json`` and ``bench --out`` too."""
    yaml_file = capture / "capture.yaml"
    line = _refused(capsys, "fit", yaml_file, "--out", tmp_path / "r.png", match="--out")
    assert "written as JSON" in line and ".png" in line and "--plot" in line
    _refused(capsys, "fit", yaml_file, "--out", tmp_path / "r.EXR", match="a .exr name")
    _refused(capsys, "inspect", yaml_file, "--json", tmp_path / "i.pdf", match="--json")
    _refused(capsys, "bench", "--out", tmp_path / "b.npy", match="a .npy name")
    assert sorted(tmp_path.iterdir()) == [capture]


def test_a_folder_of_another_command_is_not_written_over(capture, capsys, tmp_path):
    """Before: ``render --out DIR`` into simulate's folder replaced its bounces.npy
    (exit 0), and simulate into render's folder its bounces.npy and bounces.exr."""
    before = _snapshot(capture)
    results = _results(capture, tmp_path)
    line = _refused(
        capsys, "render", results, "--out", capture, match="holds the outputs of lightfield-jax"
    )
    assert "simulate (metadata.json), whose bounces.npy this command would replace" in line
    assert _snapshot(capture) == before
    rendered = tmp_path / "rendered"
    rendered.mkdir()
    # render --plot's figures too: simulate --plot would replace them.
    for name in ("bounces.npy", "bounces.exr", "render.json", "bounce_images.png"):
        (rendered / name).write_bytes(b"mine")
    cfg = tmp_path / "sim.yaml"
    cfg.write_text(SIMULATE)
    for argv in (
        ["simulate", cfg, "--out", rendered],
        ["simulate", cfg, "--out", tmp_path / "s", "--plot", rendered],
        ["demo", "--out", rendered],
    ):
        _refused(capsys, *argv, match="holds the outputs of lightfield-jax render (render.json)")
    assert all((rendered / n).read_bytes() == b"mine" for n in os.listdir(rendered))
    assert not (tmp_path / "s").exists()
    # An unrelated file of another command's folder is no conflict; nor is a rerun.
    (tmp_path / "figs").mkdir()
    (tmp_path / "figs" / "metadata.json").write_text("{}")
    assert main(["render", str(results), "--out", str(tmp_path / "figs"), "-q"]) == 0
    assert main(["render", str(results), "--out", str(tmp_path / "figs"), "-q"]) == 0


def test_a_channel_subfolder_of_another_command_is_not_written_over(
    simulated, capture, capsys, tmp_path
):
    """Before: ``render --out DIR`` of an RGB result checked DIR only, and replaced the
    bounces.npy of simulate's folder DIR/R (exit 0)."""
    fit = json.loads(_results(capture, tmp_path).read_text())
    results = tmp_path / "rgb.json"
    results.write_text(json.dumps({"capture": fit["capture"], "per_channel": {"R": fit, "G": fit}}))
    out = tmp_path / "out"
    shutil.copytree(simulated, out / "R")  # simulate's folder, where render writes R
    before = _snapshot(out / "R")
    line = _refused(capsys, "render", results, "--out", out, match="holds the outputs of")
    assert line.endswith(
        f"{out / 'R'}: holds the outputs of lightfield-jax simulate (metadata.json), whose "
        "bounces.npy this command would replace; choose another output folder"
    )
    assert _snapshot(out / "R") == before and sorted(os.listdir(out)) == ["R"]
    # An experiment's figures where render --plot writes G's.
    shutil.rmtree(out / "R")
    (out / "G").mkdir()
    (out / "G" / "summary.json").write_text("{}")
    (out / "G" / "bounce_images.png").write_bytes(b"mine")
    _refused(capsys, "render", results, "--out", out, "--plot", match="lightfield-jax experiment")
    assert (out / "G" / "bounce_images.png").read_bytes() == b"mine"
    # A subfolder that is a file is refused before the work, as DIR itself is.
    (out / "R").write_text("mine")
    _refused(capsys, "render", results, "--out", out, match=f"{out / 'R'}: exists and is not a")
    # Render's own channel folders are rerun into.
    (out / "R").unlink()
    for _ in range(2):
        assert main(["render", str(results), "--out", str(tmp_path / "own"), "-q"]) == 0
    assert sorted(os.listdir(tmp_path / "own")) == ["G", "R"]


def test_simulate_does_not_write_over_a_capture_of_the_users_own(capture, capsys, tmp_path):
    """Before: ``simulate --out DIR`` into a folder holding the user's capture (no
    simulate marker) silently replaced its capture.yaml and shift_*.exr (exit 0)."""
    (capture / "metadata.json").unlink()  # the user's own capture: not simulate's
    (capture / "capture.yaml").write_text("# mine, hand-edited\n" + SIMULATE)
    before = _snapshot(capture)
    cfg = tmp_path / "sim.yaml"
    cfg.write_text(SIMULATE)
    for argv in (["simulate", cfg, "--out", capture], ["demo", "--out", capture]):
        line = _refused(capsys, *argv, match="holds capture.yaml (and ")
        assert "lightfield-jax simulate did not write (no metadata.json" in line
    assert _snapshot(capture) == before
    # A folder of images only, and pattern's folder (its capture.yaml template).
    (capture / "capture.yaml").unlink()
    _refused(capsys, "simulate", cfg, "--out", capture, match="holds bounces.npy (and ")
    assert (
        main(["pattern", "--width", "64", "--height", "48", "--out", str(tmp_path / "pat"), "-q"])
        == 0
    )
    _refused(capsys, "simulate", cfg, "--out", tmp_path / "pat", match="holds capture.yaml")
    # Simulate's own folder is rerun into, and a folder of unrelated files is written.
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    for folder in (tmp_path / "own", tmp_path / "own", tmp_path / "other"):
        assert main(["simulate", str(cfg), "--out", str(folder), "-q"]) == 0
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"
    # Its figures folder is rerun into too (its figures replaced: no capture there).
    for _ in range(2):
        argv = ["simulate", str(cfg), "--out", str(tmp_path / "own"), "-q"]
        assert main([*argv, "--plot", str(tmp_path / "figs")]) == 0


def test_an_empty_output_path_is_refused_by_its_option(capture, capsys, tmp_path):
    """Before: ``--out ''`` gave "PosixPath('.') has an empty name" and ``fit --plot ''``
    was taken as no figure (exit 0)."""
    cfg = tmp_path / "sim.yaml"
    cfg.write_text(SIMULATE)
    results = _results(capture, tmp_path)
    for argv, option in (
        (["simulate", cfg, "--out", ""], "--out"),
        (["simulate", cfg, "--out", tmp_path / "s", "--plot", ""], "--plot"),
        (["render", results, "--out", ""], "--out"),
        (["pattern", "--width", 12, "--height", 12, "--out", ""], "--out"),
        (["experiment", cfg, "--out", ""], "--out"),
        (["fit", capture / "capture.yaml", "--out", ""], "--out"),
        (["fit", capture / "capture.yaml", "--out", tmp_path / "r.json", "--plot", ""], "--plot"),
        (["inspect", capture / "capture.yaml", "--json", ""], "--json"),
    ):
        line = _refused(capsys, *argv, match=f"{option}: an empty path")
        assert "PosixPath" not in line
    assert sorted(os.listdir(tmp_path)) == ["cap", "results.json", "sim.yaml"]


def test_a_dash_for_standard_output_is_refused_by_its_option(
    capture, capsys, tmp_path, monkeypatch
):
    """Before: ``inspect --json -`` (standard output, to most tools) wrote a file named
    ``-`` in the current folder, and ``fit --out -`` its results there."""
    monkeypatch.chdir(tmp_path)
    for argv, option in (
        (["inspect", capture / "capture.yaml", "--json", "-"], "--json"),
        (["fit", capture / "capture.yaml", "--out", "-"], "--out"),
        (["fit", capture / "capture.yaml", "--out", "r.json", "--plot", "-"], "--plot"),
    ):
        _refused(capsys, *argv, match=f"{option}: '-' (standard output) is not supported")
    assert sorted(os.listdir(tmp_path)) == ["cap"]


def test_two_outputs_naming_one_file_are_refused(capture, capsys, tmp_path):
    out = tmp_path / "r.png"
    _refused(
        capsys,
        "fit",
        capture / "capture.yaml",
        "--out",
        out,
        "--plot",
        tmp_path / "." / "r.png",
        match="names the same file as the output",
    )
    assert not out.exists()


def test_outputs_that_are_not_regular_files_are_refused(capture, capsys, tmp_path):
    fifo = tmp_path / "pipe.json"
    os.mkfifo(fifo)
    _refused(capsys, "fit", capture / "capture.yaml", "--out", fifo, match="not a regular file")
    assert fifo.is_fifo()
    _refused(capsys, "fit", capture / "capture.yaml", "--out", tmp_path, match="is a directory")
    _refused(capsys, "bench", "--out", fifo, match="not a regular file")


def test_a_read_only_output_is_not_replaced(capture, capsys, tmp_path):
    """Before: replaced through its folder's permissions (os.replace ignores the file's
    own mode), exit 0."""
    out = tmp_path / "r.json"
    out.write_text("{}")
    out.chmod(0o444)
    _refused(capsys, "fit", capture / "capture.yaml", "--out", out, match="is read-only")
    assert out.read_text() == "{}"


def test_a_hard_link_is_one_file_in_two_roles(capture, capsys):
    """Before: a symbolic link was refused, a hard link to the same frame was not."""
    os.link(capture / "dark.exr", capture / "black.exr")
    _edit(capture, black_frame="black.exr")
    _refused(capsys, "inspect", capture / "capture.yaml", match="is also dark_frame")


def test_a_pixel_size_outside_any_camera_is_refused(capture, capsys):
    """Before: 5e-324 mm gave null coefficients per mm, 1e-300 mm sigma_t 2e299 mm^-1."""
    _edit(capture, pixel_size_mm=5e-324)
    _refused(capsys, "inspect", capture / "capture.yaml", match="pixel_size_mm: must lie in")
    with pytest.raises(ValueError, match=r"pixel_size_mm: must lie in \[1e-06, 1000\] mm"):
        lfj.fit_images(np.ones((6, 8, 8)), lfj.Stripes(), pixel_size_mm=1e-300)


def test_an_experiment_config_is_read_by_the_configs_loader(capsys, tmp_path):
    """Before: plain yaml.safe_load: duplicate keys taken silently (the last one won),
    and aliases expanded without a limit (an alias bomb ran the machine out of memory)."""
    dup = tmp_path / "dup.yaml"
    dup.write_text("experiment: fit_speed\nheight: 96\nheight: -5\n")
    _refused(capsys, "experiment", dup, "--out", tmp_path / "o", match="duplicate key")
    bomb = tmp_path / "bomb.yaml"
    levels = ["a0: &l0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    levels += [f"a{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 10)}]" for i in range(1, 9)]
    bomb.write_text("experiment: fit_speed\n" + "\n".join(levels) + "\nn_theta: *l8\n")
    _refused(capsys, "experiment", bomb, "--out", tmp_path / "o", match="alias")


def test_the_default_experiment_folder_is_checked_like_a_given_one(capsys, tmp_path, monkeypatch):
    """Before: without --out the folder results/NAME was not checked: an experiment ran
    and wrote its *.json and figures into the outputs of another command there (here
    simulate's, whose metadata.json matches), which --out results/NAME refuses."""
    monkeypatch.chdir(tmp_path)
    folder = tmp_path / "results" / "coverage"
    folder.mkdir(parents=True)
    (folder / "metadata.json").write_text("{}")
    _refused(
        capsys,
        *("experiment", "coverage", "--reduced"),
        match="results/coverage: holds the outputs of lightfield-jax simulate (metadata.json)",
    )
    assert sorted(p.name for p in folder.iterdir()) == ["metadata.json"]


def test_pattern_does_not_replace_a_capture_file(capsys, tmp_path):
    """Before: ``pattern --out DIR`` replaced DIR's capture.yaml (a hand-edited capture
    file) by its template, exit 0."""
    folder = tmp_path / "cap"
    status, _, _ = _run(capsys, "pattern", "--width", 12, "--height", 12, "--out", folder)
    assert status == 0
    (folder / "capture.yaml").write_text("images: [mine.tif]\n")
    _refused(
        capsys, "pattern", "--width", 12, "--height", 12, "--out", folder, match="capture.yaml"
    )
    assert (folder / "capture.yaml").read_text() == "images: [mine.tif]\n"
    # A camera's white.png beside no capture.yaml is not a template's: kept too.
    (folder / "capture.yaml").unlink()
    (folder / "white.png").write_bytes(b"a camera's frame")
    _refused(capsys, "pattern", "--width", 12, "--height", 12, "--out", folder, match="black.png")
    assert (folder / "white.png").read_bytes() == b"a camera's frame"


def test_a_dark_channel_is_named_before_any_fit(capture, capsys, monkeypatch):
    """Before: R and G were fitted, then B (all 0) stopped the command with 'fit_decay:
    sigma_t is not identifiable: 0 usable pixels', naming no channel."""
    from lightfield_jax.inverse import capture_fit

    for f in [*sorted(capture.glob("shift_*.exr")), capture / "dark.exr"]:
        y = read_image(f).pixels[..., 0]
        write_exr(f, {"R": y, "G": 0.5 * y, "B": np.zeros_like(y)})

    def no_fit(*_args, **_kwargs):
        raise AssertionError("a channel was fitted before the dark one was refused")

    monkeypatch.setattr(capture_fit, "fit_one", no_fit)
    _refused(capsys, "fit", capture / "capture.yaml", match="channel B: no light")


@pytest.mark.parametrize(
    ("pattern", "match"),
    [
        ({"period": 8}, "pattern.period: 8 contradicts the images, whose stripes repeat every 6"),
        ({"period": 3, "lit": 1}, "pattern.period: 3 contradicts"),
        ({"direction_deg": -30.0}, "pattern.direction_deg: -30 contradicts the images"),
    ],
)
def test_a_pattern_the_images_contradict_is_refused(capture, capsys, pattern, match):
    """Before: a wrong period (phases given) or direction passed inspect; the fit ran for
    minutes (3.5 for the direction) and ended 'not converged' without naming it."""
    data = yaml.safe_load((capture / "capture.yaml").read_text())
    spec = {**data["pattern"], **pattern}
    spec["phases"] = [p % spec["period"] for p in range(6)]
    _edit(capture, pattern=spec)
    _refused(capsys, "inspect", capture / "capture.yaml", match=match)


def test_a_wrong_period_with_phases_auto_is_one_line(capture, capsys):
    """Before: with ``phases: auto`` the detector's "low confidence 0.00" warning (its
    phases measured for the wrong period) was printed before the period's refusal: two
    lines on stderr. The capture's warnings now wait for the pattern's checks."""
    data = yaml.safe_load((capture / "capture.yaml").read_text())
    _edit(capture, pattern={**data["pattern"], "period": 8, "phases": "auto"})
    _refused(capsys, "inspect", capture / "capture.yaml", match="pattern.period: 8 contradicts")


@pytest.mark.parametrize("lit", [2, 4])
def test_a_lit_width_the_images_seem_to_contradict_is_noted(capture, lit):
    """Before: ``lit: 2`` for stripes lit 3 rows of 6 passed inspect without a word and
    the fit ran for many minutes (it looked hung). The measured width moves by a row or
    two with blur and the stripes' offset from the pixel grid, so it is a note naming
    pattern.lit, not a refusal."""
    data = yaml.safe_load((capture / "capture.yaml").read_text())
    _edit(capture, pattern={**data["pattern"], "lit": lit})
    notes = lfj.load_capture(capture / "capture.yaml").notes
    assert any(f"pattern.lit: {lit}, but the stripes look lit 3.0" in n for n in notes), notes
    _edit(capture, pattern={**data["pattern"], "lit": 3})
    notes = lfj.load_capture(capture / "capture.yaml").notes
    assert not any("pattern.lit" in n for n in notes), notes


def _transform_images(folder: Path, how) -> None:
    for f in [*sorted(folder.glob("shift_*.exr")), folder / "dark.exr"]:
        if f.exists():
            y = read_image(f).pixels[..., 0]
            write_exr(f, {"Y": np.ascontiguousarray(how(y))})


@pytest.mark.parametrize(
    ("how", "pattern", "match"),
    [
        (np.rot90, {}, "pattern.entry: left contradicts the images, whose light enters "),
        (np.rot90, {"entry": "right", "direction_deg": 180.0}, "through the bottom wall"),
        (np.fliplr, {}, "pattern.entry: left contradicts the images, whose light enters "),
        (None, {"direction_deg": 4.0}, "pattern.direction_deg: 4 contradicts the images"),
        (None, {"direction_deg": -3.0}, "whose stripes run at 0.0"),
    ],
)
def test_a_misdeclared_entry_or_direction_is_refused(capture, capsys, how, pattern, match):
    """Before: a camera rotated 90 deg (light from the bottom, the file says left) or
    stripes tilted 4 deg (the file says 0) passed inspect, and the fit ran 20-30 s to end
    'not identifiable'; light from the right with the file saying left passed inspect
    (only the fit refused it). The declared wall and heading are now compared with the
    detector's, and ``auto`` is suggested."""
    if how is not None:
        _transform_images(capture, how)
    data = yaml.safe_load((capture / "capture.yaml").read_text())
    _edit(capture, pattern={**data["pattern"], "entry": "left", "direction_deg": 0.0, **pattern})
    line = _refused(capsys, "inspect", capture / "capture.yaml", match=match)
    assert "auto" in line


def test_a_declared_geometry_the_images_agree_with_is_kept(capture, capsys):
    """The measured wall, and a heading within the detector's tolerance (0.5 deg), pass;
    a rotated capture declared ``auto`` passes too."""
    data = yaml.safe_load((capture / "capture.yaml").read_text())
    _edit(capture, pattern={**data["pattern"], "entry": "left", "direction_deg": 1.0})
    assert lfj.load_capture(capture / "capture.yaml").pattern.direction_deg == 1.0
    _transform_images(capture, np.rot90)
    _edit(capture, pattern={**data["pattern"], "entry": "bottom", "direction_deg": 270.0})
    assert lfj.load_capture(capture / "capture.yaml").pattern.entry == "bottom"
    _edit(capture, pattern={**data["pattern"], "entry": "auto", "direction_deg": "auto"})
    found = lfj.load_capture(capture / "capture.yaml").pattern
    assert found.entry == "bottom" and abs(found.direction_deg - 270.0) < 0.1


def test_unwritable_output_locations_are_refused_before_the_work(capture, capsys, tmp_path):
    # /proc refuses new files even to the superuser (a read-only folder does not).
    line = _refused(
        capsys,
        "fit",
        capture / "capture.yaml",
        "--out",
        "/proc/results.json",
        match="/proc/results.json: cannot write in /proc",
    )
    assert ".tmp-" not in line
    blocker = tmp_path / "file"
    blocker.write_text("x")
    _refused(
        capsys,
        "simulate",
        capture.parent / "missing.yaml",
        "--out",
        blocker / "sub",
        match="sub: cannot be written (Not a directory)",
    )
    _refused(capsys, "pattern", "--width", 12, "--height", 12, "--out", "/proc/pat", match="/proc")


def test_unsupported_plot_format_is_refused_before_the_fit(capture, capsys, tmp_path):
    results = tmp_path / "results.json"
    results.write_text('{"kept": true}')
    t0 = time.perf_counter()
    _refused(
        capsys,
        "fit",
        capture / "capture.yaml",
        "--out",
        results,
        "--plot",
        tmp_path / "fig.exr",
        match="fig.exr: a figure needs a file extension matplotlib writes",
    )
    assert time.perf_counter() - t0 < 10  # refused before the fit (which takes longer)
    assert json.loads(results.read_text()) == {"kept": True}
    _refused(
        capsys, "inspect", capture / "capture.yaml", "--plot", tmp_path / "fig", match="no ext"
    )


def test_a_pgf_figure_without_its_tex_program_is_refused_before_the_fit(
    capture, capsys, tmp_path, monkeypatch
):
    """Before: ``fit --plot fit.pgf`` (or inspect's) on a machine without xelatex ran the
    whole fit, then ended in matplotlib's traceback "'xelatex' not found"."""
    monkeypatch.setenv("PATH", str(tmp_path))  # no TeX program on it
    results = tmp_path / "results.json"
    t0 = time.perf_counter()
    for command in ("fit", "inspect"):
        line = _refused(
            capsys,
            command,
            capture / "capture.yaml",
            "--plot",
            tmp_path / "fig.pgf",
            *(("--out", results) if command == "fit" else ()),
            match="fig.pgf: matplotlib writes .pgf figures through xelatex, which is not installed",
        )
        assert "pdf" in line and "pgf," not in line
    assert time.perf_counter() - t0 < 10  # refused before the fit (which takes longer)
    assert not results.exists() and not (tmp_path / "fig.pgf").exists()


# --------------------------------------------------- two-step caveat, staged writes


@pytest.mark.slow
def test_a_two_step_fit_says_its_bias_on_screen_and_in_results(capture, capsys, tmp_path):
    out, fig = tmp_path / "r.json", tmp_path / "r.png"
    status, stdout, err = _run(
        capsys, "fit", capture / "capture.yaml", "--method", "grid", "--out", out, "--plot", fig
    )
    assert status == 0, err
    result = json.loads(out.read_text())
    assert "separation bias" in result["caveat"] and "joint" in result["caveat"]
    assert result["uncertainty_kind"].startswith("statistical only")
    assert "note: the two-step methods (grid, gradient) carry the separation bias" in stdout
    assert fig.stat().st_size > 0


def test_a_failure_while_plotting_replaces_no_output(capture, capsys, tmp_path, monkeypatch):
    """Figures and results are staged and published together: a command that fails
    in its last step leaves the outputs of an earlier run as they were."""
    out, fig = tmp_path / "i.json", tmp_path / "i.png"
    status, _, err = _run(capsys, "inspect", capture / "capture.yaml", "--json", out, "--plot", fig)
    assert status == 0, err
    before = {p: p.read_bytes() for p in (out, fig)}

    import lightfield_jax.viz as viz

    def broken(*args, **kwargs):
        raise ValueError("plotting failed")

    monkeypatch.setattr(viz, "plot_inspect", broken)
    fig.unlink()
    line = _refused(
        capsys, "inspect", capture / "capture.yaml", "--json", out, "--plot", fig, match="plotting"
    )
    assert line.endswith("plotting failed")
    assert out.read_bytes() == before[out] and not fig.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap", "i.json"]  # no temporaries


def test_library_failures_are_translated_and_name_the_capture(capture, capsys, monkeypatch):
    import equinox as eqx

    import lightfield_jax.inverse.capture_fit as capture_fit_module

    def singular(*args, **kwargs):
        raise eqx.EquinoxRuntimeError(
            "A linear solver received non-finite input. This "
            "means that you have a bug upstream of Lineax"
        )

    monkeypatch.setattr(capture_fit_module, "fit_capture", singular)
    line = _refused(
        capsys, "fit", capture / "capture.yaml", match="the solve met a singular or non-finite"
    )
    assert str(capture / "capture.yaml") in line and "Lineax" not in line

    def decay(*args, **kwargs):
        raise ValueError("decay fit: no usable points along the beam")

    monkeypatch.setattr(capture_fit_module, "fit_capture", decay)
    line = _refused(capsys, "fit", capture / "capture.yaml", match="decay fit: no usable")
    assert line.startswith(f"lightfield-jax: error: {capture / 'capture.yaml'}: ")


# ------------------------------------------------------------------ 3, 8. YAML bombs

BOMB = """\
a: &a [x, x, x, x, x, x, x, x, x]
b: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a]
c: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b]
d: &d [*c, *c, *c, *c, *c, *c, *c, *c, *c]
e: &e [*d, *d, *d, *d, *d, *d, *d, *d, *d]
f: &f [*e, *e, *e, *e, *e, *e, *e, *e, *e]
g: &g [*f, *f, *f, *f, *f, *f, *f, *f, *f]
h: &h [*g, *g, *g, *g, *g, *g, *g, *g, *g]
"""


@pytest.mark.parametrize("key", ["channel", "medium_roi", "pattern", "truth"])
def test_alias_bombs_in_a_capture_are_refused_with_a_short_message(capture, capsys, key):
    path = capture / "bomb.yaml"
    base = yaml.safe_load((capture / "capture.yaml").read_text())
    base.pop(key, None)
    path.write_text(BOMB + yaml.safe_dump(base) + f"{key}: *h\n")
    t0 = time.perf_counter()
    line = _refused(capsys, "fit", path, match="aliases expand to more than")
    assert time.perf_counter() - t0 < 5 and len(line) < 400


@pytest.mark.parametrize("key", ["grid", "bounces"])
def test_alias_bombs_in_a_config_are_refused(tmp_path, capsys, key):
    config = yaml.safe_load(SIMULATE)
    config.pop(key, None)
    path = tmp_path / "sim.yaml"
    path.write_text(BOMB + yaml.safe_dump(config) + f"{key}: *h\n")
    line = _refused(capsys, "simulate", path, "--out", tmp_path / "o", match="aliases expand")
    assert len(line) < 400 and not (tmp_path / "o").exists()


def test_a_large_rejected_value_is_printed_bounded(tmp_path, capsys):
    config = yaml.safe_load(SIMULATE)
    config["bounces"] = "x" * 100_000
    path = tmp_path / "sim.yaml"
    path.write_text(yaml.safe_dump(config))
    line = _refused(capsys, "simulate", path, "--out", tmp_path / "o", match="bounces")
    assert len(line) < 400


def test_recursive_aliases_and_deep_nesting_are_one_line(tmp_path, capsys):
    path = tmp_path / "sim.yaml"
    path.write_text("grid: &a [*a]\n")
    _refused(capsys, "simulate", path, "--out", tmp_path / "o", match="cycle")
    path.write_text("grid: " + "[" * 20000 + "]" * 20000 + "\n")
    _refused(capsys, "simulate", path, "--out", tmp_path / "o", match="nested too deeply")


@pytest.mark.parametrize("key", ["[a, b]", "{a: 1}"])
def test_a_complex_yaml_key_is_one_line(capture, capsys, key):
    """Before: '? [a, b]' in a capture file was a TypeError traceback (unhashable)."""
    path = capture / "capture.yaml"
    path.write_text(path.read_text() + f"? {key}\n: 2\n")
    _refused(capsys, "inspect", path, match="invalid YAML: a key must be a string, got a")


def test_huge_periods_are_refused(capture, capsys, tmp_path):
    pattern = yaml.safe_load((capture / "capture.yaml").read_text())["pattern"]
    _edit(capture, pattern={**pattern, "period": 10**21})
    _refused(capsys, "inspect", capture / "capture.yaml", match="pattern.period: 10000000")
    config = yaml.safe_load(SIMULATE)
    config["illumination"]["period"] = 10**21
    path = tmp_path / "sim.yaml"
    path.write_text(yaml.safe_dump(config))
    _refused(capsys, "simulate", path, "--out", tmp_path / "o", match="illumination.period")
    _refused(
        capsys,
        *("pattern", "--width", 64, "--height", 64, "--period", 10**21, "--out", tmp_path / "p"),
        match="pattern.width: must be an integer >= the period",
    )


def test_npy_header_claiming_terabytes_is_refused(capture, capsys):
    header = {"descr": "<f4", "fortran_order": False, "shape": (P, 10**6, 10**6)}
    with open(capture / "stack.npy", "wb") as f:
        np.lib.format.write_array_header_1_0(f, header)
        f.write(b"\0" * 64)
    _edit(capture, images="stack.npy", dark_frame=None)
    (capture / "capture.yaml").write_text(
        (capture / "capture.yaml").read_text().replace("dark_frame: null\n", "")
    )
    _refused(capsys, "inspect", capture / "capture.yaml", match="truncated or corrupt")


def test_an_npy_image_without_pixels_is_named_as_empty(capture, capsys):
    """Before: an image ``.npy`` of shape (0, 32) was 'every pixel value is NaN or Inf
    (a corrupt file?)', and a dark frame of shape (24, 0) '0x24 pixels' against the
    images' size."""
    images = [f"shift_{i:02d}.npy" for i in range(P)]
    for i, name in enumerate(images):
        np.save(capture / name, read_image(capture / f"shift_{i:02d}.exr").pixels[..., 0])
    np.save(capture / images[2], np.zeros((0, W), np.float32))
    _edit(capture, images=images)
    _refused(
        capsys,
        *("inspect", capture / "capture.yaml"),
        match=f"images[2]: {capture / images[2]}: expected a (height, width) or (height, width, "
        f"channels) array, got shape (0, {W}) (no pixels)",
    )
    np.save(capture / images[2], read_image(capture / "shift_02.exr").pixels[..., 0])
    np.save(capture / "dark.npy", np.zeros((H, 0), np.float32))
    _edit(capture, dark_frame="dark.npy")
    _refused(capsys, "inspect", capture / "capture.yaml", match="dark_frame: ")
    _refused(capsys, "inspect", capture / "capture.yaml", match="(no pixels)")


# --------------------------------------------------------------------- 5. memory


def test_renders_too_large_for_memory_are_refused_with_the_estimate(tmp_path, capsys):
    config = yaml.safe_load(SIMULATE)
    config["grid"] = {"width": 3000, "height": 3000, "n_theta": 512}
    path = tmp_path / "big.yaml"
    path.write_text(yaml.safe_dump(config))
    line = _refused(capsys, "simulate", path, "--out", tmp_path / "o", match="needs about")
    assert "iB of memory, more than the" in line and "available memory" in line
    # Many bounces: every image of each is kept (6 x 10000 images of 1024x768).
    config["grid"] = {"width": 1024, "height": 768, "n_theta": 16}
    config["bounces"] = 10000
    path.write_text(yaml.safe_dump(config))
    _refused(capsys, "simulate", path, "--out", tmp_path / "o", match="needs about")
    config["bounces"] = 100000  # past the march's limit: refused by the config check
    path.write_text(yaml.safe_dump(config))
    _refused(capsys, "simulate", path, "--out", tmp_path / "o", match="at most 10000 bounces")
    # A normal render passes; --max-memory lowers (or raises) the limit.
    path.write_text(SIMULATE)
    line = _refused(
        capsys, "simulate", path, "--out", tmp_path / "o", "--max-memory", "1M", match="needs"
    )
    assert "of the --max-memory" in line
    assert not (tmp_path / "o").exists()


def test_bench_sizes_too_large_for_memory_are_refused(tmp_path, capsys):
    _refused(
        capsys,
        *("bench", "--sizes", "3000x3000x512", "--out", tmp_path / "b.json"),
        match="bench --sizes 3000x3000x512 needs about",
    )
    assert not (tmp_path / "b.json").exists()


@pytest.mark.parametrize("flag", ["--fits", "--no-fits"])
def test_bench_repeats_beyond_any_use_are_refused(tmp_path, capsys, flag):
    """Before: ``bench --repeats 1000000000`` was taken and timed the renders (with
    ``--fits``: fresh fit processes) until killed; now refused by argparse at once."""
    status, out, err = _run(
        capsys, "bench", "--repeats", "1000000000", flag, "--out", tmp_path / "b.json"
    )
    assert status == 2 and len(err.splitlines()) == 1, err
    assert "argument --repeats: must be at most 1000, got '1000000000'" in err
    assert not (tmp_path / "b.json").exists()


def _png_header(path: Path, width: int, height: int) -> None:
    """A PNG whose header declares width x height RGB 8-bit, followed by a 64 MiB data
    chunk that is a hole in a sparse file (no disk used)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = struct.pack(">I", zlib.crc32(kind + data))
        return struct.pack(">I", len(data)) + kind + data + crc

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    size = 64 << 20
    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + struct.pack(">I", size) + b"IDAT")
        f.truncate(f.tell() + size + 4)


def test_image_headers_declaring_huge_images_are_refused(capture, capsys):
    """Sizes come from the headers, before any pixel is read (under a fixed limit)."""
    _png_header(capture / "huge.png", 30000, 30000)
    _edit(capture, images=["huge.png"] * P, dark_frame=None)
    text = (capture / "capture.yaml").read_text().replace("dark_frame: null\n", "")
    (capture / "capture.yaml").write_text(text)
    line = _refused(
        capsys, "inspect", capture / "capture.yaml", "--max-memory", "8G", match="needs about"
    )
    assert "images (6 file(s), 16200000000 samples)" in line
    header = {"descr": "<f4", "fortran_order": False, "shape": (P, 30000, 30000)}
    with open(capture / "stack.npy", "wb") as f:
        np.lib.format.write_array_header_1_0(f, header)
        f.truncate(f.tell() + 4 * P * 30000 * 30000)
    _edit(capture, images="stack.npy")
    _refused(capsys, "inspect", capture / "capture.yaml", "--max-memory", "8G", match="needs about")
    # The capture's real images under a tiny limit: refused from their headers too.
    _edit(capture, images=[f"shift_{i:02d}.exr" for i in range(P)])
    line = _refused(
        capsys, "inspect", capture / "capture.yaml", "--max-memory", "10K", match="needs about"
    )
    assert f"images (6 file(s), {P * H * W} samples)" in line


def test_patterns_too_large_for_memory_are_refused(tmp_path, capsys):
    _refused(
        capsys,
        *("pattern", "--width", 100000, "--height", 100000, "--out", tmp_path / "p"),
        match="pattern: 8 images of 100000x100000 needs about",
    )
    assert not (tmp_path / "p").exists()


# ----------------------------------------------------------- 6, 7. impossible captures


def test_phases_outside_the_period_are_refused(capture, capsys):
    pattern = yaml.safe_load((capture / "capture.yaml").read_text())["pattern"]
    _edit(capture, pattern={**pattern, "phases": [0, -1, 2, 3, 4, 5]})
    _refused(capsys, "fit", capture / "capture.yaml", match="[-1] outside [0, period) = [0, 6)")
    _edit(capture, pattern={**pattern, "phases": [0, 1, 2, 3, 4, 6]})
    _refused(capsys, "fit", capture / "capture.yaml", match="[6] outside [0, period)")


def test_more_images_than_the_period_without_phases_are_named(capture, capsys):
    """Before: 12 images and no pattern.phases was 'pattern.phases: each phase must lie
    in [0, period = 6), got 6', about phases the capture file does not give."""
    images = [f"shift_{i % P:02d}.exr" for i in range(2 * P)]
    path = _edit(capture, images=images)
    data = yaml.safe_load(path.read_text())
    del data["pattern"]["phases"]
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    line = _refused(capsys, "inspect", path, match="pattern.phases: not given, so the 12 images")
    assert "take the phases 0..11, beyond the period 6" in line and "phases: auto" in line


def test_phases_that_contradict_the_images_are_refused(capture, capsys):
    pattern = yaml.safe_load((capture / "capture.yaml").read_text())["pattern"]
    _edit(capture, pattern={**pattern, "phases": [2, 3, 4, 5, 0, 1]})
    line = _refused(capsys, "fit", capture / "capture.yaml", match="pattern.phases: [2, 3, 4")
    assert "stripes are at phases [0, 1, 2, 3, 4, 5]" in line
    _edit(capture, pattern={**pattern, "phases": [0, 1, 2, 3, 5, 4]})
    _refused(capsys, "inspect", capture / "capture.yaml", match="contradict the images")
    _edit(capture, pattern={**pattern, "phases": "auto"})
    status, out, err = _run(capsys, "inspect", capture / "capture.yaml")
    assert status == 0, err
    # Phases left to their default (0..P-1) that the images contradict: a note.
    from lightfield_jax.capture.loading import load_capture

    _edit(
        capture,
        pattern={k: v for k, v in pattern.items() if k != "phases"},
        images=[f"shift_{i:02d}.exr" for i in (1, 2, 3, 4, 5, 0)],
    )
    notes = load_capture(capture / "capture.yaml").notes
    assert any(
        "pattern.phases (absent: the default) [0, 1, 2, 3, 4, 5] contradict" in n for n in notes
    )


def test_a_white_frame_listed_as_a_stripe_image_is_refused(capture, capsys):
    stripes = [read_image(capture / f"shift_{i:02d}.exr").pixels[..., 0] for i in range(P)]
    write_exr(capture / "shift_04.exr", {"Y": np.mean(stripes, axis=0)})
    _refused(
        capsys, "fit", capture / "capture.yaml", match="shift_04.exr shows no stripes of period 6"
    )


def test_one_dropped_frame_of_one_value_is_refused(capture, capsys):
    """Before: a shift all 0 (a dropped frame) among lit ones was fitted as a shift: not
    converged (albedo at 1, chi2 569) without a word of the frame."""
    write_exr(capture / "shift_03.exr", {"Y": np.zeros((H, W))})
    for command in ("fit", "inspect"):
        _refused(
            capsys, command, capture / "capture.yaml",
            match="images: shift_03.exr: every pixel value is 0, unlike the other images",
        )  # fmt: skip


def test_images_without_light_are_refused(capture, capsys):
    shifts = [capture / f"shift_{i:02d}.exr" for i in range(P)]
    images = [read_image(f).pixels[..., 0] for f in shifts]
    dark = read_image(capture / "dark.exr").pixels[..., 0]
    write_exr(capture / "dark.exr", {"Y": dark + 2 * np.max(images)})
    for command in ("fit", "inspect"):
        _refused(capsys, command, capture / "capture.yaml", match="brighter than the images")
    _edit(capture, dark_frame=None)
    (capture / "capture.yaml").write_text(
        (capture / "capture.yaml").read_text().replace("dark_frame: null\n", "")
    )
    for f, image in zip(shifts, images, strict=True):
        write_exr(f, {"Y": -image})
    for command in ("fit", "inspect"):
        _refused(capsys, command, capture / "capture.yaml", match="every image value is negative")
    for f in shifts:
        write_exr(f, {"Y": np.zeros((H, W))})
    _refused(capsys, "inspect", capture / "capture.yaml", match="every pixel of every image is 0")


def test_inspect_warns_and_exits_1_on_a_capture_without_direct_light(tmp_path, capsys):
    from lightfield_jax.capture.write import write_capture_yaml
    from lightfield_jax.scene.illumination import Stripes

    names = [f"s{i}.exr" for i in range(P)]
    for name in names:
        write_exr(tmp_path / name, {"Y": np.full((H, W), 0.5)})
    write_capture_yaml(tmp_path / "capture.yaml", images=names, pattern=Stripes())
    status, out, err = _run(
        capsys, "inspect", tmp_path / "capture.yaml", "--json", tmp_path / "i.json"
    )
    assert status == 1
    assert "warning: [Y] no direct light at the entry wall" in out
    assert err.startswith("lightfield-jax: warning: ") and "no direct light" in err
    assert any(
        "no direct light" in w for w in json.loads((tmp_path / "i.json").read_text())["warnings"]
    )


def test_inspect_of_a_capture_clipped_at_its_entry_wall_measures_past_it(
    capture, capsys, monkeypatch
):
    """Before: every capture clipped near its entry wall (common: the wall is where the
    light is brightest) was called unusable, 'no direct light at the entry wall', exit
    1, while its fit converged. The wall's statistics now come from the nearest valid
    pixels, said so."""
    shifts = sorted(capture.glob("shift_*.exr"))
    images = [read_image(f).pixels[..., 0] for f in shifts]
    top = 0.3 * max(float(np.max(i)) for i in images)
    for f, image in zip(shifts, images, strict=True):
        write_exr(f, {"Y": np.minimum(image, top)})
    _edit(capture, saturation=float(top))
    status, out, _ = _run(capsys, "inspect", capture / "capture.yaml")
    assert status == 0, out
    assert "the wall's pixels are masked" in out and "no direct light" not in out
    # The fit masks those values one shift at a time; the capture's clip flags and
    # levels (after the dark frame) reach the joint fit's censoring check.
    import lightfield_jax.inverse.joint_fit.censoring as censoring

    seen, check = [], censoring.near_the_clip

    def spy(data, fitted, sigma, floor=None):
        seen.append((int(data.clipped.sum()), float(np.min(data.clip_level))))
        return check(data, fitted, sigma, floor)

    monkeypatch.setattr(censoring, "near_the_clip", spy)
    out = capture / "r.json"
    status, _, err = _run(capsys, "fit", capture / "capture.yaml", "--out", out)
    assert status == 0, err
    (clipped, level), *_ = seen
    assert clipped > 0 and 0.9 * top < level < top  # the top less the dark frame's 0.01
    assert abs(json.loads(out.read_text())["truth_error"]["sigma_t"]["sigmas"]) < 3


# ---------------------------------------------------------- 9. non-regular inputs


def test_fifos_in_place_of_inputs_are_refused_without_hanging(capture, tmp_path):
    (capture / "shift_02.exr").unlink()
    os.mkfifo(capture / "shift_02.exr")
    fifo_yaml = tmp_path / "fifo.yaml"
    os.mkfifo(fifo_yaml)
    fifo_json = tmp_path / "fifo.json"  # render read its results file before: it hung
    os.mkfifo(fifo_json)
    env = {**os.environ, "PYTHONPATH": str(ROOT), XLA_CACHE_ENV: "off"}
    for argv, match in (
        (["inspect", str(capture / "capture.yaml")], "shift_02.exr: is not a regular file"),
        (["inspect", str(fifo_yaml)], "fifo.yaml: is not a regular file"),
        (["simulate", str(fifo_yaml), "--out", str(tmp_path / "o")], "not a regular file"),
        (["render", str(fifo_json), "--out", str(tmp_path / "r")], "fifo.json: is not a regular"),
    ):
        done = subprocess.run(
            [sys.executable, "-m", "lightfield_jax", *argv],
            capture_output=True,
            text=True,
            timeout=60,
            env=env,
        )
        assert done.returncode == 2 and match in done.stderr, done.stderr
        assert len(done.stderr.splitlines()) == 1


# ------------------------------------------------------------------ 10. smaller


def test_big_endian_npy_images_are_read(tmp_path):
    a = np.arange(12, dtype=">f4").reshape(3, 4)
    np.save(tmp_path / "be.npy", a)
    image = read_image(tmp_path / "be.npy")
    assert image.pixels.dtype == np.float32
    np.testing.assert_array_equal(image.pixels[..., 0], a.astype(np.float32))
    np.save(tmp_path / "be16.npy", np.arange(12, dtype=">u2").reshape(3, 4))
    assert read_image(tmp_path / "be16.npy").pixels[1, 1, 0] == pytest.approx(5 / 65535)


def _write_pages(path: Path, pages: list[np.ndarray], fmt: str) -> Path:
    """A file of one subimage per (height, width, channels) page: the pages of a TIFF,
    the parts of an EXR, written with OpenImageIO."""
    import OpenImageIO as oiio

    specs = [oiio.ImageSpec(a.shape[1], a.shape[0], a.shape[2], fmt) for a in pages]
    out = oiio.ImageOutput.create(str(path))
    assert out is not None and out.open(str(path), specs), oiio.geterror()
    for i, a in enumerate(pages):
        if i:
            assert out.open(str(path), specs[i], "AppendSubimage"), out.geterror()
        assert out.write_image(np.ascontiguousarray(a, dtype=np.float32)), out.geterror()
    assert out.close()
    return path


def test_signed_and_32_bit_integer_images_are_refused_alike_in_tiff_and_npy(capture, capsys):
    """Before: an int16 TIFF (counts from a scientific camera) was read scaled by 32767,
    an int32 or uint32 one by its full range, while a .npy of those types was refused."""
    import OpenImageIO as oiio

    for dtype in (np.int16, np.int32, np.uint32):
        name = np.dtype(dtype).name
        counts = np.full((H, W, 1), 1000, dtype)
        tiff = capture / f"{name}.tif"
        out = oiio.ImageOutput.create(str(tiff))
        spec = oiio.ImageSpec(W, H, 1, getattr(oiio, name.upper()))
        assert out.open(str(tiff), spec), out.geterror()
        assert out.write_image(counts) and out.close(), out.geterror()
        npy = capture / f"{name}.npy"
        np.save(npy, counts[..., 0])
        kind = "unsigned" if name.startswith("u") else "signed"
        words = f"{name} ({kind} {counts.itemsize * 8}-bit integers): integer samples are read"
        for path, what in ((tiff, "sample type"), (npy, "array dtype")):
            with pytest.raises(lfj.CaptureError, match=r"\.(tif|npy): unsupported") as e:
                read_image(path)
            assert str(e.value).startswith(f"{path}: unsupported {what} {words}"), e.value
            assert "save the counts as uint16 (0..65535) or as float32" in str(e.value)
    data = yaml.safe_load((capture / "capture.yaml").read_text())
    path = _edit(capture, images=["int16.tif", *data["images"][1:]])
    line = _refused(capsys, "inspect", path, match="images[0]: ")
    assert "int16.tif: unsupported sample type int16 (signed 16-bit integers)" in line


def test_multi_page_tiffs_and_multi_part_exrs_are_refused(capture, capsys, tmp_path):
    """Before: a burst saved as the pages of one TIFF (or the parts of one EXR) was read
    as its first page, without a word, and fitted from that one frame."""
    rng = np.random.default_rng(0)
    frames = [rng.uniform(size=(4, 5, 1)) for _ in range(3)]
    tiff = _write_pages(tmp_path / "burst.tif", frames[:2], "uint16")
    exr = _write_pages(tmp_path / "burst.exr", frames, "float")
    with pytest.raises(lfj.CaptureError, match=r"burst\.tif: holds 2 pages \(a multi-page TIFF\)"):
        read_image(tiff)
    with pytest.raises(lfj.CaptureError, match=r"burst\.exr: holds 3 parts \(a multi-part EXR\)"):
        read_image(exr)
    many = _write_pages(tmp_path / "many.tif", [np.zeros((1, 1, 1))] * 101, "uint8")
    with pytest.raises(lfj.CaptureError, match=r"many\.tif: holds more than 100 pages"):
        read_image(many)
    # One page or part reads as before.
    for name, fmt in (("one.tif", "uint16"), ("one.exr", "float")):
        image = read_image(_write_pages(tmp_path / name, frames[:1], fmt))
        np.testing.assert_allclose(image.pixels, frames[0], atol=1e-4)
    # A capture naming a burst file is refused, naming its key, before any fit.
    data = yaml.safe_load((capture / "capture.yaml").read_text())
    shifts = [read_image(capture / f).pixels for f in data["images"]]
    _write_pages(capture / "burst.exr", shifts[:2], "float")
    _edit(capture, images=["burst.exr"] + data["images"][1:])
    with pytest.raises(lfj.CaptureError, match=r"images\[0\]: .*burst\.exr: holds 2 parts"):
        lfj.load_capture(capture / "capture.yaml")
    _refused(capsys, "fit", capture / "capture.yaml", match="burst.exr: holds 2 parts")


def test_the_mip_levels_of_one_tiff_are_not_pages(tmp_path):
    """A tiled, MIP-mapped TIFF (one image at several resolutions) reads its full level."""
    import OpenImageIO as oiio

    pixels = np.random.default_rng(1).uniform(size=(16, 16, 1)).astype(np.float32)
    buf = oiio.ImageBuf(oiio.ImageSpec(16, 16, 1, "float"))
    assert buf.set_pixels(oiio.ROI(0, 16, 0, 16, 0, 1, 0, 1), pixels)
    path = tmp_path / "mip.tif"
    assert oiio.ImageBufAlgo.make_texture(oiio.MakeTxTexture, buf, str(path)), oiio.geterror()
    inp = oiio.ImageInput.open(str(path))
    assert inp.seek_subimage(0, 1)  # it has MIP levels
    inp.close()
    np.testing.assert_array_equal(read_image(path).pixels, pixels)


def test_a_constant_alpha_is_dropped_from_any_channel_count(capture, capsys):
    """Before: alpha was dropped only from 2 or 4 channels; a 5-channel EXR (R, G, B, A,
    Z) kept its constant alpha as a channel to fit."""
    data = yaml.safe_load((capture / "capture.yaml").read_text())
    for f in [*data["images"], data["dark_frame"]]:
        y = read_image(capture / f).pixels[..., 0]
        names = ("R", "G", "B", "A", "Z")
        # Channels that differ (equal ones would load as one grey channel Y).
        scale = dict(zip(names, (1.0, 0.9, 0.8, 0.0, 0.7), strict=True))
        write_exr(capture / f, {n: np.ones_like(y) if n == "A" else scale[n] * y for n in names})
    c = lfj.load_capture(capture / "capture.yaml")
    assert c.channel_names == ("R", "G", "B", "Z")
    assert "dropped the constant alpha channel A of the 5-channel images" in " ".join(c.notes)
    y = read_image(capture / data["images"][0]).pixels[..., 0]
    write_exr(capture / data["images"][0], {n: y for n in names})  # alpha varies
    with pytest.raises(lfj.CaptureError, match=r"shift_00\.exr has a varying alpha channel"):
        lfj.load_capture(capture / "capture.yaml")


def test_a_stack_saved_as_one_image_file_is_named_as_a_stack(capture, capsys):
    """Before: a .npy of shape (2, 24, 32) listed as one image was a 24x32 image with 32
    channels, refused as having 'a varying alpha channel (R, G, B, A, channel4, ...)'."""
    data = yaml.safe_load((capture / "capture.yaml").read_text())
    frames = [read_image(capture / f).pixels[..., 0] for f in data["images"]]
    pairs = []
    for i in range(0, len(frames), 2):
        np.save(capture / f"pair_{i}.npy", np.stack(frames[i : i + 2]))
        pairs.append(f"pair_{i}.npy")
    path = _edit(capture, images=pairs)
    line = _refused(capsys, "inspect", path, match="images[0]: ")
    assert f"pair_0.npy: shape (2, {H}, {W}) looks like a stack of 2 images ({H} x {W}," in line
    assert "images: pair_0.npy" in line and "alpha" not in line
    # Four channels or fewer are still one image.
    np.save(capture / "rgb.npy", np.repeat(frames[0][..., None], 3, axis=-1))
    assert read_image(capture / "rgb.npy").channel_names == ("R", "G", "B")
    # A band chosen from a multispectral .npy (six bands) is read: no stack is meant.
    bands = np.stack([frames[0] * (b + 1) for b in range(6)], axis=-1)
    np.save(capture / "bands.npy", bands)
    band = read_image(capture / "bands.npy", channel=4)
    assert band.pixels.shape == (H, W, 1) and np.allclose(band.pixels[..., 0], bands[..., 4])


def test_double_values_beyond_float32_are_one_line_naming_the_file(capture, capsys):
    """Before: five lines of numpy overflow warnings, then 'separate.images: no pixel is
    finite ... nothing to separate' for a float64 .npy stack scaled by 1e300."""
    data = yaml.safe_load((capture / "capture.yaml").read_text())
    stack = np.stack([read_image(capture / f).pixels.astype(np.float64) for f in data["images"]])
    stack[3, 5, 5] = -1e300
    np.save(capture / "stack.npy", stack)
    _edit(capture, images="stack.npy")
    _refused(
        capsys,
        "inspect",
        capture / "capture.yaml",
        match="images: stack.npy: 1 value(s) beyond float32's range (up to 1e+300",
    )
    stack[3, 5, 5] = 0.5
    np.save(capture / "stack.npy", stack)
    np.save(capture / "dark.npy", np.full((H, W), 1e300))
    _edit(capture, dark_frame="dark.npy")
    _refused(capsys, "inspect", capture / "capture.yaml", match="dark_frame: dark.npy: 768 value")


# ------------------------------------------------------------------ 4. signals


def _cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@pytest.mark.parametrize(
    ("signum", "status"), [(signal.SIGINT, 130), (signal.SIGTERM, 143), (signal.SIGHUP, 129)]
)
def test_a_signal_stops_a_fit_at_once_and_leaves_no_output(simulated, tmp_path, signum, status):
    """The fit is signalled after 6 s of CPU (imported, compiling or solving: XLA at
    work, which Python's own handling waits for) and must end within 3 s."""
    out, fig = tmp_path / "r.json", tmp_path / "r.png"
    env = {**os.environ, "PYTHONPATH": str(ROOT), XLA_CACHE_ENV: "off"}
    argv = ["fit", str(simulated / "capture.yaml"), "--out", str(out), "--plot", str(fig)]
    child = subprocess.Popen(
        [sys.executable, "-m", "lightfield_jax", *argv],
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        # As from a terminal, whatever this test runs under (nohup ignores SIGHUP).
        preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_DFL),
    )
    try:
        while _cpu_seconds(child.pid) < 6.0:
            assert child.poll() is None, "the fit ended before it was signalled"
            time.sleep(0.05)
        sent = time.perf_counter()
        child.send_signal(signum)
        code = child.wait(timeout=30)
        elapsed = time.perf_counter() - sent
        message = child.stderr.read()
    finally:
        child.kill()
        child.wait()
        child.stderr.close()
    assert code == status and elapsed < 3.0, (code, elapsed)
    assert "interrupted" in message
    assert list(tmp_path.iterdir()) == []  # no output, no temporary


def test_a_fit_past_its_time_limit_stops_at_once_and_leaves_no_output(simulated, tmp_path):
    """``fit --time-limit``: a fit still compiling or solving when the limit passes ends
    within moments, exit 124, one line naming the limit and the stage, nothing written."""
    out, fig = tmp_path / "r.json", tmp_path / "r.png"
    env = {**os.environ, "PYTHONPATH": str(ROOT), XLA_CACHE_ENV: "off"}
    argv = ["fit", str(simulated / "capture.yaml"), "--out", str(out), "--plot", str(fig)]
    done = subprocess.run(
        [sys.executable, "-m", "lightfield_jax", *argv, "--time-limit", "1.5", "-q"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 124, done.stderr
    assert len(lines) == 1 and "the fit ran past its time limit of 1.5 s" in lines[0], lines
    assert lines[0].endswith(": stopped, nothing written")
    assert list(tmp_path.iterdir()) == []  # no output, no temporary
    for bad in ("0", "soon"):
        refused = subprocess.run(
            [sys.executable, "-m", "lightfield_jax", *argv, "--time-limit", bad],
            capture_output=True,
            text=True,
            env=env,
            timeout=120,
        )
        assert refused.returncode == 2 and "--time-limit" in refused.stderr, refused.stderr
        assert "must be a positive number of seconds" in refused.stderr


def test_a_fit_whose_primal_renders_need_more_than_the_limit_is_refused(capture, capsys):
    """The estimate covers the correction's and error term's renders (larger than the
    solve's fields): a limit between the two refuses the fit before it starts."""
    import lightfield_jax as lfj
    from lightfield_jax.runtime import memory
    from lightfield_jax.runtime.memory import FIT_N_THETA, RENDER_CELLS_PER_PIXEL

    loaded = lfj.load_capture(capture / "capture.yaml")
    h, w = loaded.shape
    options = lfj.FitOptions()
    samples, n = loaded.images.size, loaded.n_images
    solve = memory.fit_bytes(samples, n, min(h * w * FIT_N_THETA, options.model.max_cells))
    renders = memory.correction_bytes(
        samples, n, min(h * w * RENDER_CELLS_PER_PIXEL, 2 * options.model.max_render_cells)
    )
    assert renders > solve
    limit = str((solve + renders) // 2)
    line = _refused(capsys, "fit", capture / "capture.yaml", "--max-memory", limit, match="the fit")
    assert "needs about" in line


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
        ({"start_grid": 2}, "fit: start_grid: must be 0 (no search) or at least 3, got 2"),
        ({"tolerance": 0.0}, "fit: tolerance: must lie in (0, 1), got 0.0"),
        ({"crop_fraction": 5.0}, "fit: crop_fraction: must lie in [0, 1)"),
        ({"rtol": -1.0}, "fit: rtol: must lie in [0, 0.01] or be None, got -1.0"),
        # Looser tolerances stopped the solver at its start: the scan's start point was
        # reported as a converged answer, sigma_t 38 sigma off.
        ({"atol": 0.1}, "fit: atol: must lie in [0, 0.01] or be None, got 0.1"),
        ({"bounces": 10**9}, "fit: bounces: at most 10000 bounces are marched"),
        ({"max_chi2": 0.0}, "fit: max_chi2: must be > 0, got 0.0"),
        # Before: a grid of a billion fits ran until killed; max_steps 10**12 ended after
        # compiling in "a value in the input is too large (An overflow ...)".
        ({"g_grid": 10**9}, "fit: g_grid: must be an integer in [3, 100000], got 1000000000"),
        ({"start_grid": 10**9}, "fit: start_grid: must be an integer <= 100000"),
        ({"max_steps": 10**12}, "fit: max_steps: must be an integer <= 1e+09"),
        ({"tail_max_steps": 10**12}, "fit: tail_max_steps: must be an integer <= 1e+09"),
        (
            {"bounces": 20, "tail": "gmres"},
            "fit: bounces: 20 marches exactly that many bounces, but tail: gmres keeps "
            "tail_bounces",
        ),
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
        # Before: accepted, then a deep TypeError at fit time, or the process aborted
        # inside XLA (a static extent overflowing int64).
        {"g_grid": 3.5},
        {"max_basins": "x"},
        {"basin_tolerance": "x"},
        {"tail_bounces": 10**9},
        {"start": 0.03},
        {"start": (float("inf"), 0.4)},
    ):
        with pytest.raises(ValueError, match=next(iter(bad))):
            FitOptions(**bad)


@pytest.mark.parametrize(
    ("fit", "match"),
    [
        # past the θ bins a grid takes (the direction tables grow as n_theta²)
        ({"n_theta": 2**30}, "n_theta: must be at most 4096 direction bins"),
        ({"n_theta": 2**16}, "n_theta: must be at most 4096 direction bins"),
        ({"refine": 8, "n_theta": 4096}, "the fit needs about"),
        # before: an out-of-memory traceback after the scan; now past the bounce limit
        ({"bounces": 100000}, "fit: bounces: at most 10000 bounces"),
        ({"max_bounces": 10**7, "tail": None}, "fit: max_bounces: at most 10000 bounces"),
        ({"bounces": 10000, "tail": None}, "the fit needs about"),
    ],
)
def test_fixed_model_sizes_count_in_the_fits_memory_estimate(capture, capsys, tmp_path, fit, match):
    """θ bins and a refinement the capture fixes are not lowered to max_cells: before,
    the estimate ignored them and the fit ran out of memory (or was killed)."""
    _edit(capture, fit=fit)
    out = tmp_path / "r.json"
    argv = ("fit", capture / "capture.yaml", "--out", out, "--max-memory", "8G")
    _refused(capsys, *argv, match=match)
    assert not out.exists()


def test_a_model_larger_than_max_cells_is_noted(capture, capsys, tmp_path):
    """Before: max_cells below the smallest model (32 θ bins), and θ bins or a
    refinement fixed beyond it, were used without a word."""
    _edit(capture, fit={"max_cells": 100})
    status, out, err = _run(capsys, "fit", capture / "capture.yaml", "--out", tmp_path / "r.json")
    assert status in (0, 1), err
    notes = [line for line in out.splitlines() if "max_cells" in line]
    assert notes == [
        f"note: max_cells 100 is below the model's size ({W}x{H} px, n_theta 32, refine 1, "
        f"{W * H * 32} cells): n_theta is not lowered below 32; the fit solves on that model"
    ], out

    class Stop(Exception):
        pass

    def notes_of(fit: dict) -> list[str]:
        _edit(capture, fit=fit)
        said = []

        def progress(message: str) -> None:  # stopped once the solve starts
            said.append(message)
            if not message.startswith(("separating", "note: ")):
                raise Stop

        with pytest.raises(Stop):
            lfj.fit_capture(lfj.load_capture(capture / "capture.yaml"), progress=progress)
        return [m for m in said if m.startswith("note: ")]

    fixed = notes_of({"n_theta": 128, "refine": 2, "max_cells": 100000})
    assert len(fixed) == 1 and fixed[0].startswith("note: max_cells 100000 is below"), fixed
    assert "n_theta 128 and refine 2 are fixed by the fit options, never lowered" in fixed[0]
    assert notes_of({}) == []  # the defaults: within max_cells, nothing said


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


@pytest.mark.parametrize(
    ("illumination", "noise", "match"),
    [
        (
            {"phases": [0, 0, 0]},
            False,
            "illumination.phases: the 3 shifts are the same image: the stripes moved nothing",
        ),
        (
            {"phases": [0, 0, 0]},
            {"read": 0},  # a noise section that adds none
            "illumination.phases: the 3 shifts are the same image: the stripes moved nothing",
        ),
        ({"phases": [4]}, True, "illumination.phases: a fit needs at least 2 shifted images"),
        ({"shifts": 1}, True, "illumination.shifts: a fit needs at least 2 shifted images"),
    ],
)
def test_simulate_refuses_stripes_whose_capture_the_fit_refuses(
    tmp_path, capsys, illumination, noise, match
):
    """Before: simulate wrote the capture, and the fit refused it ('images: the 3 shifts
    are the same image', 'pattern.phases: a fit needs at least 2 shifted images')."""
    config = yaml.safe_load(SIMULATE)
    config["illumination"] = {"kind": "stripes", "period": 6, "lit": 3, **illumination}
    if not noise:
        del config["noise"]
    elif isinstance(noise, dict):
        config["noise"] = noise
    path = tmp_path / "sim.yaml"
    path.write_text(yaml.safe_dump(config))
    line = _refused(capsys, "simulate", path, "--out", tmp_path / "o", match=match)
    assert str(path) in line and not (tmp_path / "o").exists()


def test_simulate_keeps_repeated_phases_the_fit_takes(tmp_path):
    """With noise the images of repeated phases differ, and the fit takes them."""
    from lightfield_jax.forward.simulate_config import parse_simulation_config

    config = yaml.safe_load(SIMULATE)
    config["illumination"] = {"kind": "stripes", "period": 6, "lit": 3, "phases": [0, 0, 3]}
    assert parse_simulation_config(config).illumination.phases == (0, 0, 3)
    config["illumination"]["phases"] = [1, 1, 1]
    assert parse_simulation_config(config).illumination.phases == (1, 1, 1)


# ------------------------------------------------------------------ render: results


def _results(capture: Path, tmp_path: Path, **changes) -> Path:
    """A results file as lightfield-jax fit writes it (the keys render reads)."""
    model = {"width": W, "height": H, "n_theta": 16, "refine": 1, "bounces": 4}
    model.update(changes.pop("model", {}))
    crop = changes.pop("crop", [0, 0, W, H])
    capture_file = changes.pop("capture_file", capture / "capture.yaml")
    data = {"sigma_t": 0.2051, "sigma_s": 0.0366, "g": 0.4, "gain": 400.0, "phase": "paper"}
    data.update(changes)
    data["model"] = {**model, "crop": crop, "geometry": {"kind": "plane"}}
    data["capture"] = capture_file if capture_file in (5, None) else str(capture_file)
    path = tmp_path / "results.json"
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"model": {"bounces": 10**9}}, "channel Y: model.bounces: at most 10000 bounces"),
        ({"model": {"n_theta": 8 * 10**6}}, "channel Y: model.n_theta: must be at most 4096"),
        ({"sigma_t": -1.0}, "channel Y: sigma_t: must be > 0"),
        ({"g": 1.0}, "channel Y: g: must satisfy -1 < g < 1, got 1.0"),
        ({"model": {"n_theta": 7}}, "channel Y: model.n_theta: must be a multiple of 8"),
        ({"model": {"bounces": 0}}, "channel Y: model.bounces: must be a positive integer"),
        (
            {"gain": -5.0},
            "channel Y: gain: must be a number in [1e-30, 1e+30] (images are float32), got -5.0",
        ),
        (
            {"gain": 1e39},
            "channel Y: gain: must be a number in [1e-30, 1e+30] (images are float32), got 1e+39",
        ),
        (
            {"gain": True},
            "channel Y: gain: must be a number in [1e-30, 1e+30] (images are float32), got True",
        ),
        ({"gain": "400"}, "channel Y: no usable gain"),
        ({"crop": [50, 50, 10, 10]}, "channel Y: model.crop: must be [x0, y0, x1, y1]"),
        # Before: "model.crop: [0, 0, 32, 24] is 32x24 pixels, but model.width x height is
        # 32x'24'", blaming the crop for the size's type.
        ({"model": {"height": "24"}}, "channel Y: model.height: must be an integer, got '24'"),
        ({"model": {"width": 0}}, "channel Y: model.width: must be an integer >= 2, got 0"),
        ({"crop": "all"}, "channel Y: model.crop: must be [x0, y0, x1, y1]"),
        # Before: a hand-edited "no" (or 0, null) warned "did not converge (converged)".
        ({"converged": "no"}, "channel Y: converged: must be true or false, got 'no'"),
        ({"converged": 0}, "channel Y: converged: must be true or false, got 0"),
        ({"converged": None}, "channel Y: converged: must be true or false, got None"),
        # Before: a TypeError traceback (unhashable type: 'list'), exit 1.
        ({"channel": ["Y"]}, "channel: must be the channel's name, got ['Y']"),
        ({"channel": {"name": "Y"}}, "channel: must be the channel's name, got {'name': 'Y'}"),
        ({"capture_file": "/nonexistent/capture.yaml"}, "capture: /nonexistent/capture.yaml"),
        # Before: a TypeError traceback (an edited "capture": 5 or null).
        ({"capture_file": 5}, "capture: must be the capture file's path, got 5"),
        ({"capture_file": None}, "capture: must be the capture file's path, got None"),
        # Before: rendered (a crop outside the capture, or of another size than the model).
        (
            {"crop": [0, 0, 480, 360], "model": {"width": 480, "height": 360}},
            f"model.crop: [0, 0, 480, 360] lies outside the capture's {W}x{H} images",
        ),
        (
            {"crop": [0, 0, W // 2, H]},
            f"model.crop: [0, 0, {W // 2}, {H}] is {W // 2}x{H} pixels, but model.width x "
            f"height is {W}x{H}",
        ),
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


def test_render_refuses_channel_names_that_leave_its_folder(capture, capsys, tmp_path):
    """Before: an edited results file's channel ``../x`` or ``/abs/x`` was rendered
    into that folder, outside --out (exit 0); a list for per_channel was numpy's
    "dictionary update sequence element #0 has length 6" without the file."""
    fit = json.loads(_results(capture, tmp_path).read_text())
    results = tmp_path / "rgb.json"
    for channels, match in (
        ({"R": fit, "../x": fit}, "per_channel: '../x' is not a channel name"),
        ({"R": fit, "/abs/x": fit}, "per_channel: '/abs/x' is not a channel name"),
        ({"R": fit, "..": fit}, "per_channel: '..' is not a channel name"),
        ([fit, fit], "per_channel: must map each channel's name to its fit, got [{"),
        ({"R": 5}, "per_channel: must map each channel's name to its fit, got {'R': 5}"),
    ):
        results.write_text(json.dumps({"capture": fit["capture"], "per_channel": channels}))
        line = _refused(capsys, "render", results, "--out", tmp_path / "out", match=match)
        assert line.startswith(f"lightfield-jax: error: {results}: ")
    assert sorted(os.listdir(tmp_path)) == ["cap", "results.json", "rgb.json"]


def test_render_never_takes_another_folders_capture_file(capture, capsys, tmp_path, monkeypatch):
    """Before: fit wrote the capture's path as given (``capture.yaml``, run in its
    folder), and render looked for it in the current folder first: run from another
    capture's folder, it rendered with that capture's geometry, silently. Now fit
    writes the absolute path, and a relative one that names two files is refused."""
    other = tmp_path / "other"
    shutil.copytree(capture, other)
    monkeypatch.chdir(capture)
    status = main(["fit", "capture.yaml", "--method", "gradient", "--out", "r.json", "-q"])
    assert status in (0, 1)
    capsys.readouterr()
    fit = json.loads((capture / "r.json").read_text())
    assert fit["capture"] == str(capture / "capture.yaml")
    fit["capture"] = "capture.yaml"  # as fit wrote it before
    (capture / "r.json").write_text(json.dumps(fit))
    monkeypatch.chdir(other)
    view = tmp_path / "view"
    _refused(capsys, "render", capture / "r.json", "--out", view, match="names two files")
    assert not view.exists()


def test_a_truth_in_another_phase_convention_is_not_compared_for_sigma_s(capture, capsys, tmp_path):
    """Before: ``fit --phase normalized`` of a capture whose truth is ``phase: paper``
    printed 'sigma_s -38.1 % (-186.1 sigma)' against the truth (and wrote it) for a fit
    that had found the medium: the conventions' sigma_s differ by A(g)."""
    out = tmp_path / "r.json"
    status, stdout, err = _run(
        capsys, "fit", capture / "capture.yaml", "--phase", "normalized", "--out", out
    )
    assert status in (0, 1), err
    assert "truth.phase is paper, the fit's --phase normalized: sigma_s is not compared" in err
    said = [line for line in stdout.splitlines() if "against the truth" in line]
    assert len(said) == 1 and "sigma_t" in said[0] and "sigma_s" not in said[0], stdout
    assert set(json.loads(out.read_text())["truth_error"]) == {"sigma_t", "g"}


def test_a_valid_handmade_results_file_renders(capture, capsys, tmp_path):
    results = _results(capture, tmp_path)
    assert main(["render", str(results), "--out", str(tmp_path / "r"), "-q"]) == 0
    assert np.load(tmp_path / "r" / "bounces.npy").shape == (4, H, W)


def test_render_never_replaces_a_file_of_the_capture(capture, capsys, tmp_path):
    """Before: ``render results.json --out CAPTURE_FOLDER`` of a capture whose image stack
    was named lightfield.npy and whose dark frame bounces.exr replaced both with the
    render's files (only the results file was an input). Now refused, naming the input."""
    stack = np.stack([read_image(capture / f"shift_{i:02d}.exr").pixels[..., 0] for i in range(P)])
    np.save(capture / "lightfield.npy", stack)
    (capture / "dark.exr").rename(capture / "bounces.exr")
    _edit(capture, images="lightfield.npy", dark_frame="bounces.exr")
    results = _results(capture, tmp_path)
    before = _snapshot(capture)
    _refused(capsys, "render", results, "--out", capture, match="holds an input of this command")
    assert _snapshot(capture) == before
    _edit(capture, images=[f"shift_{i:02d}.exr" for i in range(P)])
    before = _snapshot(capture)
    _refused(capsys, "render", results, "--out", capture, match="bounces.exr), which it would")
    assert _snapshot(capture) == before


def test_render_of_a_fit_that_did_not_converge_warns_and_records_it(capture, capsys, tmp_path):
    """Before: rendered without a word (render.json did not say either)."""
    reasons = ["chi2/dof = 41 is far above the noise", "g = 0.981 is at its bound"]
    results = _results(capture, tmp_path, converged=False, reasons=reasons, message="x")
    status, _, err = _run(capsys, "render", results, "--out", tmp_path / "r", "-q")
    assert status == 0
    assert err.splitlines() == [
        f"lightfield-jax: warning: {results}: channel Y: the fit did not converge "
        f"({'; '.join(reasons)}); rendering its values all the same"
    ]
    about = json.loads((tmp_path / "r" / "render.json").read_text())
    assert about["fit_converged"] is False and "; ".join(reasons) in about["fit_warning"]
    assert np.load(tmp_path / "r" / "bounces.npy").shape == (4, H, W)
    # Without reasons, the solver's message; a converged fit says nothing.
    results = _results(capture, tmp_path, converged=False, message="max_steps reached")
    _, _, err = _run(capsys, "render", results, "--out", tmp_path / "r", "-q")
    assert "the fit did not converge (max_steps reached)" in err
    results = _results(capture, tmp_path, converged=True, reasons=[])
    assert _run(capsys, "render", results, "--out", tmp_path / "r", "-q")[2] == ""
    assert json.loads((tmp_path / "r" / "render.json").read_text())["fit_converged"] is True


# ------------------------------------------------------------------ smaller


def test_a_saturation_beyond_float32_is_refused(capture, capsys):
    """Before: inspect went on with numpy's 'overflow encountered in cast' warning."""
    _edit(capture, saturation=1.0e300)
    _refused(
        capsys,
        *("inspect", capture / "capture.yaml"),
        match="saturation: must be at most 1e+30 (images are float32), got 1e+300",
    )


@pytest.mark.parametrize("bracketed", [False, True])
def test_a_saturation_in_codes_for_integer_images_is_refused(capture, capsys, bracketed):
    """Before: ``saturation: 65000`` (codes, for 16-bit images scaled to [0, 1]) masked
    nothing: the values clipped at the top code were fitted as light, without a word."""
    names = []
    for i in range(P):
        x = read_image(capture / f"shift_{i:02d}.exr").pixels[..., 0]
        write_png(capture / f"s{i}.png", np.clip(3 * x, 0, 1), bits=16)
        names.append(f"s{i}.png")
    write_png(capture / "d.png", np.zeros((H, W)), bits=16)
    if bracketed:
        _edit(capture, images=[[n, n] for n in names], exposure_times=[1, 2])
        _edit(capture, dark_frame=["d.png", "d.png"])
    else:
        _edit(capture, images=names, dark_frame="d.png")
    _edit(capture, saturation=65000)
    _refused(
        capsys,
        *("inspect", capture / "capture.yaml"),
        match="saturation: must be at most 1 with integer images (s0.png is 16-bit, scaled to "
        "[0, 1]: its top code is 1), got 65000: a threshold of 65000 codes is saturation: 0.991836",
    )


def test_a_dark_level_beyond_float32_is_refused(capture, capsys):
    """Before: dark_level 1e300 overflowed the images to -Inf: numpy's 'overflow
    encountered in cast' and 'no direct light at the entry wall', exit 1."""
    path = _edit(capture, dark_frame=None, dark_level=1.0e300)
    _refused(
        capsys,
        *("inspect", path),
        match="dark_level: must be at most 1e+30 (images are float32), got 1e+300",
    )


def test_zeros_in_a_flat_field_are_named_as_zeros(capture, capsys):
    """Before: 'N pixel value(s) are NaN or Inf (flat.exr: N)' for a flat field's zeros."""
    flat = np.ones((H, W))
    flat[3:5, 3:8] = 0.0
    flat[9, 9] = -0.5
    write_exr(capture / "flat.exr", {"Y": flat})
    _edit(capture, flat_field="flat.exr")
    status, _, err = _run(capsys, "inspect", capture / "capture.yaml", "-q")
    assert status == 0, err
    assert err.splitlines() == [
        f"lightfield-jax: warning: {capture / 'capture.yaml'}: flat_field: 11 pixel value(s) "
        "of flat.exr are not positive (10 zero, 1 negative): no vignetting is measured "
        "there; those pixels are masked"
    ]


def test_a_dead_pixel_in_a_flat_field_is_masked_not_divided_by(capture, capsys):
    """Before: a flat pixel of 1e-30 multiplied its image values by 1e30 without a word
    (inspect: 'D peak 2.674e+29'; the fit: 'the basin scan found no valid model')."""
    data = yaml.safe_load((capture / "capture.yaml").read_text())
    dark = read_image(capture / data["dark_frame"]).pixels[..., 0].astype(np.float64)
    flat = dark + 1.0
    flat[H // 2, 5] = dark[H // 2, 5] + 1e-6  # 1e-6 above the dark frame
    flat[H // 2, 6] = dark[H // 2, 6] + 0.5  # vignetting: kept
    write_exr(capture / "flat.exr", {"Y": flat})
    _edit(capture, flat_field="flat.exr")
    status, out, err = _run(capsys, "inspect", capture / "capture.yaml")
    assert status == 0, err
    assert err.splitlines() == [
        f"lightfield-jax: warning: {capture / 'capture.yaml'}: flat_field: 1 pixel value(s) "
        "of flat.exr are below 0.001 of its median (the smallest 1e-06): dividing by them "
        "would multiply those image values more than 1000-fold (dead pixels, not "
        "vignetting); those pixels are masked"
    ]
    assert "e+29" not in out and "non-finite: 1," in out


def test_infinite_pixels_are_masked_or_named_without_numpy_warnings(capture, capsys):
    """Before: numpy's 'invalid value encountered in reduce' (+Inf and -Inf in one
    pixel) or '... in scalar subtract' (Inf in the mosaic check's percentile) on the
    terminal beside the capture's own line, and an image of nothing but Inf reported
    as a detection failure (or as 'no usable pixel')."""
    images = {i: read_image(capture / f"shift_0{i}.exr").pixels[..., 0] for i in (0, 1, 2)}
    for i, value in ((1, np.inf), (2, -np.inf)):
        images[i][4:8, 4:12] = value
        write_exr(capture / f"shift_0{i}.exr", {"Y": images[i]})
    status, _, err = _run(capsys, "inspect", capture / "capture.yaml", "-q")
    assert status == 0, err
    assert err.splitlines() == [
        f"lightfield-jax: warning: {capture / 'capture.yaml'}: 64 pixel value(s) are NaN or "
        "Inf (shift_01.exr: 32, shift_02.exr: 32); 64 value(s) masked in 32 pixel(s)"
    ]
    images[1][:, : W // 2] = np.inf
    write_exr(capture / "shift_01.exr", {"Y": images[1]})
    status, _, err = _run(capsys, "inspect", capture / "capture.yaml", "-q")
    assert "encountered" not in err and "RuntimeWarning" not in err, err
    write_exr(capture / "shift_00.exr", {"Y": np.full((H, W), np.inf)})
    _refused(
        capsys,
        *("inspect", capture / "capture.yaml"),
        match="images: shift_00.exr: every pixel value is NaN or Inf",
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
    _refused(
        capsys, "demo", "--out", tmp_path / "d", "--methods", "joint,grid,joint",
        match="--methods: names joint more than once",
    )  # fmt: skip
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


def test_fit_images_refuses_images_without_light_or_stripes_by_cause():
    """Before: negated images ended in 'the basin scan found no valid model ... give
    bounces or a start', all-zero images and one image given for every shift in
    'fit_decay: sigma_t is not identifiable: 0 usable pixels ... too dim'."""
    import lightfield_jax as lfj

    lit = np.random.default_rng(0).random((6, H, W)) + 0.1
    for images, match in [
        (-lit, r"images: no value is above 0 \(the largest is -0.1"),
        (np.zeros((6, H, W)), r"images: no value is above 0 \(the largest is 0\)"),
        (np.repeat(lit[:1], 6, axis=0), "images: the 6 shifts are the same image"),
        (np.full((6, H, W), 0.5), "images: the 6 shifts are the same image"),
    ]:
        with pytest.raises(ValueError, match=match):
            lfj.fit_images(images, lfj.Stripes())


def test_an_all_saturated_capture_is_one_error_line_with_its_cause(capture, capsys):
    """Before: two warnings (every pixel saturated; pixels masked), then the error."""
    for i in range(P):
        write_exr(capture / f"shift_{i:02d}.exr", {"Y": np.ones((H, W))})
    _edit(capture, saturation=1.0)
    line = _refused(capsys, "fit", capture / "capture.yaml", match="images: no usable pixel")
    assert "every pixel is saturated in shift_00.exr" in line


@pytest.mark.parametrize("roi", [[10, 10, 12, 12], [0, 0, 32, 5]])
def test_a_medium_too_small_to_fit_is_refused(capture, capsys, roi):
    """Before: a 2x2 medium_roi was fitted, with 'Mean of empty slice' and a chi2 of NaN."""
    _edit(capture, medium_roi=roi)
    size = f"{roi[2] - roi[0]}x{roi[3] - roi[1]} px"
    for command in ("fit", "inspect"):
        _refused(
            capsys, command, capture / "capture.yaml", match=f"medium_roi: the medium is {size}"
        )


def test_a_medium_too_short_along_the_light_is_refused_by_fit(capture, capsys):
    """7 px along the light (entry left: x): inspected, but a fit's noise estimate needs 8."""
    _edit(capture, medium_roi=[0, 0, 7, 24])
    status, out, err = _run(capsys, "inspect", capture / "capture.yaml")
    assert status in (0, 1) and "Traceback" not in err, (status, err)
    _refused(capsys, "fit", capture / "capture.yaml", match="at least 8 px along the light (x")
    _edit(capture, medium_roi=[0, 0, 8, 6])
    status, out, err = _run(capsys, "inspect", capture / "capture.yaml")
    assert status in (0, 1) and "Traceback" not in err, (status, err)


@pytest.mark.parametrize(
    ("geometry", "match"),
    [
        ({"kind": "slab", "thickness": 1.0e12}, "geometry.thickness: must be at most 100000 px"),
        ({"kind": "slab", "thickness": 6.4, "boundary": "refractive", "n": 1.0e9}, "in [1, 4]"),
        ({"kind": "slab", "thickness": 6.4, "boundary": "refractive", "n": 0.5}, "in [1, 4]"),
    ],
)
def test_slabs_beyond_any_real_tank_are_refused(capture, capsys, geometry, match):
    """Before: a 1e12 px deep tank was accepted and an index of 1e9 rendered NaN."""
    _edit(capture, geometry=geometry)
    _refused(capsys, "fit", capture / "capture.yaml", match=match)


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"black_frame": "dark.exr"}, "black_frame: dark.exr is also dark_frame"),
        ({"black_frame": "shift_03.exr"}, "black_frame: shift_03.exr is also images[3]"),
        ({"dark_frame": "shift_00.exr"}, "dark_frame: shift_00.exr is also images[0]"),
        ({"dark_frame": "./shift_00.exr"}, "dark_frame: ./shift_00.exr is also images[0]"),
    ],
)
def test_one_file_in_two_roles_is_refused(capture, capsys, tmp_path, change, match):
    """Before: the same file as the dark and the black frame measured a black level of 0
    and the fit said converged with σs +47 %; a stripe image as a calibration frame ran a
    whole fit to an unrelated reason. (A stripe image listed twice is left to the
    phases' checks.)"""
    _edit(capture, **change)
    out = tmp_path / "r.json"
    _refused(capsys, "fit", capture / "capture.yaml", "--out", out, match=match)
    assert not out.exists()


def _bracketed(capture: Path) -> Path:
    """The capture as two-exposure brackets (float EXR, times 1 and 4 s), dark frame alike."""
    rows = []
    for i in range(P):
        x = read_image(capture / f"shift_{i:02d}.exr").pixels[..., 0]
        for j, t in enumerate((1, 4)):
            write_exr(capture / f"b{i}_{j}.exr", {"Y": x * t})
        rows.append([f"b{i}_{j}.exr" for j in range(2)])
    dark = read_image(capture / "dark.exr").pixels[..., 0]
    for j in range(2):
        write_exr(capture / f"dark_{j}.exr", {"Y": dark})
    return _edit(
        capture, images=rows, exposure_times=[1, 4], dark_frame=["dark_0.exr", "dark_1.exr"]
    )


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (
            {"dark_frame": ["b0_0.exr", "dark_1.exr"]},
            "dark_frame[0]: b0_0.exr is also images[0][0]",
        ),
        (
            {"black_frame": ["dark_0.exr", "dark_1.exr"]},
            "black_frame[0]: dark_0.exr is also dark_frame[0]",
        ),
    ],
)
def test_one_file_in_two_roles_is_refused_in_brackets(capture, capsys, tmp_path, change, match):
    """Before: with exposure brackets the files were not compared at all: a stripe
    image's exposure taken as a dark frame (or the dark bracket as the black one) was
    merged and fitted. Now refused as for single exposures, naming both keys."""
    _bracketed(capture)
    _edit(capture, **change)
    out = tmp_path / "r.json"
    _refused(capsys, "fit", capture / "capture.yaml", "--out", out, match=match)
    assert not out.exists()


@pytest.mark.parametrize(
    ("value", "match"),
    [
        (np.nan, "images[2][0]: b2_0.exr: every pixel value is NaN or Inf (a corrupt file?)"),
        (0.0, "images[2][0]: b2_0.exr: every pixel value is 0, unlike the other images"),
    ],
)
def test_a_corrupt_or_dropped_exposure_in_a_bracket_is_refused(capture, capsys, value, match):
    """Before: an exposure of NaN only (a corrupt file) or of zeros (a dropped frame) was
    merged as zeros without a word: its shift's image near 0 wherever the longer
    exposure clipped. Now refused as a single exposure is."""
    _bracketed(capture)
    write_exr(capture / "b2_0.exr", {"Y": np.full((H, W), value, np.float32)})
    _refused(capsys, "inspect", capture / "capture.yaml", match=match)


def test_nan_samples_in_a_bracket_are_left_out_of_the_merge(capture):
    """Before: a NaN sample was merged as 0: where the longer exposure clipped the pixel
    came out near 0, not masked; elsewhere the merge was pulled down by a fifth."""
    _bracketed(capture)
    x = read_image(capture / "b2_0.exr").pixels[..., 0]
    bright = np.unravel_index(np.argmax(x), x.shape)  # clipped at 4 s
    dim = (H // 2, W - 2)  # well exposed at 4 s
    assert x[bright] * 4 > 1 and x[dim] * 4 < 0.5
    x = x.copy()
    x[bright] = x[dim] = np.nan
    write_exr(capture / "b2_0.exr", {"Y": x})
    broken = lfj.load_capture(capture / "capture.yaml")
    assert not broken.sample_mask[2][bright].any()  # clipped in its one finite sample
    # Merged from its 4 s sample alone (the dark frame subtracted).
    alone = (
        read_image(capture / "b2_1.exr").pixels[dim]
        - read_image(capture / "dark_1.exr").pixels[dim]
    )
    assert broken.images[2][dim] == pytest.approx(alone / 4, rel=1e-5)
    assert any("2 sample value(s) are NaN or Inf (b2_0.exr: 2)" in n for n in broken.notes)


def test_a_calibration_frame_repeated_in_its_own_bracket_is_kept(capture):
    """The same dark frame at every exposure is one role, not two."""
    _bracketed(capture)
    assert lfj.load_capture(capture / "capture.yaml").brackets.times == (1.0, 4.0)


def test_a_response_table_named_npy_is_refused(capture, capsys, tmp_path):
    """Before: ``inspect --response curve.npy`` wrote the CSV text into curve.npy, which
    ``response: curve.npy`` then refused as 'not a readable .npy array'."""
    _bracketed(capture)
    table = tmp_path / "curve.npy"
    _refused(capsys, "inspect", capture / "capture.yaml", "--response", table, match="name it .csv")
    assert not table.exists()


def test_a_npy_stack_as_a_calibration_frame_too_is_named(capture, capsys):
    """Before: the stack [P, H, W] given also as the dark frame was refused as 'st.npy is
    24x6 pixels with 32 channel(s)' (its axes read as an image's), not as the slip."""
    stack = np.stack([read_image(capture / f"shift_{i:02d}.exr").pixels[..., 0] for i in range(P)])
    np.save(capture / "st.npy", stack)
    _edit(capture, images="st.npy", dark_frame="st.npy")
    _refused(capsys, "inspect", capture / "capture.yaml", match="dark_frame: st.npy is also images")


def test_api_arguments_are_checked_before_any_work():
    """Before: boolean images ran a 26 s nonsense fit, a mask of another shape ended in
    numpy's broadcast message, a negative saturation in 'sigma_t is not identifiable',
    a string σt was accepted, phases past the period were taken, and load_capture(5)
    raised a bare TypeError."""
    images = np.random.default_rng(0).random((6, 24, 32)).astype(np.float32)
    pattern = lfj.Stripes()
    for kwargs, given, match in [
        ({}, images > 0.1, "images: must be real numbers, got dtype bool"),
        ({"mask": np.ones((3, 3), bool)}, images, r"mask: must have the images' \(height"),
        ({"saturation": -1.0}, images, "saturation: must be a positive number"),
        # No pixel valid in every shift: named with its cause (it was 'fit_decay: sigma_t
        # is not identifiable: 0 usable pixels').
        ({"mask": np.zeros((24, 32), bool)}, images, r"no pixel is valid .* by mask"),
        ({"saturation": 1e-9}, images, r"no pixel is valid .* at or above saturation"),
        ({}, np.where(np.arange(6)[:, None, None] == 2, np.nan, images), "masked: 768 non-finite"),
    ]:
        with pytest.raises(ValueError, match=match):
            lfj.fit_images(given, pattern, **kwargs)
    with pytest.raises(ValueError, match="medium.sigma_t: must be a number"):
        lfj.Medium(sigma_t="0.2", sigma_s=0.05, g=0.4)
    with pytest.raises(ValueError, match=r"phase must lie in \[0, period = 6\), got 7"):
        lfj.Stripes(period=6, lit=3, phases=(0, 7))
    with pytest.raises(ValueError, match="load_capture: expected a capture file's path"):
        lfj.load_capture(5)


def test_an_impossible_black_frame_is_refused(capture, capsys, tmp_path):
    """Before: a black frame three times brighter than the stripe images gave a black
    level clipped to 0 and a fit with σs +47 % that said it converged."""
    shifts = [read_image(f).pixels[..., 0] for f in sorted(capture.glob("shift_*.exr"))]
    write_exr(capture / "black.exr", {"Y": 3 * np.mean(shifts, axis=0)})
    _edit(capture, black_level="auto", black_frame="black.exr")
    out = tmp_path / "r.json"
    argv = ("fit", capture / "capture.yaml", "--out", out)
    _refused(capsys, *argv, match="black_frame: the all-black frame against the mean")
    assert not out.exists()


def test_a_saturated_black_frame_is_refused(capture, capsys, tmp_path):
    """Before: a black frame clipped at its largest value (float) or at its top code
    (16-bit) gave black_level: auto a level near 0 (0.0004, the truth 0.02), accepted."""
    shifts = np.array([read_image(f).pixels[..., 0] for f in sorted(capture.glob("shift_*.exr"))])
    noisy = 0.3 * shifts.mean(axis=0) + 0.05 + 1e-3 * np.random.default_rng(0).random((H, W))
    write_exr(capture / "black.exr", {"Y": np.minimum(noisy, 0.06).astype(np.float32)})
    path = _edit(capture, black_level="auto", black_frame="black.exr")
    out = tmp_path / "r.json"
    line = _refused(capsys, "fit", path, "--out", out, match="black_frame: black.exr: ")
    assert "pixel values sit at its largest value (saturated" in line
    assert not out.exists()
    # 16-bit files: the black frame at the top code 65535
    names = []
    for i, image in enumerate(shifts):
        names.append(f"s{i}.png")
        write_png(capture / names[-1], 0.8 * image / shifts.max(), bits=16)
    write_png(
        capture / "black.png", np.where(np.arange(H)[:, None] < 3, 0.5, np.ones((H, W))), bits=16
    )
    data = yaml.safe_load(path.read_text())
    del data["dark_frame"]
    data.update(images=names, black_frame="black.png")
    path.write_text(yaml.safe_dump(data))
    line = _refused(capsys, "inspect", path, match="black_frame: black.png: ")
    assert f"{(H - 3) * W} of {H * W} pixel values sit at its top code" in line


@pytest.mark.parametrize("value", [0.0, 0.5])
def test_a_white_frame_of_one_value_is_refused_naming_it(capture, capsys, value):
    """Before: an all-zero white frame was blamed on the images ('detect_geometry: no
    lit medium found'); a constant one gave the whole frame as the medium."""
    write_exr(capture / "white.exr", {"Y": np.full((H, W), value, np.float32)})
    path = _edit(capture, white_frame="white.exr", medium_roi="auto")
    _refused(
        capsys, "inspect", path, match=f"white_frame: white.exr: every pixel value is {value:g}"
    )


def test_a_black_frame_of_zeros_is_a_black_level_of_zero(capture, capsys):
    """A camera clamping its black at 0 under a projector whose black is below one code
    takes an all-zero black frame: a measurement (black level 0), not refused."""
    write_exr(capture / "black.exr", {"Y": np.zeros((H, W), np.float32)})
    path = _edit(capture, black_level="auto", black_frame="black.exr")
    status, _, err = _run(capsys, "inspect", path)
    assert status == 0 and "black_frame" not in err, err


def test_a_stripe_image_listed_twice_is_said_where_the_phases_cannot_catch_it(capture, capsys):
    """Before: with phases: auto, shift_00.exr listed as images[0] and images[5] was
    accepted without a word (one image fitted as two shifts, its noise counted twice)."""
    names = yaml.safe_load((capture / "capture.yaml").read_text())["images"]
    path = _edit(capture, images=[*names[:5], names[0]])
    data = yaml.safe_load(path.read_text())
    data["pattern"]["phases"] = "auto"
    path.write_text(yaml.safe_dump(data))
    _, _, err = _run(capsys, "inspect", path)
    assert "images[5] (shift_00.exr) is the file of images[0] listed again" in err, err
    assert "Traceback" not in err


def test_a_bracket_listed_twice_is_said_where_the_phases_cannot_catch_it(capture, capsys):
    """Before: the warning above was given for single exposures only: with brackets and
    phases: auto, one shift's bracket listed again was merged and fitted as two shifts
    without a word."""
    path = _bracketed(capture)
    data = yaml.safe_load(path.read_text())
    data["images"][5] = data["images"][0]
    data["pattern"]["phases"] = "auto"
    path.write_text(yaml.safe_dump(data))
    _, _, err = _run(capsys, "inspect", path)
    assert "images[5] (b0_0.exr, b0_1.exr) is the bracket of images[0] listed again" in err, err
    assert "Traceback" not in err


def test_a_terminal_escape_in_a_file_name_is_printed_escaped(capture, capsys):
    """Before: a file name holding ESC [31m was printed raw into the error line (the
    terminal recoloured; other sequences rewrite it)."""
    names = yaml.safe_load((capture / "capture.yaml").read_text())["images"]
    path = _edit(capture, images=["\x1b[31mred.exr", *names[1:]])
    line = _refused(capsys, "inspect", path, match="images[0]: ")
    assert "\\x1b[31mred.exr: file not found" in line and "\x1b" not in line, line
    # A right-to-left override (a format character) reorders what the terminal shows.
    path = _edit(capture, images=["a\u202egnp.exr", *names[1:]])
    line = _refused(capsys, "inspect", path, match="images[0]: ")
    assert "a\\u202egnp.exr" in line and "\u202e" not in line, line


def test_a_folder_named_in_another_encoding_is_one_line(capture, capsys, tmp_path):
    """Before: a capture in (or simulate --out into) a folder whose name is not UTF-8
    was OpenImageIO's 'open(): incompatible function arguments' traceback."""
    folder = tmp_path / os.fsdecode(b"caf\xe9")  # Latin-1, as Python holds it
    shutil.copytree(capture, folder)
    _refused(
        capsys,
        "inspect",
        folder / "capture.yaml",
        match="shift_00.exr: the path is not valid UTF-8",
    )
    cfg = tmp_path / "sim.yaml"
    cfg.write_text(SIMULATE)
    out = folder / "out"
    _refused(capsys, "simulate", cfg, "--out", out, match="out: the path is not valid UTF-8")
    assert not out.exists()


def test_an_image_that_is_a_symlink_loop_is_one_line(capture, capsys):
    """Before: pathlib's 'RuntimeError: Symlink loop from ...' traceback (the check of
    one file in two roles resolved it)."""
    (capture / "shift_01.exr").unlink()
    (capture / "shift_01.exr").symlink_to(capture / "shift_01.exr")
    _refused(
        capsys,
        *("inspect", capture / "capture.yaml"),
        match="images[1]: ",
    )


def test_a_nul_in_a_path_and_a_deeply_nested_results_file_are_named(capture, capsys, tmp_path):
    """Before: 'embedded null byte' and 'an input is nested too deeply', neither naming
    the file or the key."""
    images = yaml.safe_load((capture / "capture.yaml").read_text())["images"]
    _edit(capture, images=["shift_00\0.exr", *images[1:]])
    line = _refused(
        capsys, "fit", capture / "capture.yaml", "--out", tmp_path / "r.json", match="images[0]"
    )
    assert "must be a file path" in line
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    _refused(capsys, "render", deep, "--out", tmp_path / "v", match=f"{deep}: nested too deeply")


def test_a_results_file_that_is_not_utf8_is_named(capture, capsys, tmp_path):
    """Before: 'error: 'utf-8' codec can't decode byte 0xe9 in position 14: invalid
    continuation byte', naming neither the file nor what it should have been."""
    results = _results(capture, tmp_path)
    results.write_bytes(results.read_bytes().replace(b'"paper"', b'"caf\xe9"'))
    line = _refused(capsys, "render", results, "--out", tmp_path / "v", match=f"{results}: ")
    assert "not UTF-8 text" in line and "byte 0xe9" in line
    assert not (tmp_path / "v").exists()


def test_api_values_that_broke_deep_inside_are_refused_by_name():
    """Before: a Medium stored g = 0.99999999 as 1.0 in float32 (NaN renders), 1e39 as
    inf; render took gain NaN or -1 silently; fit_images(exposure=) of another shape
    raised an IndexError inside the fit, and negative times were fitted."""
    import jax

    with jax.enable_x64(False):  # the package's default float32 (the tests run x64)
        with pytest.raises(ValueError, match="medium.g: 0.99999999 rounds to"):
            lfj.Medium(0.2, 0.01, 0.99999999)
        with pytest.raises(ValueError, match="medium.sigma_t: 1e[+]39 overflows"):
            lfj.Medium(1e39, 0.1, 0.3)
        with pytest.raises(ValueError, match="medium.sigma_t: 1e-300 underflows"):
            lfj.Medium(1e-300, 0.0, 0.3)
    medium, grid = lfj.Medium(0.2, 0.1, 0.3), lfj.Grid(16, 16, 8, 1)
    for gain in (float("nan"), -1.0, "2", np.ones(3)):
        with pytest.raises(ValueError, match="render: gain: must"):
            lfj.render(medium, grid, lfj.Stripes(), 4, gain=gain)
    images = np.ones((6, 8, 16))
    for exposure in (np.ones(3), -np.ones(images.shape)):
        with pytest.raises(ValueError, match="exposure: must"):
            lfj.fit_images(images, lfj.Stripes(), exposure=exposure)


def test_a_wrong_entry_wall_is_refused_before_the_fit():
    """Before: Stripes(entry='right') on a capture lit from the left ran for minutes (a
    start at sigma_s 1e-7, g 0.9, then the model g 0.9 needs) and did not finish."""
    images = np.asarray(
        lfj.render(lfj.Medium(0.2051, 0.0366, 0.4), lfj.Grid(48, 24, 8, 1), lfj.Stripes(), 6).total
    )
    with pytest.raises(
        ValueError, match="pattern.entry: the direct light grows away from the right"
    ):
        lfj.fit_images(images, lfj.Stripes(entry="right"))


def test_simulate_publishes_nothing_when_its_figures_fail(capsys, tmp_path, monkeypatch):
    """Before: --out was published, then the figures failed (light at 87 deg: no pixel
    on its path, a numpy error), exit 2 with the output left behind. The figures of that
    scene are now drawn; a failure in them publishes neither folder."""
    cfg = tmp_path / "obl.yaml"
    cfg.write_text(
        "grid: {width: 24, height: 16}\n"
        "medium: {sigma_t: 0.2051, sigma_s: 0.0366, g: 0.4, phase: paper}\n"
        "illumination: {kind: full, direction_deg: 87}\n"
    )
    status, _, err = _run(
        capsys, "simulate", cfg, "--out", tmp_path / "o", "--plot", tmp_path / "f"
    )
    assert status == 0, err
    assert (tmp_path / "f" / "bounce_profiles.png").is_file()
    from lightfield_jax.capture import views

    def broken(*_args, **_kwargs):
        raise ValueError("a figure failed")

    monkeypatch.setattr(views, "plot_simulation", broken)
    status, _, _ = _run(
        capsys, "simulate", cfg, "--out", tmp_path / "o2", "--plot", tmp_path / "f2"
    )
    assert status != 0
    assert not (tmp_path / "o2").exists() and not (tmp_path / "f2").exists()


def test_a_failed_command_leaves_no_folders_it_made_for_its_outputs(
    capture, capsys, tmp_path, monkeypatch
):
    """Before: ``render bad.json --out new/a/b/view`` refused the results (exit 2,
    'nothing written') but left the empty folders new/a/b it had made for the output,
    and so did inspect and simulate whose last step failed."""
    bad = _results(capture, tmp_path, g=1.0)
    _refused(capsys, "render", bad, "--out", tmp_path / "new" / "a" / "b" / "view", match="g")
    assert not (tmp_path / "new").exists()
    import lightfield_jax.viz as viz

    def broken(*args, **kwargs):
        raise ValueError("plotting failed")

    monkeypatch.setattr(viz, "plot_inspect", broken)
    _refused(
        capsys,
        *("inspect", capture / "capture.yaml"),
        *("--json", tmp_path / "j" / "i.json", "--plot", tmp_path / "p" / "q" / "i.png"),
        match="plotting failed",
    )
    assert not (tmp_path / "j").exists() and not (tmp_path / "p").exists()
    from lightfield_jax.capture import views

    monkeypatch.setattr(views, "plot_simulation", broken)
    cfg = tmp_path / "sim.yaml"
    cfg.write_text(SIMULATE)
    status, _, _ = _run(
        capsys, "simulate", cfg, "--out", tmp_path / "s" / "o", "--plot", tmp_path / "f" / "g"
    )
    assert status == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap", "results.json", "sim.yaml"]
    # A folder that existed before is kept, empty or not.
    (tmp_path / "kept").mkdir()
    _refused(capsys, "render", bad, "--out", tmp_path / "kept" / "a" / "view", match="g")
    assert list((tmp_path / "kept").iterdir()) == []


@pytest.mark.parametrize("seconds", [1e10, 1e300])
def test_a_time_limit_beyond_a_timers_range_is_no_limit_and_no_traceback(seconds):
    """Before: ``--time-limit 1e300`` started a timer whose wait overflowed (a traceback
    from its thread on stderr) and the fit ran unbounded anyway; now no timer."""
    import threading

    from lightfield_jax.app.signals import stop_after

    failed = []
    previous, threading.excepthook = threading.excepthook, failed.append
    try:
        with stop_after(seconds, "lightfield-jax", "the fit"):
            time.sleep(0.2)
    finally:
        threading.excepthook = previous
    assert failed == []


def test_a_short_write_inside_an_output_folder_names_the_folder_once(tmp_path, monkeypatch):
    """Before: numpy's short write (no errno: a quota, a file size limit) of a file in a
    staged folder (render's R/bounces.npy) read "view: write failed ([Errno None] write
    failed (8400 requested and 7648 written): '.../.view.tmp-164f67c5/R/bounces.npy')",
    naming the temporary. Now "view: write failed (8400 requested and 7648 written)"."""
    from lightfield_jax.app.cli import describe_error
    from lightfield_jax.files import atomic_directory, atomic_write_npy

    def short_write(*_, **__):
        raise OSError("8400 requested and 7648 written")

    monkeypatch.setattr(np, "save", short_write)
    view = tmp_path / "view"
    with pytest.raises(OSError) as e, atomic_directory(view) as staging:
        atomic_write_npy(staging / "R" / "bounces.npy", np.zeros(3))
    assert describe_error(e.value) == f"{view}: write failed (8400 requested and 7648 written)"
    assert os.listdir(tmp_path) == []


def test_inspect_of_one_stripe_image_names_the_images_key(capture, capsys):
    """Before: inspect of a capture of one image was refused as "separate.images: need
    at least 2 shifted images", a key no capture file has (fit names pattern.phases)."""
    _edit(capture, images=["shift_00.exr"], pattern={"period": 6, "lit": 3, "phases": [0]})
    _refused(
        capsys,
        "inspect",
        capture / "capture.yaml",
        match="capture.yaml: images: inspecting needs at least 2 shifted images",
    )


def test_a_dark_frame_of_nan_only_is_named_by_its_key(capture, capsys):
    """Before: a dark frame whose every value is NaN was refused as "images: no usable
    pixel: every pixel is non-finite or saturated in some image (...)", under the images'
    key; now by its own key, as the stripe images and the projector's frames are."""
    write_exr(capture / "bad.exr", {"Y": np.full((H, W), np.nan, np.float32)})
    _edit(capture, dark_frame="bad.exr")
    match = "dark_frame: bad.exr: every pixel value is NaN or Inf (a corrupt file?)"
    _refused(capsys, "inspect", capture / "capture.yaml", match=match)
    _bracketed(capture)
    _edit(capture, dark_frame=["dark_0.exr", "bad.exr"])
    match = "dark_frame[1]: bad.exr: every pixel value is NaN or Inf"
    _refused(capsys, "inspect", capture / "capture.yaml", match=match)


@pytest.mark.parametrize("response", ["srgb", "auto"])
def test_a_response_curve_for_float_brackets_is_refused(capture, capsys, response):
    """Before: float (EXR) brackets with a response curve were refused as exposures
    "listed out of order" (a wrong cause), or, with auto, their linear values were
    quantised to 256 codes and fitted (a NaN sample: numpy's "invalid value encountered
    in cast" on the terminal). Now refused as for single exposures: floats are linear."""
    _bracketed(capture)
    _edit(capture, response=response)
    _refused(
        capsys,
        "inspect",
        capture / "capture.yaml",
        match=f"response: {response} maps a camera's integer codes (8- or 16-bit files), but "
        "images[0][0] (b0_0.exr) holds float values, which are linear",
    )


# ------------------------------------------------- round three: files, bounds, noise


def test_render_and_experiment_never_write_over_a_folder_of_the_users_own(
    capture, capsys, tmp_path
):
    """A folder holding files the command would replace that it did not write (no
    render.json, no summary.json) is the user's: refused, its files kept."""
    results = _results(capture, tmp_path)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "bounces.npy").write_bytes(b"my own array")
    (mine / "coverage.png").write_bytes(b"my own figure")
    before = _snapshot(mine)
    line = _refused(capsys, "render", results, "--out", mine, match="holds bounces.npy")
    assert "that lightfield-jax render did not write (no render.json; a file of your own?)" in line
    line = _refused(
        capsys, "experiment", "coverage", "--reduced", "--out", mine, match="holds coverage.png"
    )
    assert "lightfield-jax experiment did not write (no summary.json" in line
    assert _snapshot(mine) == before
    # The command's own folder is rerun into as before.
    assert main(["render", str(results), "--out", str(tmp_path / "r"), "-q"]) == 0
    assert main(["render", str(results), "--out", str(tmp_path / "r"), "-q"]) == 0


def _sparse(path: Path, size: int) -> Path:
    """A file of ``size`` bytes that is a hole (no disk used)."""
    with open(path, "wb") as f:
        f.truncate(size)
    return path


def test_results_files_and_response_tables_are_bounded_in_size_before_the_read(
    capture, capsys, tmp_path
):
    from lightfield_jax.capture.io import CaptureError
    from lightfield_jax.capture.response import load_response

    results = _sparse(tmp_path / "big.json", 20 << 20)
    line = _refused(capsys, "render", results, "--out", tmp_path / "r", match="20971520 bytes")
    assert "too large for a results file of lightfield-jax fit (at most 16777216" in line
    table = _sparse(tmp_path / "curve.csv", 20 << 20)
    with pytest.raises(CaptureError, match=r"curve.csv: 20971520 bytes is too large for a resp"):
        load_response(table, 1)


def test_an_experiment_sweeping_too_many_cells_is_refused_unless_allowed(capsys, tmp_path):
    from lightfield_jax.app.experiment import load_experiment_config
    from lightfield_jax.app.experiment_config import count_cells

    config = yaml.safe_load((ROOT / "configs" / "coverage.yaml").read_text())
    config.pop("reduced")
    config["seeds"] = 5000  # every medium x 5000 seeds
    path = tmp_path / "big.yaml"
    path.write_text(yaml.safe_dump(config))
    cells = 5000 * len(config["media"])
    assert count_cells(load_experiment_config(path)) == cells
    line = _refused(
        capsys, "experiment", path, "--out", tmp_path / "o", match=f"sweeps about {cells} cells"
    )
    assert "more than the limit of 10000" in line and f"--max-cells {cells}" in line
    assert not (tmp_path / "o").exists()
    # Allowed: counted and said before the work (here refused later, by the script's
    # own check of an unknown key).
    config["unknown_key"] = 1
    path.write_text(yaml.safe_dump(config))
    status, out, err = _run(
        capsys, "experiment", path, "--out", tmp_path / "o", "--max-cells", str(cells)
    )
    assert status == 2 and "unknown_key" in err
    assert out.splitlines()[0] == f"experiment coverage: about {cells} cells of work"
    # The shipped configs stay within the default limit.
    for shipped in (ROOT / "configs").glob("*.yaml"):
        data = yaml.safe_load(shipped.read_text())
        if "experiment" in data:
            assert count_cells(load_experiment_config(shipped)) <= 10_000, shipped


def _dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_stale_temporaries_of_a_killed_command_are_removed_by_the_next(capture, tmp_path):
    """Temporaries named for a process that is gone (kill -9) are removed by the next
    command writing beside them; a running process's are kept (a concurrent writer)."""
    results = _results(capture, tmp_path)
    dead, alive = _dead_pid(), os.getppid()
    stale_folder = tmp_path / f".r.tmp-{dead}-0123abcd"
    stale_folder.mkdir()
    (stale_folder / "bounces.npy").write_bytes(b"half")
    stale_file = tmp_path / f".fig.png.tmp-{dead}-0123abcd.png"
    stale_file.write_bytes(b"half")
    live = tmp_path / f".other.json.tmp-{alive}-0123abcd.json"
    live.write_bytes(b"being written")
    assert main(["render", str(results), "--out", str(tmp_path / "r"), "-q"]) == 0
    assert not stale_folder.exists() and not stale_file.exists()
    assert live.read_bytes() == b"being written"
    assert not [p for p in tmp_path.iterdir() if ".tmp-" in p.name and p != live]


def test_a_stdout_that_cannot_be_written_is_one_line_after_the_files(
    capture, capsys, tmp_path, monkeypatch
):
    import errno
    import io

    class Full(io.StringIO):
        def write(self, text):
            raise OSError(errno.ENOSPC, "No space left on device")

    results = _results(capture, tmp_path)
    monkeypatch.setattr(sys, "stdout", Full())
    status = main(["render", str(results), "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert status == 2 and err.splitlines() == [
        "lightfield-jax: error: standard output: No space left on device: the command "
        "finished (its files written), but its report there is incomplete"
    ]
    assert np.load(tmp_path / "r" / "bounces.npy").shape == (4, H, W)


def test_a_results_file_that_cannot_be_written_has_its_values_printed(
    capture, capsys, tmp_path, monkeypatch
):
    import errno

    import lightfield_jax.files as lfiles

    def full(path, obj, **_):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(lfiles, "atomic_write_json", full)
    out = tmp_path / "r.json"
    status, stdout, err = _run(
        capsys, "fit", capture / "capture.yaml", "--method", "gradient", "--out", out, "-q"
    )
    assert status == 2 and f"{out}: No space left on device" in err, err
    assert f"not written: {out}; the fit:" in stdout
    assert "[Y] gradient: sigma_t " in stdout and "sigma_s " in stdout, stdout
    assert not out.exists()


def test_a_long_output_name_has_a_temporary_that_fits_beside_it(capture, capsys, tmp_path):
    """A valid name of 252 bytes (84 three-byte characters) or with a long extension:
    its temporary's name is cut to the file system's 255 bytes."""
    results = _results(capture, tmp_path)
    folder = tmp_path / ("日" * 84)
    assert main(["render", str(results), "--out", str(folder), "-q"]) == 0
    assert (folder / "bounces.npy").is_file()
    from lightfield_jax.files import atomic_write_json

    long_suffix = tmp_path / ("r." + "a" * 240)
    atomic_write_json(long_suffix, {"a": 1})
    assert json.loads(long_suffix.read_text()) == {"a": 1}
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_a_long_plain_list_is_not_called_an_alias_bomb(capture, capsys):
    _edit(capture, images=[f"shift_{i % P:02d}.exr" for i in range(100_001)])
    line = _refused(
        capsys, "inspect", capture / "capture.yaml", match="holds more than 100000 values"
    )
    assert "alias" not in line


def test_api_images_beyond_float32_bfloat16_and_write_exr_of_an_array():
    import jax

    from lightfield_jax.inverse.data import prepare_data

    images = np.stack([np.full((H, W), 0.2 + 0.1 * (i % 2)) for i in range(P)])
    pattern = lfj.Stripes(6, 3, tuple(range(P)))
    with jax.enable_x64(False):  # float64 images converted to float32, as in a plain session
        with pytest.raises(ValueError, match=r"images: its largest value 3e\+299 lies outsi"):
            prepare_data(images * 1e300, pattern)
        with pytest.raises(ValueError, match=r"images: its largest value 3e-301 lies outsid"):
            prepare_data(images * 1e-300, pattern)
    import ml_dtypes

    # bfloat16 images are taken as float16 ones are.
    for dtype in (np.float16, ml_dtypes.bfloat16):
        prepare_data(images.astype(dtype), pattern)
    with pytest.raises(TypeError, match=r"channels must map each channel's name to a \(height"):
        write_exr("x.exr", images[0])


def test_a_quoted_number_is_refused_like_a_quoted_integer(capture, capsys):
    _edit(capture, black_level="0.01")
    _refused(
        capsys,
        "inspect",
        capture / "capture.yaml",
        match="black_level: must be a number, got '0.01' (str) (a quoted number: remove the",
    )


def test_render_names_the_results_files_keys(capture, capsys, tmp_path):
    for changes, match in (
        ({"model": {"n_theta": 7}}, "channel Y: model.n_theta: must be a multiple of 8"),
        ({"model": {"bounces": 0}}, "channel Y: model.bounces: must be a positive integer"),
        ({"g": 1.0}, "channel Y: g: must satisfy -1 < g < 1, got 1.0"),
        ({"capture_file": "/etc/passwd"}, "capture: /etc/passwd: "),
    ):
        results = _results(capture, tmp_path, **changes)
        line = _refused(capsys, "render", results, "--out", tmp_path / "r", match=match)
        assert line.startswith(f"lightfield-jax: error: {results}: "), line


def test_an_image_whose_header_differs_in_size_is_refused_before_decoding(capture, capsys):
    _png_header(capture / "huge.png", 20000, 20000)
    _edit(capture, images=[f"shift_{i:02d}.exr" for i in range(P)][:2] + ["huge.png"] * 4)
    _refused(
        capsys,
        "inspect",
        capture / "capture.yaml",
        "--max-memory",
        "8G",
        match=f"images[2]: huge.png is 20000x20000 pixels (its header), but images[0] "
        f"(shift_00.exr) is {W}x{H}",
    )


def test_libpng_lines_are_not_printed_raw(capture, tmp_path):
    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    ihdr = struct.pack(">IIBBBBB", W, H, 8, 0, 0, 0, 0)
    (capture / "bad.png").write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", b"\x01" * 64)
        + chunk(b"IEND", b"")
    )
    _edit(capture, images=["bad.png"] + [f"shift_{i:02d}.exr" for i in range(1, P)])
    env = {**os.environ, "PYTHONPATH": str(ROOT), XLA_CACHE_ENV: "off"}
    done = subprocess.run(
        [sys.executable, "-m", "lightfield_jax", "inspect", str(capture / "capture.yaml")],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    lines = done.stderr.splitlines()
    assert done.returncode == 2 and len(lines) == 1, done.stderr
    assert "images[0]: " in lines[0] and "bad.png" in lines[0]


def test_a_full_compilation_cache_is_one_warning():
    import warnings

    from lightfield_jax.inverse.programs import CompilationCacheWarning, repairing_compilation_cache

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with repairing_compilation_cache():
            for i in range(27):
                warnings.warn(
                    f"Error writing persistent compilation cache entry for 'jit_f{i}': "
                    "OSError: [Errno 28] No space left on device",
                    stacklevel=1,
                )
    assert len(caught) == 1 and caught[0].category is CompilationCacheWarning
    assert "could not store 27 compiled program(s) (OSError: [Errno 28] No space" in str(
        caught[0].message
    )


def test_a_staged_output_is_written_without_a_nested_temporary(tmp_path, monkeypatch):
    import lightfield_jax.files as lfiles
    from lightfield_jax.app.outputs import staged_files

    made = []
    real = lfiles.make_file
    monkeypatch.setattr(lfiles, "make_file", lambda p: made.append(p.name) or real(p))
    with staged_files() as write:
        lfiles.atomic_write_json(write(tmp_path / "r.json"), {"a": 1})
    assert json.loads((tmp_path / "r.json").read_text()) == {"a": 1}
    assert made == [], made  # no temporary of the temporary (a name ..r.json.tmp-*.tmp-*)


def test_a_newline_in_an_output_path_is_printed_escaped(capture, capsys, tmp_path):
    results = _results(capture, tmp_path)
    status, out, _ = _run(capsys, "render", results, "--out", tmp_path / "a\nb")
    assert status == 0 and len(out.splitlines()) == 1, out
    assert "a\\nb: " in out


def test_a_hangup_ignored_by_nohup_stays_ignored():
    """SIGHUP ends a command as SIGTERM does, but not one started under nohup."""
    code = (
        "import os, signal\n"
        "from lightfield_jax.app.signals import stop_on_signals\n"
        "with stop_on_signals('x'):\n"
        "    os.kill(os.getpid(), signal.SIGHUP)\n"
        "    import time; time.sleep(0.5)\n"
        "print('still here')\n"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
        preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN),
    )
    assert done.returncode == 0 and done.stdout == "still here\n", done.stderr


# ------------------------------------------------- round four: numbers, addresses, arrays


def test_an_integer_past_pythons_digit_limit_is_one_line_naming_the_file(tmp_path, capsys):
    """Before: 'lightfield-jax: error: Exceeds the limit (4300 digits) for integer string
    conversion ...', Python's own words, naming neither the file nor the line."""
    path = tmp_path / "sim.yaml"
    path.write_text(SIMULATE.replace("period: 6", "period: " + "9" * 5000))
    line = _refused(capsys, "simulate", path, "--out", tmp_path / "o", match=str(path))
    assert "an integer of 5000 digits (line 3)" in line and len(line) < 400
    assert not (tmp_path / "o").exists()


def test_a_memory_size_past_float64_is_one_line(tmp_path, capsys, monkeypatch):
    """Before: --max-memory of 400 digits ended in argparse's traceback of an
    OverflowError (the size as a float is inf), and so did the environment variable."""
    from lightfield_jax.runtime.memory import current_limit

    huge = "9" * 400
    status, _, err = _run(capsys, "inspect", tmp_path / "c.yaml", "--max-memory", huge)
    assert status == 2 and "Traceback" not in err and len(err.splitlines()) == 1, err
    assert "--max-memory: memory size: expected a size such as 8G" in err and len(err) < 300
    monkeypatch.setenv(MAX_MEMORY_ENV, huge + "G")
    with pytest.raises(ValueError, match=rf"^\${MAX_MEMORY_ENV}: memory size: expected"):
        current_limit()


@pytest.mark.parametrize("address", ["nonsense", "http://host:8786"])
def test_a_malformed_scheduler_address_is_named_and_makes_no_folder(
    capture, capsys, tmp_path, address
):
    """Before: 'missing port number in address ...' or 'unknown address scheme ...',
    Dask's words naming no option, and the batch's --out folder was left made, empty."""
    other = tmp_path / "other"
    shutil.copytree(capture, other)
    out = tmp_path / "new" / "res"
    _refused(
        capsys,
        *("fit", capture / "capture.yaml", other / "capture.yaml", "--out", out),
        *("--scheduler", address),
        match=f"--scheduler {address}: not a scheduler's address (",
    )
    assert not (tmp_path / "new").exists()


def test_a_medium_denser_than_the_renders_hold_is_refused(tmp_path, capsys):
    """Before: σt 1e4 per pixel rendered the light within the first pixel 46 % low and
    1e6 rendered it 0, without a word; a slab's σt 1e25 wrote NaN images with exit
    status 0 (its second bounce's σs² beyond float32)."""
    lfj.Medium(100.0, 50.0, 0.4)
    for sigma_t in (1e3, 1e25):
        with pytest.raises(ValueError, match=r"medium.sigma_t: must be at most 100 per pixel"):
            lfj.Medium(sigma_t, sigma_t / 2, 0.4)
    config = yaml.safe_load(SIMULATE)
    config["medium"] = {"sigma_t": 1e25, "sigma_s": 1e24, "g": 0.4}
    config["geometry"] = {"kind": "slab", "thickness": 3.0}
    path = tmp_path / "sim.yaml"
    path.write_text(yaml.safe_dump(config))
    line = _refused(capsys, "simulate", path, "--out", tmp_path / "o", match="at most 100 per")
    assert str(path) in line and not (tmp_path / "o").exists()


def test_a_json_output_named_like_a_yaml_file_is_refused(capture, capsys, tmp_path):
    """Before: ``fit --out sim.yaml`` replaced the user's simulate config with the JSON
    results (exit 0), and ``bench --out``, ``inspect --json`` did alike."""
    config = tmp_path / "sim.yaml"
    config.write_text(SIMULATE)
    yaml_file = capture / "capture.yaml"
    line = _refused(capsys, "fit", yaml_file, "--out", config, match="--out")
    assert "a .yaml name is a capture file's or a config's" in line and "--plot" in line
    _refused(capsys, "inspect", yaml_file, "--json", tmp_path / "i.YML", match="a .yml name")
    _refused(capsys, "bench", "--out", config, match="a .yaml name")
    assert config.read_text() == SIMULATE and sorted(tmp_path.iterdir()) == [capture, config]


def test_a_medium_absorbing_nothing_is_not_blamed_on_the_paper_convention(tmp_path, capsys):
    """Before: σs = σt under phase: normalized (or in a slab) was refused as 'the bounce
    series of the paper phase convention diverges ... Use phase: normalized', the
    convention the user had given, and render warned alike."""
    config = yaml.safe_load(SIMULATE)
    config["medium"] = {"sigma_t": 0.2, "sigma_s": 0.2, "g": 0.4, "phase": "normalized"}
    path = tmp_path / "sim.yaml"
    path.write_text(yaml.safe_dump(config))
    line = _refused(capsys, "simulate", path, "--out", tmp_path / "o", match="rho = albedo = 1")
    assert "absorbs nothing" in line and "paper" not in line
    normalized, grid = lfj.Medium(0.2, 0.2, 0.4, "normalized"), lfj.Grid(16, 16, 8, 1)
    for geometry, medium in [(None, normalized), (lfj.Slab(3.0), lfj.Medium(0.2, 0.2, 0.4))]:
        with pytest.raises(ValueError, match="absorbs nothing") as refused:
            lfj.render(medium, grid, lfj.Full(), geometry=geometry)
        assert "paper" not in str(refused.value)
    with pytest.raises(ValueError, match="tail: rho = albedo = 1.0000 >= 1: .* sigma_s < sigma_t"):
        lfj.render(normalized, grid, lfj.Full(), 3, tail="gmres")


def test_a_decay_fit_of_light_that_does_not_decay_is_not_converged():
    """Before: fit_decay of light growing away from the entry wall (the wrong wall
    named) or flat returned sigma_t 1e-6, its start's floor, said converged, with a
    standard error 30 times smaller than that."""
    decay = np.exp(-0.2 * np.arange(16))[None, :].repeat(8, 0)
    for direct in (decay[:, ::-1].copy(), np.ones_like(decay)):
        fit = lfj.fit_decay(direct)
        assert float(fit.sigma_t) < 2e-6 and not bool(fit.converged)
    fit = lfj.fit_decay(decay)
    assert float(fit.sigma_t) == pytest.approx(0.2, rel=1e-5) and bool(fit.converged)


def test_fit_images_refuses_phases_the_images_contradict(capture):
    """Before: fit_images with the phases declared one shift off (1, ..., 5, 0) fitted
    sigma_s 27 % high and said nothing; a capture file's phases were already checked."""
    images = np.stack([read_image(capture / f"shift_{i:02d}.exr").pixels[..., 0] for i in range(P)])
    for phases, given in [((1, 2, 3, 4, 5, 0), images), ((0, 1, 2), images[::2])]:
        with pytest.raises(ValueError, match=r"^pattern.phases: \[.*\] contradict the images"):
            lfj.fit_images(given, lfj.Stripes(phases=phases))
    from lightfield_jax.capture.auto import pattern_contradiction

    assert pattern_contradiction(images, lfj.Stripes()) is None
    assert pattern_contradiction(images[::2], lfj.Stripes(phases=(0, 2, 4))) is None


def test_fit_images_refuses_a_heading_or_wall_the_images_contradict(capture):
    """Before: fit_images of 0 deg stripes declared at 30 deg fitted sigma_t 15 % low and
    said nothing (a capture file's heading was already checked), and images transposed
    (light entering the top, declared left) were taken with a decay start of sigma_t 0.
    A mask per value does
    not make a right heading look wrong: values clipped at a tenth of the peak, zeroed
    where masked, measured -11.7 deg on a 48x32 render with every line counted."""
    from lightfield_jax.capture.auto import pattern_contradiction

    images = np.stack([read_image(capture / f"shift_{i:02d}.exr").pixels[..., 0] for i in range(P)])
    with pytest.raises(ValueError, match=r"^pattern.direction_deg: 30 contradicts the images"):
        lfj.fit_images(images, lfj.Stripes(direction_deg=30))
    with pytest.raises(ValueError, match=r"^pattern.entry: left contradicts .* the top wall"):
        lfj.fit_images(np.swapaxes(images, 1, 2), lfj.Stripes())
    clip = 0.1 * images.max()
    valid = images < clip
    zeroed = np.where(valid, images, 0.0)
    assert pattern_contradiction(zeroed, lfj.Stripes(), valid) is None
    assert pattern_contradiction(zeroed, lfj.Stripes(direction_deg=30), valid)[0] == (
        "pattern.direction_deg"
    )
    for bad, match in [
        (valid[0, :3], "must have the images'"),
        (1 * valid, "must be an array of booleans"),
    ]:
        with pytest.raises(ValueError, match=f"^detect_geometry: valid: {match}"):
            lfj.detect_geometry(zeroed, valid=bad)


def test_fit_options_kept_that_is_no_pairs_is_named():
    """Before: FitOptions(kept=5) raised Python's "'int' object is not iterable"."""
    for bad in (5, "ab", [("n_theta", 3)], [("g_grid",)]):
        with pytest.raises(TypeError, match=r"^FitOptions: kept: must be \(key, value\) pairs"):
            lfj.FitOptions(kept=bad)
    assert lfj.FitOptions(kept=(("g_grid", 21),)).replace(method="grid").method.g_values == 21


def test_a_frame_without_a_value_above_zero_among_lit_ones_is_refused(capture, capsys):
    """Before: a float shift with an offset of 10 subtracted (every value negative) was
    inspected without a word and fitted for a minute (gain -387, not converged)."""
    pixels = read_image(capture / "shift_02.exr").pixels[..., 0]
    for bad in (pixels - 10.0, -pixels):
        write_exr(capture / "shift_02.exr", {"Y": bad})
        _refused(
            capsys, "inspect", capture / "capture.yaml",
            match="images: shift_02.exr: no pixel value is above 0 (the largest is -",
        )  # fmt: skip


def test_a_shift_holding_other_light_than_the_others_is_refused(capture, capsys):
    """Before: one shift taken at 10 times the exposure, or with 0.3 added, was inspected
    without a word (the fit takes every shift at one exposure); fit_images took it too."""
    pixels = read_image(capture / "shift_02.exr").pixels[..., 0]
    for bad, ratio in [(10.0 * pixels, "11.3"), (pixels + 0.3, "5.47")]:
        write_exr(capture / "shift_02.exr", {"Y": bad})
        _refused(
            capsys, "inspect", capture / "capture.yaml",
            match=f"images: shift_02.exr holds {ratio} times the light of the shifts' median",
        )  # fmt: skip
    write_exr(capture / "shift_02.exr", {"Y": pixels})
    images = np.stack([read_image(capture / f"shift_{i:02d}.exr").pixels[..., 0] for i in range(P)])
    write_exr(capture / "mean.exr", {"Y": images.mean(axis=0)})  # float32 sums: one line
    _edit(capture, dark_frame="mean.exr")
    _refused(
        capsys,
        "inspect",
        capture / "capture.yaml",
        match="holds no light: its values summed over the medium are at or below 0, the "
        "shifts' median above",
    )
    images[4] *= 2.0
    with pytest.raises(ValueError, match=r"^images: images\[4\] holds 2 times the light"):
        lfj.fit_images(images, lfj.Stripes())
    from lightfield_jax.capture.auto import light_contradiction

    images[4] /= 2.0
    assert light_contradiction(images, 0, lfj.Stripes()) is None  # 1 % apart


@pytest.mark.parametrize(
    ("old", "new", "match"),
    [
        (
            "medium_roi: auto",
            "medium_roi: [02, 010, 30, 22]",
            "010 (line 13) is read by YAML 1.1 as the octal number 8",
        ),
        ("direction_deg: 0.0", "direction_deg: 1:30", "1:30 (line 7) is read by YAML 1.1 as a"),
    ],
)
def test_numbers_yaml_reads_otherwise_than_written_are_refused(capture, capsys, old, new, match):
    """Before: YAML 1.1 read ``010`` as the octal 8 (a ROI [02, 010, 30, 22] cropped two
    rows off, without a word) and ``1:30`` as 90 in base 60; ``07`` is 7 either way."""
    path = capture / "capture.yaml"
    path.write_text(path.read_text() + "medium_roi: auto\n")
    path.write_text(path.read_text().replace(old, new))
    _refused(capsys, "inspect", path, match=match)
    path.write_text(path.read_text().replace(new, old.replace("auto", "[00, 07, 32, 24]")))
    assert _run(capsys, "inspect", path)[0] == 0


@pytest.mark.parametrize("key", ["dark_frame", "flat_field", "white_frame"])
def test_a_stripe_image_listed_as_a_calibration_frame_is_refused(capture, capsys, key):
    """Before: a copy of a stripe image as the dark frame was inspected without a word
    and fitted for a minute (albedo at 0, not converged); as the flat field, the stripe
    image it divided was blamed ("shift_00.exr shows no stripes")."""
    shutil.copy(capture / "shift_00.exr", capture / "frame.exr")
    _edit(capture, **{key: "frame.exr"})
    _refused(
        capsys, "inspect", capture / "capture.yaml",
        match=f"{key}: frame.exr shows the stripes of period 6 (1 times the stripe images'",
    )  # fmt: skip


def test_a_truncated_exr_is_named_once(capture, capsys):
    """Before: a header cut short was said as OpenEXR's "EXR Error (PATH): ..." three
    times after the file's name (a 380-character line)."""
    path = capture / "shift_01.exr"
    path.write_bytes(path.read_bytes()[:100])
    line = _refused(capsys, "inspect", capture / "capture.yaml", match="shift_01.exr: cannot read")
    assert line.count(str(path)) == 1 and line.count("EXR_ERR_READ_IO") == 1, line


def test_phases_leaving_rows_unseparated_are_a_note_not_a_dark_capture(capture, capsys):
    """Before: two shifts (phases 0, 1 of period 6, lit 3) made inspect warn that the
    direct light's SNR never reaches 10, "too dark or too noisy to fit", exit 1, though
    the joint fit recovers the milk from them (sigma_t -0.2 %, sigma_s +2 %): the
    separation leaves rows never lit and never dark, which its SNR measure reads as noise."""
    pattern = yaml.safe_load((capture / "capture.yaml").read_text())["pattern"]
    path = _edit(
        capture, images=["shift_00.exr", "shift_01.exr"], pattern={**pattern, "phases": [0, 1]}
    )
    status, out, err = _run(capsys, "inspect", path)
    assert status == 0 and "too dark" not in err, (status, err)
    assert "pattern.phases [0, 1] leave rows 3, 4 never lit and rows 0, 1 never dark" in out


def test_a_half_float_exr_among_float_ones_is_read(capture, capsys):
    """Before: one shift saved as 16-bit half floats among 32-bit float EXRs was refused
    as "integer samples are scaled by their type's maximum, so the images would not
    share units": float samples of any precision hold one unit."""
    import OpenImageIO as oiio

    pixels = read_image(capture / "shift_03.exr").pixels
    out = oiio.ImageOutput.create(str(capture / "shift_03.exr"))
    spec = oiio.ImageSpec(W, H, 1, "half")
    spec.channelnames = ("Y",)
    assert out.open(str(capture / "shift_03.exr"), spec) and out.write_image(pixels)
    out.close()
    assert read_image(capture / "shift_03.exr").sample_type == "half"
    status, out_text, err = _run(capsys, "inspect", capture / "capture.yaml")
    assert status == 0, err
