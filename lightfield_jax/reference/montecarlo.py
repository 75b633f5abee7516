"""An independent Monte Carlo reference for the 2-D plane model (docs/model.md sections 1-4).

This module is an oracle for the propagator, so it shares no code with it: it is plain
numpy, uses no jax and no other part of ``lightfield_jax`` (the illumination
dataclasses are read for their fields only; importing them runs the package's
``__init__``, which is the only reason jax gets loaded), and re-derives the geometry
(entry wall, lit set, launch power, distance to the walls, pixel traversal) and the
phase function from docs/model.md by itself.

The model. The medium fills [0, W] × [0, H] (pixels; x right, y down, θ from +x toward
+y) and its walls are black. Photons are launched uniformly over the entry wall's
launch segment heading θ0, each carrying 1/N of the launch power P = |cos α| × (segment
length), α the angle between θ0 and the wall's inward normal (unit irradiance per unit
*transverse* width). Free paths are drawn from σt e^{−σt t}; a photon that reaches a
wall first is gone (its weight is tallied as escaped power). At a collision the photon
scatters: its weight is multiplied by ω·A(g) (``phase="paper"``: p redistributes in
the plane as is, A(g) = ∫_{−π}^{π} p dθ) or by ω (``phase="normalized"``), and its new
direction is θ + Δ with Δ drawn from p(Δ)/A(g) by inverse CDF on a 65 536-interval
table (survival biasing, no Russian roulette, so paths depend on σt and g only). A
photon lives until it leaves or has scattered ``bounces − 1`` times.

The camera. I_k = σs p(π/2) Φ_{k−1}, pixel-averaged, with Φ_{k−1} the fluence of light
scattered exactly k − 1 times. Two unbiased estimators of Φ are offered:

- ``estimator="track"`` (default, lower variance): track-length. Each free-flight
  segment of a (k−1)-times scattered photon of weight w adds w × (its length inside
  the pixel) / (pixel area = 1) to Φ_{k−1} of that pixel, for every pixel it crosses
  (an exact grid traversal, Amanatides & Woo).
- ``estimator="collision"``: collision density is σt Φ, so a photon colliding at x
  after k − 1 scatterings adds w / σt to Φ_{k−1} of the pixel of x.

The statistical error. For a fixed bounce k and pixel, one photon scores at most once
(its (k−1)-th flight is one straight segment, which crosses a convex pixel at most
once, or ends in one collision), so per-photon first and second moments are tallied
exactly and ``stderr`` = sqrt((E[X²] − E[X]²)/(N − 1)) over the N photon scores X.
That estimate is itself noisy where few photons score (``hits``): compare only pixels
with ≳ 100 hits (the corners of an oblique beam's lit set can have a handful).

Stripes. All phases share one set of photons launched over the whole wall: a photon
launched in wall cell r scores for pattern p iff (r + phase_p) mod period < lit. So
the patterns are correlated (same paths), each one unbiased.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import numpy as np

from lightfield_jax.scene.illumination import Beam, Full, Stripes, along_x

Estimator = Literal["track", "collision"]
# Intervals of the tabulated CDF of the relative scattering angle (inverse-CDF sampling).
_CDF_INTERVALS = 65536
# Beam and Full: every photon scores for the single pattern.
_ONE_CLASS = np.ones((1, 1), dtype=bool)


@dataclasses.dataclass(frozen=True)
class MonteCarloResult:
    """Monte Carlo estimate of the bounce images I_k, k = 1..bounces.

    Attributes:
        images: float64 (patterns, bounces, height, width); ``images[p, k-1]`` is I_k
            for illumination pattern p, in absolute units (unit irradiance source).
        stderr: standard error of ``images``, same shape (per-photon second moments).
            It is itself a noisy estimate where few photons score: trust it where
            ``hits`` is large (≳ 100), not at the lit set's corners.
        hits: int64, same shape: number of photons that scored in the pixel.
        escaped: float64 (patterns, bounces); ``escaped[p, k-1]`` is the power of light
            scattered exactly k − 1 times that leaves through the walls (the same light
            whose fluence makes ``images[p, k-1]``).
        input_power: float64 (patterns,), exact power entering the medium (per unit
            depth of the plane): |cos α| × lit length of the entry wall.
        photons: number of photons launched.
        estimator: "track" or "collision".
    """

    images: np.ndarray
    stderr: np.ndarray
    hits: np.ndarray
    escaped: np.ndarray
    input_power: np.ndarray
    photons: int
    estimator: str


def phase_function(theta: np.ndarray | float, g: float) -> np.ndarray:
    """p(θ) = (1/4π)(1 − g²)/(1 + g² − 2g cos θ)^{3/2} (3-D HG at the in-plane angle)."""
    return (1.0 - g * g) / (4.0 * math.pi * (1.0 + g * g - 2.0 * g * np.cos(theta)) ** 1.5)


def phase_table(g: float) -> tuple[np.ndarray, np.ndarray, float]:
    """(nodes, normalised CDF, A(g)) for the relative angle Δ ∈ [−π, π].

    The trapezoid rule on the periodic integrand is spectrally accurate, so the table's
    total is A(g) to float64 precision for |g| well below 1.
    """
    nodes = np.linspace(-math.pi, math.pi, _CDF_INTERVALS + 1)
    pdf = phase_function(nodes, g)
    step = 2.0 * math.pi / _CDF_INTERVALS
    cdf = np.concatenate(([0.0], np.cumsum(0.5 * (pdf[1:] + pdf[:-1]) * step)))
    total = float(cdf[-1])
    return nodes, cdf / total, total


def phase_integral(g: float) -> float:
    """A(g) = ∫_{−π}^{π} p(θ) dθ (docs/model.md section 2; A(0) = 0.5)."""
    return phase_table(g)[2]


@dataclasses.dataclass(frozen=True)
class _Source:
    """Launch geometry, re-derived from the illumination's fields."""

    wall: str
    theta0: float  # radians
    lo: float  # launch segment [lo, hi] in wall coordinate u
    hi: float
    power: float  # power launched over [lo, hi]
    period: int  # photons are classed by floor(u) mod period (1: a single class)
    lit: np.ndarray  # bool (period, patterns): does class c score for pattern p
    input_power: np.ndarray  # (patterns,)


