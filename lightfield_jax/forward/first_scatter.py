"""The first-collided light field L_1, semi-analytically (no grid transport of the beam).

Transporting the thin unscattered beam (or the first-scatter source Q_1) on the grid
smears it into neighbouring rows (docs/model.md §4). Instead, L_1 is a 2-D convolution of
the pixel-averaged unscattered fluence S with one kernel per direction bin:

    L_1[x, j] = σs Σ_s S[s] K_j[x − s],
    K_j[Δ] = (1/Δθ) ∫_{bin j} dθ p(θ − θ0) ∫_0^∞ dr e^{−σt r} T(r ω(θ) − Δ),

with T(w) = (1 − |w_x|)(1 − |w_y|) on [−1, 1]² the density of the offset between a
uniform point of the target pixel and one of the source pixel (so K averages over both
pixels, and the 1/r of the point kernel cancels against the polar area element). The
(r, θ) integral is a quadrature on polar rings, fine near r = 0 and coarser further
out, each node bilinearly splatted onto the integer offsets Δ (bilinear weights *are*
T). Bin edges fall between nodes, so each node lands in exactly one bin.

Node geometry is static (numpy, built once per grid); only the node values
p(θ − θ0)·e^{−σt r} depend on σt and g, so new values never rebuild or recompile.
The convolution is an FFT over a (2H, 2W) zero-padded domain: no wrap-around for
offsets |Δ| < (H, W). Where S factors as u_p(across)·f(along) (light entering through
a wall along its normal: every stripe pattern's rows share the decay e^{−σt x}), it is
two matrix products instead (:func:`convolve_separable`, :func:`separable_source`):
the same sums, 2–5× faster than the FFTs on the CPU.
"""

from __future__ import annotations

import functools
import math

import jax.numpy as jnp
import numpy as np

from lightfield_jax.forward.kernels import einsum, fft_convolve, padded_spectrum, splat

# (outer radius, ring width): fine rings where T varies on the scale of the nodes'
# spacing in θ, coarser where the integrand only varies with e^{−σt r}.
_RING_BANDS = ((2.0, 1.0 / 16), (4.0, 1.0 / 8), (16.0, 0.25), (math.inf, 0.5))
_MIN_NODES_PER_BIN = 4


