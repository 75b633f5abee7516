"""Exposure brackets (lightfield_jax.capture.hdr): brackets written from a simulated stripe
capture, as a camera would take them (shot noise, a dark pedestal, clipping, 8-bit
codes, linear or γ 2.2), are merged back to the capture's radiance; the fit recovers
the medium from them (slow)."""

import json
import os
import re
import warnings

import numpy as np
import pytest
import yaml

import lightfield_jax as lfj
from lightfield_jax.app.cli import main
from lightfield_jax.capture.exposure_checks import (
    EXPOSURE_MISMATCH_SHARE,
    exposure_mismatch_problem,
    exposure_mismatches,
    exposure_ratio_problem,
    exposure_ratios,
)
from lightfield_jax.capture.hdr import merge_bracket
from lightfield_jax.capture.image_write import write_png
from lightfield_jax.capture.io import CaptureError
from lightfield_jax.capture.loading import load_capture
from lightfield_jax.capture.response import (
    calibrate_response,
    linear_response,
    load_response,
    srgb_encode,
    srgb_response,
    write_response,
)
from lightfield_jax.forward.simulate_config import parse_simulation_config
from lightfield_jax.inverse.capture_fit import fit_capture

MEDIUM = {"sigma_t": 0.1, "sigma_s": 0.05, "g": 0.3}
TIMES = [0.001, 0.008, 0.064]
PHOTONS = 20000.0  # photo-electrons at full scale
PEDESTAL = 0.02  # the camera's black pedestal (linear, full scale 1)


def _simulate(medium):
    """A capture's radiance [P, H, W] (64x48, six shifted stripes), noise free."""
    config = parse_simulation_config(
        {
            "grid": {"width": 64, "height": 48},
            "medium": {**medium, "phase": "paper"},
            "illumination": {"kind": "stripes", "period": 6, "lit": 3, "shifts": 6},
            "bounces": "auto",
        }
    )
    return np.asarray(lfj.simulate_capture(config).images, np.float64)


@pytest.fixture(scope="module")
def radiance():
    """The capture's radiance [P, H, W] (64x48, six shifted stripes), noise free."""
    return _simulate(MEDIUM)


@pytest.fixture(scope="module")
def milk():
    """The radiance of the paper's milk (per px), as :func:`radiance`."""
    return _simulate({"sigma_t": 0.2051, "sigma_s": 0.0366, "g": 0.4})


def _noisy_brackets(
    radiance, times, photons, rng, *, levels=256, encode=None, pedestal=0.0, read=0.0
):
    """Brackets [P, J, H, W, 1] of a radiance [P, H, W] as a camera takes them: the
    shortest exposure puts the peak at half of full scale; Poisson noise of ``photons``
    photo-electrons at full scale, a black ``pedestal`` and Gaussian ``read`` noise
    (linear, full scale 1), then ``encode`` (default linear) and ``levels`` codes."""
    t = np.reshape(times, (1, -1, 1, 1))
    x = (
        rng.poisson(
            (radiance[:, None] * (0.5 / (radiance.max() * times[0])) * t + pedestal) * photons
        )
        / photons
    )
    if read:
        x = x + rng.normal(0.0, read, x.shape)
    z = np.clip(x, 0, 1) if encode is None else encode(np.clip(x, 0, 1))
    return np.rint(z * (levels - 1))[..., None] / (levels - 1)