def _normal_cos(wall: str, theta0: float) -> float:
    """|cos| of the angle between the heading and the wall's normal."""
    return abs(math.cos(theta0)) if along_x(wall) else abs(math.sin(theta0))


def _beam_wall(beam: Beam, width: int, height: int) -> str:
    t = math.radians(beam.direction_deg)
    c, s = math.cos(t), math.sin(t)
    tol = 1e-9
    on_grid = -tol <= beam.x <= width + tol and -tol <= beam.y <= height + tol
    for wall, on_wall, inward in (
        ("left", abs(beam.x) <= tol, c),
        ("right", abs(beam.x - width) <= tol, -c),
        ("top", abs(beam.y) <= tol, s),
        ("bottom", abs(beam.y - height) <= tol, -s),
    ):
        if on_grid and on_wall and inward > 1e-6:
            return wall
    raise ValueError(
        f"illumination: beam entry point ({beam.x:g}, {beam.y:g}) heading "
        f"{beam.direction_deg:g} deg is not on a wall of the {width}x{height} medium "
        "pointing into it"
    )


def wall_source(illumination, width: int, height: int) -> _Source:
    if isinstance(illumination, Beam):
        wall = _beam_wall(illumination, width, height)
    elif isinstance(illumination, (Stripes, Full)):
        wall = illumination.entry
    else:
        raise TypeError(
            f"illumination: expected Beam, Stripes or Full, got {type(illumination).__name__}"
        )
    theta0 = math.radians(illumination.direction_deg)
    ncos = _normal_cos(wall, theta0)
    extent = float(height if along_x(wall) else width)
    if isinstance(illumination, Beam):
        centre = illumination.y if along_x(wall) else illumination.x
        half = 0.5 * illumination.width / ncos  # transverse width w covers w/|cos| of wall
        lo, hi = max(centre - half, 0.0), min(centre + half, extent)
        power = ncos * (hi - lo)
        return _Source(wall, theta0, lo, hi, power, 1, _ONE_CLASS, np.array([power]))
    power = ncos * extent
    if isinstance(illumination, Full):
        return _Source(wall, theta0, 0.0, extent, power, 1, _ONE_CLASS, np.array([power]))
    period = illumination.period
    phases = np.asarray(illumination.phases)
    lit = np.mod(np.arange(period)[:, None] + phases[None, :], period) < illumination.lit
    cells = np.arange(int(extent))
    lit_cells = np.mod(cells[:, None] + phases[None, :], period) < illumination.lit
    input_power = ncos * lit_cells.sum(axis=0).astype(np.float64)
    return _Source(wall, theta0, 0.0, extent, power, period, lit, input_power)


def distance_to_wall(x, y, c, s, width: int, height: int) -> np.ndarray:
    """Distance from (x, y) along (c, s) to the rectangle's boundary."""
    with np.errstate(divide="ignore", invalid="ignore"):
        dx = np.where(c > 0, (width - x) / c, np.where(c < 0, -x / c, np.inf))
        dy = np.where(s > 0, (height - y) / s, np.where(s < 0, -y / s, np.inf))
    return np.maximum(np.minimum(dx, dy), 0.0)


