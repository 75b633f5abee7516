"""What fit methods share: the abstract :class:`FitMethod` (one :meth:`~FitMethod.solve`
signature over the settings that are not a method's,
:class:`~lightfield_jax.inverse.settings.FitSettings`), the method names
(:func:`check_method`) and the checks of their own settings (:func:`check_solver`,
:func:`check_start`, :data:`MAX_G_VALUES`). The methods themselves are
:mod:`lightfield_jax.inverse.methods`; :class:`~lightfield_jax.FitOptions` (above both)
holds one.
"""

from __future__ import annotations

import abc
import dataclasses
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, ClassVar

import equinox as eqx
import numpy as np
import optimistix as optx

from lightfield_jax.checks import check_int, number_problem, shown

if TYPE_CHECKING:
    from lightfield_jax.inverse.data import FitProblem, FitSolution
    from lightfield_jax.inverse.settings import FitSettings

# The names of the methods (:data:`lightfield_jax.inverse.methods.METHODS`'s keys).
METHOD_NAMES = ("joint", "gradient", "grid")


def check_solver(solver, key: str = "solver") -> None:
    """Refuse anything but ``None`` or an optimistix least-squares solver."""
    if solver is not None and not isinstance(solver, optx.AbstractLeastSquaresSolver):
        raise ValueError(
            f"{key}: must be an optimistix least-squares solver (e.g. "
            f"optx.LevenbergMarquardt, optx.Dogleg, optx.GaussNewton), got "
            f"{type(solver).__name__}"
        )


def check_start(start, key: str = "start") -> tuple[float, float] | None:
    """A joint start (σs > 0, |g| < 1) as a tuple of two floats (``None`` as given), or
    ``ValueError``. A tuple, so that the options stay hashable and comparable (a list or
    an array would make them unhashable, ``==`` between them an error); strings and
    ``True`` are not numbers here."""
    if start is None:
        return None
    refused = ValueError(f"{key}: must be (sigma_s > 0, |g| < 1), got {shown(start)}")
    if isinstance(start, (str, bytes)):
        raise refused
    try:
        items = tuple(start)
    except TypeError:
        raise refused from None
    if len(items) != 2 or any(number_problem(v) is not None for v in items):
        raise refused
    ss, g = (float(v) for v in items)
    if not (0 < ss < math.inf and abs(g) < 1):
        raise refused
    return ss, g


class FitMethod(eqx.Module):
    """A fit method: :meth:`solve` turns a prepared capture into fitted values."""

    name: eqx.AbstractClassVar[str]
    # Whether the method needs every bounce's image (the two-step residual is a
    # polynomial in σs over them): its models march at most ``max_bounces``, never a
    # tail solve (the fit sizes them with ``tail: None``).
    per_bounce: ClassVar[bool] = False
    # The flat FitOptions keywords of this method's own settings (a capture file's fit:
    # keys), each with the field it sets.
    option_names: ClassVar[dict[str, str]] = {}

    def own_options(self) -> dict:
        """This method's own settings that are not its defaults, by their flat
        :class:`~lightfield_jax.FitOptions` keywords."""
        defaults = {f.name: f.default for f in dataclasses.fields(self)}
        out = {}
        for key, field in self.option_names.items():
            value, default = getattr(self, field), defaults[field]
            if not (value is default or (type(value) is type(default) and value == default)):
                out[key] = value
        return out

    @abc.abstractmethod
    def solve(
        self, problem: FitProblem, options: FitSettings, say: Callable[[str], None]
    ) -> FitSolution:
        """Fit ``problem`` with the settings of ``options`` besides the method's own;
        ``say`` reports each stage. Returns the model used, the seconds (``compile``,
        ``run``) and the values the :class:`~lightfield_jax.FitResult` is built from."""


# The most g values a search takes (g_grid, start_grid, g_values): 5 times the densest
# grid the experiments run (20481, configs/inverse_speed_accuracy.yaml); g_grid 10**9
# (a billion g values) would run until killed.
MAX_G_VALUES = 100_000


def check_start_grid(value) -> int:
    """``start_grid``, the gradient method's search for its start: 0 (none) or its
    number of g values (3 to :data:`MAX_G_VALUES`), as an int, or ``ValueError``."""
    if not (number_problem(value, integer=True) is None and (value == 0 or value >= 3)):
        raise ValueError(f"start_grid: must be 0 (no search) or at least 3, got {value!r}")
    return check_int(value, "start_grid", high=MAX_G_VALUES)


# The flat settings that are a fit method's own (FitOptions(g_grid=...), a capture file's
# fit: keys): each method names those it takes (FitMethod.option_names).
METHOD_KEYS = ("g_grid", "start_grid", "start", "solver")


def check_method_setting(key: str, value):
    """The flat method setting ``key`` (one of :data:`METHOD_KEYS`) checked as every
    method would, whichever method takes it (a capture file's ``fit:`` keys are checked
    before the command chooses the method): ``value`` as stored, or ``ValueError``."""
    if isinstance(value, np.generic) or (isinstance(value, np.ndarray) and value.ndim == 0):
        value = value.item()
    if key == "g_grid":
        check_int(value, "g_grid", low=3, high=MAX_G_VALUES)
    elif key == "start_grid":
        check_start_grid(value)
    elif key == "start":
        value = check_start(value)  # a tuple of floats
    else:
        check_solver(value)
    return value


def check_method(method) -> str:
    """The name of a fit method given as a known name or a :class:`FitMethod`, or
    ``ValueError``."""
    if isinstance(method, FitMethod):
        return method.name
    if method not in METHOD_NAMES:
        raise ValueError(
            f"method: must be one of {', '.join(METHOD_NAMES)} or a FitMethod, got {method!r}"
        )
    return method


__all__ = [
    "MAX_G_VALUES",
    "METHOD_KEYS",
    "METHOD_NAMES",
    "FitMethod",
    "check_method",
    "check_method_setting",
    "check_solver",
    "check_start",
    "check_start_grid",
]
