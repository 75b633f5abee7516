"""The slab renderer (docs/model.md section 7): a tank of depth h, modelled in 3-D, cheaply.

Design (docs/slab_design.md option B, with depth layers: docs/slab_depth.md): the light
field is kept as its averages over n_z depth layers, L_l(x, y, θ, μ), with θ the
azimuth (the plane model's bins) and μ = ω·ẑ on Gauss–Legendre nodes in [0, 1]. Both
faces are symmetric and the sheet is horizontal, so L(z, −μ) = L(h − z, μ) (fact 4):
only μ ≥ 0 is stored, and a face reflection becomes a periodic wrap of the depth with
weight R(μ) (:mod:`lightfield_jax.forward.slab_layers`). With the black side walls every order
is an exact free-space transport of the previous order's source (fact 1), and for
layer-uniform sources the depth integrals are analytic:

- transport: L_l(x, ω) = Σ_l' ∫ e^{−σt t} W_{l−l'}(tμ) Q_l'(x − t ω_h, ω) dt, W the
  overlap of layer l with layer l' shifted by tμ, summed over the wraps with R^m (for
  n_z = 1 the depth average's survival S(v) = R^⌊v⌋ (1 − f (1 − R)), v = tμ/h);
- camera: I(x) = T σs Σ_l' ∫ dω ∫ e^{−σt t} [p(μ) A_l'(tμ) + p(−μ) B_l'(tμ)]
  Q_l'(x − t ω_h, ω) dt, A and B the exact integrals of the camera's attenuation
  e^{−σt (h − z)} over the heights the rays of source layer l' reach.

Each is a 2-D convolution per direction (θ bin, μ node) and layer pair with a kernel
built like the plane model's first-scatter kernel (:mod:`lightfield_jax.forward.first_scatter`:
polar rings, pixel-pair averaging by bilinear splats), evaluated with a 3-point Gauss
rule across each ring, and applied as an FFT over a (2H, 2W) zero-padded domain (exact:
no wrap-around). Per bounce (:class:`~lightfield_jax.forward.slab_layers.SlabBounce`): one
forward FFT of the layered source Q_k, n_z² kernel products, one inverse FFT for L_k,
one for the image, and n_z matmuls with the discrete 3-D phase matrices (bin-averaged
in θ, balanced so a bounce conserves ω·energy exactly).

What is exact and what is not: I_1 is exact; I_2 is exact up to the discretisation
(the first source is uniform in depth, fact 2); from I_3 on the model keeps each
order's source as its n_z layer averages, which ``monte_carlo_slab(...,
depth_layers=n_z)`` reproduces exactly; the error against the true slab falls about as
1/n_z (measured in docs/slab_depth.md; :func:`~lightfield_jax.scene.geometry.default_n_z`
chooses n_z).

Units as the Monte Carlo oracle (:mod:`lightfield_jax.reference.montecarlo_slab`): the sheet
has unit irradiance (power per unit area normal to θ0), lengths are pixels, σ per
pixel, images are power per unit area of the top face (times the gain).

The geometry itself (:class:`~lightfield_jax.scene.geometry.Slab`, its faces' Fresnel
reflectance, its discretisation defaults) lives in :mod:`lightfield_jax.scene.geometry`;
the bounce loop, refinement and the tail are the base class's
(:class:`~lightfield_jax.forward.base.AbstractRenderer`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from lightfield_jax.forward.base import AbstractRenderer, FirstOrders
from lightfield_jax.forward.first_scatter import kernel_nodes
from lightfield_jax.forward.kernels import (
    bin_pair_offsets,
    einsum,
    splat,
)
from lightfield_jax.forward.slab_layers import (
    PAIRS,
    TERMS,
    SlabBounce,
    camera_integrals,
    clip_averages,
    transport_weights,
)
from lightfield_jax.forward.slab_memory import slab_blocks
from lightfield_jax.forward.tail import TailSolution, mapped_output
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import Full, Illumination
from lightfield_jax.scene.phase import hg

if TYPE_CHECKING:
    from lightfield_jax.scene.geometry import Slab

# Gauss points across each polar ring of the kernels (the radial profile is an
# exponential times piecewise-linear depth factors: 3 points are exact to ~1e-6 on the
# rings that matter).
_RING_GAUSS = 3
# Sub-samples per azimuth bin of the triangle-weighted bin average of the phase matrix.
# The plane uses 16; 16 here would move the slab's I_3..I_6 by 5e-5 to 1.6e-3 relative
# (measured, g 0.4 and 0.8, n_mu 4), so each keeps its own count.
_PHASE_SUBSAMPLES = 8
_BALANCE_ITERATIONS = 4


@functools.lru_cache(maxsize=16)
def elevation_nodes(n_mu: int, split: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre nodes μ_j in (0, 1) and weights (summing to 1).

    With ``split`` (the critical cosine of refractive faces, where the reflectance
    has its square-root kink and total internal reflection begins) the rule is
    composite: half the nodes on [0, split], half on [split, 1].
    """
    if split is None or n_mu < 2:
        x, w = np.polynomial.legendre.leggauss(n_mu)
        return 0.5 * (x + 1.0), 0.5 * w
    lo = n_mu // 2
    parts = []
    for count, a, b in ((lo, 0.0, split), (n_mu - lo, split, 1.0)):
        x, w = np.polynomial.legendre.leggauss(count)
        parts.append((a + 0.5 * (b - a) * (x + 1.0), 0.5 * (b - a) * w))
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


