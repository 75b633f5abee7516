"""Defect correction (lightfield_jax.inverse.correction) on a small analytic model: the
large model's least-squares answer from its renders and a cheap model's Jacobian."""

import functools

import numpy as np
import pytest

import lightfield_jax as lfj
from lightfield_jax.inverse.correction import correct, in_domain

X = np.arange(12.0)[None, None, :] + np.arange(3.0)[None, :, None]
SHIFTS = np.array([0.0, 1.0])[:, None, None]


def model(v, stretch=1.0):
    """A stand-in render (P=2, 3×12) at unit gain; ``stretch`` ≠ 1: the cheap model."""
    st, ss, g = v["sigma_t"], v["sigma_s"], v["g"]
    decay = np.exp(-stretch * st * (X + SHIFTS))
    return ss * decay * (1.0 + g * np.cos(0.5 * X + SHIFTS)) + 0.01


def jac_unit(v, stretch):
    out = []
    for k in ("sigma_t", "sigma_s", "g"):
        h = 1e-6
        up, dn = dict(v), dict(v)
        up[k] += h
        dn[k] -= h
        out.append((model(up, stretch) - model(dn, stretch)) / (2 * h))
    return np.stack(out, axis=-1)


TRUTH = {"sigma_t": 0.2, "sigma_s": 0.15, "g": 0.6, "black_level": 0.0}


def render(v):
    return model(v), None


@pytest.mark.parametrize("stretch", [1.0, 1.05])
def test_correction_reaches_the_large_models_answer(stretch):
    obs = 2.5 * model(TRUTH)
    start = {"sigma_t": 0.21, "sigma_s": 0.14, "g": 0.55, "black_level": 0.0}
    c = correct(render, obs, np.ones_like(obs), start, jac_unit(start, stretch), None)
    assert c.converged, c.reason
    for k in ("sigma_t", "sigma_s", "g"):
        assert abs(c.values[k] - TRUTH[k]) < 1e-3 * max(abs(TRUTH[k]), 0.1), (k, c.values)
    assert abs(c.values["gain"] - 2.5) < 1e-2
    # The cheap Jacobian costs renders, not accuracy.
    assert len(c.steps) >= 2


def test_correction_with_a_wrong_jacobian_says_so():
    obs = model(TRUTH)
    start = {"sigma_t": 0.21, "sigma_s": 0.14, "g": 0.55, "black_level": 0.0}
    wrong = -jac_unit(start, 1.0)  # every step goes the wrong way
    c = correct(render, obs, np.ones_like(obs), start, wrong, None)
    assert not c.converged
    assert c.reason


def test_a_tail_that_did_not_converge_stops_it():
    start = dict(TRUTH)

    def bad(v):
        return model(v), {"steps": 200, "converged": False}

    c = correct(bad, model(TRUTH), np.ones((2, 3, 12)), start, jac_unit(start, 1.0), None)
    assert not c.converged and "tail" in c.reason


def test_in_domain():
    assert in_domain({"sigma_t": 0.2, "sigma_s": 0.1, "g": 0.5}, None)
    assert not in_domain({"sigma_t": 0.1, "sigma_s": 0.2, "g": 0.0}, None)
    assert not in_domain({"sigma_t": 0.2, "sigma_s": 0.1, "g": 0.995}, None)
    assert not in_domain(
        {"sigma_t": 0.2, "sigma_s": 0.1, "g": 0.0, "black_level": 2.0}, (-0.2, 1.0)
    )


def test_geometric_extrapolation_sums_a_geometric_series():
    """unit_model(extrapolate=True): orders I_k = a·r^k summed to infinity from K of them
    (exact for a geometric series), at the rendered σs (u = 1) and at another (u ≠ 1)."""
    import jax.numpy as jnp

    from lightfield_jax.inverse.joint import unit_model

    r, k = 0.8, 10
    a = jnp.linspace(1.0, 2.0, 2 * 3 * 4).reshape(2, 1, 3, 4)
    orders = a * r ** jnp.arange(1, k + 1, dtype=jnp.float32)[None, :, None, None]
    for u in (1.0, 1.1):
        got = unit_model((orders, None), 1, u, 0.0, extrapolate=True)
        want = a[:, 0] * (u * r) / (1 - u * r)
        assert np.allclose(np.asarray(got), np.asarray(want), rtol=1e-5)
        plain = unit_model((orders, None), 1, u, 0.0)
        assert not np.allclose(np.asarray(plain), np.asarray(want), rtol=1e-2)


# ------------------------------------------------------------ in the joint fit

DENSE = (0.15, 0.12, 0.7)  # albedo 0.8, forward: a long series, a refined model


@functools.cache
def _dense_capture() -> np.ndarray:
    """Six stripe images of the dense forward medium on the grid its g asks for (64 θ
    bins, 2× refined), the series marched to its tail bound."""
    medium = lfj.Medium(*DENSE, "normalized")
    grid = lfj.Grid(32, 24, lfj.default_n_theta(DENSE[2]), lfj.default_refine(DENSE[2]))
    return 2.0 * np.asarray(lfj.render(medium, grid, lfj.Stripes(), "auto").total)


def _dense_fit(**kwargs) -> lfj.FitResult:
    return lfj.fit_images(
        _dense_capture(), lfj.Stripes(), black_level=0.0, phase="normalized", **kwargs
    )


def test_a_dense_forward_capture_is_recovered_through_the_correction():
    """The default fit solves on a cheap model (32 θ bins, native grid, 24 bounces and a
    geometric tail) and corrects its answer to the model the capture needs."""
    result = _dense_fit()
    correction = result.model["correction"]
    assert correction["converged"] and correction["renders"] >= 2, correction
    assert result.model["refine"] == 2 and result.model["n_theta"] >= 64
    assert result.converged, result.message
    st, ss, g = DENSE
    assert abs(result.sigma_t / st - 1) < 0.005
    assert abs(result.sigma_s / ss - 1) < 0.005
    assert abs(result.g - g) < 0.005


@pytest.mark.slow
@pytest.mark.parametrize("name", ["milk", "dense"])
def test_the_truth_is_inside_the_total_two_sigma_in_nine_fits_of_ten(name):
    """Coverage over noise seeds (not one run): Poisson noise, 2·10⁴ photons at the
    brightest pixel; the truth inside the reported total 2σ for at least 90 % of the
    (seed, parameter) pairs, and every fit converged. The dense forward medium goes
    through the cheap solve and its correction, the milk through the marched model."""
    if name == "milk":
        truth, phase = (0.2051, 0.0366, 0.4), "paper"
        medium = lfj.Medium(*truth, phase)
        clean = np.asarray(lfj.render(medium, lfj.Grid(48, 32), lfj.Stripes(), "auto").total)
    else:
        truth, phase, clean = DENSE, "normalized", _dense_capture()
    clean = clean / clean.max()
    inside, total = 0, 0
    for seed in range(10):
        rng = np.random.default_rng(seed)
        images = rng.poisson(clean * 2e4) / 2e4
        result = lfj.fit_images(images, lfj.Stripes(), black_level=0.0, phase=phase)
        assert result.converged, (seed, result.message)
        for key, value in zip(("sigma_t", "sigma_s", "g"), truth, strict=True):
            inside += abs(getattr(result, key) - value) <= 2 * result.uncertainty[key]
            total += 1
    assert inside >= 0.9 * total, f"{inside} of {total} inside 2σ"
