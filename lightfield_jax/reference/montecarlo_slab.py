"""An independent 3-D Monte Carlo reference for the slab geometry (docs/model.md section 7).

Like :mod:`lightfield_jax.reference.montecarlo` (the 2-D oracle) this is plain numpy and shares
no code with any propagator. It reuses the 2-D oracle's launch geometry along the entry
wall (``wall_source``, ``launch_photons``), side-wall distance and tally helpers, which are
themselves independent of the propagators.

The medium. It fills [0, W] × [0, H] × [0, h] (pixels; x right, y down as in the image
frame, z up toward the camera, h = ``thickness``). σt, σs are the medium's 3-D
coefficients (per pixel) and the phase function is the 3-D Henyey–Greenstein function
normalised on the sphere, p(μ) = (1/4π)(1 − g²)/(1 + g² − 2gμ)^{3/2}, μ the cosine of
the scattering angle; ∫_{S²} p dω = 1, so every bounce multiplies power by at most
ω = σs/σt < 1 and the series always converges. The side walls are black. The top
(z = h) and bottom (z = 0) faces are

- ``boundary="absorbing"``: index-matched, light that reaches a face is gone;
- ``boundary="refractive"``: a flat interface to a medium of relative index ``n``
  (n = n_medium/n_outside). A photon reaching a face at incidence cosine μ is split:
  the fraction R(μ) (:func:`fresnel_reflectance`, unpolarised, R = 1 beyond the
  critical angle asin(1/n)) is specularly reflected and continues its flight with the
  rest of its free path (paths are memoryless), 1 − R(μ) leaves. Splitting rather
  than a random choice keeps the per-bounce power balance exact photon by photon.

The source. The in-plane illumination (``Beam``, ``Stripes``, ``Full``, read for their
fields exactly as in the 2-D oracle) is extruded over the full depth: a collimated,
horizontal sheet heading θ0 (elevation 0) with unit irradiance, i.e. unit power per
unit area normal to θ0 (per unit transverse width *and* per unit depth). Its power is
P = |cos α| × (lit wall length) × h, α between θ0 and the wall's inward normal; the
unscattered radiance is L_0 = e^{−σt d0} δ(ω − ω0), independent of z. Photons are
launched uniformly over the lit wall segment and uniformly in z ∈ [0, h], each
carrying P/N. The sheet is horizontal, so its unscattered light never meets a face.

The camera. It looks along −z through the top face (docs/model.md section 7):
I_k(x, y) = T ∫_0^h e^{−σt (h − z)} ∫_{S²} σs p(ω·ẑ) L_{k−1}(x, y, z, ω) dω dz,
pixel-averaged in x and y, with T = 1 (absorbing) or T = 1 − R(1) (refractive, the
top face's transmission at normal incidence). This is the contract's formula: the ray
scattered up toward the camera is counted on its direct path only (the part of it
reflected back at the top face, and light scattered down then mirrored by the bottom
face toward the camera, are not added to I_k; each carries a factor R(1), 0.02 for
n = 1.33).
The change of radiance across the interface (the n² of the radiance theorem) is a
constant gain and is left out with it.

The estimator (next-event at each collision). The collision density of light
scattered exactly k − 1 times is σt L_{k−1}(r, ω) per unit volume and solid angle,
and it is what a photon's flight samples: a (k−1)-times scattered photon of weight w
ends its flight in a collision at r = (x, y, z) heading ω_in with density w σt L_{k−1}
(w in units of P/N). So with f(r, ω) = σs/σt p(ω·ẑ) e^{−σt (h − z)} T [r in pixel]
the sum of w·f over collisions has the expectation ∫ σt L_{k−1} f dV dω = I_k × (pixel
area, 1): the score w·σs/σt·p(ω_in·ẑ)·e^{−σt (h−z)}·T is the chance that the collision
scatters (ω), toward the camera (p per steradian of the camera's direction ẑ), and
that this ray survives to the top face and leaves. Survival biasing (the photon's
weight × ω at each collision, no Russian roulette) keeps paths dependent on σt, g and
n only, so with one seed I_k(σs) = σs^k I_k(1) exactly for fixed σt. The tests check
the estimator against an analog count of photons leaving the top face near its normal.

Depth layers (``depth_layers=L``) make the oracle of a layered forward model: each
scattering's depth is redrawn uniformly within its layer (one of L equal layers of
[0, h]), so each order's source is replaced by its layer averages (L = 1: the depth
average). Its difference from the slab (``None``) is that model's error, exactly zero
for I_1 and I_2.

The statistical error. A flight ends in at most one collision, so for a bounce k and
pixel each photon scores at most once, and ``stderr`` = sqrt((E[X²] − E[X]²)/(N − 1))
over the per-photon scores X is exact in form (noisy itself where ``hits`` is small).

Power bookkeeping, per order j = k − 1 (light scattered exactly j times, power P_j,
P_0 = ``input_power``): P_j = escaped_j + collided_j, of which ``absorbed_j`` =
(1 − ω) collided_j and ω collided_j = P_{j+1}. The last order's scattered power
P_K is ``untraced``. So input = Σ_j (escaped_j + absorbed_j) + untraced, exactly.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import numpy as np

from lightfield_jax.reference.montecarlo import (
    add_tally,
    check_scene,
    distance_to_wall,
    launch_photons,
    phase_function,
    pixel_index,
    positive_int,
    wall_source,
)
from lightfield_jax.scene.geometry import fresnel_reflectance
from lightfield_jax.scene.illumination import Beam, Full, Stripes

Boundary = Literal["absorbing", "refractive"]


@dataclasses.dataclass(frozen=True)
class SlabMonteCarloResult:
    """Monte Carlo estimate of the slab's bounce images I_k, k = 1..bounces.

    Attributes:
        images: float64 (patterns, bounces, height, width); ``images[p, k-1]`` is I_k
            for pattern p, in absolute units (unit irradiance sheet, see module doc).
        stderr: standard error of ``images``, same shape (per-photon second moments).
        total_stderr: standard error of the image sums Σ_xy I_k, (patterns, bounces)
            (a photon scores in one pixel per bounce, so its moments add over pixels).
        hits: int64, same shape: number of photons that scored in the pixel.
        escaped: float64 (patterns, bounces); ``escaped[p, k-1]`` is the power of light
            scattered exactly k − 1 times that leaves the slab (any wall or face).
        escaped_faces: the part of ``escaped`` that leaves through the top and bottom
            faces (zero for the unscattered sheet, which is horizontal).
        absorbed: float64 (patterns, bounces): power of light scattered exactly k − 1
            times absorbed at the collision that ends its flight.
        untraced: float64 (patterns,): power scattered ``bounces`` times (not traced).
        input_power: float64 (patterns,): exact power entering the slab,
            |cos α| × lit wall length × thickness.
        photons: number of photons launched.
    """

    images: np.ndarray
    stderr: np.ndarray
    total_stderr: np.ndarray
    hits: np.ndarray
    escaped: np.ndarray
    escaped_faces: np.ndarray
    absorbed: np.ndarray
    untraced: np.ndarray
    input_power: np.ndarray
    photons: int


def phase_function_cos(mu: np.ndarray | float, g: float) -> np.ndarray:
    """p(μ) = (1/4π)(1 − g²)/(1 + g² − 2gμ)^{3/2}, μ = cos(scattering angle); per sr."""
    return phase_function(np.arccos(np.clip(mu, -1.0, 1.0)), g)


def slab_single_scatter_sheet(
    sigma_t: float,
    sigma_s: float,
    g: float,
    thickness: float,
    width: int,
    *,
    boundary: Boundary = "absorbing",
    n: float = 1.33,
) -> np.ndarray:
    """I_1 on a lit row of a sheet entering the left wall along +x (docs/model.md section 7).

    I_1(c) = T σs p(0) (1 − e^{−σt h})/σt × e^{−σt c}(1 − e^{−σt})/σt for columns
    c = 0..width−1: the exact average over pixel c of σs p(cos 90°) e^{−σt x}
    (1 − e^{−σt h})/σt. T = 1 for ``absorbing`` faces; for ``refractive`` faces
    T = 1 − R(1) (the horizontal sheet never meets a face, the camera ray leaves
    through the top face at normal incidence). Units: the sheet has unit irradiance,
    lengths are pixels, σ per pixel; returns float64 (width,).
    """
    camera = _camera_transmission(boundary, n)
    depth = -math.expm1(-sigma_t * thickness) / sigma_t
    cols = np.arange(width)
    pixel = np.exp(-sigma_t * cols) * (-math.expm1(-sigma_t)) / sigma_t
    return camera * sigma_s * float(phase_function_cos(0.0, g)) * depth * pixel


def _camera_transmission(boundary: str, n: float) -> float:
    return 1.0 if boundary == "absorbing" else 1.0 - float(fresnel_reflectance(1.0, n))


def sample_scattering(rng: np.random.Generator, u: np.ndarray, g: float) -> np.ndarray:
    """New unit directions (3, N) scattered from ``u`` (3, N) by the 3-D HG function.

    μ = cos(scattering angle) by inverse CDF, written in a form that stays accurate as
    g → 0: with v = 2ξ − 1, μ = [v + g(v² + 3)/2 + g²v + g³(v² − 1)/2]/(1 + gv)²
    (the textbook (1 + g² − ((1 − g²)/(1 − g + 2gξ))²)/(2g) expanded); azimuth uniform.
    """
    v = 2.0 * rng.random(u.shape[1]) - 1.0
    mu = (v + g * (v * v + 3) / 2 + g * g * v + g**3 * (v * v - 1) / 2) / (1 + g * v) ** 2
    mu = np.clip(mu, -1.0, 1.0)
    phi = 2.0 * math.pi * rng.random(u.shape[1])
    sin_t = np.sqrt(1.0 - mu * mu)
    # An orthonormal frame (a, b) perpendicular to u, built from whichever of x̂, ẑ is
    # further from u.
    helper = np.where(np.abs(u[2]) < 0.9, np.array([[0.0], [0.0], [1.0]]), [[1.0], [0.0], [0.0]])
    a = np.cross(helper, u, axis=0)
    a /= np.linalg.norm(a, axis=0)
    b = np.cross(u, a, axis=0)
    out = mu * u + sin_t * (np.cos(phi) * a + np.sin(phi) * b)
    return out / np.linalg.norm(out, axis=0)


def _scatter(rng, u, g: float, camera_sampling: float, w: np.ndarray) -> np.ndarray:
    """New directions from ``u`` (3, N); with ``camera_sampling`` ε > 0 a share ε drawn
    around ẑ and ``w`` corrected in place by p(ω·u)/q(ω) (see :func:`monte_carlo_slab`)."""
    if camera_sampling == 0.0:
        return sample_scattering(rng, u, g)
    axis = np.zeros_like(u)
    axis[2] = 1.0
    toward = rng.random(u.shape[1]) < camera_sampling
    new = sample_scattering(rng, np.where(toward, axis, u), g)
    p_in = phase_function_cos(np.sum(new * u, axis=0), g)
    p_axis = phase_function_cos(new[2], g)
    w *= p_in / ((1.0 - camera_sampling) * p_in + camera_sampling * p_axis)
    return new


def _distance_to_face(z, uz, thickness: float) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.where(uz > 0, (thickness - z) / uz, np.where(uz < 0, -z / uz, np.inf))
    return np.maximum(d, 0.0)


@dataclasses.dataclass(frozen=True)
class OracleSlab:
    width: int
    height: int
    thickness: float
    boundary: str
    n: float


def fly(slab: OracleSlab, pos, u, w, free, klass, escaped, escaped_faces):
    """Move every photon along its flight of optical length σt·``free``.

    ``pos``, ``u`` (3, N), ``w`` are updated in place (reflections at the faces flip
    u_z and multiply w by R). Escaping power is added to ``escaped`` (and to
    ``escaped_faces`` for the faces) per photon class. Returns the boolean mask of
    photons whose flight ends in a collision (``pos`` is then the collision point).
    """
    collided = np.zeros(w.size, dtype=bool)
    active = np.arange(w.size)
    free = free.copy()
    period = escaped.size
    while active.size:
        p, d, t = pos[:, active], u[:, active], free[active]
        side = distance_to_wall(p[0], p[1], d[0], d[1], slab.width, slab.height)
        face = _distance_to_face(p[2], d[2], slab.thickness)
        ends = t < np.minimum(side, face)
        stop = active[ends]
        pos[:, stop] += free[stop] * u[:, stop]
        pos[2, stop] = np.clip(pos[2, stop], 0.0, slab.thickness)
        collided[stop] = True
        at_face = ~ends & (face < side)
        out = active[~ends & ~at_face]
        escaped += np.bincount(klass[out], w[out], minlength=period)
        hit, dist = active[at_face], face[at_face]
        if slab.boundary == "refractive":
            refl = fresnel_reflectance(np.abs(u[2, hit]), slab.n)
        else:
            refl = np.zeros(hit.size)
        lost = np.bincount(klass[hit], w[hit] * (1.0 - refl), minlength=period)
        escaped += lost
        escaped_faces += lost
        # R depends on the path only (not on w), so which photons go on is independent
        # of σs: the σs scaling stays exact path for path.
        keep = refl > 0
        hit, dist, refl = hit[keep], dist[keep], refl[keep]
        pos[:, hit] += dist * u[:, hit]
        pos[2, hit] = np.where(u[2, hit] > 0, slab.thickness, 0.0)
        u[2, hit] = -u[2, hit]
        w[hit] *= refl
        free[hit] -= dist
        active = hit
    return collided


def _check(width, height, thickness, sigma_t, sigma_s, g, bounces, boundary, n, photons, batch):
    check_scene(width, height, sigma_t, sigma_s, g, bounces, photons, batch)
    if not (math.isfinite(thickness) and thickness > 0):
        raise ValueError(f"thickness: must be finite and > 0 pixels, got {thickness!r}")
    if boundary not in ("absorbing", "refractive"):
        raise ValueError(f"boundary: must be 'absorbing' or 'refractive', got {boundary!r}")
    if not (math.isfinite(n) and n > 0):
        raise ValueError(f"n: must be finite and > 0 (n_medium / n_outside), got {n!r}")


def monte_carlo_slab(
    width: int,
    height: int,
    thickness: float,
    sigma_t: float,
    sigma_s: float,
    g: float,
    illumination: Beam | Stripes | Full,
    bounces: int,
    *,
    boundary: Boundary = "absorbing",
    n: float = 1.33,
    photons: int = 1_000_000,
    seed: int = 0,
    batch: int = 200_000,
    depth_layers: int | None = None,
    camera_sampling: float = 0.0,
) -> SlabMonteCarloResult:
    """Monte Carlo estimate of I_1..I_bounces for the slab geometry (see module doc).

    Args:
        width, height: image size W × H in pixels; the slab fills [0, W] × [0, H] × [0, h].
        thickness: slab depth h in pixels.
        sigma_t, sigma_s: 3-D extinction and scattering coefficients, per pixel.
        g: Henyey–Greenstein asymmetry, −1 < g < 1 (phase normalised on the sphere).
        illumination: ``Beam``, ``Stripes`` or ``Full``, extruded over the depth as a
            horizontal sheet of unit irradiance.
        bounces: number of bounce images K (photons scatter at most K − 1 times).
        boundary: "absorbing" or "refractive" top and bottom faces.
        n: relative index n_medium / n_outside of the faces (``refractive`` only).
        photons: photons launched in total (all stripe patterns share them).
        seed: seed of numpy's default generator. With the same seed, σt, g, n, boundary,
            photons and batch the paths are identical for any σs.
        batch: photons traced at a time (memory bound).
        depth_layers: ``None`` (the slab) or a layer count L, for judging a forward
            model that keeps each order's source as L layer averages: at every
            scattering the photon's depth is redrawn uniformly within its layer of
            thickness h/L (L = 1: the depth average). I_1 and I_2 are unchanged in
            expectation (the first source, the sheet's collisions, is already
            uniform in depth and independent of x, y, ω); from I_3 on this is the
            approximation, not the slab.
        camera_sampling: ε in [0, 1): the share of scatterings whose new direction is
            drawn from the HG lobe around the camera's axis ẑ, p(ω·ẑ), instead of the
            one around the photon's direction (the weight × p(ω·ω_in)/q(ω) with the
            mixture q = (1 − ε) p(ω·ω_in) + ε p(ω·ẑ) keeps every I_k unbiased). The
            camera scores p(ω·ẑ) per collision, which for forward-peaked media (g ≳ 0.8)
            is ~100× larger for steep than for grazing flights: steep flights are rare
            in high orders and their scores make I_k's noise heavy-tailed; drawing them
            more often cuts it. 0: the analog directions (and per-photon power balance).
    """
    _check(width, height, thickness, sigma_t, sigma_s, g, bounces, boundary, n, photons, batch)
    if depth_layers is not None:
        positive_int("depth_layers", depth_layers)
    if not 0.0 <= camera_sampling < 1.0:
        raise ValueError(f"camera_sampling: must be in [0, 1), got {camera_sampling!r}")
    slab = OracleSlab(width, height, float(thickness), boundary, float(n))
    src = wall_source(illumination, width, height)
    power = src.power * slab.thickness
    albedo = sigma_s / sigma_t
    camera = albedo * _camera_transmission(boundary, n)  # × p(μ_in) e^{−σt(h − z)}
    n_px = height * width
    n_slots = src.period * n_px
    tally = np.zeros((3, bounces * n_slots))
    escaped = np.zeros((bounces, src.period))
    escaped_faces = np.zeros((bounces, src.period))
    collided = np.zeros((bounces, src.period))
    rng = np.random.default_rng(seed)
    direction = np.array([math.cos(src.theta0), math.sin(src.theta0), 0.0])
    done = 0
    while done < photons:
        m = min(batch, photons - done)
        done += m
        x, y, klass = launch_photons(src, m, width, height, rng)
        pos = np.stack([x, y, slab.thickness * rng.random(m)])
        u = np.repeat(direction[:, None], m, axis=1)
        w = np.ones(m)
        for j in range(bounces):  # flight j carries light scattered exactly j times
            free = rng.standard_exponential(w.size) / sigma_t
            hit = fly(slab, pos, u, w, free, klass, escaped[j], escaped_faces[j])
            pos, u, w, klass = pos[:, hit], u[:, hit], w[hit], klass[hit]
            collided[j] += np.bincount(klass, w, minlength=src.period)
            score = (
                w
                * camera
                * phase_function_cos(u[2], g)
                * np.exp(-sigma_t * (slab.thickness - pos[2]))
            )
            pixel = j * n_slots + klass * n_px + pixel_index(pos[1], height) * width
            add_tally(tally, pixel + pixel_index(pos[0], width), score)
            if j + 1 == bounces:
                break
            w = w * albedo
            u = _scatter(rng, u, g, camera_sampling, w)
            if depth_layers is not None:
                layer = np.minimum(
                    np.floor(pos[2] * depth_layers / slab.thickness), depth_layers - 1
                )
                pos[2] = (layer + rng.random(w.size)) * (slab.thickness / depth_layers)
    lit = src.lit.astype(np.float64)  # (classes, patterns)
    m1, m2, hits = np.einsum("tkcq,cp->tpkq", tally.reshape(3, bounces, src.period, n_px), lit)
    mean = power * m1 / photons
    var = np.maximum(power**2 * m2 / photons - mean**2, 0.0) / max(photons - 1, 1)
    total = mean.sum(-1)
    total_var = np.maximum(power**2 * m2.sum(-1) / photons - total**2, 0.0) / max(photons - 1, 1)
    shape = (lit.shape[1], bounces, height, width)

    def per_pattern(a):
        return power * (a @ lit).T / photons

    return SlabMonteCarloResult(
        images=mean.reshape(shape),
        stderr=np.sqrt(var).reshape(shape),
        total_stderr=np.sqrt(total_var),
        hits=np.rint(hits).astype(np.int64).reshape(shape),
        escaped=per_pattern(escaped),
        escaped_faces=per_pattern(escaped_faces),
        absorbed=per_pattern((1.0 - albedo) * collided),
        untraced=albedo * per_pattern(collided)[:, -1],
        input_power=src.input_power * slab.thickness,
        photons=int(photons),
    )
