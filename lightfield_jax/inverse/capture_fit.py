"""The fit of a whole capture (:func:`fit_capture`): every channel fitted with
:func:`~lightfield_jax.fit_images`'s driver (:mod:`lightfield_jax.inverse.fit`), the
channels sharing one smallest model (the union of their signal crops, grown to each
channel's model as they are fitted) so that they share compiled programs; the results
gathered in a :class:`CaptureFit`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
from collections.abc import Callable, Iterable, Iterator, Sequence

import numpy as np

from lightfield_jax.checks import repeated, shown
from lightfield_jax.inverse.fit import fit_one, model_from
from lightfield_jax.inverse.geometry_model import geometry_model
from lightfield_jax.inverse.method_base import FitMethod
from lightfield_jax.inverse.model_size import ModelSpec, at_least, signal_crop
from lightfield_jax.inverse.options import FitOptions, FitResult, check_options, check_progress
from lightfield_jax.scene.geometry import as_geometry
from lightfield_jax.scene.geometry_spec import parse_geometry
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import Stripes


@dataclasses.dataclass(frozen=True)
class CaptureFit:
    """The fit of every channel of a capture (one :class:`FitResult` each)."""

    channels: tuple[str, ...]
    results: tuple[FitResult, ...]

    def __post_init__(self):
        # One FitResult per channel: otherwise two channels with one result would write
        # that result as the first channel's (to_dict), and a result of another kind
        # would fail in to_dict.
        if len(self.channels) != len(self.results) or not self.results:
            raise ValueError(
                f"CaptureFit: needs one result per channel, got {len(self.channels)} "
                f"channel(s) and {len(self.results)} result(s)"
            )
        for result in self.results:
            if not isinstance(result, FitResult):
                raise ValueError(
                    f"CaptureFit: results: must be FitResults, got {type(result).__name__}"
                )

    @property
    def converged(self) -> bool:
        return all(r.converged for r in self.results)

    def __getitem__(self, channel: str) -> FitResult:
        if channel not in self.channels:  # naming the channels it has
            raise ValueError(
                f"channel: {shown(channel)} is not in the fit (it has {', '.join(self.channels)})"
            )
        return self.results[self.channels.index(channel)]

    def to_dict(self) -> dict:
        """``results.json``: the result's keys for one channel; for several, each key
        holds a list in channel order and ``per_channel`` the full results."""
        if len(self.results) == 1:
            return {**self.results[0].to_dict(), "channel": self.channels[0]}
        dicts = [r.to_dict() for r in self.results]
        keys = (
            "sigma_t",
            "sigma_s",
            "sigma_a",
            "g",
            "albedo",
            "gain",
            "black_level",
            "rho",
            "iterations",
            "residual",
        )
        out = {k: [d[k] for d in dicts] for k in keys}
        out["uncertainty"] = {
            k: [d["uncertainty"].get(k) for d in dicts] for k in dicts[0]["uncertainty"]
        }
        out.update(
            method=dicts[0]["method"],
            converged=self.converged,
            seconds={"total": sum(d["seconds"]["total"] for d in dicts)},
            model=[d["model"] for d in dicts],
            channels=list(self.channels),
            per_channel=dict(zip(self.channels, dicts, strict=True)),
        )
        return out


def fit_capture(
    capture,
    method: str | FitMethod = "joint",
    *,
    channels: Sequence[str] | None = None,
    options: FitOptions | None = None,
    progress: Callable[[str], None] | None = None,
    on_result: Callable[[str, FitResult], None] | None = None,
    **overrides,
) -> CaptureFit:
    """Fit a loaded capture (:func:`~lightfield_jax.load_capture`), channel by channel.

    Args:
        capture: the capture (images dark-subtracted and cropped to the medium), or
            its capture file's path (loaded with :func:`~lightfield_jax.load_capture`).
        method: ``joint`` (default), ``gradient`` or ``grid``, or a fit method
            (:class:`~lightfield_jax.Joint`, :class:`~lightfield_jax.TwoStep`,
            :class:`~lightfield_jax.GridSearch`: :mod:`lightfield_jax.inverse.methods`)
            whose own settings (its solver, start, grid size) replace these.
        channels: channel names to fit (default: every channel the capture holds; its
            file's ``channel`` key chooses which channels are loaded).
        options, overrides: see :func:`fit_images` (``options`` ``None``: the capture
            file's ``fit:`` settings, :attr:`Capture.fit_options`, whose ``phase`` is
            ``normalized`` where the file gives none).
        progress: called with a description of each stage.
        on_result: called with each channel's name and result as soon as that channel
            is fitted (an RGB fit takes minutes per channel).
    """
    check_options(options, "fit_capture")  # before the capture's load
    check_progress(progress, "fit_capture")
    check_progress(on_result, "fit_capture", "on_result")
    if channels is not None and (
        isinstance(channels, (str, bytes)) or not isinstance(channels, Iterable)
    ):  # a string would be split into letters ('red': 'r' is not in the capture), 0 a TypeError
        raise ValueError(
            "channels: must be a sequence of channel names (e.g. ['R', 'G']) or None, "
            f"got {shown(channels)}"
        )
    if isinstance(capture, (str, os.PathLike)):
        from lightfield_jax.capture.loading import load_capture

        capture = load_capture(capture)
    elif not hasattr(capture, "channel_names"):
        raise TypeError(
            f"fit_capture: expected a capture (lightfield_jax.load_capture) or a capture "
            f"file's path, got {type(capture).__name__}"
        )
    check_capture(capture)
    names = tuple(capture.channel_names)
    chosen = names if channels is None else tuple(channels)
    for c in chosen:
        if c not in names:
            raise ValueError(
                f"channel: {c!r} is not in the capture (it has {', '.join(names)}; the capture "
                "file's channel key chooses the channels it loads)"
            )
    if not chosen:
        raise ValueError("channel: no channel chosen (give at least one, or None for all)")
    twice = repeated(chosen)
    if twice:  # else fitted twice, its results listed twice and kept once by name
        raise ValueError(f"channel: {', '.join(map(repr, twice))} chosen more than once")
    results = []
    say = progress or (lambda _m: None)
    if options is None:  # the capture file's fit: settings, under the call's own
        from lightfield_jax.capture.keys import fit_phase

        settings = getattr(capture, "fit_options", None) or {}
        # Made with the call's method: the file's g_grid or start_grid goes to the
        # method that takes it (options made for the joint fit would not keep them).
        options = FitOptions(method, **{**settings, "phase": fit_phase(capture)})
    opts = options.replace(method=method, **overrides)
    if opts.model.geometry is None and "geometry" not in overrides:
        geometry = parse_geometry(getattr(capture, "geometry", None), "geometry", allow_auto=True)
        opts = opts.replace(geometry=geometry)
    for c in chosen:  # a dark channel, before any fit runs
        i = names.index(c)
        images = np.asarray(capture.images[..., i])
        valid = np.broadcast_to(channel_mask(capture, i), images.shape) & np.isfinite(images)
        if not np.any(images[valid] > 0):
            with _naming(c, chosen):
                raise ValueError(f"channel {c}: no light (no valid value above 0)")
    floor = _capture_floor(capture, [names.index(c) for c in chosen], opts)
    for c in chosen:
        i = names.index(c)
        with _naming(c, chosen):
            result = fit_one(
                capture.images[..., i],
                capture.pattern,
                opts,
                (lambda m, c=c: say(f"[{c}] {m}")) if len(chosen) > 1 else say,
                # Per value: a pixel clipped in some shifts keeps its others. The capture
                # masked saturated values in raw units already (before the dark frame).
                mask=channel_mask(capture, i),
                clipped=_channel(capture, "clipped", i),
                floored=_channel(capture, "floored", i),
                black_level=capture.black_level,
                pixel_size_mm=capture.pixel_size_mm,
                exposure=_channel(capture, "exposure", i),
                floor=floor,
            )
        results.append(result)
        if on_result is not None:
            on_result(c, result)
        if len(chosen) > 1:
            say(f"[{c}] {_one_line(result)}")
        if floor is not None:
            # The next channel's model is at least this one's: one compiled program
            # serves every channel whose need it covers.
            floor = at_least(floor, model_from(result.model))
    return CaptureFit(channels=chosen, results=tuple(results))


def check_capture(capture) -> None:
    """Refuse a capture whose parts disagree (one made or changed by hand, e.g. with
    ``dataclasses.replace``): unchecked, a channel name too many was an IndexError, a
    mask of other shifts numpy's broadcast error, a pattern of None an AttributeError,
    and a negative pixel pitch was reported as negative coefficients per mm."""
    from lightfield_jax.capture.keys import check_pixel_size

    images = np.asarray(capture.images)
    names = capture.channel_names
    if images.ndim != 4 or 0 in images.shape or images.dtype.kind != "f":
        raise ValueError(
            "fit_capture: capture.images: must be floats [shifts, height, width, channels], "
            f"got {images.dtype} of shape {images.shape}"
        )
    if not (isinstance(names, (tuple, list)) and all(isinstance(n, str) for n in names)):
        raise ValueError(f"fit_capture: capture.channel_names: must be names, got {shown(names)}")
    if len(names) != images.shape[-1] or len(set(names)) != len(names):
        raise ValueError(
            f"fit_capture: capture.channel_names: {shown(tuple(names))} must name each of the "
            f"images' {images.shape[-1]} channel(s) once"
        )
    pattern = capture.pattern
    if not isinstance(pattern, Stripes) or pattern.n_patterns != images.shape[0]:
        raise ValueError(
            f"fit_capture: capture.pattern: must be the Stripes of the {images.shape[0]} "
            f"shifts, got {shown(pattern)}"
        )
    shapes = {"mask": images.shape[1:]} | dict.fromkeys(
        ("sample_mask", "clipped", "floored", "exposure"), images.shape
    )
    for key, shape in shapes.items():
        value = getattr(capture, key, None)
        if (value is not None or key == "mask") and np.shape(value) != shape:
            raise ValueError(
                f"fit_capture: capture.{key}: must have the shape {shape}, got {np.shape(value)}"
            )
    check_pixel_size(getattr(capture, "pixel_size_mm", None), "fit_capture: capture.pixel_size_mm")


@contextlib.contextmanager
def _naming(channel: str, chosen) -> Iterator[None]:
    """A channel's error names the channel (the others may fit alone)."""
    try:
        yield
    except ValueError as e:
        if len(chosen) < 2:
            raise
        others = ", ".join(c for c in chosen if c != channel)
        said = str(e)
        if not said.startswith(f"channel {channel}: "):
            said = f"channel {channel}: {said}"
        message = (
            f"{said} (the other channels, {others}, can be fitted alone: channel: in the "
            "capture file, --channel on the command line)"
        )
        try:
            named = type(e)(message)
        except TypeError:  # an error type with other arguments
            named = ValueError(message)
        raise named from e


def channel_mask(capture, i: int) -> np.ndarray:
    """Channel i's valid values, (P, H, W) (a capture without per-value masks: its
    per-pixel mask, (H, W))."""
    samples = getattr(capture, "sample_mask", None)
    return capture.mask[..., i] if samples is None else samples[..., i]


def _channel(capture, name: str, i: int):
    """Channel i of a capture's per-value array ``name`` (the merged brackets'
    ``exposure`` T, the ``clipped`` flags), or ``None`` where it has none."""
    values = getattr(capture, name, None)
    return None if values is None else values[..., i]


def _one_line(result: FitResult) -> str:
    flag = "converged" if result.converged else "NOT converged"
    return (
        f"sigma_t {result.sigma_t:.5g}, sigma_s {result.sigma_s:.5g}, g {result.g:.4f} "
        f"({flag}; {result.seconds['total']:.1f} s, {result.seconds['compile']:.1f} s compile)"
    )


def _capture_floor(capture, channels: list[int], options: FitOptions) -> ModelSpec | None:
    """The smallest model every channel of ``capture`` is fitted with: the union of the
    channels' signal crops (one shape for all), the cheapest discretisation (grown to
    each channel's model as the channels are fitted). ``None`` under geometry auto."""
    if as_geometry(options.model.geometry).chosen_by_fit:
        return None
    images = np.asarray(capture.images)
    p, h, w = images.shape[:3]
    crop = (0, 0, w, h)
    if options.model.crop:
        crops = []
        for i in channels:
            # The values the fit keeps (per value, as fit_images crops them).
            keep = np.broadcast_to(channel_mask(capture, i), images[..., i].shape)
            keep = keep & np.isfinite(images[..., i])
            crops.append(
                signal_crop(
                    np.where(keep, images[..., i], 0.0),
                    capture.pattern,
                    options.model.crop_fraction,
                )
            )
        crop = tuple(f(c[k] for c in crops) for k, f in enumerate((min, min, max, max)))
    return ModelSpec(
        grid=Grid(crop[2] - crop[0], crop[3] - crop[1], 8, 1),
        bounces=2,
        crop=crop,
        converges=True,
        rho=0.0,
        geometry=geometry_model(options.model.geometry).smallest(),
    )
