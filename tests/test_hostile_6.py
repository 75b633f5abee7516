"""Hostile inputs, round six: each case is refused in one line naming what is wrong,
before the work (or, where the input is usable, taken as a user would expect), and
leaves every file as it was. The earlier rounds: tests/test_hostile.py."""

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from cli_support import SIMULATE
from cli_support import refused as _refused
from cli_support import run as _run

import lightfield_jax as lfj
from lightfield_jax.app.arguments import XLA_CACHE_ENV
from lightfield_jax.app.cli import main
from lightfield_jax.capture.image_write import write_exr
from lightfield_jax.capture.io import read_image
from lightfield_jax.capture.paths import capture_files
from lightfield_jax.runtime.memory import MAX_MEMORY_ENV


@pytest.fixture(autouse=True)
def _environment(monkeypatch):
    monkeypatch.setenv(XLA_CACHE_ENV, "off")
    monkeypatch.delenv(MAX_MEMORY_ENV, raising=False)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """The milk as a 32x24 six-shift stripe capture with a dark frame."""
    folder = tmp_path_factory.mktemp("hostile6")
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
    data.update(changes)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


# ------------------------------------------------------------------- the three leftovers


def test_a_linked_capture_file_reads_the_images_beside_the_file_it_links(capture, capsys, tmp_path):
    """Before: a capture.yaml linked from another folder looked for its images in the
    link's folder ("other/shift_00.exr: file not found"), though README says image paths
    are relative to the file, and the file was written beside them."""
    other = tmp_path / "other"
    other.mkdir()
    link = other / "capture.yaml"
    link.symlink_to(os.path.relpath(capture / "capture.yaml", other))
    status, out, err = _run(capsys, "inspect", link)
    assert status == 0, err
    assert lfj.load_capture(link).image_paths[0].resolve() == capture / "shift_00.exr"
    # The inputs an output must not replace are the linked capture's.
    assert capture.resolve() / "shift_00.exr" in [p.resolve() for p in capture_files(link)]
    # A link whose own folder holds another file of a listed name: which is meant
    # cannot be told (a template linked into several captures' folders).
    shutil.copy(capture / "shift_01.exr", other / "shift_03.exr")
    before = _snapshot(other)
    line = _refused(capsys, "inspect", link, match=f"{link}: a link to ")
    assert f"the link's folder {other} holds another shift_03.exr" in line
    assert _snapshot(other) == before
    # The same file under both names (a link to it) is one file: taken.
    (other / "shift_03.exr").unlink()
    (other / "shift_03.exr").symlink_to(capture / "shift_03.exr")
    assert _run(capsys, "inspect", link)[0] == 0
    # A link beside its target reads the same folder, as before.
    (capture / "alias.yaml").symlink_to("capture.yaml")
    assert _run(capsys, "inspect", capture / "alias.yaml")[0] == 0


def _grey_as_rgb(capture: Path, dark=None) -> None:
    """Each shift and the dark frame rewritten as RGB with three equal channels."""
    data = yaml.safe_load((capture / "capture.yaml").read_text())
    for name in [*data["images"], data["dark_frame"]]:
        y = read_image(capture / name).pixels[..., 0]
        planes = (y, y, y) if name != data["dark_frame"] or dark is None else dark(y)
        write_exr(capture / name, dict(zip("RGB", planes, strict=True)))


def test_a_grey_image_saved_as_rgb_is_one_channel_with_a_note(capture, capsys):
    """Before: a grey capture saved as RGB (three equal channels) loaded as R, G, B and
    was fitted three times, three times the time for three identical answers."""
    _grey_as_rgb(capture)
    loaded = lfj.load_capture(capture / "capture.yaml")
    assert loaded.channel_names == ("Y",) and loaded.images.shape[-1] == 1
    assert loaded.mask.shape[-1] == 1 and loaded.sample_mask.shape[-1] == 1
    assert any(
        "channels R, G, B hold the same values in every image and calibration frame" in n
        and "loaded as one channel Y" in n
        for n in loaded.notes
    ), loaded.notes
    status, out, err = _run(capsys, "inspect", capture / "capture.yaml")
    assert status == 0 and "loaded as one channel Y" in out, (out, err)
    # A channel chosen by the file is that channel, by its name.
    _edit(capture, channel="G")
    assert lfj.load_capture(capture / "capture.yaml").channel_names == ("G",)
    # Values per channel in the file keep the channels, with a note.
    data = yaml.safe_load((capture / "capture.yaml").read_text())
    truth = {k: [v] * 3 if k != "phase" else v for k, v in data["truth"].items()}
    _edit(capture, channel="all", truth=truth)
    kept = lfj.load_capture(capture / "capture.yaml")
    assert kept.channel_names == ("R", "G", "B")
    assert any("gives values per channel: each is fitted" in n for n in kept.notes)


