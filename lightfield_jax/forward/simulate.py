"""Simulated captures: render a ``simulate`` config as a camera would record it.

:func:`simulate_capture` renders the per-bounce images of a config and turns them into
captured images: gain c, the projector's black level b (stripes), the camera's dark
level and noise (see :mod:`lightfield_jax.forward.simulate_config` for the keys).
:func:`write_simulation` writes the result into a folder (the ``simulate`` command).

Per-bounce images are noise-free and exclude the dark level; they include the gain
and, for stripes, the black level, so for every pattern Σ_k I_k is the captured image
before dark level and noise. With black level b a shift's image is
(1 − b)·R_pattern + b·R_full (docs/model.md section 5), where R_full, the render under full
illumination, is Σ_shifts R_pattern / lit when the phases are 0..period−1 (each row is
then lit in exactly ``lit`` shifts), and is rendered separately otherwise.
"""

from __future__ import annotations

import dataclasses
import datetime
import importlib.metadata
import os
import platform
from pathlib import Path
from typing import Any

import numpy as np

from lightfield_jax.checks import check_flag
from lightfield_jax.forward.render import render, render_memory
from lightfield_jax.forward.simulate_config import SimulationConfig, load_simulation_config
from lightfield_jax.runtime.memory import check_memory
from lightfield_jax.runtime.progress import Stage, quiet
from lightfield_jax.runtime.timing import stopwatch
from lightfield_jax.scene.illumination import Full, Stripes

_VERSIONED = ("jax", "jaxlib", "equinox", "optimistix", "numpy", "lightfield_jax")


@dataclasses.dataclass(frozen=True, eq=False)
class SimulatedCapture:
    """A rendered capture. Arrays are float32 numpy arrays in the image frame.

    Attributes:
        config: the simulation config.
        bounces: per-bounce images, index k−1 holds I_k: [K, H, W], or [P, K, H, W] for
            stripes (one row per phase); with a tail solve, one more, last: Σ_{k>K} I_k.
            Gain and black level included; no dark level, no noise.
        images: the captured images: [H, W] (beam, full), or [P, H, W] for stripes:
            Σ_k I_k + dark level, with noise.
        dark: the dark frame (dark level with noise) [H, W], or ``None`` without a
            ``dark_level``.
        lightfields: L_0..L_K, radiance per radian, gain and black level included:
            [K+1, H, W, n_theta], or [P, K+1, H, W, n_theta] for stripes (with a tail,
            one more, last: Σ_{k>K} L_k); ``None`` unless requested.
        n_bounces: K.
        rho: ω·A(g) (``paper``) or ω (``normalized``).
        converges: whether the bounce series converges (ρ < 1).
        n_theta: direction bins used.
        refine: spatial refinement used.
        full_illumination: for stripes with a black level, how R_full was obtained
            (``"sum of shifts / lit"`` or ``"rendered"``), else ``None``.
        timing: seconds: ``compile`` (tracing and XLA compilation), ``run`` (the
            rest), ``total``.
        tail: with a tail solve, its ``method`` and ``steps`` (of the stripes' render;
            ``None`` without one).
    """

    config: SimulationConfig
    bounces: np.ndarray
    images: np.ndarray
    dark: np.ndarray | None
    lightfields: np.ndarray | None
    n_bounces: int
    rho: float
    converges: bool
    n_theta: int
    refine: int
    full_illumination: str | None
    timing: dict[str, float]
    tail: dict | None = None

    @property
    def is_stripes(self) -> bool:
        return isinstance(self.config.illumination, Stripes)

    def truth(self) -> dict[str, Any]:
        """The true parameters, as a capture file's ``truth`` key holds them."""
        m = self.config.medium
        truth = {"sigma_t": m.sigma_t, "sigma_s": m.sigma_s, "g": m.g, "gain": self.config.gain}
        truth["phase"] = m.phase
        if self.config.black_level is not None:
            truth["black_level"] = self.config.black_level
        return truth

    def metadata(self) -> dict[str, Any]:
        """What was simulated, how, with which software, and when (JSON-ready)."""
        c = self.config
        return {
            "config_file": c.source,
            "config": c.raw,
            "illumination": type(c.illumination).__name__.lower(),
            "bounces": self.n_bounces,
            "rho": self.rho,
            "converges": self.converges,
            "n_theta": self.n_theta,
            "refine": self.refine,
            "geometry": c.geometry.as_dict(),
            "gain": c.gain,
            "black_level": c.black_level,
            "dark_level": c.dark_level,
            "noise": None if c.noise is None else dataclasses.asdict(c.noise),
            "full_illumination": self.full_illumination,
            "tail": self.tail,
            "timings": {f"{k}_s": v for k, v in self.timing.items()},
            "versions": _versions(),
            "device": _device(),
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        }


