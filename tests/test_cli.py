"""The command line: simulate's files, bench, errors (exit 2, one line, no output)."""

import errno
import io
import json
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import lightfield_jax.forward.simulate as simulate_module
from lightfield_jax import phase_function
from lightfield_jax.app.cli import main
from lightfield_jax.capture.io import read_image
from lightfield_jax.runtime.progress import progress

GRID = "grid: {width: 24, height: 16, n_theta: 16, refine: 1}\n"
MEDIUM = "medium: {sigma_t: 0.2, sigma_s: 0.1, g: 0.3, phase: paper}\n"
BEAM = GRID + MEDIUM + "illumination: {kind: beam, x: 0.0, y: 8.5}\nbounces: 3\ngain: 2.0\n"
STRIPES = (
    GRID
    + MEDIUM
    + "illumination: {kind: stripes, period: 6, lit: 3}\nbounces: 3\n"
    + "black_level: 0.05\ndark_level: 0.01\nnoise: {photons: 1.0e5, read: 0.001, seed: 1}\n"
)
H, W, K, N_THETA, P = 16, 24, 3, 16, 6


def _config(tmp_path, text, name="sim.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def _run(capsys, *argv):
    status = main(list(argv))
    out, err = capsys.readouterr()
    return status, out, err


def _names(folder):
    return {p.name for p in Path(folder).iterdir()}


def _no_staging_left(folder):
    return not [p for p in Path(folder).iterdir() if ".tmp-" in p.name]


def test_simulate_beam_writes_every_file(tmp_path, capsys):
    out = tmp_path / "beam"
    status, stdout, err = _run(
        capsys, "simulate", _config(tmp_path, BEAM), "--out", str(out), "--lightfield"
    )
    assert status == 0, err
    assert err == ""
    assert "K = 3 bounces" in stdout and "converges" in stdout
    expected = {"bounces.npy", "bounces.exr", "total.exr", "lightfield.npy", "metadata.json"}
    assert _names(out) == expected
    assert _no_staging_left(tmp_path)

    bounces = np.load(out / "bounces.npy")
    assert bounces.shape == (K, H, W) and bounces.dtype == np.float32
    exr = read_image(out / "bounces.exr")
    assert exr.channel_names == ("I1", "I2", "I3")
    np.testing.assert_array_equal(np.moveaxis(exr.pixels, -1, 0), bounces)
    total = read_image(out / "total.exr")
    assert total.channel_names == ("Y",)
    np.testing.assert_allclose(total.pixels[..., 0], bounces.sum(0), rtol=1e-6)

    # Light field L_0..L_K; the camera sees I_k = σs p(π/2) Σ_θ L_{k-1} Δθ (gain in both).
    fields = np.load(out / "lightfield.npy")
    assert fields.shape == (K + 1, H, W, N_THETA) and fields.dtype == np.float32
    camera = 0.1 * float(phase_function(math.pi / 2, 0.3)) * (2 * math.pi / N_THETA)
    np.testing.assert_allclose(camera * fields[:K].sum(-1), bounces, rtol=1e-4, atol=1e-9)
    assert bounces[0].max() > 0 and np.all(bounces >= 0)

    meta = json.loads((out / "metadata.json").read_text())
    assert meta["config"]["gain"] == 2.0 and meta["gain"] == 2.0
    assert (meta["bounces"], meta["n_theta"], meta["refine"]) == (K, N_THETA, 1)
    assert meta["converges"] is True and 0 < meta["rho"] < 1
    assert set(meta["timings"]) == {"compile_s", "run_s", "total_s"}
    assert {"python", "jax", "equinox", "optimistix", "numpy", "lightfield_jax"} <= set(
        meta["versions"]
    )
    assert meta["date"] and meta["warnings"] == []
    assert set(meta["files"]) == expected


def test_simulate_stripes_writes_shifts_capture_and_dark(tmp_path, capsys):
    out = tmp_path / "stripes"
    config = _config(tmp_path, STRIPES)
    status, _, err = _run(capsys, "simulate", config, "--out", str(out), "--lightfield")
    assert status == 0, err
    shifts = {f"shift_{i:02d}.exr" for i in range(P)}
    per_bounce = {f"bounces_{i:02d}.exr" for i in range(P)}
    common = {"bounces.npy", "lightfield.npy", "metadata.json", "capture.yaml", "dark.exr"}
    assert _names(out) == shifts | per_bounce | common
    # Its capture is fitted in the convention it was simulated in, whatever the default.
    assert "\nfit: {phase: paper}\n" in (out / "capture.yaml").read_text()

    bounces = np.load(out / "bounces.npy")
    assert bounces.shape == (P, K, H, W)
    fields = np.load(out / "lightfield.npy")
    assert fields.shape == (P, K + 1, H, W, N_THETA)
    for i in range(P):
        exr = read_image(out / f"bounces_{i:02d}.exr")
        assert exr.channel_names == ("I1", "I2", "I3")
        np.testing.assert_array_equal(np.moveaxis(exr.pixels, -1, 0), bounces[i])
        shot = read_image(out / f"shift_{i:02d}.exr")
        assert shot.channel_names == ("Y",) and shot.pixels.shape == (H, W, 1)
        # Noisy: the captured image is Σ_k I_k + dark level, within a few noise sigmas.
        np.testing.assert_allclose(shot.pixels[..., 0], bounces[i].sum(0) + 0.01, atol=0.01)
    dark = read_image(out / "dark.exr").pixels
    assert dark.shape == (H, W, 1) and abs(dark.mean() - 0.01) < 1e-3 and dark.std() > 0

    meta = json.loads((out / "metadata.json").read_text())
    assert meta["full_illumination"] == "sum of shifts / lit"
    assert meta["noise"] == {"photons": 1e5, "read": 0.001, "seed": 1}
    assert meta["black_level"] == 0.05 and meta["dark_level"] == 0.01

    # The same seed gives the same noise.
    again = tmp_path / "again"
    assert main(["simulate", config, "--out", str(again), "-q"]) == 0
    assert capsys.readouterr().out == ""
    np.testing.assert_array_equal(
        read_image(again / "shift_03.exr").pixels, read_image(out / "shift_03.exr").pixels
    )
    assert "lightfield.npy" not in _names(again)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (None, "missing.yaml: file not found"),
        (BEAM + "colour: red\n", "colour: unknown key"),
        (BEAM.replace("sigma_s: 0.1", "sigma_s: 0.5"), "medium.sigma_s: must satisfy"),
        (BEAM + "black_level: 0.1\n", "black_level: applies only to illumination kind stripes"),
        (BEAM + "noise: {photons: -3}\n", "noise.photons: must be > 0, got -3"),
        (BEAM + "noise: {}\n", "noise: give photons and/or read"),
        (BEAM + "noise: {read: 0.1, sed: 2}\n", "noise.sed: unknown key (did you mean 'seed'?)"),
        (BEAM + "dark_level: -0.1\n", "dark_level: must be >= 0"),
        (BEAM.replace("gain: 2.0", "gain: 0"), "gain: must be > 0, got 0"),
        ("grid: {width: 24\n", "invalid YAML"),
    ],
)
def test_bad_config_exits_2_with_one_line_and_no_output(tmp_path, capsys, text, message):
    config = str(tmp_path / "missing.yaml") if text is None else _config(tmp_path, text)
    out = tmp_path / "out"
    status, stdout, err = _run(capsys, "simulate", config, "--out", str(out))
    assert status == 2
    assert stdout == ""
    assert err.startswith("lightfield-jax: error: ") and err.count("\n") == 1, err
    assert message in err
    assert "Traceback" not in err
    assert not out.exists()
    assert _no_staging_left(tmp_path)