def test_a_colour_dark_frame_keeps_equal_image_channels_apart(capture):
    """Equal channels in the images, but a dark frame that differs per channel: the
    calibrated channels differ, so they stay three."""
    _grey_as_rgb(capture, dark=lambda y: (y, 1.5 * y, 0.5 * y))
    loaded = lfj.load_capture(capture / "capture.yaml")
    assert loaded.channel_names == ("R", "G", "B")
    assert not any("hold the same values" in n for n in loaded.notes)


@pytest.mark.parametrize("method", ["gradient", "grid"])
def test_two_step_fits_name_the_rows_their_phases_leave_unseparated(
    capture, capsys, tmp_path, method
):
    """Before: phases [0, 1] of period 6 ran the two-step fit to a bound (4-10 s) and
    ended "sigma_s is not identifiable from this capture" without naming the cause: the
    separation they fit needs each row lit in one shift and dark in another."""
    pattern = yaml.safe_load((capture / "capture.yaml").read_text())["pattern"]
    path = _edit(
        capture, images=["shift_00.exr", "shift_01.exr"], pattern={**pattern, "phases": [0, 1]}
    )
    out = tmp_path / "results.json"
    line = _refused(
        capsys, "fit", path, "--method", method, "--out", out,
        match=f"method {method}: the stripes' phases [0, 1] (period 6, lit 3) leave rows 3, 4 "
        "never lit and rows 0, 1 never dark",
    )  # fmt: skip
    assert "use the joint method" in line and not out.exists()
    # The API alike; a split given instead of the separation needs none.
    from lightfield_jax.inverse.fit import check_separable

    images = np.stack([read_image(capture / f"shift_0{i}.exr").pixels[..., 0] for i in (0, 1)])
    stripes = lfj.Stripes(phases=(0, 1))
    with pytest.raises(ValueError, match=f"^method {method}: the stripes' phases"):
        lfj.fit_images(images, stripes, method=method)
    options = lfj.FitOptions(method)
    assert check_separable(options, stripes, (images[0], images[1])) is None
    assert check_separable(lfj.FitOptions("joint"), stripes, None) is None


# ------------------------------------------------------------------------ new inputs


def _rgb(capture: Path, order=lambda i: "RGB", dark="RGB") -> None:
    """Each shift as R, G, B of 1, 0.7, 0.4 times its grey (channels in ``order(i)``), the
    dark frame as R, G, B of 1, 2, 3 times its grey (in ``dark``)."""
    data = yaml.safe_load((capture / "capture.yaml").read_text())
    for i, name in enumerate(data["images"]):
        y = read_image(capture / name).pixels[..., 0]
        planes = {"R": y, "G": 0.7 * y, "B": 0.4 * y}
        write_exr(capture / name, {c: planes[c] for c in order(i)})
    y = read_image(capture / "dark.exr").pixels[..., 0]
    planes = {"R": y, "G": 2 * y, "B": 3 * y}
    write_exr(capture / "dark.exr", {c: planes[c] for c in dark})