def _write_brackets(
    folder, radiance, gamma: float, response: str, dark: bool, calibration=False, bits=8
):
    """PNG brackets (the shortest exposure puts the peak at half of full scale, the
    longest clips 45 % of the samples) and their capture file: 8-bit, or ``bits`` of
    sensor data in 16-bit files."""
    rng = np.random.default_rng(0)
    scale = 0.5 / (radiance.max() * TIMES[0])

    def expose(signal, name):
        x = rng.poisson((signal + (PEDESTAL if dark else 0.0)) * PHOTONS) / PHOTONS
        z = np.clip(x, 0.0, 1.0) ** (1.0 / gamma)
        if bits == 8:
            write_png(folder / name, z, bits=8)
        else:  # the sensor's codes, as a raw converter writes them into 16 bits
            write_png(folder / name, np.rint(z * ((1 << bits) - 1)) / 65535, bits=16)
        return name

    images = [
        [expose(e * scale * t, f"shift{p}_{j}.png") for j, t in enumerate(TIMES)]
        for p, e in enumerate(radiance)
    ]
    capture = {
        "images": images,
        "exposure_times": TIMES,
        "response": response,
        "pattern": {"period": 6, "lit": 3, "phases": list(range(6))},
        "truth": MEDIUM,
    }
    if dark:
        zero = np.zeros(radiance.shape[1:])
        capture["dark_frame"] = [expose(zero, f"dark_{j}.png") for j in range(len(TIMES))]
    if calibration:  # the projector's all-white and all-black frames, bracketed alike
        white = radiance.sum(axis=0) / 3  # six shifts of lit 3 of period 6: 3 × white
        capture["white_frame"] = [
            expose(white * scale * t, f"white_{j}.png") for j, t in enumerate(TIMES)
        ]
        capture["black_frame"] = [  # a projector whose black is 5 % of its white
            expose(0.05 * white * scale * t, f"black_{j}.png") for j, t in enumerate(TIMES)
        ]
        capture["black_level"] = "auto"
    path = folder / "capture.yaml"
    path.write_text(yaml.safe_dump(capture))
    return path


def _relative_errors(merged, truth):
    """|merged/truth − 1| (merged scaled by the median ratio) where the truth is above
    10⁻³ of its peak: the 50th and 90th percentiles."""
    lit = truth > 1e-3 * truth.max()
    ratio = merged[lit] / truth[lit]
    return np.percentile(np.abs(ratio / np.median(ratio) - 1.0), [50, 90])


def test_linear_brackets_merge_to_the_radiance(radiance, tmp_path):
    path = _write_brackets(tmp_path, radiance, 1.0, "linear", dark=True, calibration=True)
    capture = load_capture(path)
    median, p90 = _relative_errors(capture.images[..., 0], radiance)
    # The bracketed black and white frames merge alike: the projector's black is 5 %.
    assert capture.black_level == pytest.approx(0.05, abs=0.003), capture.black_level_estimate
    assert median < 0.02 and p90 < 0.05, (median, p90)
    b = capture.brackets
    assert b.response.kind == "linear" and b.times == tuple(TIMES)
    # The longest exposure clips near the entry wall, the shortest holds everything.
    assert b.clipped_fraction[0].max() == 0 and b.clipped_fraction[-1].mean() > 0.2
    assert not b.clipped.any() and capture.mask.all()
    # Where the longest exposure clips, T comes from the shorter ones only.
    assert capture.exposure.min() < TIMES[1] + TIMES[0] + 1e-9
    assert capture.exposure.max() == pytest.approx(sum(TIMES) - TIMES[0], rel=1e-6)
    assert any(n.startswith("HDR: 6 brackets of 3 exposures") for n in capture.notes)
    assert any("dark_frame: subtracted from every exposure" in n for n in capture.notes)


def test_12_bit_data_in_16_bit_files_clips_at_the_sensor_top_code(radiance, tmp_path):
    capture = load_capture(_write_brackets(tmp_path, radiance, 1.0, "linear", False, bits=12))
    assert "12-bit data in 16-bit files: samples divided by its top code" in capture.notes
    # Clipped samples are found at the sensor's top code (not at 16 bits' one).
    assert capture.brackets.clipped_fraction[-1].mean() > 0.2
    median, p90 = _relative_errors(capture.images[..., 0], radiance)
    assert median < 0.02 and p90 < 0.05, (median, p90)


