"""The inverse pipeline (docs/model.md sections 5-6): captures rendered by the package's own
renderer, fitted back.

- ``joint`` recovers σt, σs, g and the gain of noiseless stripe captures, for the
  paper's milk, a backward and a forward medium; the forward one (high albedo, g 0.7)
  is ill-conditioned along σt-g and its correlation says so.
- ``grid`` and ``gradient`` recover the truth from a perfect split (I_1, Σ_{k≥2} I_k)
  and reproduce the separation's bias on stripe captures, agreeing with each other to
  within the grid's spacing.
- With shot noise the truth lies within 3σ of the joint fit.

The default suite fits small grids (48x32, the forward medium 32x24; 16 direction bins,
the model matching the data's); the 128x96 versions are marked ``slow``.
"""

import dataclasses
import functools
import math
import re

import jax
import numpy as np
import pytest
from programs_support import programs_built

import lightfield_jax as lfj

GAIN = 3.0
MEDIA = {
    "milk": (0.2051, 0.0366, 0.4),  # the paper's milk (per pixel)
    "backward": (0.25, 0.175, -0.3),  # albedo 0.7
    "forward": (0.15, 0.12, 0.7),  # albedo 0.8
}
SMALL = lfj.Grid(48, 32, 16, 1)
SMALL_FORWARD = lfj.Grid(32, 24, 16, 1)  # its 60-bounce model is the costly one
# 128x96 with 32 direction bins, the default for the milk and the backward medium (the
# forward one's default, 64 bins on a 2x grid, makes its 60-bounce joint fit take hours
# on a CPU; a round trip is self-consistent either way).
FULL = lfj.Grid(128, 96, 32, 1)
G_GRID = lfj.GridSearch().g_values
G_SPACING = 1.9 / (G_GRID - 1)  # the grid method searches linspace(-0.95, 0.95, g_grid)


def _medium(name: str) -> lfj.Medium:
    return lfj.Medium(*MEDIA[name], "paper")


@functools.cache
def _stripe_images(name: str, grid: lfj.Grid) -> np.ndarray:
    """The six shifted stripe images of a medium (gain included, no noise)."""
    result = lfj.render(_medium(name), grid, lfj.Stripes(), "auto")
    return GAIN * np.asarray(result.total)


@functools.cache
def _perfect_split(name: str, grid: lfj.Grid) -> tuple[np.ndarray, np.ndarray]:
    """(I_1, Σ_{k≥2} I_k) under full illumination, gain included: what an exact
    separation of the stripe capture would give."""
    images = np.asarray(lfj.render(_medium(name), grid, lfj.Full(), "auto").images)
    return GAIN * images[0], GAIN * images[1:].sum(axis=0)


@functools.cache
def _fit(name: str, grid: lfj.Grid, method: str, split: bool = False) -> lfj.FitResult:
    """Fit a noiseless stripe capture with a model of the data's own resolution: its
    truth is that model's own answer (``extrapolate`` off: the finer model the forward
    medium's g asks for, refine 2, would step it on toward the continuum's)."""
    return lfj.fit_images(
        _stripe_images(name, grid),
        lfj.Stripes(),
        black_level=0.0,
        method=method,
        split=_perfect_split(name, grid) if split else None,
        n_theta=grid.n_theta,
        refine=grid.refine,
        max_cells=grid.width * grid.height * grid.n_theta * grid.refine**2,
        extrapolate=False,
    )


def _errors(result: lfj.FitResult, name: str) -> dict:
    sigma_t, sigma_s, g = MEDIA[name]
    return {
        "sigma_t": result.sigma_t / sigma_t - 1,
        "sigma_s": result.sigma_s / sigma_s - 1,
        "g": result.g - g,
        "gain": result.gain / GAIN - 1,
    }


def _grid_for(size: str, name: str) -> lfj.Grid:
    if size == "small":
        return SMALL_FORWARD if name == "forward" else SMALL
    return FULL


SIZES = [pytest.param("small"), pytest.param("full", marks=pytest.mark.slow)]


# ------------------------------------------------------------------------------- joint


@pytest.mark.parametrize("size", SIZES)
@pytest.mark.parametrize(
    # the dense forward medium's small fit takes about a minute: slow (its valley test,
    # below, keeps a forward fit in the default suite)
    "name",
    [pytest.param(n, marks=pytest.mark.slow) if n == "forward" else n for n in MEDIA],
)
def test_joint_recovers_the_truth(name, size):
    result = _fit(name, _grid_for(size, name), "joint")
    err = _errors(result, name)
    assert result.converged, result.message
    assert result.method == "joint" and result.iterations > 0
    assert abs(err["sigma_t"]) < 0.005, err
    assert abs(err["sigma_s"]) < 0.005, err
    assert abs(err["g"]) < 0.005, err
    assert abs(err["gain"]) < 0.01, err
    assert result.black_level == 0.0  # given, not fitted
    # Every fitted parameter has a finite, positive 1σ error, and the derived keys follow.
    for key in ("sigma_t", "sigma_s", "g", "gain"):
        assert 0 < result.uncertainty[key] < math.inf, result.uncertainty
    d = result.to_dict()
    assert d["sigma_a"] == pytest.approx(d["sigma_t"] - d["sigma_s"])
    assert d["albedo"] == pytest.approx(d["sigma_s"] / d["sigma_t"])
    assert d["uncertainty"]["sigma_a"] > 0 and d["uncertainty"]["albedo"] > 0


@pytest.mark.parametrize("size", SIZES)
def test_forward_medium_reports_its_sigma_t_g_valley(size):
    """At albedo 0.8 and g 0.7, σt and g trade off (docs/model.md §6): the noise's
    correlation between them is strong, where for the milk and the backward medium it
    is not."""
    corr = {
        name: abs(_fit(name, _grid_for(size, name), "joint").correlation_statistical["sigma_t,g"])
        for name in MEDIA
    }
    assert corr["forward"] > 0.85, corr
    assert corr["milk"] < 0.6 and corr["backward"] < 0.6, corr


# ------------------------------------------------------------------- grid and gradient


@pytest.mark.parametrize("size", SIZES)
@pytest.mark.parametrize("method", ["grid", "gradient"])
def test_two_step_methods_recover_a_perfect_split(method, size):
    name = "milk"
    result = _fit(name, _grid_for(size, name), method, split=True)
    err = _errors(result, name)
    assert result.converged, result.message
    assert result.method == method
    assert abs(err["sigma_t"]) < 0.01, err
    assert abs(err["sigma_s"]) < 0.01, err
    assert abs(err["g"]) < 0.01 * abs(MEDIA[name][2]), err
    assert abs(err["gain"]) < 0.01, err


@pytest.mark.slow
@pytest.mark.parametrize("method", ["grid", "gradient"])
def test_two_step_methods_recover_a_perfect_split_backward(method):
    name = "backward"
    err = _errors(_fit(name, FULL, method, split=True), name)
    assert abs(err["sigma_t"]) < 0.01 and abs(err["sigma_s"]) < 0.01, err
    assert abs(err["g"]) < 0.01, err