def test_channels_are_matched_by_name_across_files(capture, capsys):
    """Before: one shift saved B, G, R among R, G, B files (or a dark frame so saved) was
    taken by position: its blue was fitted as the others' red, and a dark frame's blue
    subtracted from the red, without a word; files of other channel names alike."""
    _rgb(capture)
    plain = lfj.load_capture(capture / "capture.yaml")
    _rgb(capture, order=lambda i: "BGR" if i == 2 else "RGB", dark="BGR")
    assert read_image(capture / "shift_02.exr").channel_names == ("B", "G", "R")
    assert read_image(capture / "dark.exr").channel_names == ("B", "G", "R")
    swapped = lfj.load_capture(capture / "capture.yaml")
    assert swapped.channel_names == ("R", "G", "B")
    np.testing.assert_array_equal(swapped.images, plain.images)
    # channel: an index picks the same position of each file: by name, it is refused.
    _edit(capture, channel=0)
    _refused(
        capsys, "inspect", capture / "capture.yaml",
        match="images[2]: shift_02.exr has the channels B, but images[0] (shift_00.exr) has R: "
        "channels are matched by name",
    )  # fmt: skip
    _edit(capture, channel="R")
    assert lfj.load_capture(capture / "capture.yaml").images.shape[-1] == 1
    # Channels of other names: which is which cannot be told.
    y = read_image(capture / "shift_04.exr").channel("R")
    write_exr(capture / "shift_04.exr", {"X": y, "Y": y, "Z": y})
    _edit(capture, channel="all")
    _refused(
        capsys, "inspect", capture / "capture.yaml",
        match="images[4]: shift_04.exr has the channels X, Y, Z, but images[0] (shift_00.exr) "
        "has R, G, B",
    )  # fmt: skip


def test_a_calibration_frame_gives_the_channel_an_index_chose_in_the_images(capture):
    """Before: with channel: 0, a dark frame saved B, G, R among R, G, B images had its
    blue subtracted from the images' red (each file's position 0) without a word, and a
    grey dark frame was refused for channel: 2 ("channel index 2 out of range")."""
    _rgb(capture, dark="BGR")
    for index, name in enumerate("RGB"):
        _edit(capture, channel=name)
        by_name = lfj.load_capture(capture / "capture.yaml")
        _edit(capture, channel=index)
        by_index = lfj.load_capture(capture / "capture.yaml")
        assert by_index.channel_names == (name,)
        np.testing.assert_array_equal(by_index.images, by_name.images)
    # Layers: the images' chosen name, a layer's prefix included; several layers of the
    # chosen colour and none of its name cannot be told apart.
    dark = read_image(capture / "dark.exr")
    layered = {f"{layer}.{c}": (k + 1) * dark.channel(c) for k, layer in
               enumerate(("diffuse", "specular")) for c in "BGR"}  # fmt: skip
    images = yaml.safe_load((capture / "capture.yaml").read_text())["images"]
    for name in images:
        y = read_image(capture / name)
        write_exr(capture / name, {f"{layer}.{c}": y.channel(c) for layer in
                                   ("diffuse", "specular") for c in "RGB"})  # fmt: skip
    write_exr(capture / "dark.exr", layered)
    for channel, chosen in [(5, "specular.B"), ("specular.R", "specular.R"), (0, "diffuse.R")]:
        _edit(capture, channel=channel)
        loaded = lfj.load_capture(capture / "capture.yaml")
        assert loaded.channel_names == (chosen,)
        y = read_image(capture / images[0]).channel(chosen)
        lit = np.isfinite(y)
        np.testing.assert_allclose(loaded.images[0, ..., 0][lit], (y - layered[chosen])[lit])
    for name in images:  # plain R, G, B images against the layered dark frame
        y = read_image(capture / name)
        write_exr(capture / name, {c: y.channel(f"diffuse.{c}") for c in "RGB"})
    _edit(capture, channel=0)
    with pytest.raises(lfj.CaptureError, match=r"dark\.exr has diffuse\.R, specular\.R, none"):
        lfj.load_capture(capture / "capture.yaml")
    grey = dark.channel("R")
    write_exr(capture / "dark.exr", {"Y": grey})
    _edit(capture, channel=2)
    by_index = lfj.load_capture(capture / "capture.yaml")
    _edit(capture, channel="B")
    np.testing.assert_array_equal(
        by_index.images, lfj.load_capture(capture / "capture.yaml").images
    )