def test_gamma_brackets_recover_the_response_and_the_radiance(radiance, tmp_path):
    capture = load_capture(_write_brackets(tmp_path, radiance, 2.2, "auto", dark=False))
    response = capture.brackets.response
    z = np.linspace(0.2, 0.85, 30)
    x = response.linearize(z[:, None])[:, 0]
    truth = z**2.2 / 0.5**2.2
    assert np.max(np.abs(x / truth - 1.0)) < 0.04
    assert capture.brackets.near_black[0] == pytest.approx(0.17, abs=0.03)
    median, p90 = _relative_errors(capture.images[..., 0], radiance)
    assert median < 0.02 and p90 < 0.05, (median, p90)

    # The recovered curve, written and read back as a response file, merges alike (a
    # file's curve is trusted up to the usual clip level: give auto's as saturation).
    write_response(tmp_path / "response.csv", response, capture.channel_names)
    data = yaml.safe_load((tmp_path / "capture.yaml").read_text())
    data.update(response="response.csv", saturation=capture.brackets.clip)
    (tmp_path / "from_file.yaml").write_text(yaml.safe_dump(data))
    again = load_capture(tmp_path / "from_file.yaml")
    assert again.brackets.response.kind == "file"
    np.testing.assert_allclose(again.images, capture.images, rtol=1e-5)


def test_inspect_shows_the_merge(radiance, tmp_path, capsys):
    path = _write_brackets(tmp_path, radiance, 2.2, "auto", dark=False)
    files = [tmp_path / n for n in ("inspect.png", "inspect.json", "response.csv")]
    args = ["inspect", str(path), "--plot", str(files[0]), "--json", str(files[1])]
    assert main([*args, "--response", str(files[2])]) == 0
    out = capsys.readouterr().out
    assert "note: HDR: 6 brackets of 3 exposures merged, auto response" in out
    record = json.loads(files[1].read_text())["brackets"]
    assert record["exposure_times"] == TIMES and record["response"]["kind"] == "auto"
    # The longest exposure clips near the entry wall; the shortest drops the dark tail.
    assert record["clipped_fraction"][0] == 0 and record["clipped_fraction"][2] > 0.2
    assert record["near_black_fraction"][0] > 0.3
    assert files[0].stat().st_size > 50_000
    curve = load_response(files[2], 1)
    np.testing.assert_allclose(curve.curve[:, 0], record["response"]["curve"][0], rtol=1e-6)


def test_merge_weights_samples_by_exposure_and_drops_clipped_and_black_ones():
    times = [1.0, 4.0]
    z = np.array([[0.2, 0.001, 0.5, 1.0, 1.0]])[None].repeat(2, 0)[..., None]  # (J, 1, 5, 1)
    z[1, 0, :, 0] = [0.8, 0.003, 1.0, 1.0, 0.004]
    m = merge_bracket(z, times, linear_response(), levels=None)
    # Both valid: (0.2 + 0.8) / 5; both near black: the longest one's; the longest
    # clipped: the shortest alone; both clipped: flagged, the shortest's value.
    np.testing.assert_allclose(m.radiance[0, :4, 0], [0.2, 0.003 / 4, 0.5, 1.0])
    np.testing.assert_allclose(m.exposure[0, :, 0], [5.0, 4.0, 1.0, 1.0, 4.0])
    assert m.clipped[0, :, 0].tolist() == [False, False, False, True, False]
    assert m.dark[0, :, 0].tolist() == [False, True, False, False, True]
    assert m.clipped_samples.sum(axis=(1, 2, 3)).tolist() == [2, 2]
    assert m.near_black_samples.sum(axis=(1, 2, 3)).tolist() == [1, 2]


def test_auto_response_needs_lit_unclipped_pixels():
    dark = np.zeros((3, 100, 1))
    with pytest.raises(CaptureError, match="fewer than 16 pixels"):
        calibrate_response(dark, TIMES)


def _refusal(path, data) -> str:
    """The CaptureError's message of loading capture file ``path`` written with ``data``."""
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(CaptureError) as info:
        load_capture(path)
    return str(info.value)