@pytest.mark.parametrize("size", SIZES)
def test_two_step_methods_inherit_the_separation_bias(size):
    """Period-6 stripes against a mean free path of ~5 px: D keeps part of the multiple
    scatter and 2·Imin falls short of M, so the paper's method returns σs far below the
    truth and g far above it (docs/model.md §6); σt, from the decay of D, stays close. The
    gradient solve lands within one grid spacing of the grid search."""
    name = "milk"
    grid_fit = _fit(name, _grid_for(size, name), "grid")
    gradient_fit = _fit(name, _grid_for(size, name), "gradient")
    for result in (grid_fit, gradient_fit):
        err = _errors(result, name)
        assert result.converged, result.message
        assert abs(err["sigma_t"]) < 0.03, err
        assert -0.75 < err["sigma_s"] < -0.5, err
        assert 0.2 < err["g"] < 0.4, err
    assert abs(gradient_fit.g - grid_fit.g) <= G_SPACING
    # Both minimise the same residual; the continuous solve can only do better than the
    # best grid node (σs moves with g along the valley, so σs itself may differ by more
    # than the spacing suggests: 5 % at 128x96).
    assert gradient_fit.residual <= grid_fit.residual * (1 + 1e-9)


@pytest.mark.parametrize("entry", ["right", "bottom"])
def test_rotated_capture_gives_the_same_fit(entry):
    """Mirror the milk capture (light entering from the right), or transpose and flip it
    (from the bottom): the crop, the decay fit and the model must follow the entry wall.
    Mirroring is exact; transposing swaps which sweep owns the diagonal direction bins,
    a per-mille asymmetry of the forward model (tests/test_render.py)."""
    images = _stripe_images("milk", SMALL)
    turned = images[:, :, ::-1] if entry == "right" else images.transpose(0, 2, 1)[:, ::-1]
    reference = _fit("milk", SMALL, "gradient")
    result = lfj.fit_images(
        np.ascontiguousarray(turned),
        lfj.Stripes(entry=entry),
        black_level=0.0,
        method="gradient",
        n_theta=SMALL.n_theta,
        refine=SMALL.refine,
    )
    tol = 1e-6 if entry == "right" else 5e-3
    assert result.converged, result.message
    assert result.sigma_t == pytest.approx(reference.sigma_t, rel=tol)
    assert result.sigma_s == pytest.approx(reference.sigma_s, rel=tol)
    assert result.g == pytest.approx(reference.g, abs=tol)
    assert result.gain == pytest.approx(reference.gain, rel=2 * tol)


# --------------------------------------------------------------------------- with noise


def _noisy_fit(grid: lfj.Grid, seed: int, photons: float = 2e4):
    """The milk with Poisson shot noise: image value 1 (the brightest pixel) holds
    ``photons`` photons."""
    clean = _stripe_images("milk", grid)
    scale = 1.0 / clean.max()
    rng = np.random.default_rng(seed)
    images = rng.poisson(scale * clean * photons) / photons
    result = lfj.fit_images(
        images,
        lfj.Stripes(),
        black_level=0.0,
        n_theta=grid.n_theta,
        refine=grid.refine,
        max_cells=grid.width * grid.height * grid.n_theta * grid.refine**2,
    )
    return result, GAIN * scale


@pytest.mark.parametrize(
    ("size", "seed"),
    [("small", 0), pytest.param("small", 1, marks=pytest.mark.slow)]
    + [pytest.param("full", s, marks=pytest.mark.slow) for s in (0, 1)],
)
def test_noisy_milk_truth_within_three_sigma(size, seed):
    result, gain = _noisy_fit(_grid_for(size, "milk"), seed)
    sigma_t, sigma_s, g = MEDIA["milk"]
    truth = {"sigma_t": sigma_t, "sigma_s": sigma_s, "g": g, "gain": gain}
    assert result.converged, result.message
    for key, value in truth.items():
        u = result.uncertainty[key]
        assert abs(getattr(result, key) - value) < 3 * u, (key, getattr(result, key), value, u)
    # The errors are informative, not just large: 2e4 photons pin σs to well under 1 %.
    assert result.uncertainty["sigma_s"] / sigma_s < 0.01
    assert result.uncertainty["sigma_t"] / sigma_t < 0.005
    assert result.uncertainty["g"] < 0.01


def test_the_linearised_refit_lands_where_a_solve_with_the_model_weights_does(monkeypatch):
    """The refit with the model's weights is done on the model linearised at the first
    stage's answer; solved instead (the linearisation switched off), the answer is the
    same to a small fraction of its 1σ, so the shortcut costs no accuracy."""
    import lightfield_jax.inverse.joint_fit.refit as refit

    linear, _ = _noisy_fit(SMALL, 0)
    assert linear.model["refit"] == "linearised"
    monkeypatch.setattr(refit, "linear_refit", lambda *args: None)
    solved, _ = _noisy_fit(SMALL, 0)
    assert solved.model["refit"] == "solved"
    for key in ("sigma_t", "sigma_s", "g"):
        shift = abs(getattr(linear, key) - getattr(solved, key))
        assert shift < 0.1 * solved.uncertainty[key], (key, shift, solved.uncertainty[key])
        assert linear.uncertainty[key] == pytest.approx(solved.uncertainty[key], rel=0.05)


# ------------------------------------------------------------------------------ float32


def test_float32_two_step_on_a_high_albedo_medium():
    # The two-step renders at a reference sigma_s with rho <= 0.9 (the paper's sigma_s = 1
    # overflows float32 within a few dozen bounces at high albedo).
    images = _stripe_images("forward", SMALL_FORWARD).astype(np.float32)
    with jax.enable_x64(False):
        result = lfj.fit_images(
            images,
            lfj.Stripes(),
            black_level=0.0,
            method="grid",
            n_theta=SMALL_FORWARD.n_theta,
            refine=1,
        )
    assert math.isfinite(result.sigma_s) and math.isfinite(result.g)


# ------------------------------------------------- compiled programs kept in the process


# The gradient method's reuse is slow-marked: the joint fit's covers the same machinery.
@pytest.mark.forgets_compiled
@pytest.mark.parametrize("method", [pytest.param("gradient", marks=pytest.mark.slow), "joint"])
def test_a_second_fit_of_the_same_shape_reuses_the_compiled_program(method):
    from lightfield_jax.inverse.fit import clear_compiled

    images = _stripe_images("milk", SMALL)
    kwargs = dict(black_level=0.0, method=method, n_theta=16, refine=1)
    clear_compiled()
    first = lfj.fit_images(images, lfj.Stripes(), **kwargs)
    assert first.seconds["compile"] > 0
    # Other data of the same shape (another channel, the next capture): no compilation,
    # the same answer as a fresh program gives.
    other = 0.8 * images
    results = []
    assert (
        programs_built(lambda: results.append(lfj.fit_images(other, lfj.Stripes(), **kwargs))) == 0
    )
    again = results[0]
    assert again.seconds["compile"] == 0.0
    clear_compiled()
    fresh = lfj.fit_images(other, lfj.Stripes(), **kwargs)
    assert fresh.seconds["compile"] > 0
    for name in ("sigma_t", "sigma_s", "g"):
        assert getattr(again, name) == getattr(fresh, name)
    assert again.gain == pytest.approx(0.8 * first.gain, rel=1e-4)
    # What the program was built from besides its arguments is part of its key: other
    # solver settings compile a new one.
    assert programs_built(lambda: lfj.fit_images(other, lfj.Stripes(), **kwargs, max_steps=50)) > 0