@functools.lru_cache(maxsize=8)
def slab_nodes(width: int, height: int, n_theta: int):
    """The plane kernel's polar nodes, with Gauss points across each ring."""
    nodes = kernel_nodes(width, height, n_theta)
    xg, wg = np.polynomial.legendre.leggauss(_RING_GAUSS)
    r_sub = nodes["r"][:, None] + 0.5 * nodes["dr"][:, None] * xg[None, :]
    # dr·dθ/Δθ of the node, shared among the ring's Gauss points.
    w_sub = nodes["weight"][:, None] * (0.5 * wg[None, :])
    return {
        "r_sub": r_sub,
        "w_sub": w_sub,
        "phi": nodes["phi"],
        "index": nodes["index"],
        "splat": nodes["splat"],
    }


class SlabRenderer(AbstractRenderer):
    """A compiled slab forward model for one grid, illumination, slab and bounce count.

    Same call signature and outputs as :class:`~lightfield_jax.Renderer`
    (:class:`~lightfield_jax.forward.base.AbstractRenderer`, tail included):
    ``renderer(sigma_t, sigma_s, g, gain=1.0, lightfield=False)`` returns ``(images,
    lightfields)`` with images Float[Array, "patterns bounces H W"] and light fields
    (depth- and elevation-integrated: ∫_0^h ∫_{−1}^{1} L dμ dz per radian of azimuth)
    Float[Array, "bounces+1 patterns H W n_theta"] or ``None``. The phase function is
    the 3-D Henyey–Greenstein (normalised on the sphere) whatever ``phase`` says. The
    light field is resolved in ``slab.n_z`` depth layers
    (:mod:`lightfield_jax.forward.slab_layers`).
    """

    n_mu: int = eqx.field(static=True)
    n_z: int = eqx.field(static=True)
    n_m: int = eqx.field(static=True)  # depth profile coefficients per layer: 1 or 2
    thickness: float = eqx.field(static=True)  # on the working grid (pixels × refine)
    camera_t: float = eqx.field(static=True)
    fft_rows: int = eqx.field(static=True)  # 2H: zero-padded in y (a periodic cell: H)
    pattern_block: int = eqx.field(static=True)  # patterns marched at once
    mu_block: int = eqx.field(static=True)  # μ nodes transported at once
    # Per node and Gauss point across its ring: the in-plane distance r and the ring
    # weight (a node's path length is t = r/s, its vertical travel tμ, s = √(1 − μ²)).
    r_sub: Float[Array, "nodes q"]
    w_sub: Float[Array, "nodes q"]
    cos_phi: Float[Array, " nodes"]  # cos(φ − θ0): ω_node·ω0 = s_j cos(φ − θ0)
    sin_mu: Float[Array, " n_mu"]  # s_j
    index: Array
    splat: Array
    mu: Float[Array, " n_mu"]
    w_mu: Float[Array, " n_mu"]
    refl: Float[Array, " n_mu"]

    def __init__(
        self,
        grid: Grid,
        illumination: Illumination,
        bounces: int,
        slab: Slab,
        phase: str = "normalized",
        *,
        tail: str | None = None,
        tail_tol: float = 1e-4,
        tail_max_steps: int = 500,
        coarse_after: int | None = None,
        moments=None,
    ):
        if grid.n_theta is not None and (slab.n_mu is None or slab.n_z is None):
            raise ValueError("SlabRenderer needs slab.n_mu and slab.n_z: call Slab.resolve first")
        if phase not in ("paper", "normalized"):
            raise ValueError(f"phase: must be paper or normalized, got {phase!r}")
        self._setup(
            grid,
            illumination,
            bounces,
            phase,
            tail,
            tail_tol,
            tail_max_steps,
            coarse_after,
            moments,
            basis=True,
        )
        f = self.refine
        self.n_mu = int(slab.n_mu)
        self.n_z = int(slab.n_z)
        self.n_m = slab.depth_coefficients
        self.thickness = float(slab.thickness) * f
        self.camera_t = slab.camera_transmission
        theta0 = math.radians(illumination.direction_deg)

        mu, w_mu = elevation_nodes(self.n_mu, slab.critical_cosine)
        s = np.sqrt(1.0 - mu * mu)
        nodes = slab_nodes(self.width, self.height, self.n_theta)
        self.r_sub = jnp.asarray(nodes["r_sub"])
        self.w_sub = jnp.asarray(nodes["w_sub"])
        self.cos_phi = jnp.asarray(np.cos(nodes["phi"] - theta0))
        self.sin_mu = jnp.asarray(s)
        self.index = jnp.asarray(nodes["index"])
        self.splat = jnp.asarray(nodes["splat"])
        self.mu = jnp.asarray(mu)
        self.w_mu = jnp.asarray(w_mu)
        self.refl = jnp.asarray(slab.reflectance(mu))
        self.fft_rows = 2 * self.height
        self.pattern_block, self.mu_block = slab_blocks(
            self.coverage.shape[0],  # the marched patterns
            self.height,
            self.width,
            self.n_theta,
            self.n_mu,
            self.n_z,
            self.n_m,
        )

    # σ/f and h·f on the refined grid: images (ratios like σs/σt) are unchanged; the
    # depth-integrated fields are in refined pixels of depth: divided by f.
    @property
    def image_scale(self) -> float:
        return 1.0

    @property
    def field_scale(self) -> float:
        return 1.0 / self.refine

    @property
    def direct_depth(self) -> float:
        return self.thickness

    def integrate(self, field):
        """(patterns, n_m·n_z, n_mu, n_theta, H, W) → ∫dz ∫dμ: (patterns, n_theta, H,
        W); only the layer averages integrate to anything (∫φ_1 = 0)."""
        dz = self.thickness / self.n_z
        w_mu = self.w_mu.astype(field.dtype)
        return 2.0 * dz * einsum("j,pljnhw->pnhw", w_mu, field[:, : self.n_z])

    # -- pieces -------------------------------------------------------------------

    def _kernels_f(self, values):
        """values (…, n_mu, N) → rfft2 of their kernels (…, n_mu, n_theta, 2H, W + 1)."""
        lead = values.shape[:-1]
        size = self.n_theta * self.fft_rows * 2 * self.width
        kernels = splat(self.index, self.splat, values.reshape((-1, values.shape[-1])), size)
        kernels = kernels.reshape(-1, self.n_theta, self.fft_rows, 2 * self.width)
        return jnp.fft.rfft2(kernels).reshape(lead + (self.n_theta, self.fft_rows, -1))

    def _spectrum(self, a):
        """rfft2 of ``a`` (…, H, W) on the FFT domain (fft_rows, 2W)."""
        return jnp.fft.rfft2(a, s=(self.fft_rows, 2 * self.width))

    def _convolve(self, source_f, kernel_f):
        """The convolution of two spectra of the FFT domain, cropped to (H, W)."""
        field = jnp.fft.irfft2(source_f * kernel_f, s=(self.fft_rows, 2 * self.width))
        return field[..., : self.height, : self.width]

    def _phase_matrices(self, g, dtype):
        """(M⁺, M⁻), each (n_mu·n_theta) square: from stored up-going directions into
        up-going (M⁺) and down-going (M⁻) ones, so Q(+μ) = σs (M⁺ L(+μ) + M⁻ L(−μ)).

        Entries are dΩ_{j'} p̄(ω_ji·ω_j'i'^±), p̄ the triangle-weighted average over the
        two azimuth bins, balanced (the same symmetric scaling of both) so that the
        discrete sphere integral of every row and every column of M⁺ + M⁻ is exactly 1.
        """
        n, J = self.n_theta, self.n_mu
        dtheta = 2 * math.pi / n
        delta, tri = bin_pair_offsets(n, _PHASE_SUBSAMPLES)  # (n, 2ns+1), (2ns+1,)
        tri = tri.astype(dtype)
        mu = self.mu.astype(dtype)
        s = jnp.sqrt(1.0 - mu * mu)
        ss = (s[:, None] * s[None, :])[:, :, None, None]
        mm = (mu[:, None] * mu[None, :])[:, :, None, None]
        cosd = jnp.asarray(np.cos(delta), dtype)[None, None]
        j = np.arange(n)
        circ = (j[:, None] - j[None, :]) % n

        def matrix(sign):  # (J, J', n, n') → (J·n, J'·n')
            taps = jnp.sum(hg(ss * cosd + sign * mm, g) * tri, axis=-1)
            return jnp.transpose(taps[:, :, circ], (0, 2, 1, 3)).reshape(J * n, J * n)

        plus, minus = matrix(1.0), matrix(-1.0)
        a = plus + minus
        domega = jnp.repeat(self.w_mu.astype(dtype) * dtheta, n)  # dΩ per stored node
        # Symmetric balancing of the kernel a (symmetric) so Σ_c a[r, c] dΩ_c = 1.
        d = jnp.ones(J * n, dtype)
        for _ in range(_BALANCE_ITERATIONS):
            row = (a * (d[None, :] * domega[None, :])).sum(axis=1) * d
            d = d / jnp.sqrt(row)
        scale = d[:, None] * d[None, :]
        col = (a * scale * domega[:, None]).sum(axis=0)  # exact conservation per column
        scale = scale / col[None, :] * domega[None, :]
        return plus * scale, minus * scale

    def _elevation_parts(self):
        """The per-μ-node tables, each with the μ nodes as its first axis."""
        return (self.sin_mu, self.mu, self.w_mu, self.refl)

    def _transport_and_camera(self, sigma_t, g, dtype, parts):
        """Node values of the layer-to-layer transport kernels W^{ab}_δ per distinct
        profile pair, δ = −(n_z−1)..n_z−1 (pairs, 2 n_z − 1, μ nodes, N), and of the
        camera kernels per source coefficient and layer (n_m·n_z, μ nodes, N):
        T dΩ_j [p(μ_j)·A + p(−μ_j)·B] (σs apart), for the μ nodes of ``parts``
        (:meth:`_elevation_parts`, or a block of them)."""
        sin_mu, mu, w_mu, refl = parts
        h, n_z = self.thickness, self.n_z
        inv_s = 1.0 / sin_mu.astype(dtype)[:, None, None]
        t = self.r_sub.astype(dtype)[None] * inv_s  # (μ nodes, N, q)
        u = jax.lax.stop_gradient(t * mu.astype(dtype)[:, None, None])
        refl = jax.lax.stop_gradient(refl.astype(dtype))[:, None, None]
        att = jnp.exp(-sigma_t * t) * (self.w_sub.astype(dtype)[None] * inv_s)
        v = u / (h / n_z)
        transport = jnp.stack(
            [
                jnp.stack(
                    [
                        jnp.sum(att * transport_weights(v, refl, n_z, delta, pair), axis=-1)
                        for delta in range(-(n_z - 1), n_z)
                    ]
                )
                for pair in PAIRS[self.n_m]
            ]
        )
        mu = mu.astype(dtype)
        weight = (w_mu.astype(dtype) * (2 * math.pi / self.n_theta) * self.camera_t)[:, None]
        camera = []
        for moment in range(self.n_m):
            for layer in range(n_z):
                up, down = camera_integrals(u, h, n_z, layer, refl, sigma_t, moment)
                up, down = jnp.sum(att * up, axis=-1), jnp.sum(att * down, axis=-1)
                camera.append(weight * (hg(mu, g)[:, None] * up + hg(-mu, g)[:, None] * down))
        return transport, jnp.stack(camera)

    def _first_phase_norm(self, g, dtype):
        """The discrete sphere integral of p(ω·ω0) that normalises the first scatter's
        phase at the kernels' nodes (so the first bounce conserves ω·energy)."""
        n = self.n_theta
        dtheta = 2 * math.pi / n
        mu = self.mu.astype(dtype)
        fine = (np.arange(n * 16) + 0.5) * (dtheta / 16)
        ring = jnp.sum(
            hg(jnp.sqrt(1 - mu * mu)[:, None] * jnp.asarray(np.cos(fine), dtype)[None], g),
            axis=1,
        ) * (dtheta / 16)
        return 2.0 * jnp.sum(self.w_mu.astype(dtype) * ring)

    def first_orders(self, sigma_t, sigma_s, g, source, scattered: bool) -> FirstOrders:
        """I_1 = T σs p(cos 90°) (1 − e^{−σt h})/σt · S (docs/model.md §7) and, when
        ``scattered``, the bounce step with I_2, the layered light field L_1 and source
        Q_2 (patterns, n_m·n_z, n_mu, n_theta, H, W). I_2 comes straight from the
        first-scatter kernels (the first source is uniform in depth: exact). The kernels
        are built ``mu_block`` μ nodes at a time (their node values are as large as the
        kernels' spectra)."""
        dtype = sigma_t.dtype
        t_cam = jnp.asarray(self.camera_t, dtype)
        depth_factor = -jnp.expm1(-sigma_t * self.thickness) / sigma_t
        image = t_cam * sigma_s * hg(jnp.zeros((), dtype), g) * depth_factor * source
        if not scattered:
            return FirstOrders(image)
        n_z, height, width = self.n_z, self.height, self.width
        norm = self._first_phase_norm(g, dtype)
        src_f = self._spectrum(source)

        def block(parts):
            """One block of μ nodes: its kernels' spectra, its part of L_1 and of the
            first scatter's camera kernel."""
            transport, camera = self._transport_and_camera(sigma_t, g, dtype, parts)
            node_cos = parts[0].astype(dtype)[:, None] * self.cos_phi.astype(dtype)[None]
            p1 = hg(node_cos, g) / norm  # p(ω_node·ω0) at the kernels' nodes
            # The first source is uniform in depth (its average alone): coefficient a of
            # layer l receives Σ_l' W^{a0}_{l−l'}, and only the average's camera kernels
            # see it.
            first = jnp.concatenate(
                [
                    factor
                    * jnp.stack(
                        [
                            jnp.sum(transport[pair, layer : layer + n_z], axis=0)
                            for layer in range(n_z)
                        ]
                    )
                    for _, b, pair, factor in TERMS[self.n_m]
                    if b == 0
                ]
            )
            k1_f = self._kernels_f(p1 * first)
            k1_cam_f = jnp.sum(self._kernels_f(p1 * jnp.sum(camera[:n_z], axis=0)), (0, 1))
            l1 = self._convolve(src_f[:, None, None, None], k1_f)
            kernels = (self._kernels_f(transport), sigma_s * self._kernels_f(camera))
            return kernels, l1, k1_cam_f

        blocks = self.n_mu // self.mu_block
        parts = tuple(
            a.reshape((blocks, self.mu_block) + a.shape[1:]) for a in self._elevation_parts()
        )
        if blocks == 1:
            kernels, l1, k1_cam_f = jax.tree_util.tree_map(
                lambda a: a[None], block(tuple(a[0] for a in parts))
            )
        else:
            kernels, l1, k1_cam_f = jax.lax.map(block, parts)
        # (blocks, patterns, n_m·n_z, mu_block, …) → (patterns, n_m·n_z, n_mu, …)
        l1 = jnp.moveaxis(l1, 0, 2)
        l1 = sigma_s * clip_averages(l1.reshape(l1.shape[:2] + (self.n_mu,) + l1.shape[4:]), n_z)
        i2 = sigma_s**2 * jnp.maximum(self._convolve(src_f, jnp.sum(k1_cam_f, axis=0)), 0.0)
        plus, minus = self._phase_matrices(g, dtype)
        bounce = SlabBounce(
            transport_f=kernels[0],
            camera_f=kernels[1],
            mix_even=0.5 * sigma_s * (plus + minus),
            mix_odd=0.5 * sigma_s * (plus - minus),
            height=height,
            width=width,
            fft_rows=self.fft_rows,
        )
        return FirstOrders(image, bounce, i2, l1, bounce.scatter(l1))

    def _march(self, sigma_t, sigma_s, g, gain, lightfield: bool):
        """The march of :class:`~lightfield_jax.forward.base.AbstractRenderer`,
        ``pattern_block`` patterns at a time (each block builds its own kernels: only one
        block's fields are alive at once)."""
        n, size = self.coverage.shape[0], self.pattern_block  # the marched patterns
        if size == n:
            return super()._march(sigma_t, sigma_s, g, gain, lightfield)
        moments = tuple(
            a.reshape((n // size, size) + a.shape[1:])
            for a in (self.coverage, self.mean_depth, self.var_depth)
        )

        def block(part):
            renderer = eqx.tree_at(lambda r: (r.coverage, r.mean_depth, r.var_depth), self, part)
            return AbstractRenderer._march(renderer, sigma_t, sigma_s, g, gain, lightfield)

        out = jax.lax.map(block, moments)

        def patterns_first(a):  # (blocks, size, …) → (n, …)
            return a.reshape((n,) + a.shape[2:])

        def fields_first(a):  # (blocks, K+1, size, …) → (K+1, n, …)
            a = jnp.moveaxis(a, 0, 1)
            return a.reshape((a.shape[0], n) + a.shape[3:])

        out = mapped_output(out, patterns_first, fields_first, patterns_first)
        if len(out) == 2:
            return out
        steps, converged = jnp.max(out[2].steps), jnp.all(out[2].converged)
        return out[:2] + (TailSolution(out[2].image, out[2].lightfield, steps, converged),)


@functools.lru_cache(maxsize=64)
def _bounce_ratio_cached(slab: Slab, key: tuple, width: int, height: int) -> float:
    sigma_t, albedo, g = key
    f = max(1.0, max(width, height) / 24.0)  # the same tank, in pixels of f px
    w, h = max(4, round(width / f)), max(4, round(height / f))
    coarse = dataclasses.replace(
        slab, thickness=slab.thickness / f, n_mu=min(slab.n_mu or 4, 8), n_z=min(slab.n_z or 1, 2)
    )
    grid = Grid(w, h, 8, 1)
    k = 14
    r = SlabRenderer(grid, Full(0.0, "left"), k, coarse)
    images = np.asarray(r(sigma_t * f, albedo * sigma_t * f, g)[0], np.float64)[0]
    totals = images.sum(axis=(1, 2))
    ratios = totals[1:] / np.maximum(totals[:-1], 1e-300)
    return float(np.max(ratios[4:]))


def slab_bounce_ratio(
    slab: Slab, sigma_t: float, albedo: float, g: float, width: int, height: int
) -> float:
    """The slab's per-bounce energy ratio ΣI_{k+1}/ΣI_k at these values, measured on a
    coarse render of the same tank (≤ 24 px a side, 14 bounces; the largest ratio from
    the fifth bounce on). Light leaving through the faces and walls makes it smaller
    than the albedo bound ω, often by far: it sizes the bounce count of slab fits."""
    key = (round(float(sigma_t), 4), round(float(albedo), 3), round(float(g), 2))
    return _bounce_ratio_cached(slab.resolve(g, sigma_t, albedo), key, int(width), int(height))


__all__ = [
    "SlabRenderer",
    "elevation_nodes",
    "hg",
    "slab_bounce_ratio",
    "slab_nodes",
]