def test_failure_while_writing_leaves_no_folder(tmp_path, capsys, monkeypatch):
    def write_then_fail(sim, folder, **_):
        (Path(folder) / "bounces.npy").write_bytes(b"partial")
        raise ValueError("disk said no")

    monkeypatch.setattr(simulate_module, "write_simulation", write_then_fail)
    out = tmp_path / "out"
    status, _, err = _run(capsys, "simulate", _config(tmp_path, BEAM), "--out", str(out))
    assert status == 2 and err == "lightfield-jax: error: disk said no\n"
    assert not out.exists() and _no_staging_left(tmp_path)


@pytest.mark.parametrize(
    ("failure", "message"),
    [
        (OSError(errno.ENOSPC, "No space left on device"), "No space left on device"),
        # numpy's tofile on a full disk, with no errno
        (OSError("51840 requested and 16352 written"), "write failed (51840 requested"),
    ],
)
def test_a_full_disk_is_one_line_naming_the_output(tmp_path, capsys, monkeypatch, failure, message):
    """Before: a traceback (``OSError: 51840 requested and 16352 written``)."""

    def write_then_fail(sim, folder, **_):
        (Path(folder) / "bounces.npy").write_bytes(b"partial")
        raise failure

    monkeypatch.setattr(simulate_module, "write_simulation", write_then_fail)
    out = tmp_path / "out"
    status, _, err = _run(capsys, "simulate", _config(tmp_path, BEAM), "--out", str(out))
    assert status == 2 and err.startswith(f"lightfield-jax: error: {out}: {message}"), err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists() and _no_staging_left(tmp_path)


