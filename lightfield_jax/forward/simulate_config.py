"""The ``simulate`` config parsed into a typed, validated, frozen :class:`SimulationConfig`
(through :mod:`lightfield_jax.schema`).

The ``simulate`` config (lengths in pixels, coefficients per pixel, angles in degrees)::

    grid: {width: 128, height: 96, n_theta: 64}     # n_theta optional: chosen from g
    medium: {sigma_t: 0.2051, sigma_s: 0.0366, g: 0.4, phase: paper}  # phase optional: normalized
    illumination: {kind: beam, x: 0.0, y: 48.5, direction_deg: 0.0, width: 1.0}
    #   kind: stripes -> period, lit, shifts: N (phases 0..N-1) or phases: [..],
    #                    direction_deg, entry: left|right|top|bottom
    #   kind: full    -> direction_deg, entry
    bounces: 10          # or auto (the default)
    tolerance: 1e-4      # only with bounces: auto

Optional keys (all absent by default):

- ``grid.refine``: spatial refinement of the working grid, an integer in [1, 8]
  (absent: chosen from g, see :class:`Grid`).
- ``gain: 1.0``: the source gain c > 0 (projector power × camera response) that
  multiplies every rendered image and light field.
- ``noise: {photons: 1e4, read: 0.002, seed: 0}``: camera noise on the captured images
  (``total.exr``, ``shift_XX.exr``, ``dark.exr``; never on the per-bounce renders).
  ``photons`` > 0 is the expected photon count at image value 1.0 (Poisson shot noise:
  image = Poisson(photons·image)/photons); ``read`` ≥ 0 is the standard deviation of
  Gaussian read noise in image units; ``seed`` ≥ 0 seeds the generator (default 0).
  At least one of ``photons`` and ``read`` must be given.
- ``black_level: 0.05`` (stripes only), in [0, 1): a dark stripe still emits b times
  a lit one, so a shift's image is (1 − b)·R_pattern + b·R_full (docs/model.md section 5).
- ``geometry: {kind: slab, thickness: 6.4, boundary: absorbing}``: the tank's depth
  modelled in 3-D (docs/model.md section 7; thickness in pixels, ``boundary: refractive``
  with ``n: 1.33``, optional ``n_mu`` elevation nodes). Absent or ``{kind: plane}``:
  the paper's 2-D model.
- ``dark_level: 0.01`` ≥ 0: a constant (image units) added to every captured image; a
  dark frame with that constant (plus noise) is written as ``dark.exr``.
- ``tail: gmres`` (or ``bicgstab``): the bounces past K summed by one Krylov solve
  (relative tolerance ``tolerance``) instead of marched: a medium near albedo 1 (a slab
  at ω 0.95 marches hundreds of bounces) renders several times faster. ``bounces: auto``
  then keeps at most 4 explicit bounces; the per-bounce images hold I_1..I_K and, last,
  the tail Σ_{k>K} I_k.

Every error is a :class:`ConfigError` whose message starts with the file name, then
the key's path (``medium.sigma_t``) and the offending value (its text bounded in
size). Stripe phases lie in [0, period), ``shifts`` in [1, period], and the period is
no longer than the grid; stripes whose capture a fit refuses (one shift, or phases that
all light the same rows without noise: identical images) are refused too. What a YAML
file may hold is :mod:`lightfield_jax.schema`'s rule.
"""

from __future__ import annotations

import copy
import dataclasses
import os
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np

from lightfield_jax.checks import check_int, check_number, gain_problem
from lightfield_jax.forward.base import MAX_BOUNCES, too_many_bounces
from lightfield_jax.forward.render import resolve_bounces
from lightfield_jax.forward.tail import TAIL_METHODS, check_tail
from lightfield_jax.scene.geometry import Plane, Slab, as_geometry, paper_bound, rho_bound
from lightfield_jax.scene.geometry_spec import parse_geometry
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import (
    WALLS,
    Beam,
    Full,
    Illumination,
    Stripes,
    period_problem,
    shifts_problem,
)
from lightfield_jax.scene.medium import (
    FILE_PHASE,
    PHASE_CONVENTIONS,
    Medium,
    bounces_for_tolerance,
)
from lightfield_jax.schema import (
    MAX_VALUE,
    ConfigError,
    Section,
    as_int,
    at_most,
    brief,
    load_yaml,
    show,
)

