"""Where does each inverse method fail, and why?

Recovery error and convergence of ``grid``, ``gradient`` and ``joint`` (``methods``)
on small simulated stripe captures (``width`` × ``height``), over:

- ``albedo_g``: albedo ω × asymmetry g at fixed σt (noiseless). The region where the
  paper's bounce series diverges, ρ = ω·A(g) ≥ 1 under ``phase: paper``, is drawn as
  the contour ρ = 1; captures there are an explicit truncation after
  ``divergent_bounces`` bounces (no convergent truth exists), captures near it are
  truncated at ``max_truth_bounces`` (the record keeps the tail bound). These truths are
  rendered in batches, one per (g, bounces) group: ``vmap`` over the albedos
  (``experiments/_batch.py``, sharded when several devices exist).
- ``noise``: photons at the brightest pixel (Poisson) and Gaussian read noise (as a
  fraction of the brightest pixel): every capture is scaled to peak 1 first.
- ``period``: stripe period against the mean free path 1/σt (the separation's bias).
- ``shifts``: the number of shifted images (phases of a period-6, lit-3 pattern).
- ``black_level``: the projector's dark-stripe level b, given to the fit (``known``)
  or not (two-step methods then assume 0; ``joint`` estimates it).
- ``start`` (``joint`` only): the joint fit started away from the truth, σs × a
  factor, g + an offset (``Joint.start``; σt comes from the decay fit: it has no
  start), the basin search off.
- ``high_albedo``: albedo × g near ω = 1 under ``phase: normalized`` (captures and
  fits), where ρ = ω < 1: the series converges but slowly. Truths are marched to the
  bounces ``tolerance`` needs, capped at the row's ``max_truth_bounces``; the record
  keeps the a-priori tail bound ρ^K/(1 − ρ) and the tail measured on the render (the
  last bounce's energy extrapolated geometrically with its ratio to the one before).
- ``refractive_slab``: media captured by the slab model with refractive faces (the
  row's ``geometry``) and fitted with the same slab (the fit setting ``geometry``).

Both rows take their own ``methods`` (default: the config's) and ``joint_timeout``
(default: the config's), and report each fit's time (``high_albedo.png``,
``refractive_slab.png``).

Each fit's outcome is classified (:func:`_inverse.failure`): ``ok`` (error at most
``bias_threshold``), ``biased`` (converged, finite, error above it), ``ill-conditioned``
(biased and the unit-free condition number of JᵀJ above ``ill_conditioned``), ``not
converged`` (the solver says so), ``divergent`` (the truth has ρ ≥ 1), ``non-finite``
(NaN or inf returned), ``exception``, ``timeout`` (``joint`` runs on a Dask worker
stopped after ``joint_timeout`` seconds: its cost follows the model its start asks for,
up to 256 θ bins, refinement 2 and 60 bounces). Error = max(|Δσt|/σt, |Δσs|/σs, |Δg|).

Every fit is one cached unit (resume). With ``xla_cache`` the persistent XLA cache
(``OUT/xla_cache``) spares recompiling identical solves: compile times here are then
not cold ones (``inverse_speed_accuracy`` measures those).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import textwrap
import time
from pathlib import Path
from typing import Annotated

import numpy as np

import lightfield_jax as lfj
from lightfield_jax.app.experiment import load_helper
from lightfield_jax.app.experiment_config import (
    Dtype,
    Pixels,
    Positive,
    Range,
    check_choices,
    typed_config,
)
from lightfield_jax.app.experiment_records import pyplot, save_figure, write_csv
from lightfield_jax.inverse.methods import METHODS
from lightfield_jax.scene.geometry_spec import parse_geometry

inv = load_helper("_inverse")
batch = load_helper("_batch")

SWEEPS = ("noise", "period", "shifts", "black_level")
# Rows with their own captures (phase, geometry), methods, truth cap and time limit.
ROWS = ("high_albedo", "refractive_slab")
Albedo = Annotated[float, Range(0, 1, open_low=True, open_high=True)]
G = Annotated[float, Range(-0.99, 0.99)]
Bounces = Annotated[int, Range(1, 100_000)]
Timeout = Annotated[float, Range(0, 86_400, open_low=True)]  # seconds


def _at_least_one(spec, key: str) -> None:
    """Refuse an empty list in a sweep's or row's mapping ``key`` (and an empty phase set
    in ``shifts.phases``): before, ``albedo_g.albedo: []`` ended in scipy's "array of
    sample points is empty", an empty ``noise``, ``period``, ``shifts``,
    ``black_level`` or ``start`` list ran and published empty tables and figures (exit
    0), and a row's ``methods: []`` ran the top level's methods."""
    for field in dataclasses.fields(spec):
        value = getattr(spec, field.name)
        if isinstance(value, tuple) and not value:
            raise ValueError(f"stability_maps: {key}.{field.name}: at least one value, got []")
        if isinstance(value, tuple) and any(v == () for v in value):
            i = value.index(())
            raise ValueError(f"stability_maps: {key}.{field.name}[{i}]: at least one value, got []")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Coefficients:
    """A medium: σt, σs per pixel (σs ≤ σt), g."""

    sigma_t: Positive
    sigma_s: Annotated[float, Range(0)]
    g: G

    def __post_init__(self):
        if self.sigma_s > self.sigma_t:
            raise ValueError(f"stability_maps: sigma_s {self.sigma_s} > sigma_t {self.sigma_t}")


@dataclasses.dataclass(frozen=True, kw_only=True)
class NamedCoefficients(Coefficients):
    name: str


@dataclasses.dataclass(frozen=True)
class AlbedoG:
    sigma_t: Positive
    albedo: tuple[Albedo, ...]
    g: tuple[G, ...]

    def __post_init__(self):
        _at_least_one(self, "albedo_g")


@dataclasses.dataclass(frozen=True)
class NoiseSweep:
    """``levels``: [photons at the peak (null: none), read noise / peak] pairs."""

    levels: tuple[tuple[float | None, ...], ...]

    def __post_init__(self):
        _at_least_one(self, "noise")
        for level in self.levels:
            photons, read = level if len(level) == 2 else (-1, -1)
            if not ((photons is None or photons > 0) and read is not None and read >= 0):
                raise ValueError(
                    f"stability_maps: noise.levels: [photons > 0 or null, read >= 0], got {level}"
                )


@dataclasses.dataclass(frozen=True)
class PeriodSweep:
    sigma_t: tuple[Positive, ...]
    period: tuple[Annotated[int, Range(2, 1000)], ...]

    def __post_init__(self):
        _at_least_one(self, "period")


@dataclasses.dataclass(frozen=True)
class ShiftsSweep:
    phases: tuple[tuple[Annotated[int, Range(0, 5)], ...], ...]  # of period 6

    def __post_init__(self):
        _at_least_one(self, "shifts")


@dataclasses.dataclass(frozen=True)
class BlackLevelSweep:
    levels: tuple[Annotated[float, Range(0, 1)], ...]
    known: tuple[bool, ...]

    def __post_init__(self):
        _at_least_one(self, "black_level")


@dataclasses.dataclass(frozen=True)
class StartMap:
    media: tuple[Annotated[dict, NamedCoefficients], ...]
    sigma_s_factor: tuple[Positive, ...]
    g_offset: tuple[float, ...]

    def __post_init__(self):
        _at_least_one(self, "start")


@dataclasses.dataclass(frozen=True, kw_only=True)
class RowSettings:
    """A row's own methods, truth cap and joint time limit (default: the top level's)."""

    methods: tuple[str, ...] | None = None
    max_truth_bounces: Bounces | None = None
    joint_timeout: Timeout | None = None


@dataclasses.dataclass(frozen=True, kw_only=True)
class HighAlbedo(RowSettings):
    sigma_t: Positive
    albedo: tuple[Albedo, ...]
    g: tuple[G, ...]

    def __post_init__(self):
        _at_least_one(self, "high_albedo")


@dataclasses.dataclass(frozen=True, kw_only=True)
class RefractiveSlab(RowSettings):
    geometry: dict
    media: tuple[Annotated[dict, NamedCoefficients], ...]

    def __post_init__(self):
        _at_least_one(self, "refractive_slab")
        where = "stability_maps: refractive_slab.geometry"
        if not isinstance(parse_geometry(self.geometry, where), lfj.Slab):
            raise ValueError(f"{where}: must be a slab")


@dataclasses.dataclass(frozen=True)
class Config:
    """configs/stability_maps.yaml: the captures (pixels), the methods, the 1-D sweeps'
    ``base`` medium, the persistent XLA cache, the outcome thresholds, the truths'
    bounces, the joint fit's time limit (s), the albedo × g map and the optional sweeps
    (``noise``, ``period``, ``shifts``, ``black_level``), ``start`` and rows
    (``high_albedo``, ``refractive_slab``) (null or absent: skipped)."""

    dtype: Dtype
    width: Pixels
    height: Pixels
    methods: tuple[str, ...]
    base: Annotated[dict, Coefficients]
    xla_cache: bool
    bias_threshold: Positive
    ill_conditioned: Positive
    divergent_bounces: Bounces
    max_truth_bounces: Bounces
    tolerance: Annotated[float, Range(0, 0.1, open_low=True)]
    joint_timeout: Timeout
    albedo_g: Annotated[dict, AlbedoG] | None = None
    noise: Annotated[dict, NoiseSweep] | None = None
    period: Annotated[dict, PeriodSweep] | None = None
    shifts: Annotated[dict, ShiftsSweep] | None = None
    black_level: Annotated[dict, BlackLevelSweep] | None = None
    start: Annotated[dict, StartMap] | None = None
    high_albedo: Annotated[dict, HighAlbedo] | None = None
    refractive_slab: Annotated[dict, RefractiveSlab] | None = None

    def __post_init__(self):
        check_choices("stability_maps", "methods", self.methods, METHODS)
        if not self.methods:
            raise ValueError("stability_maps: methods: at least one")
        for name in ROWS:
            spec = getattr(self, name)
            if spec is not None:
                methods = spec.get("methods") or ()
                check_choices("stability_maps", f"{name}.methods", methods, METHODS)


def _row(config: Config, name: str) -> dict:
    """A row's settings with their defaults: methods, truth cap, joint time limit."""
    spec = getattr(config, name)
    return {
        "methods": tuple(spec.get("methods") or config.methods),
        "max_truth_bounces": int(spec.get("max_truth_bounces") or config.max_truth_bounces),
        "joint_timeout": float(spec.get("joint_timeout") or config.joint_timeout),
    }


