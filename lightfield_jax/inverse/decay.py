"""σt from the decay of the direct (single-scatter) image (docs/model.md section 6).

Light entering a wall heading θ0 reaches a point x after a path s(x) through the
medium, the distance from x back to the entry wall along −ω(θ0), ω(θ) = (cos θ, sin θ).
The single scatter there is c·exp(−σt·s) (docs/model.md section 4), so the direct image
follows

    D(x) ≈ c_ℓ · exp(−σt · s(x)),

with one amplitude c_ℓ per transverse line ℓ: the wall cell [ℓ, ℓ+1) (a pixel row of
the left/right wall, a pixel column of the top/bottom wall) where the backward ray from
the pixel centre meets the entry wall. For a pixel centre (x, y) = (c+½, r+½) of a
W × H frame, s is x/cos θ0 (left wall), (x − W)/cos θ0 (right), y/sin θ0 (top) or
(y − H)/sin θ0 (bottom). Per-line amplitudes absorb whatever is constant along a line
of propagation (stripe coverage of a row, projector falloff across the wall) and any
constant offset of s, so the frame need not start exactly at the medium's wall. The
pixel average of an exponential is the exponential at the pixel centre times a constant,
which the amplitudes absorb too.

At oblique incidence the shadow edge from the end of the entry wall cuts pixels, whose
lit fraction varies along a line: pixels not lit through the wall over their whole
footprint are not used. Stripe edges cut pixels in the same way, and nothing here knows
the stripes: fit the separated direct image (every wall cell lit in some shift) or a
full-illumination image, not a single oblique stripe image.

The fit is a separable least-squares problem (variable projection): for a given σt the
best amplitudes are a weighted linear fit per line, so the nonlinear solve
(optimistix Levenberg–Marquardt) is over σt alone, parametrised as σt = exp(v) so that
it stays positive. It starts from a weighted log-linear fit on the pixels above
``min_fraction`` of the peak and refines in linear space on the pixels whose *modelled*
signal (from that start) is above it, with Poisson-like weights 1/model (noise variance
∝ signal). Selecting and weighting on the model rather than on the noisy data keeps σt
unbiased and its standard error calibrated (tests/test_decay.py checks both).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from lightfield_jax.checks import check_float_range, check_number, masked_to_nan, number_problem
from lightfield_jax.inverse.separate import real_dtype
from lightfield_jax.scene.illumination import (
    INWARD_DEG,
    WALLS,
    Wall,
    along_x,
)
from lightfield_jax.scene.illumination import (
    check_direction as _check_direction,
)
from lightfield_jax.scene.illumination import (
    checked_direction as _direction,
)
from lightfield_jax.scene.medium import is_concrete

# A log-linear start below this (data that do not decay) is raised to it: far smaller
# than any σt whose decay a frame can resolve, and still positive for the log.
_SIGMA_T_FLOOR = 1e-6


class DecayFit(eqx.Module):
    """The result of :func:`fit_decay`.

    Attributes:
        sigma_t: extinction coefficient σt (per pixel).
        sigma_t_stderr: its standard error, √(s²·[(JᵀJ)⁻¹]_σσ) from the Jacobian of the
            weighted residual over (σt, c_ℓ), s² = residual sum of squares/(n − p);
            NaN when n ≤ p.
        amplitude: c_ℓ per transverse line (entry-wall cell), the direct image's value
            extrapolated to the entry wall (s = 0), in the image's units; NaN for lines
            with no usable pixel.
        initial_sigma_t: the weighted log-linear estimate the solve started from.
        converged: whether the solve succeeded (``result`` is successful) on an
            identifiable problem, with σt above its floor (light that does not decay
            away from the wall leaves it there).
        result: the optimistix result (``optx.RESULTS[fit.result]`` is its message).
        iterations: Levenberg–Marquardt steps taken.
        residual: root-mean-square of D − model over the usable pixels (image units).
        n_pixels: usable pixels: finite, in the mask, unsaturated, lit through the entry
            wall over their whole footprint, on a line that has a pixel of at least
            ``min_fraction`` of the brightest such pixel, and modelled (by the
            log-linear start) at least that bright.
        n_lines: transverse lines with at least one usable pixel.
    """

    sigma_t: Float[Array, ""]
    sigma_t_stderr: Float[Array, ""]
    amplitude: Float[Array, " lines"]
    initial_sigma_t: Float[Array, ""]
    converged: Bool[Array, ""]
    result: optx.RESULTS
    iterations: Int[Array, ""]
    residual: Float[Array, ""]
    n_pixels: Int[Array, ""]
    n_lines: Int[Array, ""]


def entry_coordinates(
    height: int, width: int, entry: Wall, direction_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Path length s and wall coordinate u of every pixel centre (float64, (height, width)).

    s is the distance (pixels) from the pixel centre (c+½, r+½) back along −ω(θ0) to the
    entry wall; u is where that backward ray meets the wall (y on the left/right wall,
    x on the top/bottom wall, pixels). The ray misses the entry wall (the point is not
    lit through it) where u lies outside [0, height) or [0, width).
    """
    t0 = math.radians(direction_deg)
    cos0, sin0 = math.cos(t0), math.sin(t0)
    y, x = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    if along_x(entry):
        s = (x - (0.0 if entry == "left" else width)) / cos0
        return s, y - s * sin0
    s = (y - (0.0 if entry == "top" else height)) / sin0
    return s, x - s * cos0


