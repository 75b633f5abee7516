"""The discretisation: pixels × direction bins (MODEL.md section 1).

Pixel (r, c) covers [c, c+1) × [r, r+1); x grows right, y grows down. Direction bin j
is centred on θ_j = j·Δθ, Δθ = 2π/n_theta, θ measured from +x toward +y.
"""

from __future__ import annotations

import dataclasses

import numpy as np

# n_theta chosen from |g| when a grid does not give it: the smallest count whose
# per-bounce error against the Monte Carlo oracle stays within the accuracy contract
# (docs in README, measured by experiments/forward_accuracy.py).
_N_THETA_RULE: tuple[tuple[float, int], ...] = ((0.5, 32), (0.85, 64), (0.93, 128))
_N_THETA_MAX = 256


def default_n_theta(g: float) -> int:
    """Number of direction bins for a phase function of asymmetry ``g``.

    The forward lobe of p narrows like (1 − |g|); the bins must resolve it.
    """
    ag = abs(float(g))
    for limit, n in _N_THETA_RULE:
        if ag <= limit:
            return n
    return _N_THETA_MAX


@dataclasses.dataclass(frozen=True)
class Grid:
    """The (x, y, θ) grid. Sizes are static (they set array shapes).

    Attributes:
        width: number of pixel columns (x), ≥ 2.
        height: number of pixel rows (y), ≥ 2.
        n_theta: number of direction bins, a multiple of 8 (≥ 8), or ``None`` to choose
            it from g with :func:`default_n_theta` (see :meth:`resolve`).
    """

    width: int
    height: int
    n_theta: int | None = None

    def __post_init__(self):
        for name in ("width", "height"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 2:
                raise ValueError(f"grid.{name}: must be an integer >= 2, got {v!r}")
        n = self.n_theta
        if n is not None and (
            not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 8 or n % 8
        ):
            raise ValueError(f"grid.n_theta: must be a multiple of 8 (>= 8), got {n!r}")

    def resolve(self, g: float) -> Grid:
        """This grid with ``n_theta`` filled in from g when it was not given."""
        if self.n_theta is not None:
            return self
        return dataclasses.replace(self, n_theta=default_n_theta(g))

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