# ------------------------------------------------------------------------ captures


def _rho(medium: dict) -> float:
    """ρ of the tail bound: ω·A(g) under ``phase: paper`` (the default), ω under
    ``normalized`` (also a slab's: its phase function is normalised on the sphere)."""
    albedo = medium["sigma_s"] / medium["sigma_t"]
    if medium.get("phase", "paper") == "normalized":
        return albedo
    return albedo * float(lfj.phase_integral(medium["g"]))


def _truth_bounces(medium: dict, config: Config, cap: int | None = None) -> tuple[int, str]:
    """Bounces of a truth and how they were chosen (``auto``, ``capped``, ``divergent``);
    ``cap``: the most bounces (default ``max_truth_bounces``)."""
    cap = config.max_truth_bounces if cap is None else cap
    rho = _rho(medium)
    if rho >= 1.0:
        return config.divergent_bounces, "divergent"
    k = lfj.bounces_for_tolerance(rho, config.tolerance, max_bounces=100_000)
    if k > cap:
        return cap, "capped"
    return k, "auto"


def _tail_bound(rho: float, k: int) -> float | None:
    """The a-priori relative tail after K bounces, ρ^K/(1 − ρ) (None: ρ ≥ 1)."""
    return rho**k / (1.0 - rho) if rho < 1.0 else None


def _capture_cfg(cell: dict, config: Config, cap: int | None = None) -> dict:
    """The ``simulate`` config of a cell's noise-free capture: its stripes, black level
    and geometry, the truth's bounces (:func:`_truth_bounces`, at most ``cap``)."""
    k, _how = _truth_bounces(cell["medium"], config, cap)
    cfg = inv.capture_config(
        cell["medium"],
        config.width,
        config.height,
        period=cell["period"],
        lit=cell["lit"],
        phases=cell["phases"],
        black_level=cell.get("black_level") or None,
        bounces=k,
    )
    if cell.get("geometry"):
        cfg["geometry"] = dict(cell["geometry"])
    return cfg


def _simulated(cell: dict, config: Config) -> np.ndarray:
    """A cell's noise-free capture through ``simulate_capture`` (stripes, black level)."""
    return inv.simulate(_capture_cfg(cell, config)).images


