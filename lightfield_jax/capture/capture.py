"""A loaded capture (:class:`Capture`): its calibrated images, mask, stripe pattern and
what was measured from them, as :func:`~lightfield_jax.capture.loading.load_capture`
returns it (the capture file's format is described there)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from lightfield_jax.capture.calibration import (
    BlackLevel,
)
from lightfield_jax.capture.detect import Geometry
from lightfield_jax.capture.hdr import Brackets
from lightfield_jax.capture.keys import FIT_KEYS as FIT_KEYS
from lightfield_jax.capture.keys import GEOMETRY_KINDS as GEOMETRY_KINDS
from lightfield_jax.capture.response import Response
from lightfield_jax.scene.illumination import Stripes

# The smallest medium (px per side, after medium_roi) a capture may have; a fit also
# needs MIN_ALONG px along the light (inverse/noise.py).
MIN_SIDE = 6


class CaptureWarning(UserWarning):
    """Pixels of a capture were masked (non-finite, saturated or clipped)."""


@dataclasses.dataclass(frozen=True, eq=False)
class Capture:
    """A loaded, validated capture (see the module docstring).

    Attributes:
        images: float array [P, H, W, C]: the images after dark-frame subtraction and
            the ROI crop, in image units. Masked non-finite values are set to 0.
        channel_names: one name per channel.
        pattern: the stripes of each image, phases counted in the cropped frame.
        mask: bool [H, W, C], True where a pixel is valid in every image (finite in the
            images and the dark frame, and not saturated).
        sample_mask: bool [P, H, W, C], True where one image's value is valid: the joint
            fit uses every valid value, also those of a pixel clipped in other shifts.
        clipped: bool [P, H, W, C], True where a value was masked as saturated or clipped
            (finite): the joint fit treats these as censored from above.
        floored: bool [P, H, W, C], True where a value sits at a floor it was clamped at
            (a pile-up at a channel's lowest raw value: an integer file's lowest code, or
            a float frame's lowest value where the images show an additive noise that
            could have taken values below it): the fit masks these as censored from below;
            or ``None``.
        black_level: b, or ``None`` when unknown.
        roi: (x0, y0, x1, y1) of the medium in the full frame, or ``None``.
        pixel_size_mm: pixel pitch, or ``None``.
        saturation: the saturation threshold used, or ``None``.
        source: the capture file.
        image_paths: the image files (one ``.npy`` stack repeated for a stack).
        dark_frame: the dark frame's file, or ``None``.
        dark_level: the constant dark level subtracted instead (``dark_level`` key): one
            value, or one per channel (in ``channel_names``' order), or ``None``.
        n_masked: masked [H, W, C] entries: ``nonfinite``, ``saturated`` (finite but
            saturated or clipped in some image) and ``total``; ``values``: masked
            [P, H, W, C] values.
        geometry: the geometry mapping (``{"kind": "plane"}``).
        truth: the true parameters of a simulated capture, or ``None``.
        warnings: the messages of the :class:`CaptureWarning` s issued while loading.
        notes: what loading measured or decided on its own (``auto`` values, a dropped
            alpha channel, the sensor's bit depth), one line each.
        detected: what :func:`~lightfield_jax.capture.detect.detect_geometry` found, when a
            key asked for ``auto``; else ``None``.
        black_level_estimate: the estimate behind ``black_level: auto``, else ``None``.
        overview: the mean of the shifts over the whole camera frame (dark frame
            subtracted, flat-fielded), [H, W, C], before the ROI crop.
        black_frame, white_frame, flat_field: the files given for these keys, or ``None``.
        brackets: what merging exposure brackets did (:mod:`lightfield_jax.capture.hdr`), or
            ``None`` for single exposures.
        response: a single exposure's inverse response (``response`` key: ``linear``,
            ``srgb`` or a table file), ``None`` for brackets (``brackets.response``).
        exposure: the merged images' effective exposure T (seconds) [P, H, W, C] after
            the ROI crop (their noise: Var ∝ image / T), or ``None``.
        fit_options: the file's ``fit:`` settings (:class:`~lightfield_jax.FitOptions`
            fields), which :func:`~lightfield_jax.fit_capture` uses unless told otherwise.
    """

    images: np.ndarray
    channel_names: tuple[str, ...]
    pattern: Stripes
    mask: np.ndarray
    sample_mask: np.ndarray
    clipped: np.ndarray
    black_level: float | None
    roi: tuple[int, int, int, int] | None
    pixel_size_mm: float | None
    saturation: float | None
    source: Path
    image_paths: tuple[Path, ...]
    dark_frame: Path | None
    n_masked: dict[str, int]
    geometry: dict[str, Any]
    truth: dict[str, Any] | None
    warnings: tuple[str, ...]
    notes: tuple[str, ...] = ()
    detected: Geometry | None = None
    black_level_estimate: BlackLevel | None = None
    overview: np.ndarray | None = None
    black_frame: Path | None = None
    white_frame: Path | None = None
    flat_field: Path | None = None
    brackets: Brackets | None = None
    exposure: np.ndarray | None = None
    fit_options: dict[str, Any] = dataclasses.field(default_factory=dict)
    floored: np.ndarray | None = None
    response: Response | None = None
    dark_level: float | np.ndarray | None = None

    def response_record(self) -> dict:
        """The inverse response the codes were linearised with: ``kind`` (linear, srgb,
        auto, file) and ``source`` (a table's file, else ``None``)."""
        r = self.response if self.brackets is None else self.brackets.response
        if r is None:
            return {"kind": "linear", "source": None}
        return {"kind": r.kind, "source": None if r.source is None else str(r.source)}

    @property
    def n_images(self) -> int:
        return self.images.shape[0]

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the (cropped) images."""
        return self.images.shape[1:3]


__all__ = [
    "MIN_SIDE",
    "Capture",
    "CaptureWarning",
]