def _versions() -> dict[str, str]:
    versions = {"python": platform.python_version()}
    for name in _VERSIONED:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def _device() -> str:
    import jax

    return str(jax.devices()[0])


def _full_from_shifts(stripes: Stripes) -> bool:
    """Whether Σ over the shifts is exactly ``lit`` times full illumination."""
    return sorted(p % stripes.period for p in stripes.phases) == list(range(stripes.period))


def _render(config: SimulationConfig, illumination, k: int, lightfield: bool):
    """The render's result and its per-bounce images and light fields as numpy arrays,
    a tail solve's sum appended last on the bounce axis (refused where it did not
    converge: a capture short of its light would be written without a word)."""
    result = render(
        config.medium.medium(),
        config.grid,
        illumination,
        k,
        gain=config.gain,
        lightfield=lightfield,
        geometry=config.geometry,
        tail=config.tail,
        tail_tol=config.tolerance,
    )
    images = np.asarray(result.images, dtype=np.float64)
    fields = None if not lightfield else np.asarray(result.lightfields, dtype=np.float32)
    if config.tail is not None:
        if not bool(result.tail_converged):
            raise ValueError(
                f"{config.source}: tail: the {config.tail} solve did not reach tolerance "
                f"{config.tolerance:g} within {int(result.tail_steps)} iterations: more "
                "explicit bounces (bounces: K) leave it less to sum"
            )
        images = np.concatenate([images, np.asarray(result.tail)[..., None, :, :]], axis=-3)
        if fields is not None:
            last = np.asarray(result.tail_lightfield, dtype=np.float32)[..., None, :, :, :]
            fields = np.concatenate([fields, last], axis=-4)
    return result, images, fields


def _add_black_level(config: SimulationConfig, k: int, bounces, fields, stage: Stage):
    """(1 − b)·R_pattern + b·R_full for the per-bounce images and light fields; returns
    them and how R_full was obtained."""
    illum, b = config.illumination, config.black_level
    if _full_from_shifts(illum):
        how = "sum of shifts / lit"
        full = bounces.sum(axis=0) / illum.lit
        full_field = None if fields is None else fields.sum(axis=0) / illum.lit
    else:
        how = "rendered"
        stage("render full illumination (black level)")
        _, full, full_field = _render(
            config, Full(illum.direction_deg, illum.entry), k, fields is not None
        )
    bounces = (1.0 - b) * bounces + b * full[None]
    if fields is not None:
        fields = ((1.0 - b) * fields + b * full_field[None]).astype(np.float32)
    return bounces, fields, how


def memory_estimate(config: SimulationConfig, k: int, lightfield: bool) -> int:
    """Bytes a render of ``config`` with ``k`` bounces needs (an upper bound, see
    :func:`~lightfield_jax.forward.render.render_memory`), from the sizes alone."""
    patterns = config.illumination.n_patterns + (1 if config.black_level else 0)
    return render_memory(
        patterns,
        config.grid,
        config.geometry,
        config.medium.medium(),
        k,
        lightfield,
        config.tail is not None,
    )