def test_a_full_disk_while_staging_files_names_the_file_and_keeps_the_old_one(tmp_path):
    from lightfield_jax.app.outputs import staged_files

    old = tmp_path / "r.json"
    old.write_text("old")
    with pytest.raises(OSError) as e, staged_files() as write:
        write(tmp_path / "fig.png").write_bytes(b"fig")
        write(old).write_bytes(b"part")
        raise OSError(errno.ENOSPC, "No space left on device")
    assert e.value.filename == str(old) and e.value.errno == errno.ENOSPC
    assert old.read_text() == "old" and sorted(os.listdir(tmp_path)) == ["r.json"]


def test_out_is_a_file(tmp_path, capsys):
    out = tmp_path / "taken"
    out.write_text("x")
    status, _, err = _run(capsys, "simulate", _config(tmp_path, BEAM), "--out", str(out))
    assert status == 2 and "taken: exists and is not a directory" in err
    assert out.read_text() == "x"


def test_divergent_series_warns_and_is_recorded(tmp_path, capsys):
    text = BEAM.replace("sigma_s: 0.1, g: 0.3", "sigma_s: 0.19, g: 0.9")
    out = tmp_path / "out"
    status, stdout, err = _run(capsys, "simulate", _config(tmp_path, text), "--out", str(out))
    assert status == 0
    assert err.startswith("lightfield-jax: warning: rho = albedo*A(g)") and err.count("\n") == 1
    assert "DOES NOT CONVERGE" in stdout
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["converges"] is False and meta["rho"] > 1
    assert meta["warnings"][0].startswith("rho = albedo*A(g)")


def test_bench_tiny(tmp_path, capsys):
    out = tmp_path / "bench.json"
    status, stdout, err = _run(
        capsys, "bench", "--sizes", "16x16x8", "--repeats", "1", "--out", str(out)
    )
    assert status == 0, err
    assert stdout.startswith("16x16x8: compile") and f"wrote {out}" in stdout
    result = json.loads(out.read_text())
    assert [r["grid"] for r in result["results"]] == [[16, 16, 8]]
    assert result["results"][0]["per_bounce_s"] is not None


@pytest.mark.slow  # about 10-20 s: run by make test-slow
def test_bench_fits_runs_each_fit_in_a_fresh_process():
    from lightfield_jax.app.bench import bench_fits

    config = {
        "grid": {"width": 32, "height": 24, "n_theta": 16},
        "medium": {"sigma_t": 0.2051, "sigma_s": 0.0366, "g": 0.4, "phase": "paper"},
        "illumination": {"kind": "stripes", "period": 6, "lit": 3, "shifts": 6},
        "bounces": 4,
    }
    lines = []
    result = bench_fits(config, methods=("gradient",), repeats=1, progress=lines.append)
    (row,) = result["results"]
    assert row["method"] == "gradient" and row["converged"]
    # a fresh process compiles; the same fit again in it does not
    assert row["cold_compile_s"] > 0 and row["runs"][0]["warm"]["compile"] == 0.0
    assert row["warm_s"] < row["cold_s"]
    assert len(lines) == 1 and lines[0].startswith("gradient  cold")


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["bench", "--fits", "--slab"], "--fits and --slab are separate benchmarks"),
        (["bench", "--fits", "--methods", "grid,fly"], "--methods: must be distinct names"),
        (["bench", "--sizes", "16x16"], "argument --sizes: '16x16' is not WIDTHxHEIGHTxN_THETA"),
        (["bench", "--sizes", "16x16x12"], "grid.n_theta: must be a multiple of 8"),
        (["bench", "--repeats", "0"], "argument --repeats: must be a positive integer"),
        ([], "the following arguments are required: COMMAND"),
        (["fly"], "invalid choice: 'fly'"),
        (["simulate", "x.yaml"], "the following arguments are required: --out"),
    ],
)
def test_command_line_syntax_errors(capsys, argv, message):
    status, stdout, err = _run(capsys, *argv)
    assert status == 2 and stdout == ""
    assert err.count("\n") == 1 and message in err and err.startswith("lightfield-jax")


def test_help_describes_the_files(capsys):
    status, stdout, _ = _run(capsys, "simulate", "--help")
    assert status == 0
    for name in ("bounces.npy", "shift_XX.exr", "capture.yaml", "lightfield.npy"):
        assert name in stdout


@pytest.mark.parametrize(
    "command", ["simulate", "bench", "fit", "demo", "pattern", "inspect", "render", "experiment"]
)
def test_every_help_runs_and_its_text_starts_at_the_margin(capsys, command):
    """Before: each description was the raw docstring, so every line after the first was
    printed indented by four spaces (the file tables by six)."""
    status, stdout, err = _run(capsys, command, "--help")
    assert status == 0 and err == ""
    description = stdout.split("\n\n")[1]
    assert not description.startswith(" ") and "\n    " not in description, description


