"""What an experiment records besides its own data, written once for every script: the
run's provenance (software versions, machine, date), CSV tables and figures (matplotlib
imported on first use: the package does not import it)."""

from __future__ import annotations

import csv
import os
import platform
import sys
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from lightfield_jax.files import atomic_path


def versions() -> dict[str, str]:
    """Versions of the software an experiment ran with."""
    import equinox
    import jax
    import numpy
    import optimistix

    from lightfield_jax import __version__

    return {
        "lightfield_jax": __version__,
        "python": sys.version.split()[0],
        "jax": jax.__version__,
        "equinox": equinox.__version__,
        "optimistix": optimistix.__version__,
        "numpy": numpy.__version__,
    }


def machine() -> dict[str, Any]:

    import jax

    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "devices": [str(d) for d in jax.devices()],
    }


def provenance() -> dict[str, Any]:
    """What a measurement's JSON records besides its numbers: the software's versions,
    the machine and the date (UTC)."""
    return {
        "versions": versions(),
        "machine": machine(),
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def write_csv(path: Path, header: Sequence[str], rows: Iterable[Sequence]) -> Path:
    """A CSV table (``header``, then one line per row), written atomically."""
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)
    return Path(path)


def pyplot():
    """matplotlib's pyplot on the non-interactive Agg backend (imported on first use:
    the package does not import matplotlib)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path, dpi: int = 110) -> Path:
    """Write ``fig`` to ``path`` atomically at ``dpi`` and close it; returns the path."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi)
    pyplot().close(fig)
    return Path(path)