class _BatchedTruths:
    """Noise-free stripe captures of many media, rendered in groups of equal (g, K):
    one :func:`_batch.batched_render` call (vmap over σt, σs) per group."""

    def __init__(self, cells: list[dict], config: Config):
        self.config = config
        self.groups: dict = {}
        for i, cell in enumerate(cells):
            k, _ = _truth_bounces(cell["medium"], config)
            self.groups.setdefault((cell["medium"]["g"], k), []).append(i)
        self.cells = cells
        self.done: dict[int, np.ndarray] = {}

    def images(self, i: int) -> np.ndarray:
        if i not in self.done:
            self._render_group(i)
        return self.done[i]

    def _render_group(self, i: int) -> None:
        (g, k), members = next((key, m) for key, m in self.groups.items() if i in m)
        cell = self.cells[i]
        grid = lfj.Grid(self.config.width, self.config.height).resolve(g)
        stripes = lfj.Stripes(cell["period"], cell["lit"], tuple(cell["phases"]))
        renderer = lfj.Renderer(grid, stripes, k, "paper")
        params = np.array(
            [[self.cells[j]["medium"][p] for p in ("sigma_t", "sigma_s", "g")] for j in members]
        )
        images = np.asarray(batch.batched_render(renderer, params)).sum(axis=2)
        for j, im in zip(members, images, strict=True):
            self.done[j] = im


def _cell(config: Config, **changes) -> dict:
    """The base cell (the config's ``base`` medium, period 6, 6 shifts, no noise) with
    ``changes``."""
    base = config.base
    cell = {
        "medium": {k: float(base[k]) for k in ("sigma_t", "sigma_s", "g")},
        "period": 6,
        "lit": 3,
        "phases": list(range(6)),
        "noise": None,
        "black_level": 0.0,
        "known_black": True,
        "seed": 0,
    }
    cell.update(changes)
    return cell


def _key(cell: dict, method: str, config: Config, cap: int | None = None) -> str:
    key = (
        f"lib{inv.library_fingerprint()}|"
        f"{config.dtype}|{config.width}x{config.height}|{method}|{cell['medium']}|"
        f"p{cell['period']}/{cell['lit']}|{cell['phases']}|n{cell['noise']}|s{cell['seed']}|"
        f"b{cell['black_level']}/{cell['known_black']}|K{config.divergent_bounces}/"
        f"{config.max_truth_bounces if cap is None else cap}|tol{config.tolerance}"
    )
    if cell.get("geometry"):
        key += f"|geo{cell['geometry']}"
    return key


def _fit(
    cell: dict,
    method: str,
    images: np.ndarray,
    config: Config,
    xla_dir,
    *,
    timeout: float,
    cap: int | None = None,
    truth_extra=None,
) -> dict:
    """One fit of a cell's capture as a record, its truth (ρ, bounces, tail bound, and
    ``truth_extra()``'s keys) and outcome; ``joint`` on a Dask worker stopped after
    ``timeout`` seconds. The medium's ``phase`` and the cell's ``geometry`` (when
    given) are the fit's too."""
    medium = cell["medium"]
    pattern = lfj.Stripes(cell["period"], cell["lit"], tuple(cell["phases"]))
    black = cell["black_level"] if cell["known_black"] else None
    truth = inv.truth_of(medium)
    kwargs = {"method": method, "black_level": black}
    if "phase" in medium:
        kwargs["phase"] = medium["phase"]
    if cell.get("geometry"):
        kwargs["geometry"] = parse_geometry(cell["geometry"], "geometry")
    if method == "joint":
        rec = inv.fit_record_limited(
            images,
            pattern,
            truth,
            timeout=timeout,
            dtype=config.dtype,
            xla_cache_dir=xla_dir,
            **kwargs,
        )
    else:
        rec = inv.fit_record(images, pattern, truth, **kwargs)
    k, how = _truth_bounces(medium, config, cap)
    rho = _rho(medium)
    rec["truth"] = {
        "rho": rho,
        "bounces": k,
        "bounces_how": how,
        "tail_bound": _tail_bound(rho, k),
        **(truth_extra() if truth_extra is not None else {}),
    }
    rec["failure"] = inv.failure(
        rec,
        truth_rho=rec["truth"]["rho"],
        bias=config.bias_threshold,
        ill_conditioned=config.ill_conditioned,
    )
    return inv.jsonable(rec)


def _run_cells(
    name,
    cells,
    images_of,
    config,
    ctx,
    *,
    methods=None,
    timeout: float | None = None,
    cap: int | None = None,
    truth_extra=None,
) -> list[dict]:
    """Every method's fit of every cell (cached). ``methods``, ``timeout`` (joint, s) and
    ``cap`` (truth bounces) default to the config's; ``truth_extra(i)``: more about
    cell i's truth for its record (called after ``images_of(i)``)."""
    rows = []
    xla_dir = ctx.kept("xla_cache") if config.xla_cache else None
    timeout = config.joint_timeout if timeout is None else timeout
    for i, cell in enumerate(cells):
        for method in methods or config.methods:
            ctx.progress(f"{name} {i + 1}/{len(cells)}: {method}")
            key = f"{name}|{_key(cell, method, config, cap)}"

            def compute(c=cell, m=method, i=i):
                extra = None if truth_extra is None else functools.partial(truth_extra, i)
                images = images_of(i)
                return _fit(
                    c, m, images, config, xla_dir, timeout=timeout, cap=cap, truth_extra=extra
                )

            rec = ctx.cached(key, compute)
            if rec.get("timeout") and (rec.get("timeout_s") or 0.0) < timeout:
                # Killed under a lower limit (an earlier config): measured again.
                rec = ctx.cached(f"{key}|timeout{timeout:g}", compute)
            if method == "joint" and rec["seconds"]["total"] > timeout:
                # A result that came later than the limit (a run before the limit
                # existed) counts as a timeout too; its values stay in the record.
                rec = {**rec, "failure": "timeout", "late": True}
            rows.append({"sweep": name, "cell": i, "method": method, "setting": cell, **rec})
    return rows


def _albedo_g(config: Config, ctx) -> tuple[list[dict], list[dict]]:
    spec = config.albedo_g
    st = float(spec["sigma_t"])
    cells = [
        _cell(config, medium={"sigma_t": st, "sigma_s": st * w, "g": float(g)})
        for w in spec["albedo"]
        for g in spec["g"]
    ]
    truths = _BatchedTruths(cells, config)
    return cells, _run_cells(
        "albedo_g", cells, lambda i: inv.camera(truths.images(i), None, 0), config, ctx
    )


