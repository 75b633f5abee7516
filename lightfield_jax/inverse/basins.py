"""The joint fit's global start: a scan of the misfit over (g, albedo) on a cheap model.

A joint fit started locally can settle in a wrong basin and say it converged (the
paper's milk behind refractive faces: g −0.97, σs +162 %). Before the full solve, the
scan evaluates the joint residual everywhere on a grid of g and albedo ω = σs/σt, with
σt from the decay of the direct image, on a cheap model (coarse grid and θ bins, the
bounces the capture's brightness ratio calls for):

- per g, one render of the per-bounce images I_k at a reference σs (``lax.map`` over
  g); every albedo on the grid is then the polynomial Σ_k u^k I_k (I_k ∝ σs^k), so the
  albedo axis costs no render;
- the gain (and the projector's black level, where it is fitted) is eliminated by
  variable projection: at each grid point the model is linear in c·(1 − b) and c·b,
  whose least-squares values come from 2×2 normal equations built from the K×K Gram
  matrices of the weighted I_k, so the whole map costs n_g renders and small algebra;
- where the fit sums the series' tail with a solve (high albedo: the series is too
  long to march), the scan marches K bounces and extrapolates the rest geometrically:
  Σ_{k>K} u^k I_k ≈ u^K I_K·(u r)/(1 − u r), r = ΣI_K/ΣI_{K−1} the per-bounce ratio
  of the render at σs_ref (u r at σs = u·σs_ref), so I_K's coefficient becomes
  u^K/(1 − u r) and the map still costs n_g renders; points with u r ≥ 1 are left out;
- every local minimum of the map whose misfit is within ``tolerance`` (relative) of the
  best is a basin; the fit solves each with the full model and keeps the best.

The map also tells which basin a solution lies in (:func:`basin_of`, steepest descent
on the grid), which is how a solution that ended in a basin worse than another found
is reported (never as converged).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from lightfield_jax.forward.kernels import matmul
from lightfield_jax.inverse.joint import BLACK_RANGE
from lightfield_jax.inverse.programs import jitted
from lightfield_jax.scene.phase import phase_integral

# ρ of the reference renders: I_k grows like ρ^k, so rendering at σs = σt (or the
# paper's σs = 1) overflows float32 within a few dozen bounces at high albedo; at
# ρ_ref ≤ 0.9 every I_k stays below I_1.
RHO_REF = 0.9


def reference_sigma_s(sigma_t, g, phase: str):
    """σs_ref for renders at g, and u_max = σs_max/σs_ref: the largest σs that is both
    ≤ σt and inside the convergent region ρ ≤ 1."""
    in_plane = phase_integral(g) if phase == "paper" else 1.0
    ref = sigma_t * jnp.minimum(1.0, RHO_REF / in_plane)
    rho_ref = ref / sigma_t * in_plane
    return ref, jnp.minimum(sigma_t / ref, 1.0 / rho_ref)


@dataclasses.dataclass(frozen=True)
class ScanSettings:
    """Static settings of the scan program."""

    phase: str
    fit_black: bool
    lit: int
    extrapolate: bool = False


@dataclasses.dataclass(frozen=True)
class ScanOffset:
    """What a constant offset d in every image value (a camera pedestal left in the
    images) would do to the scan: ``misfit`` the best misfit with it, ``value`` d there,
    ``fraction`` that misfit over the best without (1: it explains nothing)."""

    misfit: float
    value: float
    fraction: float

    @classmethod
    def of(cls, cost: np.ndarray, offset_cost: np.ndarray, offset: np.ndarray) -> ScanOffset:
        if not np.isfinite(offset_cost).any() or not np.isfinite(cost).any():
            return cls(math.nan, math.nan, 1.0)
        at = np.unravel_index(np.argmin(offset_cost), offset_cost.shape)
        best, with_offset = float(np.min(cost)), float(offset_cost[at])
        fraction = max(with_offset, 0.0) / best if best > 0 else 1.0
        return cls(with_offset, float(offset[at]), min(fraction, 1.0))

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True)
class Basin:
    """A local minimum of the scan: its grid point and what it gives as a start.

    ``misfit`` is the weighted mean square residual (gain, black level projected out)."""

    g: float
    albedo: float
    black_level: float
    misfit: float
    index: tuple[int, int]

    def as_dict(self) -> dict:
        return {
            "g": self.g,
            "albedo": self.albedo,
            "black_level": self.black_level,
            "misfit": self.misfit,
        }


@dataclasses.dataclass(frozen=True)
class Scan:
    """The misfit map over ``gs`` × ``albedos`` (inf where the model is not valid:
    ρ ≥ 1 under the paper's phase, or a bounce series the model truncates by more than
    1 %), and its basins, best first."""

    gs: np.ndarray
    albedos: np.ndarray
    misfit: np.ndarray  # (n_g, n_albedo)
    black: np.ndarray  # (n_g, n_albedo), the projected black level
    basins: tuple[Basin, ...]
    sigma_t: float
    seconds: dict
    # Per g: the render's last per-bounce ratio ΣI_K/ΣI_{K−1} at σs_ref and σs_ref
    # (NaN: not measured), for :meth:`ratio_at`.
    ratios: np.ndarray | None = None
    sigma_s_ref: np.ndarray | None = None
    offset: ScanOffset | None = None

    def ratio_at(self, g: float, albedo: float) -> float:
        """The per-bounce ratio of the scan's model at (g, albedo): I_k ∝ σs^k, so the
        ratio at σs is (σs/σs_ref)·ratio(σs_ref), interpolated linearly in g (NaN where
        the scan did not measure it)."""
        if self.ratios is None:
            return math.nan
        scaled = albedo * self.sigma_t / self.sigma_s_ref * self.ratios
        return float(np.interp(g, self.gs, scaled))

    def as_dict(self) -> dict:
        return {
            "sigma_t": self.sigma_t,
            "g": [float(self.gs[0]), float(self.gs[-1]), len(self.gs)],
            "albedo": [float(self.albedos[0]), float(self.albedos[-1]), len(self.albedos)],
            "basins": [b.as_dict() for b in self.basins],
            "seconds": self.seconds,
            **({} if self.offset is None else {"offset": self.offset.as_dict()}),
        }


def _weighted_grams(settings: ScanSettings, renderer, full, obs, weights, sigma_t, g):
    """The Gram matrix (2K × 2K) of the weighted basis [I_k^p, I_k^full] at g (rendered
    at σs_ref(g)), its products with the weighted data (2K), σs_ref and the per-bounce
    ratio r = ΣI_K/ΣI_{K−1} of the render."""
    ref, _ = reference_sigma_s(sigma_t, g, settings.phase)
    images = renderer(sigma_t, ref, g)[0]  # (P, K, h, w)
    if full is None:
        full_images = jnp.sum(images, axis=0) / settings.lit
    else:
        full_images = full(sigma_t, ref, g)[0][0]
    k = images.shape[1]
    stripes = jnp.moveaxis(images, 1, 0)  # (K, P, h, w)
    lit_all = jnp.broadcast_to(full_images[:, None], stripes.shape)
    basis = jnp.concatenate([stripes, lit_all], axis=0) * weights[None]
    basis = basis.reshape(2 * k, -1)
    sums = jnp.sum(images, axis=(0, 2, 3))
    ratio = (
        sums[-1] / jnp.maximum(sums[-2], jnp.finfo(sums.dtype).tiny)
        if k > 1
        else jnp.zeros((), sums.dtype)
    )
    with_ones = matmul(basis, weights.reshape(-1))  # the basis against a constant offset
    return matmul(basis, basis.T), matmul(basis, (weights * obs).reshape(-1)), with_ones, ref, ratio


def _scan(settings: ScanSettings, renderer, full, obs, weights, sigma_t, gs, albedos, black):
    """Misfit (weighted mean square) and projected black level on gs × albedos, and per
    g the render's last per-bounce ratio and σs_ref."""
    total = jnp.sum((weights * obs) ** 2)
    n = jnp.sum(weights > 0)
    ones2, ones_obs = jnp.sum(weights**2), jnp.sum(weights**2 * obs)
    total_c = total - ones_obs**2 / ones2

    def per_g(g):
        grams = _weighted_grams(settings, renderer, full, obs, weights, sigma_t, g)
        gram, proj, with_ones, ref, ratio = grams
        gram_c = gram - jnp.outer(with_ones, with_ones) / ones2
        proj_c = proj - with_ones * (ones_obs / ones2)
        k = gram.shape[0] // 2
        orders = jnp.arange(1, k + 1, dtype=gram.dtype)

        def per_albedo(albedo):
            u = albedo * sigma_t / ref
            v = u**orders
            ur = u * ratio
            if settings.extrapolate:  # Σ_{k≥K} u^k I_k ≈ u^K I_K / (1 − u r)
                v = v.at[-1].divide(jnp.where(ur < 1, 1 - ur, 1.0))
            z = jnp.zeros_like(v)
            va, vb = jnp.concatenate([v, z]), jnp.concatenate([z, v])
            pair = jnp.stack([va, vb])  # (2, 2K)
            m = matmul(matmul(pair, gram), pair.T)
            rhs = matmul(pair, proj)
            # Two columns: c·(1 − b) and c·b; their least-squares values give b.
            c = jnp.linalg.solve(m + 1e-30 * jnp.eye(2, dtype=m.dtype), rhs)
            b_free = c[1] / (c[0] + c[1])
            lo, hi = BLACK_RANGE
            b = jnp.clip(b_free, lo, hi) if settings.fit_black else black
            # One column at that b: the gain's least-squares value and the misfit.
            col = jnp.array([1.0 - b, b])
            norm = jnp.sum(col * matmul(m, col))
            cost = (total - jnp.sum(col * rhs) ** 2 / norm) / n
            # Diagnostic: the misfit with a constant offset d in every image value too,
            # the constant profiled out (the weighted basis and data less their
            # projections on it: the centred Gram matrix), and d.
            m_c = matmul(matmul(pair, gram_c), pair.T)
            rhs_c = matmul(pair, proj_c)
            if settings.fit_black:  # the 2×2 solve in closed form (no second LU)
                det = m_c[0, 0] * m_c[1, 1] - m_c[0, 1] ** 2
                c0 = m_c[1, 1] * rhs_c[0] - m_c[0, 1] * rhs_c[1]
                c1 = m_c[0, 0] * rhs_c[1] - m_c[0, 1] * rhs_c[0]
                b_c = jnp.clip(c1 / jnp.where(c0 + c1 != 0, c0 + c1, 1.0), lo, hi)
                b_c = jnp.where(det > 0, b_c, b)
            else:
                b_c = black
            col_c = jnp.array([1.0 - b_c, b_c])
            fitted = jnp.sum(col_c * rhs_c)
            norm_c = jnp.sum(col_c * matmul(m_c, col_c))
            offset_cost = (total_c - fitted**2 / norm_c) / n
            offset = (ones_obs - fitted / norm_c * jnp.sum(col_c * matmul(pair, with_ones))) / ones2
            if settings.extrapolate:
                cost = jnp.where(ur < 1, cost, jnp.inf)
                offset_cost = jnp.where(ur < 1, offset_cost, jnp.inf)
            return cost, b, offset_cost, offset

        cost, b, offset_cost, offset = jax.vmap(per_albedo)(albedos)
        return cost, b, ratio, ref, offset_cost, offset

    return jax.lax.map(per_g, gs)