def _segment_sum(values, line, n_lines: int):
    return jax.ops.segment_sum(values, line, num_segments=n_lines)


def _project(sigma_t, d, w2, s, line, n_lines: int):
    """Best amplitudes per line for a given σt (weighted linear least squares)."""
    e = jnp.exp(-sigma_t * s)
    num = _segment_sum(w2 * d * e, line, n_lines)
    den = _segment_sum(w2 * e * e, line, n_lines)
    return num / jnp.where(den > 0, den, 1.0), e


@eqx.filter_jit
def _fit(
    direct: Float[Array, "height width"],
    mask: Bool[Array, "height width"],
    s: Float[Array, "height width"],
    line: Int[Array, "height width"],
    on_wall: Bool[Array, "height width"],
    saturation: Float[Array, ""],
    min_fraction: Float[Array, ""],
    n_lines: int,
    max_steps: int,
) -> DecayFit:
    d = direct.reshape(-1)
    s = s.reshape(-1).astype(d.dtype)
    line = line.reshape(-1)
    candidate = jnp.isfinite(d) & mask.reshape(-1) & on_wall.reshape(-1) & (d < saturation)
    peak = jnp.max(jnp.where(candidate, d, -jnp.inf))
    # Work in units of the peak, and with s measured from each line's first candidate
    # pixel, so that the residual is scale-free and exp(−σt s) starts near 1 on a line.
    dn = jnp.where(candidate, d / jnp.where(peak > 0, peak, 1.0), 0.0)
    s_ref = jax.ops.segment_min(jnp.where(candidate, s, jnp.inf), line, num_segments=n_lines)
    s_ref = jnp.where(jnp.isfinite(s_ref), s_ref, 0.0)
    sl = jnp.where(candidate, s - s_ref[line], 0.0)

    # Log-linear start on the pixels at least min_fraction of the peak: log D = log c_ℓ
    # − σt s with one intercept per line, weights ∝ D (var(log D) ∝ 1/D for Poisson-like
    # noise). Lines with no such pixel (dark rows) are not used at all.
    q = jnp.where(candidate & (peak > 0) & (dn >= min_fraction), dn, 0.0)
    logd = jnp.log(jnp.where(q > 0, dn, 1.0))
    q_line = _segment_sum(q, line, n_lines)
    lit_line = q_line > 0
    q_line = jnp.where(lit_line, q_line, 1.0)
    s_mean = _segment_sum(q * sl, line, n_lines) / q_line
    y_mean = _segment_sum(q * logd, line, n_lines) / q_line
    ds = sl - s_mean[line]
    den = jnp.sum(q * ds**2)
    sigma0 = -jnp.sum(q * ds * (logd - y_mean[line])) / jnp.where(den > 0, den, 1.0)
    sigma0 = jnp.maximum(sigma0, _SIGMA_T_FLOOR)

    # The refinement uses the pixels whose *modelled* signal is at least min_fraction
    # of the peak (selecting on the noisy data would keep the pixels that noise lifted
    # above the threshold and bias σt low), weighted by the start's model
    # (Poisson-like, var ∝ signal; weights from the data would bias the fit too).
    model0 = jnp.exp(y_mean[line] - sigma0 * ds)
    used = candidate & lit_line[line] & (model0 >= min_fraction)
    w2 = jnp.where(used, 1.0 / model0, 0.0)
    w = jnp.sqrt(w2)
    dn = jnp.where(used, dn, 0.0)
    per_line = _segment_sum(used.astype(jnp.int32), line, n_lines)
    n_pixels = jnp.sum(per_line)
    n_used_lines = jnp.sum(per_line > 0)

    def weighted_residual(log_sigma_t, _):
        amp, e = _project(jnp.exp(log_sigma_t), dn, w2, sl, line, n_lines)
        return w * (dn - amp[line] * e)

    # From the log-linear start each step gains about three digits, so eps^(1/3) leaves
    # σt accurate far below its statistical error; a √eps tolerance would push the
    # steps into round-off, where the trust region rejects them for long runs.
    tol = float(jnp.finfo(d.dtype).eps) ** (1 / 3)
    sol = optx.least_squares(
        weighted_residual,
        optx.LevenbergMarquardt(rtol=tol, atol=tol),
        jnp.log(sigma0),
        max_steps=max_steps,
        throw=False,
    )
    sigma_t = jnp.exp(sol.value)
    amp, e = _project(sigma_t, dn, w2, sl, line, n_lines)
    model = amp[line] * e
    r = w * (dn - model)

    # Marginal variance of σt with the amplitudes as nuisance parameters: JᵀJ is an
    # arrow matrix (each pixel depends on one amplitude), so [(JᵀJ)⁻¹]_σσ is the inverse
    # of the Schur complement J_σᵀJ_σ − Σ_ℓ (J_σᵀJ_ℓ)²/(J_ℓᵀJ_ℓ).
    j_sigma = w * model * sl
    j_amp = -w * e
    cross = _segment_sum(j_sigma * j_amp, line, n_lines)
    amp_norm = _segment_sum(j_amp**2, line, n_lines)
    schur = jnp.sum(j_sigma**2) - jnp.sum(
        jnp.where(amp_norm > 0, cross**2 / jnp.where(amp_norm > 0, amp_norm, 1.0), 0.0)
    )
    dof = n_pixels - 1 - n_used_lines
    s2 = jnp.where(dof > 0, jnp.sum(r**2) / jnp.maximum(dof, 1), jnp.nan)
    stderr = jnp.sqrt(s2 / schur)

    amplitude = jnp.where(per_line > 0, amp * jnp.exp(sigma_t * s_ref) * peak, jnp.nan)
    residual = peak * jnp.sqrt(jnp.sum(jnp.where(used, (dn - model) ** 2, 0.0)) / n_pixels)
    # σt at its floor is no answer: light that grows away from the wall (or stays flat)
    # ends there, a step from the start, in a "successful" solve
    at_floor = sigma_t < 2 * _SIGMA_T_FLOOR
    converged = (sol.result == optx.RESULTS.successful) & (n_pixels > n_used_lines) & ~at_floor
    return DecayFit(
        sigma_t=sigma_t,
        sigma_t_stderr=stderr,
        amplitude=amplitude,
        initial_sigma_t=sigma0,
        converged=converged,
        result=sol.result,
        iterations=sol.stats["num_steps"],
        residual=residual,
        n_pixels=n_pixels,
        n_lines=n_used_lines,
    )