def simulate_capture(
    config: SimulationConfig | str | os.PathLike,
    *,
    lightfield: bool = False,
    stage: Stage = quiet,
) -> SimulatedCapture:
    """Render a config as a captured data set (see the module docstring).

    Args:
        config: a :class:`SimulationConfig`, or the path of a ``simulate`` YAML file.
        lightfield: also keep the light fields L_0..L_K (memory: (K+1)·P·H·W·n_theta
            floats).
        stage: progress callback, called with the name of each stage as it starts.

    Raises:
        ConfigError: an invalid config file.
        ValueError: an invalid config object.

    A :class:`~lightfield_jax.DivergentSeriesWarning` is issued when the bounce series
    of the ``paper`` convention diverges (an explicit bounce count is then a reported
    truncation, ``converges`` is ``False``).
    """
    if not isinstance(config, (SimulationConfig, str, os.PathLike)):
        raise ValueError(
            f"simulate_capture: config: must be a SimulationConfig or the path of a simulate "
            f"YAML file, got {type(config).__name__}"
        )
    check_flag(lightfield, "simulate_capture: lightfield")
    if not callable(stage):
        raise ValueError(f"simulate_capture: stage: must be callable, got {type(stage).__name__}")
    if not isinstance(config, SimulationConfig):
        config = load_simulation_config(config)
    illum = config.illumination
    k = config.n_bounces()
    check_memory(memory_estimate(config, k, lightfield), f"{config.source}: the render")
    stripes = isinstance(illum, Stripes)
    with stopwatch() as timing:
        stage(f"render {type(illum).__name__.lower()} ({k} bounces)")
        result, bounces, fields = _render(config, illum, k, lightfield)
        full_how = None
        if stripes and config.black_level:
            bounces, fields, full_how = _add_black_level(config, k, bounces, fields, stage)
        stage("camera")
        images, dark = _camera(config, bounces.sum(axis=-3))
    return SimulatedCapture(
        config=config,
        bounces=bounces.astype(np.float32),
        images=images,
        dark=dark,
        lightfields=fields,
        n_bounces=k,
        rho=float(result.rho),
        converges=result.converges,
        n_theta=result.n_theta,
        refine=result.refine,
        full_illumination=full_how,
        timing={"compile": timing.compile, "run": timing.run, "total": timing.total},
        tail=None
        if config.tail is None
        else {"method": config.tail, "steps": int(result.tail_steps)},
    )


