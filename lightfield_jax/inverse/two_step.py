"""The paper's two-step problem after σt (docs/model.md §5-6): the multiple-scattering
image M against the series Σ_{k≥2} I_k, the gain from the single scatter, over (σs, g).

- :func:`poly_fit_sigma_s`: for one g, the exact σs of the paper's eq. 10 (a polynomial
  in σs, minimised densely then by Newton).
- :func:`two_step_residual`: the residual at (σs, g) with its Jacobian written out,
  the images' slope along g from :func:`rendered_and_g_slope`; what a least-squares
  solver (the package's, or an outside one) is handed.
- :func:`solve_two_step`: one compiled program: the search over g (the grid method),
  or an optimistix least-squares solve over (σs, g) (the gradient method) from a given
  start (:func:`centre_start`, or on a larger model the first model's answer) or from
  a search's best point; the residual and its Jacobian at the answer for the error
  budget. The fit methods (:mod:`lightfield_jax.inverse.methods`) call it.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from lightfield_jax.forward.kernels import einsum, matmul
from lightfield_jax.inverse.basins import reference_sigma_s
from lightfield_jax.inverse.budget import Uncertainty, error_budget
from lightfield_jax.inverse.data import FitData
from lightfield_jax.inverse.jacobian import with_jacobian
from lightfield_jax.inverse.programs import jitted
from lightfield_jax.runtime.timing import stopwatch
from lightfield_jax.scene.illumination import Full, Stripes


def masked_dot(a, b, mask):
    """Σ a·b over ``mask``."""
    return jnp.sum(jnp.where(mask, a * b, 0.0))


def full_for(pattern: Stripes) -> Full:
    """Full illumination from the stripes' direction and entry wall."""
    return Full(direction_deg=pattern.direction_deg, entry=pattern.entry)


def poly_fit_sigma_s(d, m, i1, ik, mask, u_max, n_grid: int = 2001):
    """The paper's eq. 10 for one g, on images rendered at a reference σs_ref:
    I_k(σs) = u^k I_k(σs_ref), u = σs/σs_ref. The gain from the single scatter,
    a = ⟨D, I_1⟩/⟨I_1, I_1⟩, then u* = argmin_{0≤u≤u_max} ‖M − a Σ_{k≥2} u^{k−1} I_k‖²
    (exact polynomial minimisation: dense evaluation, then Newton on the derivative).
    Returns (u*, a, residual²), the residual² summed from the residual itself: the
    expanded polynomial is a difference of large terms, which in float32 cannot tell
    apart values of g near the minimum (it left the grid's g error at ~1e-3 however
    dense the grid)."""
    a = masked_dot(d, i1, mask) / masked_dot(i1, i1, mask)
    kk = ik.shape[0]
    gram = einsum("khw,lhw->kl", jnp.where(mask, ik, 0.0), ik)
    mk = einsum("khw,hw->k", jnp.where(mask, ik, 0.0), m)
    mm = masked_dot(m, m, mask)
    # cost(u) = mm − 2a·Σ_k u^k mk_k + a²·Σ_kl u^k u^l G_kl = Σ_n c_n u^n, n = 0..2K: its
    # coefficients once, then values and derivatives of a polynomial (no autodiff of
    # a Newton loop, which would be most of the compiled program).
    n = 2 * kk + 1
    degree = jnp.arange(1, kk + 1)
    pairs = degree[:, None] + degree[None, :]
    coef = jnp.zeros(n, gram.dtype).at[0].set(mm).at[degree].add(-2 * a * mk)
    coef = coef.at[pairs.reshape(-1)].add((a**2 * gram).reshape(-1))
    orders = jnp.arange(n, dtype=gram.dtype)

    def powers(u, shift):  # u^(n − shift), 0 where n < shift
        e = orders - shift
        return jnp.where(e >= 0, u ** jnp.maximum(e, 0.0), 0.0)

    def cost(u):
        return matmul(powers(u, 0), coef)

    d1_coef = coef * orders
    d2_coef = coef * orders * (orders - 1)
    grid = jnp.linspace(0.0, 1.0, n_grid) * u_max
    costs = jax.vmap(cost)(grid)
    u = grid[jnp.argmin(costs)]
    for _ in range(6):
        d1, d2 = matmul(powers(u, 1), d1_coef), matmul(powers(u, 2), d2_coef)
        u = jnp.clip(u - d1 / jnp.where(d2 > 0, d2, jnp.inf), 0.0, u_max)
    r = m - a * einsum("k,khw->hw", u ** degree.astype(ik.dtype), ik)
    return u, a, masked_dot(r, r, mask)