# -------------------------------------------- the two-step residual's written-out Jacobian


# g 0.7 under ``paper``: A(g) > 0.9, so the reference σs changes with g too.
@pytest.mark.parametrize("phase, g", [("paper", 0.3), ("paper", 0.7), ("normalized", 0.3)])
def test_two_step_residual_jacobian_matches_autodiff_and_differences(phase, g):
    """The Jacobian the two-step methods hand to Levenberg-Marquardt (and use for their
    uncertainties) is written out: check it against forward-mode autodiff of the
    residual and against central differences through the plain renderer."""
    import jax.numpy as jnp

    from lightfield_jax.forward.render import renderer_for
    from lightfield_jax.inverse.basins import reference_sigma_s
    from lightfield_jax.inverse.two_step import rendered_and_g_slope as _rendered_and_g_slope
    from lightfield_jax.inverse.two_step import two_step_residual as _two_step_residual

    grid = lfj.Grid(24, 16, 16, 1)
    sigma_t = jnp.asarray(0.2051)
    renderer = renderer_for(grid, lfj.Full(), 5, phase)
    rng = np.random.default_rng(1)
    d, m = (jnp.asarray(a) for a in _perfect_split("milk", grid))
    d, m = d * (1 + 0.05 * rng.standard_normal(d.shape)), m * 1.3  # not at the minimum
    mask = jnp.asarray(rng.random(d.shape) > 0.1)
    slope = _rendered_and_g_slope(renderer, sigma_t, phase)

    def residual(p):
        return _two_step_residual(slope, sigma_t, d, m, mask, 0.7, phase, p)

    p = jnp.asarray([0.05, g])
    r, jac, _a = residual(p)
    auto = jax.jacfwd(lambda q: residual(q)[0])(p)
    assert float(jnp.max(jnp.abs(jac))) > 0
    np.testing.assert_allclose(jac, auto, rtol=0, atol=1e-10 * float(jnp.max(jnp.abs(auto))))

    def plain(q):  # the same residual through renders, no slopes
        ref = reference_sigma_s(sigma_t, q[1], phase)[0]
        images = renderer(sigma_t, ref, q[1])[0][0]
        a = jnp.sum(jnp.where(mask, d * images[0], 0)) / jnp.sum(jnp.where(mask, images[0] ** 2, 0))
        u = q[0] / ref
        model = a * jnp.einsum("k,khw->hw", u ** jnp.arange(1, 5), images[1:])
        return jnp.where(mask, (m - model) / 0.7, 0.0).reshape(-1)

    np.testing.assert_allclose(r, plain(p), rtol=1e-12, atol=1e-15)
    for i in range(2):
        e = jnp.zeros(2).at[i].set(1e-6)
        fd = (plain(p + e) - plain(p - e)) / 2e-6
        np.testing.assert_allclose(jac[:, i], fd, rtol=0, atol=1e-6 * float(jnp.max(jnp.abs(fd))))


# ------------------------------------------- the global start and the honest verdicts


def _slab_milk(grid: lfj.Grid, slab: lfj.Slab, bounces, n_mu=None) -> np.ndarray:
    import dataclasses

    geometry = slab if n_mu is None else dataclasses.replace(slab, n_mu=n_mu)
    result = lfj.render(lfj.Medium(*MEDIA["milk"]), grid, lfj.Stripes(), bounces, geometry=geometry)
    return GAIN * np.asarray(result.total)


REFRACTIVE = lfj.Slab(6.4, boundary="refractive", n=1.33)


def test_a_start_forced_into_the_wrong_basin_is_not_trusted():
    """The paper's milk behind refractive faces has a second basin at g near -1 (where
    a locally started fit once ended, reporting convergence). Started there with the
    basin search off, the fit must say it is in a worse basin, never converged (the
    default start's recovery of the same medium: the slow test below)."""
    images = _slab_milk(lfj.Grid(32, 24), REFRACTIVE, "auto")
    wrong = lfj.fit_images(
        images,
        lfj.Stripes(),
        black_level=0.0,
        geometry=REFRACTIVE,
        model_error=False,
        start=(0.08, -0.9),
        max_steps=15,
    )
    assert not wrong.converged
    assert any("worse basin" in r for r in wrong.reasons), wrong.reasons
    assert wrong.g < 0 and wrong.to_dict()["converged"] is False
    (tried,) = wrong.to_dict()["basins"]["tried"]
    assert tried["start"]["g"] == -0.9 and tried["chosen"]
    # The better basin the scan found is not on the slope of this answer's: the line
    # from the answer to that basin's start does not rise all the way (it would be
    # skipped as the same basin otherwise).
    from types import SimpleNamespace

    from lightfield_jax.inverse.fit import model_from
    from lightfield_jax.inverse.joint_fit import FitContext, joint_weights
    from lightfield_jax.inverse.joint_fit.slope import downhill_from

    scan = wrong.to_dict()["basins"]
    best = scan["basins"][0]
    model = model_from(wrong.model)
    x0, y0, x1, y1 = model.crop
    cropped = images[:, y0:y1, x0:x1]
    data = SimpleNamespace(images=cropped)
    weights = joint_weights(cropped, np.ones(cropped.shape[1:], bool))
    answer = {k: getattr(wrong, k) for k in ("sigma_t", "sigma_s", "g", "black_level")}
    start = (scan["sigma_t"], best["albedo"] * scan["sigma_t"], best["g"], 0.0)
    options = lfj.FitOptions(geometry=REFRACTIVE)
    ctx = FitContext(data, lfj.Stripes(), options, 0.0, weights, images, None, print)
    assert not downhill_from(ctx, model, start, answer)


@pytest.mark.slow  # ~30 s (two noisy 64x48 fits); the line's own rule is tested above
def test_basins_on_the_slope_of_an_answer_found_are_not_solved_again(monkeypatch):
    """Shot noise breaks the scan's flat σt–g valley into several grid minima; those
    whose line to the first answer rises all the way are not solved (the answer is the
    one solving each of them gives)."""
    import lightfield_jax.inverse.joint_fit.search as search

    clean = _stripe_images("milk", lfj.Grid(64, 48))
    clean = clean / clean.max()
    images = np.random.default_rng(1).poisson(clean * 2e4) / 2e4

    def fit():
        result = lfj.fit_images(images, lfj.Stripes())
        return result, result.to_dict()["basins"]["tried"]

    skipping, tried = fit()
    skipped = [t for t in tried if t.get("by") == "a line downhill to it"]
    assert skipping.converged and skipped, tried
    monkeypatch.setattr(search, "downhill_from", lambda *args: False)
    solving, tried = fit()
    assert all("by" not in t for t in tried)
    assert {t["label"] for t in skipped} <= {t["label"] for t in tried if "same_as" in t}
    for key in ("sigma_t", "sigma_s", "g", "black_level"):
        assert getattr(skipping, key) == getattr(solving, key), key