def _camera(config: SimulationConfig, totals: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """Captured images and dark frame: dark level added, then noise (seeded)."""
    dark_level = config.dark_level or 0.0
    images = totals + dark_level
    dark = None if config.dark_level is None else np.full(totals.shape[-2:], dark_level)
    if config.noise is not None:
        rng = np.random.default_rng(config.noise.seed)
        images = config.noise.apply(images, rng)
        if dark is not None:
            dark = config.noise.apply(dark, rng)
    return images.astype(np.float32), None if dark is None else dark.astype(np.float32)


# --------------------------------------------------------------------------- files


def shift_names(n: int, stem: str) -> list[str]:
    """``stem_00.exr``, ``stem_01.exr``, ... (two digits, more when n > 100)."""
    width = max(2, len(str(n - 1)))
    return [f"{stem}_{i:0{width}d}.exr" for i in range(n)]


def _bounce_channels(bounces: np.ndarray, k: int) -> dict[str, np.ndarray]:
    """Channels I1..IK, and ``tail`` (Σ_{k>K} I_k) where a tail solve added it."""
    return {f"I{i + 1}" if i < k else "tail": plane for i, plane in enumerate(bounces)}


def write_simulation(
    sim: SimulatedCapture,
    folder: str | os.PathLike,
    *,
    extra_metadata: dict | None = None,
    compact: bool = False,
) -> dict[str, str]:
    """Write a simulated capture's files into ``folder`` (which must exist); with
    ``compact``, not the per-bounce images (``bounces.npy``, ``bounces*.exr``: 129 MB
    of a 128x96 capture of 238 bounces), only what a fit reads and ``metadata.json``.

    Not atomic by itself: callers stage the folder with
    :func:`~lightfield_jax.files.atomic_directory`. Returns file name → description (also
    recorded in ``metadata.json``). The files:

    - ``bounces.npy``: float32 per-bounce images, [K, H, W] (index k−1 holds I_k), or
      [P, K, H, W] for stripes.
    - beam/full: ``bounces.exr`` (channels I1..IK), ``total.exr`` (channel ``Y``: the
      captured image Σ_k I_k + dark level, with noise).
    - stripes: per shift p, ``bounces_XX.exr`` (channels I1..IK) and ``shift_XX.exr``
      (channel ``Y``, the captured image), and ``capture.yaml`` (the capture format of
      :mod:`lightfield_jax.capture.capture`, the inverse pipeline's input).
    - ``dark.exr`` (channel ``Y``) when the config has a ``dark_level``.
    - ``lightfield.npy`` when light fields were rendered: float32 [K+1, H, W, n_theta]
      (L_0..L_K, radiance per radian), or [P, K+1, H, W, n_theta] for stripes.
    - ``metadata.json``: :meth:`SimulatedCapture.metadata`, the file list and
      ``extra_metadata``.
    """
    from lightfield_jax.capture.image_write import write_exr
    from lightfield_jax.capture.write import write_capture_yaml
    from lightfield_jax.files import atomic_write_json, atomic_write_npy

    folder = Path(folder)
    k = sim.n_bounces
    kk = "K+1" if sim.tail else "K"
    shape = f"[P, {kk}, H, W]" if sim.is_stripes else f"[{kk}, H, W]"
    tail = ", tail (the sum of the bounces past K)" if sim.tail else ""
    files = {}
    if not compact:
        files["bounces.npy"] = f"float32 {shape} per-bounce images, index k-1 holds I_k{tail}"
        atomic_write_npy(folder / "bounces.npy", sim.bounces)
    if sim.is_stripes:
        n = len(sim.images)
        per_bounce = [] if compact else zip(shift_names(n, "bounces"), sim.bounces, strict=True)
        for name, bounces in per_bounce:
            write_exr(folder / name, _bounce_channels(bounces, k))
            files[name] = f"channels I1..I{k}{tail}: per-bounce images of one shift"
        shifts = shift_names(n, "shift")
        for name, image in zip(shifts, sim.images, strict=True):
            write_exr(folder / name, {"Y": image})
            files[name] = "channel Y: the captured image of one shift"
    else:
        if not compact:
            write_exr(folder / "bounces.exr", _bounce_channels(sim.bounces, k))
            files["bounces.exr"] = f"channels I1..I{k}{tail}: per-bounce images"
        write_exr(folder / "total.exr", {"Y": sim.images})
        files["total.exr"] = "channel Y: the captured image (sum of bounces, dark level, noise)"
    if sim.dark is not None:
        write_exr(folder / "dark.exr", {"Y": sim.dark})
        files["dark.exr"] = "channel Y: dark frame (dark level with noise)"
    if sim.lightfields is not None:
        kk = "K+2" if sim.tail else "K+1"
        lf_shape = f"[P, {kk}, H, W, n_theta]" if sim.is_stripes else f"[{kk}, H, W, n_theta]"
        atomic_write_npy(folder / "lightfield.npy", sim.lightfields)
        unit = sim.config.geometry.lightfield_unit
        files["lightfield.npy"] = f"float32 {lf_shape} L_0..L_K{tail}, {unit}"
    if sim.is_stripes:
        illum = sim.config.illumination
        slab = sim.config.geometry.slab_or_none
        write_capture_yaml(
            folder / "capture.yaml",
            images=shifts,
            pattern=illum,
            dark_frame="dark.exr" if sim.dark is not None else None,
            black_level=sim.config.black_level,
            geometry=None if slab is None else slab.as_dict(),
            # The fit models the light as the simulation did: a fit's phase default
            # would otherwise compare sigma_s of two conventions.
            fit={"phase": sim.config.medium.phase},
            truth=sim.truth(),
        )
        files["capture.yaml"] = "the shifted images as a capture (input of the inverse pipeline)"
    files["metadata.json"] = "this file"
    metadata = {**sim.metadata(), "files": files, **(extra_metadata or {})}
    atomic_write_json(folder / "metadata.json", metadata)
    return files