def parabolic_minimum(xs, costs, best):
    """The vertex of the parabola through the grid's best point and its two
    neighbours (uniform spacing), kept within one spacing of the best point: (x, t)
    with t the offset in spacings. At an end of the grid, the best point itself."""
    n = xs.shape[0]
    i = jnp.clip(best, 1, n - 2)
    lo, mid, hi = costs[i - 1], costs[i], costs[i + 1]
    curvature = lo - 2 * mid + hi
    t = jnp.where(curvature > 0, 0.5 * (lo - hi) / jnp.where(curvature > 0, curvature, 1.0), 0.0)
    t = jnp.where((best > 0) & (best < n - 1), jnp.clip(t, -1.0, 1.0), 0.0)
    return xs[best] + t * (xs[1] - xs[0]), t


def rendered_and_g_slope(renderer, sigma_t, phase: str):
    """``x = [g]`` → (I_k at (σt, σs_ref(g), g) under full illumination, (K, h, w), and
    dI_k/dg, (K, h, w, 1)), differentiable in ``x`` through that slope. The renderer
    gives the slope (``images_and_g_slope``: the plane in one pass of its own code, the
    slab by ``jax.jvp``); I_k ∝ σs^k carries the change of σs_ref with g."""

    def reference(g):
        return reference_sigma_s(sigma_t, g, phase)[0]

    def value_and_jacobian(x):
        g = x[0]
        ref, dref = jax.jvp(reference, (g,), (jnp.ones_like(g),))
        images, slope = renderer.images_and_g_slope(sigma_t, ref, g)
        images, slope = images[0], slope[0]
        k = jnp.arange(1, images.shape[0] + 1, dtype=images.dtype)[:, None, None]
        return images, (slope + images * k * (dref / ref))[..., None]

    return with_jacobian(value_and_jacobian)


def two_step_residual(rendered_and_slope, sigma_t, d, m, mask, scale, phase: str, p):
    """The residual of eq. 10 at p = (σs, g) and its Jacobian written out: ``(r,
    ∂r/∂(σs, g) (N, 2), a = c·σs)``, r = mask·(M − a_ref Σ_{k≥2} u^{k−1} I_k)/scale with
    the images rendered at σs_ref(g), u = σs/σs_ref and a_ref = ⟨D, I_1⟩/⟨I_1, I_1⟩.
    The images' slope along g comes from ``rendered_and_slope``
    (:func:`rendered_and_g_slope`); σs and the gain enter in closed form, so the
    Jacobian costs no autodiff of this code (a small program)."""
    sigma_s, g = p[0], p[1]
    ref, dref = jax.jvp(lambda g: reference_sigma_s(sigma_t, g, phase)[0], (g,), (1.0 + 0 * g,))
    images, slope = rendered_and_slope(p[1:])
    slope = slope[..., 0]
    i1, s1 = images[0], slope[0]
    n1, n2 = masked_dot(d, i1, mask), masked_dot(i1, i1, mask)
    a_ref = n1 / n2  # the gain from the single scatter, and its slope along g
    da_ref = (masked_dot(d, s1, mask) * n2 - 2 * n1 * masked_dot(i1, s1, mask)) / n2**2
    k = jnp.arange(1, images.shape[0], dtype=images.dtype)
    u = sigma_s / ref  # I_k(σs) = u^k I_k(σs_ref)
    series = einsum("k,khw->hw", u**k, images[1:])
    d_series_du = einsum("k,khw->hw", k * u ** (k - 1), images[1:])
    # along g at fixed σs: the images change, and u with σs_ref
    d_series_dg = einsum("k,khw->hw", u**k, slope[1:]) - d_series_du * u * dref / ref
    jac = jnp.stack([a_ref * d_series_du / ref, da_ref * series + a_ref * d_series_dg], axis=-1)
    r = jnp.where(mask, (m - a_ref * series) / scale, 0.0).reshape(-1)
    jac = -jnp.where(mask[..., None], jac / scale, 0.0).reshape(-1, 2)
    return r, jac, a_ref * ref


def search_g(renderer, sigma_t, d, m, mask, gs, phase: str):
    """The search over ``gs``: for each g, render I_k at (σt, σs_ref(g), g) under full
    illumination (``lax.map``) and solve eq. 10 for σs (:func:`poly_fit_sigma_s`).
    Returns (σs, residual²), one value per g (the gain at the answer comes from the
    residual there, :func:`two_step_residual`)."""

    def per_g(g):
        ref, u_max = reference_sigma_s(sigma_t, g, phase)
        images = renderer(sigma_t, ref, g)[0][0]
        u, _, cost = poly_fit_sigma_s(d, m, images[0], images[1:], mask, u_max)
        return u * ref, cost

    return jax.lax.map(per_g, gs)


