"""The real-capture path: projector patterns and their capture template, geometry and
black level measured from the images, calibration frames, raw-file checks, inspect, and
per-channel fits of a synthetic camera capture.

The synthetic capture is rendered with the package (oblique stripes, one medium per
colour channel, a projector black level), embedded in a larger dark camera frame (so the
medium has an ROI), with a dark level, shot and read noise and a few saturated pixels,
and written as 16-bit TIFF (through the template of ``lightfield-jax pattern``) and
16-bit PNG; the pipeline must recover what was put in.
"""

import dataclasses
import json
import math
import re
import subprocess
import sys
import warnings

import numpy as np
import pytest
import yaml

import lightfield_jax as lfj
import lightfield_jax.inverse.capture_fit as capture_fit_module
import lightfield_jax.viz as viz
from lightfield_jax.app.cli import main
from lightfield_jax.capture.calibration import mosaic_score
from lightfield_jax.capture.capture import CaptureWarning
from lightfield_jax.capture.detect import detect_geometry
from lightfield_jax.capture.image_write import write_exr, write_png, write_tiff
from lightfield_jax.capture.inspect import inspect_capture
from lightfield_jax.capture.io import CaptureError, read_image
from lightfield_jax.capture.loading import load_capture
from lightfield_jax.capture.pattern import pattern_phases, stripe_patterns

# The medium: a W x H rectangle at (X0, Y0) of a FRAME_H x FRAME_W camera frame.
W, H, X0, Y0 = 36, 28, 11, 9
FRAME_H, FRAME_W = 48, 64
ROI = (X0, Y0, X0 + W, Y0 + H)
DIRECTION = 10.0
BLACK = 0.03
DARK = 0.02
PERIOD, LIT = 6, 3
PHASES = (0, 1, 2, 3, 4, 5)  # counted from the ROI's edge
PHASES_FULL = tuple((p - Y0) % PERIOD for p in PHASES)  # counted from the frame's edge
MEDIA = {"R": (0.06, 0.03, 0.3), "G": (0.075, 0.04, 0.4), "B": (0.09, 0.06, 0.5)}
GAINS = {"R": 1.0, "G": 0.8, "B": 1.2}
STRIPES = "pattern: {period: 6, lit: 3}\n"


def _render(media, direction=DIRECTION, phases=PHASES, width=W, height=H, entry="left"):
    """Stripe renders [P, H, W, C] and the full illumination [H, W, C] (Σ shifts / lit),
    at unit gain, float32 (fast), black level not applied."""
    pattern = lfj.Stripes(PERIOD, LIT, phases, direction_deg=direction, entry=entry)
    renderer = lfj.Renderer(lfj.Grid(width, height, 16, 1), pattern, 6)
    stripes = []
    for st, ss, g in media:
        images = renderer(np.float32(st), np.float32(ss), np.float32(g))[0]
        stripes.append(np.asarray(images.sum(axis=1), np.float64))
    stripes = np.stack(stripes, axis=-1)
    return stripes, stripes.sum(axis=0) / LIT


def _camera(rng, light, scale):
    """A camera frame of ``light`` (cropped-frame units): embedded at the ROI, dark level,
    shot and read noise, clipped at 1."""
    frame = np.zeros(light.shape[:-3] + (FRAME_H, FRAME_W) + light.shape[-1:])
    frame[..., Y0 : Y0 + H, X0 : X0 + W, :] = scale * light
    frame = frame + DARK
    noisy = frame + rng.normal(0.0, 1.0, frame.shape) * np.sqrt(2e-5 * frame + 0.0015**2)
    return np.clip(noisy, 0.0, 1.0)


@pytest.fixture(scope="module")
def rgb(tmp_path_factory):
    """The synthetic RGB camera capture, written through the pattern command's template
    (16-bit TIFF) and as 16-bit PNG; returns (template folder, png folder, raw arrays)."""
    stripes, full = _render(list(MEDIA.values()))
    gains = np.array(list(GAINS.values()))
    stripes, full = stripes * gains, full * gains
    shots = (1.0 - BLACK) * stripes + BLACK * full[None]
    scale = 1.03 / shots.max()  # the brightest pixels at the entry wall clip
    rng = np.random.default_rng(7)
    frames = {
        "stripes": _camera(rng, shots, scale),
        "white": _camera(rng, full, scale),
        "black": _camera(rng, BLACK * full, scale),
        "dark": np.clip(DARK + rng.normal(0.0, 0.0015, (FRAME_H, FRAME_W, 3)), 0, 1),
    }
    folder = tmp_path_factory.mktemp("camera")
    assert main(["pattern", "--width", "64", "--height", "40", "--out", str(folder), "-q"]) == 0
    template = yaml.safe_load((folder / "capture.yaml").read_text())
    for name, frame in zip(template["images"], frames["stripes"], strict=True):
        write_tiff(folder / name, frame, bits=16)
    write_tiff(folder / template["white_frame"], frames["white"], bits=16)
    write_tiff(folder / template["black_frame"], frames["black"], bits=16)
    write_tiff(folder / "camera_dark.tif", frames["dark"], bits=16)
    text = (folder / "capture.yaml").read_text()
    text = text.replace("# dark_frame: camera_dark.tif", "dark_frame: camera_dark.tif")
    (folder / "capture.yaml").write_text(text)

    png = tmp_path_factory.mktemp("png")
    names = []
    for i, frame in enumerate(frames["stripes"]):
        names.append(f"shot_{i}.png")
        write_png(png / names[-1], frame, bits=16)
    write_png(png / "black.png", frames["black"], bits=16)
    write_png(png / "dark.png", frames["dark"], bits=16)
    return folder, png, names, frames


