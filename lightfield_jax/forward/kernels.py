"""Kernels the plane and the slab renderers share: splatting node values onto kernel
grids, the zero-padded FFT convolution, and the bin-pair average of a phase function.

- :func:`splat`: quadrature nodes, each spread over its four bilinear corners of a
  kernel grid (one scatter-add for a batch of kernels).
- :func:`fft_convolve`: the linear convolution of (H, W) sources with (2H, 2W) kernels,
  given as rfft2 spectra over the zero-padded (2H, 2W) domain (exact: no wrap-around
  for offsets |Δ| < (H, W)), cropped back to (H, W).
- :func:`einsum`, :func:`matmul`: products at full float32 precision on every backend.
- :func:`bin_pair_offsets`: the angles and weights of the triangle-weighted average
  c_m = (1/Δθ²)∫_{bin j}∫_{bin j'} f(θ − θ') dθ dθ' (m = j − j') of a function of the
  angle between two direction bins, sampled ``subsamples`` times per bin.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float

# float32 matrix products at full precision: on GPUs XLA's default rounds their inputs
# to TF32 (10-bit mantissa), which a misfit that is a difference of large sums (the
# basin scan's) and a fit to 1e-4 cannot take; on the CPU it changes nothing.
HIGHEST = jax.lax.Precision.HIGHEST


def einsum(subscripts: str, *operands):
    """``jnp.einsum`` at full float32 precision (:data:`HIGHEST`)."""
    return jnp.einsum(subscripts, *operands, precision=HIGHEST)


def matmul(a, b):
    """``a @ b`` at full float32 precision (:data:`HIGHEST`)."""
    return jnp.matmul(a, b, precision=HIGHEST)


def splat(index, weights, values, size: int) -> Float[Array, "kernels size"]:
    """Kernels (A, size) from node values (A, N): node i adds ``values[:, i]·weights[i, c]``
    at flat cell ``index[i, c]`` for each of its corners c (``index``, ``weights``:
    (N, corners), from :func:`~lightfield_jax.forward.first_scatter.kernel_nodes`)."""
    count = values.shape[0]
    contrib = weights.astype(values.dtype)[:, :, None] * values.T[:, None, :]
    kernel = jnp.zeros((size, count), values.dtype)
    kernel = kernel.at[index.reshape(-1)].add(contrib.reshape(-1, count))
    return kernel.T


def fft_convolve(
    source_f: Complex[Array, "... fy fx"],
    kernel_f: Complex[Array, "... fy fx"],
    height: int,
    width: int,
) -> Float[Array, "... H W"]:
    """irfft2 of the product of two rfft2 spectra over the (2H, 2W) domain, cropped to
    (H, W): the linear convolution of an (H, W) source with a (2H, 2W) kernel whose
    offsets are stored modulo (2H, 2W)."""
    field = jnp.fft.irfft2(source_f * kernel_f, s=(2 * height, 2 * width))
    return field[..., :height, :width]


def padded_spectrum(a: Float[Array, "... H W"]) -> Complex[Array, "... fy fx"]:
    """rfft2 of ``a`` zero-padded to (2H, 2W)."""
    return jnp.fft.rfft2(a, s=(2 * a.shape[-2], 2 * a.shape[-1]))


def bin_pair_offsets(n_theta: int, subsamples: int) -> tuple[np.ndarray, np.ndarray]:
    """``(delta, weights)``: angles δ[m, s] = (m + s/n)·Δθ, s = −n..n, n = ``subsamples``
    (radians, (n_theta, 2n + 1)) and triangle weights (1 − |s|/n)/n summing to 1, so that
    c_m = Σ_s f(δ[m, s])·weights[s] is the bin-pair average of f at bin offset m."""
    n = subsamples
    s = np.arange(-n, n + 1)
    weights = (1.0 - np.abs(s) / n) / n
    delta = (np.arange(n_theta)[:, None] + s[None, :] / n) * (2 * math.pi / n_theta)
    return delta, weights
