"""Shared plumbing of the figure functions (matplotlib imported lazily)."""

from __future__ import annotations

import warnings
from pathlib import Path

from lightfield_jax.files import atomic_path


def new_figure(width: float, height: float):
    """A matplotlib Figure without pyplot (no global state, no display)."""
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), layout="constrained")


def finish(fig, path):
    """Write ``fig`` to ``path`` atomically (returning the path), or return ``fig``."""
    if path is None:
        return fig
    path = Path(path)
    with atomic_path(path) as tmp, warnings.catch_warnings():
        # matplotlib's layout notes (a legend or a title that leaves an axis no room)
        # are about drawing, not the user's data; the figure is written regardless.
        warnings.filterwarnings("ignore", category=UserWarning, module=r"matplotlib(\.|$)")
        fig.savefig(tmp, dpi=110)
    return path