@pytest.fixture(scope="module")
def loaded(rgb):
    folder = rgb[0]
    with pytest.warns(CaptureWarning, match=r"clipped at their top code 65535"):
        return load_capture(folder / "capture.yaml")


# ----------------------------------------------------------------------- pattern command


def test_pattern_writes_the_stripes_size_on_the_camera_from_a_measured_scale(tmp_path, capsys):
    """``--period`` is in projector pixels, the capture file's period in camera pixels
    (the model's unit): the template said they were the same, always."""
    out = tmp_path / "projector"
    argv = ["pattern", "--width", "30", "--height", "20", "--period", "3", "--lit", "1"]
    assert main([*argv, "--camera-px-per-projector-px", "2", "--out", str(out)]) == 0
    assert "(period 6, lit 2 camera px at 2 camera px per projector px)" in capsys.readouterr().out
    template = yaml.safe_load((out / "capture.yaml").read_text())
    assert template["pattern"]["period"] == 6 and template["pattern"]["lit"] == 2
    assert "fit: {phase: normalized}" in (out / "capture.yaml").read_text()
    # A scale that puts a stripe between camera pixels is refused, naming the option.
    status = main([*argv, "--camera-px-per-projector-px", "1.5", "--out", str(tmp_path / "b")])
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1, err
    assert "--camera-px-per-projector-px: 1.5 puts a period of 3 projector px on 4.5" in err
    assert not (tmp_path / "b").exists()


def test_pattern_command_writes_stripes_white_black_and_template(tmp_path, capsys):
    out = tmp_path / "projector"
    status = main(
        [
            "pattern",
            "--width",
            "30",
            "--height",
            "20",
            "--shifts",
            "3",
            "--orientation",
            "columns",
            "--out",
            str(out),
        ]
    )
    assert status == 0
    assert "phases [0, 2, 4]" in capsys.readouterr().out
    names = {p.name for p in out.iterdir()}
    assert names == {
        "stripe_00.png",
        "stripe_01.png",
        "stripe_02.png",
        "white.png",
        "black.png",
        "capture.yaml",
    }
    for k, phase in enumerate((0, 2, 4)):
        image = read_image(out / f"stripe_{k:02d}.png")
        assert image.sample_type == "uint8" and image.pixels.shape == (20, 30, 1)
        lit = (np.arange(30) + phase) % 6 < 3
        np.testing.assert_array_equal(image.pixels[..., 0], np.broadcast_to(lit, (20, 30)))
    assert read_image(out / "white.png").pixels.min() == 1.0
    assert read_image(out / "black.png").pixels.max() == 0.0
    template = yaml.safe_load((out / "capture.yaml").read_text())
    assert template["images"] == [f"camera_stripe_{k:02d}.tif" for k in range(3)]
    assert template["pattern"] == {
        "period": 6,
        "lit": 3,
        "phases": "auto",
        "entry": "auto",
        "direction_deg": "auto",
    }
    assert template["medium_roi"] == "auto" and template["black_level"] == "auto"
    assert template["white_frame"] == "camera_white.tif"
    text = (out / "capture.yaml").read_text()
    for key in (
        "images:",
        "phases:",
        "entry:",
        "direction_deg:",
        "medium_roi:",
        "white_frame:",
        "black_frame:",
        "black_level:",
        "dark_frame:",
        "flat_field:",
    ):
        lines = text.splitlines()
        i = next(i for i, li in enumerate(lines) if key in li)
        assert "#" in lines[i] or lines[i - 1].startswith("#"), f"{key} has no comment"