def test_a_max_steps_past_the_solvers_count_is_named_as_the_option(capture, capsys, tmp_path):
    """Before: --max-steps 1000000000000 was refused after the capture's load, as the
    capture file's error ("capture.yaml: max_steps: must be an integer <= 1e+09")."""
    status, out, err = _run(
        capsys, "fit", capture / "capture.yaml", "--max-steps", "1000000000000",
        "--out", tmp_path / "r.json",
    )  # fmt: skip
    assert status == 2 and "capture.yaml" not in err, err
    assert "argument --max-steps: must be at most 1e+09, got '1000000000000'" in err
    assert not (tmp_path / "r.json").exists()


def test_solver_tolerances_that_can_never_be_met_are_refused(capture, capsys):
    """Before: fit: {rtol: 0, atol: 0} (or 1e-300 each) was taken: the solve ran to
    max_steps (14 s on this capture) and ended "not converged"."""
    for rtol, atol in [(0.0, 0.0), (1e-300, 1e-300)]:
        with pytest.raises(ValueError, match=r"^rtol, atol: .* can never be met \(below"):
            lfj.FitOptions(rtol=rtol, atol=atol)
        _edit(capture, fit={"phase": "paper", "rtol": rtol, "atol": atol})
        _refused(
            capsys, "inspect", capture / "capture.yaml",
            match=f"fit: rtol, atol: {rtol!r} and {atol!r} can never be met",
        )  # fmt: skip
    # Either one alone may be 0: the other (or its default) is met.
    assert lfj.FitOptions(rtol=0.0, atol=1e-10).solve.rtol == 0.0
    assert lfj.FitOptions(rtol=0.0).solve.atol is None


def test_write_capture_yaml_never_replaces_a_file_it_lists(capture):
    """Before: write_capture_yaml(cap / "shift_00.exr", images=[...shift_00.exr...])
    replaced the image with the YAML, and an empty or short image list was written into
    a file load_capture then refused."""
    names = [f"shift_0{i}.exr" for i in range(6)]
    before = _snapshot(capture)
    for target, kwargs in [
        ("shift_00.exr", {}),
        ("dark.exr", {"dark_frame": "dark.exr"}),
    ]:
        with pytest.raises(ValueError, match=f"is the listed file {target}, which the capture"):
            lfj.write_capture_yaml(capture / target, images=names, pattern=lfj.Stripes(), **kwargs)
    for images, match in [
        ([], r"images: 0 listed for the pattern's 6 phases"),
        (names[:2], r"images: 2 listed for the pattern's 6 phases \[0, 1, 2, 3, 4, 5\]"),
        ([1, 2, 3, 4, 5, 6], r"images: must be image file names"),
    ]:
        with pytest.raises(ValueError, match=f"^write_capture_yaml: {match}"):
            lfj.write_capture_yaml(capture / "new.yaml", images=images, pattern=lfj.Stripes())
    assert _snapshot(capture) == before
    # A stack, and brackets (one list per shift), are written.
    lfj.write_capture_yaml(capture / "new.yaml", images="stack.npy", pattern=lfj.Stripes())
    lfj.write_capture_yaml(capture / "new.yaml", images=[[n] for n in names], pattern=lfj.Stripes())


def test_write_capture_yaml_refuses_frames_that_are_not_file_names(tmp_path):
    """A calibration frame of 5 was a TypeError of the check that the capture file
    replaces none of its files, and a name holding a NUL byte its "embedded null
    byte"; a bracketed capture's frames, one per exposure time, are written."""
    names = [f"shift_0{i}.exr" for i in range(6)]
    path = tmp_path / "capture.yaml"
    for kwargs, match in [
        ({"dark_frame": 5}, r"dark_frame: must be an image file name \(with brackets"),
        ({"flat_field": ["a.exr", 3]}, r"flat_field: must be an image file name"),
        ({"white_frame": "w\0.exr"}, r"white_frame: must be an image file name"),
        ({"images": ["a\0.exr", *names[1:]]}, r"images: must be image file names"),
        ({"images": "stack\0.npy"}, r"images: must be image file names or one .npy stack"),
    ]:
        with pytest.raises(ValueError, match="^write_capture_yaml: " + match):
            lfj.write_capture_yaml(path, **{"images": names, "pattern": lfj.Stripes(), **kwargs})
    assert not path.exists()
    brackets = [[n, n.replace(".exr", "_long.exr")] for n in names]
    lfj.write_capture_yaml(
        path, images=brackets, pattern=lfj.Stripes(), dark_frame=["d.exr", "d_long.exr"]
    )
    assert yaml.safe_load(path.read_text())["dark_frame"] == ["d.exr", "d_long.exr"]


