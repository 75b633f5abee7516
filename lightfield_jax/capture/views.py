"""Look at the transport without code: the per-bounce images and light fields of a
simulated scene (``lightfield-jax simulate --plot``) or of a fitted medium in its
capture's geometry (``lightfield-jax render results.json``), as files and the paper's
figures (:func:`lightfield_jax.viz.plot_transport`).

Both render the scene under full illumination through the capture's (or config's)
entry wall and heading: the light every shift adds up to, which the figures show
(stripes would draw the stripes, not the transport). A fitted medium is rendered on
its fit's model: the model region (``model.crop`` of the results, inside the capture's
medium ROI: the fit crops where the light fades), its θ bins, refinement, bounces,
geometry and phase convention, with the fitted gain.

Light fields take (K+1)·H·W·n_theta floats; above :data:`MAX_LIGHTFIELD_FLOATS` they are
not rendered (said in the returned notes), the images still are.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from lightfield_jax.checks import gain_problem, number_problem, one_path_part, shown
from lightfield_jax.forward.render import (
    RenderResult,
    model_memory,
    render,
    resolve_bounces,
    resolve_model,
)
from lightfield_jax.scene.geometry import paper_bound
from lightfield_jax.scene.geometry_spec import parse_fitted_geometry
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import Beam, Full, Stripes
from lightfield_jax.scene.medium import Medium

MAX_LIGHTFIELD_FLOATS = 50_000_000  # 200 MB of float32
# A fit's results file is a few kilobytes per channel.
MAX_RESULTS_BYTES = 1 << 24


def full_light(illumination) -> Beam | Full:
    """The full illumination of stripes (same wall and heading); a beam or full as is."""
    if isinstance(illumination, Stripes):
        return Full(direction_deg=illumination.direction_deg, entry=illumination.entry)
    return illumination


def render_transport(
    medium: Medium, grid: Grid, light, bounces, *, gain=1.0, geometry=None, what="the render"
) -> tuple[RenderResult, list[str]]:
    """Per-bounce images and (memory allowing) light fields of a scene; notes say what
    was left out. A render estimated to need more memory than the limit is refused
    (:func:`~lightfield_jax.runtime.memory.check_memory`, naming ``what``)."""
    from lightfield_jax.runtime.memory import check_memory

    resolved, model_geometry, rho = resolve_model(medium, grid, geometry)
    k = resolve_bounces(float(rho), bounces, paper=paper_bound(medium, model_geometry))
    size = (k + 1) * resolved.height * resolved.width * resolved.n_theta
    fields = size <= MAX_LIGHTFIELD_FLOATS
    check_memory(model_memory(1, resolved, model_geometry, k, fields), what)
    result = render(medium, grid, light, k, gain=gain, lightfield=fields, geometry=geometry)
    if fields:
        return result, []
    return result, [
        f"light fields not rendered: {size:.3g} floats (K+1 = {k + 1}, {resolved.width}x"
        f"{resolved.height}, n_theta {resolved.n_theta}) exceed {MAX_LIGHTFIELD_FLOATS:.0e}"
    ]


def write_transport(result: RenderResult, folder: Path, compact: bool = False) -> dict[str, str]:
    """``bounces.npy``/``bounces.exr`` (I_1..I_K) and ``lightfield.npy`` (L_0..L_K);
    ``compact``: ``bounces.npy`` only (the EXR repeats it, the light fields are most of
    the bytes: 104 MB for a 128x96 render of 238 bounces)."""
    from lightfield_jax.capture.image_write import write_exr
    from lightfield_jax.files import atomic_write_npy

    images = np.asarray(result.images, np.float32)
    atomic_write_npy(folder / "bounces.npy", images)
    files = {"bounces.npy": "float32 [K, H, W] per-bounce images, index k-1 holds I_k"}
    if compact:
        return files
    write_exr(folder / "bounces.exr", {f"I{k + 1}": im for k, im in enumerate(images)})
    files["bounces.exr"] = f"channels I1..I{len(images)}: per-bounce images"
    if result.lightfields is not None:
        atomic_write_npy(folder / "lightfield.npy", np.asarray(result.lightfields, np.float32))
        files["lightfield.npy"] = "float32 [K+1, H, W, n_theta] L_0..L_K, radiance per radian"
    return files


_FIT_KEYS = ("sigma_t", "sigma_s", "g", "gain")
_MODEL_KEYS = ("width", "height", "n_theta", "refine", "bounces", "crop")


def _folder_name(name) -> bool:
    """Whether ``name`` names one folder inside another: not empty, no separator, not
    ``.`` or ``..`` (an edited results file's ``../x`` or ``/x`` would write elsewhere)."""
    return isinstance(name, str) and name not in ("", ".", "..") and one_path_part(name)


def _channel_results(data: dict[str, Any], source: Path) -> dict[str, dict[str, Any]]:
    """Each channel's fit, checked: its values are numbers and its model is complete."""
    if not isinstance(data, dict) or ("model" not in data and "per_channel" not in data):
        raise ValueError(f"{source}: not a results file of lightfield-jax fit (no model)")
    per_channel = data.get("per_channel")
    if "per_channel" in data and not (
        isinstance(per_channel, dict)
        and per_channel
        and all(isinstance(f, dict) for f in per_channel.values())
    ):
        raise ValueError(
            f"{source}: per_channel: must map each channel's name to its fit, got "
            f"{shown(per_channel)}"
        )
    if "per_channel" not in data and not isinstance(data.get("channel", "Y"), str):
        # An edited list or mapping: one line, not a TypeError (an unhashable name).
        raise ValueError(
            f"{source}: channel: must be the channel's name, got {shown(data['channel'])}"
        )
    channels = dict(per_channel) if "per_channel" in data else {data.get("channel", "Y"): data}
    for name, fit in channels.items():
        if len(channels) > 1 and not _folder_name(name):
            raise ValueError(
                f"{source}: per_channel: {shown(name)} is not a channel name render can use as "
                "a subfolder of DIR (a name with no / or \\, not . or ..)"
            )
        model = fit.get("model")
        missing = [k for k in _FIT_KEYS if not isinstance(fit.get(k), (int, float))]
        missing += [
            f"model.{k}" for k in _MODEL_KEYS if not isinstance(model, dict) or k not in model
        ]
        if missing:
            raise ValueError(
                f"{source}: channel {name}: no usable {', '.join(missing)} (a failed fit?)"
            )
        converged = fit.get("converged", True)
        if not isinstance(converged, bool):  # "no" is no verdict
            raise ValueError(
                f"{source}: channel {name}: converged: must be true or false, got "
                f"{shown(converged)}"
            )
        for key in ("width", "height"):  # before the crop is compared with them
            if (problem := number_problem(model[key], integer=True, low=2)) is not None:
                raise ValueError(f"{source}: channel {name}: model.{key}: {problem}")
        crop = model["crop"]
        if not (
            isinstance(crop, list)
            and len(crop) == 4
            and all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in crop)
            and crop[0] < crop[2]
            and crop[1] < crop[3]
        ):
            raise ValueError(
                f"{source}: channel {name}: model.crop: must be [x0, y0, x1, y1] with "
                f"0 <= x0 < x1 and 0 <= y0 < y1, got {crop!r}"
            )
        size = (crop[2] - crop[0], crop[3] - crop[1])
        if (model["width"], model["height"]) != size:
            raise ValueError(
                f"{source}: channel {name}: model.crop: {crop!r} is {size[0]}x{size[1]} "
                f"pixels, but model.width x height is {model['width']!r}x{model['height']!r}"
            )
    return {str(k): v for k, v in channels.items()}


