"""Fit methods as values (:mod:`lightfield_jax.inverse.methods`): any optimistix
least-squares solver gives the answer Levenberg-Marquardt gives, the names map onto
the methods, a minimiser is refused, and the prepared data are frozen records."""

import dataclasses
import functools

import equinox as eqx
import numpy as np
import optimistix as optx
import pytest
from programs_support import programs_built

import lightfield_jax as lfj
from lightfield_jax.inverse.data import prepare_data

MILK = lfj.Medium(0.2051, 0.0366, 0.4)
GRID = lfj.Grid(32, 24, 16, 1)
GAIN = 3.0
MODEL = dict(black_level=0.0, n_theta=GRID.n_theta, refine=1, model_error=False)
DOGLEG = optx.Dogleg(rtol=1e-8, atol=1e-10)


@functools.cache
def _images() -> np.ndarray:
    return GAIN * np.asarray(lfj.render(MILK, GRID, lfj.Stripes(), "auto").total)


@functools.cache
def _split() -> tuple[np.ndarray, np.ndarray]:
    images = GAIN * np.asarray(lfj.render(MILK, GRID, lfj.Full(), "auto").images)
    return images[0], images[1:].sum(axis=0)


def _values(result: lfj.FitResult) -> np.ndarray:
    return np.array([result.sigma_t, result.sigma_s, result.g, result.gain])


@pytest.mark.slow  # the default suite keeps to ~10 min on 2 cores
def test_joint_with_dogleg_gives_the_levenberg_marquardt_answer():
    start = (0.03, 0.3)
    lm = lfj.fit_images(_images(), lfj.Stripes(), method=lfj.Joint(start=start), **MODEL)
    dogleg = lfj.fit_images(
        _images(), lfj.Stripes(), method=lfj.Joint(solver=DOGLEG, start=start), **MODEL
    )
    assert lm.converged and dogleg.converged, (lm.message, dogleg.message)
    assert lm.method == dogleg.method == "joint"
    np.testing.assert_allclose(_values(dogleg), _values(lm), rtol=1e-5)
    # The method's start is the option's start.
    by_option = lfj.fit_images(_images(), lfj.Stripes(), start=start, **MODEL)
    np.testing.assert_array_equal(_values(by_option), _values(lm))


def test_two_step_with_another_solver_gives_the_gradient_answer():
    kwargs = dict(split=_split(), **MODEL)
    named = lfj.fit_images(_images(), lfj.Stripes(), method="gradient", **kwargs)
    dogleg = lfj.fit_images(_images(), lfj.Stripes(), method=lfj.TwoStep(solver=DOGLEG), **kwargs)
    assert named.converged and dogleg.converged, (named.message, dogleg.message)
    assert dogleg.method == "gradient"
    np.testing.assert_allclose(_values(dogleg), _values(named), rtol=1e-6)
    assert abs(dogleg.g - 0.4) < 0.01 and abs(dogleg.sigma_s / 0.0366 - 1) < 0.01


@pytest.mark.parametrize(
    "max_steps",
    [2, pytest.param(3, marks=pytest.mark.slow), pytest.param(100, marks=pytest.mark.slow)],
)
def test_the_gradient_programs_residual_and_jacobian_are_those_at_its_answer(max_steps):
    """The gradient program takes r and ∂r/∂(σs, g) at its answer from a Gauss-Newton
    solver's last accepted evaluation (its auxiliary output) instead of a second copy
    of the render: they must be a fresh evaluation's at the answer, also for a solve
    stopped after two or three steps (where ``sol.aux`` is the point before)."""
    import jax.numpy as jnp

    from lightfield_jax.forward.render import renderer_for
    from lightfield_jax.inverse.programs import jitted
    from lightfield_jax.inverse.two_step import (
        TwoStepSettings,
        rendered_and_g_slope,
        two_step_residual,
        two_step_run,
    )

    direct, multiple = _split()  # with 2 % noise: a residual well above rounding
    noise = 1 + 0.02 * np.random.default_rng(0).standard_normal(multiple.shape)
    d, m = jnp.asarray(direct), jnp.asarray(multiple * noise)
    mask = jnp.ones(d.shape, bool)
    renderer = renderer_for(GRID, lfj.Full(), 8, "paper")
    st, scale = jnp.asarray(MILK.sigma_t), jnp.asarray(float(np.sqrt(np.mean(m**2))))
    lm = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-10)
    arrays, static = eqx.partition(lm, eqx.is_array)
    s, g, _a, r, jac, _result, steps = jitted(two_step_run, ("settings", "solver_static"))(
        TwoStepSettings(True, "paper", max_steps),
        static,
        arrays,
        renderer,
        st,
        d,
        m,
        mask,
        jnp.linspace(-0.95, 0.95, 9),
        scale,
    )
    assert int(steps) == max_steps or max_steps == 100
    slope = rendered_and_g_slope(renderer, st, "paper")
    fresh_r, fresh_jac, _ = two_step_residual(
        slope, st, d, m, mask, scale, "paper", jnp.stack([s, g])
    )
    assert float(jnp.sum(fresh_r**2)) > 1e-6
    np.testing.assert_allclose(r, fresh_r, rtol=0, atol=1e-9 * float(jnp.max(jnp.abs(fresh_r))))
    np.testing.assert_allclose(jac, fresh_jac, rtol=1e-9, atol=1e-12)


