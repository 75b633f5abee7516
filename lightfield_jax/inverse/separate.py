"""Direct/global separation of a shifted-stripe capture (Nayar et al. 2006; docs/model.md
section 5).

Each pixel is seen under N shifted stripe patterns. Over the shifts it takes its
maximum Imax when its own stripe is lit and its minimum Imin when it is dark. With lit
fraction a (lit rows / period) and black level b (a dark stripe still emits b times a
lit one),

    Imax = D + (a + b(1 − a))·M,     Imin = b·D + (a + b(1 − a))·M,

so D = (Imax − Imin)/(1 − b) and M = (Imin − b·D)/(a + b(1 − a)). The paper's form,
D = Imax − Imin and M = 2·Imin, is the case a = ½, b = 0.

Here D ("direct") is the light scattered toward the camera by the beam of the pixel's
own stripe, i.e. the single scatter I_1, and M ("multiple", Nayar's global component)
is the multiple scatter Σ_{k≥2} I_k under full illumination. The split is exact only
when the stripe period is small against the mean free path 1/σt; otherwise D keeps part
of the multiple scatter (docs/model.md section 6 measures this bias).
"""

from __future__ import annotations

import math
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from lightfield_jax.checks import check_float_range, masked_to_nan, number_problem

SeparationMethod = Literal["general", "paper"]
SEPARATION_METHODS: tuple[str, ...] = ("general", "paper")


class Separation(eqx.Module):
    """The direct/global split of a stripe capture.

    Every field has the shape of one input image, ``(height, width)`` or
    ``(height, width, channels)``, in the images' units (after dark-frame subtraction),
    in the image frame of docs/model.md section 1.

    Attributes:
        direct: D, the direct (single-scatter) image.
        multiple: M, the global (multiple-scatter) image under full illumination.
        imax: Imax, the per-pixel maximum over the shifts.
        imin: Imin, the per-pixel minimum over the shifts.
    """

    direct: Float[Array, "height width *channels"]
    multiple: Float[Array, "height width *channels"]
    imax: Float[Array, "height width *channels"]
    imin: Float[Array, "height width *channels"]


@eqx.filter_jit
def _split(
    images: Float[Array, "shifts height width *channels"],
    dark_frame: Float[Array, "..."],
    lit_fraction: Float[Array, ""],
    black_level: Float[Array, ""],
) -> Separation:
    images = images - dark_frame
    imax = jnp.max(images, axis=0)
    imin = jnp.min(images, axis=0)
    direct = (imax - imin) / (1.0 - black_level)
    multiple = (imin - black_level * direct) / (lit_fraction + black_level * (1.0 - lit_fraction))
    return Separation(direct=direct, multiple=multiple, imax=imax, imin=imin)


def real_dtype(dtype) -> bool:
    """Integers or floats (NumPy's or JAX's, bfloat16 included), not bool or complex."""
    return jnp.issubdtype(dtype, jnp.integer) or jnp.issubdtype(dtype, jnp.floating)


def _as_float(x: ArrayLike, name: str = "images") -> Float[Array, "..."]:
    dtype = x.dtype if hasattr(x, "dtype") else np.asarray(x).dtype
    if not real_dtype(dtype):  # complex, bool and object images are no light
        raise ValueError(f"separate.{name}: must be real numbers, got dtype {dtype}")
    check_float_range(x, f"separate.{name}")  # 1e300 is inf in float32
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        # Camera frames are often unsigned integers: convert before subtracting.
        x = x.astype(jnp.result_type(float))
    return x


def _fraction(value, name: str, *, closed_low: bool) -> float:
    # True and "0.5" are not fractions; NaN and inf are out of the range below.
    problem = number_problem(value)
    if problem is not None and not problem.startswith("must be finite"):
        raise ValueError(f"separate.{name}: {problem}")
    v = float(value)
    low_ok = v >= 0.0 if closed_low else v > 0.0
    if not (math.isfinite(v) and low_ok and v < 1.0):
        interval = "[0, 1)" if closed_low else "(0, 1)"
        raise ValueError(f"separate.{name}: must be in {interval}, got {value!r}")
    return v