@pytest.mark.slow
def test_refractive_tank_milk_from_a_finer_render_is_recovered():
    """The milk in a refractive-faced tank, rendered with a finer model than the fit's
    (32 azimuth bins, 16 elevation nodes, 40 bounces): the default fit recovers it."""
    images = _slab_milk(lfj.Grid(64, 48, 32), REFRACTIVE, 40, n_mu=16)
    result = lfj.fit_images(images, lfj.Stripes(), black_level=0.0, geometry=REFRACTIVE)
    err = _errors(result, "milk")
    assert result.converged, result.message
    scan = result.to_dict()["basins"]
    assert scan["basins"] and any(t.get("chosen") for t in scan["tried"])
    assert abs(err["sigma_t"]) < 0.01 and abs(err["sigma_s"]) < 0.03 and abs(err["g"]) < 0.02
    # The truth is inside the reported total 2σ (the model's own error included).
    for key, truth in zip(("sigma_t", "sigma_s", "g"), MEDIA["milk"], strict=True):
        assert abs(getattr(result, key) - truth) < 2 * result.uncertainty[key], key


def test_an_albedo_at_its_bound_is_not_trusted():
    medium = lfj.Medium(0.2, 0.0005, 0.3)  # albedo 0.0025: σs is at the edge of the model
    images = np.asarray(lfj.render(medium, SMALL, lfj.Stripes(), "auto").total)
    result = lfj.fit_images(
        images, lfj.Stripes(), black_level=0.0, n_theta=16, refine=1, model_error=False
    )
    assert not result.converged
    assert any("albedo" in r and "bound" in r for r in result.reasons), result.reasons
    assert result.to_dict()["converged"] is False


def test_a_misfit_far_above_the_noise_is_not_trusted():
    """Stray light (a constant 5 % of the peak) the model has no term for, with shot
    noise: the fit ends far above the noise and must say so (``offset_stop: 0``: by
    default the scan names the constant and the fit stops there, test_basins)."""
    clean = _stripe_images("milk", SMALL)
    rng = np.random.default_rng(0)
    photons = 1e5 / clean.max()
    images = rng.poisson((clean + 0.05 * clean.max()) * photons) / photons
    result = lfj.fit_images(
        images,
        lfj.Stripes(),
        black_level=0.0,
        n_theta=16,
        refine=1,
        max_basins=1,
        max_steps=20,
        model_error=False,
        offset_stop=0.0,
    )
    assert result.chi2_dof > 100 and result.chi2_model > 100
    assert not result.converged
    assert any("misfit far above" in r for r in result.reasons), result.reasons


def test_values_at_the_saturation_are_masked_one_shift_at_a_time():
    """A capture clipped at 10 % of its peak: the lit stripes near the entry wall are
    clipped in their lit shifts only. ``saturation`` masks those values (the same
    pixels' dark shifts still count in the joint fit), and the truth is recovered; fitted
    as they are, the clipped values cannot be, and the fit says so."""
    images = _stripe_images("milk", SMALL)
    clip = 0.1 * images.max()
    clipped = np.minimum(images, clip)
    kwargs = {"black_level": 0.0, "n_theta": 16, "refine": 1, "max_cells": 48 * 32 * 16}
    result = lfj.fit_images(clipped, lfj.Stripes(), saturation=clip, **kwargs)
    err = _errors(result, "milk")
    assert result.converged, result.message
    assert abs(err["sigma_t"]) < 0.005 and abs(err["sigma_s"]) < 0.005, err
    assert abs(err["g"]) < 0.005, err
    # The same with the clip given as a per-value mask.
    samples = lfj.fit_images(clipped, lfj.Stripes(), mask=clipped < clip, **kwargs)
    assert samples.sigma_s == pytest.approx(result.sigma_s, rel=1e-4)
    with pytest.raises(ValueError, match=r"mask: must have the images' \(height, width\)"):
        lfj.fit_images(clipped, lfj.Stripes(), mask=clipped[:2] < clip, **kwargs)
    unmasked = lfj.fit_images(clipped, lfj.Stripes(), max_basins=1, max_steps=20, **kwargs)
    assert not unmasked.converged


@pytest.mark.slow  # about 10-20 s: run by make test-slow
def test_values_the_answer_puts_near_the_clip_are_masked_too(tmp_path):
    """The clip keeps a value near it only when its noise went down: the kept values
    there are biased low (censoring), and with them σt (−0.64 %, −3.2σ, before) and σs
    (+2.4 %). The fit masks the values its answer puts within 3σ of the clip and solves
    again."""
    config = tmp_path / "sim.yaml"
    config.write_text(
        "grid: {width: 64, height: 48}\n"
        "medium: {sigma_t: 0.2051, sigma_s: 0.0366, g: 0.4, phase: paper}\n"
        "illumination: {kind: stripes, period: 6, lit: 3, shifts: 6, direction_deg: 0.0, "
        "entry: left}\n"
        "bounces: auto\ngain: 400\nnoise: {photons: 20000, read: 0.0005, seed: 0}\n"
    )
    images = np.asarray(lfj.simulate_capture(config).images)
    clip = float(0.05 * images.max())
    result = lfj.fit_images(
        np.minimum(images, clip), lfj.Stripes(), black_level=0.0, saturation=clip
    )
    assert result.converged, result.message
    censoring = result.model["censoring"]
    assert censoring["values_near_clip"] > 0 and censoring["refit"] == "kept"
    for key, value in zip(("sigma_t", "sigma_s"), MEDIA["milk"][:2], strict=False):
        z = (getattr(result, key) - value) / result.uncertainty[key]
        assert abs(z) < 2, (key, z)
    assert abs(result.g - 0.4) < 0.02


def test_near_the_clip_judges_the_fitted_light_not_the_values():
    from lightfield_jax.inverse.data import prepare_data
    from lightfield_jax.inverse.joint_fit import CLIP_SIGMAS, near_the_clip

    images = _stripe_images("milk", SMALL)
    level = 0.3 * images.max()
    data = prepare_data(np.minimum(images, level), lfj.Stripes(), saturation=level)
    np.testing.assert_array_equal(data.clip_level, level)
    sigma = np.full(images.shape, 0.05 * level)
    risk = near_the_clip(data, images, sigma)  # the truth's light as the answer's
    # The valid values whose light is within 3σ below the clip; never a clipped one.
    expected = (images < level) & (images + CLIP_SIGMAS * sigma >= level)
    assert expected.any()
    np.testing.assert_array_equal(risk, expected)
    assert near_the_clip(data, images, np.full(images.shape, 1e-9 * level)) is None
    # Without a saturation the level is the clipped value of each pixel (one stuck
    # pixel at a higher code does not move it elsewhere), else their median.
    clipped = np.minimum(images, level)
    clipped[:, 5, 40] = 2 * level  # a hot pixel, far from the wall
    data = prepare_data(clipped, lfj.Stripes(), clipped=clipped >= level)
    assert np.all(data.clip_level[:, 5, 40] == 2 * level)
    np.testing.assert_array_equal(np.delete(data.clip_level.reshape(6, -1), 5 * 48 + 40, 1), level)
    unclipped = prepare_data(images, lfj.Stripes())
    assert unclipped.clipped is None and near_the_clip(unclipped, images, sigma) is None