def test_pattern_refuses_shifts_that_cannot_separate(tmp_path, capsys):
    assert pattern_phases(6, 3, 2) == (0, 3)
    with pytest.raises(ValueError, match=r"leave rows 1, 3, 5 never lit \(phases \[0, 2, 4\]\)"):
        stripe_patterns(12, 12, period=6, lit=1, shifts=3)
    status = main(
        ["pattern", "--width", "8", "--height", "8", "--shifts", "7", "--out", str(tmp_path / "p")]
    )
    err = capsys.readouterr().err
    assert status == 2 and "pattern.shifts: must be an integer in [2, period]" in err
    assert not (tmp_path / "p").exists()


# ------------------------------------------------------------------------- detection


def test_template_capture_recovers_roi_direction_phases_and_black_level(loaded):
    c = loaded
    assert c.roi == ROI  # within 1 px: exactly, here
    assert c.pattern.entry == "left"
    assert abs(c.pattern.direction_deg - DIRECTION) < 0.2
    assert c.pattern.phases == PHASES
    assert abs(c.black_level - BLACK) < 0.01
    assert c.black_level_estimate.method.startswith(
        "slope of the all-black frame against the all-white"
    )
    det = c.detected
    assert det.confidence > 0.8 and det.given == ()
    assert det.edges == {"left": "wall", "right": "wall", "top": "wall", "bottom": "wall"}
    assert abs(det.period_px - PERIOD) < 0.05 and det.phase_offset < 0.1
    assert any(n.startswith("detected: medium_roi [11, 9, 47, 37]") for n in c.notes)
    assert any(n.startswith("black_level: auto: 0.0") for n in c.notes)
    # The clipped pixels sit at the entry wall, and are masked.
    assert c.n_masked["saturated"] > 0
    assert not c.mask[:, :2].all() and c.mask[:, 3:].all()
    assert c.images.shape == (6, H, W, 3) and c.channel_names == ("R", "G", "B")
    assert c.overview.shape == (FRAME_H, FRAME_W, 3)


def test_given_values_override_detection_png(rgb):
    _, png, names, _ = rgb
    base = (
        f"images: {names}\ndark_frame: dark.png\nblack_frame: black.png\n"
        "black_level: auto\nsaturation: 0.999\n"
    )
    # Everything measured, from 16-bit PNG, the black level against the mean of the shifts.
    (png / "capture.yaml").write_text(
        base + "medium_roi: auto\npattern: {phases: auto, entry: auto, direction_deg: auto}\n"
    )
    with pytest.warns(CaptureWarning, match="saturation 0.999"):
        c = load_capture(png / "capture.yaml")
    assert c.roi == ROI and c.pattern.phases == PHASES
    assert abs(c.pattern.direction_deg - DIRECTION) < 0.2
    assert abs(c.black_level - BLACK) < 0.01
    assert "against the mean of the shifts" in c.black_level_estimate.method
    # A given ROI (one pixel in from each side) and direction (within the detector's
    # tolerance of the stripes' 10 deg) are kept; the phases are measured inside them.
    (png / "capture.yaml").write_text(
        base + f"medium_roi: [{X0 + 1}, {Y0 + 1}, {X0 + W - 1}, {Y0 + H - 1}]\n"
        "pattern: {phases: auto, direction_deg: 9.8}\n"
    )
    with pytest.warns(CaptureWarning):
        c = load_capture(png / "capture.yaml")
    assert c.roi == (X0 + 1, Y0 + 1, X0 + W - 1, Y0 + H - 1)
    assert c.pattern.direction_deg == 9.8 and c.pattern.entry == "left"
    assert c.pattern.phases == tuple((p + 1) % PERIOD for p in PHASES)
    assert set(c.detected.given) == {"roi", "entry", "direction"}


def _wall_lit(phases, n, offset=0):
    """[P, n] lit wall cells of stripes with these phases, cells counted from ``offset``."""
    u = np.arange(n) + offset
    return (u[None] + np.array(phases)[:, None]) % PERIOD < LIT