def _measured_tail(energy: np.ndarray) -> tuple[float | None, float | None]:
    """(relative tail, ratio r): the energy past the last bounce K estimated as
    E_K·r/(1 − r) with r = E_K/E_{K−1}, over Σ E_k (None where r ≥ 1 or unknown).
    Bounces that underflowed to 0 at the end are left out: the estimate is then from the
    last two nonzero ones (an upper bound of the tail past K)."""
    energy = np.asarray(energy, np.float64)
    total = float(energy.sum())
    nonzero = np.flatnonzero(energy > 0.0)
    if len(nonzero):
        energy = energy[: nonzero[-1] + 1]
    if len(energy) < 2 or energy[-2] <= 0.0 or total <= 0.0:
        return None, None
    r = float(energy[-1] / energy[-2])
    if r >= 1.0:
        return None, r
    return float(energy[-1] * r / (1.0 - r) / total), r


def _truth_capture(cell: dict, config: Config, cap: int) -> tuple[np.ndarray, dict]:
    """A row's noise-free capture (the medium's phase, the cell's geometry; bounces for
    ``tolerance``, at most ``cap``) and what its render measured: the tail past the last
    bounce (:func:`_measured_tail`), the model's size and the render's seconds."""
    t0 = time.perf_counter()
    sim = inv.simulate(_capture_cfg(cell, config, cap))
    seconds = time.perf_counter() - t0
    energy = np.asarray(sim.bounces, np.float64).sum(axis=(0, 2, 3))  # per bounce
    tail, ratio = _measured_tail(energy)
    info = {
        "tail_measured": tail,
        "last_ratio": ratio,
        "n_theta": int(sim.n_theta),
        "refine": int(sim.refine),
        "render_seconds": seconds,
    }
    return np.asarray(sim.images), info


def _row_run(name: str, cells: list[dict], config: Config, ctx) -> list[dict]:
    """The fits of a row's cells, on captures from :func:`_truth_capture`."""
    row = _row(config, name)
    truths: dict[int, tuple] = {}

    def truth(i):
        if i not in truths:
            ctx.progress(f"{name} {i + 1}/{len(cells)}: truth")
            truths[i] = _truth_capture(cells[i], config, row["max_truth_bounces"])
        return truths[i]

    return _run_cells(
        name,
        cells,
        lambda i: inv.camera(truth(i)[0], None, 0),
        config,
        ctx,
        methods=row["methods"],
        timeout=row["joint_timeout"],
        cap=row["max_truth_bounces"],
        truth_extra=lambda i: truth(i)[1],
    )


def _row_cells(name: str, config: Config) -> list[dict]:
    """The cells of a row: ``high_albedo``'s albedo × g (phase normalized) or
    ``refractive_slab``'s media (in its slab)."""
    spec = getattr(config, name)
    if name == "high_albedo":
        st = float(spec["sigma_t"])
        return [
            _cell(
                config,
                medium={
                    "sigma_t": st,
                    "sigma_s": st * float(w),
                    "g": float(g),
                    "phase": "normalized",
                },
            )
            for w in spec["albedo"]
            for g in spec["g"]
        ]
    if name == "refractive_slab":
        geometry = parse_geometry(spec["geometry"], "refractive_slab.geometry").as_dict()
        return [
            _cell(
                config,
                medium={
                    **{k: float(m[k]) for k in ("sigma_t", "sigma_s", "g")},
                    "phase": "normalized",  # a slab's phase function: on the sphere
                },
                geometry=geometry,
                name=str(m["name"]),
            )
            for m in spec["media"]
        ]
    raise ValueError(name)


def _sweep_cells(name: str, config: Config) -> list[dict]:
    spec = getattr(config, name)
    if name == "noise":
        return [_cell(config, noise=(p, r), seed=i) for i, (p, r) in enumerate(spec["levels"])]
    if name == "period":
        base = config.base
        w, g = base["sigma_s"] / base["sigma_t"], base["g"]
        return [
            _cell(
                config,
                medium={"sigma_t": float(st), "sigma_s": float(st) * w, "g": float(g)},
                period=int(p),
                lit=int(p) // 2,
                phases=list(range(int(p))),
            )
            for st in spec["sigma_t"]
            for p in spec["period"]
        ]
    if name == "shifts":
        return [_cell(config, phases=list(ph)) for ph in spec["phases"]]
    if name == "black_level":
        return [
            _cell(config, black_level=float(b), known_black=bool(known))
            for b in spec["levels"]
            for known in spec["known"]
        ]
    raise ValueError(name)


def _sweep(name: str, config: Config, ctx) -> tuple[list[dict], list[dict]]:
    cells = _sweep_cells(name, config)
    memo: dict[int, np.ndarray] = {}

    def images_of(i):
        if i not in memo:
            c = cells[i]
            memo[i] = inv.camera(_simulated(c, config), c["noise"], c["seed"])
        return memo[i]

    return cells, _run_cells(name, cells, images_of, config, ctx)


# ------------------------------------------------------------------- initial guess


def _start_solve(medium: dict, start: tuple, images, config: Config) -> dict:
    """One joint fit from ``start``'s (σs, g) (σt from the decay fit, as always), the
    basin search off: where the solve from there ends, and whether it is trusted."""
    t0 = time.perf_counter()
    fit = lfj.fit_images(
        images, lfj.Stripes(), black_level=0.0, start=tuple(start[1:3]), **inv.OWN_MODEL
    )
    values = {k: getattr(fit, k) for k in inv.PARAMS}
    finite = all(math.isfinite(v) for v in values.values())
    rec = {
        **values,
        "start": list(start[:3]),
        "errors": inv.errors(values, inv.truth_of(medium)),
        "finite": finite,
        "converged": fit.converged,
        "message": fit.message,
        "iterations": fit.iterations,
        "condition_number": fit.condition_number,
        "seconds": {
            "compile": fit.seconds["compile"],
            "total": time.perf_counter() - t0,
        },
        "model": fit.model,
    }
    rec["failure"] = inv.failure(
        rec, bias=config.bias_threshold, ill_conditioned=config.ill_conditioned
    )
    return inv.jsonable(rec)


def _starts(config: Config, ctx) -> list[dict]:
    spec = config.start
    rows = []
    for medium in spec["media"]:
        m = {k: float(medium[k]) for k in ("sigma_t", "sigma_s", "g")}
        cell = _cell(config, medium=m)
        images = functools.cache(lambda c=cell: inv.camera(_simulated(c, config), None, 0))
        # σt is not a start: the fit takes it from the direct light's decay (a start is
        # σs and g, Joint.start); σs's start is kept below 0.98·σt.
        offsets = [(fs, dg) for fs in spec["sigma_s_factor"] for dg in spec["g_offset"]]
        for i, (fs, dg) in enumerate(offsets):
            ctx.progress(f"start {medium['name']} {i + 1}/{len(offsets)}")
            st0 = m["sigma_t"]
            start = (
                st0,
                min(m["sigma_s"] * fs, 0.98 * st0),
                float(np.clip(m["g"] + dg, -0.95, 0.95)),
                0.0,
            )
            rec = ctx.cached(
                f"start|{_key(cell, 'joint', config)}|{start}",
                lambda m=m, start=start, images=images: _start_solve(m, start, images(), config),
            )
            offset = {"sigma_s_factor": fs, "g_offset": dg}
            rows.append({"medium": medium["name"], **offset, **rec})
    return rows


