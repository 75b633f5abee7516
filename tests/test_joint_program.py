"""The joint fit's compiled solve (lightfield_jax.inverse.joint.solve): the model and
Jacobian it returns at its answer come from the solver's last accepted render (its
auxiliary output), so they must be exactly what a fresh forward-mode pass at the
returned answer gives, however the solve ended (converged, or stopped after two or three
steps, where the auxiliary output ``sol.aux`` would still be the previous point's), with
explicit bounces and with a tail solve."""

import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import lightfield_jax as lfj
from lightfield_jax.forward.render import renderer_for
from lightfield_jax.inverse.joint import (
    JointSettings,
    model_and_jacobian,
    pack,
    solve,
)

GRID = lfj.Grid(24, 16, 16, 1)
TRUTH = (0.2, 0.1, 0.5)


@pytest.mark.parametrize("tail", [None, "bicgstab"])
# 3 steps is slow-marked (two more compiled programs): 2 ends at the step limit, 50
# converges, and either keeps the answer's render.
@pytest.mark.parametrize("max_steps", [2, pytest.param(3, marks=pytest.mark.slow), 50])
def test_the_returned_model_and_jacobian_are_those_at_the_answer(tail, max_steps):
    pattern = lfj.Stripes()
    obs = 2.0 * np.asarray(lfj.render(lfj.Medium(*TRUTH, "normalized"), GRID, pattern, 12).total)
    renderer = renderer_for(GRID, pattern, 6, "normalized", None, tail, 1e-6, 200)
    settings = JointSettings(fit_black=True, lit=pattern.lit, max_steps=max_steps)
    dtype = jnp.result_type(float)
    y0 = pack((0.22, 0.07, 0.2, 0.05), True, dtype)
    black = jnp.asarray(0.0, dtype)
    weights = jnp.ones(obs.shape, dtype)
    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-8)
    y, _, steps, model, jac, _ = solve(
        settings, solver, renderer, None, jnp.asarray(obs, dtype), black, weights, y0
    )
    assert 2 <= int(steps) <= max_steps
    assert not np.allclose(np.asarray(y), np.asarray(y0))  # it moved
    fresh_model, fresh_jac = model_and_jacobian(settings, renderer, None, black, y)
    scale = float(jnp.max(jnp.abs(fresh_model)))
    np.testing.assert_allclose(model, fresh_model, rtol=0, atol=1e-5 * scale)
    jac_scale = np.max(np.abs(np.asarray(fresh_jac)), axis=(0, 1, 2))
    np.testing.assert_allclose(
        np.asarray(jac) / jac_scale, np.asarray(fresh_jac) / jac_scale, rtol=0, atol=1e-5
    )