@pytest.mark.parametrize("wall", ["left", "right", "top", "bottom"])
def test_detection_on_every_wall(wall):
    """Mirror and transpose one render (exact symmetries of the model) so that the light
    enters each wall; ROI, entry, direction and the lit wall cells must follow."""
    rng = np.random.default_rng(3)
    stripes, _ = _render([MEDIA["R"]], direction=-12.0, phases=(0, 2, 4))
    light, truth_lit, direction = stripes[..., 0], _wall_lit((0, 2, 4), H), -12.0
    if wall == "right":
        light, direction = light[..., ::-1], 180.0 + 12.0
    elif wall == "top":
        light, direction = np.swapaxes(light, 1, 2), 90.0 + 12.0
    elif wall == "bottom":
        # Transposed, then turned half a turn: the wall cells run backwards.
        light, direction = np.swapaxes(light, 1, 2)[:, ::-1, ::-1], 270.0 + 12.0
        truth_lit = truth_lit[:, ::-1]
    p, h, w = light.shape
    frame = np.zeros((p, h + 20, w + 14)) + DARK
    frame[:, 12 : 12 + h, 5 : 5 + w] += light / light.max()
    frame += rng.normal(0.0, 0.002, frame.shape)
    g = detect_geometry(frame, period=PERIOD, lit=LIT)
    assert g.roi == (5, 12, 5 + w, 12 + h)
    assert g.entry == wall
    assert abs(g.direction_deg - direction) < 0.2, g.summary()
    across = h if wall in ("left", "right") else w
    offset = 12 if wall in ("left", "right") else 5
    measured = _wall_lit(g.phases, across, offset)
    np.testing.assert_array_equal(measured, truth_lit)


def test_low_confidence_detection_warns(tmp_path):
    """Stripes that do not decay: nothing tells the entry wall from the far one."""
    frame = np.full((3, 30, 40), DARK)
    rows = _wall_lit((0, 2, 4), 20)[:, :, None]
    frame[:, 5:25, 6:34] += 0.5 * np.broadcast_to(rows, (3, 20, 28))
    names = []
    for i, f in enumerate(frame):
        names.append(f"f{i}.exr")
        write_exr(tmp_path / names[-1], {"Y": f})
    (tmp_path / "capture.yaml").write_text(
        f"images: {names}\nmedium_roi: auto\npattern: {{entry: auto}}\n"
    )
    with pytest.warns(CaptureWarning, match=r"low confidence 0\.\d\d .*entry 0\.0"):
        c = load_capture(tmp_path / "capture.yaml")
    assert c.roi == (6, 5, 34, 25)
    assert "low confidence" in c.warnings[0]


def test_detection_errors_name_the_keys(tmp_path):
    names = []
    for i in range(3):
        names.append(f"n{i}.exr")
        write_exr(tmp_path / names[-1], {"Y": np.full((20, 20), 0.01)})
    (tmp_path / "capture.yaml").write_text(f"images: {names}\nmedium_roi: auto\n{STRIPES}")
    with pytest.raises(
        CaptureError, match=r"capture\.yaml: medium_roi: auto: detect_geometry: no lit"
    ):
        load_capture(tmp_path / "capture.yaml")
    (tmp_path / "capture.yaml").write_text(f"images: {names}\npattern: {{phases: [0, 1]}}\n")
    with pytest.raises(CaptureError, match=r"pattern\.phases: lists 2 phase"):
        load_capture(tmp_path / "capture.yaml")
    (tmp_path / "capture.yaml").write_text(f"images: {names}\npattern: {{phases: some}}\n")
    with pytest.raises(
        CaptureError, match=r"pattern\.phases: must be a non-empty list .* or 'auto'"
    ):
        load_capture(tmp_path / "capture.yaml")
    (tmp_path / "capture.yaml").write_text(f"images: {names}\nmedium_roi: everything\n{STRIPES}")
    with pytest.raises(
        CaptureError, match=r"medium_roi: must be a list of 4 integers .* or 'auto'"
    ):
        load_capture(tmp_path / "capture.yaml")


# ------------------------------------------------------------------------ black level


def test_black_level_without_a_black_frame_is_an_upper_bound(rgb):
    _, png, names, _ = rgb
    (png / "capture.yaml").write_text(
        f"images: {names}\ndark_frame: dark.png\nblack_level: auto\nsaturation: 0.999\n"
        f"medium_roi: [{X0}, {Y0}, {X0 + W}, {Y0 + H}]\n"
        f"pattern: {{phases: {list(PHASES_FULL)}, direction_deg: {DIRECTION}}}\n"
    )
    with pytest.warns(CaptureWarning):
        c = load_capture(png / "capture.yaml")
    est = c.black_level_estimate
    assert est.upper_bound and "upper bound" in est.method
    assert BLACK - 0.005 < c.black_level < BLACK + 0.04


# ---------------------------------------------------------------------- calibration


def _exr_images(folder, planes, prefix="i"):
    names = []
    for i, plane in enumerate(planes):
        names.append(f"{prefix}{i}.exr")
        write_exr(folder / names[-1], {"Y": plane})
    return names