def pixel_index(p: np.ndarray, n: int) -> np.ndarray:
    return np.clip(np.floor(p).astype(np.int64), 0, n - 1)


def add_tally(tally: np.ndarray, pixel: np.ndarray, score: np.ndarray) -> None:
    """Add per-photon scores to the flat tallies: Σ X, Σ X², number of X > 0."""
    size = tally.shape[1]
    tally[0] += np.bincount(pixel, score, minlength=size)
    tally[1] += np.bincount(pixel, score * score, minlength=size)
    tally[2] += np.bincount(pixel, score > 0, minlength=size)


def _tally_tracks(x, y, c, s, length, score, slot, width, height, tally) -> None:
    """Add score × (length inside pixel) of each segment to every pixel it crosses.

    ``slot`` is the offset of the segment's image in the flat ``tally`` (see
    :func:`add_tally`). Vectorised Amanatides–Woo traversal: one loop step moves every
    unfinished segment into its next pixel.
    """
    # A start on a grid line may pick the cell behind it: its piece is then empty.
    ix = pixel_index(x, width)
    iy = pixel_index(y, height)
    step_x = np.where(c > 0, 1, -1)
    step_y = np.where(s > 0, 1, -1)
    t = np.zeros_like(length)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_c = np.where(c != 0, 1.0 / c, np.inf)
        inv_s = np.where(s != 0, 1.0 / s, np.inf)
    up_x = (c > 0).astype(np.int64)
    up_y = (s > 0).astype(np.int64)
    while length.size:
        with np.errstate(invalid="ignore"):
            tx = np.where(c != 0, (ix + up_x - x) * inv_c, np.inf)
            ty = np.where(s != 0, (iy + up_y - y) * inv_s, np.inf)
        t_next = np.minimum(np.minimum(tx, ty), length)
        piece = score * (t_next - t)
        pixel = slot + np.clip(iy, 0, height - 1) * width + np.clip(ix, 0, width - 1)
        add_tally(tally, pixel, piece)
        go = t_next < length
        move_x = tx <= ty
        ix = np.where(move_x, ix + step_x, ix)
        iy = np.where(move_x, iy, iy + step_y)
        keep = np.flatnonzero(go)
        x, y, c, s, length, score, slot = (a[keep] for a in (x, y, c, s, length, score, slot))
        ix, iy, step_x, step_y, inv_c, inv_s, up_x, up_y = (
            a[keep] for a in (ix, iy, step_x, step_y, inv_c, inv_s, up_x, up_y)
        )
        t = t_next[keep]


def sample_deflection(rng, n: int, nodes: np.ndarray, cdf: np.ndarray) -> np.ndarray:
    """n relative scattering angles Δ drawn from p(Δ)/A(g) by inverse CDF."""
    return np.interp(rng.random(n), cdf, nodes)


def launch_photons(src: _Source, n: int, width: int, height: int, rng: np.random.Generator):
    u = src.lo + (src.hi - src.lo) * rng.random(n)
    klass = np.mod(np.floor(u).astype(np.int64), src.period)
    if src.wall == "left":
        x, y = np.zeros(n), u
    elif src.wall == "right":
        x, y = np.full(n, float(width)), u
    elif src.wall == "top":
        x, y = u, np.zeros(n)
    else:
        x, y = u, np.full(n, float(height))
    return x, y, klass


def positive_int(name: str, v) -> None:
    if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 1:
        raise ValueError(f"{name}: must be a positive integer, got {v!r}")


def check_scene(width, height, sigma_t, sigma_s, g, bounces, photons, batch) -> None:
    """The checks both oracles share: positive integer sizes and counts, the medium."""
    for name, v in (
        ("width", width),
        ("height", height),
        ("bounces", bounces),
        ("photons", photons),
        ("batch", batch),
    ):
        positive_int(name, v)
    if not (math.isfinite(sigma_t) and sigma_t > 0):
        raise ValueError(f"sigma_t: must be finite and > 0 per pixel, got {sigma_t!r}")
    if not (0 <= sigma_s <= sigma_t):
        raise ValueError(f"sigma_s: must lie in [0, sigma_t] = [0, {sigma_t}], got {sigma_s!r}")
    if not (-1 < g < 1):
        raise ValueError(f"g: must lie in (-1, 1), got {g!r}")