def test_progress_display_names_stages():
    stream = io.StringIO()
    with progress("simulate", 2, enabled=True, delay=0.0, file=stream) as stage:
        stage("render")
        stage("write files")
    text = stream.getvalue()
    assert "simulate: render" in text and "simulate: write files (1/2 done)" in text
    silent = io.StringIO()
    with progress("simulate", mode="none", file=silent) as stage:
        stage("render")
    assert silent.getvalue() == ""


def test_progress_without_a_terminal_is_one_plain_line_per_stage():
    """Where stderr is a log file, a redrawn bar is unreadable and was not shown at all:
    a fit that ran for 108 minutes printed nothing."""
    log = io.StringIO()  # not a terminal
    with progress("fit (joint)", prefix="lightfield-jax: ", file=log) as stage:
        stage("scan")
        stage("[R] solve")
    lines = log.getvalue().splitlines()
    assert len(lines) == 3 and "\r" not in log.getvalue()
    assert re.fullmatch(r"lightfield-jax: fit \(joint\): scan \[\d+\.\d s\]", lines[0])
    assert lines[1].startswith("lightfield-jax: fit (joint): [R] solve [")
    assert lines[2].startswith("lightfield-jax: fit (joint): done [")


@pytest.mark.parametrize(
    ("flags", "env", "lines"),
    [((), None, True), (("--progress", "lines"), "none", True), (("--quiet",), None, False),
     (("--progress", "none"), None, False), (("--quiet", "--progress", "lines"), None, True)],
)  # fmt: skip
def test_commands_choose_their_progress_display(tmp_path, capsys, monkeypatch, flags, env, lines):
    if env is None:
        monkeypatch.delenv("LIGHTFIELD_JAX_PROGRESS", raising=False)
    else:
        monkeypatch.setenv("LIGHTFIELD_JAX_PROGRESS", env)
    status, _, err = _run(
        capsys, "simulate", _config(tmp_path, BEAM), "--out", str(tmp_path / "o"), *flags
    )
    assert status == 0, err
    said = [line for line in err.splitlines() if line.startswith("lightfield-jax: simulate: ")]
    assert bool(said) == lines, err
    if lines:
        assert said[-1].startswith("lightfield-jax: simulate: done [") and len(said) >= 2


def test_a_progress_setting_that_is_no_mode_is_refused(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("LIGHTFIELD_JAX_PROGRESS", "loud")
    status, _, err = _run(capsys, "simulate", _config(tmp_path, BEAM), "--out", str(tmp_path / "o"))
    assert status == 2 and "LIGHTFIELD_JAX_PROGRESS: must be one of auto, bar, lines, none" in err


def test_console_script_is_installed(tmp_path):
    script = shutil.which("lightfield-jax", path=os.path.dirname(sys.executable))
    assert script is not None
    config = _config(tmp_path, BEAM + "bounces_typo: 3\n")
    run = subprocess.run(
        [script, "simulate", config, "--out", str(tmp_path / "out")],
        capture_output=True,
        text=True,
        check=False,
    )
    assert run.returncode == 2 and run.stdout == ""
    assert run.stderr.startswith("lightfield-jax: error: ") and run.stderr.count("\n") == 1
    assert "bounces_typo: unknown key (did you mean 'bounces'?)" in run.stderr


def test_cli_modules_do_not_load_image_libraries():
    code = (
        "import sys, lightfield_jax, lightfield_jax.app.cli, lightfield_jax.forward.simulate, "
        "lightfield_jax.capture.capture; "
        "bad = {'OpenImageIO', 'matplotlib', 'cv2', 'tqdm'} & set(sys.modules); "
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_matplotlibs_own_warnings_are_not_shown_as_the_packages(capsys):
    """A figure's layout warning printed as "lightfield-jax: warning: ..."."""
    import warnings

    from lightfield_jax.app.cli import warnings_to_stderr

    collected = []
    with warnings_to_stderr(collected), warnings.catch_warnings():
        warnings.simplefilter("always")
        where = str(Path("site-packages") / "matplotlib" / "layout_engine.py")
        warnings.warn_explicit("constrained_layout not applied", UserWarning, where, 1)
        warnings.warn_explicit("a note of ours", UserWarning, "lightfield_jax/x.py", 1)
    err = capsys.readouterr().err
    assert "lightfield-jax: warning: constrained_layout" not in err
    assert "lightfield-jax: warning: a note of ours" in err and collected == ["a note of ours"]