def test_brackets_out_of_order_or_with_wrong_times_are_refused(radiance, tmp_path):
    """Before: merged as given, and the fit ended not converged, sigma_t 22 % off."""
    path = _write_brackets(tmp_path, radiance, 1.0, "linear", dark=True)
    data = yaml.safe_load(path.read_text())
    row = data["images"][3]
    data["images"][3] = [row[1], row[0], row[2]]  # the two shorter exposures swapped
    message = _refusal(path, data)
    assert message.startswith(f"{path}: images[3]: shift3_0.png (listed for 0.008 s) is 0.12")
    assert "as bright as shift3_1.png (listed for 0.001 s)" in message and "\n" not in message
    assert "exposure_times make it 8 (more than 1.5x apart)" in message
    assert "listed out of order" in message
    # Times one stop short of the brackets' (two stops were taken: 8x apart, given 4x).
    data["images"][3] = row
    data["exposure_times"] = [0.001, 0.004, 0.016]
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(
        CaptureError, match=r"images\[0\]: shift0_1.png \(listed for 0.004 s\) is (7\.9\d|8) times"
    ):
        load_capture(path)
    data["exposure_times"] = [0.001, 0.009, 0.07]  # within the tolerance: a shutter's error
    path.write_text(yaml.safe_dump(data))
    assert load_capture(path).brackets.times == (0.001, 0.009, 0.07)


def test_an_exposure_of_another_shift_is_refused(radiance, tmp_path):
    """Shift 2's 64 ms file listed in shift 1's bracket: the right brightness for its
    time (its median ratio to the 8 ms exposure is as stated), its stripes a row away.
    Merged, it mixes two stripe patterns into one image: refused, naming both files.
    Shift 2's 8 ms file instead keeps its median ratio to the 1 ms exposure as stated
    too (where both hold signal): refused alike, not for the files' order."""
    path = _write_brackets(tmp_path, radiance, 1.0, "linear", dark=True)
    data = yaml.safe_load(path.read_text())
    data["images"][1][2] = "shift2_2.png"
    message = _refusal(path, data)
    assert message.startswith(
        f"{path}: images[1]: shift2_2.png (listed for 0.064 s) and shift1_1.png (listed "
        "for 0.008 s) disagree pixel by pixel: "
    ), message
    assert message.endswith(
        "(exposures of one scene: at most 20 %): is one a file from another shift, or did "
        "the scene move between exposures?"
    ), message
    share = re.search(r": (\d+) % of the \d+ samples compared differ from their median", message)
    assert share is not None and int(share.group(1)) > 25, message
    assert "\n" not in message
    data["images"][1][2] = "shift1_2.png"
    data["images"][1][1] = "shift2_1.png"
    message = _refusal(path, data)
    assert message.startswith(
        f"{path}: images[1]: shift2_1.png (listed for 0.008 s) and shift1_0.png (listed "
        "for 0.001 s) disagree pixel by pixel: "
    ), message
    assert "from another shift" in message and "listed out of order" not in message


def test_an_exposure_of_another_shift_is_named_where_another_pair_is_off(radiance, tmp_path):
    """With an auto response, shift 2's 64 ms file in shift 1's bracket: the 1 ms and
    64 ms exposures have no light in common to compare (the 64 ms one clips where the
    1 ms one holds signal), so the refusal names the pair that disagrees pixel by
    pixel, not the files' order."""
    path = _write_brackets(tmp_path, radiance, 2.2, "auto", dark=False)
    data = yaml.safe_load(path.read_text())
    data["images"][1][2] = "shift2_2.png"
    message = _refusal(path, data)
    assert message.startswith(
        f"{path}: images[1]: shift2_2.png (listed for 0.064 s) and shift1_1.png (listed "
        "for 0.008 s) disagree pixel by pixel: "
    ), message
    assert "from another shift" in message and "listed out of order" not in message


