"""The homogeneous medium (docs/model.md section 2); its phase function is
:mod:`lightfield_jax.scene.phase` (re-exported here).

Units: coefficients are per pixel (lengths are in pixels). Angles are radians.
"""

from __future__ import annotations

import math
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from lightfield_jax.checks import check_number, number_problem
from lightfield_jax.scene.phase import phase_function as phase_function
from lightfield_jax.scene.phase import phase_integral as phase_integral

PhaseConvention = Literal["paper", "normalized"]
PHASE_CONVENTIONS: tuple[str, ...] = ("paper", "normalized")
# The convention of the files (a capture file's ``fit.phase``, a simulate config's
# ``medium.phase``) and of the command line where they say none: real media (milk,
# σs near σt and g near 0.8) have ρ = ω·A(g) ≥ 1 under ``paper``, which has no finite
# answer for them; ``normalized`` conserves energy in the plane and describes every
# medium. The Python objects (Medium, FitOptions) keep the paper's own convention.
FILE_PHASE = "normalized"
# The largest σt (per pixel) the renders hold: light lost within a fraction of a pixel
# is a pixel average there, measured 0.6 % low at 100, 6 % at 1000 and 46 % at 1e4, then
# 0 (and a slab's second bounce NaN past 1e19, σs² beyond float32). No capture resolves
# a decay within 0.01 px.
MAX_SIGMA_T = 100.0


def is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


class Medium(eqx.Module):
    """A homogeneous scattering medium.

    Attributes:
        sigma_t: extinction coefficient 0 < σt ≤ :data:`MAX_SIGMA_T` (per pixel).
        sigma_s: scattering coefficient 0 ≤ σs ≤ σt (per pixel).
        g: Henyey-Greenstein asymmetry, −1 < g < 1.
        phase: ``"paper"`` (p used as is in the plane, the paper's model; each bounce
            multiplies in-plane energy by at most ρ = ω·A(g), which may be ≥ 1) or
            ``"normalized"`` (redistribution by p/A(g), ρ = ω < 1). The camera term
            σs·p(π/2) is the same under both.

    The physical values are JAX arrays (traced under ``jit``): new values never
    recompile. Concrete values are validated on construction.
    """

    sigma_t: Float[Array, ""]
    sigma_s: Float[Array, ""]
    g: Float[Array, ""]
    phase: str = eqx.field(static=True, default="paper")

    def __init__(self, sigma_t, sigma_s, g, phase: PhaseConvention = "paper"):
        if not isinstance(phase, str) or phase not in PHASE_CONVENTIONS:
            raise ValueError(
                f"medium.phase: unknown phase convention {phase!r}; "
                f"expected one of {', '.join(PHASE_CONVENTIONS)}"
            )
        # Concrete values are checked on the host (NumPy): eager JAX operations would
        # each compile a small program the first time (a few hundred ms per process).
        # A single real number each (True, "0.2", 0.2j, [0.2] or None are refused):
        # lightfield_jax.checks, as every constructor of the API.
        given = {"sigma_t": sigma_t, "sigma_s": sigma_s, "g": g}
        concrete = {}
        for name, value in given.items():
            if is_concrete(value):
                check_number(value, f"medium.{name}")
                concrete[name] = np.asarray(value, dtype=np.float64)
        if "sigma_t" in concrete and float(np.min(concrete["sigma_t"])) <= 0.0:
            raise ValueError(f"medium.sigma_t: must be > 0 (per pixel), got {sigma_t!r}")
        if "sigma_s" in concrete and "sigma_t" in concrete:
            s, t = concrete["sigma_s"], concrete["sigma_t"]
            if np.any(s < 0) or np.any(s > t * (1 + 1e-6)):
                raise ValueError(
                    f"medium.sigma_s: must satisfy 0 <= sigma_s <= sigma_t = {sigma_t!r}, "
                    f"got {sigma_s!r}"
                )
        if "g" in concrete and np.any(np.abs(concrete["g"]) >= 1.0):
            raise ValueError(f"medium.g: must satisfy -1 < g < 1, got {g!r}")
        # The values are stored in JAX's float dtype (float32 unless x64 is on): checked
        # there too (g = 0.99999999 becomes 1.0, sigma_t = 1e39 inf, 1e-300 zero: NaN
        # renders or errors deep inside).
        work = np.dtype(jnp.result_type(float))
        with np.errstate(over="ignore"):
            stored = {name: value.astype(work) for name, value in concrete.items()}
        for name, value in stored.items():
            if not np.all(np.isfinite(value)):
                raise ValueError(f"medium.{name}: {given[name]!r} overflows {work}")
        if "sigma_t" in stored and float(np.min(stored["sigma_t"])) < np.finfo(work).tiny:
            raise ValueError(
                f"medium.sigma_t: {sigma_t!r} underflows {work} (at least "
                f"{np.finfo(work).tiny:.3g} per pixel)"
            )
        if (
            "sigma_s" in stored
            and 0.0 < float(concrete["sigma_s"])
            and not (float(stored["sigma_s"]) >= np.finfo(work).tiny)
        ):
            # A subnormal σs is flushed to zero on the devices: all-zero images.
            raise ValueError(
                f"medium.sigma_s: {sigma_s!r} underflows {work} (0, or at least "
                f"{np.finfo(work).tiny:.3g} per pixel)"
            )
        if "g" in stored and np.any(np.abs(stored["g"]) >= 1.0):
            raise ValueError(f"medium.g: {g!r} rounds to +-1 in {work}; must satisfy -1 < g < 1")
        if "sigma_t" in concrete and float(np.max(concrete["sigma_t"])) > MAX_SIGMA_T:
            raise ValueError(
                f"medium.sigma_t: must be at most {MAX_SIGMA_T:g} per pixel (a mean free path "
                f"of {1 / MAX_SIGMA_T:g} px; denser, the light lost within a pixel renders "
                f"low, 6 % at 1000, then 0), got {sigma_t!r}"
            )
        self.sigma_t = jnp.asarray(sigma_t, dtype=jnp.result_type(float))
        self.sigma_s = jnp.asarray(sigma_s, dtype=jnp.result_type(float))
        self.g = jnp.asarray(g, dtype=jnp.result_type(float))
        self.phase = phase

    @property
    def sigma_a(self) -> Float[Array, ""]:
        """Absorption coefficient σa = σt − σs."""
        return self.sigma_t - self.sigma_s

    @property
    def albedo(self) -> Float[Array, ""]:
        """Single-scattering albedo ω = σs/σt."""
        return self.sigma_s / self.sigma_t

    @property
    def rho(self) -> Float[Array, ""]:
        """Bound on the per-bounce in-plane energy ratio: ω·A(g) (paper) or ω (normalized)."""
        if self.phase == "paper":
            return self.albedo * phase_integral(self.g)
        return self.albedo


