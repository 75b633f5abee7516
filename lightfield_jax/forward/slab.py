"""The slab geometry (docs/model.md section 7): a tank of depth h, modelled in 3-D, cheaply.

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
1/n_z (measured in docs/slab_depth.md; :func:`default_n_z` chooses n_z).

Units as the Monte Carlo oracle (:mod:`lightfield_jax.reference.montecarlo_slab`): the sheet
has unit irradiance (power per unit area normal to θ0), lengths are pixels, σ per
pixel, images are power per unit area of the top face (times the gain).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from lightfield_jax.forward.first_scatter import kernel_nodes
from lightfield_jax.forward.render import _count_trace, render_refined, unscattered_fluence
from lightfield_jax.forward.slab_layers import SlabBounce, camera_integrals, transport_weights
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import Illumination, scaled, source_moments

Boundary = Literal["absorbing", "refractive"]
BOUNDARIES = ("absorbing", "refractive")

# Gauss points across each polar ring of the kernels (the radial profile is an
# exponential times piecewise-linear depth factors: 3 points are exact to ~1e-6 on the
# rings that matter).
_RING_GAUSS = 3
# Sub-samples per azimuth bin of the triangle-weighted bin average of the phase matrix.
_PHASE_SUBSAMPLES = 8
_BALANCE_ITERATIONS = 4
# The most depth layers a slab model may use (Slab.n_z).
MAX_LAYERS = 16
# Below this albedo the orders a depth average gets wrong (k ≥ 3) carry little light.
DIM_ALBEDO = 0.3


def _positive_finite(value, what: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: must be a number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{what}: must be a finite number > 0, got {value!r}")
    return v


@dataclasses.dataclass(frozen=True)
class Plane:
    """The paper's 2-D model: all light stays in the image plane (docs/model.md §1-4)."""

    kind: Literal["plane"] = "plane"

    def as_dict(self) -> dict:
        return {"kind": "plane"}