@pytest.mark.slow  # about 10-20 s: run by make test-slow
def test_dark_values_clamped_at_zero_are_censored_from_below(tmp_path):
    """A 16-bit file or a camera's black subtraction clamps the read noise of dark values
    at 0: those values are censored from below, and the values near 0 that are left
    are biased up. Fitted as they were, the near/far split disagreed (chi2 93, p ~ 1e-19)
    and sigma_s came out 'not identifiable' (exit 1) on a capture whose unclamped fit is
    exact. The fit finds the pile-up at 0, masks it and the values its answer puts
    within 3 sigma of it, and solves again."""
    config = tmp_path / "sim.yaml"
    config.write_text(
        "grid: {width: 48, height: 36}\n"
        "medium: {sigma_t: 0.2051, sigma_s: 0.0366, g: 0.4, phase: paper}\n"
        "illumination: {kind: stripes, period: 6, lit: 3, shifts: 6, direction_deg: 0.0, "
        "entry: left}\n"
        "bounces: auto\ngain: 1\nblack_level: 0.01\n"
    )
    clean = np.asarray(lfj.simulate_capture(config).images, np.float64)
    clean = 0.7 * clean / clean.max()
    rng = np.random.default_rng(6)
    photons = 2e4
    noisy = rng.poisson(clean * photons) / photons + rng.normal(0.0, 5e-4, clean.shape)
    clamped = np.clip(noisy, 0.0, None)
    assert 0.05 < np.mean(clamped == 0) < 0.3  # the far end is mostly dark
    result = lfj.fit_images(clamped, lfj.Stripes(), black_level=0.01)
    assert result.converged, result.message
    censoring = result.model["censoring"]
    assert censoring["values_near_floor"] > 0 and censoring["refit"] == "kept", censoring
    for key, value in zip(("sigma_t", "sigma_s", "g"), MEDIA["milk"], strict=True):
        z = (getattr(result, key) - value) / result.uncertainty[key]
        assert abs(z) < 3, (key, z)
    assert all(split["p"] > 1e-3 for split in result.consistency.values()), result.consistency


def test_a_floor_is_a_pile_up_at_the_lowest_value_not_a_tail():
    from lightfield_jax.inverse.data import FLOOR_MIN, floor_pileup, prepare_data, valid_values

    rng = np.random.default_rng(0)
    values = rng.normal(0.0, 1.0, (6, 20, 30)) + np.linspace(0, 40, 30)
    assert not floor_pileup(values).any()  # measured values: all distinct
    clamped = np.clip(values, 0.0, None)
    np.testing.assert_array_equal(floor_pileup(clamped), clamped == 0)
    # Only among the values asked about: zeros outside a mask are no floor.
    outside = np.zeros(values.shape, bool)
    outside[:, :, :3] = True
    zeroed = np.where(outside, 0.0, values + 5.0)
    assert not floor_pileup(zeroed, ~outside).any()
    # Integer codes with an offset: the lowest code is the noise's tail, fewer than the
    # next code up; a pile-up at a level far from dark is no floor either.
    codes = np.rint(values + 4.0)
    assert not floor_pileup(codes).any()
    assert not floor_pileup(np.maximum(values, 30.0)).any()
    few = np.where(values == values.min(), 0.0, values + 1.0)
    assert np.sum(few == 0) < FLOOR_MIN and not floor_pileup(few).any()
    # A noiseless render's decay flushed to 0 below float32's smallest normal number is
    # a pile-up, but nothing was cut there: no floor.
    decay = np.exp(-np.linspace(0.0, 95.0, 48)) * (1 + 1e-3 * rng.random((6, 32, 48)))
    flushed = np.where(decay < np.finfo(np.float32).tiny, 0.0, decay)
    assert floor_pileup(flushed).sum() >= FLOOR_MIN
    assert not valid_values(flushed, lfj.Stripes())[2].any()
    # prepare_data masks them and records their level where the capture shows read
    # noise; a given ``floored`` overrides. Zeros of shot noise alone are measured, not
    # cut (nothing falls below 0 without an additive noise): they stay.
    clean = _stripe_images("milk", SMALL)
    clean = clean / clean.max()
    rng = np.random.default_rng(3)
    shot = rng.poisson(clean * 2e4) / 2e4
    assert np.mean(shot == 0) > 0.03
    data = prepare_data(shot, lfj.Stripes())
    assert data.floor_level is None and data.samples is None
    dark = np.clip(shot + rng.normal(0.0, 5e-4, shot.shape), 0.0, None)
    data = prepare_data(dark, lfj.Stripes())
    np.testing.assert_array_equal(data.valid, dark > 0)
    np.testing.assert_array_equal(data.floor_level, 0.0)
    none = prepare_data(dark, lfj.Stripes(), floored=np.zeros(dark.shape, bool))
    assert none.floor_level is None and none.samples is None


@pytest.mark.slow  # the forward medium's plane fit: about 35 s
def test_geometry_auto_keeps_the_plane_for_a_forward_plane_capture():
    """The choice measures the plane model's misfit at its own answer: the answer the
    fit reports is stepped on to the continuum (extrapolate, the default), whose render
    on the model's grid misfits the capture by that step (measured: 1.29e-2 against a
    noise of 1.51e-3, the slab chosen; at the model's own answer 1.43e-3, the plane)."""
    clean = _stripe_images("forward", SMALL_FORWARD)
    photons = 1e6 / clean.max()
    images = np.random.default_rng(0).poisson(clean * photons) / photons
    result = lfj.fit_images(
        images,
        lfj.Stripes(),
        black_level=0.0,
        n_theta=SMALL_FORWARD.n_theta,
        refine=1,
        max_cells=SMALL_FORWARD.width * SMALL_FORWARD.height * SMALL_FORWARD.n_theta,
        geometry=lfj.AutoGeometry(lfj.Slab(6.4)),
    )
    assert result.model["finer_model"]["extrapolation"]["step"], result.model["finer_model"]
    choice = result.model["geometry_choice"]
    assert choice["chosen"] == "plane", choice


def test_geometry_auto_takes_a_mask_per_value():
    """The plane-or-slab choice measures its misfit on pixels valid in every shift, from
    a mask per value or the saturation (it broadcast a per-pixel mask only)."""
    clean = _stripe_images("milk", SMALL)
    photons = 1e5 / clean.max()
    images = np.random.default_rng(0).poisson(clean * photons) / photons
    clip = 0.1 * images.max()
    clipped = np.minimum(images, clip)
    result = lfj.fit_images(
        clipped,
        lfj.Stripes(),
        black_level=0.0,
        n_theta=16,
        refine=1,
        max_cells=48 * 32 * 16,
        saturation=clip,
        geometry=lfj.AutoGeometry(lfj.Slab(6.4)),
    )
    assert result.model["geometry_choice"]["chosen"] == "plane"
    assert result.converged, result.message
    assert abs(result.g - MEDIA["milk"][2]) < 0.01


