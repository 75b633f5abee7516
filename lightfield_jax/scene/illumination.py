"""Collimated illumination entering through a wall (docs/model.md section 3).

Every source here is a collimated sheet of unit irradiance (power per unit transverse
width) heading θ0, restricted to a lit set of the entry wall:

- :class:`Beam`: entry point on a wall, transverse width w; it covers w/|cos| of the
  wall (the cosine between θ0 and the wall's normal).
- :class:`Stripes`: the projector's shifted stripes, one image per phase. Wall cell r
  (the segment [r, r+1) of the entry wall, a pixel row for the left/right walls, a
  pixel column for the top/bottom walls) is lit iff (r + phase) mod period < lit.
  At normal incidence a lit cell is the docs/model.md beam of width 1 centred on r + ½;
  at oblique incidence the lit cell is the wall segment (transverse width |cos|).
- :class:`Full`: the whole entry wall lit (the "all white" pattern).

The unscattered light at a point x is E(x)·exp(−σt d0(x)), d0 the distance from x
back to the entry wall along −ω(θ0) and E = 1 where the backward ray meets the lit set.
:func:`source_moments` returns per-pixel moments of d0 over the lit part of each
pixel (supersampled), from which the renderer forms the exact pixel average.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import numpy as np

from lightfield_jax.checks import as_array, check_int, check_number, number_problem, shown

Wall = Literal["left", "right", "top", "bottom"]
WALLS: tuple[str, ...] = ("left", "right", "top", "bottom")
# Inward normal direction (degrees) of each wall: the default heading of light entering it.
INWARD_DEG = {"left": 0.0, "right": 180.0, "top": 90.0, "bottom": 270.0}


def along_x(wall: str) -> bool:
    """Whether light entering through ``wall`` crosses the image along x (its rows):
    the left and right walls; the top and bottom walls send it along y."""
    return wall in ("left", "right")


def check_direction(entry: str, direction_deg: float, what: str) -> None:
    t = math.radians(direction_deg)
    inward = {
        "left": math.cos(t),
        "right": -math.cos(t),
        "top": math.sin(t),
        "bottom": -math.sin(t),
    }
    if inward[entry] <= 1e-6:
        raise ValueError(
            f"{what}.direction_deg: {direction_deg!r} degrees does not point into the medium "
            f"from the {entry} wall (light entering the {entry} wall must head within 90 "
            f"degrees of {INWARD_DEG[entry]:g})"
        )


# The widest beam (pixels) and the largest heading (degrees, either sign) taken: a beam
# wider than any medium is full illumination (Full), and the lit length of a wall cell,
# a difference of coordinates offset by half the width, cancels to 0 in float64 for
# widths near 1e16 (Beam(width=1e20) would render all-zero images); a heading past a
# turn is a slip (1e20 degrees has no direction left in float64). The narrowest beam:
# the lit length cancels likewise in float64 below it (width 1e-12 at y = 12 is 0.2 % off),
# and the images, proportional to the width, underflow float32 (1e-20: all zero).
MAX_BEAM_WIDTH = 1e5
MIN_BEAM_WIDTH = 1e-6
MAX_DIRECTION_DEG = 360.0


def checked_direction(value, what: str) -> float:
    return check_number(
        value, what, low=-MAX_DIRECTION_DEG, high=MAX_DIRECTION_DEG, unit=" degrees"
    )


@dataclasses.dataclass(frozen=True)
class Beam:
    """A collimated beam entering through a wall.

    Attributes:
        x, y: entry point on a wall of the medium (pixels; x = 0 is the left wall,
            x = width the right wall, y = 0 the top wall, y = height the bottom wall).
        direction_deg: heading θ0 in degrees from +x toward +y, in [−360, 360].
        width: transverse width w in pixels (uniform unit irradiance across it), in
            [:data:`MIN_BEAM_WIDTH`, :data:`MAX_BEAM_WIDTH`]: a wider light is
            :class:`Full` illumination.
    """

    x: float
    y: float
    direction_deg: float = 0.0
    width: float = 1.0

    def __post_init__(self):
        for name in ("x", "y"):
            object.__setattr__(
                self, name, check_number(getattr(self, name), f"illumination.{name}")
            )
        direction = checked_direction(self.direction_deg, "illumination.direction_deg")
        object.__setattr__(self, "direction_deg", direction)
        width = check_number(self.width, "illumination.width")
        if width <= 0:
            raise ValueError(f"illumination.width: must be > 0 pixels, got {self.width!r}")
        if width < MIN_BEAM_WIDTH:
            raise ValueError(
                f"illumination.width: must be at least {MIN_BEAM_WIDTH:g} pixels (narrower, "
                f"the lit length cancels in float64 and the images underflow), got "
                f"{self.width!r}"
            )
        if width > MAX_BEAM_WIDTH:
            raise ValueError(
                f"illumination.width: must be at most {MAX_BEAM_WIDTH:g} pixels (a beam; a "
                f"wider light is Full illumination), got {self.width!r}"
            )
        object.__setattr__(self, "width", width)

    n_patterns = 1

    def entry_wall(self, width: int, height: int) -> str:
        t = math.radians(self.direction_deg)
        tol = 1e-9
        candidates = []
        if abs(self.x) <= tol and math.cos(t) > 1e-6:
            candidates.append("left")
        if abs(self.x - width) <= tol and math.cos(t) < -1e-6:
            candidates.append("right")
        if abs(self.y) <= tol and math.sin(t) > 1e-6:
            candidates.append("top")
        if abs(self.y - height) <= tol and math.sin(t) < -1e-6:
            candidates.append("bottom")
        if not (-tol <= self.x <= width + tol and -tol <= self.y <= height + tol):
            candidates = []
        if not candidates:
            raise ValueError(
                f"illumination: beam entry point ({self.x:g}, {self.y:g}) heading "
                f"{self.direction_deg:g} deg must lie on a wall of the {width}x{height} "
                "medium (x = 0 or x = width, y = 0 or y = height) and point into it"
            )
        return candidates[0]


# Phases (one image each) a stripe pattern may list.
MAX_PHASES = 4096


@dataclasses.dataclass(frozen=True)
class Stripes:
    """Shifted projector stripes entering through one wall (one image per phase)."""

    period: int = 6
    lit: int = 3
    phases: tuple[int, ...] = (0, 1, 2, 3, 4, 5)
    direction_deg: float | None = None
    entry: Wall = "left"

    def __post_init__(self):
        object.__setattr__(self, "period", check_int(self.period, "illumination.period", low=2))
        if number_problem(self.lit, integer=True, low=1, high=self.period - 1) is not None:
            raise ValueError(
                f"illumination.lit: must be an integer in [1, period-1] = [1, {self.period - 1}], "
                f"got {shown(self.lit)}"
            )
        object.__setattr__(self, "lit", int(self.lit))
        given = self.phases
        if hasattr(given, "__array__") and not isinstance(given, np.ndarray):
            # A JAX array (jnp.arange(6)): its values, as a NumPy array's; traced, refused.
            given = as_array(given, "illumination.phases", "a sequence of integers")
        if (
            isinstance(given, (str, bytes))
            or not isinstance(given, (tuple, list, range, np.ndarray))
            or (isinstance(given, np.ndarray) and given.ndim == 0)
        ):
            raise ValueError(
                f"illumination.phases: must be a sequence of integers, got {shown(self.phases)}"
            )
        if isinstance(given, np.ndarray) and given.ndim != 1:  # else flattened into phases
            raise ValueError(
                "illumination.phases: must be a sequence of integers (one per image), got an "
                f"array of shape {given.shape}"
            )
        object.__setattr__(self, "phases", given)
        count = np.size(self.phases) if isinstance(self.phases, np.ndarray) else len(self.phases)
        if count > MAX_PHASES:  # range(10**12) as a tuple: out of memory
            raise ValueError(
                f"illumination.phases: at most {MAX_PHASES} phases (one image each), got {count}"
            )
        phases = (
            tuple(np.asarray(self.phases).ravel())
            if isinstance(self.phases, np.ndarray)
            else tuple(self.phases)
        )
        if not phases:
            raise ValueError("illumination.phases: must list at least one phase")
        for p in phases:
            if not isinstance(p, (int, np.integer)) or isinstance(p, bool):
                raise ValueError(f"illumination.phases: phases must be integers, got {p!r}")
            if not 0 <= p < self.period:
                raise ValueError(
                    f"illumination.phases: each phase must lie in [0, period = {self.period}), "
                    f"got {p!r}"
                )
        object.__setattr__(self, "phases", tuple(int(p) for p in phases))
        _check_entry(self.entry)
        object.__setattr__(self, "direction_deg", _direction_for(self.entry, self.direction_deg))

    @classmethod
    def shifted(cls, period: int = 6, lit: int = 3, shifts: int | None = None, **kw) -> Stripes:
        """Stripes with phases 0..shifts−1 (default: one per row of the period)."""
        n = period if shifts is None else shifts
        if number_problem(n, integer=True, low=1) is not None:
            raise ValueError(
                f"illumination.shifts: must be a positive integer, got {shown(shifts)}"
            )
        if number_problem(period, integer=True) is None and n > period:
            raise ValueError(
                f"illumination.shifts: must be an integer in [1, period] = [1, {period}] (one "
                f"image per row of the period), got {shown(shifts)}"
            )
        return cls(period=period, lit=lit, phases=tuple(range(n)), **kw)

    @property
    def n_patterns(self) -> int:
        return len(self.phases)

    def as_dict(self) -> dict:
        """The YAML/JSON form (``Stripes(**d)`` gives it back)."""
        return {
            "period": self.period,
            "lit": self.lit,
            "phases": list(self.phases),
            "direction_deg": self.direction_deg,
            "entry": self.entry,
        }

    @property
    def lit_fraction(self) -> float:
        return self.lit / self.period

    @property
    def along_x(self) -> bool:
        """Whether the light crosses the image along x (:func:`along_x` of the entry)."""
        return along_x(self.entry)

    def entry_wall(self, width: int, height: int) -> str:
        return self.entry


@dataclasses.dataclass(frozen=True)
class Full:
    """Full illumination: the whole entry wall lit (the all-white pattern)."""

    direction_deg: float | None = None
    entry: Wall = "left"

    def __post_init__(self):
        _check_entry(self.entry)
        object.__setattr__(self, "direction_deg", _direction_for(self.entry, self.direction_deg))

    n_patterns = 1

    def entry_wall(self, width: int, height: int) -> str:
        return self.entry


Illumination = Beam | Stripes | Full


def scaled(illum: Illumination, factor: int) -> Illumination:
    """The same illumination on a grid refined ``factor`` times (lengths × factor)."""
    if factor == 1:
        return illum
    if isinstance(illum, Beam):
        return dataclasses.replace(
            illum, x=illum.x * factor, y=illum.y * factor, width=illum.width * factor
        )
    if isinstance(illum, Stripes):
        # Wall cell r of the coarse grid is fine cells [r·f, r·f + f).
        return dataclasses.replace(
            illum,
            period=illum.period * factor,
            lit=illum.lit * factor,
            phases=tuple(p * factor for p in illum.phases),
        )
    return illum


def _check_entry(entry) -> None:
    if not isinstance(entry, str) or entry not in WALLS:
        raise ValueError(f"illumination.entry: must be one of {', '.join(WALLS)}, got {entry!r}")


def _direction_for(entry: str, direction_deg) -> float:
    if direction_deg is None:
        return INWARD_DEG[entry]
    d = checked_direction(direction_deg, "illumination.direction_deg")
    check_direction(entry, d, "illumination")
    return d


# A slope whose shift of the wall coordinate across the whole grid stays below this many
# pixels is the wall's normal (rounding of cos/sin of the inward directions).
_STRAIGHT = 1e-9


def _lit_measure(illum: Illumination, wall: str, lo: np.ndarray, hi: np.ndarray, extent: int):
    """Length of [lo, hi] (wall coordinates) that is lit, per pattern: shape (P, ...)."""

    def cumulative(u):
        u = np.clip(u, 0.0, extent)
        if isinstance(illum, Beam):
            t = math.radians(illum.direction_deg)
            normal_cos = abs(math.cos(t)) if along_x(wall) else abs(math.sin(t))
            centre = illum.y if along_x(wall) else illum.x
            half = 0.5 * illum.width / normal_cos
            return (np.clip(u, centre - half, centre + half) - (centre - half))[None]
        if isinstance(illum, Full):
            return u[None]
        # Stripes: lit cells r with (r + phase) mod period < lit, counted in closed form.
        period, lit = illum.period, illum.lit
        phases = np.asarray(illum.phases).reshape((-1,) + (1,) * u.ndim)
        cell = np.floor(u)
        frac = u - cell

        def lit_cells_before(m):  # number of lit cells r in [0, m)
            def count(n):
                return (n // period) * lit + np.minimum(np.mod(n, period), lit)

            return count(m + phases) - count(phases)

        in_cell = (np.mod(cell + phases, period) < lit) & (cell < extent)
        return lit_cells_before(cell) + frac * in_cell

    return cumulative(hi) - cumulative(lo)


def source_moments(
    illum: Illumination, width: int, height: int, supersample: int = 64
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel moments of the unscattered light, for each pattern.

    Returns ``(coverage, mean, var)``, each float64 of shape (patterns, height, width):
    the lit fraction of the pixel, and the mean and variance of d0 (distance back to the
    entry wall, pixels) over its lit part. The pixel-averaged unscattered fluence is then
    coverage·exp(−σt·mean + σt²·var/2) (second-order cumulant expansion; exact to
    O(σt⁴/2880) for the uniform spread of d0 across a pixel).

    d0 depends only on the coordinate normal to the entry wall; along the wall the lit
    length is computed exactly (the wall coordinate is a shift of the pixel's extent),
    and the normal coordinate is sampled at ``supersample`` midpoints per pixel.
    """
    wall = illum.entry_wall(width, height)
    t0 = math.radians(illum.direction_deg)
    c, s = math.cos(t0), math.sin(t0)
    sub = (np.arange(supersample) + 0.5) / supersample
    if along_x(wall):
        normal_n, along_n, extent = width, height, height
        wall_pos, cos_n, slope = (0.0 if wall == "left" else float(width)), c, s
    else:
        normal_n, along_n, extent = height, width, width
        wall_pos, cos_n, slope = (0.0 if wall == "top" else float(height)), s, c
    # Normal coordinate samples (normal_n, supersample) and their depth d0 ≥ 0.
    xn = np.arange(normal_n)[:, None] + sub[None, :]
    d0 = (xn - wall_pos) / cos_n
    # Pixel k along the wall covers [k, k+1]; its wall coordinate is shifted by −d0·slope.
    k = np.arange(along_n)[:, None, None]
    if abs(slope) * float(np.max(d0)) < _STRAIGHT:
        # Light along the wall's normal: a pixel's lit length is the same at every depth
        # across it, so the sums over the samples factor (the common case, and the
        # general one's (P, along, normal, samples) arrays cost seconds on a fit's grids).
        lit = _lit_measure(illum, wall, k[..., 0], k[..., 0] + 1.0, extent)  # (P, along, 1)
        m1 = lit * d0.sum(axis=-1)
        m2 = lit * (d0**2).sum(axis=-1)
        cnt = np.broadcast_to(lit * supersample, m1.shape)
    else:
        lo = k - d0[None] * slope
        lit = _lit_measure(illum, wall, lo, lo + 1.0, extent)  # (P, along, normal, sub)
        cnt = lit.sum(axis=-1)
        m1 = (lit * d0).sum(axis=-1)
        m2 = (lit * d0**2).sum(axis=-1)
    safe = np.where(cnt > 0, cnt, 1.0)
    cov = cnt / supersample
    mean = m1 / safe
    var = np.maximum(m2 / safe - mean**2, 0.0)
    if along_x(wall):  # (P, along=y, normal=x) is already (P, H, W)
        return cov, mean, var
    return (np.swapaxes(a, 1, 2) for a in (cov, mean, var))