def _results_key(error: ValueError, model_key: str, results_key: str) -> str:
    """``error``'s message with its leading key ``model_key`` said as the results file's
    ``results_key``."""
    text = str(error)
    if text.startswith(model_key):
        return results_key + text[len(model_key) :]
    return text


def unconverged_fit(fit: dict[str, Any]) -> str | None:
    """Why a fit of a results file is not to be trusted (``converged: false``): its
    ``reasons``, else its ``message``; ``None`` for a converged fit (or one that does
    not say)."""
    if "converged" not in fit or fit["converged"] is True:
        return None
    reasons = fit.get("reasons")
    if isinstance(reasons, list) and reasons:
        return "; ".join(str(r) for r in reasons)
    message = fit.get("message")
    return str(message) if message else "no reason recorded"


def _results_text(source: Path) -> str:
    """The text of a results file, refused before the read where it is no regular file
    (a FIFO would block the read forever)."""
    from lightfield_jax.files import require_regular_file

    require_regular_file(source, "a results file", ValueError)
    size = os.path.getsize(source)
    if size > MAX_RESULTS_BYTES:  # read whole, it would take several times its size
        raise ValueError(
            f"{source}: {size} bytes is too large for a results file of lightfield-jax fit "
            f"(at most {MAX_RESULTS_BYTES}; a fit writes a few kilobytes)"
        )
    try:
        return source.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:  # the codec's own message names no file
        byte = e.object[e.start : e.start + 1].hex()
        raise ValueError(
            f"{source}: not UTF-8 text (byte 0x{byte} at offset {e.start}): not a results "
            "file of lightfield-jax fit"
        ) from None


