"""Fit methods as values: :class:`GridSearch`, :class:`TwoStep` and :class:`Joint`, each a
small module with one :meth:`FitMethod.solve` signature, passed to a fit as
``fit_images(..., method=Joint(solver=optx.Dogleg(1e-8, 1e-10)))`` or
``FitOptions(method=TwoStep())``. The names ``"grid"``, ``"gradient"`` and ``"joint"``
map onto them with their default settings (:data:`METHODS`); each method owns its
settings, and reads the others (model, trust, solver limits) from the
:class:`~lightfield_jax.inverse.settings.FitSettings` its :meth:`FitMethod.solve` gets.

- :class:`GridSearch` (the paper's baseline): σt from the decay of the separated direct
  image, then g searched on a grid with σs from eq. 10 at each g
  (:mod:`lightfield_jax.inverse.two_step`).
- :class:`TwoStep` (``gradient``): the same residual solved over (σs, g) by an
  optimistix least-squares solver from g = 0 and σs half its bound (or from a coarse
  search's best point, ``start_grid``).
- :class:`Joint` (``joint``): σt, σs, g, gain (and the black level) fitted to the raw
  shifted images from the basin scan's starts (:mod:`lightfield_jax.inverse.basins`,
  :mod:`lightfield_jax.inverse.joint`).

``solver`` is any optimistix least-squares solver (Levenberg-Marquardt, ``Dogleg``,
``GaussNewton``, ...); ``None`` is Levenberg-Marquardt with the tolerances of the
settings' ``solve`` group. A minimiser (``BFGS``) is refused: the residuals are
least-squares problems.
"""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import optimistix as optx

from lightfield_jax.checks import check_int
from lightfield_jax.inverse.data import FitProblem, FitSolution
from lightfield_jax.inverse.joint_fit import joint_fit
from lightfield_jax.inverse.joint_fit.stage import (
    least_squares_solver,
    model_renderer,
    result_message,
)
from lightfield_jax.inverse.method_base import (
    MAX_G_VALUES,
    FitMethod,
    check_method,
    check_solver,
    check_start,
    check_start_grid,
)
from lightfield_jax.inverse.model_size import at_least, size_model
from lightfield_jax.inverse.two_step import (
    TwoStepSettings,
    centre_start,
    full_for,
    sigma_s_bound,
    solve_two_step,
)
from lightfield_jax.inverse.verdict import untrustworthy

# The default numbers of g values of the grid search (the paper's method) and of the
# coarse search that starts the gradient method: none. The two-step residual's misfit is
# one smooth valley in g (the demo capture's 39 values fall to one minimum), and a solve
# from g = 0 lands on the searched start's answer (to the solver's tolerance) in as
# few steps, while a search adds a second copy of the render to the compiled program
# (a third of its compile time, docs/fit_speed.md).
G_VALUES = 39
START_GRID = 0


class GridSearch(FitMethod):
    """The paper's method: g searched on ``g_values`` points of (−0.95, 0.95) (the flat
    setting ``g_grid``), σs from eq. 10 at each."""

    g_values: int = G_VALUES
    name: ClassVar[str] = "grid"
    per_bounce: ClassVar[bool] = True
    option_names: ClassVar[dict[str, str]] = {"g_grid": "g_values"}

    def __check_init__(self):
        check_int(self.g_values, "g_values", low=3, high=MAX_G_VALUES)

    def solve(self, problem, options, say):
        say(f"{self.name}: search over g")
        return _two_step_fit(self.name, problem, options, say, None, self.g_values)


class TwoStep(FitMethod):
    """The two-step residual solved over (σs, g) by ``solver`` (see the module), started
    at g = 0 and σs half its bound there (``start_grid`` 0), or from the best point of a
    search over ``start_grid`` (at least 3) values of g."""

    solver: optx.AbstractLeastSquaresSolver | None = None
    start_grid: int = START_GRID
    name: ClassVar[str] = "gradient"
    per_bounce: ClassVar[bool] = True
    option_names: ClassVar[dict[str, str]] = {"solver": "solver", "start_grid": "start_grid"}

    def __check_init__(self):
        check_solver(self.solver)
        check_start_grid(self.start_grid)

    def solve(self, problem, options, say):
        solver = least_squares_solver(self.solver, options.solve, jnp.result_type(float))
        start = (
            f"search over {self.start_grid} values of g and" if self.start_grid else "from g = 0,"
        )
        say(f"{self.name}: {start} {type(solver).__name__} over (sigma_s, g)")
        return _two_step_fit(self.name, problem, options, say, solver, self.start_grid)


class Joint(FitMethod):
    """The joint fit to the raw images by ``solver`` (see the module), from ``start`` =
    (σs, g) (σt from the decay fit) instead of the basin scan's starts when given."""

    solver: optx.AbstractLeastSquaresSolver | None = None
    start: tuple[float, float] | None = eqx.field(default=None, converter=check_start)
    name: ClassVar[str] = "joint"
    option_names: ClassVar[dict[str, str]] = {"solver": "solver", "start": "start"}

    def __check_init__(self):
        check_solver(self.solver)
        check_start(self.start)

    def solve(self, problem, options, say):
        model, seconds, values = joint_fit(problem, options, say, self.solver, self.start)
        return FitSolution(model=model, seconds=seconds, values=values)


METHODS: dict[str, FitMethod] = {"joint": Joint(), "gradient": TwoStep(), "grid": GridSearch()}