def separate(
    images: Float[ArrayLike, "shifts height width *channels"],
    *,
    lit_fraction: float = 0.5,
    black_level: float = 0.0,
    dark_frame: Float[ArrayLike, "..."] | None = None,
    method: SeparationMethod = "general",
) -> Separation:
    """Separate a shifted-stripe capture into direct and global (multiple-scatter) images.

    Arguments:
        images: the N ≥ 2 shifted stripe images, shape ``(shifts, height, width)`` or
            ``(shifts, height, width, channels)``, in any linear camera units. Integer
            frames are converted to the default float dtype. Every pixel must be lit in
            at least one shift and dark in at least one (e.g. one shift per row of the
            stripe period). A numpy masked array's masked values count as NaN.
        lit_fraction: a = lit rows / period of the stripes, in (0, 1).
        black_level: b, the projector's dark-stripe level relative to a lit stripe,
            in [0, 1).
        dark_frame: camera dark frame (projector off), subtracted from every image
            first. Any shape that broadcasts to ``images`` (one frame, one per shift,
            or a per-channel level).
        method: ``"general"`` (the formulas above with a and b) or ``"paper"`` (the
            paper's D = Imax − Imin, M = 2·Imin, which requires a = ½ and b = 0).

    Returns:
        A :class:`Separation` (D, M, Imax, Imin). NaN pixels stay NaN; a stack with
        no pixel finite in every image is refused.

    Jit-compiled once per input shape and dtype; new values of a and b do not
    recompile. Raises ``ValueError`` for malformed inputs, naming the problem.
    """
    if method not in SEPARATION_METHODS:
        raise ValueError(
            f"separate.method: unknown method {method!r}; "
            f"expected one of {', '.join(SEPARATION_METHODS)}"
        )
    a = _fraction(lit_fraction, "lit_fraction", closed_low=False)
    b = _fraction(black_level, "black_level", closed_low=True)
    if method == "paper" and (a != 0.5 or b != 0.0):
        raise ValueError(
            "separate.method: 'paper' (D = Imax - Imin, M = 2*Imin) assumes lit_fraction 0.5 "
            f"and black_level 0, got lit_fraction={lit_fraction!r}, "
            f"black_level={black_level!r}; use method='general'"
        )
    images = _as_float(masked_to_nan(images))
    if images.ndim not in (3, 4):
        raise ValueError(
            "separate.images: must have shape (shifts, height, width) or "
            f"(shifts, height, width, channels), got shape {images.shape}"
        )
    if images.shape[0] < 2:
        raise ValueError(
            f"separate.images: need at least 2 shifted images to form Imax and Imin, got "
            f"{images.shape[0]}"
        )
    dark = (
        jnp.zeros((), images.dtype) if dark_frame is None else _as_float(dark_frame, "dark_frame")
    )
    try:
        broadcast_ok = np.broadcast_shapes(dark.shape, images.shape) == images.shape
    except ValueError:
        broadcast_ok = False
    if not broadcast_ok:
        raise ValueError(
            f"separate.dark_frame: shape {dark.shape} does not broadcast to the images' "
            f"shape {images.shape} (shifts, height, width[, channels])"
        )
    # Inside a traced loss there is no value to test.
    concrete = not any(isinstance(x, jax.core.Tracer) for x in (images, dark))
    if concrete and not bool(jnp.all(jnp.isfinite(images - dark), axis=0).any()):
        raise ValueError(
            f"separate.images: no pixel is finite in every one of the {images.shape[0]} "
            "images less the dark frame (NaN or Inf everywhere): nothing to separate"
        )
    dtype = jnp.result_type(images.dtype, dark.dtype)
    return _split(
        images.astype(dtype), dark.astype(dtype), jnp.asarray(a, dtype), jnp.asarray(b, dtype)
    )