@pytest.mark.parametrize("phases", ["auto", None])
def test_a_copied_shift_is_said_like_a_shift_listed_twice(capture, phases):
    """Before: with phases: auto, a shift saved over by a copy of another (the same
    pixels under another file name) was taken as two shifts at one phase without a word,
    where the same file listed twice is warned of; under the default phases (none
    given) only a note said that the measured phases differ from the default."""
    shutil.copy(capture / "shift_02.exr", capture / "shift_03.exr")
    pattern = yaml.safe_load((capture / "capture.yaml").read_text())["pattern"]
    pattern.pop("phases", None)
    _edit(capture, pattern=pattern if phases is None else {**pattern, "phases": phases})
    with pytest.warns(lfj.CaptureWarning) as caught:
        lfj.load_capture(capture / "capture.yaml")
    said = [str(w.message) for w in caught]
    assert any(
        "images[3] (shift_03.exr) holds the same pixels as images[2] (shift_02.exr): one "
        "image counted as two shifts" in s
        for s in said
    ), said


def test_fit_capture_refuses_a_capture_whose_parts_disagree(capture):
    """Before: a Capture changed by hand (dataclasses.replace) with a channel name too
    many raised an IndexError, a mask of other shifts numpy's broadcast error, a pattern
    of None an AttributeError, and a negative pixel pitch was fitted and reported as
    negative coefficients per mm."""
    import dataclasses

    loaded = lfj.load_capture(capture / "capture.yaml")
    for change, match in [
        ({"channel_names": ("Y", "Z")}, r"capture\.channel_names: \('Y', 'Z'\) must name each"),
        ({"sample_mask": loaded.sample_mask[:2]}, r"capture\.sample_mask: must have the shape"),
        ({"images": loaded.images[:3]}, r"capture\.pattern: must be the Stripes of the 3 shifts"),
        ({"pattern": None}, r"capture\.pattern: must be the Stripes of the 6 shifts, got None"),
        ({"mask": loaded.mask[:5]}, r"capture\.mask: must have the shape \(24, 32, 1\)"),
        ({"pixel_size_mm": -1.0}, r"capture\.pixel_size_mm: must lie in"),
        ({"images": loaded.images.astype(int)}, r"capture\.images: must be floats"),
    ]:
        with pytest.raises(ValueError, match="^fit_capture: " + match):
            lfj.fit_capture(dataclasses.replace(loaded, **change))


def test_more_worker_processes_than_the_memory_holds_are_refused(
    capture, capsys, tmp_path, monkeypatch
):
    """Before: --workers 100000 started a local cluster of 100000 processes (each about
    240 MB before any task): the memory and the process table ran out first."""
    import distributed as dask_distributed

    from lightfield_jax.app import distributed

    def started(*_args, **_kwargs):
        raise AssertionError("a cluster was started")

    monkeypatch.setattr(dask_distributed, "LocalCluster", started)
    monkeypatch.setenv(MAX_MEMORY_ENV, "1G")
    other = tmp_path / "other"
    shutil.copytree(capture, other)
    out = tmp_path / "results"
    _refused(
        capsys, "fit", capture / "capture.yaml", other / "capture.yaml", "--workers", 8,
        "--out", out,
        match="--workers 8: 8 worker processes (about 256.0 MiB each before any task) needs "
        "about 2.0 GiB of memory, more than the 1.0 GiB",
    )  # fmt: skip
    assert not out.exists()
    with pytest.raises(ValueError, match="--workers 100000: 100000 worker processes"):
        with distributed.cluster(workers=100000):
            pass