# ------------------------------------------------------------------------ driver


def run(raw: dict, out: Path, ctx) -> dict:
    config = typed_config(Config, raw)
    cache = ctx.kept("xla_cache") if config.xla_cache else None
    results = {}
    with inv.precision(config.dtype), inv.xla_cache(cache):
        if config.albedo_g:
            results["albedo_g"] = _albedo_g(config, ctx)[1]
        for name in SWEEPS:
            if getattr(config, name):
                results[name] = _sweep(name, config, ctx)[1]
        starts = _starts(config, ctx) if config.start else []
        for name in ROWS:
            if getattr(config, name):
                results[name] = _row_run(name, _row_cells(name, config), config, ctx)
    all_rows = [r for rows in results.values() for r in rows]
    _write_csv(out / "stability.csv", all_rows, starts)
    ctx.write_json("stability.json", inv.jsonable({"fits": all_rows, "starts": starts}))
    figures = []
    if "albedo_g" in results:
        figures.append(_plot_albedo_g(config, results["albedo_g"], out))
    if any(name in results for name in SWEEPS):
        figures.append(_plot_sweeps(config, results, out))
    if starts:
        figures.append(_plot_starts(config, starts, out))
    if "high_albedo" in results:
        figures.append(_plot_albedo_g(config, results["high_albedo"], out, row="high_albedo"))
    if "refractive_slab" in results:
        figures.append(_plot_refractive_slab(config, results["refractive_slab"], out))
    return inv.jsonable(_summary(config, results, starts, figures))


def _counts(rows) -> dict:
    out = {}
    for r in rows:
        out.setdefault(r["method"], {}).setdefault(r["failure"], 0)
        out[r["method"]][r["failure"]] += 1
    return out


def _summary(config, results, starts, figures) -> dict:
    def brief(r):
        s = r["setting"]
        m = s["medium"]
        e = r["errors"]
        return {
            "medium": [round(m["sigma_t"], 4), round(m["sigma_s"], 4), m["g"]],
            "rho": round(_rho(m), 3),
            "failure": r["failure"],
            "error": e["error"],
            "condition_number": r.get("condition_number"),
            "message": r.get("message", r.get("error_message")),
        }

    summary = {
        "figures": figures,
        "data": ["stability.json", "stability.csv"],
        "failure_counts": {name: _counts(rows) for name, rows in results.items()},
        "albedo_g_failures": {
            m: [
                brief(r)
                for r in results.get("albedo_g", ())
                if r["method"] == m and r["failure"] != "ok"
            ]
            for m in config.methods
        },
        "sweeps": {
            name: [
                {
                    "method": r["method"],
                    "setting": _setting_label(name, r["setting"]),
                    "error": r["errors"]["error"],
                    "failure": r["failure"],
                    "converged": r["converged"],
                }
                for r in rows
            ]
            for name, rows in results.items()
            if name != "albedo_g" and name not in ROWS
        },
        "timing_note": "compile times use the persistent XLA cache when xla_cache is on",
        "library_fingerprint": inv.library_fingerprint(),
    }
    for name in ROWS:
        if name in results:
            summary[name] = [
                {
                    "method": r["method"],
                    "setting": _setting_label(name, r["setting"]),
                    "failure": r["failure"],
                    "error": r["errors"]["error"],
                    "errors": {k: r["errors"][k] for k in inv.PARAMS},
                    "converged": r["converged"],
                    "iterations": r.get("iterations"),
                    "seconds": r["seconds"]["total"],
                    "truth": {
                        k: (r.get("truth") or {}).get(k)
                        for k in ("rho", "bounces", "bounces_how", "tail_bound", "tail_measured")
                    },
                    "message": r.get("message", r.get("error_message")),
                }
                for r in results[name]
            ]
    if starts:
        summary["start"] = {
            "counts": {
                med: {
                    f: sum(1 for s in starts if s["medium"] == med and s["failure"] == f)
                    for f in inv.FAILURES
                    if any(s["medium"] == med and s["failure"] == f for s in starts)
                }
                for med in dict.fromkeys(s["medium"] for s in starts)
            },
            "failed_starts": [
                {
                    "medium": s["medium"],
                    "sigma_s_factor": s["sigma_s_factor"],
                    "g_offset": s["g_offset"],
                    "failure": s["failure"],
                    "error": s["errors"]["error"],
                }
                for s in starts
                if s["failure"] != "ok"
            ],
        }
    return summary


def _setting_label(name: str, s: dict) -> str:
    if name in ROWS:
        m = s["medium"]
        what = f"albedo {m['sigma_s'] / m['sigma_t']:.4g}, g {m['g']:g}"
        if name == "high_albedo":
            return f"{what}, sigma_t {m['sigma_t']:g} (normalized)"
        return f"{s.get('name', '')}: sigma_t {m['sigma_t']:g}, {what} ({_geometry_label(s)})"
    if name == "noise":
        p, r = s["noise"]
        return f"photons {p:g}, read {r:g}" if p else f"read {r:g}"
    if name == "period":
        st = s["medium"]["sigma_t"]
        return f"period {s['period']}, sigma_t {st:g} ({s['period'] * st:.2f} mfp)"
    if name == "shifts":
        return f"{len(s['phases'])} shifts {s['phases']}"
    return f"b {s['black_level']:g} ({'known' if s['known_black'] else 'unknown'})"


def _geometry_label(s: dict) -> str:
    geo = s.get("geometry")
    if not geo:
        return "plane"
    text = f"slab h {geo['thickness']:g} {geo['boundary']}"
    return text + (f" n {geo['n']:g}" if "n" in geo else "")