ILLUMINATION_KINDS: tuple[str, ...] = ("beam", "stripes", "full")
_TOP_KEYS = (
    "grid",
    "medium",
    "illumination",
    "bounces",
    "tolerance",
    "gain",
    "noise",
    "black_level",
    "dark_level",
    "geometry",
    "tail",
)
_GRID_KEYS = ("width", "height", "n_theta", "refine")
_NOISE_KEYS = ("photons", "read", "seed")
_MEDIUM_KEYS = ("sigma_t", "sigma_s", "g", "phase")
_ILLUMINATION_KEYS = {
    "beam": ("kind", "x", "y", "direction_deg", "width"),
    "stripes": ("kind", "period", "lit", "shifts", "phases", "direction_deg", "entry"),
    "full": ("kind", "direction_deg", "entry"),
}
# The shot-noise draw counts photons in 64-bit integers (at most 9.2e18), so photons ×
# (gain + dark level), about the largest count, is kept below MAX_PHOTONS.
MAX_PHOTONS = 1e15


@dataclasses.dataclass(frozen=True)
class MediumConfig:
    """The medium's parameters as plain floats (per pixel); see :class:`Medium`.

    Validated on construction (σt > 0, 0 ≤ σs ≤ σt, −1 < g < 1, a known phase
    convention); :meth:`medium` builds the JAX :class:`Medium`.
    """

    sigma_t: float
    sigma_s: float
    g: float
    phase: Literal["paper", "normalized"] = "paper"

    def __post_init__(self):
        for name in ("sigma_t", "sigma_s", "g"):
            check_number(getattr(self, name), f"medium.{name}")
        if 0 < self.sigma_t < 1 / MAX_VALUE or self.sigma_t > MAX_VALUE:
            raise ValueError(
                f"medium.sigma_t: must lie in [{1 / MAX_VALUE:g}, {MAX_VALUE:g}] per pixel "
                f"(the render is float32), got {self.sigma_t!r}"
            )
        self.medium()

    def medium(self) -> Medium:
        return Medium(self.sigma_t, self.sigma_s, self.g, self.phase)


