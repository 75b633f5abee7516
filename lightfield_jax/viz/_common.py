"""Shared plumbing of the figure functions (matplotlib imported lazily)."""

from __future__ import annotations

from pathlib import Path

from lightfield_jax.capture.io import atomic_path


def new_figure(width: float, height: float):
    """A matplotlib Figure without pyplot (no global state, no display)."""
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), layout="constrained")


def finish(fig, path):
    """Write ``fig`` to ``path`` atomically (returning the path), or return ``fig``."""
    if path is None:
        return fig
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    return path