def test_a_solver_passed_as_a_value_is_compiled_once():
    """The solver is a static part of the two-step program: a second capture of the
    same shape with the same (equal, newly built) solver compiles nothing."""
    split = _split()
    kwargs = dict(method=lfj.TwoStep(solver=optx.Dogleg(rtol=1e-8, atol=1e-10)), **MODEL)
    lfj.fit_images(_images(), lfj.Stripes(), split=split, **kwargs)
    other = dict(kwargs, method=lfj.TwoStep(solver=optx.Dogleg(rtol=1e-8, atol=1e-10)))
    fits = []
    count = programs_built(
        lambda: fits.append(
            lfj.fit_images(
                0.8 * _images(), lfj.Stripes(), split=(0.8 * split[0], 0.8 * split[1]), **other
            )
        )
    )
    assert count == 0 and fits[0].seconds["compile"] == 0.0
    assert fits[0].sigma_s == pytest.approx(0.0366, rel=0.01)


def test_grid_search_is_the_grid_method():
    kwargs = dict(split=_split(), **MODEL)
    named = lfj.fit_images(_images(), lfj.Stripes(), method="grid", g_grid=9, **kwargs)
    search = lfj.fit_images(
        _images(), lfj.Stripes(), options=lfj.FitOptions(method=lfj.GridSearch(9)), **kwargs
    )
    np.testing.assert_array_equal(_values(search), _values(named))
    assert search.method == "grid" and search.iterations == 9


@pytest.mark.parametrize(
    "make",
    [
        lambda s: lfj.Joint(solver=s),
        lambda s: lfj.TwoStep(solver=s),
        lambda s: lfj.FitOptions(solver=s),
    ],
)
def test_a_minimiser_is_refused_with_a_clear_error(make):
    with pytest.raises(ValueError, match="solver: must be an optimistix least-squares solver"):
        make(optx.BFGS(rtol=1e-6, atol=1e-6))


def test_bad_method_settings_are_refused():
    with pytest.raises(ValueError, match="method: must be one of joint, gradient, grid"):
        lfj.FitOptions(method="newton")
    with pytest.raises(ValueError, match=r"g_values: must be an integer in \[3, 100000\], got 2"):
        lfj.GridSearch(2)
    # A billion g values ran until killed (the API's twin of fit: {g_grid: 1e9}).
    with pytest.raises(ValueError, match=r"g_values: must be an integer in \[3, 100000\]"):
        lfj.GridSearch(10**9)
    with pytest.raises(ValueError, match=r"start_grid: must be an integer <= 100000"):
        lfj.TwoStep(start_grid=10**7)
    with pytest.raises(
        ValueError, match=r"start_grid: must be 0 \(no search\) or at least 3, got 2"
    ):
        lfj.TwoStep(start_grid=2)
    with pytest.raises(ValueError, match="start: must be"):
        lfj.Joint(start=(0.03, 1.2))