def test_flat_field_divides_the_images_and_masks_bad_pixels(tmp_path):
    y, x = np.mgrid[0:16, 0:20]
    vignette = 1.0 - 0.3 * (((x - 10) / 10) ** 2 + ((y - 8) / 8) ** 2) / 2
    names = _exr_images(tmp_path, [0.01 + 0.4 * vignette] * 3)
    flat = 0.01 + 0.8 * vignette
    flat[2, 3] = 0.0  # below the dark level: not a flat-field pixel
    write_exr(tmp_path / "flat.exr", {"Y": flat})
    write_exr(tmp_path / "dark.exr", {"Y": np.full((16, 20), 0.01)})
    (tmp_path / "capture.yaml").write_text(
        f"images: {names}\ndark_frame: dark.exr\nflat_field: flat.exr\n"
        "pattern: {phases: [0, 2, 4]}\n"
    )
    with pytest.warns(
        CaptureWarning, match=r"flat_field: 1 pixel value\(s\) of flat\.exr are not positive \(1 "
    ):
        c = load_capture(tmp_path / "capture.yaml")
    assert c.flat_field == tmp_path / "flat.exr" and not c.mask[2, 3, 0]
    median = float(np.median(0.8 * vignette))
    np.testing.assert_allclose(c.images[0][c.mask[..., 0]], 0.5 * median, rtol=2e-5)
    write_exr(tmp_path / "flat.exr", {"Y": np.zeros((16, 20))})
    with pytest.raises(
        CaptureError, match=r"flat_field: flat\.exr is not positive .* in 320 of its 320 pixel"
    ):
        load_capture(tmp_path / "capture.yaml")
    # A flat field clipped at its top code measures no vignetting there (before: taken,
    # and those pixels divided by a wrong flat, without a word).
    bright = np.minimum(1.05 * vignette, 1.0)
    write_png(tmp_path / "flat.png", bright, bits=16)
    (tmp_path / "capture.yaml").write_text(
        f"images: {names}\nflat_field: flat.png\npattern: {{phases: [0, 2, 4]}}\n"
    )
    with pytest.warns(CaptureWarning) as caught:
        c = load_capture(tmp_path / "capture.yaml")
    said = " ".join(str(w.message) for w in caught)
    assert re.search(r"flat_field: \d+ pixel value\(s\) of flat\.png sit at its top code", said)
    np.testing.assert_array_equal(c.mask[..., 0], bright < 1.0)
    # One overexposed at its top code nearly everywhere is said as such (before: "not
    # positive in 100% of its pixels", of a flat whose pixels were all bright).
    over = np.ones((16, 20))
    over[0, :2] = 0.5
    write_png(tmp_path / "flat.png", over, bits=16)
    with pytest.raises(CaptureError) as refused:
        load_capture(tmp_path / "capture.yaml")
    assert "flat.png is clipped at its top code in 318 of its 320 pixel values" in str(
        refused.value
    )
    # A perfectly flat float flat field is no clip: its one level is taken.
    write_exr(tmp_path / "flat.exr", {"Y": np.ones((16, 20))})
    (tmp_path / "capture.yaml").write_text(
        f"images: {names}\nflat_field: flat.exr\npattern: {{phases: [0, 2, 4]}}\n"
    )
    assert load_capture(tmp_path / "capture.yaml").mask.all()


# -------------------------------------------------------------------------- raw files


def test_mixed_bit_depths_are_refused(tmp_path):
    a = np.full((12, 16), 0.3)
    write_png(tmp_path / "a.png", a, bits=16)
    write_png(tmp_path / "b.png", a, bits=8)
    # Each shift its own exposure (one file listed twice, or a copied one, is a warning).
    write_png(tmp_path / "a2.png", a + 0.01, bits=16)
    (tmp_path / "capture.yaml").write_text(f"images: [a.png, b.png, a2.png]\n{STRIPES}")
    with pytest.raises(
        CaptureError,
        match=r"capture\.yaml: images\[1\]: b\.png is 8-bit integer \(uint8\) but images\[0\] "
        r"\(a\.png\) is 16-bit integer \(uint16\)",
    ):
        load_capture(tmp_path / "capture.yaml")
    write_exr(tmp_path / "c.exr", {"Y": a})
    write_exr(tmp_path / "c2.exr", {"Y": a + 0.01})
    (tmp_path / "capture.yaml").write_text(f"images: [a.png, c.exr]\n{STRIPES}")
    with pytest.raises(CaptureError, match=r"c\.exr is 32-bit float"):
        load_capture(tmp_path / "capture.yaml")
    # An integer calibration frame of another depth is refused; a float one is taken.
    (tmp_path / "capture.yaml").write_text(f"images: [a.png, a2.png]\ndark_frame: b.png\n{STRIPES}")
    with pytest.raises(CaptureError, match=r"dark_frame: b\.png is 8-bit integer .* share"):
        load_capture(tmp_path / "capture.yaml")
    (tmp_path / "capture.yaml").write_text(f"images: [a.png, a2.png]\ndark_frame: c.exr\n{STRIPES}")
    load_capture(tmp_path / "capture.yaml")
    # Float images with an integer dark frame: [0, 1]-scaled codes against the images'
    # own units (before: taken). A flat field's units do not matter: taken.
    (tmp_path / "capture.yaml").write_text(f"images: [c.exr, c2.exr]\ndark_frame: a.png\n{STRIPES}")
    with pytest.raises(CaptureError, match=r"dark_frame: a\.png is 16-bit integer .* 32-bit float"):
        load_capture(tmp_path / "capture.yaml")
    (tmp_path / "capture.yaml").write_text(f"images: [c.exr, c2.exr]\nflat_field: a.png\n{STRIPES}")
    load_capture(tmp_path / "capture.yaml")