def read_results(results: str | os.PathLike) -> tuple[dict[str, Any], Path]:
    """A results file's data and path, read once (render checks its outputs against it,
    then renders from the same data): a ``ValueError`` naming the file where it is no
    regular file, not UTF-8, not JSON or nested too deeply."""
    source = Path(results)
    try:
        return json.loads(_results_text(source)), source
    except json.JSONDecodeError as e:
        raise ValueError(f"{source}: not JSON ({e})") from None
    except RecursionError:
        raise ValueError(f"{source}: nested too deeply to be a results file") from None


def render_folders(data: dict[str, Any], source: Path, folder: Path) -> list[Path]:
    """The per-channel subfolders of ``folder`` that :func:`render_results` writes for
    the results ``data`` read from ``source`` (none for one channel), for the output
    checks before the work; none for results it cannot use either
    (:func:`render_results` says why)."""
    try:
        channels = _channel_results(data, source)
    except (ValueError, RecursionError, TypeError, AttributeError, KeyError):
        return []
    return [folder / name for name in channels] if len(channels) > 1 else []


def _capture_path(data: dict, source: Path) -> Path:
    """The capture file a results file ``data`` (read from ``source``) names."""
    if "capture" not in data:
        raise ValueError(f"{source}: names no capture (key 'capture'), whose geometry is needed")
    if not isinstance(data["capture"], str) or not data["capture"]:
        raise ValueError(
            f"{source}: capture: must be the capture file's path, got {data['capture']!r}"
        )
    # The fit writes the capture's absolute path; a relative one (a hand-written or
    # moved results file) is tried here, then beside the results. A relative path that
    # names one file here and another beside the results is refused: which capture's
    # geometry is meant cannot be told.
    named = Path(data["capture"])
    candidates = [named, source.parent / named, source.parent / named.name]
    found = {os.path.realpath(c): c for c in candidates if c.exists()}
    if len(found) > 1:
        here, beside = list(found.values())[:2]
        raise ValueError(
            f"{source}: capture: {named} names two files, {here} (from the current folder) "
            f"and {beside} (beside the results): run render where the fit ran, or give the "
            "capture's absolute path in the results"
        )
    return next(iter(found.values()), named)


def render_inputs(data: dict[str, Any], source: Path) -> list[Path]:
    """The capture file that the results ``data`` (read from ``source``) name and every
    file it lists (the inputs render's outputs must not replace); none for results or a
    capture that :func:`render_results` cannot use (it says why)."""
    from lightfield_jax.capture.paths import capture_files

    try:
        return capture_files(_capture_path(data, source))
    except (OSError, ValueError, RecursionError, TypeError, AttributeError, KeyError):
        return []