@functools.lru_cache(maxsize=16)
def kernel_nodes(width: int, height: int, n_theta: int):
    """Static polar quadrature of the first-scatter kernel, splatted onto offsets.

    Returns a dict of numpy arrays:
      ``r``, ``phi`` (node radius, angle), ``weight`` (dr·dθ/Δθ), ``dr`` (the node's
      ring width) of shape (N,),
      ``index`` (N, 4) flat indices into an (n_theta, 2H, 2W) kernel array (offsets
      wrapped modulo the FFT size) and ``splat`` (N, 4) bilinear weights.
    """
    r_max = math.hypot(width, height) + 1.5
    radii, widths = [], []
    r0 = 0.0
    for outer, h in _RING_BANDS:
        outer = min(outer, r_max)
        n = max(0, math.ceil((outer - r0) / h - 1e-9))
        radii.append(r0 + (np.arange(n) + 0.5) * h)
        widths.append(np.full(n, h))
        r0 = r0 + n * h
        if r0 >= r_max:
            break
    radii = np.concatenate(radii)
    widths = np.concatenate(widths)
    dtheta = 2.0 * np.pi / n_theta
    per_bin = np.maximum(
        _MIN_NODES_PER_BIN, np.ceil(2.0 * np.pi * radii / (widths * n_theta))
    ).astype(np.int64)

    two_h, two_w = 2 * height, 2 * width
    rs, phis, ws, drs, idxs, spl = [], [], [], [], [], []
    for m in np.unique(per_bin):
        rings = per_bin == m
        r = radii[rings][:, None]
        h = widths[rings][:, None]
        q = np.arange(n_theta * m)
        # Nodes of bin j: θ_j − Δθ/2 + (i + ½)Δθ/m, i = 0..m−1 (midpoint rule per bin).
        phi = (-0.5 * dtheta + (q + 0.5) * dtheta / m)[None, :]
        dx = r * np.cos(phi)
        dy = r * np.sin(phi)
        x0 = np.floor(dx)
        y0 = np.floor(dy)
        fx = dx - x0
        fy = dy - y0
        x0 = x0.astype(np.int64)
        y0 = y0.astype(np.int64)
        jbin = np.broadcast_to(q // m, dx.shape)
        corner_idx, corner_w = [], []
        for ox, oy, wgt in (
            (0, 0, (1 - fx) * (1 - fy)),
            (1, 0, fx * (1 - fy)),
            (0, 1, (1 - fx) * fy),
            (1, 1, fx * fy),
        ):
            tx = x0 + ox
            ty = y0 + oy
            valid = (np.abs(tx) <= width - 1) & (np.abs(ty) <= height - 1)
            flat = (jbin * two_h + np.mod(ty, two_h)) * two_w + np.mod(tx, two_w)
            corner_idx.append(np.where(valid, flat, 0))
            corner_w.append(np.where(valid, wgt, 0.0))
        corner_idx = np.stack(corner_idx, axis=-1)
        corner_w = np.stack(corner_w, axis=-1)
        keep = corner_w.sum(axis=-1) > 0
        rs.append(np.broadcast_to(r, dx.shape)[keep])
        phis.append(np.broadcast_to(phi, dx.shape)[keep])
        ws.append(np.broadcast_to(h / m, dx.shape)[keep])
        drs.append(np.broadcast_to(h, dx.shape)[keep])
        idxs.append(corner_idx[keep])
        spl.append(corner_w[keep])
    return {
        "r": np.concatenate(rs),
        "phi": np.concatenate(phis),
        "weight": np.concatenate(ws),
        "dr": np.concatenate(drs),
        "index": np.concatenate(idxs).astype(np.int32),
        "splat": np.concatenate(spl),
    }


def first_scatter_kernel(nodes: dict, phase_values, sigma_t, n_theta: int, height: int, width: int):
    """Evaluate K_j[Δ] (without σs) as an (n_theta, 2H, 2W) array.

    ``phase_values`` are p(φ − θ0) at the nodes (already divided by A(g) under the
    normalised convention).
    """
    dtype = phase_values.dtype
    values = (
        phase_values * jnp.exp(-sigma_t * nodes["r"].astype(dtype)) * nodes["weight"].astype(dtype)
    )
    size = n_theta * 2 * height * 2 * width
    kernel = splat(nodes["index"], nodes["splat"], values[None], size)
    return kernel.reshape(n_theta, 2 * height, 2 * width)


def separable_source(coverage, mean, var, tol: float = 1e-9):
    """Whether the unscattered fluence of these source moments (each (P, H, W), see
    :func:`~lightfield_jax.scene.illumination.source_moments`) factors as
    u_p(across)·f(along): the coverage constant along one axis and the depth's mean and
    variance of every lit pixel the same along the other (light entering through a wall
    along its normal), each to ``tol`` (relative to 1 and to the depth; coverages below
    ``tol``, round-off of the lit length, count as unlit). Returns ``(axis, u)`` with
    ``axis`` "x" (f varies along x: u is (P, H)) or "y" (u is (P, W)), or ``None``."""
    coverage, mean, var = (np.asarray(a, np.float64) for a in (coverage, mean, var))
    lit = coverage > tol
    if not lit.any():
        return None
    for axis, along in (("x", 2), ("y", 1)):
        across = 3 - along
        u = np.take(coverage, 0, axis=along)
        if np.max(np.abs(coverage - np.expand_dims(u, along))) > tol:
            continue
        lit_along = np.any(lit, axis=(0, across))
        shared = True
        for moment in (mean, var):
            ref = np.where(lit_along, np.max(np.where(lit, moment, -np.inf), axis=(0, across)), 0)
            off = np.abs(moment - np.expand_dims(ref, (0, across)))
            shared = shared and bool(np.all((off <= tol * (1.0 + np.abs(moment))) | ~lit))
        if shared:
            return axis, u
    return None


@functools.lru_cache(maxsize=32)
def _toeplitz(n: int) -> np.ndarray:
    """Index (2n, n) into a length-(n + 1) vector (its last entry zero): entry [d, i]
    picks element (i − d) mod 2n where that lies in [0, n), else the zero."""
    d = np.arange(2 * n)[:, None]
    i = np.arange(n)[None, :]
    src = (i - d) % (2 * n)
    return np.where(src < n, src, n).astype(np.int32)


def convolve_separable(across, along, kernel):
    """The convolution of :func:`convolve_kernels` for a separable source
    S[p, a, l] = across[p, a]·along[l]: (P, A) and (L,) with kernels (J, 2A, 2L) whose
    offsets are stored modulo (2A, 2L) → (P, J, A, L). Two matrix products with
    Toeplitz matrices of the factors: along l for all kernels at once (no pattern), then
    along a per pattern."""
    n_across, n_along = across.shape[-1], along.shape[0]
    zero = jnp.zeros((1,), along.dtype)
    v = jnp.concatenate([along, zero])[_toeplitz(n_along)]  # (2L, L)
    m = einsum("jad,dl->jal", kernel, v)  # (J, 2A, L)
    zeros = jnp.zeros(across.shape[:-1] + (1,), across.dtype)
    u = jnp.concatenate([across, zeros], axis=-1)[:, _toeplitz(n_across)]  # (P, 2A, A)
    return einsum("pea,jel->pjal", u, m)


def convolve_kernels(source, kernel):
    """(patterns, H, W) ⊛ (kernels, 2H, 2W) → (patterns, kernels, H, W), the linear
    FFT convolution (no clipping: kernels may be signed, e.g. derivatives)."""
    _, height, width = source.shape
    return fft_convolve(
        padded_spectrum(source)[:, None], jnp.fft.rfft2(kernel)[None], height, width
    )