@dataclasses.dataclass(frozen=True)
class Slab:
    """A tank of depth ``thickness`` (pixels) with 3-D directions (docs/model.md §7).

    Attributes:
        thickness: depth h of the medium in pixels (> 0).
        boundary: ``"absorbing"`` (index-matched faces: light that reaches them is gone)
            or ``"refractive"`` (relative index ``n``: Fresnel reflection and total
            internal reflection at the top and bottom faces; the camera sees through
            the top face with transmission 1 − R(normal)).
        n: relative refractive index of the medium (used with ``refractive``; ≥ 1).
        n_mu: elevation nodes in μ ∈ [0, 1] (the discretisation, like ``n_theta``), or
            ``None`` to choose from g (:func:`default_n_mu`).
        n_z: depth layers of the light field (1: the depth average), or ``None`` to
            choose from σt·h, the albedo and g (:func:`default_n_z`).
    """

    thickness: float
    boundary: Boundary = "absorbing"
    n: float = 1.33
    n_mu: int | None = None
    n_z: int | None = None
    kind: Literal["slab"] = "slab"

    def __post_init__(self):
        if isinstance(self.thickness, (bool, str)):
            raise ValueError(f"geometry.thickness: must be a number, got {self.thickness!r}")
        object.__setattr__(
            self, "thickness", _positive_finite(self.thickness, "geometry.thickness")
        )
        if self.boundary not in BOUNDARIES:
            raise ValueError(
                f"geometry.boundary: must be one of {', '.join(BOUNDARIES)}, got {self.boundary!r}"
            )
        n = _positive_finite(self.n, "geometry.n")
        if n < 1.0:
            raise ValueError(f"geometry.n: must be >= 1 (medium denser than outside), got {n!r}")
        object.__setattr__(self, "n", n)
        if self.n_mu is not None and (
            not isinstance(self.n_mu, (int, np.integer))
            or isinstance(self.n_mu, bool)
            or not 1 <= self.n_mu <= 64
        ):
            raise ValueError(f"geometry.n_mu: must be an integer in [1, 64], got {self.n_mu!r}")
        if self.n_mu is not None and self.boundary == "refractive" and self.n_mu < 4:
            raise ValueError(
                f"geometry.n_mu: refractive faces need at least 4 elevation nodes (2 on each "
                f"side of the critical angle), got {self.n_mu!r}"
            )
        if self.n_z is not None and (
            not isinstance(self.n_z, (int, np.integer))
            or isinstance(self.n_z, bool)
            or not 1 <= self.n_z <= MAX_LAYERS
        ):
            raise ValueError(
                f"geometry.n_z: must be an integer in [1, {MAX_LAYERS}], got {self.n_z!r}"
            )

    def as_dict(self) -> dict:
        d = {"kind": "slab", "thickness": self.thickness, "boundary": self.boundary}
        if self.boundary == "refractive":
            d["n"] = self.n
        if self.n_mu is not None:
            d["n_mu"] = int(self.n_mu)
        if self.n_z is not None:
            d["n_z"] = int(self.n_z)
        return d

    def resolve(self, g: float, sigma_t: float | None = None, albedo: float | None = None) -> Slab:
        """This slab with ``n_mu`` chosen from g (and the thickness) and ``n_z`` from
        σt·h, the albedo and g (:func:`default_n_z`; σt or the albedo unknown: the
        count their worst case needs) when not given."""
        n_mu = self.n_mu
        if n_mu is None:
            n_mu = default_n_mu(g, self.thickness, self.boundary, albedo)
        n_z = self.n_z
        if n_z is None:
            tau = None if sigma_t is None else float(sigma_t) * self.thickness
            n_z = default_n_z(tau, albedo, self.boundary)
        return dataclasses.replace(self, n_mu=n_mu, n_z=n_z)

    @property
    def critical_cosine(self) -> float | None:
        """cos of the critical angle of total internal reflection (refractive, n > 1)."""
        if self.boundary == "absorbing" or self.n == 1.0:
            return None
        return math.sqrt(1.0 - 1.0 / self.n**2)

    @property
    def camera_transmission(self) -> float:
        """T = 1 − R(1) through the top face (1 for absorbing faces)."""
        if self.boundary == "absorbing":
            return 1.0
        return 1.0 - float(fresnel_reflectance(1.0, self.n))


@dataclasses.dataclass(frozen=True)
class AutoGeometry:
    """Plane or slab, chosen per capture by the fit (``geometry: {kind: auto, ...}``):
    the plane model where its misfit is at most ``threshold`` × the capture's relative
    noise, else ``slab`` (:mod:`lightfield_jax.inverse.model_choice`)."""

    slab: Slab
    threshold: float = 1.0
    kind: Literal["auto"] = "auto"

    def as_dict(self) -> dict:
        d = {**self.slab.as_dict(), "kind": "auto"}
        if self.threshold != 1.0:
            d["threshold"] = self.threshold
        return d


SceneGeometry = Plane | Slab


def rho_bound(medium, geometry=None):
    """The per-bounce energy ratio bound ρ of the tail bound: ω·A(g) (or ω) for the
    plane per its phase convention, ω for a slab (its 3-D phase function is normalised
    on the sphere, whatever ``medium.phase`` says)."""
    return medium.albedo if isinstance(geometry, Slab) else medium.rho


def _guides_light(boundary: str, albedo: float | None) -> bool:
    """Refractive faces guide light far (total internal reflection) and, unless the
    medium is dim (ω < 0.3, or unknown), the high orders that carry it matter."""
    return boundary == "refractive" and (albedo is None or albedo >= DIM_ALBEDO)