def sigma_s_max(sigma_t, g, phase: str):
    """The largest σs the two-step solve allows at g: min(σt, the σs where ρ = 1)."""
    ref, u_max = reference_sigma_s(sigma_t, g, phase)
    return ref * u_max


def sigma_s_bound(sigma_t: float, g: float, phase: str) -> float:
    """:func:`sigma_s_max` at concrete values, as a float: one small compiled program
    (op by op, its phase integral compiled some ten programs: about 0.5 s of a cold
    fit)."""
    return float(jitted(sigma_s_max, ("phase",))(sigma_t, g, phase))


def to_params(y, sigma_t, phase: str):
    """Unconstrained y → p = (σs, g): 0 < σs < :func:`sigma_s_max`, |g| < 1."""
    g = jnp.tanh(y[1])
    return jnp.stack([sigma_s_max(sigma_t, g, phase) * jax.nn.sigmoid(y[0]), g])


def search_start(gs, s_all, cost, sigma_t, phase: str):
    """The solve's start y (see :func:`to_params`): the vertex of the parabola through the
    search's best g and its neighbours, σs interpolated toward the neighbour."""
    best = jnp.argmin(cost)
    g_vertex, t = parabolic_minimum(gs, cost, best)
    near = jnp.clip(best + jnp.sign(t).astype(best.dtype), 0, gs.shape[0] - 1)
    s_vertex = s_all[best] + jnp.abs(t) * (s_all[near] - s_all[best])
    return start_y(jnp.stack([s_vertex, g_vertex]), sigma_t, phase)


def centre_start(sigma_t, phase: str) -> tuple[float, float]:
    """The gradient method's start without a search, (σs, g): g = 0 and σs half its
    bound there (:func:`sigma_s_max`), the solve's unconstrained y = 0
    (:func:`to_params`)."""
    return 0.5 * sigma_s_bound(sigma_t, 0.0, phase), 0.0


def start_y(start, sigma_t, phase: str):
    """The solve's start y (see :func:`to_params`) at ``start`` = (σs, g), kept off the
    bounds (σs within 0.1 % of them, |g| ≤ 0.95)."""
    s, g = start[0], start[1]
    frac = jnp.clip(s / sigma_s_max(sigma_t, g, phase), 1e-3, 1 - 1e-3)
    return jnp.stack([jnp.log(frac / (1 - frac)), jnp.arctanh(jnp.clip(g, -0.95, 0.95))])


@dataclasses.dataclass(frozen=True)
class TwoStepSettings:
    """Static settings of the two-step program: ``solve`` false, the search over g
    alone (the grid method); true, the solve over (σs, g) (the gradient method): with
    ``search`` false from a given start (:func:`centre_start`, or on a larger model the
    answer on the first: one copy of the render in the program), with ``search`` true
    from the best point of a search over g (two copies: the search's and the solve's);
    the phase convention, the step limit."""

    solve: bool
    phase: str
    max_steps: int
    search: bool = True


def two_step_run(
    settings: TwoStepSettings,
    solver_static,
    solver_arrays,
    renderer,
    sigma_t,
    d,
    m,
    mask,
    gs,
    scale,
    start=None,
):
    """The two-step program: the search over ``gs`` and (``settings.solve``) the solve
    over (σs, g) from its best point, or (``settings.search`` false) the solve alone from
    ``start`` = (σs, g); returns (σs, g, a = c·σs, r, ∂r/∂(σs, g), result, steps), the
    residual and its Jacobian evaluated explicitly at the answer."""
    phase = settings.phase
    rendered_and_slope = rendered_and_g_slope(renderer, sigma_t, phase)

    def residual(p):
        return two_step_residual(rendered_and_slope, sigma_t, d, m, mask, scale, phase, p)

    if settings.search or not settings.solve:
        s_all, cost = search_g(renderer, sigma_t, d, m, mask, gs, phase)
        best = jnp.argmin(cost)
        if not settings.solve:
            r, jac, a = residual(jnp.stack([s_all[best], gs[best]]))
            steps = jnp.asarray(gs.shape[0])
            return s_all[best], gs[best], a, r, jac, optx.RESULTS.successful, steps
        y0 = search_start(gs, s_all, cost, sigma_t, phase)
    else:
        y0 = start_y(start, sigma_t, phase)
    solver = eqx.combine(solver_arrays, solver_static)

    def residual_y(y):  # (r, (r, ∂r/∂p, a)) and their Jacobians in y (of the second: 0)
        r, jac, a = residual(to_params(y, sigma_t, phase))
        jac_y = matmul(jac, jax.jacfwd(lambda y: to_params(y, sigma_t, phase))(y))
        return (r, (r, jac, a)), (
            jac_y,
            (jnp.zeros(r.shape + y.shape), jnp.zeros(jac.shape + y.shape), jnp.zeros(y.shape)),
        )

    # The solver linearises a matrix product J·δy (the custom JVP), not the residual's
    # code: one copy of the renderer in the loop, a small program.
    residual_y = with_jacobian(residual_y)
    sol = optx.least_squares(
        lambda y, _: residual_y(y)[0],
        solver,
        y0,
        has_aux=True,
        max_steps=settings.max_steps,
        throw=False,
    )
    s, g = to_params(sol.value, sigma_t, phase)
    if isinstance(solver, optx.AbstractGaussNewton):
        # Gauss-Newton solvers keep the auxiliary output at their last accepted point,
        # the answer: its residual and Jacobian without another copy of the render
        # (about a second of compilation), and a = c·σs from that render.
        r, jac, a = sol.state.aux
    else:
        r, jac, a = residual(jnp.stack([s, g]))
    return s, g, a, r, jac, sol.result, sol.stats["num_steps"]