def method_for(method: str | FitMethod) -> FitMethod:
    """The :class:`FitMethod` of a method's name (its default settings), or ``method``
    itself."""
    if isinstance(method, FitMethod):
        return method
    return METHODS[check_method(method)]


# The two-step methods march at most ``max_bounces``; orders left out that sum to more
# than this fraction of the single-scattering image make the fit untrustworthy.
TRUNCATION_LIMIT = 0.01


def _marched(model):
    """``model`` with every bounce on its own grid: the two-step methods, the paper's
    baseline, take no coarse tail (``coarse_after`` is the joint fit's)."""
    return dataclasses.replace(model, coarse_after=None)


def _grown(problem: FitProblem, options, model, sigma_s: float, g: float):
    """The model an estimate (σs, g) needs where it is much larger than ``model`` (4×
    the θ bins, a finer grid, more bounces, a slab's depth layers or twice its elevation
    nodes: a forward-peaked medium), else ``None`` (a 2× θ difference costs less than a
    refit)."""
    data = problem.data
    if not (math.isfinite(sigma_s) and math.isfinite(g) and sigma_s > 0):
        return None
    need = size_model(
        problem.images,
        problem.pattern,
        albedo=min(sigma_s / data.sigma_t0, 0.98),
        g=g,
        options=options,
        sigma_t=data.sigma_t0,
        crop=model.crop,
    )
    deeper = need.geometry.deeper(model.geometry)
    if (
        need.grid.n_theta >= 4 * model.grid.n_theta
        or need.grid.refine > model.grid.refine
        or need.bounces > model.bounces
        or deeper
    ):
        return _marched(at_least(need, model))
    return None


def _model_words(model) -> str:
    words = f"n_theta {model.grid.n_theta}, refine {model.grid.refine}, {model.bounces} bounces"
    return words + model.geometry.words()


def _two_step_fit(name: str, problem: FitProblem, options, say, solver, n_g: int) -> FitSolution:
    """The two-step methods after σt: solve on the first model (sized before g was
    known, g = 0); where the estimate needs a much larger one (:func:`_grown`), once more
    on that one: the grid searches again, the gradient method solves from its first
    answer without the search (its program then holds one copy of the render, not two,
    and renders no search on the larger model). The gradient method's first solve
    starts at :func:`centre_start` where ``n_g`` is 0 (no search), else at the best of
    a search over ``n_g`` values of g."""
    data = problem.data
    phase = options.model.phase
    solve = solver is not None
    settings = TwoStepSettings(solve, phase, options.solve.max_steps, search=not solve or n_g > 0)

    def on(model, settings=settings, start=None):
        renderer = model_renderer(model, full_for(problem.pattern), phase)
        return solve_two_step(data, renderer, solver, settings, n_g, start)

    model = _marched(at_least(problem.model, problem.floor))
    sol = on(model, start=None if settings.search else centre_start(data.sigma_t0, phase))
    compile_s = sol.compile
    bigger = _grown(problem, options, model, sol.sigma_s, sol.g)
    if bigger is not None:
        say(f"{name}: again with the model the estimate needs ({_model_words(bigger)})")
        model = bigger
        if solver is None:
            sol = on(model)
        else:
            sol = on(model, dataclasses.replace(settings, search=False), (sol.sigma_s, sol.g))
        compile_s += sol.compile
    ok, msg = result_message(sol.result)
    if solver is None:
        msg = f"grid search over {n_g} values of g"
    truncated = model.tail_bound
    if truncated is not None and truncated > TRUNCATION_LIMIT:
        ok, msg = (
            False,
            (
                f"the series is truncated at {model.bounces} bounces (the orders left out sum "
                f"to about {truncated:.2g} of I_1 at the estimate): raise max_bounces or use "
                f"method: joint"
            ),
        )
    if not data.decay_converged:
        ok, msg = False, "the decay fit of sigma_t did not converge"
    stat = {"sigma_t": data.sigma_t0_err, **sol.budget.statistical}
    budget = dataclasses.replace(sol.budget, statistical=stat, total=stat)
    # The joint fit's rules for an answer not to be trusted (a bound, a parameter the
    # capture does not determine, a gain that is not positive); no misfit test here.
    found = {"sigma_t": data.sigma_t0, "sigma_s": sol.sigma_s, "g": sol.g, "gain": sol.gain}
    reasons = untrustworthy(found, budget, math.inf)
    cap = sigma_s_bound(data.sigma_t0, sol.g, phase)
    if math.isfinite(sol.g) and sol.sigma_s >= (1 - 1e-3) * cap:
        reasons.append(
            f"sigma_s = {sol.sigma_s:.4g} is at the two-step's bound {cap:.4g} (sigma_t, "
            "or the sigma_s where the bounce series stops converging)"
        )
    if reasons:
        ok, msg = False, "not trustworthy: " + "; ".join(reasons) + f" ({msg})"
    return FitSolution(
        model=model,
        seconds={"compile": compile_s, "run": 0.0},
        values=dict(
            method=name,
            sigma_t=data.sigma_t0,
            sigma_s=sol.sigma_s,
            g=sol.g,
            gain=sol.gain,
            black_level=problem.black_level,
            budget=budget,
            converged=ok,
            message=msg,
            iterations=n_g if solver is None else sol.steps,
            residual=sol.rms,
            reasons=tuple(reasons),
        ),
    )


__all__ = ["METHODS", "GridSearch", "Joint", "TwoStep", "method_for"]