def default_slab_n_theta(g: float, boundary: str = "absorbing", albedo: float | None = None) -> int:
    """Azimuth bins of the slab model for asymmetry g. The first scatter's kernels keep
    the phase function at every quadrature node, so only the phase matrix of the later
    bounces is binned: against 128 bins, 8 bins change I_3..I_5 by ≤ 0.11 % for g 0.4
    and by ≤ 0.34 % at g 0.7, 16 bins by ≤ 0.11 % there (measured on a 48×32 beam).
    Light guided by refractive faces travels far between scatterings and needs at least
    16 (measured, σt·h 0.3, g −0.3, ω 0.9, n_z 2: I_5 −2.2 % with 8 bins and 8 μ nodes
    against the 3-D Monte Carlo, −1.0 % with 16)."""
    a = abs(float(g))
    if a <= 0.6:
        n = 8
    elif a <= 0.85:
        n = 16
    else:
        n = 32
    return max(n, 16) if _guides_light(boundary, albedo) else n


def resolve_slab_grid(
    grid: Grid,
    slab: Slab,
    g: float,
    sigma_t: float | None = None,
    albedo: float | None = None,
) -> tuple[Grid, Slab]:
    """Grid and slab with the discretisation the slab model needs for the medium filled
    in: ``n_theta`` from :func:`default_slab_n_theta`, ``refine`` 1 (the FFT transport
    does not smear thin beams), ``n_mu`` and ``n_z`` by :meth:`Slab.resolve` (σt or the
    albedo ``None``: what their worst case needs)."""
    if grid.n_theta is None:
        n = default_slab_n_theta(g, slab.boundary, albedo)
    else:
        n = grid.n_theta
    r = 1 if grid.refine is None else grid.refine
    return dataclasses.replace(grid, n_theta=n, refine=r), slab.resolve(g, sigma_t, albedo)


def default_n_mu(
    g: float,
    thickness: float | None = None,
    boundary: str = "absorbing",
    albedo: float | None = None,
) -> int:
    """Elevation nodes for a phase function of asymmetry g: 4 for |g| ≤ 0.5, 8 to 0.7,
    16 to 0.85, 24 beyond (measured: I_2, I_3 within 1 % of 16 nodes for g ≤ 0.4; g 0.8
    needs 16). Absorbing slabs thinner than 2 px need more: the survival (1 − tμ/h)₊ then
    confines the light to grazing μ ≲ h/r (measured against the layer-averaged oracle,
    σt 0.1, g 0.4: ΣI_2 −15 % at h 0.25 px with 4 nodes, −1.7 % with 8, −0.2 % with 16):
    at least 8 below 2 px, 16 below 0.5 px, 32 below 0.15 px."""
    a = abs(float(g))
    if a <= 0.5:
        n = 4
    elif a <= 0.7:
        n = 8
    elif a <= 0.85:
        n = 16
    else:
        n = 24
    if thickness is not None and boundary == "absorbing":
        for limit, need in ((0.15, 32), (0.5, 16), (2.0, 8)):
            if thickness < limit:
                n = max(n, need)
                break
    return max(n, 16) if _guides_light(boundary, albedo) else n


def default_n_z(
    optical_thickness: float | None, albedo: float | None, boundary: str = "absorbing"
) -> int:
    """Depth layers for a slab of optical thickness σt·h and albedo ω (``None``:
    unknown, the worst case): 1 for dim media (ω < 0.3: the orders a depth average
    gets wrong, k ≥ 3, carry little light), else 8 behind absorbing faces, 4 behind
    refractive ones thinner than one mean free path, 2 thicker ones.

    Measured against the 3-D slab Monte Carlo (h 6.4 px, 48×32, full illumination,
    σt·h 0.3 / 1.3 / 3, g −0.3 / 0.4 / 0.8 / 0.9; docs/slab_depth.md): the error of a
    layer average falls about as 1/n_z. Absorbing faces empty the layers near them, so
    the depth average misses I_6 by up to 20–50 %, 4 layers by up to 4.5 % (σt·h 1.3,
    g −0.3), 8 layers by ≤ 2.2 %; refractive faces keep the light spread over the depth
    (n_z = 1: 5–6 % at I_5, I_6 for g ≥ 0.8), 2 layers are within 1.3 % from σt·h 1.3
    and 4 within 1.6 % at 0.3."""
    if albedo is not None and albedo < DIM_ALBEDO:
        return 1
    if boundary == "absorbing":
        return 8
    return 4 if optical_thickness is None or optical_thickness < 1.0 else 2