def shifts_problem(n_shifts: int, same: bool) -> str | None:
    """What a fit refuses about a stripe capture's shifts (``None``: nothing): fewer
    than 2 images, or images that are all the same (``same``: the stripes moved
    nothing). The rule of the fit (:mod:`lightfield_jax.inverse.data`), and of a
    simulate config (:mod:`lightfield_jax.forward.simulate_config`), whose capture the fit reads."""
    if n_shifts < 2:
        return (
            "a fit needs at least 2 shifted images (the separation of the direct light "
            f"compares them), got {n_shifts}"
        )
    if same:
        return (
            f"the {n_shifts} shifts are the same image: the stripes moved nothing, so there "
            "is no direct light to separate"
        )
    return None


def unseparated_rows(period: int, lit: int, phases) -> str | None:
    """What rows of the period the ``phases`` leave never lit or never dark (the
    separation of the direct light needs each row lit in one shift and dark in
    another), e.g. ``"rows 3, 4 never lit and rows 0, 1 never dark"``; ``None``: none."""
    lit_rows = (np.arange(period)[:, None] + np.asarray(phases)[None]) % period < lit
    parts = [
        f"row{'s' if len(rows) > 1 else ''} {', '.join(map(str, rows))} never {how}"
        for rows, how in (
            (np.flatnonzero(~lit_rows.any(1)), "lit"),
            (np.flatnonzero(lit_rows.all(1)), "dark"),
        )
        if len(rows)
    ]
    return " and ".join(parts) or None


