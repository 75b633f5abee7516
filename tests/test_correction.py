"""Defect correction (lightfield_jax.inverse.correction) on a small analytic model: the
large model's least-squares answer from its renders and a cheap model's Jacobian."""

import functools

import numpy as np
import pytest

import lightfield_jax as lfj
from lightfield_jax.inverse.correction import correct, in_domain
from lightfield_jax.inverse.fit import model_from

X = np.arange(12.0)[None, None, :] + np.arange(3.0)[None, :, None]
SHIFTS = np.array([0.0, 1.0])[:, None, None]
NAMES = ("sigma_t", "sigma_s", "g", "black_level")


def model(v, stretch=1.0):
    """A stand-in render (P=2, 3×12) at unit gain with a black level b; ``stretch`` ≠ 1:
    another model (the cheap one, or the capture's reality)."""
    st, ss, g, b = (v[k] for k in NAMES)
    decay = np.exp(-stretch * st * (X + SHIFTS))
    # Single scatter ∝ σs and a second order ∝ σs² (σs apart from the gain).
    r = ss * decay * (1.0 + g * np.cos(0.5 * stretch * X + SHIFTS)) + 3 * ss**2 * decay**0.5
    return (1.0 - b) * r + b * r.mean(axis=0)


def jac_unit(v, stretch, names=NAMES[:3]):
    out = []
    for k in names:
        h = 1e-6
        up, dn = dict(v), dict(v)
        up[k] += h
        dn[k] -= h
        out.append((model(up, stretch) - model(dn, stretch)) / (2 * h))
    return np.stack(out, axis=-1)


def least_squares(obs, start, names):
    """The large model's own weighted least-squares answer (unit weights), by plain
    Gauss–Newton with its exact Jacobian and the gain in closed form: the reference."""
    v = dict(start)
    for _ in range(50):
        unit = model(v)
        gain = float(np.sum(unit * obs) / np.sum(unit * unit))
        r = (gain * unit - obs).reshape(-1)
        cols = gain * jac_unit(v, 1.0, names).reshape(-1, len(names))
        jac = np.concatenate([cols, unit.reshape(-1, 1)], axis=1)
        delta = np.linalg.lstsq(jac, -r, rcond=None)[0]
        v.update({k: v[k] + d for k, d in zip(names, delta, strict=False)})
        if np.max(np.abs(delta[: len(names)])) < 1e-12:
            break
    return v


TRUTH = {"sigma_t": 0.2, "sigma_s": 0.15, "g": 0.6, "black_level": 0.0}
START = {"sigma_t": 0.21, "sigma_s": 0.14, "g": 0.55, "black_level": 0.0, "gain": 2.4}


def render(v):
    return model(v), None


@pytest.mark.parametrize("stretch", [1.0, 1.05])
def test_correction_reaches_the_large_models_answer(stretch):
    obs = 2.5 * model(TRUTH)
    c = correct(render, obs, np.ones_like(obs), START, jac_unit(START, stretch), None)
    assert c.converged, c.reason
    for k in ("sigma_t", "sigma_s", "g"):
        assert abs(c.values[k] - TRUTH[k]) < 5e-4 * max(abs(TRUTH[k]), 0.1), (k, c.values)
    assert abs(c.values["gain"] / 2.5 - 1) < 5e-4


def test_with_a_misfit_it_is_the_large_models_least_squares_answer():
    """Data the large model cannot fit (another 'reality', noise) and a cheap Jacobian
    10 % off, the black level fitted: the answer is the large model's own least-squares
    answer (Jᵀr = 0), not the cheap Jacobian's fixed point (J_cᵀr = 0)."""
    names = list(NAMES)
    rng = np.random.default_rng(0)
    reality = {**TRUTH, "black_level": 0.1}
    obs = 2.5 * model(reality, 0.99) * (1 + 0.01 * rng.standard_normal(X.shape))
    start = {**START, "black_level": 0.05}
    c = correct(render, obs, np.ones_like(obs), start, jac_unit(start, 1.05, names), (-0.2, 1.0))
    assert c.converged, c.reason
    want = least_squares(obs, start, names)
    for k in names:
        assert abs(c.values[k] - want[k]) < 2e-4 * max(abs(want[k]), 0.1), (k, c.values, want)
    assert c.steps[-1]["jacobian"] == "exact"


def test_a_wrong_cheap_jacobian_costs_renders_not_the_answer():
    """A cheap Jacobian whose steps go the wrong way: the iteration turns to the large
    model's own Jacobian from the best point it rendered, and still gets the answer."""
    obs = 2.5 * model(TRUTH)
    wrong = -jac_unit(START, 1.0)
    c = correct(render, obs, np.ones_like(obs), START, wrong, None)
    assert c.converged, c.reason
    assert [s["jacobian"] for s in c.steps][:2] == ["cheap", "cheap"]
    assert abs(c.values["sigma_t"] / TRUTH["sigma_t"] - 1) < 5e-4