def _write_csv(path: Path, rows, starts) -> None:
    cols = [
        "sweep",
        "cell",
        "method",
        "sigma_t_true",
        "sigma_s_true",
        "g_true",
        "rho",
        "period",
        "shifts",
        "photons",
        "read",
        "black_level",
        "black_known",
        "sigma_t",
        "sigma_s",
        "g",
        "err_sigma_t",
        "err_sigma_s",
        "err_g",
        "error",
        "failure",
        "converged",
        "iterations",
        "condition_number",
        "total_s",
        "phase",
        "geometry",
        "truth_bounces",
        "truth_tail_bound",
        "truth_tail_measured",
    ]

    def lines():
        for r in rows:
            s, m, e = r["setting"], r["setting"]["medium"], r["errors"]
            truth = r.get("truth") or {}
            noise = s["noise"] or (None, None)
            yield (
                [
                    r["sweep"],
                    r["cell"],
                    r["method"],
                    m["sigma_t"],
                    m["sigma_s"],
                    m["g"],
                    _rho(m),
                    s["period"],
                    len(s["phases"]),
                    noise[0],
                    noise[1],
                    s["black_level"],
                    s["known_black"],
                    r.get("sigma_t"),
                    r.get("sigma_s"),
                    r.get("g"),
                    e["sigma_t"],
                    e["sigma_s"],
                    e["g"],
                    e["error"],
                    r["failure"],
                    r["converged"],
                    r.get("iterations"),
                    r.get("condition_number"),
                    r["seconds"]["total"],
                    m.get("phase", "paper"),
                    _geometry_label(s),
                    truth.get("bounces"),
                    truth.get("tail_bound"),
                    truth.get("tail_measured"),
                ]
            )
        for s in starts:
            e = s["errors"]
            yield (
                [
                    f"start:{s['medium']}",
                    f"{s['sigma_s_factor']}/{s['g_offset']}",
                    "joint",
                    None,
                    None,
                    None,
                    None,
                    6,
                    6,
                    None,
                    None,
                    0.0,
                    True,
                    s["sigma_t"],
                    s["sigma_s"],
                    s["g"],
                    e["sigma_t"],
                    e["sigma_s"],
                    e["g"],
                    e["error"],
                    s["failure"],
                    s["converged"],
                    s["iterations"],
                    s["condition_number"],
                    s["seconds"]["total"],
                    "paper",
                    "plane",
                    None,
                    None,
                    None,
                ]
            )

    write_csv(path, cols, lines())


# ------------------------------------------------------------------------ figures

_CODES = {
    "ok": "ok",
    "biased": "bias",
    "ill-conditioned": "cond",
    "not converged": "n.c.",
    "divergent": "div",
    "non-finite": "NaN",
    "exception": "exc",
    "timeout": "time",
}
_MARKERS = {
    "ok": "o",
    "biased": "s",
    "ill-conditioned": "D",
    "not converged": "x",
    "divergent": "^",
    "non-finite": "*",
    "exception": "P",
    "timeout": "v",
}
_COLORS = {"grid": "tab:red", "gradient": "tab:blue", "joint": "tab:green"}
_ERROR = "error: max(|Δσt|/σt, |Δσs|/σs, |Δg|)"


def _capture_text(config: Config) -> str:
    """The captures' parameters, for the figures' captions."""
    return (
        f"{config.width}×{config.height} px stripe captures (period 6, lit 3, 6 shifts "
        f"unless varied), {config.dtype}; grid, gradient: two-step (Nayar split, then fit "
        "the global part); joint: all parameters from the raw images"
    )


def _index_coords(values, n: int = 200):
    """Cell-index coordinates spanning the cells (one unit per cell, however the values
    are spaced) and the values there (linear between centres, extended half a cell)."""
    v = np.asarray(values, float)
    idx = np.linspace(-0.5, len(v) - 0.5, n)
    if len(v) == 1:
        return idx, np.full(n, v[0])
    inside = np.interp(idx, np.arange(len(v)), v)
    below = np.minimum(idx, 0.0) * (v[1] - v[0])
    above = np.maximum(idx - (len(v) - 1), 0.0) * (v[-1] - v[-2])
    return idx, inside + below + above