@pytest.mark.slow  # about 10-20 s: run by make test-slow
def test_an_error_the_model_cannot_show_is_seen_by_the_parts_of_the_capture():
    """Light the model has no term for near the entry wall (up to +10 %, fading over 4
    pixels), with shot noise: the fit is biased (σt +2.7 %) with a misfit only 1.6×
    the noise. The capture's near and far halves, and its lit and dark rows, disagree
    beyond their noise, which enters the model term: the truth is inside the total 1σ.
    That term (the parts' own linearised answers) leaves σs and g undetermined (± 162 %,
    ± 0.63), so the fit is not trusted and says why. Without the stray light the parts
    agree and there is no such term."""
    st, ss, g = 0.2051, 0.0366, 0.4
    grid = lfj.Grid(48, 32)
    clean = 2.0 * np.asarray(lfj.render(lfj.Medium(st, ss, g), grid, lfj.Stripes(), "auto").total)
    photons = 5000 / clean.max()
    for amp in (0.0, 0.1):
        stray = clean * (1 + amp * np.exp(-np.arange(grid.width) / 4.0))
        images = np.random.default_rng(0).poisson(stray * photons) / photons
        result = lfj.fit_images(images, lfj.Stripes(), black_level=0.0)
        splits = result.consistency
        assert set(splits) == {"near/far", "lit/dark"}
        assert result.to_dict()["consistency"]["near/far"]["p"] == splits["near/far"]["p"]
        if amp == 0:
            assert all(v["p"] > 1e-3 for v in splits.values()), splits
            continue
        assert result.sigma_t / st - 1 > 0.02  # the bias the test is about
        assert all(v["p"] < 1e-6 for v in splits.values()), splits
        assert result.model_limited and not result.converged
        assert any("total 1σ" in r for r in result.reasons), result.reasons
        for key, truth in (("sigma_t", st), ("sigma_s", ss), ("g", g)):
            assert abs(getattr(result, key) - truth) < result.uncertainty[key], key


def test_noisy_fit_reports_chi2_near_one_and_a_total_error():
    result, _gain = _noisy_fit(SMALL, 0)
    assert 0.5 < result.chi2_dof < 2.0, result.chi2_dof
    for key in ("sigma_t", "sigma_s", "g"):
        stat, model = result.uncertainty_statistical[key], result.uncertainty_model[key]
        assert result.uncertainty[key] == pytest.approx(math.hypot(stat, model))
    d = result.to_dict()
    assert d["model_limited"] == result.model_limited and d["chi2_dof"] == result.chi2_dof


def test_a_second_channel_with_other_values_compiles_nothing_new():
    """The channels of a capture share one model (the largest need so far, one crop):
    a second channel with other values (another medium, another exposure) runs on the
    programs the first one compiled."""
    import types

    first = _stripe_images("milk", SMALL)
    medium = lfj.Medium(0.19, 0.03, 0.35)  # less scattering: needs no larger model
    second = 0.5 * np.asarray(lfj.render(medium, SMALL, lfj.Stripes(), "auto").total)
    capture = types.SimpleNamespace(
        images=np.stack([first, second], axis=-1),
        channel_names=("R", "G"),
        pattern=lfj.Stripes(),
        mask=np.ones(first.shape[1:] + (2,), bool),
        black_level=0.0,
        saturation=None,
        pixel_size_mm=None,
        geometry=None,
    )
    kwargs = dict(n_theta=16, refine=1, phase="paper")  # the renders' convention
    lfj.fit_capture(capture, channels=["R"], **kwargs)  # compiles, and sizes the floor
    fits = []
    count = programs_built(lambda: fits.append(lfj.fit_capture(capture, **kwargs)))
    # Fitting both channels again: R's programs serve G as well.
    assert count == 0
    assert fits[0]["G"].seconds["compile"] == 0.0
    assert fits[0]["G"].sigma_s == pytest.approx(0.03, rel=0.01)
    keys = ("width", "height", "n_theta", "refine", "bounces", "crop")
    assert [fits[0]["G"].model[k] for k in keys] == [fits[0]["R"].model[k] for k in keys]


def test_any_optimistix_least_squares_solver_can_be_passed():
    import optimistix as optx

    solver = optx.GaussNewton(rtol=1e-8, atol=1e-10)
    result = lfj.fit_images(
        _stripe_images("milk", SMALL),
        lfj.Stripes(),
        black_level=0.0,
        n_theta=16,
        refine=1,
        solver=solver,
        model_error=False,
    )
    err = _errors(result, "milk")
    assert result.converged, result.message
    assert abs(err["sigma_s"]) < 0.005 and abs(err["g"]) < 0.005, err


# ------------------------------------------------------------------ the series' tail

# A forward medium at albedo 0.95 (normalized phase): its series needs hundreds of
# bounces (the tail bound at the fit's margin asks for thousands). On this small grid
# walls leak much of the light at every bounce, so the automatic choice could march;
# the tests name the tail solve to test it.
HIGH_ALBEDO = (0.5, 0.475, 0.5)
TAIL_GRID = lfj.Grid(24, 16, 16, 1)


@functools.cache
def _high_albedo_images() -> np.ndarray:
    """Six stripe images of the high-albedo medium, the plain series marched to the tail
    bound's 1e-4 (no tail in the data)."""
    medium = lfj.Medium(*HIGH_ALBEDO, "normalized")
    return GAIN * np.asarray(lfj.render(medium, TAIL_GRID, lfj.Stripes(), "auto").total)


def _tail_fit(**kwargs) -> lfj.FitResult:
    return lfj.fit_images(
        _high_albedo_images(),
        lfj.Stripes(),
        black_level=0.0,
        phase="normalized",
        n_theta=TAIL_GRID.n_theta,
        refine=1,
        model_error=False,
        tail="bicgstab",
        **kwargs,
    )


@pytest.mark.slow
def test_a_high_albedo_capture_is_recovered_with_the_tail():
    result = _tail_fit()
    tail = result.to_dict()["model"]["tail"]
    assert tail["method"] == "bicgstab" and tail["K0"] == result.model["bounces"] == 8
    assert tail["converged"] and tail["steps"] > 0
    assert result.converged, result.message
    st, ss, g = HIGH_ALBEDO
    assert abs(result.sigma_t / st - 1) < 0.01
    assert abs(result.sigma_s / ss - 1) < 0.03
    assert abs(result.g - g) < 0.02


def test_a_tail_that_does_not_converge_is_not_trusted():
    """Two BiCGStab iterations cannot sum this series' tail: the fit must say so and
    never report convergence."""
    result = _tail_fit(tail_max_steps=2)
    assert not result.converged
    assert any("tail solve" in r and "did not converge" in r for r in result.reasons), (
        result.reasons
    )
    d = result.to_dict()
    assert d["converged"] is False and d["model"]["tail"]["converged"] is False
    assert d["model"]["tail"]["max_steps"] == 2