def test_flat_settings_go_to_their_group_or_to_the_method_that_owns_them():
    options = lfj.FitOptions(method="grid", g_grid=21, n_theta=32, max_chi2=50.0, max_steps=7)
    assert options.method == lfj.GridSearch(21)
    assert (options.model.n_theta, options.trust.max_chi2, options.solve.max_steps) == (32, 50.0, 7)
    assert options == lfj.FitOptions(**options.flat())
    slab = lfj.FitOptions(geometry=lfj.Slab(6.4))
    assert slab.replace(n_theta=16).model.geometry == lfj.Slab(6.4)
    # A method's setting lives in the method only: the same fit however it is given.
    assert lfj.FitOptions(method="gradient", start_grid=5).method == lfj.TwoStep(start_grid=5)
    assert lfj.FitOptions(start=(0.03, 0.4)).method == lfj.Joint(start=(0.03, 0.4))
    # A method given as a value keeps its own setting; a name takes the one it replaces.
    assert lfj.FitOptions(method=lfj.GridSearch(9), g_grid=21).method == lfj.GridSearch(9)
    joint = lfj.FitOptions(solver=optx.Dogleg(rtol=1e-6, atol=1e-8), max_steps=7)
    assert joint.replace(method="gradient").method.solver == joint.method.solver
    assert joint.replace(method="gradient").solve.max_steps == 7
    # g_grid / start_grid are checked for every method (a capture file's fit: keys are
    # read before the command chooses one), then apply to the method that takes them.
    assert lfj.FitOptions(g_grid=21).method == lfj.Joint()
    # ... and are kept for a method chosen later (fit_images(options=..., method=...)).
    assert lfj.FitOptions(g_grid=21).replace(method="grid").method == lfj.GridSearch(21)
    kept = lfj.FitOptions(g_grid=21, start_grid=5)
    assert kept.replace(method="gradient").method == lfj.TwoStep(start_grid=5)
    assert kept == lfj.FitOptions(**kept.flat()) and kept != lfj.FitOptions()
    # A method's setting given to replace() replaces the method's own; it reads back
    # from the method that takes it.
    grid = lfj.FitOptions(method="grid", g_grid=30)
    assert grid.replace(g_grid=21).method == lfj.GridSearch(21) and grid.g_grid == 30
    assert grid.replace(n_theta=16).method == lfj.GridSearch(30)
    assert lfj.FitOptions(start=(0.03, 0.4)).replace(start=(0.05, 0.5)).start == (0.05, 0.5)
    with pytest.raises(AttributeError, match="'g_grid' .the joint method does not take it"):
        _ = lfj.FitOptions().g_grid
    with pytest.raises(ValueError, match=r"^g_grid: must be an integer in \[3, 100000\]"):
        lfj.FitOptions(g_grid=2)
    with pytest.raises(
        TypeError, match=r"^FitOptions: unknown setting 'n_thetas' \(the settings: "
    ):
        lfj.FitOptions(n_thetas=32)
    with pytest.raises(ValueError, match="^model: must be a ModelOptions or None, got dict"):
        lfj.FitOptions(model={"n_theta": 32})


def test_the_options_know_every_method_by_its_name():
    # The options check a method's name below the methods (method_base): every method
    # is known there under its own name, and nothing else is.
    from lightfield_jax.inverse.method_base import METHOD_NAMES
    from lightfield_jax.inverse.methods import METHODS

    assert tuple(METHODS) == METHOD_NAMES
    assert all(method.name == name for name, method in METHODS.items())


def test_prepared_data_are_frozen_and_cropped_alike():
    exposure = np.ones_like(_images())
    data = prepare_data(_images(), lfj.Stripes(), black_level=0.0, exposure=exposure)
    crop = (2, 3, 20, 15)
    cut = data.cropped(crop)
    for name in ("mask", "direct", "multiple"):
        assert getattr(cut, name).shape == (12, 18)
        np.testing.assert_array_equal(getattr(cut, name), getattr(data, name)[3:15, 2:20])
    assert cut.images.shape == cut.exposure.shape == (6, 12, 18)
    assert cut.sigma_t0 == data.sigma_t0
    with pytest.raises(dataclasses.FrozenInstanceError):
        cut.images = data.images


@pytest.mark.parametrize("method", ["grid", pytest.param("gradient", marks=pytest.mark.slow)])
def test_two_step_methods_march_where_the_joint_fit_gets_a_tail(method):
    # ω 0.99: the joint fit's model sums the series past K0 by a tail solve; the
    # two-step residual needs per-bounce images, so it marches max_bounces and says
    # the series was truncated instead of raising (or calling the answer converged).
    medium = lfj.Medium(0.1, 0.099, 0.0, phase="normalized")
    grid = lfj.Grid(48, 32, 16, 1)
    images = np.asarray(lfj.render(medium, grid, lfj.Stripes(), 400).total)
    kwargs = dict(method=method, phase="normalized", n_theta=16, refine=1, model_error=False)
    fit = lfj.fit_images(images, lfj.Stripes(), **kwargs)
    assert fit.model["tail"] is None and fit.model["bounces"] == 80
    assert not fit.converged and "truncated at 80 bounces" in fit.message
    # With the series marched far enough the same method trusts its answer.
    long = lfj.fit_images(images, lfj.Stripes(), max_bounces=400, **kwargs)
    assert long.model["tail"] is None and long.model["bounces"] > 80
    assert "truncated" not in long.message


