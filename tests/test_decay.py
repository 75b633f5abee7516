"""σt from the direct image's decay (docs/model.md section 6) on closed-form beam images."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from jax import monitoring

from lightfield_jax.inverse.decay import DecayFit, fit_decay

H, W = 48, 64


def _entry_wall_line(entry, height, width):
    """The entry wall as the line {q : n·q = offset}, n its inward normal (up to sign)."""
    return {
        "left": ((1.0, 0.0), 0.0),
        "right": ((1.0, 0.0), width),
        "top": ((0.0, 1.0), 0.0),
        "bottom": ((0.0, 1.0), height),
    }[entry]


def _line_amplitude(line):
    return 1.0 + 0.3 * np.sin(line)


def _beam_image(
    sigma_t,
    entry,
    direction_deg,
    period=None,
    lit=None,
    height=H,
    width=W,
    amplitude=_line_amplitude,
):
    """c_ℓ·exp(−σt·s) at pixel centres: s is where the backward ray p − tω meets the entry
    wall's line, ℓ the wall cell it meets; zero where it misses the wall or (with stripes)
    where the cell is dark."""
    n, offset = _entry_wall_line(entry, height, width)
    t0 = math.radians(direction_deg)
    omega = np.array([math.cos(t0), math.sin(t0)])
    y, x = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    p = np.stack([x, y], axis=-1)
    s = (p @ np.array(n) - offset) / (omega @ np.array(n))
    hit = p - s[..., None] * omega
    u = hit[..., 1] if entry in ("left", "right") else hit[..., 0]
    extent = height if entry in ("left", "right") else width
    line = np.floor(u)
    on = (u >= 0) & (u < extent)
    if period is not None:
        on &= np.mod(line, period) < lit
    return np.where(on, amplitude(line) * np.exp(-sigma_t * s), 0.0)


GEOMETRIES = [
    ("left", 0.0, 0.2051),
    ("left", 30.0, 0.2051),
    ("right", 180.0, 0.08),
    ("right", 200.0, 0.12),
    ("top", 90.0, 0.1),
    ("bottom", 300.0, 0.15),
]


@pytest.mark.parametrize("entry, direction_deg, sigma_t", GEOMETRIES)
def test_noiseless_stripes_with_saturation_and_nan(entry, direction_deg, sigma_t):
    img = _beam_image(sigma_t, entry, direction_deg, period=6, lit=3)
    saturation = 0.8
    img = np.minimum(img, saturation)  # the camera clips near the entry wall
    assert (img == saturation).sum() > 20
    rng = np.random.default_rng(0)
    img[rng.integers(0, H, 30), rng.integers(0, W, 30)] = np.nan
    fit = fit_decay(img, direction_deg=direction_deg, entry=entry, saturation=saturation)
    assert isinstance(fit, DecayFit)
    assert bool(fit.converged), optx.RESULTS[fit.result]
    assert float(fit.sigma_t) == pytest.approx(sigma_t, rel=1e-4)
    assert float(fit.residual) < 1e-10
    lines = np.arange(fit.amplitude.shape[0])
    fitted = np.isfinite(fit.amplitude)
    assert not fitted[lines % 6 >= 3].any(), "dark stripe lines must not be fitted"
    assert fitted[lines % 6 < 3].mean() > 0.8
    np.testing.assert_allclose(fit.amplitude[fitted], _line_amplitude(lines[fitted]), rtol=1e-6)


def test_pixel_averaged_beam_is_exact():
    # docs/model.md section 4: a beam along +x averages to σs p(π/2) e^{−σt c}(1 − e^{−σt})/σt
    # on column c, the pixel-centre exponential times a constant.
    sigma_t, c = 0.3, np.arange(W)
    row = 0.0366 * 0.08 * np.exp(-sigma_t * c) * (1 - np.exp(-sigma_t)) / sigma_t
    img = np.zeros((H, W))
    img[20] = row
    fit = fit_decay(img)
    assert float(fit.sigma_t) == pytest.approx(sigma_t, rel=1e-10)
    assert int(fit.n_lines) == 1


def test_partly_lit_pixels_along_the_shadow_edge_are_not_used():
    # Full illumination from the left at 30°, averaged over n×n sub-pixels: the shadow
    # edge from the wall's top end cuts pixels, whose coverage varies along their line.
    n, sigma_t = 8, 0.15
    fine = _beam_image(sigma_t / n, "left", 30.0, height=H * n, width=W * n, amplitude=np.ones_like)
    img = fine.reshape(H, n, W, n).mean(axis=(1, 3))
    coverage = (fine > 0).reshape(H, n, W, n).mean(axis=(1, 3))
    assert ((coverage > 0) & (coverage < 1)).sum() > 30
    fit = fit_decay(img, direction_deg=30.0)
    assert float(fit.sigma_t) == pytest.approx(sigma_t, rel=1e-9)


def test_mirrored_image_from_the_right_wall_gives_the_same_fit():
    img = _beam_image(0.1, "left", 20.0)
    left = fit_decay(img, direction_deg=20.0)
    right = fit_decay(img[:, ::-1], entry="right", direction_deg=160.0)
    assert float(right.sigma_t) == pytest.approx(float(left.sigma_t), rel=1e-12)
    np.testing.assert_allclose(right.amplitude, left.amplitude, rtol=1e-10)


@pytest.mark.parametrize("entry", ["left", "right", "top", "bottom"])
def test_default_direction_is_the_entry_walls_inward_normal(entry):
    normal = {"left": 0.0, "right": 180.0, "top": 90.0, "bottom": 270.0}[entry]
    fit = fit_decay(_beam_image(0.1, entry, normal), entry=entry)
    assert float(fit.sigma_t) == pytest.approx(0.1, rel=1e-10)


def test_mask_excludes_pixels_outside_the_medium():
    img = _beam_image(0.1, "left", 0.0)
    img[:, 50:] = 0.7  # a bright frame edge that is not medium
    mask = np.ones(img.shape, bool)
    mask[:, 50:] = False
    assert float(fit_decay(img, mask=mask).sigma_t) == pytest.approx(0.1, rel=1e-10)
    assert float(fit_decay(img).sigma_t) != pytest.approx(0.1, rel=1e-2)


@pytest.mark.parametrize("entry, direction_deg, sigma_t", GEOMETRIES[:3])
def test_poisson_noise_true_sigma_t_within_three_stderr(entry, direction_deg, sigma_t):
    truth = 1000.0 * _beam_image(sigma_t, entry, direction_deg)
    rng = np.random.default_rng(3)
    for _ in range(5):
        fit = fit_decay(rng.poisson(truth).astype(float), direction_deg=direction_deg, entry=entry)
        assert bool(fit.converged)
        assert 0 < float(fit.sigma_t_stderr) < 0.02 * sigma_t
        assert abs(float(fit.sigma_t) - sigma_t) < 3 * float(fit.sigma_t_stderr)


def test_stderr_is_calibrated():
    # Over many noisy captures (σ̂ − σ)/stderr should have mean ≈ 0 and spread ≈ 1; a
    # selection of pixels on the noisy data (not the model) would bias this low.
    sigma_t = 0.05
    truth = 50.0 * _beam_image(sigma_t, "left", 30.0)
    rng = np.random.default_rng(4)
    z = []
    for _ in range(100):
        fit = fit_decay(rng.poisson(truth).astype(float), direction_deg=30.0)
        z.append((float(fit.sigma_t) - sigma_t) / float(fit.sigma_t_stderr))
    assert abs(np.mean(z)) < 0.35
    assert 0.8 < np.std(z) < 1.25


def test_float32_default_precision():
    img = _beam_image(0.2051, "left", 30.0, period=6, lit=3).astype(np.float32)
    with jax.enable_x64(False):
        fit = fit_decay(img, direction_deg=30.0)
    assert fit.sigma_t.dtype == jnp.float32
    assert bool(fit.converged)
    assert float(fit.sigma_t) == pytest.approx(0.2051, rel=1e-4)
    # With x64 enabled float32 data are fitted in float64 (optimistix's LM needs one dtype).
    assert fit_decay(img, direction_deg=30.0).sigma_t.dtype == jnp.float64


def test_non_convergence_is_reported_not_raised():
    # Light that grows along the assumed direction has no σt > 0: the solve runs out of
    # steps heading for σt → 0 and says so.
    img = _beam_image(0.1, "right", 180.0)
    fit = fit_decay(img, entry="left", max_steps=32)
    assert not bool(fit.converged)
    assert fit.result != optx.RESULTS.successful
    assert int(fit.iterations) == 32


def test_new_data_directions_and_thresholds_never_recompile():
    img = _beam_image(0.1, "left", 0.0)
    fit_decay(img)
    compiles = []

    def listener(name, secs, **kwargs):
        if name == "/jax/core/compile/backend_compile_duration":
            compiles.append(name)

    monitoring.register_event_duration_secs_listener(listener)
    try:
        mask = np.ones(img.shape, bool)
        mask[:5] = False
        fit_decay(2 * img, mask=mask, saturation=1.5, min_fraction=0.1)
        fit_decay(_beam_image(0.2, "left", 25.0), direction_deg=25.0)
        fit_decay(_beam_image(0.3, "right", 180.0), entry="right")
    finally:
        monitoring.unregister_event_duration_listener(listener)
    assert compiles == []


@pytest.mark.parametrize(
    "image, kwargs, match",
    [
        (np.ones((2, H, W)), {}, r"direct: must be one image of shape \(height, width\)"),
        (None, {"entry": "front"}, "entry: must be one of left, right, top, bottom"),
        (None, {"direction_deg": 90.0}, "direction_deg.*does not point into the medium"),
        (None, {"direction_deg": float("inf")}, "direction_deg: must be finite"),
        (None, {"mask": np.ones((H, W - 1), bool)}, "mask: must be a boolean array"),
        (None, {"mask": np.ones((H, W))}, "mask: must be a boolean array"),
        (None, {"saturation": float("nan")}, "saturation: must be finite"),
        (None, {"min_fraction": 0.0}, r"min_fraction: must be in \(0, 1\)"),
        (None, {"min_fraction": 1.0}, r"min_fraction: must be in \(0, 1\)"),
        (None, {"max_steps": 0}, "max_steps: must be a positive integer"),
        (np.full((H, W), np.nan), {}, "not identifiable: 0 usable pixels"),
        (None, {"saturation": 0.0}, "not identifiable: 0 usable pixels"),
        (np.ones((H, 1)), {}, "not identifiable: 48 usable pixels on 48 lines"),
    ],
)
def test_bad_input_raises(image, kwargs, match):
    image = _beam_image(0.1, "left", 0.0) if image is None else image
    with pytest.raises(ValueError, match=match):
        fit_decay(image, **kwargs)