def test_few_bounces_keep_the_explicit_series():
    """The paper's milk needs few bounces: no tail, the per-bounce model as before."""
    result = _fit("milk", SMALL, "joint")
    assert result.model["tail"] is None and result.model["tail_bound"] is not None


def test_the_model_size_chooses_a_march_or_the_tail():
    """``tail: auto``: the tail bound's count where it is at most max_bounces (the milk);
    beyond it K0 and BiCGStab (albedo 0.99), unless the scan's measured per-bounce
    ratio asks for a march within max_bounces; ``tail: None`` marches, capped."""
    from lightfield_jax.inverse.model_size import by_measured_ratio, size_model

    images = np.zeros((6, 24, 32))
    crop = (0, 0, 32, 24)

    def sized(albedo, **kw):
        opts = lfj.FitOptions(phase="normalized", n_theta=16, refine=1, **kw)
        return size_model(images, lfj.Stripes(), albedo, 0.5, opts, crop=crop), opts

    low, _ = sized(0.3)
    assert low.tail is None and low.bounces <= 16
    high, opts = sized(0.99)
    assert (high.tail, high.bounces) == ("bicgstab", opts.model.tail_bounces)
    assert high.as_dict()["tail"]["K0"] == opts.model.tail_bounces
    assert high.as_dict()["tail_bound"] is None
    marched = by_measured_ratio(high, opts, 0.75)
    assert marched.tail is None and 32 <= marched.bounces <= opts.model.max_bounces
    assert marched.as_dict()["ratio_measured"] == 0.75
    assert by_measured_ratio(high, opts, 0.97).tail == "bicgstab"
    capped, opts = sized(0.99, tail=None)
    assert capped.tail is None and capped.bounces == opts.model.max_bounces
    forced, opts = sized(0.3, tail="gmres")
    assert (forced.tail, forced.bounces) == ("gmres", opts.model.tail_bounces)


def test_the_error_terms_plane_model_is_finer_past_256_bins():
    """At g 0.9 the fit's model has 256 θ bins and refine 2 on a small capture; the error
    term's model doubles the bins where memory allows (it stopped at 256: the same
    discretisation, a model term of zero), and refines space once more."""
    from lightfield_jax.inverse.joint_fit.finer import finer
    from lightfield_jax.inverse.model_size import size_model

    opts = lfj.FitOptions(phase="normalized")
    model = size_model(np.zeros((6, 24, 32)), lfj.Stripes(), 0.98, 0.9, opts, 1.03, 0.05)
    assert (model.grid.n_theta, model.grid.refine) == (256, 2)
    fine = finer(model, opts, 0.9)
    assert (fine.grid.n_theta, fine.grid.refine) == (512, 3)
    capped = lfj.FitOptions(phase="normalized", max_cells=10**5, max_render_cells=10**5)
    assert finer(model, capped, 0.9).grid == model.grid  # nothing finer fits


@pytest.mark.parametrize("ratio, cut", [(0.999, True), (1.2, True), (0.9, False)])
def test_a_divergent_bound_marched_to_a_cut_series_is_not_converged(ratio, cut):
    """Under the paper's phase ρ = ω·A(g) passes 1 for g ≳ 0.7 and the fit marches
    ``max_bounces``; where the ratio measured at the answer leaves more than 1 % of I_1
    past them, the fit says so (a reason: not converged); a ratio the march covers
    (0.9^80) gives none. A series the bound called convergent but marched to a given
    count (``tail: null`` caps it at ``max_bounces``) is judged alike."""
    from lightfield_jax.inverse.basins import Scan
    from lightfield_jax.inverse.joint_fit.verdict import cut_series
    from lightfield_jax.inverse.model_size import ModelSpec

    model = ModelSpec(lfj.Grid(32, 24, 32, 1), 80, (0, 0, 32, 24), converges=False, rho=1.3)
    two = np.array([-0.9, 0.9])
    scan = Scan(
        two, two, np.zeros((2, 2)), np.zeros((2, 2)), (), 0.2, {}, two * 0 + ratio, two * 0 + 0.2
    )
    values = {"sigma_t": 0.2, "sigma_s": 0.2, "g": 0.8}  # albedo 1: the ratio as measured
    options = lfj.FitOptions(phase="paper")
    reasons = cut_series(model, scan, values, options)
    assert bool(reasons) == cut
    if cut:
        assert "cut at 80 bounces" in reasons[0]
    converges = dataclasses.replace(model, converges=True, rho=0.95)
    assert bool(cut_series(converges, scan, values, options)) == cut
    summed = dataclasses.replace(converges, tail="bicgstab")
    assert cut_series(summed, scan, values, options) == []


def test_the_least_squares_steps_scale_their_columns():
    """The gain's Jacobian column and the coefficients' differ by the image units: the
    Gauss-Newton steps and covariances scale the columns before solving. Unscaled,
    lstsq's relative cutoff drops a column that small (it dropped the gain's direction
    for images in units 10^6x larger, and σs moved by 0.8σ on a noisy 48x36 milk)."""
    from lightfield_jax.inverse.lstsq import gram_inverse, scaled_lstsq

    rng = np.random.default_rng(0)
    jac = rng.normal(size=(500, 4))
    jac[:, 3] = 1e-12 * (jac[:, 2] + 0.05 * rng.normal(size=500))  # tiny, correlated
    truth = np.array([1.0, -2.0, 0.5, 3e11])
    rhs = jac @ truth + 1e-3 * rng.normal(size=500)
    exact = np.linalg.solve(jac.T @ jac, jac.T @ rhs)
    plain, *_ = np.linalg.lstsq(jac, rhs, rcond=None)
    assert abs(plain[2] / exact[2] - 1) > 1e-3  # the cutoff the scaling avoids
    np.testing.assert_allclose(scaled_lstsq(jac, rhs), exact, rtol=1e-6)
    np.testing.assert_allclose(gram_inverse(jac), np.linalg.inv(jac.T @ jac), rtol=1e-6)
    np.testing.assert_allclose(gram_inverse(jac, pseudo=True), gram_inverse(jac), rtol=1e-6)


@pytest.mark.slow
def test_a_noisy_capture_in_large_units_gives_the_same_answer():
    """The capture the scaling was found on: the paper's milk, 48x36, noisy (2e4
    photons, read noise 5e-4, seed 5; float32, the defect correction to 64 θ bins),
    fitted as it is and in units 10^6x larger."""
    from lightfield_jax.forward.simulate_config import parse_simulation_config

    config = {
        "grid": {"width": 48, "height": 36},
        "medium": {
            **dict(zip(("sigma_t", "sigma_s", "g"), MEDIA["milk"], strict=True)),
            "phase": "paper",
        },
        "illumination": {"kind": "stripes", "period": 6, "lit": 3, "shifts": 6},
    }
    peak = float(lfj.simulate_capture(parse_simulation_config(config)).images.max())
    config |= {"gain": 1 / peak, "noise": {"photons": 2e4, "read": 5e-4, "seed": 5}}
    images = lfj.simulate_capture(parse_simulation_config(config)).images
    with jax.enable_x64(False):
        results = [lfj.fit_images(images * np.float32(s), lfj.Stripes()) for s in (1, 1e6)]
    for key in ("sigma_t", "sigma_s", "g"):
        a, b = (getattr(r, key) for r in results)
        assert abs(a - b) < 0.05 * results[0].uncertainty[key], key


