"""The Monte Carlo oracle checked against closed forms, energy balance and symmetry.

These tests hold the oracle itself to account before it is used to judge the
propagator: every statistical comparison uses the oracle's own error estimate (or an
analytic one), and the symmetry test carries a negative control to show it can fail.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lightfield_jax.reference.montecarlo import (
    monte_carlo_render,
    phase_function,
    phase_integral,
    phase_table,
    sample_deflection,
)
from lightfield_jax.scene.illumination import Beam, Full, Stripes

ESTIMATORS = ("track", "collision")


def p90(g):
    return float(phase_function(math.pi / 2, g))


def same(a):
    return a


def z_scores(a, b, view_a=same, view_b=same):
    """z of result ``a`` against ``b`` (each seen through its view) where both have at
    least 30 scoring photons: fewer make the stated error itself unreliable."""
    ia, sa, ha = (view_a(v) for v in (a.images, a.stderr, a.hits))
    ib, sb, hb = (view_b(v) for v in (b.images, b.stderr, b.hits))
    mask = (ha >= 30) & (hb >= 30)
    assert mask.sum() > 50
    return (ia - ib)[mask] / np.sqrt(sa**2 + sb**2)[mask]


def test_phase_integral_matches_model_table():
    # docs/model.md section 2: A(0) = 0.5, A(0.4) ≈ 0.619, A(0.7) ≈ 1.105, ...; even in g.
    for g, a in ((0.0, 0.5), (0.4, 0.619), (0.7, 1.105), (0.8, 1.622), (0.9, 3.20)):
        assert phase_integral(g) == pytest.approx(a, abs=1e-3)
        assert phase_integral(-g) == pytest.approx(phase_integral(g), rel=1e-12)
    # Closed form A(g) = E(k)/(π(1 − g)), k² = 4g/(1 + g)², E by the AGM.
    g = 0.6
    k2 = 4 * g / (1 + g) ** 2
    a, b, c2, s = 1.0, math.sqrt(1 - k2), k2, 1.0 - k2 / 2
    for n in range(1, 8):
        a, b, c2 = (a + b) / 2, math.sqrt(a * b), ((a - b) / 2) ** 2
        s -= 2 ** (n - 1) * c2
    ellip_e = math.pi / (2 * a) * s
    assert phase_integral(g) == pytest.approx(ellip_e / (math.pi * (1 - g)), rel=1e-12)


@pytest.mark.parametrize("g", [0.7, -0.5, 0.0])
def test_deflection_sampler_follows_the_phase_function(g):
    # Bin probabilities of p/A(g) from a fine midpoint rule, written here independently.
    n, bins = 400_000, 48
    nodes, cdf, _ = phase_table(g)
    delta = sample_deflection(np.random.default_rng(0), n, nodes, cdf)
    assert np.all(np.abs(delta) <= math.pi)
    edges = np.linspace(-math.pi, math.pi, bins + 1)
    fine = (np.arange(bins * 200) + 0.5) * (2 * math.pi / (bins * 200)) - math.pi
    dens = phase_function(fine, g).reshape(bins, 200).sum(axis=1) * (2 * math.pi / fine.size)
    prob = dens / dens.sum()
    counts = np.histogram(delta, edges)[0]
    z = (counts - n * prob) / np.sqrt(n * prob * (1 - prob))
    assert np.max(np.abs(z)) < 5
    assert 0.6 < np.mean(z**2) < 1.5
    # The mean cosine (forward for g > 0, backward for g < 0) against quadrature.
    weights = phase_function(fine, g)
    mean_cos = np.sum(np.cos(fine) * weights) / np.sum(weights)
    assert abs(np.mean(np.cos(delta)) - mean_cos) < 5 * np.std(np.cos(delta)) / math.sqrt(n)


@pytest.mark.parametrize("estimator", ESTIMATORS)
def test_single_scatter_of_beam_matches_closed_form(estimator):
    # docs/model.md section 4: I_1 = σs p(π/2) e^{−σt c}(1 − e^{−σt})/σt on the beam's row.
    w, h, row = 32, 12, 5
    st, ss, g, n = 0.15, 0.1, 0.4, 200_000
    res = monte_carlo_render(
        w, h, st, ss, g, Beam(0.0, row + 0.5), 1, photons=n, seed=1, estimator=estimator
    )
    cols = np.arange(w)
    exact = ss * p90(g) * np.exp(-st * cols) * (1 - np.exp(-st)) / st
    img, se = res.images[0, 0], res.stderr[0, 0]
    assert np.all(np.delete(img, row, axis=0) == 0.0)
    if estimator == "track":  # every photon crosses the first pixel of its row
        assert res.hits[0, 0, row, 0] == n
    z = (img[row] - exact) / se[row]
    assert np.max(np.abs(z)) < 4.5
    # Row sum against its analytic standard error (pixels of a row are correlated).
    total = ss * p90(g) * (1 - np.exp(-st * w)) / st
    if estimator == "track":  # per photon: σs p90 × min(Exp(σt), W)
        m2 = 2 / st**2 * (1 - np.exp(-st * w) * (1 + st * w))
        var = (ss * p90(g)) ** 2 * m2 - total**2
    else:  # per photon: σs p90/σt × [collides inside]
        q = 1 - np.exp(-st * w)
        var = (ss * p90(g) / st) ** 2 * q * (1 - q)
    assert abs(img[row].sum() - total) < 4 * math.sqrt(var / n)


def test_single_scatter_of_oblique_sheet_matches_closed_form():
    # Full left wall at 30°: unit transverse irradiance, fluence e^{−σt x/cos θ0} where
    # the backward ray meets the left wall, zero where it meets the top wall.
    w, h, st, ss, g = 20, 16, 0.2, 0.15, 0.3
    theta = math.radians(30.0)
    res = monte_carlo_render(w, h, st, ss, g, Full(direction_deg=30.0), 1, photons=200_000)
    img, se = res.images[0, 0], res.stderr[0, 0]
    assert res.input_power[0] == pytest.approx(h * math.cos(theta))
    rows, cols = np.mgrid[0:h, 0:w]
    tau = st / math.cos(theta)
    exact = ss * p90(g) * np.exp(-tau * cols) * (1 - np.exp(-tau)) / tau
    lit = rows - (cols + 1) * math.tan(theta) >= 0
    dark = rows + 1 - cols * math.tan(theta) <= 0
    assert lit.sum() > 50 and dark.sum() > 50
    assert np.max(np.abs((img - exact)[lit] / se[lit])) < 5
    assert np.all(img[dark] == 0.0)


@pytest.mark.parametrize("estimator", ESTIMATORS)
@pytest.mark.parametrize(
    ("phase", "sigma_s", "g"), [("normalized", 0.5, 0.5), ("paper", 0.35, 0.8)]
)
def test_energy_balance_per_bounce(estimator, phase, sigma_s, g):
    # Light scattered j times has power P_j; it leaves (escaped_j) or collides, and the
    # colliding power is σt ∫Φ_j = σt/(σs p90) ΣI_{j+1}. The next order carries
    # P_{j+1} = ρ × (colliding power), ρ = ω (normalized) or ω A(g) (paper).
    w, h, st, n, k = 16, 12, 0.5, 100_000, 6
    beam = Beam(0.0, 6.0, 10.0, 3.0)
    kw = dict(phase=phase, photons=n, estimator=estimator)
    res = monte_carlo_render(w, h, st, sigma_s, g, beam, k, **kw)
    rho = sigma_s / st * (phase_integral(g) if phase == "paper" else 1.0)
    collided = st / (sigma_s * p90(g)) * res.images[0].sum(axis=(1, 2))
    power = res.input_power[0]
    for j in range(k):
        # Exact per photon for collisions. The track-length fluence only matches in
        # expectation: per photon, σt·(flight length) − [collided] has an rms below 1
        # in units of the photon weight, at most max(ρ, 1)^j × P_0/N.
        if estimator == "collision":
            tol = 1e-12 * power
        else:
            tol = 5 * max(rho, 1.0) ** j * res.input_power[0] / math.sqrt(n)
        assert abs(res.escaped[0, j] + collided[j] - power) <= tol
        power = rho * (power - res.escaped[0, j])


def test_all_power_leaves_without_absorption():
    # normalized phase, σs = σt: nothing is absorbed, so every photon leaves a wall.
    kw = dict(phase="normalized", photons=20_000, estimator="collision")
    res = monte_carlo_render(16, 12, 0.5, 0.5, 0.3, Beam(0.0, 6.0), 400, **kw)
    assert res.escaped[0].sum() == pytest.approx(res.input_power[0], rel=1e-9)
    # ... and it does take many bounces: a ten-bounce truncation would miss power.
    assert res.escaped[0, :10].sum() < 0.9 * res.input_power[0]


def test_bounce_images_scale_as_sigma_s_to_the_k():
    # docs/model.md section 4: at fixed σt, I_k(σs) = σs^k I_k(1). Same seed, same paths.
    kw = dict(phase="paper", photons=50_000, seed=3)
    a = monte_carlo_render(20, 14, 0.3, 0.3, 0.4, Beam(0.0, 7.0), 4, **kw)
    b = monte_carlo_render(20, 14, 0.3, 0.12, 0.4, Beam(0.0, 7.0), 4, **kw)
    scale = (0.12 / 0.3) ** np.arange(1, 5)
    assert np.all(a.images[0].sum(axis=(1, 2)) > 0)
    np.testing.assert_allclose(b.images[0], a.images[0] * scale[:, None, None], rtol=1e-10)
    np.testing.assert_allclose(b.stderr[0], a.stderr[0] * scale[:, None, None], rtol=1e-8)


def test_mirror_symmetric_beam_gives_symmetric_images():
    w, h = 20, 16
    kw = dict(photons=150_000, seed=4)

    def asymmetry(y):
        res = monte_carlo_render(w, h, 0.3, 0.24, 0.6, Beam(0.0, y, 0.0, 4.0), 3, **kw)
        return np.max(np.abs(z_scores(res, res, view_b=lambda a: a[..., ::-1, :])))

    assert asymmetry(h / 2) < 5
    assert asymmetry(h / 2 + 1) > 10  # negative control: the test can fail


def test_mirrored_oblique_beam_gives_mirrored_images():
    # Independent runs: the beam heading −20° is the mirror image of the one at +20°.
    w, h = 20, 16
    kw = dict(photons=100_000)
    up = monte_carlo_render(w, h, 0.3, 0.2, 0.5, Beam(0.0, 8.0, -20.0), 3, seed=5, **kw)
    down = monte_carlo_render(w, h, 0.3, 0.2, 0.5, Beam(0.0, 8.0, 20.0), 3, seed=6, **kw)
    z = z_scores(up, down, view_b=lambda a: a[..., ::-1, :])
    assert np.max(np.abs(z)) < 5
    assert 0.7 < np.mean(z**2) < 1.4  # the stated errors are the actual scatter


@pytest.mark.parametrize("wall", ["right", "top", "bottom"])
def test_every_entry_wall_is_the_left_one_turned(wall):
    # A beam entering through another wall, 25° off its normal, is the left-wall beam
    # mirrored (right), transposed (top) or transposed and mirrored (bottom).
    w, h, y0, kw = 18, 12, 5.0, dict(photons=60_000, bounces=3)
    medium = (0.35, 0.25, 0.5)
    ref = monte_carlo_render(w, h, *medium, Beam(0.0, y0, 25.0, 2.0), seed=10, **kw)

    def transpose(a):
        return np.swapaxes(a, -1, -2)

    beam, size, turn = {
        "right": (Beam(w, y0, 155.0, 2.0), (w, h), lambda a: a[..., ::-1]),
        "top": (Beam(y0, 0.0, 65.0, 2.0), (h, w), transpose),
        "bottom": (Beam(y0, w, -65.0, 2.0), (h, w), lambda a: transpose(a[..., ::-1, :])),
    }[wall]
    res = monte_carlo_render(*size, *medium, beam, seed=11, **kw)
    assert res.input_power[0] == pytest.approx(2.0)
    z = z_scores(res, ref, view_a=turn)
    assert np.max(np.abs(z)) < 5
    assert 0.7 < np.mean(z**2) < 1.4


def test_estimators_agree_on_multiple_scatter():
    kw = dict(photons=150_000)
    args = (16, 12, 0.4, 0.3, 0.5, Beam(0.0, 6.0, 0.0, 2.0), 4)
    a = monte_carlo_render(*args, estimator="track", seed=7, **kw)
    b = monte_carlo_render(*args, estimator="collision", seed=8, **kw)

    def multiple(v):
        return v[0, 1:]

    z = z_scores(a, b, multiple, multiple)
    assert np.max(np.abs(z)) < 5
    assert 0.7 < np.mean(z**2) < 1.4
    # Track-length has the smaller error, which is why it is the default.
    assert np.median(a.stderr[0, 1] / b.stderr[0, 1]) < 0.7


def test_stderr_matches_scatter_between_seeds():
    args = (12, 10, 0.4, 0.3, 0.5, Beam(0.0, 5.0), 2)
    runs = [monte_carlo_render(*args, photons=10_000, seed=s) for s in range(12)]
    images = np.stack([r.images[0, 1] for r in runs])
    stated = np.mean([r.stderr[0, 1] for r in runs], axis=0)
    ratio = images.std(axis=0, ddof=1) / stated
    assert 0.85 < np.median(ratio) < 1.15


def test_stripes_split_full_illumination_exactly():
    # All phases of period-6/lit-3 stripes light every wall cell three times, and the
    # photons (launched over the whole wall either way) are the same: sum = 3 × Full.
    w, h, kw = 14, 18, dict(photons=30_000, seed=9)
    stripes = monte_carlo_render(w, h, 0.3, 0.2, 0.4, Stripes(), 3, **kw)
    full = monte_carlo_render(w, h, 0.3, 0.2, 0.4, Full(), 3, **kw)
    np.testing.assert_allclose(stripes.images.sum(axis=0), 3 * full.images[0], rtol=1e-12)
    np.testing.assert_allclose(stripes.input_power, 9.0)
    for phase in range(6):
        lit_rows = (np.arange(h) + phase) % 6 < 3
        single = stripes.images[phase, 0]
        assert np.all(single[lit_rows] > 0) and np.all(single[~lit_rows] == 0)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(sigma_t=0.0), "sigma_t"),
        (dict(sigma_s=0.6), "sigma_s"),
        (dict(g=1.0), "g"),
        (dict(phase="flatland"), "phase"),
        (dict(bounces=0), "bounces"),
        (dict(estimator="path"), "estimator"),
        (dict(illumination=Beam(3.0, 4.0)), "not on a wall"),
        (dict(illumination="full"), "illumination"),
    ],
)
def test_bad_input_is_rejected(kwargs, match):
    args = dict(width=8, height=8, sigma_t=0.5, sigma_s=0.3, g=0.2, bounces=2, photons=100)
    args = {"illumination": Full(), **args, **kwargs}
    with pytest.raises((ValueError, TypeError), match=match):
        monte_carlo_render(**args)
