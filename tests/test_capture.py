"""The capture format: simulate → load round trip, and every documented bad input."""

import re
import warnings

import numpy as np
import pytest
import yaml

import lightfield_jax as lfj
from lightfield_jax import Stripes
from lightfield_jax.capture.capture import Capture, CaptureWarning
from lightfield_jax.capture.image_write import write_exr, write_png
from lightfield_jax.capture.io import CaptureError, CaptureFileNotFoundError, read_image
from lightfield_jax.capture.loading import load_capture
from lightfield_jax.capture.write import write_capture_yaml
from lightfield_jax.files import atomic_directory
from lightfield_jax.forward.simulate import simulate_capture, write_simulation
from lightfield_jax.forward.simulate_config import parse_simulation_config
from lightfield_jax.inverse import capture_fit

H, W, P = 8, 12, 3
PATTERN = Stripes(period=6, lit=3, phases=(0, 2, 4))


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A stripe capture written by simulate (black level, dark level, no noise)."""
    config = parse_simulation_config(
        {
            "grid": {"width": 24, "height": 16, "n_theta": 16, "refine": 1},
            "medium": {"sigma_t": 0.2, "sigma_s": 0.1, "g": 0.3, "phase": "paper"},
            "illumination": {"kind": "stripes", "period": 6, "lit": 3},
            "bounces": 3,
            "gain": 1.5,
            "black_level": 0.05,
            "dark_level": 0.02,
        }
    )
    sim = simulate_capture(config)
    folder = tmp_path_factory.mktemp("simulated")
    with atomic_directory(folder) as staging:
        write_simulation(sim, staging)
    return sim, folder


def test_round_trip_simulate_then_load(simulated):
    sim, folder = simulated
    capture = load_capture(folder / "capture.yaml")
    assert isinstance(capture, Capture)
    assert capture.images.shape == (6, 16, 24, 1) and capture.channel_names == ("Y",)
    assert capture.pattern == sim.config.illumination
    assert capture.black_level == 0.05
    assert capture.dark_frame == folder / "dark.exr"
    assert capture.image_paths == tuple(folder / f"shift_{i:02d}.exr" for i in range(6))
    assert capture.mask.shape == (16, 24, 1) and capture.mask.all()
    assert capture.n_masked == {"nonfinite": 0, "saturated": 0, "total": 0, "values": 0}
    assert capture.warnings == () and capture.roi is None
    assert capture.geometry == {"kind": "plane"}
    assert capture.truth == {
        "sigma_t": 0.2,
        "sigma_s": 0.1,
        "g": 0.3,
        "gain": 1.5,
        "black_level": 0.05,
        "phase": "paper",
    }
    # Dark frame subtracted: what is left is Σ_k I_k of each shift.
    np.testing.assert_allclose(capture.images[..., 0], sim.bounces.sum(1), atol=1e-7)


def _images(folder, n=P, shape=(H, W), fill=None, prefix="s"):
    rng = np.random.default_rng(0)
    names = []
    for i in range(n):
        plane = rng.uniform(0.1, 0.5, shape) if fill is None else np.full(shape, fill)
        names.append(f"{prefix}{i}.exr")
        write_exr(folder / names[-1], {"Y": plane})
    return names


def _capture(folder, text=None, **keys):
    """Write capture.yaml (from keys, or literally from text) and load it."""
    path = folder / "capture.yaml"
    if text is None:
        keys.setdefault("pattern", PATTERN)
        write_capture_yaml(path, **keys)
    else:
        path.write_text(text)
    return load_capture(path)


def _error(folder, match, error=CaptureError, **keys):
    with pytest.raises(error) as info:
        _capture(folder, **keys)
    message = str(info.value)
    assert message.startswith(str(folder / "capture.yaml") + ": "), message
    assert re.search(match, message), message
    assert "\n" not in message
    return message


def test_write_capture_yaml_all_keys_round_trip(tmp_path):
    names = _images(tmp_path)
    write_exr(tmp_path / "dark.exr", {"Y": np.full((H, W), 0.05)})
    capture = _capture(
        tmp_path,
        images=names,
        dark_frame="dark.exr",
        black_level=0.1,
        medium_roi=[2, 1, 10, 7],
        pixel_size_mm=0.05,
        saturation=0.98,
        channel="Y",
        geometry={"kind": "plane"},
        truth={"sigma_t": np.float64(0.2), "phase": "normalized"},
    )
    assert capture.images.shape == (P, 6, 8, 1)
    assert capture.roi == (2, 1, 10, 7) and capture.pixel_size_mm == 0.05
    assert capture.saturation == 0.98 and capture.black_level == 0.1
    assert capture.truth == {"sigma_t": 0.2, "phase": "normalized"}
    data = yaml.safe_load((tmp_path / "capture.yaml").read_text())
    assert list(data) == [
        "images",
        "pattern",
        "dark_frame",
        "black_level",
        "medium_roi",
        "pixel_size_mm",
        "saturation",
        "channel",
        "geometry",
        "truth",
    ]


def test_roi_crops_and_counts_pattern_rows_from_its_edge(tmp_path):
    names = _images(tmp_path)
    capture = _capture(tmp_path, images=names, medium_roi=[3, 2, 11, 8])
    whole = _capture(tmp_path, images=names)
    np.testing.assert_array_equal(capture.images, whole.images[:, 2:8, 3:11])
    # Row r of the frame is row r - 2 of the ROI: phase φ becomes (φ + 2) mod 6.
    assert capture.pattern.phases == (2, 4, 0)
    top = _capture(
        tmp_path,
        images=names,
        pattern=Stripes(6, 3, (0, 2, 4), entry="top"),
        medium_roi=[3, 2, 11, 8],
    )
    assert top.pattern.phases == (3, 5, 1) and top.pattern.entry == "top"


def test_npy_stack_channel_selection_and_integer_scaling(tmp_path):
    stack = np.zeros((P, H, W, 3), np.uint16)
    stack[..., 1] = 30000
    stack[..., 2] = 100  # a channel without light is refused
    np.save(tmp_path / "stack.npy", stack)
    capture = _capture(tmp_path, images="stack.npy", channel="G")
    assert capture.images.shape == (P, H, W, 1) and capture.channel_names == ("G",)
    np.testing.assert_allclose(capture.images, 30000 / 65535, rtol=1e-6)
    every = _capture(tmp_path, images="stack.npy")
    assert every.channel_names == ("R", "G", "B") and every.images.shape == (P, H, W, 3)
    by_index = _capture(tmp_path, images="stack.npy", channel=2)
    assert by_index.channel_names == ("B",)
    _error(tmp_path, r"images: .*stack\.npy: no channel named 'Q'", images="stack.npy", channel="Q")
    np.save(tmp_path / "flat.npy", np.zeros((H, W)))
    _error(tmp_path, r"images: .*flat\.npy: expected an \(images, height", images="flat.npy")
    _error(tmp_path, r"images: a single file must be a \.npy stack", images="s0.exr")


def test_missing_unreadable_and_empty_images(tmp_path):
    names = _images(tmp_path)
    _error(
        tmp_path,
        r"images\[1\]: .*nope\.exr: file not found",
        error=CaptureFileNotFoundError,
        images=[names[0], "nope.exr", names[2]],
    )
    (tmp_path / "junk.exr").write_bytes(b"not an image")
    _error(tmp_path, r"images\[2\]: .*junk\.exr: cannot read", images=[*names[:2], "junk.exr"])
    (tmp_path / "x.gif").write_bytes(b"GIF89a")
    _error(tmp_path, r"images\[0\]: .*unsupported image extension", images=["x.gif", *names[1:3]])
    # Written by hand: write_capture_yaml refuses an empty list.
    _error(tmp_path, r"images: the list is empty", text="images: []\npattern: {period: 6}\n")
    _error(tmp_path, r"images\[1\]: must be a file path, got 3", text=f"images: [{names[0]}, 3]\n")
    _error(tmp_path, r"images: required key is missing", text="pattern: {period: 6}\n")
    with pytest.raises(CaptureFileNotFoundError, match=r"gone\.yaml: file not found"):
        load_capture(tmp_path / "gone.yaml")


def test_images_of_different_sizes(tmp_path):
    names = _images(tmp_path, n=2)
    names += _images(tmp_path, n=1, shape=(H + 1, W), prefix="big")
    _error(
        tmp_path,
        r"images\[2\]: big0\.exr is 12x9 pixels .* images\[0\] \(s0\.exr\) is 12x8",
        images=names,
    )


def test_phases_inconsistent_with_image_count(tmp_path):
    names = _images(tmp_path)
    # Written by hand: write_capture_yaml refuses a list of another length.
    _error(
        tmp_path,
        r"pattern\.phases: lists 2 phase\(s\) for 3 image\(s\)",
        text=f"images: {names}\npattern: {{period: 6, lit: 3, phases: [0, 3]}}\n",
    )
    # Phases default to 0..P-1.
    text = f"images: {names}\npattern: {{period: 4, lit: 2}}\n"
    assert _capture(tmp_path, text=text).pattern == Stripes(4, 2, (0, 1, 2))


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        (
            "imagez: []\n",
            r"imagez: unknown key \(did you mean 'images'\?\); allowed keys: images, pattern",
        ),
        ("pattern: {perod: 6}\n", r"pattern\.perod: unknown key \(did you mean 'period'\?\)"),
        ("pattern: {period: 6.5}\n", r"pattern\.period: must be an integer, got 6\.5"),
        ("pattern: {lit: 7}\n", r"pattern\.lit: must be an integer in \[1, period-1\]"),
        ("pattern: {phases: [0, x, 2]}\n", r"pattern\.phases\[1\]: must be an integer, got 'x'"),
        ("pattern: {entry: north}\n", r"pattern\.entry: must be one of left, right, top"),
        ("pattern: {direction_deg: 180}\n", r"pattern\.direction_deg: 180\.0 degrees does not"),
        ("pattern: [6, 3]\n", r"pattern: must be a mapping of keys"),
        ("black_level: dim\n", r"black_level: must be a number, got 'dim'"),
        ("black_level: 1.0\n", r"black_level: must lie in \[0, 1\), got 1\.0"),
        ("medium_roi: [0, 0, 4]\n", r"medium_roi: must be a list of 4 integers"),
        ("medium_roi: [0, 0, 4.5, 4]\n", r"medium_roi: must be a list of 4 integers"),
        ("pixel_size_mm: 0\n", r"pixel_size_mm: must be > 0, got 0"),
        ("saturation: -1\n", r"saturation: must be > 0"),
        ("channel: [R]\n", r"channel: must be a channel name, an index or 'all'"),
        ("channel: R\n", r"images\[0\]: .*s0\.exr: no channel named 'R'; channels: Y"),
        ("geometry: {kind: slab}\n", r"geometry\.thickness: required for kind 'slab'"),
        ("geometry: {kind: auto}\n", r"geometry\.thickness: required for the slab it may"),
        (
            "geometry: {kind: slab, thickness: 0}\n",
            r"geometry\.thickness: must be a finite number > 0",
        ),
        ("geometry: {kind: plane, n: 1.3}\n", r"geometry\.n: unknown key"),
        ("truth: {sigma: 0.2}\n", r"truth\.sigma: unknown key"),
        ("truth: {phase: flat}\n", r"truth\.phase: must be one of paper, normalized"),
        ("truth: {g: high}\n", r"truth\.g: must be a number"),
        ("fit: {n_thet: 64}\n", r"fit\.n_thet: unknown key \(did you mean 'n_theta'\?\)"),
        ("fit: {method: grid}\n", r"fit\.method: unknown key"),
        ("fit: {max_steps: 1.5}\n", r"fit\.max_steps: must be an integer, got 1\.5"),
        ("fit: {correct: yes please}\n", r"fit\.correct: must be true or false"),
        ("fit: {tail: krylov}\n", r"fit\.tail: must be one of auto, "),
        ("fit: {bounces: many}\n", r"fit\.bounces: must be an integer"),
        ("fit: {start: [0.1]}\n", r"fit\.start: must be \[sigma_s, g\]"),
        ("fit: {start: [0.1, 1.5]}\n", r"fit: start: must be \(sigma_s > 0, \|g\| < 1\)"),
        ("fit: {max_render_cells: 10}\n", r"fit: max_render_cells: must be at least max_cells"),
        ("fit: [1, 2]\n", r"fit: must be a mapping of keys"),
    ],
)
def test_bad_keys_and_values(tmp_path, extra, match):
    names = _images(tmp_path)
    base = {"images": f"images: {names}\n", "pattern": "pattern: {period: 6, lit: 3}\n"}
    key = extra.split(":")[0]
    text = "".join(v for k, v in base.items() if k != key) + extra
    _error(tmp_path, match, text=text)


def test_fit_settings_reach_the_fit_options(tmp_path, monkeypatch):
    names = _images(tmp_path)
    text = (
        f"images: {names}\npattern: {{period: 6, lit: 3}}\n"
        "fit: {n_theta: 64, bounces: 12, tail: null, rtol: 1.0e-5, correct: false, "
        "start: [0.03, 0.4], max_render_cells: 4000000, coarse_after: null}\n"
    )
    capture = _capture(tmp_path, text=text)
    assert capture.fit_options == {
        "n_theta": 64,
        "bounces": 12,
        "tail": None,
        "rtol": 1e-5,
        "correct": False,
        "start": (0.03, 0.4),
        "max_render_cells": 4_000_000,
        "coarse_after": None,
    }
    # fit_capture fits with them (the call's own keywords win).
    seen = []

    def fake_fit(images, pattern, options, *args, **kwargs):
        seen.append(options)
        raise StopIteration

    monkeypatch.setattr(capture_fit, "_capture_floor", lambda *a: None)
    monkeypatch.setattr(capture_fit, "fit_one", fake_fit)
    with pytest.raises(StopIteration):
        lfj.fit_capture(capture, max_steps=7)
    assert seen[0].n_theta == 64 and seen[0].start == (0.03, 0.4) and not seen[0].correct
    assert seen[0].max_steps == 7 and seen[0].bounces == 12


def test_a_files_method_settings_reach_the_method_the_call_chooses(tmp_path, monkeypatch):
    """The file's g_grid / start_grid go to the method fit_capture is told to use (the
    command line's --method), not to the joint fit's options, which drop them."""
    names = _images(tmp_path)
    text = f"images: {names}\npattern: {{period: 6, lit: 3}}\nfit: {{g_grid: 5, start_grid: 7}}\n"
    capture = _capture(tmp_path, text=text)
    seen = []

    def fake_fit(images, pattern, options, *args, **kwargs):
        seen.append(options.method)
        raise StopIteration

    monkeypatch.setattr(capture_fit, "_capture_floor", lambda *a: None)
    monkeypatch.setattr(capture_fit, "fit_one", fake_fit)
    for method in ("grid", "gradient", "joint"):
        with pytest.raises(StopIteration):
            lfj.fit_capture(capture, method)
    assert seen == [lfj.GridSearch(5), lfj.TwoStep(start_grid=7), lfj.Joint()]


@pytest.mark.parametrize(("fit", "phase"), [("", "normalized"), ("fit: {phase: paper}\n", "paper")])
def test_a_capture_is_fitted_in_its_files_phase_convention_normalized_by_default(
    tmp_path, monkeypatch, fit, phase
):
    """``fit: {phase: ...}`` was refused as an unknown key, and a capture that said none
    was fitted under ``paper``, which has no answer for milk (ρ = ω·A(g) ≥ 1)."""
    names = _images(tmp_path)
    capture = _capture(tmp_path, text=f"images: {names}\npattern: {{period: 6, lit: 3}}\n{fit}")
    seen = []

    def fake_fit(images, pattern, options, *args, **kwargs):
        seen.append(options)
        raise StopIteration

    monkeypatch.setattr(capture_fit, "_capture_floor", lambda *a: None)
    monkeypatch.setattr(capture_fit, "fit_one", fake_fit)
    with pytest.raises(StopIteration):
        lfj.fit_capture(capture)
    assert seen[0].phase == phase
    with pytest.raises(StopIteration):  # the call's own keyword wins
        lfj.fit_capture(capture, phase="paper")
    assert seen[1].phase == "paper"


def test_a_fit_phase_that_is_no_convention_is_named(tmp_path):
    names = _images(tmp_path)
    message = _error(
        tmp_path,
        r"fit\.phase: must be one of paper, normalized, got 'physical'",
        text=f"images: {names}\npattern: {{period: 6, lit: 3}}\nfit: {{phase: physical}}\n",
    )
    assert "unknown key" not in message


def test_dark_frame_size_and_channels(tmp_path):
    names = _images(tmp_path)
    write_exr(tmp_path / "small.exr", {"Y": np.zeros((H, W - 1))})
    _error(
        tmp_path,
        r"dark_frame: small\.exr is 11x8 pixels .* images are 12x8",
        images=names,
        dark_frame="small.exr",
    )
    write_exr(tmp_path / "two.exr", {"A": np.zeros((H, W)), "B": np.zeros((H, W))})
    _error(tmp_path, r"dark_frame: two\.exr is .*2 channel", images=names, dark_frame="two.exr")
    _error(
        tmp_path,
        r"dark_frame: .*void\.exr: file not found",
        error=CaptureFileNotFoundError,
        images=names,
        dark_frame="void.exr",
    )


@pytest.mark.parametrize("roi", [[0, 0, 13, 8], [-1, 0, 5, 5], [4, 4, 5, 8], [0, 6, 12, 9]])
def test_roi_outside_the_image(tmp_path, roi):
    names = _images(tmp_path)
    _error(tmp_path, r"medium_roi: .* does not fit the 12x8 image", images=names, medium_roi=roi)


def test_nonfinite_pixels_are_masked_with_a_warning(tmp_path):
    names = _images(tmp_path)
    bad = np.full((H, W), 0.3)
    bad[1, 2] = np.nan
    bad[3, 4] = np.inf
    write_exr(tmp_path / names[1], {"Y": bad})
    dark = np.zeros((H, W))
    dark[5, 5] = np.nan
    write_exr(tmp_path / "dark.exr", {"Y": dark})
    with pytest.warns(
        CaptureWarning,
        match=r"3 pixel value\(s\) are NaN or Inf \(s1\.exr: 2, dark\.exr: 1\); 5 value\(s\) "
        r"masked in 3 pixel",
    ):
        capture = _capture(tmp_path, images=names, dark_frame="dark.exr")
    # Per value: the two in s1 only; the dark frame's NaN in every image (3 of them).
    assert capture.n_masked == {"nonfinite": 3, "saturated": 0, "total": 3, "values": 5}
    assert not capture.mask[1, 2, 0] and not capture.mask[3, 4, 0] and not capture.mask[5, 5, 0]
    assert not capture.sample_mask[1, 1, 2, 0] and capture.sample_mask[0, 1, 2, 0]
    assert not capture.sample_mask[:, 5, 5, 0].any()
    assert np.isfinite(capture.images).all() and capture.images[1, 1, 2, 0] == 0
    assert len(capture.warnings) == 1


def test_saturation_threshold_and_all_saturated_frame(tmp_path):
    names = _images(tmp_path)
    write_exr(tmp_path / names[2], {"Y": np.full((H, W), 0.99)})
    # One error that carries its cause, not warnings before it.
    with warnings.catch_warnings():
        warnings.simplefilter("error", CaptureWarning)
        _error(
            tmp_path,
            r"images: no usable pixel: .* \(every pixel is saturated in s2.exr\)",
            images=names,
            saturation=0.98,
        )
    hot = np.full((H, W), 0.3)
    hot[0, :4] = 0.99
    write_exr(tmp_path / names[2], {"Y": hot})
    with pytest.warns(
        CaptureWarning,
        match=r"at or above saturation 0\.98 \(s2\.exr: 4\); 4 value\(s\) masked in 4 pixel",
    ):
        capture = _capture(tmp_path, images=names, saturation=0.98)
    assert capture.n_masked["saturated"] == 4 and not capture.mask[0, :4].any()
    # Float frames without a saturation key keep bright values.
    hot[0, :4] = 5.0
    write_exr(tmp_path / names[2], {"Y": hot})
    assert _capture(tmp_path, images=names).mask.all()


def test_clipped_8bit_frames_warn_and_mask(tmp_path):
    rng = np.random.default_rng(1)
    names = []
    for i in range(P):
        frame = rng.uniform(0.1, 0.6, (H, W))
        lit = (np.arange(H) + 2 * i) % 6 < 3
        frame[lit, :3] = 1.0  # lit rows clipped at 255 near the entry wall
        names.append(f"p{i}.png")
        write_png(tmp_path / names[-1], frame)
    with pytest.warns(
        CaptureWarning, match=r"integer frames clipped at their top code 255 \(8-bit\)"
    ):
        capture = _capture(tmp_path, images=names)
    assert capture.n_masked["saturated"] == (~capture.mask).sum() == H * 3
    assert not capture.mask[:, :3].any() and capture.mask[:, 3:].all()
    # Per value, only the lit shifts of those pixels are masked: their dark shifts stay
    # (the joint fit uses them).
    for i in range(P):
        lit = (np.arange(H) + 2 * i) % 6 < 3
        assert not capture.sample_mask[i, lit, :3].any()
        assert capture.sample_mask[i, ~lit].all() and capture.sample_mask[i, :, 3:].all()
    assert capture.n_masked["values"] == (~capture.sample_mask).sum() == P * H * 3 // 2
    # An explicit saturation replaces the default threshold.
    with pytest.warns(CaptureWarning, match="at or above saturation 0.5"):
        _capture(tmp_path, images=names, saturation=0.5)


def test_16bit_frames_clamped_at_0_are_censored_from_below(tmp_path):
    """A camera's black subtraction or a 16-bit file clamps the dark values' read noise
    at code 0: the capture notes the pile-up (Capture.floored, found in raw codes, so a
    dark frame does not hide it) and the fit masks those values as censored from below
    at their calibrated level (an integer file's lowest code is always a cut)."""
    from lightfield_jax.inverse.data import prepare_data

    h, w = 24, 48
    rng = np.random.default_rng(2)
    pattern = Stripes(period=6, lit=3, phases=tuple(range(6)))
    names = []
    for i in range(6):
        lit = (np.arange(h)[:, None] + i) % 6 < 3
        light = np.where(lit, 0.5, 0.05) * np.exp(-0.15 * np.arange(w))[None]
        frame = light + rng.normal(0, 5e-3, (h, w))
        names.append(f"d{i}.png")
        write_png(tmp_path / names[-1], np.clip(frame, 0, 1), bits=16)
    write_png(tmp_path / "dark.png", np.full((h, w), 1e-3), bits=16)
    capture = _capture(tmp_path, images=names, dark_frame="dark.png", pattern=pattern)
    assert any(re.search(r"sit at their channel's lowest \(Y 0; ", n) for n in capture.notes)
    raw = np.stack([read_image(tmp_path / n).pixels[..., 0] for n in names])
    np.testing.assert_array_equal(capture.floored[..., 0], raw == 0)
    assert capture.sample_mask.all()  # the fit decides
    data = prepare_data(
        capture.images[..., 0],
        capture.pattern,
        mask=capture.sample_mask[..., 0],
        floored=capture.floored[..., 0],
    )
    np.testing.assert_array_equal(data.valid, raw > 0)
    dark = read_image(tmp_path / "dark.png").pixels[..., 0]
    np.testing.assert_allclose(data.floor_level, np.broadcast_to(-dark, raw.shape), atol=1e-7)


@pytest.mark.parametrize("value", [1e30, -1e6])
def test_corrupt_pixel_values_are_masked_with_a_warning(tmp_path, value):
    """Before: one pixel of 1e30 ended the fit in 'the basin scan found no valid model'
    without naming it, one of −1e6 in an unidentifiable σt."""
    names = _images(tmp_path)
    bad = np.full((H, W), 0.3)
    bad[2, 3] = value
    write_exr(tmp_path / names[1], {"Y": bad})
    with pytest.warns(CaptureWarning) as caught:
        capture = _capture(tmp_path, images=names)
    said = [str(w.message) for w in caught]
    assert any(re.search(r"1 pixel value\(s\) beyond 10000 times .* s1\.exr", m) for m in said)
    assert capture.n_masked["nonfinite"] == 1 and not capture.mask[2, 3, 0]
    assert np.abs(capture.images).max() < 1


def test_clipped_float_images_are_masked_with_a_warning(tmp_path):
    """Float files carry no top code: a clip shows as many values equal to the largest
    (before: not seen, and the fit ran on the clipped values)."""
    names = _images(tmp_path)
    for name in names:
        pixels = read_image(tmp_path / name).pixels[..., 0]
        write_exr(tmp_path / name, {"Y": np.minimum(pixels, 0.45)})
    with pytest.warns(CaptureWarning, match=r"float pixel values equal the images' largest, 0\.45"):
        capture = _capture(tmp_path, images=names)
    assert capture.n_masked["saturated"] > 0
    clipped = np.any([read_image(tmp_path / n).pixels[..., 0] >= 0.45 for n in names], axis=0)
    assert np.array_equal(~capture.mask[..., 0], clipped)
    # RGB, each channel's own clip (a white balance scales them): G clipped at 0.45
    # while R, brighter and unclipped, reaches 0.9 (before: G's clip went unseen).
    plain = _images(tmp_path, prefix="p")
    rgb = []
    for i, (name, free) in enumerate(zip(names, plain, strict=True)):
        g = read_image(tmp_path / name).pixels[..., 0]
        y = read_image(tmp_path / free).pixels[..., 0]
        rgb.append(f"rgb{i}.exr")
        write_exr(tmp_path / rgb[-1], {"R": 2 * y, "G": g, "B": 0.5 * y})
    with pytest.warns(CaptureWarning, match=r"equal their channel's largest \(G 0\.45\)"):
        capture = _capture(tmp_path, images=rgb)
    assert np.array_equal(~capture.mask[..., 1], clipped)
    assert capture.mask[..., 0].all() and capture.mask[..., 2].all()
    # Unclipped measured values: nothing is masked.
    with warnings.catch_warnings():
        warnings.simplefilter("error", CaptureWarning)
        assert _capture(tmp_path, images=plain).mask.all()


def test_truth_per_channel(tmp_path):
    """An RGB capture's media differ by channel: truth takes a list, one per channel."""
    names = _images(tmp_path)
    truth = {"sigma_t": [0.2], "sigma_s": [0.05], "g": 0.4}
    capture = _capture(tmp_path, images=names, truth=truth)
    assert capture.truth["sigma_t"] == [0.2] and capture.truth["g"] == 0.4
    _error(
        tmp_path,
        r"truth\.sigma_t: a list gives one value per channel: 1 here, got 3",
        images=names,
        truth={**truth, "sigma_t": [0.2, 0.3, 0.4]},
    )
    _error(
        tmp_path,
        r"truth\.sigma_s: must satisfy 0 <= sigma_s <= sigma_t",
        images=names,
        truth={**truth, "sigma_s": [0.5]},
    )


def test_truth_as_a_list_of_one_medium_per_channel(tmp_path):
    """``truth: [{...}, {...}, {...}]`` (one medium per channel, as the README's "a list
    per channel" reads) was refused: only a mapping of lists was taken."""
    rng = np.random.default_rng(0)
    np.save(tmp_path / "rgb.npy", rng.uniform(0.1, 0.5, (P, H, W, 3)).astype(np.float32))
    text = "images: rgb.npy\npattern: {period: 6, lit: 3}\ntruth: [{}, {}, {}]\n"
    media = "[{sigma_t: 0.2, g: 0.8}, {sigma_t: 0.3, g: 0.7}, {sigma_t: 0.4, g: 0.6}]"
    capture = _capture(tmp_path, text=text.replace("[{}, {}, {}]", media))
    assert capture.truth == {"sigma_t": [0.2, 0.3, 0.4], "g": [0.8, 0.7, 0.6]}
    _error(
        tmp_path,
        r"truth: a list gives one mapping per channel: 3 here, got 2",
        text=text.replace("[{}, {}, {}]", "[{g: 0.8}, {g: 0.7}]"),
    )
    _error(
        tmp_path,
        r"truth\[1\]: sigma_t: given for another channel but not this one",
        text=text.replace("[{}, {}, {}]", "[{sigma_t: 0.2}, {g: 0.7}, {sigma_t: 0.4}]"),
    )
    _error(
        tmp_path,
        r"truth\.g\[2\]: must be a number",
        text=text.replace("[{}, {}, {}]", "[{g: 0.8}, {g: 0.7}, {g: high}]"),
    )


def _srgb_capture(folder, response=None, flat=None):
    """Three 16-bit PNGs written through the sRGB curve (with a dark frame and, where
    given, a flat field's vignetting) and their capture file; returns the linear light."""
    from lightfield_jax.capture.response import srgb_response

    encode = srgb_response().encode
    rng = np.random.default_rng(3)
    light = rng.uniform(0.002, 0.8, (P, 16, 24))
    dark = 0.05
    vignetting = np.ones((16, 24)) if flat is None else flat
    names = [f"s{i}.png" for i in range(P)]
    for name, x in zip(names, light, strict=True):
        write_png(folder / name, encode(x * vignetting + dark), bits=16)
    write_png(folder / "dark.png", encode(np.full((16, 24), dark)), bits=16)
    text = f"images: {names}\ndark_frame: dark.png\npattern: {{phases: [0, 2, 4]}}\n"
    if flat is not None:
        write_png(folder / "flat.png", encode(0.7 * vignetting + dark), bits=16)
        text += "flat_field: flat.png\n"
    if response is not None:
        text += f"response: {response}\n"
    return light, text


def test_srgb_encoded_single_exposures_are_linearised(tmp_path):
    """Phones and most cameras write sRGB-encoded files: `response: srgb` linearises the
    codes of the images and the calibration frames before the dark frame and the flat
    field; read as linear (the default) the same files are not the light."""
    vignetting = np.linspace(0.8, 1.0, 24)[None, :] * np.ones((16, 1))
    light, text = _srgb_capture(tmp_path, "srgb", flat=vignetting)
    capture = _capture(tmp_path, text=text)
    assert capture.response_record() == {"kind": "srgb", "source": None}
    assert any(n.startswith("response: srgb: ") for n in capture.notes)
    expected = light * np.median(vignetting)
    np.testing.assert_allclose(capture.images[..., 0], expected, rtol=2e-3, atol=2e-5)
    plain = _capture(tmp_path, text=text.replace("response: srgb\n", ""))
    assert plain.response.kind == "linear"
    assert np.max(np.abs(plain.images[..., 0] / expected - 1)) > 0.5


def test_a_float_flat_field_is_linear_under_a_response(tmp_path):
    """A float (EXR) flat field holds linear values: only integer codes go through the
    curve (decoded as sRGB, a linear vignetting 0.3-1 slowed a fit 60x and left it
    σt 17 % off)."""
    vignetting = np.linspace(0.3, 1.0, 24)[None, :] * np.ones((16, 1))
    light, text = _srgb_capture(tmp_path, "srgb", flat=vignetting)
    write_exr(tmp_path / "flat.exr", {"Y": (0.7 * vignetting + 0.05).astype(np.float32)})
    capture = _capture(tmp_path, text=text.replace("flat.png", "flat.exr"))
    expected = light * np.median(vignetting)
    np.testing.assert_allclose(capture.images[..., 0], expected, rtol=2e-3, atol=2e-5)


def test_a_response_table_linearises_single_exposures(tmp_path):
    from lightfield_jax.capture.response import srgb_response, write_response

    light, text = _srgb_capture(tmp_path, "curve.csv")
    write_response(tmp_path / "curve.csv", srgb_response(), ["Y"])
    capture = _capture(tmp_path, text=text)
    assert capture.response.kind == "file"
    np.testing.assert_allclose(capture.images[..., 0], light, rtol=2e-3, atol=2e-5)


def test_single_exposure_response_errors(tmp_path):
    _, text = _srgb_capture(tmp_path, "auto")
    with pytest.raises(CaptureError, match=r"response: auto recovers .* from exposure brackets"):
        _capture(tmp_path, text=text)
    with pytest.raises(CaptureError, match=r"response: must be linear or srgb or auto or a file"):
        _capture(tmp_path, text=text.replace("response: auto", "response: 2.2"))
    with pytest.raises(CaptureError, match=r"response: write 'srgb' in lower case, got 'sRGB'"):
        _capture(tmp_path, text=text.replace("response: auto", "response: sRGB"))
    (tmp_path / "flat.csv").write_text("0, 0.3\n1, 0.3\n")
    with pytest.raises(CaptureError, match=r"response: .*flat.csv: x is constant"):
        _capture(tmp_path, text=text.replace("response: auto", "response: flat.csv"))
    names = _images(tmp_path, fill=1.5, prefix="bright")
    text = f"images: {names}\npattern: {{phases: [0, 2, 4]}}\nresponse: srgb\n"
    with pytest.raises(CaptureError) as info:
        _capture(tmp_path, text=text)
    message = str(info.value)
    assert "\n" not in message
    assert re.search(
        r"response: srgb maps a camera's integer codes .* images\[0\] \(bright0.exr\)", message
    )


@pytest.mark.slow
def test_fit_of_an_srgb_encoded_8bit_capture(tmp_path):
    """A noisy capture of the paper's milk written as 8-bit sRGB PNGs (a phone's files):
    with `response: srgb` the fit recovers the medium; read as linear the same files are
    reported not trustworthy, never a converged wrong answer."""
    from lightfield_jax.capture.response import srgb_response

    truth = {"sigma_t": 0.2051, "sigma_s": 0.0366, "g": 0.4}
    config = {
        "grid": {"width": 48, "height": 36},
        "medium": {**truth, "phase": "paper"},
        "illumination": {"kind": "stripes", "period": 6, "lit": 3, "shifts": 6},
    }
    peak = float(simulate_capture(parse_simulation_config(config)).images.max())
    config |= {"gain": 0.9 / peak, "noise": {"photons": 2e4, "read": 5e-4, "seed": 1}}
    images = np.asarray(simulate_capture(parse_simulation_config(config)).images)
    names = [f"s{i}.png" for i in range(6)]
    for name, image in zip(names, images, strict=True):
        write_png(tmp_path / name, srgb_response().encode(np.clip(image, 0, 1)), bits=8)
    text = (
        f"images: {names}\npattern: {{period: 6, lit: 3, phases: [0, 1, 2, 3, 4, 5]}}\n"
        "fit: {phase: paper}\n"  # the simulation's convention
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CaptureWarning)
        fit = capture_fit.fit_capture(_capture(tmp_path, text=text + "response: srgb\n"))
        plain = capture_fit.fit_capture(_capture(tmp_path, text=text))
    result = fit.results[0]
    assert result.converged, result.reasons
    assert abs(result.sigma_t / truth["sigma_t"] - 1) < 0.005
    assert abs(result.sigma_s / truth["sigma_s"] - 1) < 0.02
    assert abs(result.g - truth["g"]) < 0.01
    assert not plain.results[0].converged


def test_fit_capture_takes_a_path_and_refuses_other_things(tmp_path):
    with pytest.raises(CaptureFileNotFoundError, match="missing.yaml: file not found"):
        capture_fit.fit_capture(tmp_path / "missing.yaml")
    with pytest.raises(TypeError, match=r"^fit_capture: expected a capture .* got int$"):
        capture_fit.fit_capture(42)
    _, text = _srgb_capture(tmp_path, "srgb")
    (tmp_path / "capture.yaml").write_text(text)
    with pytest.raises(ValueError, match=r"channel: 'nope' is not in the capture \(it has Y; "):
        capture_fit.fit_capture(str(tmp_path / "capture.yaml"), channels=["nope"])
    with pytest.raises(ValueError, match=r"channel: 'Y' chosen more than once"):
        capture_fit.fit_capture(str(tmp_path / "capture.yaml"), channels=["Y", "Y"])
    with pytest.raises(ValueError, match=r"channel: no channel chosen"):
        capture_fit.fit_capture(str(tmp_path / "capture.yaml"), channels=[])


def test_a_float_floor_is_a_cut_only_where_the_images_show_read_noise(tmp_path):
    """Float frames: zeros of shot noise alone are measured (nothing falls below 0
    without an additive noise) and stay; read noise clamped at 0 is a floor. An
    integer file's lowest code is always a cut (test_16bit_frames_clamped_at_0...)."""
    h, w = 24, 48
    rng = np.random.default_rng(4)
    lit = (np.arange(h)[:, None, None] + np.arange(6)[None, None, :]) % 6 < 3
    light = np.where(lit, 1.0, 0.05) * np.exp(-0.15 * np.arange(w))[None, :, None]
    pattern = Stripes(period=6, lit=3, phases=tuple(range(6)))
    shot = rng.poisson(light * 2e3) / 2e3
    read = np.clip(light + rng.normal(0, 2e-3, light.shape), 0, None)
    for name, frames in (("shot", shot), ("read", read)):
        names = [f"{name}{i}.exr" for i in range(6)]
        for i, n in enumerate(names):
            write_exr(tmp_path / n, {"Y": frames[..., i].astype(np.float32)})
        capture = _capture(tmp_path, images=names, pattern=pattern)
        assert np.mean(frames == 0) > 0.03, name
        if name == "shot":
            assert not capture.floored.any()
        else:
            np.testing.assert_array_equal(capture.floored[..., 0], np.moveaxis(frames, -1, 0) == 0)


def test_black_level_auto_against_a_uniform_white_frame_is_refused(tmp_path):
    names = _images(tmp_path)
    (white,) = _images(tmp_path, n=1, fill=0.5, prefix="white")
    (black,) = _images(tmp_path, n=1, fill=0.02, prefix="black")
    _error(
        tmp_path,
        r"white_frame: white0\.\w+: every pixel value is 0\.5: not a camera image",
        images=names,
        white_frame=white,
        black_frame=black,
        black_level="auto",
    )


def test_a_table_of_every_channel_serves_one_chosen_channel(tmp_path):
    """`inspect --response` on RGB brackets writes one column per channel, named in its
    header; a capture that chooses one channel (`channel: G`) takes that column."""
    from lightfield_jax.capture.response import Response, srgb_response, write_response

    srgb = srgb_response()
    codes = np.linspace(0, 1, 257)
    gains = np.array([0.5, 2.0, 1.0])  # a different curve per channel
    curves = srgb.linearize(codes[:, None]) * gains
    write_response(tmp_path / "rgb.csv", Response("file", codes, curves), ["R", "G", "B"])
    rng = np.random.default_rng(1)
    z = rng.uniform(0.05, 0.95, (P, H, W, 3))
    names = [f"c{i}.png" for i in range(P)]
    for name, image in zip(names, z, strict=True):
        write_png(tmp_path / name, image, bits=16)
    text = f"images: {names}\npattern: {{phases: [0, 2, 4]}}\nresponse: rgb.csv\n"
    green = _capture(tmp_path, text=text + "channel: G\n")
    assert green.channel_names == ("G",)
    coded = np.stack([read_image(tmp_path / n).pixels[..., 1] for n in names])
    expected = np.interp(coded, codes, curves[:, 1])
    np.testing.assert_allclose(green.images[..., 0], expected, rtol=1e-5)
    every = _capture(tmp_path, text=text)
    np.testing.assert_allclose(every.images[..., 1], expected, rtol=1e-5)


def test_a_response_counts_12_bit_codes_to_their_top_code(tmp_path):
    """12-bit data in 16-bit files: the response maps codes counted to 4095, as the
    brackets' merge and the tables it writes count them."""
    from lightfield_jax.capture.response import srgb_response

    rng = np.random.default_rng(2)
    codes = rng.integers(50, 4000, (P, H, W)).astype(np.uint16)
    codes[:, 0, :2] = 4095  # clipped at the sensor's top code
    names = [f"t{i}.png" for i in range(P)]
    for name, c in zip(names, codes, strict=True):
        write_png(tmp_path / name, c, bits=16)
    text = f"images: {names}\npattern: {{phases: [0, 2, 4]}}\nresponse: srgb\n"
    with pytest.warns(CaptureWarning, match="clipped at their top code 4095"):
        capture = _capture(tmp_path, text=text)
    expected = srgb_response().linearize(codes[..., None] / 4095.0)[..., 0]
    keep = capture.sample_mask[..., 0]
    np.testing.assert_allclose(capture.images[..., 0][keep], expected[keep], rtol=1e-5)
    assert not keep[:, 0, :2].any()  # the top code is masked as clipped


def test_a_response_table_header_orders_its_columns(tmp_path):
    """Columns named in a table's header are taken by name, whatever their order; a
    header naming other channels is refused."""
    from lightfield_jax.capture.response import Response, srgb_response, write_response

    codes = np.linspace(0, 1, 257)
    curves = srgb_response().linearize(codes[:, None]) * np.array([0.5, 2.0, 1.0])
    write_response(tmp_path / "bgr.csv", Response("file", codes, curves), ["B", "G", "R"])
    rng = np.random.default_rng(1)
    names = [f"c{i}.png" for i in range(P)]
    for name in names:
        write_png(tmp_path / name, rng.uniform(0.05, 0.95, (H, W, 3)), bits=16)
    text = f"images: {names}\npattern: {{phases: [0, 2, 4]}}\nresponse: bgr.csv\n"
    capture = _capture(tmp_path, text=text)
    coded = np.stack([read_image(tmp_path / n).pixels for n in names])
    for c, column in enumerate((2, 1, 0)):  # R, G, B from the B, G, R columns
        expected = np.interp(coded[..., c], codes, curves[:, column])
        np.testing.assert_allclose(capture.images[..., c], expected, rtol=1e-5)
    write_response(tmp_path / "xyz.csv", Response("file", codes, curves), ["X", "Y", "Z"])
    with pytest.raises(CaptureError, match=r"xyz.csv: its header names the channels X, Y, Z"):
        _capture(tmp_path, text=text.replace("bgr.csv", "xyz.csv"))


def test_a_dark_level_is_subtracted_like_a_dark_frame_of_that_value(simulated, tmp_path):
    """simulate's dark frame is its constant dark level (0.02): ``dark_level: 0.02``
    instead of the frame gives the same images."""
    _, folder = simulated
    with_frame = load_capture(folder / "capture.yaml")
    text = (folder / "capture.yaml").read_text().replace("dark_frame: dark.exr", "dark_level: 0.02")
    assert "dark_level" in text
    path = folder / "capture_level.yaml"
    path.write_text(text)
    capture = load_capture(path)
    assert capture.dark_level == 0.02 and capture.dark_frame is None
    np.testing.assert_allclose(capture.images, with_frame.images, atol=1e-7)
    assert "dark_level: 0.02 subtracted from every image" in capture.notes
    # Without it the pedestal stays in the images.
    path.write_text(text.replace("dark_level: 0.02", ""))
    assert load_capture(path).images.min() > 0.019


def test_dark_level_refusals(tmp_path):
    names = _images(tmp_path)
    write_exr(tmp_path / "dark.exr", {"Y": np.zeros((H, W))})
    base = f"images: {names}\npattern: {{period: 6, lit: 3, phases: [0, 2, 4]}}\n"

    def refused(extra, match):
        (tmp_path / "capture.yaml").write_text(base + extra)
        with pytest.raises(CaptureError, match=match) as info:
            load_capture(tmp_path / "capture.yaml")
        assert "\n" not in str(info.value)

    refused("dark_level: 0.01\ndark_frame: dark.exr\n", "dark_level: give a dark_frame or a")
    refused("dark_level: -0.01\n", r"dark_level: must be a finite value >= 0, got -0\.01")
    # Above the pedestal: values in [0.1, 0.5] less 0.3 (44 % below zero).
    refused("dark_level: 0.3\n", r"dark_level: 0\.3 is above the camera's pedestal: .* 4\d% of")
    assert _capture(tmp_path, text=base + "dark_level: 0\n").dark_level is None  # none
    # Integer files: a value in codes is named as such, with its image value.
    for i, name in enumerate(names):
        write_png(tmp_path / f"c{i}.png", read_image(tmp_path / name).pixels[..., 0], bits=16)
    pngs = [f"c{i}.png" for i in range(P)]
    base = f"images: {pngs}\npattern: {{period: 6, lit: 3, phases: [0, 2, 4]}}\n"
    refused(
        "dark_level: 2048\n",
        r"dark_level: 2048 is not an image value of these 16-bit files .* dark_level: "
        r"0\.0312505 \(2048/65535\)",
    )
    refused("dark_level: 0.01\nresponse: srgb\n", "dark_level: applies to linear images")
    capture = _capture(tmp_path, text=base + "dark_level: 0.05\n")
    raw = np.stack([read_image(tmp_path / p).pixels for p in pngs])
    np.testing.assert_allclose(capture.images, raw - 0.05, atol=1e-6)


def test_a_dark_level_per_channel_by_name(tmp_path):
    """An RGB camera whose channels have pedestals of their own: ``dark_level`` as one
    value per channel name, subtracted from each; a name the images lack, a channel
    without a value and a list (whose order the user might not know) are refused; with
    ``channel:`` the mapping names the channels loaded."""
    rng = np.random.default_rng(1)
    names = []
    for i in range(P):
        names.append(f"rgb{i}.exr")
        write_exr(tmp_path / names[-1], {c: rng.uniform(0.1, 0.5, (H, W)) for c in "RGB"})
    base = f"images: {names}\npattern: {{period: 6, lit: 3, phases: [0, 2, 4]}}\n"
    raw = np.stack([read_image(tmp_path / n).pixels for n in names])
    capture = _capture(tmp_path, text=base + "dark_level: {R: 0.03, G: 0.01, B: 0.02}\n")
    assert capture.channel_names == ("R", "G", "B")
    np.testing.assert_allclose(capture.images, raw - [0.03, 0.01, 0.02], atol=1e-6)
    assert "dark_level: [0.03, 0.01, 0.02] subtracted from every image" in capture.notes

    def refused(extra, match):
        (tmp_path / "capture.yaml").write_text(base + extra)
        with pytest.raises(CaptureError, match=match) as info:
            load_capture(tmp_path / "capture.yaml")
        assert "\n" not in str(info.value)

    refused(
        "dark_level: {R: 0.03, G: 0.01, Y: 0.02}\n",
        r"dark_level\.Y: no channel named 'Y' in the images; channels: R, G, B",
    )
    refused("dark_level: {R: 0.03, G: 0.01}\n", r"dark_level: no value for channel B")
    refused("dark_level: [0.03, 0.01, 0.02]\n", r"dark_level: one value, or one per channel")
    refused("dark_level: {R: 0.03, G: -1, B: 0.02}\n", r"dark_level\.G: must be a finite value")
    refused(
        "dark_level: {R: 0.03, G: 0.4, B: 0.02}\n",
        r"dark_level: \[0\.03, 0\.4, 0\.02\] is above the camera's pedestal",
    )
    green = _capture(tmp_path, text=base + "channel: G\ndark_level: {G: 0.01}\n")
    np.testing.assert_allclose(green.images[..., 0], raw[..., 1] - 0.01, atol=1e-6)


def test_help_of_load_capture_describes_the_files_keys():
    """``help(lfj.load_capture)``, which the README points to, said only "see the module
    docstring"."""
    import pydoc

    text = pydoc.render_doc(lfj.load_capture, renderer=pydoc.plaintext)
    assert "see the module docstring" not in text
    for key in ("images", "pattern", "dark_frame", "medium_roi", "fit", "truth", "phase"):
        assert f"``{key}``" in text, key