def parse_geometry(spec, where: str = "geometry", allow_auto: bool = False):
    """``geometry:`` of a simulate config or a capture file (absent: the plane).

    ``kind: auto`` (captures only, ``allow_auto``) takes the slab's keys and an
    optional ``threshold``; the fit chooses plane or slab (:class:`AutoGeometry`)."""
    if spec is None:
        return Plane()
    if not isinstance(spec, dict):
        raise ValueError(f"{where}: must be a mapping with 'kind', got {spec!r}")
    kind = spec.get("kind", "plane")
    if not isinstance(kind, str):
        raise ValueError(f"{where}.kind: must be a string (plane, slab), got {kind!r}")
    if "kind" not in spec and "thickness" in spec:
        raise ValueError(f"{where}.kind: missing (a slab needs kind: slab with its thickness)")
    slab_keys = {"kind", "thickness", "boundary", "n", "n_mu", "n_z"}
    allowed = {"plane": {"kind"}, "slab": slab_keys}
    if allow_auto:
        allowed["auto"] = slab_keys | {"threshold"}
    if kind not in allowed:
        raise ValueError(
            f"{where}.kind: must be {' or '.join(repr(k) for k in allowed)}, got {kind!r}"
            + ("" if allow_auto or kind != "auto" else " (auto is for fits: a capture file)")
        )
    unknown = sorted(set(spec) - allowed[kind])
    if unknown:
        raise ValueError(
            f"{where}.{unknown[0]}: unknown key for kind {kind!r}; allowed keys: "
            f"{', '.join(sorted(allowed[kind]))}"
        )
    if kind == "plane":
        return Plane()
    if "thickness" not in spec:
        raise ValueError(f"{where}.thickness: required for kind 'slab' (depth in pixels)")
    boundary = spec.get("boundary", "absorbing")
    if "n" in spec and boundary != "refractive":
        raise ValueError(f"{where}.n: only meaningful with boundary 'refractive'")
    try:
        slab = Slab(
            thickness=spec["thickness"],
            boundary=boundary,
            n=spec.get("n", 1.33),
            n_mu=spec.get("n_mu"),
            n_z=spec.get("n_z"),
        )
    except ValueError as err:
        raise ValueError(str(err).replace("geometry", where, 1)) from None
    if kind == "slab":
        return slab
    threshold = _positive_finite(spec.get("threshold", 1.0), f"{where}.threshold")
    return AutoGeometry(slab, threshold)