def test_12_bit_data_in_16_bit_files_is_clipped_at_4095(tmp_path):
    codes = np.full((12, 16), 2000, np.uint16)
    codes[3, :5] = 4095  # the sensor's top code
    names = []
    for i in range(3):
        names.append(f"t{i}.tif")
        write_tiff(tmp_path / names[-1], np.where(codes == 4095, codes, codes + i), bits=16)
    (tmp_path / "capture.yaml").write_text(f"images: {names}\n{STRIPES}")
    with pytest.warns(CaptureWarning, match=r"top code 4095 \(12-bit data in 16-bit files\)"):
        c = load_capture(tmp_path / "capture.yaml")
    assert c.n_masked["saturated"] == 5 and not c.mask[3, :5].any()


def test_bayer_mosaic_and_four_channels_are_refused(tmp_path):
    y, x = np.mgrid[0:24, 0:32]
    smooth = 0.2 + 0.5 * np.exp(-0.05 * x)
    gains = np.array([[0.55, 1.0], [1.0, 0.7]])  # R G / G B
    mosaic = smooth * np.tile(gains, (12, 16))
    assert mosaic_score(mosaic)[0] > math.log(1.2) and mosaic_score(smooth)[0] < 0.01
    names = []
    for i in range(3):
        names.append(f"raw{i}.png")
        write_png(tmp_path / names[-1], mosaic, bits=16)
    (tmp_path / "capture.yaml").write_text(f"images: {names}\n{STRIPES}")
    with pytest.raises(
        CaptureError,
        match=r"raw0\.png: the 1-channel images look like an undemosaiced Bayer mosaic",
    ):
        load_capture(tmp_path / "capture.yaml")
    # Stripes along rows (row parity differs) are not a mosaic.
    rows = smooth * np.where(y % 2 == 0, 1.0, 0.4)
    assert mosaic_score(rows)[0] < 0.01

    # Three channels that differ (equal ones would load as one grey channel Y).
    rgba = np.stack([smooth, 0.8 * smooth, 0.6 * smooth, np.ones_like(smooth)], axis=-1)
    write_png(tmp_path / "rgba.png", rgba, bits=16)
    write_png(tmp_path / "rgba2.png", rgba * [1.01, 1.01, 1.01, 1.0], bits=16)
    (tmp_path / "capture.yaml").write_text(f"images: [rgba.png, rgba2.png]\n{STRIPES}")
    c = load_capture(tmp_path / "capture.yaml")
    assert c.channel_names == ("R", "G", "B") and any("alpha" in n for n in c.notes)
    rgba[..., 3] = smooth
    write_png(tmp_path / "rgba.png", rgba, bits=16)
    with pytest.raises(CaptureError, match=r"rgba\.png has a varying alpha channel"):
        load_capture(tmp_path / "capture.yaml")
    write_exr(tmp_path / "planes.exr", {n: smooth for n in ("R", "G1", "G2", "B")})
    write_exr(tmp_path / "planes2.exr", {n: 1.01 * smooth for n in ("R", "G1", "G2", "B")})
    (tmp_path / "capture.yaml").write_text(f"images: [planes.exr, planes2.exr]\n{STRIPES}")
    with pytest.raises(CaptureError, match=r"planes\.exr has 4 channels .* Bayer"):
        load_capture(tmp_path / "capture.yaml")
    (tmp_path / "capture.yaml").write_text(
        f"images: [planes.exr, planes2.exr]\nchannel: G1\n{STRIPES}"
    )
    assert load_capture(tmp_path / "capture.yaml").channel_names == ("G1",)


def test_calibration_frames_of_the_wrong_size(tmp_path):
    names = _exr_images(tmp_path, [np.full((10, 12), 0.3)] * 2)
    write_exr(tmp_path / "small.exr", {"Y": np.zeros((10, 11))})
    for key in ("black_frame", "white_frame", "flat_field"):
        (tmp_path / "capture.yaml").write_text(f"images: {names}\n{key}: small.exr\n{STRIPES}")
        with pytest.raises(CaptureError, match=rf"{key}: small\.exr is 11x10 pixels .* 12x10"):
            load_capture(tmp_path / "capture.yaml")