@dataclasses.dataclass(frozen=True)
class TwoStepSolution:
    """The two-step answer: σs (per pixel), g, the gain, the residual's RMS in image
    units, the error budget of (σs, g), the solver's result, its steps (the search's
    size for the grid method) and the seconds spent compiling."""

    sigma_s: float
    g: float
    gain: float
    rms: float
    budget: Uncertainty
    result: optx.RESULTS
    steps: int
    compile: float


def problem_arrays(data: FitData, renderer, n_g: int) -> tuple:
    """The arguments of the two-step program after its static settings: ``(renderer,
    σt, D, M, mask, g values, scale)``, each value that depends on the data an argument
    rather than a constant of the program (a persistent compilation cache then serves
    any capture of this shape). ``scale``, the RMS of M, puts the residuals in units of
    the data, so solver tolerances mean the same for any exposure."""
    dtype = jnp.result_type(float)
    scale = float(np.sqrt(np.mean(np.square(data.multiple[data.mask])))) or 1.0
    return (
        renderer,
        jnp.asarray(data.sigma_t0, dtype),
        jnp.asarray(data.direct, dtype),
        jnp.asarray(data.multiple, dtype),
        jnp.asarray(data.mask),
        jnp.linspace(-0.95, 0.95, n_g, dtype=dtype),
        jnp.asarray(scale, dtype),
    )


def solve_two_step(
    data: FitData, renderer, solver, settings: TwoStepSettings, n_g: int, start=None
) -> TwoStepSolution:
    """Run the two-step program (:func:`two_step_run`) on ``data`` at its σt estimate:
    ``renderer`` renders full illumination on the model, ``solver`` is the optimistix
    least-squares solver of the gradient method, ``n_g`` values of g on (−0.95, 0.95)
    are searched (not with ``settings.search`` false: the solve then starts at
    ``start`` = (σs, g)). One compiled program (search, solve and the Jacobian for the
    uncertainties).

    σs enters the model only through the polynomial (I_k ∝ σs^k), so the residual's
    derivative in σs is exact without the renderer, and one forward-mode pass through
    the renderer along g gives the Jacobian of each step."""
    args = problem_arrays(data, renderer, n_g)
    scale = float(args[-1])
    if not settings.search:
        if not settings.solve or start is None:
            raise ValueError("solve_two_step: without the search, a solve and its start")
        args = (*args, jnp.asarray(start, args[1].dtype))
    run = jitted(two_step_run, ("settings", "solver_static"))
    arrays, static = eqx.partition(solver, eqx.is_array)
    with stopwatch() as timing:
        out = jax.block_until_ready(run(settings, static, arrays, *args))
    s, g, a, r, jac, result, steps = out
    s, g = float(s), float(g)
    r = np.asarray(r, np.float64)
    return TwoStepSolution(
        sigma_s=s,
        g=g,
        gain=float(a) / s if s > 0 else math.inf,
        rms=scale * float(np.sqrt(np.sum(r**2) / max(int(np.sum(data.mask)), 1))),
        budget=error_budget(np.asarray(jac), r, ["sigma_s", "g"], math.nan),
        result=result,
        steps=int(steps),
        compile=timing.compile,
    )


__all__ = [
    "TwoStepSettings",
    "TwoStepSolution",
    "centre_start",
    "full_for",
    "masked_dot",
    "poly_fit_sigma_s",
    "problem_arrays",
    "rendered_and_g_slope",
    "search_g",
    "search_start",
    "sigma_s_bound",
    "sigma_s_max",
    "solve_two_step",
    "start_y",
    "to_params",
    "two_step_residual",
    "two_step_run",
]
