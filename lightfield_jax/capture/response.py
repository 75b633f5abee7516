"""The camera's inverse response: a sample value to linear exposure, per channel.

A sample value z ∈ [0, 1] (integer codes scaled by their type's maximum)
is mapped to a linear exposure x = f⁻¹(z) (relative units) by the camera's inverse
response, per channel (:class:`Response`): ``linear`` (x = z, a raw converter's
linear output), ``srgb`` (the sRGB curve of most 8-bit camera files,
:func:`srgb_response`), a table from a file (:func:`load_response`), or ``auto``, recovered
from the brackets themselves (:func:`calibrate_response`) with OpenCV's Debevec–Malik
calibration (``cv2.createCalibrateDebevec``: the smooth g = ln f⁻¹ that makes
g(z_ij) − ln t_j agree between the exposures of every sample pixel, a linear least-
squares problem over 256 codes). OpenCV's calibration takes 8-bit images only: for
16-bit brackets the samples are rounded to 8 bits for the calibration and the curve is
interpolated at their full resolution. OpenCV picks its sample pixels at random (or on
a grid) from the frame, which in a mostly dark tank image lands mostly on black
pixels; here 256 pixels are chosen with their summed codes evenly spread over the range
they cover and handed to it as a 16×16 image on its grid, with a smoothness weight
λ = 50 (measured on 8-bit γ 2.2 brackets of such scenes: the curve is within 1-2 % of
the truth over codes 16-232 with λ = 50, within 10 % with OpenCV's default 10). The
curve is not supported near the top code (few samples, and the calibration's hat weight
vanishes there: 4-17 % off above code 240), so with an ``auto`` response samples above
``AUTO_CLIP`` = 0.9 count as clipped. An ``auto`` curve is normalised to x(0.5) = 1 and
x(0) = 0 (Debevec's log curve leaves the black code undetermined). The calibration
assumes z = f(E·t): light that scales with the exposure (ambient light is fine), no
black pedestal under the non-linear curve (cameras that write gamma-encoded files
subtract their black level before encoding). Measured with a pedestal of 2 % of full
scale under γ 2.2, the recovered curve is 10-30 % low over z 0.25-0.4 and the fit's g
0.025 low.

OpenCV is imported inside :func:`calibrate_response`, so ``import lightfield_jax``
does not load it.
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lightfield_jax.capture.io import CaptureError, error_line, load_npy, require_capture_file
from lightfield_jax.files import atomic_write_text

RESPONSES = ("linear", "srgb", "auto")


CLIP = 0.98


AUTO_CLIP = 0.9


_SMOOTHNESS = 50.0


NEAR_BLACK = 0.005


MAX_QUANTISATION = 0.05


_CALIBRATION_PIXELS = 256


@dataclasses.dataclass(frozen=True, eq=False)
class Response:
    """The camera's inverse response x = f⁻¹(z), per channel.

    Attributes:
        kind: ``linear``, ``srgb``, ``auto`` (recovered from the brackets) or ``file``.
        codes: z at the table's nodes, increasing over [0, 1], shape (N,).
        curve: x at the nodes, shape (N, C) (C = 1: every channel alike), increasing.
        source: the file a ``file`` curve came from, else ``None``.
    """

    kind: str
    codes: np.ndarray
    curve: np.ndarray
    source: Path | None = None

    def linearize(self, z: np.ndarray) -> np.ndarray:
        """x = f⁻¹(z) for samples z (…, C) in [0, 1]."""
        z = np.asarray(z, np.float64)
        if self.kind == "linear":
            return z
        if self.kind == "srgb":
            return _srgb_decode(z)
        out = np.empty_like(z)
        for c in range(z.shape[-1]):
            column = self.curve[:, min(c, self.curve.shape[1] - 1)]
            out[..., c] = np.interp(z[..., c], self.codes, column)
        return out

    def encode(self, x: np.ndarray) -> np.ndarray:
        """z = f(x), the code of linear exposures x (…, C) (the inverse of
        :meth:`linearize`, clipped to [0, 1])."""
        x = np.asarray(x, np.float64)
        if self.kind == "linear":
            return np.clip(x, 0.0, 1.0)
        if self.kind == "srgb":
            return srgb_encode(np.clip(x, 0.0, 1.0))
        out = np.empty_like(x)
        for c in range(x.shape[-1]):
            column = self.curve[:, min(c, self.curve.shape[1] - 1)]
            out[..., c] = np.interp(x[..., c], column, self.codes)
        return out

    def step(self, z: np.ndarray, levels: int | None) -> np.ndarray:
        """f⁻¹(z + Δz) − f⁻¹(z): the linear size of one code at z (0 for float samples,
        ``levels`` None)."""
        if levels is None:
            return np.zeros(np.shape(z))
        return self.linearize(np.minimum(z + 1.0 / (levels - 1), 1.0)) - self.linearize(z)

    def near_black(self, levels: int | None) -> np.ndarray:
        """Per channel, the code z below which a sample without a dark frame is near
        black (module docstring); ``levels``: the samples' number of codes (None: float)."""
        n = self.curve.shape[1]
        z = np.repeat(np.linspace(0.0, 1.0, 1025)[:, None], n, axis=1)
        with np.errstate(invalid="ignore"):
            coarse = ~(self.step(z, levels) <= MAX_QUANTISATION * self.linearize(z))
        z = z[:, 0]
        out = np.empty(n)
        for c in range(n):
            bad = np.flatnonzero(coarse[: int(CLIP * 1024), c])
            out[c] = max(NEAR_BLACK, z[bad[-1] + 1] if bad.size else 0.0)
        return out

    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "source": None if self.source is None else str(self.source),
            "codes": self.codes.tolist(),
            "curve": self.curve.T.tolist(),
        }


