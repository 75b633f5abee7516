"""Shared pieces of the inverse-problem experiments (speed/accuracy, stability, model size).

- Captures: :func:`simulate` renders a stripe capture of a medium (the package's
  :func:`~lightfield_jax.simulate_capture`: Poisson photons + Gaussian read noise, gain,
  black level) and :func:`perfect_split` the true direct/multiple split (I_1 and
  Σ_{k≥2} I_k under full illumination), which removes the separation's bias.
- Errors: σt and σs relative, g absolute; ``error`` (the charts' one number) is the
  largest of the three, |Δσt|/σt, |Δσs|/σs and |Δg|.
- :func:`fit_record`: one :func:`~lightfield_jax.fit_images` call as a JSON-ready record
  (an exception becomes a record with ``error_message``; :data:`OWN_MODEL`: the
  captures are the model's own renders, so the fit reports the model's own answer),
  and :func:`failure`, why a fit failed: ``timeout``, ``exception``, ``non-finite``,
  ``divergent`` (ρ = ω·A(g) ≥ 1 under ``phase: paper``), ``not converged``,
  ``ill-conditioned``, ``biased``, or ``ok``;
  :func:`fit_record_limited` runs a fit on a Dask worker with a time limit.
- :func:`camera`: a capture scaled to peak 1 with the package's noise model, so that
  photon counts and read noise are relative to the brightest pixel.
- :func:`precision`: the dtype the experiment runs in, whatever the caller's x64 flag.
- :func:`xla_cache`: JAX's persistent compilation cache for a block (sweeps refit
  captures of the same shape; compile times under it are not cold ones).
- :func:`library_fingerprint`: a hash of the package's source, in every cache key.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import os
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import jax
import numpy as np

import lightfield_jax as lfj
from lightfield_jax.app.experiment import ExperimentError
from lightfield_jax.forward.simulate_config import NoiseConfig, parse_simulation_config

PARAMS = ("sigma_t", "sigma_s", "g")


@functools.cache
def library_fingerprint() -> str:
    """A hash of the package's source: part of every cache key, so that a rerun after
    the package changed recomputes instead of mixing results of two versions."""
    import hashlib
    from pathlib import Path

    root = Path(lfj.__file__).resolve().parent
    h = hashlib.sha1()
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:12]


@contextlib.contextmanager
def precision(dtype: str) -> Iterator[None]:
    """Run in ``float32`` (the package's default) or ``float64``."""
    if dtype not in ("float32", "float64"):
        raise ValueError(f"dtype: must be float32 or float64, got {dtype!r}")
    with jax.enable_x64(dtype == "float64"):
        yield


@contextlib.contextmanager
def xla_cache(folder) -> Iterator[None]:
    """JAX's persistent compilation cache in ``folder`` for the block (``None``: off)."""
    if folder is None:
        yield
        return
    from jax.experimental.compilation_cache import compilation_cache

    from lightfield_jax.inverse.programs import use_compilation_cache

    names = (
        "jax_compilation_cache_dir",
        "jax_compilation_cache_max_size",
        "jax_enable_compilation_cache",
        "jax_persistent_cache_min_compile_time_secs",
        "jax_persistent_cache_min_entry_size_bytes",
    )
    before = {n: getattr(jax.config, n) for n in names}
    use_compilation_cache(Path(folder))  # (locked: the sweep's processes share it)
    try:
        yield
    finally:
        for n, v in before.items():
            jax.config.update(n, v)
        compilation_cache.reset_cache()


def capture_config(
    medium: dict,
    width: int,
    height: int,
    *,
    period: int = 6,
    lit: int = 3,
    phases=None,
    noise: dict | None = None,
    black_level: float | None = None,
    gain: float = 1.0,
    bounces: int | str = "auto",
    n_theta: int | None = None,
) -> dict:
    """A ``simulate`` config (plain dict) of a stripe capture of ``medium``
    (keys sigma_t, sigma_s, g, optional phase)."""
    grid = {"width": width, "height": height}
    if n_theta is not None:
        grid["n_theta"] = n_theta
    illum = {"kind": "stripes", "period": period, "lit": lit}
    illum["phases"] = list(range(period)) if phases is None else list(phases)
    cfg = {
        "grid": grid,
        # The experiments fit under FitOptions' phase (paper unless a medium says):
        # the simulated truth follows the same convention, not the files' default.
        "medium": {
            **{k: medium[k] for k in ("sigma_t", "sigma_s", "g")},
            "phase": medium.get("phase", "paper"),
        },
        "illumination": illum,
        "bounces": bounces,
        "gain": gain,
    }
    if noise:
        cfg["noise"] = dict(noise)
    if black_level is not None:
        cfg["black_level"] = black_level
    return cfg


@dataclasses.dataclass(frozen=True, kw_only=True)
class MediumSpec:
    """A config's medium (``Annotated[dict, MediumSpec]``): σt, σs per pixel, g, phase;
    their ranges are checked by :func:`check_simulation_config`."""

    sigma_t: float
    sigma_s: float
    g: float
    phase: str = "paper"


@dataclasses.dataclass(frozen=True, kw_only=True)
class NamedMedium(MediumSpec):
    """A medium with a ``name``."""

    name: str


def check_simulation_config(cfg: dict, where: str) -> None:
    """A :func:`capture_config` checked as ``simulate`` checks its config (the medium,
    the grid, the bounces, a geometry), before any render; errors name ``where``."""
    parse_simulation_config(cfg, source=where)


def simulate(cfg: dict) -> lfj.SimulatedCapture:
    """The capture of a :func:`capture_config`; a divergent truth (ρ ≥ 1 under ``paper``,
    an explicit truncation) is allowed here: the caller records ``sim.converges``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", lfj.DivergentSeriesWarning)
        return lfj.simulate_capture(parse_simulation_config(cfg, source="experiment capture"))


def camera(images: np.ndarray, noise, seed: int) -> np.ndarray:
    """Noise-free images scaled to peak 1, with the package's camera noise:
    ``noise = (photons at value 1 or None, read noise σ)``, or ``None`` for none."""
    images = images / float(np.max(images))
    if noise is None:
        return images.astype(np.float32)
    photons, read = noise
    cfg = NoiseConfig(photons=photons, read=read, seed=seed)
    return cfg.apply(images, np.random.default_rng(seed)).astype(np.float32)


def perfect_split(sim: lfj.SimulatedCapture) -> tuple[np.ndarray, np.ndarray]:
    """(I_1, Σ_{k≥2} I_k) under full illumination, gain included: what an exact
    separation would give. Needs phases that tile the period and no black level."""
    illum = sim.config.illumination
    if sorted(p % illum.period for p in illum.phases) != list(range(illum.period)):
        raise ValueError("perfect_split: the phases must tile the stripe period")
    if sim.config.black_level:
        raise ValueError("perfect_split: needs a capture without black level")
    full = sim.bounces.sum(axis=0) / illum.lit
    return full[0], full[1:].sum(axis=0)


def truth_of(medium: dict) -> dict:
    return {k: float(medium[k]) for k in PARAMS}


def errors(values: dict, truth: dict) -> dict:
    """σt, σs relative, g absolute errors and ``error``, the largest magnitude."""
    e = {
        "sigma_t": values["sigma_t"] / truth["sigma_t"] - 1.0,
        "sigma_s": values["sigma_s"] / truth["sigma_s"] - 1.0,
        "g": values["g"] - truth["g"],
    }
    mags = [abs(v) for v in e.values()]
    e["error"] = max(mags) if all(math.isfinite(m) for m in mags) else math.inf
    return e


def _finite_or_none(v):
    v = float(v)
    return v if math.isfinite(v) else None


def result_record(res: lfj.FitResult, truth: dict) -> dict:
    """The JSON-ready record of a fit: values, errors and how far to trust them."""
    values = {k: float(getattr(res, k)) for k in PARAMS}
    finite = all(math.isfinite(v) for v in values.values())
    return {
        **{k: _finite_or_none(v) for k, v in values.items()},
        "errors": {k: _finite_or_none(v) for k, v in errors(values, truth).items()},
        "finite": finite,
        "converged": bool(res.converged),
        "message": res.message,
        "iterations": int(res.iterations),
        "rho": _finite_or_none(res.rho) if finite else None,
        "condition_number": _finite_or_none(res.condition_number),
        "uncertainty": {k: _finite_or_none(res.uncertainty.get(k, math.nan)) for k in PARAMS},
        "seconds": {k: float(v) for k, v in res.seconds.items()},
        "model": res.model,
    }


# The fit keywords for a capture that :func:`simulate` rendered on the grid the fit's
# model uses (θ bins and refinement from g): that model's own answer is its truth, so
# the answer is not extrapolated to the continuum (the default for refined models,
# checked against Monte Carlo captures instead, tests/test_dense_media.py).
OWN_MODEL = {"extrapolate": False}


def fit_record(images, pattern, truth: dict, **kwargs) -> dict:
    """:func:`~lightfield_jax.fit_images` on ``images`` as a record (with
    :data:`OWN_MODEL` unless ``kwargs`` give ``options`` or ``extrapolate``); an
    exception is recorded (``error_message``), not raised: failures are data here."""
    if "options" not in kwargs:
        kwargs = {**OWN_MODEL, **kwargs}
    t = time.perf_counter()
    load = os.getloadavg()[0]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", lfj.DivergentSeriesWarning)
            res = lfj.fit_images(images, pattern, **kwargs)
    except (ValueError, FloatingPointError, RuntimeError) as e:
        return {
            "error_message": f"{type(e).__name__}: {e}",
            "finite": False,
            "converged": False,
            "errors": {k: None for k in (*PARAMS, "error")},
            "seconds": {"total": time.perf_counter() - t, "compile": None, "run": None},
            "load_avg": load,
        }
    return {**result_record(res, truth), "load_avg": load}


def fit_record_limited(
    images,
    pattern: lfj.Stripes,
    truth: dict,
    *,
    timeout: float,
    dtype: str,
    xla_cache_dir,
    **kwargs,
) -> dict:
    """:func:`fit_record` on a Dask worker, stopped after ``timeout`` seconds (a fit's
    cost follows the model its start asks for and is otherwise unbounded); a stopped fit
    is recorded with ``timeout`` set. The worker is the experiment run's cluster's
    (:func:`~lightfield_jax.app.experiment.current_client`; outside a run, a local one
    of one worker for this fit), and shares the persistent XLA cache. A ``geometry``
    keyword (a :class:`~lightfield_jax.Slab`) is passed as its dict. A worker that died
    twice under the fit, or a fit that raised, is an ``ExperimentError`` (one line)."""
    import contextlib
    import uuid

    from lightfield_jax.app.distributed import Task, cluster, run_tasks
    from lightfield_jax.app.experiment import current_client

    t = time.perf_counter()
    load = os.getloadavg()[0]
    if kwargs.get("geometry") is not None:  # a Plane or Slab travels as its dict
        kwargs = {**kwargs, "geometry": kwargs["geometry"].as_dict()}
    args = (
        np.asarray(images),
        pattern.as_dict(),
        truth,
        kwargs,
        dtype,
        None if xla_cache_dir is None else str(xla_cache_dir),
    )
    task = Task(uuid.uuid4().hex, "a fit on a Dask worker failed", _limited_fit, args)

    def timed_out(_task, limit: float) -> dict:
        return {
            "error_message": f"timeout: no result within {limit:g} s",
            "timeout": True,
            "timeout_s": limit,
            "finite": False,
            "converged": False,
            "errors": {k: None for k in (*PARAMS, "error")},
            "seconds": {"total": time.perf_counter() - t, "compile": None, "run": None},
        }

    with contextlib.ExitStack() as stack:
        client = current_client() or stack.enter_context(cluster(workers=1))
        report = run_tasks(
            [task],
            load=lambda _t: None,
            save=lambda _t, _v: None,
            client=client,
            timeout=timeout,
            on_timeout=timed_out,
            show_progress=False,
        )
    if report.failures:
        raise ExperimentError(report.failures[task.key])
    rec = dict(report.results[task.key])
    rec["load_avg"] = load
    return rec


def _limited_fit(images, pattern: dict, truth, kwargs: dict, dtype: str, xla_cache_dir):
    """:func:`fit_record_limited`'s fit, on the worker."""
    pattern = lfj.Stripes(**{**pattern, "phases": tuple(pattern["phases"])})
    kwargs = dict(kwargs)
    if kwargs.get("geometry") is not None:
        from lightfield_jax.scene.geometry_spec import parse_geometry

        kwargs["geometry"] = parse_geometry(kwargs["geometry"], "geometry")
    with precision(dtype), xla_cache(xla_cache_dir):
        return jsonable(fit_record(images, pattern, truth, **kwargs))


def failure(
    rec: dict,
    *,
    truth_rho: float | None = None,
    bias: float = 0.05,
    ill_conditioned: float = 1e6,
) -> str:
    """Why a fit failed (the first that applies), or ``ok``.

    ``divergent`` is the truth's ρ ≥ 1 (``paper``): no convergent model exists.
    ``biased``: converged, finite, but ``error`` above ``bias``; ``ill-conditioned`` when
    such a result's condition number (unit-free, of JᵀJ) also exceeds
    ``ill_conditioned``: the data barely constrain some combination of parameters.
    """
    if rec.get("timeout"):
        return "timeout"
    if "error_message" in rec:
        return "exception"
    if not rec["finite"]:
        return "non-finite"
    if truth_rho is not None and truth_rho >= 1.0:
        return "divergent"
    if not rec["converged"]:
        return "not converged"
    if rec["errors"]["error"] is None or rec["errors"]["error"] > bias:
        cond = rec.get("condition_number")
        return "ill-conditioned" if cond is None or cond > ill_conditioned else "biased"
    return "ok"


FAILURES = (
    "ok",
    "biased",
    "ill-conditioned",
    "not converged",
    "divergent",
    "non-finite",
    "exception",
)


def jsonable(obj):
    """``obj`` with NaN and infinities as ``None`` (strict JSON) and tuples as lists."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def log_axes(ax, x: bool = True, y: bool = True) -> None:
    """Log axes labelled at 1, 2, 5 × 10^k (short ranges get labels too)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    for on, axis, scale in ((x, ax.xaxis, ax.set_xscale), (y, ax.yaxis, ax.set_yscale)):
        if on:
            scale("log")
            axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            axis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:.3g}"))
            axis.set_minor_formatter(NullFormatter())


def median(values) -> float:
    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    return float(np.median(v)) if v else math.nan
