"""Depth layers of the slab model: the weights between layers and one bounce.

The slab [0, h] is cut into n_z layers of thickness Δ = h/n_z, and each order's source
is kept as its layer averages Q_l(x, y, θ, μ) (n_z = 1: the depth average). The faces
are symmetric and the sheet is horizontal, so the light field has the mirror symmetry
L(z, −μ) = L(h − z, μ) (docs/slab_design.md, fact 4): only up-going directions μ > 0
are stored, the down-going field of layer l being the up-going one of layer
n_z − 1 − l.

With that symmetry a face reflection is a periodic wrap: light heading up from height
a, after a vertical travel u and m reflections (weight R(μ)^m), is up-going light at
y = a + u − m h of the stored field, whichever face it met first (the down-going
branch is the mirror image of the up-going one). So the layer average of the
transported field is, exactly for layer-uniform sources,

    L_l(x) = Σ_{l'} ∫ dt e^{−σt t} W_{l−l'}(t μ) Q_{l'}(x − t ω_h),
    W_δ(u) = Σ_{m ≥ 0} R^m Λ(u/Δ − δ − m n_z),   Λ(x) = (1 − |x|)₊,

the overlap of layer l with layer l' shifted by u (R = 0 for absorbing faces: m = 0
only). For n_z = 1, W_0(u) = R^⌊v⌋(1 − f(1 − R)), v = u/h, f = v − ⌊v⌋: the depth
average's survival S. The camera sees (docs/model.md §7) T σs ∫ dz e^{−σt(h−z)} Σ_ω p(ω·ẑ) L,
which for the stored up-going field at height y is the weight
p(μ) e^{−σt(h−y)} + p(−μ) e^{−σt y}; integrated exactly over the rays leaving source
layer l' (:func:`camera_integrals`), I_{k+1} is exact given the layered Q_k.

Only the radial quadrature points' vertical travel u = tμ enters: it is static, and
the σt-dependent factors (e^{−σt t}, the camera's exponentials) are evaluated in the
compiled program, so new σt, σs, g never recompile.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float

from lightfield_jax.forward.kernels import einsum

_GAUSS4 = tuple(tuple(float(v) for v in a) for a in np.polynomial.legendre.leggauss(4))


def _wraps(m, refl):
    """R^m for wrap counts m ≥ 0 (R^0 = 1, also for R = 0)."""
    log_r = jnp.log(jnp.maximum(refl, 1e-300))
    return jnp.where(m == 0, 1.0, jnp.where(refl > 0, jnp.exp(m * log_r), 0.0))


def _overlap(x, pair: str):
    """The Legendre coefficients of a source of profile φ_b in a layer shifted by x layer
    thicknesses, in the receiving layer's profile φ_a (φ_0 = 1, φ_1 = 2ξ − 1 on the
    layer's local height ξ ∈ [0, 1]): w^{ab}(x) = (2a + 1) ∫ φ_a(ξ) φ_b(ξ − x) dξ over
    the overlap, L = (1 − |x|)₊ long. ``pair`` "00": L (the triangle Λ); "01": −x L
    (and "10" = −3 × "01"); "11": L (6L − 2L² − 3)."""
    overlap = jnp.maximum(1.0 - jnp.abs(x), 0.0)
    if pair == "00":
        return overlap
    if pair == "01":
        return -x * overlap
    if pair == "11":
        return overlap * (6.0 * overlap - 2.0 * overlap * overlap - 3.0)
    raise ValueError(f"pair: {pair!r}")


# The distinct transport kernels of each profile: the constant profile's one, the linear
# profile's three (w^{10} = −3 w^{01}).
PAIRS = {1: ("00",), 2: ("00", "01", "11")}
# Per profile, how they couple coefficients: (receiving coefficient a, source
# coefficient b, index of the kernel in PAIRS, factor).
TERMS = {
    1: ((0, 0, 0, 1.0),),
    2: ((0, 0, 0, 1.0), (0, 1, 1, 1.0), (1, 0, 1, -3.0), (1, 1, 2, 1.0)),
}


def clip_averages(field, n_z: int):
    """A layered field (patterns, n_m·n_z, …) with its layer averages clipped at 0 (FFT
    round-off of non-negative light); the slopes, signed, are left as they are."""
    if field.shape[1] == n_z:
        return jnp.maximum(field, 0.0)
    return jnp.concatenate([jnp.maximum(field[:, :n_z], 0.0), field[:, n_z:]], axis=1)


def transport_weights(v, refl, n_z: int, delta: int, pair: str = "00"):
    """W_δ at u = v·Δ (v in layer thicknesses) for faces of reflectance ``refl``
    (broadcastable to v; 0 for absorbing faces); ``pair`` the profiles' coefficient
    (:func:`_overlap`; "00" is the layer average's). At most two wraps m overlap; a wrap
    shifts the unfolded height by h and keeps the profile's orientation."""
    x = v - delta
    m_a = jnp.floor(x / n_z)
    total = jnp.zeros_like(v)
    for m in (m_a, m_a + 1.0):
        w = _overlap(x - m * n_z, pair)
        total = total + jnp.where(m >= 0, _wraps(m, refl) * w, 0.0)
    return total


# Below this optical length of an interval the slope's integrals take the Gauss rule
# (the closed form cancels there); above it the closed form (the rule's error grows as
# (σt ℓ)⁸: 1e-3 at σt ℓ = 6).
_CLOSED_FORM_FROM = 1.0


def _slope_integrals(lo, hi, centre, h: float, sigma_t):
    """∫_lo^hi (y − c) e^{−σt (h − y)} dy and ∫_lo^hi (y − c) e^{−σt y} dy, c = ``centre``:
    a 4-point Gauss rule where σt (hi − lo) < _CLOSED_FORM_FROM, else the closed forms
    [e^{−σt(h−y)} ((y − c)/σt − 1/σt²)] and [−e^{−σt y} ((y − c)/σt + 1/σt²)]."""
    half = 0.5 * (hi - lo)
    gauss_a = gauss_b = 0.0
    for node, weight in zip(_GAUSS4[0], _GAUSS4[1], strict=True):
        y = lo + half * (node + 1.0)
        wq = half * weight * (y - centre)
        gauss_a = gauss_a + wq * jnp.exp(-sigma_t * (h - y))
        gauss_b = gauss_b + wq * jnp.exp(-sigma_t * y)
    inv = 1.0 / sigma_t

    def upper(y):
        return jnp.exp(-sigma_t * (h - y)) * ((y - centre) * inv - inv * inv)

    def lower(y):
        return -jnp.exp(-sigma_t * y) * ((y - centre) * inv + inv * inv)

    thick = sigma_t * (hi - lo) >= _CLOSED_FORM_FROM
    return (
        jnp.where(thick, upper(hi) - upper(lo), gauss_a),
        jnp.where(thick, lower(hi) - lower(lo), gauss_b),
    )


def camera_integrals(u, h: float, n_z: int, layer: int, refl, sigma_t, moment: int = 0):
    """(A, B): Σ_m R^m ∫ e^{−σt (h − y)} dy and Σ_m R^m ∫ e^{−σt y} dy over the heights
    y ∈ [0, h] reached (as stored up-going light, after m wraps) by rays leaving source
    layer ``layer`` (uniform, unit density) with vertical travel ``u``. The camera's
    weight of these rays is p(μ)·A + p(−μ)·B. Only ``sigma_t`` carries a derivative.
    ``moment`` 1: the same for the source profile φ_1 = 2ξ − 1 (ξ the height within the
    layer, :func:`_slope_integrals`)."""
    dz = h / n_z
    a0 = layer * dz + u
    m0 = jnp.floor(a0 / h)
    a_sum = jnp.zeros_like(a0 * sigma_t)
    b_sum = jnp.zeros_like(a_sum)
    for m in (m0, m0 + 1.0):
        a = a0 - m * h
        lo = jnp.clip(a, 0.0, h)
        hi = jnp.clip(a + dz, 0.0, h)
        rm = _wraps(m, refl)
        if moment == 0:
            span = -jnp.expm1(-sigma_t * (hi - lo)) / sigma_t  # 0 where the interval is empty
            a_sum = a_sum + rm * jnp.exp(-sigma_t * (h - hi)) * span
            b_sum = b_sum + rm * jnp.exp(-sigma_t * lo) * span
            continue
        slope_a, slope_b = _slope_integrals(lo, hi, a + 0.5 * dz, h, sigma_t)
        a_sum = a_sum + rm * (2.0 / dz) * slope_a
        b_sum = b_sum + rm * (2.0 / dz) * slope_b
    return a_sum, b_sum


class SlabBounce(eqx.Module):
    """One bounce of the layered slab model, built once per (σt, σs, g).

    ``bounce(q) -> (q_next, image)`` maps the layered source Q_k (σs included),
    Float[Array, "patterns n_m·n_z n_mu n_theta H W"], to Q_{k+1} and the image I_{k+1}
    Float[Array, "patterns H W"]; :meth:`step` also returns the transported light field
    L_k. The layer axis holds the profile's coefficients moment-major: index a·n_z + l
    is coefficient a of layer l (a = 0 the layer average; a = 1, with the linear
    profile, n_m = 2, the slope's coefficient of φ_1 = 2ξ − 1). Pure; linear in q up to
    the clipping of FFT round-off below 0 (``clip``, on in the march, on the averages
    only); :attr:`linear` is the same step without it, exactly linear (the operator of a
    Krylov solve, whose vectors have signs).

    The elevation nodes are transported in blocks of ``mu_block`` (the kernels' leading
    axis; one block: every node at once): a block's spectra are all a bounce holds at
    once, beside the source, its field and the kernels (a 128×128 tank of 16 θ bins,
    16 μ nodes and 2 linear layers: 270 MB of spectra per pattern in one block).

    Attributes:
        transport_f: rfft2 of the kernels of W^{ab}_δ, δ = −(n_z−1)..n_z−1 (index
            δ + n_z − 1), per distinct profile pair (:data:`PAIRS`), per block of μ
            nodes: (blocks, pairs, 2 n_z − 1, mu_block, n_theta, 2H, W + 1).
        camera_f: rfft2 of the camera kernels per source coefficient and layer
            (blocks, n_m·n_z, mu_block, n_theta, 2H, W + 1), σs and T included.
        fft_rows: the rows of the FFT domain: 2H (zero-padded: the tank's walls), or H
            (a grid periodic in y: :mod:`lightfield_jax.forward.slab_cell`).
        mix_even, mix_odd: ½(M⁺ ± M⁻) (σs included), M^± the discrete phase matrices
            from up-going directions into up-going (⁺) and down-going (⁻) ones.
        clip: whether images and fields are clipped at 0 (FFT round-off of non-negative
            sources).
    """

    transport_f: Complex[Array, "blocks pairs kernels mu_block n_theta fy fx"]
    camera_f: Complex[Array, "blocks n_m_z mu_block n_theta fy fx"]
    mix_even: Float[Array, "a a"]
    mix_odd: Float[Array, "a a"]
    height: int = eqx.field(static=True)
    width: int = eqx.field(static=True)
    fft_rows: int = eqx.field(static=True)  # 2H (zero-padded), or H on a grid periodic in y
    clip: bool = eqx.field(static=True, default=True)

    @property
    def n_m(self) -> int:
        """Coefficients of the depth profile per layer (1 constant, 2 linear)."""
        return 2 if self.transport_f.shape[1] == len(PAIRS[2]) else 1

    @property
    def n_z(self) -> int:
        return self.camera_f.shape[1] // self.n_m

    @property
    def linear(self) -> SlabBounce:
        """This step without clipping: exactly linear in q."""
        return dataclasses.replace(self, clip=False)

    def __call__(self, q):
        q_next, image, _ = self.step(q)
        return q_next, image

    def _clipped(self, a):
        return jnp.maximum(a, 0.0) if self.clip else a

    def step(self, q):
        """(Q_{k+1}, I_{k+1}, L_k) from Q_k."""
        field, image_f = self._transport_blocks(q)
        image = jnp.fft.irfft2(image_f, s=(self.fft_rows, 2 * self.width))
        return self.scatter(field), self._clipped(image[..., : self.height, : self.width]), field

    def transport(self, q):
        """L_l = Σ_l' K_{l−l'} ⊛ Q_l' (patterns, n_m·n_z, n_mu, n_theta, H, W)."""
        return self._transport_blocks(q)[0]

    def _transport_blocks(self, q):
        """(L_k, the image's spectrum) from Q_k, one block of μ nodes at a time."""
        blocks = self.transport_f.shape[0]
        if blocks == 1:
            return self._block(q, self.transport_f[0], self.camera_f[0])
        p, coefficients, n_mu = q.shape[:3]
        size = n_mu // blocks
        split = q.reshape((p, coefficients, blocks, size) + q.shape[3:])

        def block(image_f, parts):
            field, more = self._block(*parts)
            return image_f + more, field

        image_f = jnp.zeros(
            (p, self.fft_rows, self.width + 1), jnp.result_type(q.dtype, jnp.complex64)
        )
        image_f, fields = jax.lax.scan(
            block, image_f, (jnp.moveaxis(split, 2, 0), self.transport_f, self.camera_f)
        )
        return jnp.moveaxis(fields, 0, 2).reshape(q.shape), image_f

    def _block(self, q, transport_f, camera_f):
        """(field, image spectrum) of the μ nodes of ``q`` with their kernels."""
        q_f = jnp.fft.rfft2(q, s=(self.fft_rows, 2 * self.width))
        image_f = einsum("plmnyx,lmnyx->pyx", q_f, camera_f)
        return self._transport_f(q_f, transport_f), image_f

    def _transport_f(self, q_f, transport_f):
        """The transported field from the sources' rfft2 and one block's kernels."""
        n_z = self.n_z
        out = jnp.zeros_like(q_f)
        for a, b, pair, factor in TERMS[self.n_m]:
            source = q_f[:, b * n_z : (b + 1) * n_z]
            if factor != 1.0:
                source = factor * source  # once per bounce, not per kernel
            for delta in range(-(n_z - 1), n_z):
                lo, hi = max(delta, 0), n_z + min(delta, 0)  # receiving layers
                k = transport_f[pair, delta + n_z - 1]
                out = out.at[:, a * n_z + lo : a * n_z + hi].add(
                    k * source[:, lo - delta : hi - delta]
                )
        field = jnp.fft.irfft2(out, s=(self.fft_rows, 2 * self.width))
        field = field[..., : self.height, : self.width]
        return clip_averages(field, n_z) if self.clip else field

    def scatter(self, field):
        """Q_l = M⁺ L_l + M⁻ L_{n_z−1−l} per coefficient, through the layer-mirror sums
        and differences (each costs one matmul on half the layers). The mirror reverses
        the height within a layer, so a slope's mirror image enters with its sign
        flipped: Q¹_l = M⁺ L¹_l − M⁻ L¹_{n_z−1−l}."""
        if self.n_m == 1:
            return self._scatter_layers(field, 1.0)
        n_z = self.n_z
        return jnp.concatenate(
            [
                self._scatter_layers(field[:, :n_z], 1.0),
                self._scatter_layers(field[:, n_z:], -1.0),
            ],
            axis=1,
        )

    def _scatter_layers(self, field, mirror: float):
        p, n_z = field.shape[:2]
        flat = field.reshape((p, n_z, -1) + field.shape[-2:])
        even_m, odd_m = (
            (self.mix_even, self.mix_odd) if mirror > 0 else (self.mix_odd, self.mix_even)
        )
        if n_z == 1:
            return einsum("ab,plbyx->playx", 2.0 * even_m, flat).reshape(field.shape)
        half = (n_z + 1) // 2
        rev = flat[:, ::-1]
        even = einsum("ab,plbyx->playx", even_m, (flat + rev)[:, :half])
        odd = einsum("ab,plbyx->playx", odd_m, (flat - rev)[:, :half])
        lower = (even - odd)[:, ::-1][:, n_z % 2 :]
        return jnp.concatenate([even + odd, lower], axis=1).reshape(field.shape)