def scan(
    renderer,
    full,
    obs,
    weights,
    sigma_t: float,
    *,
    phase: str,
    lit: int,
    black_level: float | None,
    rho_limit,
    n_g: int = 13,
    n_albedo: int = 33,
    extrapolate: bool = False,
):
    """The misfit map of the joint problem on the cheap model ``renderer`` (and ``full``
    for full illumination, or ``None`` when the phases tile the period), σt fixed.

    ``rho_limit(g, albedos)`` gives the per-bounce ratio ρ of each albedo at g; points
    whose ρ^K/(1 − ρ) exceeds 1 % (K the renderer's bounces) are left out (inf), as
    are ρ ≥ 1. With ``extrapolate`` the orders past K are extrapolated geometrically
    from the render's last ratio (see the module) instead, and only ρ ≥ 1 and points
    where that extrapolation diverges are left out. Returns ``(misfit, black, gs,
    albedos, ratios, sigma_s_ref)`` as NumPy arrays (``ratios``: per g, the render's
    last per-bounce ratio at σs_ref)."""
    dtype = obs.dtype
    gs = np.linspace(-0.9, 0.9, n_g)
    albedos = np.linspace(0.02, 0.98, n_albedo)
    settings = ScanSettings(phase, black_level is None, lit, extrapolate)
    cost, black, ratios, refs, offset_cost, offset = jitted(_scan, ("settings",))(
        settings,
        renderer,
        full,
        obs,
        weights,
        jnp.asarray(sigma_t, dtype),
        jnp.asarray(gs, dtype),
        jnp.asarray(albedos, dtype),
        jnp.asarray(0.0 if black_level is None else black_level, dtype),
    )
    cost, black = np.array(cost, np.float64), np.array(black, np.float64)  # writable
    offset_cost = np.array(offset_cost, np.float64)
    k = renderer.bounces
    for i, g in enumerate(gs):
        rho = np.asarray(rho_limit(float(g), albedos), np.float64)
        with np.errstate(divide="ignore"):
            tail = np.where(rho < 1, rho**k / np.maximum(1 - rho, 1e-12), np.inf)
        cost[i, (rho >= 1) if extrapolate else (tail > 0.01)] = np.inf
    invalid = ~np.isfinite(cost)
    cost[invalid] = np.inf
    offset_cost[invalid | ~np.isfinite(offset_cost)] = np.inf
    ratios, refs = np.asarray(ratios, np.float64), np.asarray(refs, np.float64)
    # A ratio of light sums is never negative: one that is (−1.9e34 on a 48×36 Monte
    # Carlo capture of the dense forward medium, whose last bounce summed below zero
    # over the second last's ~0) was not measured, and sized no march from garbage.
    ratios = np.where(ratios >= 0.0, ratios, np.nan)
    offset = ScanOffset.of(cost, offset_cost, np.asarray(offset, np.float64))
    return cost, black, gs, albedos, ratios, refs, offset