@pytest.mark.parametrize("response", ["linear", "srgb", "auto"])
def test_noisy_brackets_of_one_scene_agree_pixel_by_pixel(radiance, response):
    """Brackets of one scene with 1000 photo-electrons at full scale, 8-bit, pass the
    pixel-by-pixel check with a margin; the same brackets with one exposure from the
    next shift do not."""
    rng = np.random.default_rng(3)
    times = [0.001, 0.004, 0.016]
    encode = {"linear": lambda x: x, "srgb": srgb_encode, "auto": lambda x: x ** (1 / 2.2)}
    z = _noisy_brackets(radiance, times, 1000, rng, encode=encode[response])
    if response == "auto":
        curve = calibrate_response(np.moveaxis(z, 1, 0).reshape(3, -1, 1), times)
    else:
        curve = srgb_response() if response == "srgb" else linear_response()
    for bracket in z:
        shares = [s for *_, s, _ in exposure_mismatches(bracket, times, curve, levels=256)]
        assert shares and max(shares) < EXPOSURE_MISMATCH_SHARE / 4, shares
        assert exposure_mismatch_problem(bracket, times, curve, levels=256) is None
    for j in range(len(times)):  # each exposure in turn from the next shift
        swapped = z[1].copy()
        swapped[j] = z[2, j]
        found = exposure_mismatch_problem(swapped, times, curve, levels=256)
        assert found is not None and found[2] > 1.2 * EXPOSURE_MISMATCH_SHARE, (j, found)