@pytest.mark.parametrize("start_grid", [0, pytest.param(9, marks=pytest.mark.slow)])
def test_the_gradient_solves_a_larger_model_from_its_first_answer_without_searching_again(
    monkeypatch, start_grid
):
    """Where the first answer needs a much larger model (a forward medium: 4× the θ
    bins), the gradient method solves on it from that answer: a search over g for the
    start (``start_grid`` values) is compiled once (on the first model), not again on
    the larger one; by default none is, and the answer is the larger model's own, the
    one a search and solve there finds."""
    import jax.numpy as jnp

    from lightfield_jax.forward.render import renderer_for
    from lightfield_jax.inverse import two_step

    medium, grid = lfj.Medium(0.25, 0.15, 0.7), lfj.Grid(30, 22, 16, 1)
    full = GAIN * np.asarray(lfj.render(medium, grid, lfj.Full(), "auto").images)
    split = (full[0], full[1:].sum(axis=0))
    images = GAIN * np.asarray(lfj.render(medium, grid, lfj.Stripes(), "auto").total)
    searched = []
    search = two_step.search_g
    monkeypatch.setattr(
        two_step, "search_g", lambda *a, **k: searched.append(a[0]) or search(*a, **k)
    )
    said = []
    lfj.clear_compiled()
    result = lfj.fit_images(
        images,
        lfj.Stripes(),
        method=lfj.TwoStep(start_grid=start_grid),
        split=split,
        black_level=0.0,
        model_error=False,
        progress=said.append,
    )
    assert any("again with the model the estimate needs" in m for m in said), said
    assert result.converged, result.message
    assert result.model["n_theta"] >= 4 * grid.n_theta
    assert len(searched) == (start_grid > 0), "a search was compiled for the larger model"
    # The same minimum as a search (9 values of g) and solve on the larger model.
    model = result.model
    larger = lfj.Grid(30, 22, model["n_theta"], model["refine"])
    data = prepare_data(images, lfj.Stripes(), black_level=0.0, split=split)
    again = two_step.solve_two_step(
        data,
        renderer_for(larger, lfj.Full(), model["bounces"], "paper"),
        optx.LevenbergMarquardt(rtol=1e-4, atol=1e-4),
        two_step.TwoStepSettings(True, "paper", 100),
        9,
    )
    np.testing.assert_allclose([result.sigma_s, result.g], [again.sigma_s, again.g], rtol=2e-4)
    assert float(jnp.asarray(result.sigma_t)) == pytest.approx(data.sigma_t0)


@pytest.mark.slow  # about 15 s
def test_the_gradient_from_g_0_recovers_a_high_albedo_forward_medium():
    """Without a search the gradient solve starts at g = 0 (σs half its bound); on a
    perfect split of an albedo-0.9 forward medium it lands on the truth (measured: a
    start from the best of a 9-value search settled at σs 0.1505, g 0.666 instead,
    docs/fit_speed.md)."""
    medium, grid = lfj.Medium(0.2, 0.18, 0.6), lfj.Grid(32, 24, 16, 1)
    full = GAIN * np.asarray(lfj.render(medium, grid, lfj.Full(), "auto").images)
    images = GAIN * np.asarray(lfj.render(medium, grid, lfj.Stripes(), "auto").total)
    result = lfj.fit_images(
        images,
        lfj.Stripes(),
        method="gradient",
        split=(full[0], full[1:].sum(axis=0)),
        black_level=0.0,
        n_theta=grid.n_theta,
        refine=1,
        max_cells=grid.width * grid.height * grid.n_theta,
        extrapolate=False,
        model_error=False,
    )
    assert result.converged, result.message
    assert result.sigma_s == pytest.approx(0.18, rel=1e-3)
    assert result.g == pytest.approx(0.6, abs=1e-3)