def _neighbours(i: int, j: int, shape) -> list[tuple[int, int]]:
    return [
        (i + di, j + dj)
        for di in (-1, 0, 1)
        for dj in (-1, 0, 1)
        if (di or dj) and 0 <= i + di < shape[0] and 0 <= j + dj < shape[1]
    ]


def local_minima(cost: np.ndarray) -> list[tuple[int, int]]:
    """Grid points whose (finite) value is at most every neighbour's (8-neighbourhood,
    edges included), one per plateau, lowest first."""
    out = []
    for i, j in zip(*np.nonzero(np.isfinite(cost)), strict=True):
        c = cost[i, j]
        nb = _neighbours(int(i), int(j), cost.shape)
        if all(c <= cost[p] for p in nb) and not any(cost[p] == c and p < (i, j) for p in nb):
            out.append((int(i), int(j)))
    return sorted(out, key=lambda p: cost[p])


def basin_of(cost: np.ndarray, i: int, j: int) -> tuple[int, int]:
    """The local minimum reached from grid point (i, j) by steepest descent."""
    p = (i, j)
    while True:
        nb = [q for q in _neighbours(*p, cost.shape) if cost[q] < cost[p]]
        if not nb:
            return p
        p = min(nb, key=lambda q: cost[q])


def nearest_point(gs: np.ndarray, albedos: np.ndarray, g: float, albedo: float):
    """The grid point nearest to (g, albedo) (in grid spacings)."""
    i = int(np.clip(round((g - gs[0]) / (gs[1] - gs[0])), 0, len(gs) - 1))
    j = int(np.clip(round((albedo - albedos[0]) / (albedos[1] - albedos[0])), 0, len(albedos) - 1))
    return i, j