def _plot_albedo_g(config, rows, out: Path, row: str = "albedo_g") -> str:
    """The albedo × g map of ``row``: ``albedo_g`` (phase paper, the ρ = 1 contour) or
    ``high_albedo`` (phase normalized, ρ = ω < 1; each fit's seconds in its cell)."""
    from matplotlib.colors import LogNorm

    plt = pyplot()

    spec = getattr(config, row)
    normalized = row == "high_albedo"
    albedos, gs = list(spec["albedo"]), list(spec["g"])
    methods = config.methods if row == "albedo_g" else _row(config, row)["methods"]
    timeout = config.joint_timeout if row == "albedo_g" else _row(config, row)["joint_timeout"]
    xi, gv = _index_coords(gs)
    yi, wv = _index_coords(albedos)
    gg, ww = np.meshgrid(gv, wv)
    if normalized:
        rho = ww
    else:
        rho = ww * np.asarray(lfj.phase_integral(np.clip(gg, -0.99, 0.99)))
    xx, yy = np.meshgrid(xi, yi)
    fig, axes = plt.subplots(2, len(methods), figsize=(4.6 * len(methods), 7.8), squeeze=False)
    for j, method in enumerate(methods):
        err = np.full((len(albedos), len(gs)), np.nan)
        cond = np.full_like(err, np.nan)
        codes = {}
        for r in rows:
            if r["method"] != method:
                continue
            m = r["setting"]["medium"]
            a = albedos.index(min(albedos, key=lambda w: abs(w - m["sigma_s"] / m["sigma_t"])))
            b = gs.index(m["g"])
            e = r["errors"]["error"]
            err[a, b] = np.nan if e is None else max(e, 1e-4)
            c = r.get("condition_number")
            cond[a, b] = np.nan if c is None else c
            codes[(a, b)] = (r["failure"], e, r["seconds"]["total"])
        for i, (data, label, norm) in enumerate(
            (
                (err, _ERROR, LogNorm(1e-4, 1.0)),
                (cond, "condition number (unit-free JᵀJ)", LogNorm(1.0, 1e8)),
            )
        ):
            ax = axes[i, j]
            ax.set_facecolor("0.85")  # no result (timeout, exception, NaN)
            mesh = ax.imshow(
                np.ma.masked_invalid(data),
                norm=norm,
                cmap="viridis",
                origin="lower",
                aspect="auto",
                extent=(-0.5, len(gs) - 0.5, -0.5, len(albedos) - 0.5),
            )
            fig.colorbar(mesh, ax=ax, label=label, shrink=0.85)
            if np.nanmax(rho) >= 1.0 > np.nanmin(rho):
                cs = ax.contour(xx, yy, rho, levels=[1.0], colors="r", linewidths=2)
                ax.clabel(cs, fmt={1.0: "ρ = 1"}, fontsize=8)
            if np.nanmax(rho) >= 1.0:
                hatched = ax.contourf(
                    xx, yy, rho, levels=[1.0, np.inf], colors="none", hatches=["///"]
                )
                hatched.set_edgecolor("r")
                hatched.set_linewidth(0.0)
            for (a, b), (f, e, t) in codes.items():
                txt = _CODES[f] if i == 1 or e is None else f"{_CODES[f]}\n{e:.2g}"
                if normalized and i == 0:
                    txt += f"\n{t:.0f} s"
                ax.text(
                    b,
                    a,
                    txt,
                    ha="center",
                    va="center",
                    fontsize=7,
                    bbox={"boxstyle": "round,pad=0.15", "fc": "w", "alpha": 0.7, "lw": 0},
                )
            ax.set_xticks(range(len(gs)), [f"{g:g}" for g in gs])
            ax.set_yticks(range(len(albedos)), [f"{w:g}" for w in albedos])
            ax.set_xlabel("g")
            ax.set_ylabel("albedo ω = σs/σt")
            what = "error" if i == 0 else "condition number of JᵀJ"
            ax.set_title(f"{method}: {what}", fontsize=9)
    if normalized:
        cap = _row(config, row)["max_truth_bounces"]
        capped: dict[float, list[dict]] = {}
        for r in rows:
            t = r.get("truth") or {}
            if t.get("bounces_how") == "capped":
                m = r["setting"]["medium"]
                capped.setdefault(round(m["sigma_s"] / m["sigma_t"], 6), []).append(t)
        capped_text = "; ".join(
            f"ω {w:g}: K {ts[0]['bounces']}, bound {ts[0]['tail_bound']:.2g}, measured ≤ "
            + _largest_tail(ts)
            for w, ts in sorted(capped.items())
        )
        first = (
            f"High albedo, phase: normalized (ρ = ω < 1): σt {spec['sigma_t']} px⁻¹, "
            "noiseless; cell text: outcome, error (floored at 1e-4), fit seconds; gray: no "
            f"result\ntruths marched to the bounces for a tail of {config.tolerance:g}, at "
            f"most {cap}" + (f" (capped: {capped_text})" if capped_text else "")
        )
    else:
        first = (
            f"Where each method fails over albedo × g: σt {spec['sigma_t']} px⁻¹, noiseless; "
            f"cell text: outcome and error (floored at 1e-4); gray: no result\n"
            f"red hatching: ρ = ω·A(g) ≥ 1 (phase: paper), the bounce series diverges, the "
            f"truth is cut after {config.divergent_bounces} bounces"
        )
    title = (
        first + "\n"
        f"ok: error ≤ {config.bias_threshold:g}; bias: converged, error above; cond: bias "
        f"with condition number > {config.ill_conditioned:.0e}; n.c.: not converged; "
        f"div: ρ ≥ 1; NaN; exc: exception; time: joint over {timeout:g} s\n" + _capture_text(config)
    )
    # lines wrapped to the figure's width (about 15 characters an inch at 9 pt)
    chars = int(15 * 4.6 * len(methods))
    fig.suptitle("\n".join(textwrap.fill(line, chars) for line in title.split("\n")), fontsize=9)
    fig.tight_layout()
    name = f"{row}.png"
    save_figure(fig, out / name, dpi=110)
    return name