def test_the_correlations_go_with_the_total_uncertainty():
    """``correlation`` is the total covariance's: the noise's plus the finer model's
    signed shift (rank one) and any further model term (uncorrelated), so its diagonal
    is the total 1σ²; ``correlation_statistical`` is the noise's alone."""
    from lightfield_jax.inverse.budget import error_budget

    rng = np.random.default_rng(1)
    jac = rng.normal(size=(400, 3))
    jac[:, 2] = jac[:, 0] + 0.3 * jac[:, 2]  # a valley: parameters 0 and 2 correlated
    residual = rng.normal(size=400)
    shift_r = 0.5 * (jac[:, 0] - 2 * jac[:, 2])  # a model error along the valley's side
    names = ["sigma_t", "sigma_s", "g"]
    b = error_budget(jac, residual, names, 1.0, shift_r)
    stat = np.array([b.statistical[k] for k in names])
    total = np.array([b.total[k] for k in names])
    cov_stat = np.linalg.inv(jac.T @ jac) * max(1.0, b.chi2_dof)
    shift = -np.linalg.solve(jac.T @ jac, jac.T @ shift_r)
    np.testing.assert_allclose(stat, np.sqrt(np.diag(cov_stat)), rtol=1e-9)
    np.testing.assert_allclose(total, np.hypot(stat, np.abs(shift)), rtol=1e-9)
    cov = cov_stat + np.outer(shift, shift)
    for i, j in ((0, 1), (0, 2), (1, 2)):
        key = f"{names[i]},{names[j]}"
        assert b.correlation[key] == pytest.approx(cov[i, j] / (total[i] * total[j]))
        assert b.correlation_statistical[key] == pytest.approx(cov_stat[i, j] / (stat[i] * stat[j]))
    assert abs(b.correlation_statistical["sigma_t,g"]) > 0.9
    assert abs(b.correlation["sigma_t,g"] - b.correlation_statistical["sigma_t,g"]) > 0.01


def test_a_finer_model_that_is_not_finite_leaves_the_misfit_judged_against_the_noise():
    """A finer model's render that is not finite (a solve at a bound) measures no model
    error: chi2_model is the noise's χ² and the misfit rule still fires, instead of a
    NaN that hid a misfit 400 times the noise (an over-subtracted dark frame)."""
    from lightfield_jax.inverse.budget import error_budget
    from lightfield_jax.inverse.verdict import untrustworthy

    rng = np.random.default_rng(2)
    jac = rng.normal(size=(300, 3))
    residual = 20.0 * rng.normal(size=300)
    names = ["sigma_t", "sigma_s", "g"]
    shift_r = np.full(300, np.nan)
    b = error_budget(jac, residual, names, 1.0, shift_r)
    assert b.chi2_model == pytest.approx(b.chi2_dof) and b.chi2_dof > 100
    assert all(np.isfinite(v) for v in b.correlation.values())
    values = {"sigma_t": 0.2, "sigma_s": 0.05, "g": 0.3, "gain": 1.0}
    assert any("misfit far above" in r for r in untrustworthy(values, b, 100.0))


@pytest.mark.parametrize("shift", ["nan", "none", "measured"])
def test_a_misfit_judged_against_the_noise_alone_says_only_the_noise(shift):
    """Before: with the model's own error not measured (chi2_model the noise's χ²), the
    reason still said 'far above the capture's noise and the model's own error'."""
    from lightfield_jax.inverse.budget import error_budget
    from lightfield_jax.inverse.verdict import untrustworthy

    rng = np.random.default_rng(2)
    jac = rng.normal(size=(300, 3))
    residual = 20.0 * rng.normal(size=300)
    dr = {"nan": np.full(300, np.nan), "none": None, "measured": 0.1 * rng.normal(size=300)}
    b = error_budget(jac, residual, ["sigma_t", "sigma_s", "g"], 1.0, dr[shift])
    values = {"sigma_t": 0.2, "sigma_s": 0.05, "g": 0.3, "gain": 1.0}
    (reason,) = [r for r in untrustworthy(values, b, 100.0) if r.startswith("misfit")]
    if shift == "measured":
        assert reason.startswith("misfit far above the capture's noise and the model's own")
    else:
        assert reason.startswith("misfit far above the capture's noise: chi2/dof = "), reason
        assert reason.endswith("(the model's own error not measured)"), reason


@pytest.mark.parametrize("scale", [1e-30, 1e38])
def test_images_beyond_the_float32_scale_are_refused_before_the_fit(scale):
    """Before: the paper's milk times 1e-30 ended "converged" with g 0.30 ± 0.003 for 0.40
    (its noise variances underflowed), times 1e38 "rho: must be finite, got nan"."""
    rng = np.random.default_rng(0)
    images = (scale * rng.uniform(0.1, 1.0, (6, 12, 16))).astype(np.float32)
    with pytest.raises(ValueError, match=r"images: their values' 99th percentile is .* outside"):
        lfj.fit_images(images, lfj.Stripes())


@pytest.mark.slow  # about 25 s: run by make test-slow
def test_a_cut_series_names_a_setting_that_sums_the_orders_left_out():
    """The advice was 'raise max_bounces (or bounces), or ... tail: auto': the tail is
    the default already, and max_bounces does not move a count that was given or sized
    from the scan (measured: the same K and verdict at max_bounces 160). The setting
    the reason names, applied, must clear it."""
    from lightfield_jax.forward.simulate_config import parse_simulation_config

    config = {
        "grid": {"width": 24, "height": 16},
        "medium": {**dict(zip(("sigma_t", "sigma_s", "g"), MEDIA["milk"], strict=True)),
                   "phase": "paper"},
        "illumination": {"kind": "stripes", "period": 6, "lit": 3, "shifts": 6},
        "gain": 400, "black_level": 0.01, "noise": {"photons": 2e4, "read": 5e-4, "seed": 0},
    }  # fmt: skip
    images = np.asarray(lfj.simulate_capture(parse_simulation_config(config)).images)
    cut = lfj.fit_images(images, lfj.Stripes(), bounces=2)
    said = [r for r in cut.reasons if r.startswith("the bounce series is cut at 2 bounces")]
    assert said and not cut.converged, cut.reasons
    assert "max_bounces" not in said[0]
    setting = re.search(r"fit: \{bounces: (\d+)\}", said[0])
    assert setting, said[0]
    again = lfj.fit_images(images, lfj.Stripes(), bounces=int(setting.group(1)))
    assert not [r for r in again.reasons if "the bounce series is cut" in r], again.reasons