def basins(
    cost: np.ndarray,
    black: np.ndarray,
    gs: np.ndarray,
    albedos: np.ndarray,
    tolerance: float,
    max_basins: int,
) -> tuple[Basin, ...]:
    """The local minima within ``tolerance`` (relative) of the best, best first, at most
    ``max_basins``."""
    minima = local_minima(cost)
    if not minima:
        return ()
    best = cost[minima[0]]
    # Relative to |best|: a misfit is a difference of sums, which rounding can leave
    # slightly negative on a noiseless capture.
    kept = [p for p in minima if cost[p] <= best + tolerance * abs(best)][:max_basins]
    return tuple(
        Basin(
            g=float(gs[i]),
            albedo=float(albedos[j]),
            black_level=float(black[i, j]),
            misfit=float(cost[i, j]),
            index=(i, j),
        )
        for i, j in kept
    )


def worse_basin(scan: Scan, g: float, albedo: float, tolerance: float) -> Basin | None:
    """The best basin of ``scan`` when the solution (g, albedo) lies in another basin
    of the map whose misfit is more than ``tolerance`` (relative) above it; else
    ``None``."""
    if not scan.basins or not math.isfinite(g) or not math.isfinite(albedo):
        return None
    p = nearest_point(scan.gs, scan.albedos, g, albedo)
    if not np.isfinite(scan.misfit[p]):
        return None
    home = basin_of(scan.misfit, *p)
    best = scan.basins[0]
    if home == best.index or scan.misfit[home] <= best.misfit + tolerance * abs(best.misfit):
        return None
    return best


__all__ = [
    "Basin",
    "Scan",
    "basin_of",
    "basins",
    "local_minima",
    "reference_sigma_s",
    "scan",
    "worse_basin",
]