@dataclasses.dataclass(frozen=True)
class NoiseConfig:
    """Camera noise on captured images (see the module docstring).

    Attributes:
        photons: expected photon count at image value 1.0 (Poisson shot noise), or
            ``None`` for no shot noise.
        read: standard deviation of Gaussian read noise, image units (≥ 0).
        seed: seed of the noise generator.
    """

    photons: float | None = None
    read: float = 0.0
    seed: int = 0

    def __post_init__(self):
        if self.photons is not None:
            check_number(self.photons, "noise.photons", low=0.0, low_open=True, high=MAX_PHOTONS)
        check_number(self.read, "noise.read", low=0.0, high=MAX_VALUE)
        check_int(self.seed, "noise.seed", low=0)

    def apply(self, image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """``image`` (image units, ≥ 0) with shot and read noise drawn from ``rng``."""
        out = np.asarray(image, dtype=np.float64)
        if self.photons is not None:
            out = rng.poisson(np.clip(out, 0.0, None) * self.photons) / self.photons
        if self.read > 0:
            out = out + rng.normal(0.0, self.read, out.shape)
        return out


@dataclasses.dataclass(frozen=True)
class SimulationConfig:
    """A validated ``simulate`` config.

    Attributes:
        grid: the grid (``n_theta`` is ``None`` when the file leaves it to g).
        medium: σt, σs, g (per pixel) and the phase convention.
        illumination: a :class:`Beam`, :class:`Stripes` or :class:`Full`.
        bounces: K, or ``"auto"`` (the smallest K whose tail bound is ≤ tolerance).
        tolerance: the relative tail bound for ``bounces: auto``.
        gain: source gain c multiplying every rendered image (> 0).
        noise: camera noise on the captured images, or ``None``.
        black_level: stripes only: b in [0, 1), or ``None`` (no black level).
        dark_level: constant added to every captured image, or ``None`` (no dark frame).
        geometry: :class:`Plane` (the paper's 2-D model, default) or a :class:`Slab`.
        tail: ``None`` (the series marched to K), or the Krylov solve (``"gmres"``,
            ``"bicgstab"``) that sums the bounces past K to ``tolerance``.
        source: the file (or ``"<dict>"``) the config came from.
        raw: the parsed YAML, for metadata.
    """

    grid: Grid
    medium: MediumConfig
    illumination: Illumination
    bounces: int | Literal["auto"] = "auto"
    tolerance: float = 1e-4
    gain: float = 1.0
    noise: NoiseConfig | None = None
    black_level: float | None = None
    dark_level: float | None = None
    geometry: Plane | Slab = Plane()
    tail: str | None = None
    source: str = "<dict>"
    raw: dict = dataclasses.field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self):
        object.__setattr__(self, "geometry", as_geometry(self.geometry))  # None: the plane
        # The Python API's checks of what parse_simulation_config checks in a file (a
        # config made in code is checked too: black_level 5 would render negative
        # images, gain 1e-40 zero ones).
        for key, value, kind in (
            ("grid", self.grid, Grid),
            ("medium", self.medium, MediumConfig),
            ("illumination", self.illumination, (Beam, Stripes, Full)),
            ("noise", self.noise, (NoiseConfig, type(None))),
        ):
            if not isinstance(value, kind):
                names = (
                    kind.__name__
                    if isinstance(kind, type)
                    else " or ".join(k.__name__ for k in kind if k is not type(None))
                )
                raise ValueError(f"{key}: must be a {names}, got {brief(value)}")
        if isinstance(self.bounces, str):
            if self.bounces != "auto":
                raise ValueError(
                    f"bounces: must be a positive integer or 'auto', got {brief(self.bounces)}"
                )
        else:
            check_int(self.bounces, "bounces", low=1)
        check_number(self.tolerance, "tolerance", low=0.0, high=1.0, low_open=True, high_open=True)
        check_tail(self.tail, self.tolerance, 1)
        if self.tail is not None:
            rho, paper = series_bound(self.medium, self.geometry)
            if not rho < 1.0:
                raise ValueError(f"tail: {diverges(rho, paper)}")
        if gain_problem(self.gain) is not None:
            raise ValueError(f"gain: {gain_problem(self.gain)}")
        if self.dark_level is not None:
            check_number(self.dark_level, "dark_level", low=0.0, high=MAX_VALUE)
        problem = period_problem(self.illumination, self.grid.width, self.grid.height)
        if problem is not None:
            raise ValueError(f"illumination.period: {problem}")
        if self.black_level is not None:
            if not isinstance(self.illumination, Stripes):
                raise ValueError("black_level: applies only to illumination kind stripes")
            check_number(self.black_level, "black_level", low=0.0, high=1.0, high_open=True)

    def n_bounces(self) -> int:
        """The bounce count K, with ``"auto"`` resolved from ρ and the tolerance."""
        if self.bounces == "auto":
            rho, paper = series_bound(self.medium, self.geometry)
            return resolve_bounces(rho, "auto", self.tolerance, self.tail, paper=paper)
        return self.bounces


def load_simulation_config(path: str | os.PathLike) -> SimulationConfig:
    """Read and validate a ``simulate`` YAML config (see the module docstring)."""
    return parse_simulation_config(load_yaml(path), source=str(path))


def parse_simulation_config(data: Mapping, source: str = "<dict>") -> SimulationConfig:
    """Validate an already parsed ``simulate`` config; errors name ``source``."""
    top = Section(source, "", data, _TOP_KEYS)
    grid = _grid(Section(source, "grid", top.get("grid"), _GRID_KEYS))
    medium = _medium(Section(source, "medium", top.get("medium"), _MEDIUM_KEYS))
    illumination = _illumination(source, top.get("illumination"), grid)
    geometry = _geometry(top)
    tail = _tail(top, medium, geometry)
    bounces, tolerance = _bounces(top, medium, geometry, tail is not None)
    camera = _camera(top, illumination)
    _check_shifts(top, illumination, camera["noise"])
    return SimulationConfig(
        grid=grid,
        medium=medium,
        illumination=illumination,
        bounces=bounces,
        tolerance=tolerance,
        **camera,
        geometry=geometry,
        tail=tail,
        source=source,
        raw=copy.deepcopy(dict(data)),
    )


def _geometry(top: Section) -> Plane | Slab:
    if "geometry" not in top.data:
        return Plane()
    try:
        return parse_geometry(top.data["geometry"], top.key("geometry"))
    except ValueError as err:
        raise top.error(f"{top.source}: {err}") from None