def bounces_for_tolerance(
    rho: float, tolerance: float = 1e-4, max_bounces: int = 500, *, paper: bool = True
) -> int:
    """Smallest K whose neglected tail Σ_{k>K} I_k is at most ``tolerance`` of the total.

    In-plane energy of bounce k is at most ρ^{k−1} times that of the single scatter, so
    the relative tail after K bounces is at most ρ^K / (1 − ρ). Raises ``ValueError``
    when ρ ≥ 1 (the series does not converge: there is no such K), with advice for ρ
    the paper's ω·A(g) (``paper``) or the albedo ω (``phase: normalized``, a slab).
    """
    # rho = albedo*A(g) >= 0 (a negative rho would give one bounce)
    rho = check_number(rho, "rho", low=0.0, allow_inf=True)
    if number_problem(tolerance, low=0.0, high=1.0, low_open=True, high_open=True) is not None:
        raise ValueError(f"bounce tolerance must be in (0, 1), got {tolerance!r}")
    if rho >= 1.0 and not paper:
        raise ValueError(
            f"bounces: auto is impossible: rho = albedo = {rho:.4f}: a medium that absorbs "
            "nothing (sigma_s = sigma_t) has no bound on its bounce series' tail; give an "
            "explicit bounce count, or sigma_s < sigma_t"
        )
    if rho >= 1.0:
        raise ValueError(
            f"bounces: auto is impossible: rho = albedo*A(g) = {rho:.4f} >= 1, so the "
            "bounce series of the 'paper' phase convention diverges for this medium. "
            "Use phase: normalized, or give an explicit bounce count (the result will "
            "say that the series does not converge)."
        )
    if rho == 0.0:
        return 1
    k = math.ceil(math.log(tolerance * (1.0 - rho)) / math.log(rho))
    k = max(1, k)
    if k > max_bounces:
        raise ValueError(
            f"bounces: auto needs {k} bounces for rho = {rho:.6f} at tolerance "
            f"{tolerance:g} (more than {max_bounces}); raise the tolerance"
        )
    return k