def _check(width, height, sigma_t, sigma_s, g, bounces, phase, photons, batch, estimator):
    check_scene(width, height, sigma_t, sigma_s, g, bounces, photons, batch)
    if phase not in ("paper", "normalized"):
        raise ValueError(f"phase: must be 'paper' or 'normalized', got {phase!r}")
    if estimator not in ("track", "collision"):
        raise ValueError(f"estimator: must be 'track' or 'collision', got {estimator!r}")


def monte_carlo_render(
    width: int,
    height: int,
    sigma_t: float,
    sigma_s: float,
    g: float,
    illumination: Beam | Stripes | Full,
    bounces: int,
    *,
    phase: Literal["paper", "normalized"] = "paper",
    photons: int = 1_000_000,
    seed: int = 0,
    batch: int = 200_000,
    estimator: Estimator = "track",
) -> MonteCarloResult:
    """Monte Carlo estimate of I_1..I_bounces for the 2-D plane model.

    Args:
        width, height: grid size W × H in pixels; the medium fills [0, W] × [0, H].
        sigma_t, sigma_s: extinction and scattering coefficients, per pixel.
        g: Henyey–Greenstein asymmetry, −1 < g < 1.
        illumination: a ``Beam``, ``Stripes`` or ``Full`` (unit transverse irradiance).
        bounces: number of bounce images K (photons scatter at most K − 1 times).
        phase: "paper" (weight × ω·A(g) per scattering) or "normalized" (× ω).
        photons: photons launched in total (all patterns share them).
        seed: seed of numpy's default generator. With the same seed, σt, g, photons and
            batch, the photon paths are identical for any σs and phase convention.
        batch: photons traced at a time (memory bound).
        estimator: "track" (track-length, default) or "collision".

    Under ``phase="paper"`` with ω·A(g) ≥ 1 the bounce series diverges (docs/model.md
    section 2), but every single I_k is still finite and is what this returns.
    """
    _check(width, height, sigma_t, sigma_s, g, bounces, phase, photons, batch, estimator)
    src = wall_source(illumination, width, height)
    nodes, cdf, a_g = phase_table(g)
    factor = sigma_s / sigma_t * (a_g if phase == "paper" else 1.0)
    camera = sigma_s * float(phase_function(math.pi / 2, g))
    n_px = height * width
    n_slots = src.period * n_px  # one image per (photon class, bounce)
    tally = np.zeros((3, bounces * n_slots))
    escaped = np.zeros((bounces, src.period))
    rng = np.random.default_rng(seed)
    done = 0
    while done < photons:
        n = min(batch, photons - done)
        done += n
        x, y, klass = launch_photons(src, n, width, height, rng)
        theta = np.full(n, src.theta0)
        w = np.ones(n)
        for j in range(bounces):  # flight j carries light scattered exactly j times
            c, s = np.cos(theta), np.sin(theta)
            d = distance_to_wall(x, y, c, s, width, height)
            t = rng.standard_exponential(x.size) / sigma_t
            hit = t < d
            slot = j * n_slots + klass * n_px
            if estimator == "track":
                seg = np.minimum(t, d)
                _tally_tracks(x, y, c, s, seg, w * camera, slot, width, height, tally)
            else:
                xc, yc = x[hit] + t[hit] * c[hit], y[hit] + t[hit] * s[hit]
                score = w[hit] * camera / sigma_t
                pixel = slot[hit] + pixel_index(yc, height) * width + pixel_index(xc, width)
                add_tally(tally, pixel, score)
            escaped[j] += np.bincount(klass[~hit], w[~hit], minlength=src.period)
            if j + 1 == bounces:
                break
            x, y = x[hit] + t[hit] * c[hit], y[hit] + t[hit] * s[hit]
            klass, w = klass[hit], w[hit] * factor
            theta = theta[hit] + sample_deflection(rng, x.size, nodes, cdf)
    # Photon i scores X_i = P·(tally) for pattern p iff its class is lit in p.
    lit = src.lit.astype(np.float64)  # (classes, patterns)
    m1, m2, hits = np.einsum("tkcq,cp->tpkq", tally.reshape(3, bounces, src.period, n_px), lit)
    mean = src.power * m1 / photons
    second = src.power**2 * m2 / photons
    var = np.maximum(second - mean**2, 0.0) / max(photons - 1, 1)
    shape = (lit.shape[1], bounces, height, width)
    return MonteCarloResult(
        images=mean.reshape(shape),
        stderr=np.sqrt(var).reshape(shape),
        hits=np.rint(hits).astype(np.int64).reshape(shape),
        escaped=src.power * (escaped @ lit).T / photons,
        input_power=src.input_power,
        photons=int(photons),
        estimator=estimator,
    )