# --------------------------------------------------------------------- inspect and fit


def test_inspect_reports_what_the_pipeline_sees(rgb, loaded, tmp_path, capsys):
    inspection = inspect_capture(loaded)
    assert inspection.direct.shape == (H, W, 3)
    assert np.all(np.asarray(inspection.reach) > 20)
    assert np.nanmax(inspection.snr_direct) > 50
    folder = rgb[0]
    status = main(
        [
            "inspect",
            str(folder / "capture.yaml"),
            "--plot",
            str(tmp_path / "inspect.png"),
            "--json",
            str(tmp_path / "inspect.json"),
        ]
    )
    out, err = capsys.readouterr()
    assert status == 0 and "clipped at their top code 65535" in err
    assert f"medium_roi: {list(ROI)} (auto)" in out
    assert "entry: left, direction_deg 10.0" in out and "SNR of D" in out
    assert (tmp_path / "inspect.png").stat().st_size > 10_000
    data = json.loads((tmp_path / "inspect.json").read_text())
    assert data["medium_roi"] == list(ROI) and data["detected"]["entry"] == "left"
    assert set(data["snr_direct"]) == {"R", "G", "B"}


@pytest.fixture(scope="module")
def fitted(loaded):
    # One small model for every channel: n_theta 16, 6 bounces, no crop.
    # phase: the convention the frames were rendered in.
    return lfj.fit_capture(
        loaded, "gradient", n_theta=16, refine=1, bounces=6, start_grid=5, phase="paper"
    )


def test_each_channel_fit_converges(fitted):
    assert fitted.channels == ("R", "G", "B") and fitted.converged
    for name, r in zip(fitted.channels, fitted.results, strict=True):
        sigma_t = MEDIA[name][0]
        # σt comes from the direct light's decay along the detected direction.
        assert abs(r.sigma_t / sigma_t - 1) < 0.05, (name, r.sigma_t)
        assert r.uncertainty["sigma_t"] > 0 and math.isfinite(r.uncertainty["g"])
    # σt orders the channels as the media do.
    assert fitted["R"].sigma_t < fitted["G"].sigma_t < fitted["B"].sigma_t