@pytest.mark.parametrize("seed", range(6))
def test_noisy_wide_pairs_of_one_scene_agree_pixel_by_pixel(seed):
    """Two 8-bit RGB exposures 16x apart with 300 photo-electrons at full scale (a phone
    at high ISO) of a scene over three decades with stripes: the pixel-by-pixel check
    predicts one exposure from the other by their unbiased measured ratio, so the pair
    passes with a margin (predicted by the median over samples with signal in both,
    the short exposure's noise-lifted ones, the ratio comes out near 10 for 16 and a
    fifth of the samples look off: seeds 3 and 4 would be refused)."""
    yy, xx = np.mgrid[0:96, 0:128]
    scene = np.exp(-xx / 20.0) * (0.3 + 0.7 * ((yy // 3) % 2)) + 0.002
    scene = scene[..., None] * np.array([1.0, 0.6, 0.3])
    times = [0.001, 0.016]
    rng = np.random.default_rng(seed)
    light = scene[None] * (0.5 / (scene.max() * times[0])) * np.reshape(times, (-1, 1, 1, 1))
    bracket = np.rint(np.clip(rng.poisson(light * 300) / 300, 0, 1) * 255) / 255
    shares = [s for *_, s, _ in exposure_mismatches(bracket, times, linear_response(), levels=256)]
    assert shares and max(shares) < EXPOSURE_MISMATCH_SHARE / 2, shares


@pytest.mark.parametrize("photons", [2000, 20000])
@pytest.mark.parametrize("times", [[0.001, 0.008, 0.064], [0.001, 0.004, 0.016]])
def test_noisy_wide_brackets_keep_their_median_ratio(milk, times, photons):
    """Brackets of the paper's milk, 16-bit with a 2 % pedestal (its dark level given)
    and read noise, exposures 8 and 4 times apart: the median ratio of each pair is the
    ratio of their times (samples chosen on the short exposure's own value would be
    those its noise lifted above its floor: 1/8/64 ms at 2000 photo-electrons would
    come out 27 for 64, refused as listed out of order). Swapped files and a time 2x
    off are still refused."""
    rng = np.random.default_rng(5)
    z = _noisy_brackets(milk, times, photons, rng, levels=65536, pedestal=0.02, read=5e-4)
    dark = np.full(z.shape[1:], 0.02)
    kw = {"levels": 65536, "dark": dark}
    curve = linear_response()
    for bracket in z:
        assert exposure_ratio_problem(bracket, times, curve, **kw) is None
        ratios = list(exposure_ratios(bracket, times, curve, **kw))
        assert ratios, "no pair judged"
        for j, k, measured, stated in ratios:
            assert abs(measured / stated - 1) < 0.1, (j, k, measured, stated)
        for j in range(len(times) - 1):
            swapped = bracket.copy()
            swapped[[j, j + 1]] = bracket[[j + 1, j]]
            assert exposure_ratio_problem(swapped, times, curve, **kw) is not None, j
        for j in range(len(times)):
            wrong = list(times)
            wrong[j] *= 2 if j == len(times) - 1 else 0.5
            assert exposure_ratio_problem(bracket, wrong, curve, **kw) is not None, j


def _capture_file(tmp_path, **changes):
    for j in range(2):
        write_png(tmp_path / f"a{j}.png", np.full((8, 8), 0.5), bits=8)
    data = {
        "images": [["a0.png", "a1.png"]] * 6,
        "exposure_times": [0.01, 0.02],
        "pattern": {"period": 6, "lit": 3},
    }
    data.update(changes)
    data = {k: v for k, v in data.items() if v is not None}
    path = tmp_path / "capture.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"exposure_times": None}, "exposure_times: bracketed images need a list"),
        ({"exposure_times": [0.02, 0.01]}, "exposure_times: must increase"),
        ({"exposure_times": [0.01, -1]}, r"exposure_times\[1\]: must be a positive number"),
        # Before: a numpy overflow warning, then "no usable pixel" (1e-308 s: every merged
        # value Inf) or "no light was captured" (1e308 s: every value 0).
        ({"exposure_times": [1e-308, 2e-308]}, r"exposure_times\[0\]: must be a number of "),
        ({"exposure_times": [0.01, 1e308]}, r"exposure_times\[1\]: .* in \[1e-09, 1e\+06\]"),
        ({"exposure_times": [0.01, 0.02, 0.04]}, r"images\[0\]: lists 2 exposure\(s\) for 3"),
        ({"images": [["a0.png", "a1.png"], "a0.png"]}, "images: mixes files and brackets"),
        ({"dark_frame": "a0.png"}, "dark_frame: with bracketed images give one file per"),
        ({"response": "gamma"}, "response: .*gamma: file not found"),
        ({"response": 2.2}, "response: must be linear or srgb or auto or a file"),
    ],
)
def test_bracket_errors_name_the_key(tmp_path, changes, message):
    with pytest.raises(CaptureError, match=message):
        load_capture(_capture_file(tmp_path, **changes))


def test_exposure_keys_need_brackets(tmp_path):
    write_png(tmp_path / "a.png", np.full((8, 8), 0.5), bits=8)
    path = tmp_path / "capture.yaml"
    path.write_text(yaml.safe_dump({"images": ["a.png"] * 6, "exposure_times": [0.1, 0.2]}))
    with pytest.raises(CaptureError, match="exposure_times: applies to bracketed images only"):
        load_capture(path)
    path.write_text(yaml.safe_dump({"images": ["a.png"] * 6, "response": "auto"}))
    with pytest.raises(CaptureError, match="response: auto recovers .* from exposure brackets"):
        load_capture(path)


def test_response_file_is_validated(tmp_path):
    bad = tmp_path / "r.csv"
    bad.write_text("0, 0\n0.5, 0.6\n0.9, 0.5\n1, 1\n")
    with pytest.raises(CaptureError, match="x must not decrease"):
        load_response(bad, 1)
    bad.write_text("0.1, 0\n1, 1\n")
    with pytest.raises(CaptureError, match="must run from 0 to 1"):
        load_response(bad, 1)


def test_response_files_that_are_no_tables_are_one_line_without_hanging(tmp_path):
    # A FIFO blocked the read forever; a structured or complex .npy was a TypeError
    # traceback or lost its imaginary part; an empty file also printed numpy's warning.
    fifo = tmp_path / "fifo.csv"
    os.mkfifo(fifo)
    with pytest.raises(CaptureError, match="not a regular file .* not a response table"):
        load_response(fifo, 1)
    for dtype, value in (([("a", "f4"), ("b", "f4")], 0), (np.complex128, 1 + 1j)):
        table = tmp_path / "r.npy"
        np.save(table, np.array([[0, 0], [1, value]]).astype(dtype))
        with pytest.raises(CaptureError, match="a response table holds numbers, got .* dtype"):
            load_response(table, 1)
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(CaptureError, match="got shape"):
            load_response(empty, 1)
    good = tmp_path / "good.npy"
    np.save(good, np.array([[0, 0], [1, 1]], np.int32))
    assert load_response(good, 1).curve[-1, 0] == 1.0


@pytest.mark.slow
@pytest.mark.parametrize(
    "gamma, response, tolerance",
    [(1.0, "linear", (0.02, 0.05, 0.03)), (2.2, "auto", (0.03, 0.10, 0.05))],
)
def test_fit_recovers_the_medium_from_brackets(radiance, tmp_path, gamma, response, tolerance):
    # A pedestal under a gamma curve breaks z = f(E·t) (see lightfield_jax.capture.hdr): the
    # γ 2.2 brackets have none, the linear ones do (their dark frame removes it).
    path = _write_brackets(tmp_path, radiance, gamma, response, dark=gamma == 1.0)
    capture = load_capture(path)
    fit = fit_capture(capture, "joint").results[0]
    assert fit.converged
    assert abs(fit.sigma_t / MEDIUM["sigma_t"] - 1) < tolerance[0]
    assert abs(fit.sigma_s / MEDIUM["sigma_s"] - 1) < tolerance[1]
    assert abs(fit.g - MEDIUM["g"]) < tolerance[2]


@pytest.mark.parametrize("signal", [0.0, 2e-4, 1e-3, 1e-2])
def test_dim_pixels_merge_without_bias(signal):
    """Whether a sample is too dim to merge is judged on the light the pixel's longest
    unclipped exposure measured, not on the sample itself: keeping the dim samples
    that read noise lifted biased the merge up (a tank's far end 17-1500× too bright,
    light outside the tank where there was none)."""
    rng = np.random.default_rng(1)
    times = np.array([0.001, 0.008, 0.064])
    n, pedestal, read = 20000, 0.02, 0.0005
    rate = signal / times[-1]  # the longest exposure sees `signal` above the pedestal

    def expose(e, shape):
        x = rng.poisson(e * 20000.0, size=shape) / 20000.0 + pedestal
        x = x + rng.normal(0.0, read, size=shape)
        return np.rint(np.clip(x, 0.0, 1.0) * 65535) / 65535

    z = np.stack([expose(rate * t, (1, n, 1)) for t in times])
    dark = np.full((len(times), 1, n, 1), pedestal)
    m = merge_bracket(z, times, linear_response(), levels=65536, dark=dark)
    merged = m.radiance[0, :, 0] * times[-1]  # in units of the longest exposure
    # The merged mean is the truth within 4 standard errors of the longest exposure.
    sem = np.sqrt(signal / 20000.0 + read**2 + 1 / 12 / 65535**2) / np.sqrt(n)
    assert abs(merged.mean() - signal) < 4 * sem, (merged.mean(), signal, sem)


def test_a_shift_clipped_in_every_exposure_is_named(radiance, tmp_path):
    """Before: 'no usable pixel: every pixel is non-finite or saturated in some image',
    naming neither the shift nor its files."""
    path = _write_brackets(tmp_path, radiance, 1.0, "linear", dark=False)
    for j in range(len(TIMES)):  # every exposure of the third shift clips
        write_png(tmp_path / f"shift2_{j}.png", np.ones(radiance.shape[1:]), bits=8)
    with pytest.raises(
        CaptureError, match=r"every pixel is clipped in every exposure of images\[2\] \(shift2_"
    ):
        load_capture(path)


def test_a_dark_level_is_subtracted_from_every_exposure(radiance, tmp_path):
    """Brackets with the camera's pedestal and no dark frames: ``dark_level`` (the
    pedestal) merges them as the dark frames do."""
    path = _write_brackets(tmp_path, radiance, 1.0, "linear", dark=True)
    with_frames = load_capture(path)
    capture = yaml.safe_load(path.read_text())
    del capture["dark_frame"]
    capture["dark_level"] = PEDESTAL
    path.write_text(yaml.safe_dump(capture))
    with_level = load_capture(path)
    assert any("dark_level: 0.02: subtracted from every exposure" in n for n in with_level.notes)
    lit = radiance > 1e-2 * radiance.max()
    ratio = with_level.images[..., 0][lit] / with_frames.images[..., 0][lit]
    assert np.percentile(np.abs(ratio - 1.0), 90) < 0.01
    capture["dark_level"] = {"Y": PEDESTAL}  # by channel name: the same merge
    path.write_text(yaml.safe_dump(capture))
    np.testing.assert_array_equal(load_capture(path).images, with_level.images)
    capture["dark_level"] = 0.3  # far above the pedestal: refused, naming dark_level
    path.write_text(yaml.safe_dump(capture))
    with pytest.raises(CaptureError, match=r"dark_level: 0\.3 is above the camera's pedestal"):
        load_capture(path)
    del capture["dark_level"]  # the pedestal left in: the dimmest light comes out brighter
    path.write_text(yaml.safe_dump(capture))
    ratio = load_capture(path).images[..., 0][lit] / with_frames.images[..., 0][lit]
    assert np.percentile(ratio, 10) > 1.03


@pytest.mark.parametrize("level, said", [(None, "+0.05"), (0.08, "-0.03")])
def test_a_bracket_off_by_a_pedestal_is_said_to_be(tmp_path, level, said):
    """Exposures that scale as their times say but for one constant in every sample (a
    pedestal left in, or a dark_level above it) name that constant, not the files'
    order (before: "are the files listed out of order ...?" for either)."""
    radiance = np.linspace(0.005, 0.1, 16 * 20).reshape(16, 20)
    rows = []
    for i in range(6):
        for j, t in enumerate((1.0, 4.0)):
            shift = (1 + 0.01 * i) * radiance  # (each its own exposure: no copies)
            write_png(tmp_path / f"s{i}_{j}.png", np.clip(t * shift + 0.05, 0, 1), bits=16)
        rows.append([f"s{i}_0.png", f"s{i}_1.png"])
    data = {"images": rows, "exposure_times": [0.01, 0.04], "pattern": {"period": 6, "lit": 3}}
    if level is not None:
        data["dark_level"] = level
    path = tmp_path / "capture.yaml"
    message = _refusal(path, data)
    assert f"with a constant {said} in every image value" in message, message
    assert "listed out of order" not in message and "\n" not in message
    data["dark_level"] = 0.05
    path.write_text(yaml.safe_dump(data))
    load_capture(path)


def test_a_merge_with_a_dark_frame_says_so_and_where_near_black_samples_are(radiance, tmp_path):
    """The response plot said "(no dark frame)" of a capture that had one, and inspect's
    "near black 61.6 %" did not say that those are mostly pixels outside the tank."""
    from lightfield_jax.capture.inspect import inspect_capture
    from lightfield_jax.viz import plot_inspect

    for dark in (True, False):
        folder = tmp_path / str(dark)
        folder.mkdir()
        capture = load_capture(_write_brackets(folder, radiance, 2.2, "srgb", dark=dark))
        assert capture.brackets.dark_frame is dark
        summary = capture.brackets.summary()
        assert "pixels outside the medium are near black" in summary
        assert ("without a dark frame z <" in summary) is not dark
        figure = plot_inspect(inspect_capture(capture))
        labels = [t.get_text() for ax in figure.axes if ax.get_legend() for t in
                  ax.get_legend().get_texts()]  # fmt: skip
        assert ("near black below (no dark frame)" in labels) is not dark, labels