def linear_response() -> Response:
    return Response("linear", np.array([0.0, 1.0]), np.array([[0.0], [1.0]]))


def _srgb_decode(z: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.where(z <= 0.04045, z / 12.92, ((np.maximum(z, 0.04045) + 0.055) / 1.055) ** 2.4)


def srgb_encode(x: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.where(
            x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 0.0031308) ** (1 / 2.4) - 0.055
        )


def srgb_response() -> Response:
    """The sRGB transfer curve (IEC 61966-2-1), which cameras, phones and image editors
    write into 8-bit files: x = z/12.92 for z ≤ 0.04045, else ((z + 0.055)/1.055)^2.4
    (evaluated exactly; the table, 1025 nodes, is what ``to_dict`` records)."""
    z = np.linspace(0.0, 1.0, 1025)
    return Response("srgb", z, _srgb_decode(z)[:, None])


def _header_names(text: str) -> list[str]:
    """The channel names of a table's ``# z, x_R, x_G, x_B`` header (:func:`write_response`)."""
    for line in text.splitlines():
        if line.lstrip().startswith("#"):
            words = line.lstrip("# \t").replace(",", " ").split()
            if words[:1] == ["z"] and all(w.startswith("x_") for w in words[1:]):
                return [w[2:] for w in words[1:]]
    return []


# A response table has at most one row per code of a 16-bit camera (65536 rows of a
# code and four columns: about 5 MB of text).
MAX_RESPONSE_BYTES = 1 << 24


def load_response(
    path: str | os.PathLike, n_channels: int, names: Sequence[str] | None = None
) -> Response:
    """A response table: a text file (CSV or whitespace, ``#`` comments) or ``.npy``
    array whose first column is z in [0, 1] (increasing, from 0 to 1) and whose other
    columns are x = f⁻¹(z), one column for every channel or one per channel,
    increasing (as :func:`write_response` writes them). Columns named in a header
    (``# z, x_R, x_G, x_B``) are taken by name: those of ``names``, the capture's
    channels (also one chosen with ``channel:``), in their order."""
    path = Path(path)
    # A FIFO would block the read forever, a folder or device is no table.
    require_capture_file(path, "a response table")
    size = os.path.getsize(path)
    if size > MAX_RESPONSE_BYTES:  # parsed as text, it would take ten times its size
        raise CaptureError(
            f"{path}: {size} bytes is too large for a response table (at most "
            f"{MAX_RESPONSE_BYTES}: one row per code of a 16-bit camera is about 5 MB)"
        )
    header: list[str] = []
    try:
        if path.suffix.lower() == ".npy":
            table = load_npy(path)  # its header checked against the memory first
            if table.dtype.kind not in "iuf":
                raise CaptureError(
                    f"{path}: a response table holds numbers, got an array of dtype {table.dtype}"
                )
        else:
            text = path.read_text()
            header = _header_names(text)
            with warnings.catch_warnings():  # "input contained no data": the shape says it
                warnings.simplefilter("ignore", UserWarning)
                table = np.loadtxt(text.replace(",", " ").splitlines(), ndmin=2)
    except (OSError, ValueError) as e:
        if isinstance(e, CaptureError):
            raise
        raise CaptureError(f"{path}: cannot read a response table ({error_line(e)})") from None
    table = np.asarray(table, np.float64)
    wanted = list(names or ())
    if wanted and table.ndim == 2 and len(header) == table.shape[1] - 1 > 1:
        # Columns named in the header are taken by name, in the capture's order.
        if not set(wanted) <= set(header):
            raise CaptureError(
                f"{path}: its header names the channels {', '.join(header)}, but the "
                f"capture's are {', '.join(wanted)}"
            )
        table = table[:, [0] + [1 + header.index(n) for n in wanted]]
    if table.ndim != 2 or table.shape[1] not in (2, n_channels + 1) or table.shape[0] < 2:
        raise CaptureError(
            f"{path}: a response table has rows (z, x) or (z, x per channel: {n_channels}), "
            f"got shape {table.shape}"
        )
    codes, curve = table[:, 0], table[:, 1:]
    if not np.all(np.isfinite(table)) or codes[0] != 0.0 or codes[-1] != 1.0:
        raise CaptureError(f"{path}: the first column (z) must run from 0 to 1, finite")
    if np.any(np.diff(codes) <= 0) or np.any(np.diff(curve, axis=0) < 0):
        raise CaptureError(f"{path}: z must increase and x must not decrease down the table")
    if np.any(curve[-1] <= curve[0]):
        raise CaptureError(f"{path}: x is constant down the table: not a response (x(1) > x(0))")
    return Response("file", codes, curve, path)


def write_response(path: str | os.PathLike, response: Response, names: Sequence[str]) -> Path:
    """Write a response table (CSV, header comment) that ``response: FILE`` reads."""
    curve = response.curve
    header = "# z, " + ", ".join(f"x_{n}" for n in names[: curve.shape[1]])
    rows = [
        ", ".join(f"{v:.8g}" for v in (z, *x)) for z, x in zip(response.codes, curve, strict=True)
    ]
    return atomic_write_text(path, "\n".join([header, *rows]) + "\n")


def _calibration_pixels(samples: np.ndarray, clip: float) -> np.ndarray:
    """Indices of up to 256 pixels of a (J, N) channel whose summed codes spread evenly
    over their range, among the pixels neither black nor clipped in every exposure."""
    score = samples.sum(axis=0)
    usable = np.flatnonzero((samples.max(axis=0) > 0) & (samples.min(axis=0) < clip))
    if usable.size < 16:
        raise CaptureError(
            "auto: fewer than 16 pixels are lit and unclipped in some exposure; "
            "give response: linear or a response file"
        )
    order = usable[np.argsort(score[usable])]
    targets = np.linspace(score[order[0]], score[order[-1]], _CALIBRATION_PIXELS)
    picks = np.clip(np.searchsorted(score[order], targets), 0, order.size - 1)
    return order[np.unique(picks)]


def calibrate_response(
    brackets: np.ndarray, times: Sequence[float], clip: float = CLIP
) -> Response:
    """Recover the inverse response from brackets (J exposures of a scene, pooled over
    the shifts: (J, N, C) samples in [0, 1]) with OpenCV's Debevec calibration (module
    docstring); times in seconds."""
    import cv2

    j, _, n_channels = brackets.shape
    times32 = np.asarray(times, np.float32)
    codes = np.arange(256) / 255.0
    curve = np.empty((256, n_channels))
    calibrate = cv2.createCalibrateDebevec(_CALIBRATION_PIXELS, _SMOOTHNESS, False)
    side = int(math.isqrt(_CALIBRATION_PIXELS))
    for c in range(n_channels):
        z8 = np.rint(np.clip(brackets[..., c], 0.0, 1.0) * 255.0).astype(np.uint8)
        pick = _calibration_pixels(z8 / 255.0, clip)
        grid = np.resize(pick, side * side)  # the grid OpenCV samples, every cell a pick
        images = [np.repeat(z8[i, grid].reshape(side, side, 1), 3, axis=2) for i in range(j)]
        g = np.asarray(calibrate.process(images, times32), np.float64)[:, 0, 0]
        g = np.maximum.accumulate(g)  # a response never decreases
        g[0] = 0.0
        curve[:, c] = g / g[128]
    return Response("auto", codes, curve)


def frame_linearizer(top, response, frames, names, top_code: float = 1.0):
    """Integer codes to linear values by a single exposure's ``response`` (after dividing
    by ``top_code``, the sensor's top code of 10-14-bit data in 16-bit files); ``None``
    for a linear one. Float images hold linear values: a curve is refused for them."""
    if response is None or response.kind == "linear":
        return None
    floating = [i for i, f in enumerate(frames) if not f.is_integer]
    if floating:
        i = floating[0]
        top.fail(
            "response",
            f"{top.get('response')} maps a camera's integer codes (8- or 16-bit files), "
            f"but images[{i}] ({names[i]}) holds float values, which are linear: give "
            "response: linear",
        )
    n_channels = frames[0].pixels.shape[-1]
    dtype = np.float32

    def linear(a: np.ndarray) -> np.ndarray:
        a = np.broadcast_to(a, (*a.shape[:-1], n_channels))
        if a.ndim < 4:
            return response.linearize(a / top_code).astype(dtype, copy=False)
        out = np.empty(a.shape, dtype)
        for i, image in enumerate(a):  # one image at a time: float64 temporaries stay small
            out[i] = response.linearize(image / top_code)
        return out

    return linear


__all__ = [
    "frame_linearizer",
    "AUTO_CLIP",
    "CLIP",
    "MAX_QUANTISATION",
    "NEAR_BLACK",
    "RESPONSES",
    "Response",
    "calibrate_response",
    "linear_response",
    "load_response",
    "srgb_response",
    "write_response",
]
