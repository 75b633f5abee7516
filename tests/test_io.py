"""Image and file I/O: round trips, sample scaling, errors, atomic writes."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from lightfield_jax.capture.image_write import write_exr, write_png, write_tiff
from lightfield_jax.capture.io import CaptureError, CaptureFileNotFoundError, ImageData, read_image
from lightfield_jax.files import (
    atomic_directory,
    atomic_path,
    atomic_write_bytes,
    atomic_write_json,
    atomic_write_npy,
    atomic_write_text,
)


@pytest.fixture
def rng():
    return np.random.default_rng(0)


def _no_temporaries(folder):
    return [p.name for p in folder.rglob("*") if ".tmp-" in p.name] == []


def test_import_does_not_load_image_libraries():
    code = (
        "import sys, lightfield_jax, lightfield_jax.capture.io, lightfield_jax.schema; "
        "bad = {'OpenImageIO', 'matplotlib', 'cv2'} & set(sys.modules); "
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_exr_round_trip_keeps_names_order_and_values(tmp_path, rng):
    # Alphabetical order (EXR's own) would put I10 before I2; R would go first in OIIO.
    names = [f"I{k}" for k in range(1, 12)] + ["R"]
    channels = {n: rng.normal(size=(6, 9)) for n in names}
    path = write_exr(tmp_path / "bounces.exr", channels, metadata={"sigma_t": 0.2051})
    image = read_image(path)
    assert isinstance(image, ImageData)
    assert image.channel_names == tuple(names)
    assert image.pixels.shape == (6, 9, len(names))
    assert image.pixels.dtype == np.float32
    assert (image.bit_depth, image.sample_type, image.is_integer) == (32, "float", False)
    for n in names:
        np.testing.assert_array_equal(image.channel(n), channels[n].astype(np.float32))
    assert _no_temporaries(tmp_path)


def test_exr_channel_selection_and_count(tmp_path, rng):
    channels = {n: rng.uniform(size=(4, 5)) for n in ("I1", "I2", "I3")}
    path = write_exr(tmp_path / "a.exr", channels)
    two = read_image(path, ["I3", 0])
    assert two.channel_names == ("I3", "I1")
    np.testing.assert_array_equal(two.pixels[..., 0], channels["I3"].astype(np.float32))
    assert read_image(path, "I2", n_channels=1).pixels.shape == (4, 5, 1)
    with pytest.raises(CaptureError, match=r"a\.exr: no channel named 'I9'; channels: I1"):
        read_image(path, "I9")
    with pytest.raises(CaptureError, match="a.exr: channel index 3 out of range"):
        read_image(path, 3)
    with pytest.raises(CaptureError, match=r"a\.exr: expected 1 channel\(s\), found 3"):
        read_image(path, n_channels=1)


def test_write_exr_rejects_mismatched_channels(tmp_path):
    with pytest.raises(ValueError, match="'b' has shape \\(3, 3\\)"):
        write_exr(tmp_path / "a.exr", {"a": np.zeros((2, 3)), "b": np.zeros((3, 3))})
    with pytest.raises(ValueError, match="at least one channel"):
        write_exr(tmp_path / "a.exr", {})
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("bits", [8, 16])
def test_png_round_trip_scales_by_type_max(tmp_path, rng, bits):
    top = (1 << bits) - 1
    values = rng.uniform(size=(7, 5, 3))
    image = read_image(write_png(tmp_path / "p.png", values, bits=bits))
    assert (image.bit_depth, image.sample_type) == (bits, f"uint{bits}")
    assert image.is_integer and image.channel_names == ("R", "G", "B")
    np.testing.assert_allclose(image.pixels, np.rint(values * top) / top, atol=1e-6)
    np.testing.assert_allclose(image.pixels, values, atol=0.5 / top + 1e-6)


def test_png_integer_codes_and_masks_are_written_as_is(tmp_path):
    codes = np.array([[0, 1000], [65535, 7]], dtype=np.uint16)
    image = read_image(write_png(tmp_path / "c.png", codes, bits=16))
    np.testing.assert_allclose(image.pixels[..., 0] * 65535, codes, atol=1e-2)
    mask = read_image(write_png(tmp_path / "m.png", np.array([[True, False]])))
    np.testing.assert_array_equal(mask.pixels[..., 0], [[1.0, 0.0]])


def test_png_rejects_out_of_range_values(tmp_path):
    with pytest.raises(ValueError, match=r"lie in \[0, 1\]"):
        write_png(tmp_path / "p.png", np.array([[0.5, 1.5]]))
    with pytest.raises(ValueError, match=r"lie in \[0, 255\]"):
        write_png(tmp_path / "p.png", np.array([[0, 256]]))
    with pytest.raises(ValueError, match="bits must be 8 or 16"):
        write_png(tmp_path / "p.png", np.zeros((2, 2)), bits=12)
    assert list(tmp_path.iterdir()) == []


def test_tiff_16bit_round_trip(tmp_path, rng):
    values = rng.uniform(size=(5, 6))
    image = read_image(write_tiff(tmp_path / "t.tif", values, bits=16))
    assert (image.bit_depth, image.sample_type, image.pixels.shape) == (16, "uint16", (5, 6, 1))
    np.testing.assert_allclose(image.pixels[..., 0], np.rint(values * 65535) / 65535, atol=1e-6)


def test_tiff_float_round_trip_keeps_values(tmp_path, rng):
    values = rng.normal(scale=10.0, size=(5, 6, 2))  # HDR: negative and above 1 are kept
    image = read_image(write_tiff(tmp_path / "t.tiff", values, bits=32))
    assert (image.bit_depth, image.sample_type) == (32, "float")
    np.testing.assert_array_equal(image.pixels, values.astype(np.float32))


@pytest.mark.parametrize(
    ("dtype", "scale", "bits", "out"),
    [
        (np.uint8, 255, 8, np.float32),
        (np.uint16, 65535, 16, np.float32),
        (np.float32, 1, 32, np.float32),
        (np.float64, 1, 64, np.float64),
    ],
)
def test_npy_round_trip(tmp_path, rng, dtype, scale, bits, out):
    raw = (rng.uniform(size=(4, 3)) * scale).astype(dtype)
    image = read_image(atomic_write_npy(tmp_path / "a.npy", raw))
    assert image.pixels.dtype == out and image.bit_depth == bits
    assert image.channel_names == ("Y",)
    np.testing.assert_allclose(image.pixels[..., 0], raw.astype(np.float64) / scale, rtol=1e-6)


def test_npy_rejects_bad_shape_and_dtype(tmp_path):
    np.save(tmp_path / "cube.npy", np.zeros((2, 3, 4, 5)))
    with pytest.raises(CaptureError, match=r"cube\.npy: expected a \(height, width\)"):
        read_image(tmp_path / "cube.npy")
    np.save(tmp_path / "ints.npy", np.zeros((2, 3), dtype=np.int32))
    with pytest.raises(CaptureError, match=r"ints\.npy: unsupported array dtype int32"):
        read_image(tmp_path / "ints.npy")


def test_missing_file_is_capture_and_file_not_found_error(tmp_path):
    missing = tmp_path / "nope.exr"
    with pytest.raises(CaptureFileNotFoundError, match="nope.exr: file not found") as info:
        read_image(missing)
    assert isinstance(info.value, FileNotFoundError) and isinstance(info.value, CaptureError)


def test_unsupported_extension_and_unreadable_file(tmp_path):
    (tmp_path / "a.jpg").write_bytes(b"\xff\xd8")
    with pytest.raises(CaptureError, match=r"a\.jpg: unsupported image extension '\.jpg'.*lossy"):
        read_image(tmp_path / "a.jpg")
    (tmp_path / "broken.png").write_bytes(b"not a png")
    with pytest.raises(CaptureError, match=r"broken\.png: cannot read image"):
        read_image(tmp_path / "broken.png")
    (tmp_path / "broken.npy").write_bytes(b"junk")
    with pytest.raises(CaptureError, match=r"broken\.npy: not a readable \.npy"):
        read_image(tmp_path / "broken.npy")
    with pytest.raises(CaptureError, match="is a directory"):
        read_image(tmp_path)


def test_atomic_text_json_bytes(tmp_path):
    atomic_write_text(tmp_path / "a.txt", "héllo")
    assert (tmp_path / "a.txt").read_text(encoding="utf-8") == "héllo"
    atomic_write_json(tmp_path / "sub" / "r.json", {"x": np.float64(1.5), "a": np.arange(3)})
    assert json.loads((tmp_path / "sub" / "r.json").read_text()) == {"x": 1.5, "a": [0, 1, 2]}
    atomic_write_bytes(tmp_path / "a.txt", b"new")
    assert (tmp_path / "a.txt").read_bytes() == b"new"
    assert _no_temporaries(tmp_path)


def test_atomic_write_failure_keeps_old_file_and_leaves_no_temporary(tmp_path, monkeypatch):
    target = tmp_path / "a.npy"
    np.save(target, np.ones(3))
    with pytest.raises(RuntimeError, match="disk full"), atomic_path(target) as tmp:
        tmp.write_bytes(b"half a fi")
        raise RuntimeError("disk full")

    def failing_save(f, *args, **kwargs):
        f.write(b"\x93NUMPY partial")
        raise OSError("disk full")

    monkeypatch.setattr(np, "save", failing_save)
    with pytest.raises(OSError, match="disk full"):
        atomic_write_npy(target, np.zeros(3))
    monkeypatch.undo()
    np.testing.assert_array_equal(np.load(target), np.ones(3))
    with pytest.raises(ValueError, match="Out of range float values"):
        atomic_write_json(tmp_path / "nan.json", {"x": float("nan")})
    assert sorted(os.listdir(tmp_path)) == ["a.npy"]


def test_atomic_directory_publishes_only_on_success(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(RuntimeError, match="fit failed"), atomic_directory(out) as stage:
        atomic_write_text(stage / "a.txt", "a")
        write_png(stage / "figs" / "b.png", np.zeros((2, 2)))
        raise RuntimeError("fit failed")
    assert os.listdir(tmp_path) == []

    with atomic_directory(out) as stage:
        atomic_write_text(stage / "a.txt", "a")
        write_png(stage / "figs" / "b.png", np.zeros((2, 2)))
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == [
        "a.txt",
        "figs",
        "figs/b.png",
    ]
    assert os.listdir(tmp_path) == ["run"]


def test_atomic_directory_into_existing_folder_replaces_only_written_files(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "keep.txt").write_text("keep")
    (out / "a.txt").write_text("old")
    with pytest.raises(RuntimeError), atomic_directory(out) as stage:
        atomic_write_text(stage / "a.txt", "partial")
        raise RuntimeError
    assert (out / "a.txt").read_text() == "old"

    with atomic_directory(out) as stage:
        atomic_write_text(stage / "a.txt", "new")
        atomic_write_text(stage / "sub" / "c.txt", "c")
    assert (out / "a.txt").read_text() == "new"
    assert (out / "keep.txt").read_text() == "keep"
    assert (out / "sub" / "c.txt").read_text() == "c"
    assert os.listdir(tmp_path) == ["run"]


def test_atomic_directory_refuses_a_file(tmp_path):
    (tmp_path / "out").write_text("x")
    with pytest.raises(NotADirectoryError, match="out: exists and is not a directory"):
        with atomic_directory(tmp_path / "out"):
            pass


def test_atomic_directory_into_the_working_folder_keeps_the_folder(tmp_path, monkeypatch):
    """Before: "PosixPath('.') has an empty name" for --out . (and --out /)."""
    here = tmp_path / "here"
    (here / "sub").mkdir(parents=True)
    monkeypatch.chdir(here / "sub")
    inode = os.stat(".").st_ino
    with atomic_directory(".") as stage:  # empty: a rename would replace the folder
        (stage / "a.txt").write_text("a")
    assert os.stat(".").st_ino == inode and (here / "sub" / "a.txt").read_text() == "a"
    with atomic_directory("..") as stage:
        (stage / "b.txt").write_text("b")
    assert sorted(p.name for p in here.iterdir()) == ["b.txt", "sub"]
    with pytest.raises(ValueError, match="^/: the root folder cannot be an output folder"):
        with atomic_directory("/"):
            pass