def _plot_sweeps(config, results, out: Path) -> str:
    from matplotlib.lines import Line2D

    plt = pyplot()

    names = [n for n in SWEEPS if n in results]
    fig, axes = plt.subplots(
        1, max(len(names), 1), figsize=(4.6 * max(len(names), 1), 4.4), squeeze=False
    )
    for ax, name in zip(axes[0], names, strict=False):
        rows = results[name]
        for method in config.methods:
            mine = [r for r in rows if r["method"] == method]
            if name == "black_level":
                # one category per (b, given or not): a single level still reads
                def label(st):
                    given = "given" if st["known_black"] else "unknown"
                    return f"b {st['black_level']:g}, {given}"

                sel = sorted(
                    mine,
                    key=lambda r: (r["setting"]["black_level"], not r["setting"]["known_black"]),
                )
                _line(ax, list(range(len(sel))), sel, method, "-")
                ax.set_xticks(range(len(sel)), [label(r["setting"]) for r in sel], fontsize=8)
                ax.set_xlim(-0.5, len(sel) - 0.5)
                ax.set_xlabel("projector black level b, given to the fit or estimated")
            elif name == "period":
                sts = sorted({r["setting"]["medium"]["sigma_t"] for r in mine})
                for st, ls in zip(sts, ("-", "--", ":", "-."), strict=False):
                    sel = [r for r in mine if r["setting"]["medium"]["sigma_t"] == st]
                    _line(ax, [r["setting"]["period"] * st for r in sel], sel, method, ls)
                inv.log_axes(ax, y=False)
                ax.set_xlabel(
                    "stripe period / mean free path (σt·period)\n"
                    + ", ".join(
                        f"{ls}: σt {st:g}"
                        for st, ls in zip(sts, ("—", "--", ":", "-."), strict=False)
                    )
                )
            elif name == "shifts":
                _line(ax, [len(r["setting"]["phases"]) for r in mine], mine, method, "-")
                ax.set_xlabel("number of shifts (period 6)")
            else:
                labels = [_setting_label("noise", r["setting"]) for r in mine]
                _line(ax, list(range(len(mine))), mine, method, "-")
                ax.set_xticks(range(len(mine)), labels, rotation=45, ha="right", fontsize=7)
                ax.set_xlabel("photons at the brightest pixel, read noise / brightest pixel")
        ax.set_yscale("log")
        ax.axhline(config.bias_threshold, color="k", lw=0.8, ls=":")
        ax.set_ylabel(_ERROR, fontsize=8)
        ax.set_title(_SWEEP_TITLES.get(name, name), fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
    handles = [
        Line2D([], [], color=c, lw=_LW.get(m, 1), alpha=0.5 if m == "grid" else 1, label=m)
        for m, c in _COLORS.items()
        if m in config.methods
    ]
    handles += [
        Line2D([], [], color="gray", marker=mk, ls="none", label=f) for f, mk in _MARKERS.items()
    ]
    fig.legend(handles=handles, fontsize=8, loc="center right", title="method / outcome")
    base = config.base
    fig.suptitle(
        f"Recovery error against one capture setting at a time: σt {base['sigma_t']} px⁻¹, "
        f"σs {base['sigma_s']} px⁻¹, g {base['g']} (the paper's milk) unless varied; "
        f"dotted: the 'ok' threshold {config.bias_threshold:g} (grid, wide pale red, lies "
        "under gradient where they agree)\n" + _capture_text(config),
        fontsize=9,
    )
    fig.tight_layout(rect=(0, 0, 0.9, 1))
    name = "sweeps.png"
    save_figure(fig, out / name, dpi=110)
    return name


_LW = {"grid": 4.0}  # drawn wide and pale: gradient lies on top of it where they agree
_SWEEP_TITLES = {
    "noise": "noise (Poisson photons, Gaussian read noise)",
    "period": "stripe period vs mean free path",
    "shifts": "number of shifted images",
    "black_level": "projector black level",
}


def _line(ax, xs, rows, method, ls) -> None:
    """Errors (no result drawn at 10, floored at 1e-5) with the outcome's marker."""
    ys = [
        max(r["errors"]["error"] if r["errors"]["error"] is not None else 10.0, 1e-5) for r in rows
    ]
    wide = method in _LW
    kw = {"color": _COLORS.get(method, "k"), "alpha": 0.5 if wide else 1.0}
    ax.plot(xs, ys, ls, lw=_LW.get(method, 1.0), **kw)
    for x, y, r in zip(xs, ys, rows, strict=True):
        ax.plot(x, y, _MARKERS[r["failure"]], ms=10 if wide else 6, **kw)


def _plot_starts(config, starts, out: Path) -> str:
    from matplotlib.colors import LogNorm

    plt = pyplot()

    spec = config.start
    media = list(dict.fromkeys(s["medium"] for s in starts))
    fs, dg = list(spec["sigma_s_factor"]), list(spec["g_offset"])
    fig, axes = plt.subplots(
        len(media), 1, figsize=(7, 0.8 + (2.4 + 0.5 * len(fs)) * len(media)), squeeze=False
    )
    for i, med in enumerate(media):
        mine = [s for s in starts if s["medium"] == med]
        grid = np.full((len(fs), len(dg)), np.nan)
        ax = axes[i, 0]
        for s in mine:
            a, b = fs.index(s["sigma_s_factor"]), dg.index(s["g_offset"])
            e = s["errors"]["error"]
            grid[a, b] = np.nan if e is None else max(e, 1e-5)
            ax.text(
                b,
                a,
                f"{_CODES[s['failure']]}, {s['iterations']} it\nerror {e:.1g}"
                if e is not None
                else f"{_CODES[s['failure']]}, {s['iterations']} it",
                ha="center",
                va="center",
                fontsize=7,
                bbox={"boxstyle": "round,pad=0.15", "fc": "w", "alpha": 0.7, "lw": 0},
            )
        im = ax.imshow(
            np.ma.masked_invalid(grid),
            norm=LogNorm(1e-5, 1.0),
            origin="lower",
            cmap="viridis",
            aspect="auto",
        )
        fig.colorbar(im, ax=ax, label="final " + _ERROR, shrink=0.9)
        ax.set_xticks(range(len(dg)), [f"{d:+g}" for d in dg])
        ax.set_yticks(range(len(fs)), [f"×{f:g}" for f in fs])
        ax.set_xlabel("start g − true g")
        ax.set_ylabel("start σs / true σs")
        true = {m["name"]: m for m in spec["media"]}.get(med, {})
        truth = ", ".join(
            f"{sym} {true[k]:g}"
            for sym, k in (("σt", "sigma_t"), ("σs", "sigma_s"), ("g", "g"))
            if k in true
        )
        ax.set_title(f"{med} ({truth}): σs and g starts, σt from the decay fit", fontsize=9)
    fig.suptitle(
        "The joint fit's basin of convergence: the default fit from each start (σs, g), the "
        "basin scan off\n"
        f"noiseless {config.width}×{config.height} px captures, period 6, lit 3, 6 shifts; "
        f"ok: error ≤ {config.bias_threshold:g}; n.c.: not converged\n"
        "it: iterations; start |g| clipped to 0.95, start σs to 0.98·σt",
        fontsize=9,
    )
    fig.tight_layout()
    name = "start_basin.png"
    save_figure(fig, out / name, dpi=110)
    return name


def _largest_tail(truths: list[dict]) -> str:
    tails = [t.get("tail_measured") for t in truths]
    if any(v is None for v in tails):
        return "?"
    return f"{max(tails):.1e}"


def _plot_refractive_slab(config, rows, out: Path) -> str:
    """A table: per medium and method, the truth, the outcome, the errors and the time."""
    plt = pyplot()

    spec = config.refractive_slab
    geo = parse_geometry(spec["geometry"], "refractive_slab.geometry")
    cols = [
        "medium",
        "σt",
        "ω",
        "g",
        "truth K",
        "method",
        "outcome",
        "Δσt/σt",
        "Δσs/σs",
        "Δg",
        "iterations",
        "fit s",
    ]

    def fmt(v, f="{:+.2g}"):
        return "–" if v is None else f.format(v)

    cells = []
    for r in rows:
        m, e, t = r["setting"]["medium"], r["errors"], r.get("truth") or {}
        cells.append(
            [
                r["setting"].get("name", ""),
                f"{m['sigma_t']:g}",
                f"{m['sigma_s'] / m['sigma_t']:.3g}",
                f"{m['g']:g}",
                f"{t.get('bounces', '?')}"
                + (" (capped)" if t.get("bounces_how") == "capped" else ""),
                r["method"],
                r["failure"],
                fmt(e["sigma_t"]),
                fmt(e["sigma_s"]),
                fmt(e["g"]),
                fmt(r.get("iterations"), "{}"),
                f"{r['seconds']['total']:.0f}",
            ]
        )
    fig, ax = plt.subplots(figsize=(12, 1.4 + 0.35 * max(len(cells), 1)))
    ax.axis("off")
    table = ax.table(cellText=cells or [["–"] * len(cols)], colLabels=cols, loc="center")
    table.auto_set_font_size(False)
    table.set_fontsize(8)
    table.scale(1.0, 1.3)
    for k, r in enumerate(rows, start=1):
        table[k, cols.index("outcome")].set_facecolor(
            "#c8e6c9" if r["failure"] == "ok" else "#ffcdd2"
        )
    fig.suptitle(
        f"Refractive slab (thickness {geo.thickness:g} px, n {geo.n:g}): captures rendered by "
        f"the slab model and fitted with the same slab; ok: error ≤ {config.bias_threshold:g}; "
        f"joint limit {_row(config, 'refractive_slab')['joint_timeout']:g} s\n"
        + _capture_text(config),
        fontsize=9,
    )
    fig.tight_layout()
    name = "refractive_slab.png"
    save_figure(fig, out / name, dpi=110)
    return name