def test_slowly_shrinking_steps_get_the_renders_they_need_or_stop_early():
    """A cheap Jacobian 2.5× too large: each step goes 0.4 of the way, so the steps
    shrink by about 0.6 per render. With the default budget the iteration converges;
    with a budget its rate cannot meet, it stops as soon as the rate says so."""
    obs = 2.5 * model(TRUTH)
    steep = 2.5 * jac_unit(START, 1.0)
    c = correct(render, obs, np.ones_like(obs), START, steep, None)
    assert c.converged, c.reason
    assert 8 < c.renders <= 16  # more than the former budget of 8
    assert abs(c.values["sigma_t"] / TRUTH["sigma_t"] - 1) < 5e-4
    short = correct(render, obs, np.ones_like(obs), START, steep, None, max_iterations=6)
    assert not short.converged
    assert "shrink by 0.6" in short.reason and short.renders == 3, short.reason


def test_an_answer_outside_the_domain_is_not_converged():
    """Data whose best σs exceeds σt (no valid medium): the correction must not say it
    converged."""
    obs = 2.5 * model({**TRUTH, "sigma_s": 0.3})
    c = correct(render, obs, np.ones_like(obs), START, jac_unit(START, 1.0), None)
    assert not c.converged and c.reason


def test_a_non_finite_render_stops_it():
    c = correct(
        lambda v: (np.full((2, 3, 12), np.nan), None),
        model(TRUTH),
        np.ones((2, 3, 12)),
        START,
        jac_unit(START, 1.0),
        None,
    )
    assert not c.converged and "non-finite" in c.reason


def test_a_tail_that_did_not_converge_stops_it():
    def bad(v):
        return model(v), {"steps": 200, "converged": False}

    start = {**TRUTH, "gain": 1.0}
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
    geometric tail) and corrects its answer to the model the capture needs. The capture
    is rendered on that model's own grid, which is its truth: the model's own answer
    (``extrapolate`` off; the default steps on to the continuum's, tests/test_dense_media.py)."""
    result = _dense_fit(extrapolate=False)
    correction = result.model["correction"]
    assert correction["converged"] and correction["renders"] >= 2, correction
    assert result.model["refine"] == 2 and result.model["n_theta"] >= 64
    # Its full light's bounces after the eighth on the native grid (coarse_after; its
    # side-wall stripes the cell marches refined throughout), and the error term's finer
    # model marching twice as many refined before its own.
    coarse = {"after": 8, "n_theta": result.model["n_theta"], "refine": 1, "stripes": False}
    assert result.model["coarse_tail"] == coarse
    assert result.model["stripe_cell"] == {"shift_orders": 10, "walls_coarsen": 1}
    fine = result.model["finer_model"]
    assert fine["coarse_after"] == (16 if fine["bounces"] > 16 else None)
    # The model a result names renders as fitted (fitted_images): the cell, the coarse
    # tail for full light.
    assert model_from(result.model).coarse == 8 and model_from(result.model).cell == 10
    assert result.converged, result.message
    st, ss, g = DENSE
    assert abs(result.sigma_t / st - 1) < 0.005
    assert abs(result.sigma_s / ss - 1) < 0.005
    assert abs(result.g - g) < 0.005


@pytest.mark.slow  # about 10-20 s: run by make test-slow
def test_the_two_step_methods_march_every_bounce_on_the_models_grid():
    # The paper's baseline takes no coarse tail, on a capture whose joint fit does (12
    # bounces: past the joint fit's coarse_after 8).
    result = _dense_fit(method="grid", bounces=12)
    assert result.model["refine"] == 2 and result.model["bounces"] > 8
    assert result.model["coarse_tail"] is None


@pytest.mark.slow
@pytest.mark.parametrize("name", ["milk", "dense"])
def test_the_truth_is_inside_the_total_two_sigma_in_nine_fits_of_ten(name):
    """Coverage over noise seeds (not one run): Poisson noise, 2·10⁴ photons at the
    brightest pixel; the truth inside the reported total 2σ for at least 90 % of the
    (seed, parameter) pairs, and every fit converged. The dense forward medium goes
    through the cheap solve and its correction, the milk through the marched model.
    The captures are the model's own renders: fitted without the extrapolation to the
    continuum (on by default), whose answer is not theirs (the dense medium's moves
    σt by -1.7 % here, its discretisation error; the Monte Carlo captures' coverage is
    tests/test_dense_media.py's)."""
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
        result = lfj.fit_images(
            images, lfj.Stripes(), black_level=0.0, phase=phase, extrapolate=False
        )
        assert result.converged, (seed, result.message)
        for key, value in zip(("sigma_t", "sigma_s", "g"), truth, strict=True):
            inside += abs(getattr(result, key) - value) <= 2 * result.uncertainty[key]
            total += 1
    assert inside >= 0.9 * total, f"{inside} of {total} inside 2σ"