def _build(section: Section, make, *args, **kwargs):
    """Call a validating constructor, turning its ``ValueError`` into a ConfigError."""
    try:
        return make(*args, **kwargs)
    except ValueError as e:
        raise ConfigError(f"{section.source}: {e}") from None


def _grid(s: Section) -> Grid:
    return _build(
        s, Grid, s.int("width"), s.int("height"), s.int("n_theta", None), s.int("refine", None)
    )


def _medium(s: Section) -> MediumConfig:
    return _build(
        s,
        MediumConfig,
        sigma_t=s.float("sigma_t"),
        sigma_s=s.float("sigma_s"),
        g=s.float("g"),
        phase=s.choice("phase", PHASE_CONVENTIONS, FILE_PHASE),
    )


def _illumination(source: str, value: Any, grid: Grid) -> Illumination:
    kind = Section(source, "illumination", value, None).choice("kind", ILLUMINATION_KINDS)
    s = Section(source, "illumination", value, _ILLUMINATION_KEYS[kind], f" for kind {kind}")
    direction = s.float("direction_deg", None)
    if kind == "beam":
        beam = _build(
            s,
            Beam,
            x=s.float("x"),
            y=s.float("y"),
            direction_deg=0.0 if direction is None else direction,
            width=s.float("width", 1.0),
        )
        _build(s, beam.entry_wall, grid.width, grid.height)
        return beam
    entry = s.choice("entry", WALLS, "left")
    if kind == "full":
        return _build(s, Full, direction_deg=direction, entry=entry)
    period, lit = s.int("period", 6), s.int("lit", 3)
    if period < 2:  # before the shifts and phases, which count rows modulo it
        s.fail(s.key("period"), f"must be an integer >= 2, got {period}")
    if (problem := period_problem(period, grid.width, grid.height)) is not None:
        s.fail(s.key("period"), problem)
    if "shifts" in s.data and "phases" in s.data:
        s.fail("illumination", "give either shifts or phases, not both")
    if "phases" in s.data:
        phases = s.get("phases")
        if not isinstance(phases, list) or not phases:
            s.fail(s.key("phases"), f"must be a non-empty list of integers, got {show(phases)}")
        phases = [as_int(s, f"{s.key('phases')}[{i}]", p) for i, p in enumerate(phases)]
        outside = [p for p in phases if not 0 <= p < period]
        if outside:
            s.fail(s.key("phases"), f"{brief(outside)} outside [0, period) = [0, {period})")
        return _build(s, Stripes, period, lit, tuple(phases), direction_deg=direction, entry=entry)
    shifts = s.int("shifts", period)
    if not 1 <= shifts <= period:
        s.fail(s.key("shifts"), f"must be an integer in [1, period] = [1, {period}], got {shifts}")
    return _build(
        s, Stripes, period, lit, tuple(range(shifts)), direction_deg=direction, entry=entry
    )


def _check_shifts(top: Section, illumination: Illumination, noise) -> None:
    """Refuse stripes whose capture the fit refuses (the fit's rule,
    :func:`~lightfield_jax.scene.illumination.shifts_problem`): one shift, or shifts
    whose noise-free images are all the same (every phase the same): refused here, before
    the render, as the fit would refuse the capture."""
    if not isinstance(illumination, Stripes):
        return
    phases = illumination.phases
    noisy = noise is not None and (noise.photons is not None or noise.read > 0)
    same = not noisy and len({p % illumination.period for p in phases}) == 1
    if (problem := shifts_problem(len(phases), same)) is None:
        return
    key = "illumination.phases" if "phases" in top.data["illumination"] else "illumination.shifts"
    if len(phases) >= 2:
        problem += (
            f" (the phases {brief(list(phases))} light the same rows, and there is no "
            "noise): give phases that differ"
        )
    top.fail(key, problem)