def fresnel_reflectance(cos_incidence: np.ndarray | float, n: float) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a face seen from inside the slab.

    Args:
        cos_incidence: cosine of the angle between the ray and the face normal, in [0, 1].
        n: relative index n_medium / n_outside (> 0). For n > 1, R = 1 (total internal
            reflection) where sin θi ≥ 1/n.

    Returns R = (r_s² + r_p²)/2 with r_s = (n cos θi − cos θt)/(n cos θi + cos θt),
    r_p = (cos θi − n cos θt)/(cos θi + n cos θt), n sin θi = sin θt. R(1) =
    ((n − 1)/(n + 1))². (Shared with the Monte Carlo oracle, whose tests check it
    against the angle form of the Fresnel equations.)
    """
    ci = np.clip(np.asarray(cos_incidence, dtype=np.float64), 0.0, 1.0)
    if n == 1.0:  # index matched: no interface (and no 0/0 at grazing incidence)
        return np.zeros_like(ci)
    sin_t2 = n * n * (1.0 - ci * ci)
    tir = sin_t2 > 1.0
    ct = np.sqrt(np.maximum(1.0 - sin_t2, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        rs = (n * ci - ct) / (n * ci + ct)
        rp = (ci - n * ct) / (ci + n * ct)
    return np.where(tir, 1.0, 0.5 * (rs * rs + rp * rp))


def hg(cos_angle, g):
    """The 3-D Henyey–Greenstein phase function, normalised on the sphere."""
    return (1.0 - g * g) / (4.0 * math.pi * (1.0 + g * g - 2.0 * g * cos_angle) ** 1.5)


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
def _slab_nodes(width: int, height: int, n_theta: int):
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


class SlabRenderer(eqx.Module):
    """A compiled slab forward model for one grid, illumination, slab and bounce count.

    Same call signature and outputs as :class:`~lightfield_jax.Renderer`:
    ``renderer(sigma_t, sigma_s, g, gain=1.0, lightfield=False)`` returns ``(images,
    lightfields)`` with images Float[Array, "patterns bounces H W"] and light fields
    (depth- and elevation-integrated: ∫_0^h ∫_{−1}^{1} L dμ dz per radian of azimuth)
    Float[Array, "bounces+1 patterns H W n_theta"] or ``None``. The phase function is
    the 3-D Henyey–Greenstein (normalised on the sphere) whatever ``phase`` says. The
    light field is resolved in ``slab.n_z`` depth layers (:mod:`._slab_layers`).
    """

    height: int = eqx.field(static=True)
    width: int = eqx.field(static=True)
    n_theta: int = eqx.field(static=True)
    n_mu: int = eqx.field(static=True)
    n_z: int = eqx.field(static=True)
    refine: int = eqx.field(static=True)
    bounces: int = eqx.field(static=True)
    phase: str = eqx.field(static=True)
    theta0_bin: int = eqx.field(static=True)
    thickness: float = eqx.field(static=True)  # on the working grid (pixels × refine)
    camera_t: float = eqx.field(static=True)
    coverage: Float[Array, "patterns H W"]
    mean_depth: Float[Array, "patterns H W"]
    var_depth: Float[Array, "patterns H W"]
    t_sub: Float[Array, "n_mu nodes q"]  # path length t = r/s at the Gauss points
    cam_u: Float[Array, "n_mu nodes q"]  # vertical travel u = tμ
    w_over_s: Float[Array, "n_mu nodes q"]  # ring weight / s
    node_cos: Float[Array, "n_mu nodes"]  # ω_node·ω0 = s_j cos(φ − θ0)
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
    ):
        if grid.n_theta is None:
            raise ValueError("SlabRenderer needs grid.n_theta: call Grid.resolve(g) first")
        if slab.n_mu is None or slab.n_z is None:
            raise ValueError("SlabRenderer needs slab.n_mu and slab.n_z: call Slab.resolve first")
        if not isinstance(bounces, (int, np.integer)) or isinstance(bounces, bool) or bounces < 1:
            raise ValueError(f"bounces: must be an integer >= 1, got {bounces!r}")
        if phase not in ("paper", "normalized"):
            raise ValueError(f"phase: must be paper or normalized, got {phase!r}")
        f = self.refine = 1 if grid.refine is None else grid.refine
        self.height, self.width, self.n_theta = grid.height * f, grid.width * f, grid.n_theta
        self.n_mu = int(slab.n_mu)
        self.n_z = int(slab.n_z)
        self.bounces = int(bounces)
        self.phase = phase
        self.thickness = float(slab.thickness) * f
        self.camera_t = slab.camera_transmission
        illumination.entry_wall(grid.width, grid.height)
        cov, mean, var = source_moments(scaled(illumination, f), self.width, self.height)
        self.coverage = jnp.asarray(cov)
        self.mean_depth = jnp.asarray(mean)
        self.var_depth = jnp.asarray(var)
        theta0 = math.radians(illumination.direction_deg)
        self.theta0_bin = int(round(theta0 / grid.dtheta)) % grid.n_theta

        mu, w_mu = elevation_nodes(self.n_mu, slab.critical_cosine)
        s = np.sqrt(1.0 - mu * mu)
        refl = (
            np.zeros_like(mu) if slab.boundary == "absorbing" else fresnel_reflectance(mu, slab.n)
        )
        nodes = _slab_nodes(self.width, self.height, self.n_theta)
        t = nodes["r_sub"][None] / s[:, None, None]  # (n_mu, N, q)
        self.t_sub = jnp.asarray(t)
        self.cam_u = jnp.asarray(t * mu[:, None, None])
        self.w_over_s = jnp.asarray(nodes["w_sub"][None] / s[:, None, None])
        self.node_cos = jnp.asarray(s[:, None] * np.cos(nodes["phi"] - theta0)[None, :])
        self.index = jnp.asarray(nodes["index"])
        self.splat = jnp.asarray(nodes["splat"])
        self.mu = jnp.asarray(mu)
        self.w_mu = jnp.asarray(w_mu)
        self.refl = jnp.asarray(refl)

    @property
    def n_patterns(self) -> int:
        return self.coverage.shape[0]

    def __call__(self, sigma_t, sigma_s, g, gain=1.0, lightfield: bool = False):
        # σ/f and h·f on the refined grid: images (ratios like σs/σt) are unchanged; the
        # depth-integrated fields are in refined pixels of depth: divided by f.
        f = self.refine
        return render_refined(self, (sigma_t, sigma_s, g, gain), lightfield, 1, 1.0 / f)

    # -- pieces -------------------------------------------------------------------

    def _splat(self, values):
        """values (A, N) → kernels (A, n_theta, 2H, 2W): every node's four bilinear
        corners receive a row of A values (one scatter of rows for all kernels)."""
        count = values.shape[0]
        cells = self.n_theta * 2 * self.height * 2 * self.width
        contrib = self.splat.astype(values.dtype)[:, :, None] * values.T[:, None, :]
        kernel = (
            jnp.zeros((cells, count), values.dtype)
            .at[self.index.reshape(-1)]
            .add(contrib.reshape(-1, count))
        )
        return kernel.T.reshape(count, self.n_theta, 2 * self.height, 2 * self.width)

    def _kernels_f(self, values):
        """values (…, n_mu, N) → rfft2 of their kernels (…, n_mu, n_theta, 2H, W + 1)."""
        lead = values.shape[:-1]
        kernels = self._splat(values.reshape((-1, values.shape[-1])))
        return jnp.fft.rfft2(kernels).reshape(lead + (self.n_theta, 2 * self.height, -1))

    def _phase_matrices(self, g, dtype):
        """(M⁺, M⁻), each (n_mu·n_theta) square: from stored up-going directions into
        up-going (M⁺) and down-going (M⁻) ones, so Q(+μ) = σs (M⁺ L(+μ) + M⁻ L(−μ)).

        Entries are dΩ_{j'} p̄(ω_ji·ω_j'i'^±), p̄ the triangle-weighted average over the
        two azimuth bins, balanced (the same symmetric scaling of both) so that the
        discrete sphere integral of every row and every column of M⁺ + M⁻ is exactly 1.
        """
        n, J = self.n_theta, self.n_mu
        dtheta = 2 * math.pi / n
        ns = _PHASE_SUBSAMPLES
        sub = np.arange(-ns, ns + 1)
        tri = ((1.0 - np.abs(sub) / ns) / ns).astype(dtype)
        delta = (np.arange(n)[:, None] + sub[None, :] / ns) * dtheta  # (n, 2ns+1)
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

    def _transport_and_camera(self, sigma_t, g, dtype):
        """Node values of the layer-to-layer transport kernels W_δ, δ = −(n_z−1)..n_z−1
        (2 n_z − 1, n_mu, N), and of the camera kernels per source layer (n_z, n_mu, N):
        T dΩ_j [p(μ_j)·A + p(−μ_j)·B] (σs apart)."""
        h, n_z = self.thickness, self.n_z
        u = jax.lax.stop_gradient(self.cam_u.astype(dtype))
        refl = jax.lax.stop_gradient(self.refl.astype(dtype))[:, None, None]
        att = jnp.exp(-sigma_t * self.t_sub.astype(dtype)) * self.w_over_s.astype(dtype)
        v = u / (h / n_z)
        transport = jnp.stack(
            [
                jnp.sum(att * transport_weights(v, refl, n_z, delta), axis=-1)
                for delta in range(-(n_z - 1), n_z)
            ]
        )
        mu = self.mu.astype(dtype)
        weight = (self.w_mu.astype(dtype) * (2 * math.pi / self.n_theta) * self.camera_t)[:, None]
        camera = []
        for layer in range(n_z):
            up, down = camera_integrals(u, h, n_z, layer, refl, sigma_t)
            up, down = jnp.sum(att * up, axis=-1), jnp.sum(att * down, axis=-1)
            camera.append(weight * (hg(mu, g)[:, None] * up + hg(-mu, g)[:, None] * down))
        return transport, jnp.stack(camera)

    def _first_phase(self, g, dtype):
        """p(ω_node·ω0) at the kernels' nodes (n_mu, N), normalised on the discrete
        sphere (so the first bounce conserves ω·energy)."""
        n = self.n_theta
        dtheta = 2 * math.pi / n
        mu = self.mu.astype(dtype)
        p1 = hg(self.node_cos.astype(dtype), g)
        fine = (np.arange(n * 16) + 0.5) * (dtheta / 16)
        ring = jnp.sum(
            hg(jnp.sqrt(1 - mu * mu)[:, None] * jnp.asarray(np.cos(fine), dtype)[None], g),
            axis=1,
        ) * (dtheta / 16)
        return p1 / (2.0 * jnp.sum(self.w_mu.astype(dtype) * ring))

    def bounce_step(self, sigma_t, sigma_s, g) -> SlabBounce:
        """The bounce ``q -> (q_next, image)`` at these values (working-grid units:
        σ per refined pixel), and the first two orders it starts from: returns
        ``(bounce, i2, l1, q2)`` with I_2 (patterns, H, W), the layered light field
        L_1 and source Q_2 (patterns, n_z, n_mu, n_theta, H, W)."""
        dtype = sigma_t.dtype
        n_z = self.n_z
        shape = (2 * self.height, 2 * self.width)
        source = unscattered_fluence(self, sigma_t)
        transport, camera = self._transport_and_camera(sigma_t, g, dtype)
        p1 = self._first_phase(g, dtype)
        # The first source is uniform in depth: layer l receives Σ_l' W_{l−l'}.
        first = jnp.stack([jnp.sum(transport[layer : layer + n_z], axis=0) for layer in range(n_z)])
        k1_f = self._kernels_f(p1 * first)  # (n_z, n_mu, n_theta, 2H, W+1)
        k1_cam_f = jnp.sum(self._kernels_f(p1 * jnp.sum(camera, axis=0)), axis=(0, 1))
        src_f = jnp.fft.rfft2(source, s=shape)
        l1 = jnp.fft.irfft2(src_f[:, None, None, None] * k1_f, s=shape)
        l1 = sigma_s * jnp.maximum(l1[..., : self.height, : self.width], 0.0)
        i2 = jnp.fft.irfft2(src_f * k1_cam_f, s=shape)[..., : self.height, : self.width]
        i2 = sigma_s**2 * jnp.maximum(i2, 0.0)
        plus, minus = self._phase_matrices(g, dtype)
        bounce = SlabBounce(
            transport_f=self._kernels_f(transport),
            camera_f=sigma_s * self._kernels_f(camera),
            mix_even=0.5 * sigma_s * (plus + minus),
            mix_odd=0.5 * sigma_s * (plus - minus),
            height=self.height,
            width=self.width,
        )
        return bounce, i2, l1, bounce.scatter(l1)

    @eqx.filter_jit
    def _render(self, sigma_t, sigma_s, g, gain, lightfield: bool):
        _count_trace()
        dtype = sigma_t.dtype
        n = self.n_theta
        h = self.thickness
        dz = h / self.n_z
        dtheta = 2 * math.pi / n
        t_cam = jnp.asarray(self.camera_t, dtype)

        source = unscattered_fluence(self, sigma_t)  # (P, H, W), uniform in depth
        depth_factor = -jnp.expm1(-sigma_t * h) / sigma_t
        images = [t_cam * sigma_s * hg(jnp.zeros((), dtype), g) * depth_factor * source]
        fields = []
        if lightfield:
            l0 = jnp.zeros((source.shape[0], n) + source.shape[1:], dtype)
            fields.append(l0.at[:, self.theta0_bin].set(h * source / dtheta))

        def integrate(field):  # (P, n_z, n_mu, n, H, W) → ∫dz ∫dμ: (P, n, H, W)
            return 2.0 * dz * jnp.einsum("j,pljnhw->pnhw", self.w_mu.astype(dtype), field)

        if self.bounces > 1 or lightfield:
            bounce, i2, l1, q = self.bounce_step(sigma_t, sigma_s, g)
            if self.bounces > 1:
                images.append(i2)
            if lightfield:
                fields.append(integrate(l1))
            images = [jnp.stack(images)]
            fields = [jnp.stack(fields)] if lightfield else []
            if self.bounces > 2:

                def body(q, _):
                    q_next, image, field = bounce.step(q)
                    return q_next, (image, integrate(field) if lightfield else None)

                q, (more, more_fields) = jax.lax.scan(body, q, None, length=self.bounces - 2)
                images.append(more)
                if lightfield:
                    fields.append(more_fields)
            if lightfield and self.bounces > 1:
                shape = (2 * self.height, 2 * self.width)
                fields.append(integrate(bounce.transport(jnp.fft.rfft2(q, s=shape)))[None])
        else:
            images = [jnp.stack(images)]
            fields = [jnp.stack(fields)] if lightfield else []
        stacked = gain * jnp.moveaxis(jnp.concatenate(images, axis=0), 0, 1)
        lf = gain * jnp.moveaxis(jnp.concatenate(fields, axis=0), 2, -1) if lightfield else None
        return stacked, lf


def describe_geometry(model: dict) -> str:
    """A short description of a fit result's ``model`` geometry (and auto's choice)."""
    geo = model.get("geometry") or {"kind": "plane"}
    if geo.get("kind") == "slab":
        text = f"slab h {geo['thickness']:g} px {geo['boundary']}"
        if geo["boundary"] == "refractive":
            text += f" n {geo['n']:g}"
        text += f", n_mu {geo.get('n_mu')}, n_z {geo.get('n_z', 1)}"
    else:
        text = "plane"
    choice = model.get("geometry_choice")
    if choice and "reason" in choice:
        text += f" (auto: {choice['reason']})"
    elif choice:
        text += f" (auto: plane error {choice['plane_error']:.2g} vs noise {choice['noise']:.2g})"
    return text


@functools.lru_cache(maxsize=64)
def _bounce_ratio_cached(slab: Slab, key: tuple, width: int, height: int) -> float:
    sigma_t, albedo, g = key
    from lightfield_jax.scene.illumination import Full

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
    "AutoGeometry",
    "Plane",
    "Slab",
    "SlabRenderer",
    "SceneGeometry",
    "default_n_mu",
    "default_n_z",
    "describe_geometry",
    "default_slab_n_theta",
    "resolve_slab_grid",
    "rho_bound",
    "slab_bounce_ratio",
    "elevation_nodes",
    "fresnel_reflectance",
    "hg",
    "parse_geometry",
]