def period_problem(illumination, width: int, height: int, what: str = "grid") -> str | None:
    """What is wrong with stripes whose period is longer than a ``width``x``height``
    grid (``None``: nothing, or not stripes; ``illumination`` may be the period
    itself). The rule of a simulate config's ``illumination.period``
    (:mod:`lightfield_jax.forward.simulate_config`), for the Python API too: such stripes light at
    most one run of rows, and some of their shifts none at all (all-zero images)."""
    if isinstance(illumination, Stripes):
        period = illumination.period
    elif isinstance(illumination, int):
        period = illumination
    else:
        return None
    if period <= max(width, height):
        return None
    return (
        f"{period} rows is longer than the {width}x{height} {what}: a stripe period is a few rows"
    )


def cell_moments(illumination, width: int, rows: int):
    """Source moments of one period of ``illumination`` (phase 0, working grid) on a
    grid periodic in y: those of the last ``rows`` rows of a grid tall enough that no
    pixel there sees the top wall (an oblique sheet's backward ray climbs |tan θ0| rows
    per column)."""
    t0 = math.radians(illumination.direction_deg)
    climb = abs(math.tan(t0)) * width
    tall = rows * (math.ceil(climb / rows) + 2)
    moments = source_moments(illumination, width, tall)
    return tuple(m[:, tall - rows :] for m in moments)