def _camera(top: Section, illumination: Illumination) -> dict:
    """The optional gain, noise, black-level and dark-level keys."""
    gain = top.float("gain", 1.0)
    if gain <= 0:
        top.fail("gain", f"must be > 0, got {gain!r}")
    at_most(top, "gain", gain)
    if gain_problem(gain) is not None:
        top.fail("gain", gain_problem(gain))
    dark_level = top.float("dark_level", None)
    if dark_level is not None and dark_level < 0:
        top.fail("dark_level", f"must be >= 0 (image units), got {dark_level!r}")
    at_most(top, "dark_level", dark_level or 0.0)
    noise = None
    if "noise" in top.data:
        s = top.section("noise", _NOISE_KEYS)
        if not s.data:
            s.fail("noise", "give photons and/or read")
        photons = s.float("photons", None)
        if photons is not None and photons <= 0:
            s.fail(s.key("photons"), f"must be > 0, got {photons!r}")
        if photons is not None and photons * (gain + (dark_level or 0.0)) > MAX_PHOTONS:
            s.fail(
                s.key("photons"),
                f"{photons!r} photons at image value 1.0 times the brightest value (gain + "
                f"dark_level = {gain + (dark_level or 0.0):g}) exceeds {MAX_PHOTONS:g}, "
                "more photons than the shot-noise draw counts",
            )
        read = s.float("read", 0.0)
        if read < 0:
            s.fail(s.key("read"), f"must be >= 0 (image units), got {read!r}")
        at_most(s, s.key("read"), read)
        seed = s.int("seed", 0)
        if seed < 0:
            s.fail(s.key("seed"), f"must be a non-negative integer, got {seed!r}")
        noise = NoiseConfig(photons, read, seed)
    black_level = top.float("black_level", None)
    if black_level is not None:
        if not isinstance(illumination, Stripes):
            top.fail("black_level", "applies only to illumination kind stripes")
        if not 0.0 <= black_level < 1.0:
            top.fail("black_level", f"must lie in [0, 1), got {black_level!r}")
    return {"gain": gain, "noise": noise, "black_level": black_level, "dark_level": dark_level}


def series_bound(medium: MediumConfig, geometry) -> tuple[float, bool]:
    """The medium's per-bounce ratio bound ρ in ``geometry`` and whether it is the paper
    convention's ω·A(g) (:func:`~lightfield_jax.scene.geometry.paper_bound`)."""
    model = medium.medium()
    return float(rho_bound(model, geometry)), paper_bound(model, geometry)


def diverges(rho: float, paper: bool) -> str:
    """Why a tail solve is refused where the series does not converge (``paper``: ρ is
    the paper convention's ω·A(g), else the albedo)."""
    said = f"the bounce series does not converge (per-bounce ratio bound {rho:.4g} >= 1)"
    if paper:
        return f"{said}: no solve sums it; phase: normalized (or a slab) keeps it convergent"
    return f"{said}: a medium that absorbs nothing (sigma_s = sigma_t) sends its light on forever"


def _tail(top: Section, medium: MediumConfig, geometry) -> str | None:
    tail = top.get("tail", None)
    if tail is None:
        return None
    if not (isinstance(tail, str) and tail in TAIL_METHODS):
        top.fail("tail", f"must be one of {', '.join(TAIL_METHODS)}, got {brief(tail)}")
    rho, paper = series_bound(medium, geometry)
    if not rho < 1.0:
        top.fail("tail", diverges(rho, paper))
    return tail


def _bounces(
    top: Section, medium: MediumConfig, geometry=None, tail: bool = False
) -> tuple[int | str, float]:
    bounces = top.get("bounces", "auto")
    if bounces != "auto":
        if isinstance(bounces, str):
            top.fail("bounces", f"must be a positive integer or 'auto', got {brief(bounces)}")
        bounces = as_int(top, "bounces", bounces)
        if bounces < 1:
            top.fail("bounces", f"must be a positive integer or 'auto', got {brief(bounces)}")
        if bounces > MAX_BOUNCES:  # the renderer's own check did not name the file
            top.fail("bounces", too_many_bounces("bounces", bounces).removeprefix("bounces: "))
        if "tolerance" in top.data and not tail:
            top.fail(
                "tolerance",
                f"is used only with bounces: auto or a tail (bounces is {bounces})",
            )
    tolerance = top.float("tolerance", 1e-4)
    if not 0.0 < tolerance < 1.0:
        top.fail("tolerance", f"must lie in (0, 1), got {tolerance!r}")
    if bounces == "auto" and not tail:
        try:
            rho, paper = series_bound(medium, geometry)
            bounces_for_tolerance(rho, tolerance, paper=paper)
        except ValueError as e:
            top.fail("bounces", str(e).removeprefix("bounces: "))
    return bounces, tolerance


__all__ = [
    "ILLUMINATION_KINDS",
    "MediumConfig",
    "NoiseConfig",
    "SimulationConfig",
    "load_simulation_config",
    "parse_simulation_config",
]