def test_fit_plot_draws_the_channels(rgb, fitted, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(capture_fit_module, "fit_capture", lambda *a, **k: fitted)
    folder = rgb[0]
    status = main(
        [
            "fit",
            str(folder / "capture.yaml"),
            "--method",
            "gradient",
            "--out",
            str(tmp_path / "r.json"),
            "--plot",
            str(tmp_path / "fit.png"),
        ]
    )
    out, _ = capsys.readouterr()
    assert status == 0
    assert "note: detected: medium_roi" in out
    for name in ("fit.png", "fit_R.png", "fit_G.png", "fit_B.png"):
        assert (tmp_path / name).stat().st_size > 10_000, name
    results = json.loads((tmp_path / "r.json").read_text())
    assert results["channels"] == ["R", "G", "B"]
    assert results["medium_roi"]["roi"] == list(ROI) and results["medium_roi"]["faded"] is None
    assert set(results["medium_roi"]["edges"].values()) == {"wall"}
    truth = [dict(zip(("sigma_t", "sigma_s", "g"), m, strict=True)) for m in MEDIA.values()]
    figure = viz.plot_channels(fitted, truth=truth, pixel_size_mm=0.05)
    assert len(figure.axes) == 3


def test_new_modules_do_not_load_image_libraries():
    code = (
        "import sys, lightfield_jax, lightfield_jax.capture.capture, "
        "lightfield_jax.capture.detect, lightfield_jax.capture.calibration, "
        "lightfield_jax.capture.pattern, lightfield_jax.capture.inspect, "
        "lightfield_jax.app.cli, lightfield_jax.capture.hdr, lightfield_jax.capture.views; "
        "bad = {'OpenImageIO', 'matplotlib', 'cv2', 'skimage'} & set(sys.modules); "
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_no_warning_for_a_clean_given_capture(rgb):
    """A capture that gives every value measures nothing and notes nothing but the
    pixels its saturation masks (its shots reach the top code; a saturation above 1,
    which masked nothing here before, is refused for integer images)."""
    _, png, names, _ = rgb
    (png / "capture.yaml").write_text(
        f"images: {names}\ndark_frame: dark.png\nsaturation: 1.0\n"
        f"medium_roi: {list(ROI)}\npattern: {{phases: {list(PHASES_FULL)}, direction_deg: 10}}\n"
    )
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        c = load_capture(png / "capture.yaml")
    said = [str(w.message) for w in seen]
    assert len(said) == 1 and "at or above saturation 1 (" in said[0], said
    assert c.detected is None and c.black_level is None
    assert c.notes == (), c.notes  # the masked pixels are a warning, not a measurement
    assert c.pattern.phases == PHASES


def test_write_capture_yaml_takes_auto_and_calibration_frames(rgb):
    _, png, names, _ = rgb
    lfj.write_capture_yaml(
        png / "capture.yaml",
        images=names,
        pattern=lfj.Stripes(PERIOD, LIT, PHASES_FULL, direction_deg=DIRECTION),
        dark_frame="dark.png",
        black_frame="black.png",
        black_level="auto",
        medium_roi="auto",
        saturation=0.999,
    )
    with pytest.warns(CaptureWarning, match="saturation 0.999"):
        c = load_capture(png / "capture.yaml")
    assert c.roi == ROI and c.black_frame == png / "black.png"
    assert abs(c.black_level - BLACK) < 0.01 and c.pattern.phases == PHASES


# ------------------------------------------------------------- where the medium ends


def _faded_frames(lit_from=None):
    """A dense medium (σt 0.3: its light fades about 20 px into the 36 px tank) in the
    dark camera frame; with ``lit_from``, something lit from that column on."""
    stripes, _ = _render([(0.3, 0.06, 0.3)], direction=0.0)
    rng = np.random.default_rng(5)
    frame = np.full((len(PHASES), FRAME_H, FRAME_W), DARK)
    frame[:, Y0 : Y0 + H, X0 : X0 + W] += stripes[..., 0] / stripes.max()
    if lit_from is not None:
        frame[:, Y0 : Y0 + H, lit_from:] += 0.3
    return frame + rng.normal(0.0, 0.002, frame.shape)


@pytest.mark.parametrize("lit_from", [None, 60])
@pytest.mark.parametrize("mirror", [False, True])
def test_a_faded_far_edge_is_not_a_wall(lit_from, mirror):
    frames = _faded_frames(lit_from)
    g = detect_geometry(frames[..., ::-1] if mirror else frames, period=PERIOD, lit=LIT)
    if mirror:  # back to the unmirrored frame: x → FRAME_W − x
        x0, y0, x1, y1 = g.roi
        g = dataclasses.replace(
            g,
            roi=(FRAME_W - x1, y0, FRAME_W - x0, y1),
            entry={"right": "left"}.get(g.entry, g.entry),
            edges={**g.edges, "left": g.edges["right"], "right": g.edges["left"]},
            faded={
                **g.faded,
                "side": {"left": "right"}.get(g.faded["side"], g.faded["side"]),
                "at": FRAME_W - g.faded["at"],
                "extended_to": FRAME_W - g.faded["extended_to"],
            },
        )
    assert g.entry == "left" and g.edges["right"] == "faded", g.summary()
    assert {g.edges[k] for k in ("left", "top", "bottom")} == {"wall"}
    # The light faded inside the tank; the ROI goes on through the dark frame.
    assert X0 + 12 < g.faded["at"] < X0 + W - 4
    assert g.faded == {
        "side": "right",
        "at": g.faded["at"],
        "extended_to": FRAME_W if lit_from is None else lit_from,
        "until": "frame" if lit_from is None else "lit",
    }
    assert g.roi == (X0, Y0, g.faded["extended_to"], Y0 + H)
    assert "not a wall" in g.summary()


def test_a_faded_edge_is_reported_on_screen_and_in_results(fitted, tmp_path, capsys, monkeypatch):
    # The record does not depend on the fit: any fit stands in for this capture's.
    monkeypatch.setattr(capture_fit_module, "fit_capture", lambda *a, **k: fitted)
    names = []
    for i, f in enumerate(_faded_frames()):
        names.append(f"f{i}.exr")
        write_exr(tmp_path / names[-1], {"Y": f})
    (tmp_path / "capture.yaml").write_text(
        f"images: {names}\nmedium_roi: auto\npattern: {{period: 6, lit: 3, phases: auto}}\n"
    )
    out = tmp_path / "results.json"
    assert main(["fit", str(tmp_path / "capture.yaml"), "--method", "grid", "--out", str(out)]) == 0
    assert "not a wall (the tank goes on)" in capsys.readouterr().out
    record = json.loads(out.read_text())["medium_roi"]
    assert record["source"] == "auto" and record["edges"]["right"] == "faded"
    assert record["roi"][2] == FRAME_W and record["faded"]["until"] == "frame"
    assert "not a wall" in record["note"]
    assert main(["inspect", str(tmp_path / "capture.yaml")]) == 0
    assert "not a wall (the tank goes on)" in capsys.readouterr().out
