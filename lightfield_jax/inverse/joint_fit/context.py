"""What every step of one joint fit shares (:class:`FitContext`) and the seconds its
programs spent (:class:`Seconds`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import optimistix as optx

from lightfield_jax.inverse.data import FitData
from lightfield_jax.inverse.joint import BLACK_RANGE
from lightfield_jax.inverse.model_size import ModelSpec
from lightfield_jax.scene.illumination import Stripes

if TYPE_CHECKING:
    from lightfield_jax.inverse.settings import FitSettings


@dataclasses.dataclass(frozen=True)
class FitContext:
    """One joint fit's fixed inputs.

    Attributes:
        data: the capture inside the model's crop (its read-noise floor resolved).
        pattern: the stripes that lit it.
        options: the fit's options.
        black: the projector's dark-stripe level, or ``None``: fitted.
        weights: the data's noise weights (:func:`~.stage.joint_weights`), ``(P, h, w)``.
        images: the whole masked images (the final model is sized on them anew).
        floor: the smallest model to use, or ``None``.
        say: the progress printer.
        solver: the joint method's optimistix least-squares solver, or ``None``:
            Levenberg-Marquardt with the options' tolerances.
        start: the joint method's start (σs, g), or ``None``: the basin scan's.
    """

    data: FitData
    pattern: Stripes
    options: FitSettings
    black: float | None
    weights: np.ndarray
    images: np.ndarray
    floor: ModelSpec | None
    say: Callable[[str], None]
    solver: optx.AbstractLeastSquaresSolver | None = None
    start: tuple[float, float] | None = None

    @property
    def fit_black(self) -> bool:
        """Whether the black level is a fitted parameter."""
        return self.black is None

    @property
    def black_range(self) -> tuple[float, float] | None:
        """The fitted black level's range, ``None`` where it is given."""
        return BLACK_RANGE if self.fit_black else None


@dataclasses.dataclass
class Seconds:
    """Seconds spent compiling and running programs, added up over a fit."""

    compile: float = 0.0
    run: float = 0.0

    def add(self, compile: float, run: float) -> None:
        self.compile += compile
        self.run += run

    def add_from(self, spent) -> None:
        """Adds the seconds of ``spent`` (a stopwatch, a stage: ``compile``, ``run``)."""
        self.add(spent.compile, spent.run)

    def as_dict(self) -> dict:
        return {"compile": self.compile, "run": self.run}


__all__ = ["FitContext", "Seconds"]