def render_results(
    data: dict[str, Any],
    source: Path,
    folder: Path,
    *,
    plot: bool,
    stage=lambda _s: None,
    warn=lambda _t: None,
    compact: bool = False,
) -> tuple[dict[str, str], list[str]]:
    """Render the fitted medium of every channel of the results ``data`` (read from
    ``source`` by :func:`read_results`) into ``folder`` (one subfolder per channel when
    there are several): the files written and notes.
    ``warn`` is told at once of a channel whose fit did not converge (rendered all
    the same; its ``render.json`` says so)."""
    from lightfield_jax.capture.loading import load_capture
    from lightfield_jax.files import atomic_write_json

    channels = _channel_results(data, source)
    capture_path = _capture_path(data, source)
    stage("load the capture")
    try:
        capture = load_capture(capture_path)
    except FileNotFoundError as e:
        raise ValueError(f"{source}: capture: {e}") from None
    except ValueError as e:  # not a capture file (capture: /etc/passwd): named by its key
        e.args = (f"{source}: capture: {e}",)  # its kind kept (a MemoryLimitError)
        raise
    height, width = capture.shape
    for name, fit in channels.items():
        crop = fit["model"]["crop"]
        if crop[2] > width or crop[3] > height:
            raise ValueError(
                f"{source}: channel {name}: model.crop: {crop!r} lies outside the capture's "
                f"{width}x{height} images (its medium ROI), [0, 0, {width}, {height}]"
            )
    light = full_light(capture.pattern)
    files, notes = {}, []
    for name, fit in channels.items():
        target = folder / name if len(channels) > 1 else folder
        m = fit["model"]
        where = f"{source}: channel {name}"
        geometry = parse_fitted_geometry(m.get("geometry"), f"{source}: model.geometry")
        gain = fit.get("gain")
        if (problem := gain_problem(gain)) is not None:
            raise ValueError(f"{where}: gain: {problem}")
        unconverged = unconverged_fit(fit)
        fit_warning = None
        if unconverged is not None:
            fit_warning = (
                f"{where}: the fit did not converge ({unconverged}); rendering its values "
                "all the same"
            )
            warn(fit_warning)
        # The model's messages name its own keys (medium.g, grid.n_theta, bounces);
        # said here by the results file's (g, model.n_theta, model.bounces).
        try:
            medium = Medium(fit["sigma_t"], fit["sigma_s"], fit["g"], fit.get("phase", "paper"))
        except ValueError as e:
            raise ValueError(f"{where}: {_results_key(e, 'medium.', '')}") from None
        try:
            grid = Grid(m["width"], m["height"], m["n_theta"], m["refine"])
        except ValueError as e:
            raise ValueError(f"{where}: {_results_key(e, 'grid.', 'model.')}") from None
        try:
            resolve_bounces(0.0, m["bounces"])  # its type; "auto" is resolved below
        except ValueError as e:
            raise ValueError(f"{where}: {_results_key(e, 'bounces', 'model.bounces')}") from None
        stage(f"render {name}")
        result, left_out = render_transport(
            medium,
            grid,
            light,
            m["bounces"],
            gain=float(gain),
            geometry=geometry,
            what=f"{where}: the render",
        )
        notes += [f"[{name}] {n}" for n in left_out]
        target.mkdir(exist_ok=True)
        written = write_transport(result, target, compact)
        about = {
            "results": str(source),
            "capture": str(capture_path),
            "channel": name,
            "medium": {k: fit[k] for k in ("sigma_t", "sigma_s", "g", "gain", "phase") if k in fit},
            "illumination": f"full, {light.entry} wall, {light.direction_deg:g} deg",
            "model_crop": m["crop"],
            "medium_roi": None if capture.roi is None else list(capture.roi),
            "bounces": result.bounces,
            "n_theta": result.n_theta,
            "notes": left_out,
            "fit_converged": unconverged is None,
        }
        if fit_warning is not None:
            about["fit_warning"] = fit_warning
        atomic_write_json(target / "render.json", about)
        written["render.json"] = "what was rendered (medium, model region, illumination)"
        if plot:
            from lightfield_jax.viz import plot_transport

            stage(f"plot {name}")
            title = (
                f"[{name}] fitted σt {fit['sigma_t']:.4g}, σs {fit['sigma_s']:.4g} px⁻¹, "
                f"g {fit['g']:.3f}; model region {m['crop']} of the ROI"
            )
            for p in plot_transport(result, target, illumination=light, title=title):
                written[p.name] = "figure"
        prefix = f"{name}/" if len(channels) > 1 else ""
        files.update({prefix + k: v for k, v in written.items()})
    return files, notes


def plot_simulation(
    sim, folder: Path, *, stage=lambda _s: None
) -> tuple[dict[str, str], list[str]]:
    """The paper's figures of a simulated scene (:class:`~lightfield_jax.SimulatedCapture`)
    into ``folder``: its medium, grid, geometry and gain under the config's light (full
    illumination for stripes), K = the simulation's bounces."""
    from lightfield_jax.viz import plot_transport

    config = sim.config
    light = full_light(config.illumination)
    stage("render the light fields for the figures")
    result, notes = render_transport(
        config.medium.medium(),
        config.grid,
        light,
        sim.n_bounces,
        gain=config.gain,
        geometry=config.geometry,
    )
    stage("plot")
    m = config.medium
    title = f"simulated σt {m.sigma_t:g}, σs {m.sigma_s:g} px⁻¹, g {m.g:g}"
    figures = plot_transport(result, folder, illumination=light, title=title)
    return {p.name: "figure" for p in figures}, notes
