"""The slab render's memory: how it is cut into blocks, and what it needs.

A slab render holds, besides its images, three kinds of arrays
(:class:`~lightfield_jax.forward.slab.SlabRenderer`,
:class:`~lightfield_jax.forward.slab_layers.SlabBounce`):

- the kernels' spectra, built once per (σt, σs, g): the transport kernels of every
  profile pair and layer offset and the camera kernels, each (n_mu, n_theta, 2H, W + 1)
  complex;
- per pattern, the layered fields: the source Q_k, the next one, the transported field
  L_k and the scatter's temporaries, each n_m·n_z·n_mu·n_theta·H·W floats;
- per pattern and μ node transported at once, the zero-padded spectra of the source and
  of its transported field and the inverse FFT's (2H, 2W) output.

The patterns are marched ``pattern_block`` at a time and the μ nodes transported
``mu_block`` at a time (:func:`slab_blocks`), the largest blocks whose working set
stays within :data:`SLAB_WORKING_SET`: a 128×128 refractive milk tank of six stripe
shifts (16 θ bins, 16 μ nodes, 2 linear layers) peaked at 7.8 GiB in one block and
fits in 2 GiB in blocks (docs/slab_memory.md). Small renders (a fit's models, tests)
stay in one block, the march they always had.

:func:`slab_render_bytes` is the estimate of the whole render that ``simulate`` and
:func:`~lightfield_jax.render` check against the memory limit
(:mod:`lightfield_jax.runtime.memory`).
"""

from __future__ import annotations

from lightfield_jax.forward.slab_layers import PAIRS
from lightfield_jax.forward.tail import GMRES_RESTART

# Bytes of the blocked part of a render's working set (the fields of a pattern block
# and the spectra of a μ block); the kernels come on top.
SLAB_WORKING_SET = 768 << 20
# Layered fields of a pattern alive at once in a bounce (Q_k, Q_{k+1}, L_k, the scatter's
# mirror sums and products, the μ-major copy of a blocked source, XLA's temporaries).
FIELD_COPIES = 6
# Spectra of a μ block alive at once (the source's, the transported field's accumulator,
# a product, the inverse FFT's padded output counted as one).
SPECTRUM_COPIES = 4
# Copies of the kernels' spectra (the stored ones, and the block being built: its
# splatted real kernels and their spectrum).
KERNEL_COPIES = 1


def _divisors(n: int) -> list[int]:
    """Divisors of n, largest first."""
    return [d for d in range(n, 0, -1) if n % d == 0]


def field_bytes(height: int, width: int, n_theta: int, n_mu: int, coefficients: int) -> int:
    """One pattern's layered field (float32)."""
    return 4 * coefficients * n_mu * n_theta * height * width


def spectrum_bytes(height: int, width: int, n_theta: int, n_mu: int, coefficients: int) -> int:
    """The zero-padded rfft2 of ``n_mu`` nodes of one pattern's layered field (complex64)."""
    return 8 * coefficients * n_mu * n_theta * 2 * height * (width + 1)


def kernel_count(n_z: int, n_m: int) -> int:
    """Kernels per (μ node, θ bin): the transport's (profile pairs × layer offsets), the
    camera's (n_m·n_z) and the first scatter's (n_m·n_z, and its camera's one)."""
    return len(PAIRS[n_m]) * (2 * n_z - 1) + 2 * n_m * n_z + 1


def working_bytes(
    pattern_block: int,
    mu_block: int,
    height: int,
    width: int,
    n_theta: int,
    n_mu: int,
    n_z: int,
    n_m: int,
) -> int:
    """The blocked part of the working set: :data:`FIELD_COPIES` fields of
    ``pattern_block`` patterns, :data:`SPECTRUM_COPIES` spectra of ``mu_block`` μ nodes
    of them, and the spectra of one block of kernels being built."""
    c = n_m * n_z
    fields = FIELD_COPIES * pattern_block * field_bytes(height, width, n_theta, n_mu, c)
    spectra = SPECTRUM_COPIES * pattern_block * spectrum_bytes(height, width, n_theta, mu_block, c)
    building = 2 * kernel_count(n_z, n_m) * spectrum_bytes(height, width, n_theta, mu_block, 1)
    return fields + spectra + building


def slab_blocks(
    n_patterns: int,
    height: int,
    width: int,
    n_theta: int,
    n_mu: int,
    n_z: int,
    n_m: int,
    budget: int = SLAB_WORKING_SET,
) -> tuple[int, int]:
    """``(pattern_block, mu_block)``: divisors of the pattern count and of ``n_mu``, the
    largest whose :func:`working_bytes` is within ``budget`` (the patterns' block
    first: a μ block costs little but a scan, a pattern block rebuilds the kernels),
    ``(1, 1)`` where none is."""
    for patterns in _divisors(n_patterns):
        for mu in _divisors(n_mu):
            if working_bytes(patterns, mu, height, width, n_theta, n_mu, n_z, n_m) <= budget:
                return patterns, mu
    return 1, 1


def slab_render_bytes(
    n_patterns: int,
    height: int,
    width: int,
    n_theta: int,
    n_mu: int,
    n_z: int,
    n_m: int,
    *,
    refine: int = 1,
    bounces: int = 1,
    lightfield: bool = False,
    tail: bool = False,
) -> int:
    """The memory of a slab render, an upper bound from the sizes alone: the kernels'
    spectra, the blocked working set (:func:`slab_blocks`) and the march's per-bounce
    images (float32), with ``lightfield`` the stored depth-integrated fields ((K+1) ×
    patterns × H × W × n_theta float32, two copies) and with ``tail`` the Krylov vectors
    of a pattern block (GMRES's restart and three more, layered fields); or, where it is
    more, the images' copies after the render (float64, two, and the march's): the
    kernels are gone by then. Sizes are those of the working grid (× ``refine``)."""
    h, w = height * refine, width * refine
    c = n_m * n_z

    def blocked(blocks) -> int:
        """The blocked working set and, with ``tail``, the Krylov vectors of a block."""
        patterns, mu = blocks
        krylov = (GMRES_RESTART + 3) * patterns * field_bytes(h, w, n_theta, n_mu, c)
        return working_bytes(patterns, mu, h, w, n_theta, n_mu, n_z, n_m) + (krylov if tail else 0)

    # A render may march fewer patterns than it returns (stripes as fewer shifts and
    # full light, forward/pattern_basis.py), whose blocks may differ: the most any count
    # up to n_patterns takes.
    most = max(
        blocked(slab_blocks(m, h, w, n_theta, n_mu, n_z, n_m)) for m in range(1, n_patterns + 1)
    )
    kernels = KERNEL_COPIES * kernel_count(n_z, n_m) * spectrum_bytes(h, w, n_theta, n_mu, 1)
    images = bounces * n_patterns * height * width * 4
    stored = 2 * (bounces + 1) * n_patterns * h * w * n_theta * 4 if lightfield else 0
    return max(kernels + most + images + stored, 5 * images + stored)


__all__ = [
    "SLAB_WORKING_SET",
    "field_bytes",
    "kernel_count",
    "slab_blocks",
    "slab_render_bytes",
    "spectrum_bytes",
    "working_bytes",
]