def fit_decay(
    direct: Float[ArrayLike, "height width"],
    *,
    direction_deg: float | None = None,
    entry: Wall = "left",
    mask: Bool[ArrayLike, "height width"] | None = None,
    saturation: float | None = None,
    min_fraction: float = 0.02,
    max_steps: int = 256,
) -> DecayFit:
    """Fit σt to the decay of a direct image, D ≈ c_ℓ·exp(−σt·s) (see the module docs).

    Arguments:
        direct: the direct (single-scatter) image, ``(height, width)``, linear units, in
            the image frame (x = column, y = row); its frame is the medium's rectangle
            (crop to the medium first). Fit colour channels one at a time.
        direction_deg: propagation direction θ0 (degrees from +x toward +y); ``None``
            is the entry wall's inward normal (0° for the left wall, 180° right, 90°
            top, 270° bottom). It must point into the medium from ``entry``.
        entry: the wall the light enters through: left, right, top or bottom.
        mask: ``True`` where the pixel shows the medium; other pixels are not used.
        saturation: pixels at or above this value (clipped by the camera) are not used.
        min_fraction: signal level, as a fraction in (0, 1) of the brightest usable
            pixel, below which light is not used: lines with no pixel above it (the dark
            rows of a stripe image) and pixels modelled below it (the noise floor).
        max_steps: Levenberg–Marquardt step limit.

    NaN and infinite pixels are not used, nor the masked values of a numpy masked
    array. The fit runs in the wider of the image's
    dtype and JAX's default float dtype (float32, or float64 with x64 enabled);
    tolerances follow it (eps^(1/3)). The solve is jit-compiled once per image shape,
    dtype, entry-wall extent and ``max_steps``; new data, directions, thresholds and
    masks do not recompile.

    Returns:
        A :class:`DecayFit`. Non-convergence is reported in ``converged`` and ``result``,
        not raised.

    Raises:
        ValueError: for malformed arguments, or (on concrete data) when fewer than two
            usable pixels lie on any one line of propagation, so σt is not identifiable.
    """
    if not isinstance(entry, str) or entry not in WALLS:
        raise ValueError(f"fit_decay.entry: must be one of {', '.join(WALLS)}, got {entry!r}")
    if direction_deg is None:
        direction_deg = INWARD_DEG[entry]
    direction_deg = _direction(direction_deg, "fit_decay.direction_deg")
    _check_direction(entry, direction_deg, "fit_decay")
    direct = masked_to_nan(direct)
    dtype = direct.dtype if hasattr(direct, "dtype") else np.asarray(direct).dtype
    if not real_dtype(dtype):  # a bool image would be fitted (True as 1)
        raise ValueError(f"fit_decay.direct: must be real numbers, got dtype {dtype}")
    check_float_range(direct, "fit_decay.direct")
    direct = jnp.asarray(direct)
    # The fit runs in the wider of the image's and JAX's default float dtype: integer
    # frames become floats, and float32 data with x64 enabled is widened because
    # optimistix's Levenberg–Marquardt fails on mixed float32/float64 state.
    direct = direct.astype(jnp.promote_types(direct.dtype, jnp.result_type(float)))
    if direct.ndim != 2:
        raise ValueError(
            f"fit_decay.direct: must be one image of shape (height, width), got shape "
            f"{direct.shape}; fit colour channels one at a time"
        )
    if mask is None:
        mask = jnp.ones(direct.shape, bool)
    else:
        mask = jnp.asarray(mask)
        if mask.shape != direct.shape or mask.dtype != jnp.bool_:
            raise ValueError(
                f"fit_decay.mask: must be a boolean array of the image's shape {direct.shape}, "
                f"got {mask.dtype} of shape {mask.shape}"
            )
    saturation = (
        math.inf if saturation is None else check_number(saturation, "fit_decay.saturation")
    )
    min_fraction = check_number(min_fraction, "fit_decay.min_fraction")
    if not 0.0 < min_fraction < 1.0:
        raise ValueError(f"fit_decay.min_fraction: must be in (0, 1), got {min_fraction!r}")
    if number_problem(max_steps, integer=True, low=1) is not None:
        raise ValueError(f"fit_decay.max_steps: must be a positive integer, got {max_steps!r}")

    height, width = direct.shape
    s, u = entry_coordinates(height, width, entry, direction_deg)
    across = along_x(entry)
    n_lines = height if across else width
    line = np.clip(np.floor(u), 0, n_lines - 1).astype(np.int32)
    # u is linear across a pixel, spanning u ± half: a pixel is fully lit through the
    # wall only if all of that span meets it (oblique light leaves partly lit pixels
    # along the shadow edge from the wall's end, whose coverage varies along a line).
    t0 = math.radians(direction_deg)
    half = 0.5 * (1.0 + abs(math.tan(t0) if across else 1.0 / math.tan(t0)))
    on_wall = (u - half >= -1e-9) & (u + half <= n_lines + 1e-9)
    dtype = direct.dtype
    fit = _fit(
        direct,
        mask,
        s,
        line,
        on_wall,
        jnp.asarray(saturation, dtype),
        jnp.asarray(min_fraction, dtype),
        n_lines,
        max_steps,
    )
    if is_concrete(fit.n_pixels) and int(fit.n_pixels) <= int(fit.n_lines):
        raise ValueError(
            f"fit_decay: sigma_t is not identifiable: {int(fit.n_pixels)} usable pixels on "
            f"{int(fit.n_lines)} lines of propagation from the {entry} wall; at least one "
            "line needs two. Pixels are not used when NaN, outside the mask, at or above "
            "saturation, too dim (see min_fraction), or not wholly lit through the "
            f"{entry} wall by light heading {direction_deg:g} deg"
        )
    return fit