def test_a_word_for_a_number_is_not_called_a_quoted_number(capture, capsys):
    """Before: black_level: 'auto ' (a space) or 'x' was refused as "must be a number,
    got 'auto ' (str) (a quoted number: remove the quotes)": no number was quoted."""
    for value, match in [
        ("auto ", "black_level: must be a number in [0, 1) or 'auto', got 'auto '"),
        ("Auto", "black_level: must be a number in [0, 1) or 'auto', got 'Auto'"),
        ("x", "black_level: must be a number, got 'x' (str)"),
    ]:
        _edit(capture, black_level=value)
        line = _refused(capsys, "inspect", capture / "capture.yaml", match=match)
        assert "quoted" not in line, line
    _edit(capture, black_level="0.02")
    _refused(
        capsys, "inspect", capture / "capture.yaml",
        match="black_level: must be a number, got '0.02' (str) (a quoted number: remove the",
    )  # fmt: skip


def test_stripes_take_a_jax_arrays_phases_and_refuse_a_table_of_them():
    """Before: Stripes(phases=jnp.arange(6)) was refused as "must be a sequence of
    integers" (a NumPy array was taken), and a 2x2 array of phases was flattened into
    four phases without a word."""
    import jax
    import jax.numpy as jnp

    assert lfj.Stripes(phases=jnp.arange(6)).phases == (0, 1, 2, 3, 4, 5)
    assert lfj.Stripes(phases=np.arange(3)).phases == (0, 1, 2)
    with pytest.raises(ValueError, match=r"^illumination.phases: .* array of shape \(2, 2\)$"):
        lfj.Stripes(phases=np.arange(4).reshape(2, 2))
    with pytest.raises(ValueError, match=r"^illumination.phases: .* got np.int64\(3\)$"):
        lfj.Stripes(phases=np.int64(3))
    with pytest.raises(ValueError, match=r"^illumination.phases: .* got a traced value"):
        jax.jit(lambda p: lfj.Stripes(phases=p).period)(jnp.arange(6))


def test_bench_sizes_given_twice_are_refused(capsys, tmp_path):
    """Before: --sizes 16x16x8,16x16X8 measured the one grid twice (26 s) and wrote two
    rows of it, where --methods refuses a name given twice."""
    status, out, err = _run(
        capsys, "bench", "--sizes", "16x16x8,16X16x8", "--no-fits", "--out", tmp_path / "b.json"
    )
    assert status == 2 and "argument --sizes: '16X16x8' is given twice" in err, err
    assert not (tmp_path / "b.json").exists()


@pytest.mark.parametrize(
    "variable, said",
    [
        ("JAX_COMPILATION_CACHE_MAX_SIZE=2G", 'Invalid value "2G" for JAX flag'),
        ("JAX_ENABLE_X64=maybe", "invalid truth value 'maybe'"),
    ],
)
def test_a_jax_variable_jax_cannot_read_is_one_line(variable, said):
    """Before: a traceback from JAX's import on every command, --help included."""
    import subprocess
    import sys

    name, value = variable.split("=")
    env = {**os.environ, name: value}
    for argv in (["-m", "lightfield_jax", "--help"], ["-c", "import lightfield_jax"]):
        done = subprocess.run([sys.executable, *argv], env=env, capture_output=True, text=True)
        err = done.stderr.strip().splitlines()
        if argv[0] == "-m":  # the command: one line, exit status 2
            assert done.returncode == 2 and len(err) == 1, err
            assert err[0].startswith("lightfield-jax: error: JAX cannot start: ")
        else:  # the API: an ImportError naming the variable
            assert err[-1].startswith("ImportError: lightfield_jax: JAX cannot start: ")
        assert said in err[-1] and f"{name}='{value}'" in err[-1], err


def test_a_jax_backend_that_cannot_start_is_one_line(capsys, monkeypatch, tmp_path):
    """Before: JAX_PLATFORMS=tpu on a machine without one: a traceback at the first
    computation."""
    import jax

    def unavailable(*_a, **_k):
        raise RuntimeError("Unable to initialize backend 'tpu': INTERNAL: no libtpu.so")

    monkeypatch.setattr(jax.numpy, "asarray", unavailable)
    monkeypatch.setattr(jax.numpy, "array", unavailable)
    status, _, err = _run(capsys, "demo", "--out", tmp_path / "d")
    assert status == 2 and err.strip() == (
        "lightfield-jax: error: JAX cannot start: Unable to initialize backend 'tpu': "
        "INTERNAL: no libtpu.so"
    ), err
    assert not (tmp_path / "d").exists()
