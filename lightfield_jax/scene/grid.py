"""The discretisation: pixels × direction bins (docs/model.md section 1).

Pixel (r, c) covers [c, c+1) × [r, r+1); x grows right, y grows down. Direction bin j
is centred on θ_j = j·Δθ, Δθ = 2π/n_theta, θ measured from +x toward +y.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from lightfield_jax.checks import check_number, number_problem

# n_theta chosen from |g| when a grid does not give it: the smallest count whose
# per-bounce error against the Monte Carlo oracle stays within the accuracy contract
# (docs in README, measured by experiments/forward_accuracy.py).
_N_THETA_RULE: tuple[tuple[float, int], ...] = ((0.5, 32), (0.85, 64), (0.93, 128))
_N_THETA_MAX = 256
# The most θ bins a grid takes: 16x the finest default. The renderer's direction tables
# grow as n_theta² (Grid(2, 2, 80000) or FitOptions(n_theta=80000) would end in a
# 47.7 GiB MemoryError, the fit's after 47 s).
N_THETA_LIMIT = 4096


# Spatial refinement chosen from |g| (see Grid.refine).
_REFINE_RULE: tuple[tuple[float, int], ...] = ((0.65, 1),)
_REFINE_MAX = 2
# The finest refinement a grid takes.
REFINE_LIMIT = 8


def default_refine(g: float) -> int:
    """Spatial refinement of the transport grid for a phase function of asymmetry g.

    Forward-peaked light scattered off a thin beam stays near it; the grid transport's
    interpolation diffuses it across rows (measured: I_3 4-5% off for g = 0.8 on the
    native grid, about half that on a 2x grid).
    """
    ag = abs(check_number(g, "g", low=-1.0, high=1.0, low_open=True, high_open=True))
    for limit, r in _REFINE_RULE:
        if ag <= limit:
            return r
    return _REFINE_MAX


def default_n_theta(g: float) -> int:
    """Number of direction bins for a phase function of asymmetry ``g``.

    The forward lobe of p narrows like (1 − |g|); the bins must resolve it.
    """
    ag = abs(check_number(g, "g", low=-1.0, high=1.0, low_open=True, high_open=True))
    for limit, n in _N_THETA_RULE:
        if ag <= limit:
            return n
    return _N_THETA_MAX


def check_n_theta(n, key: str = "grid.n_theta") -> None:
    """Refuse θ bins that are not ``None`` or a multiple of 8 (>= 8), naming ``key``."""
    if n is not None and (number_problem(n, integer=True, low=8) is not None or n % 8):
        raise ValueError(f"{key}: must be a multiple of 8 (>= 8), got {n!r}")
    if n is not None and n > N_THETA_LIMIT:
        raise ValueError(
            f"{key}: must be at most {N_THETA_LIMIT} direction bins (the finest default is "
            f"{_N_THETA_MAX}; the renderer's tables grow as n_theta squared), got {n!r}"
        )


def check_refine(r, key: str = "grid.refine") -> None:
    """Refuse a refinement that is not ``None`` or an integer in [1, REFINE_LIMIT],
    naming ``key``."""
    if r is not None and number_problem(r, integer=True, low=1, high=REFINE_LIMIT) is not None:
        raise ValueError(f"{key}: must be an integer in [1, {REFINE_LIMIT}], got {r!r}")


@dataclasses.dataclass(frozen=True)
class Grid:
    """The (x, y, θ) grid. Sizes are static (they set array shapes).

    Attributes:
        width: number of pixel columns (x), ≥ 2.
        height: number of pixel rows (y), ≥ 2.
        n_theta: number of direction bins, a multiple of 8 (≥ 8), or ``None`` to choose
            it from g with :func:`default_n_theta` (see :meth:`resolve`).
        refine: the renderer works on a grid ``refine`` times finer in x and y and
            averages back to these pixels (accuracy for forward-peaked scattering at
            refine² the cost), or ``None`` to choose it from g (:func:`default_refine`).
    """

    width: int
    height: int
    n_theta: int | None = None
    refine: int | None = None

    def __post_init__(self):
        for name in ("width", "height"):
            v = getattr(self, name)
            if number_problem(v, integer=True, low=2) is not None:
                raise ValueError(f"grid.{name}: must be an integer >= 2, got {v!r}")
        check_n_theta(self.n_theta)
        check_refine(self.refine)

    def resolve(self, g: float) -> Grid:
        """This grid with ``n_theta`` and ``refine`` filled in from g where not given."""
        n = default_n_theta(g) if self.n_theta is None else self.n_theta
        r = default_refine(g) if self.refine is None else self.refine
        return dataclasses.replace(self, n_theta=n, refine=r)

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape (height, width)."""
        return (self.height, self.width)

    @property
    def dtheta(self) -> float:
        return 2.0 * np.pi / self._n()

    @property
    def thetas(self) -> np.ndarray:
        """Bin centres θ_j = j·Δθ in radians."""
        return np.arange(self._n()) * self.dtheta

    def _n(self) -> int:
        if self.n_theta is None:
            raise ValueError("grid.n_theta is not set: call Grid.resolve(g) first")
        return self.n_theta
