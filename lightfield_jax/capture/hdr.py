"""Exposure brackets to linear radiance: the camera's response and the HDR merge.

The light in a tank spans three to four decades (the direct light at the entry wall to
the multiple-scattered tail), more than one 8- or 16-bit exposure holds. A capture may
therefore give each shift (and each calibration frame) as a bracket of exposures with
times t_j (seconds); :func:`merge_bracket` turns a bracket into one linear image.

The camera's response is :mod:`lightfield_jax.capture.response`; the checks of a
bracket before its merge are :mod:`lightfield_jax.capture.exposure_checks`.

OpenCV's ``mergeDebevec``/``mergeRobertson`` weight samples by a hat
function of the code and take 8-bit input; neither drops a sample by how much light
it holds nor returns the merged noise. The merge here is the maximum-likelihood
estimate under shot noise, where x_j is Poisson in E·t_j: over the samples that are
valid (neither clipped nor near black),

    E = Σ_j (x_j − d_j) / Σ_j t_j,    Var E ∝ E / T,   T = Σ_j t_j (the effective exposure),

with d_j the dark frame's sample at the same exposure (a camera's black pedestal does
not scale with t, so it is subtracted before merging, never after). A sample is
**clipped** when z ≥ ``clip`` (default 0.98: sensors knee below their top code). Every
pixel merges its longest unclipped exposure (none: its shortest, flagged ``clipped``;
the capture masks it), and each shorter unclipped one unless it is **near black**:
judged on the signal that longest exposure predicts for it, s_j = (x_J − d_J)·t_j/t_J,
never on the sample itself (keeping the dim samples that read noise happened to lift
would bias a tank's far end and its black surround up, measured 17-1500× on a 16-bit
bracket): one code exceeds 5 % of that signal, f⁻¹(z + Δz) − f⁻¹(z) > 0.05·s_j at its
code z = f(s_j + d_j) (without a dark frame, for 8-bit γ 2.2 that is z < 0.17), or z <
0.005 (read noise). A pixel whose longest unclipped exposure is itself near black is
merged from that one sample (it is dark: the best there is). T goes to the joint fit's
weights (w ∝ √(T / (E + floor)) instead of 1/√(E + floor)).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lightfield_jax.capture.response import (
    AUTO_CLIP,
    CLIP,
    MAX_QUANTISATION,
    NEAR_BLACK,
    Response,
)


@dataclasses.dataclass(frozen=True, eq=False)
class Merged:
    """One merged bracket (module docstring).

    Attributes:
        radiance: E (H, W, C), linear, in response units per second.
        exposure: T = Σ t_j over the valid samples (H, W, C), seconds (the longest
            unclipped exposure's time where no sample is valid).
        clipped: (H, W, C) True where every exposure is clipped.
        dark: (H, W, C) True where no sample is valid and E comes from one dark sample.
        clipped_samples, near_black_samples: (J, H, W, C) True where a sample was
            dropped as clipped, or as near black (and not clipped).
    """

    radiance: np.ndarray
    exposure: np.ndarray
    clipped: np.ndarray
    dark: np.ndarray
    clipped_samples: np.ndarray
    near_black_samples: np.ndarray


def merge_bracket(
    samples: np.ndarray,
    times: Sequence[float],
    response: Response,
    *,
    levels: int | None,
    dark: np.ndarray | None = None,
    clip: float = CLIP,
) -> Merged:
    """Merge a bracket (J, H, W, C) of samples in [0, 1], exposure times in seconds,
    into linear radiance (module docstring). ``dark``: the dark frame's bracket at the
    same times, (J, H, W, C) or (J, H, W, 1); ``levels``: the samples' code count
    (256, 65536) or ``None`` for float samples."""
    z = np.asarray(samples, np.float64)
    if response.kind == "auto":
        clip = min(clip, AUTO_CLIP)
    t = np.asarray(times, np.float64).reshape(-1, 1, 1, 1)
    # A NaN or Inf sample (or dark value) is no sample: read as 0, it would become the
    # pixel's reference where the longer exposures clipped, and the merge near 0.
    finite = np.isfinite(z)
    z = np.where(finite, z, 0.0)
    x = response.linearize(z)
    d = np.zeros_like(x)
    if dark is not None:
        dz = np.broadcast_to(np.asarray(dark, np.float64), z.shape)
        dark_finite = np.isfinite(dz)
        finite = finite & dark_finite
        d = response.linearize(np.where(dark_finite, dz, 0.0))
        x = x - d
    clipped = ~(z < clip) & finite
    unclipped = (z < clip) & finite
    # The reference of each pixel: its longest unclipped exposure (none: the shortest,
    # flagged clipped). It is always merged; the light it measured predicts each other
    # sample's signal, and a sample joins where that prediction resolves it.
    by_time = np.broadcast_to(t, z.shape)
    ref = np.argmax(np.where(unclipped, by_time, -np.inf), axis=0)
    none_ok = ~unclipped.any(axis=0)
    ref = np.where(none_ok, np.argmin(t[:, 0, 0, 0]), ref)
    ref_x = np.take_along_axis(x, ref[None], axis=0)[0]
    ref_t = t[:, 0, 0, 0][ref]
    # Near black, judged on the prediction (the sample's own value would select on its
    # noise: keeping only the dim samples that noise lifted biases the merge up): one
    # code more than 5 % of the predicted signal left after the dark frame, or a
    # predicted code below the read-noise floor.
    predicted = np.maximum(ref_x, 0.0)[None] * (t / ref_t[None])
    z_pred = response.encode(predicted + d)
    black = unclipped & (
        (z_pred < NEAR_BLACK) | ~(response.step(z_pred, levels) <= MAX_QUANTISATION * predicted)
    )
    is_ref = np.arange(len(t)).reshape(-1, 1, 1, 1) == ref[None]
    valid = (unclipped & ~black) | (is_ref & unclipped)
    total = np.sum(np.where(valid, t, 0.0), axis=0)
    merged = np.sum(np.where(valid, x, 0.0), axis=0)
    empty = total == 0  # every exposure clipped: the shortest one's value
    radiance = np.where(empty, ref_x / ref_t, merged / np.where(empty, 1.0, total))
    radiance = np.where(finite.any(axis=0), radiance, np.nan)  # no sample: masked as NaN
    ref_black = np.take_along_axis(black, ref[None], axis=0)[0]
    return Merged(
        radiance=radiance,
        exposure=np.where(empty, ref_t, total),
        clipped=none_ok & finite.any(axis=0),
        dark=ref_black & (total == ref_t) & ~none_ok,
        clipped_samples=clipped,
        near_black_samples=black,
    )


@dataclasses.dataclass(frozen=True, eq=False)
class Brackets:
    """What merging a capture's exposure brackets did (``Capture.brackets``).

    Attributes:
        times: the exposure times t_j (seconds), shortest first as given.
        response: the inverse response used.
        clip: the sample value at or above which a sample counted as clipped.
        near_black: per channel, the value below which a sample counted as near black
            without a dark frame (with one: where one code exceeds 5 % of the signal).
        exposure: T (P, H, W, C) of every merged shift (seconds), whole frame.
        clipped: (H, W, C) True where every exposure of some shift is clipped.
        clipped_shifts: (P, H, W, C) the same per shift.
        clipped_fraction, near_black_fraction: (J, H, W): per exposure, the fraction of a
            pixel's samples (over shifts and channels) that were dropped as clipped or
            near black.
        dark_pixels: pixel values (shifts × pixels × channels) merged from one dark sample.
        files: the image files, one list per shift.
        dark_frame: whether a dark frame was subtracted (near black is then judged
            against the signal, not ``near_black``).
    """

    times: tuple[float, ...]
    response: Response
    clip: float
    near_black: tuple[float, ...]
    exposure: np.ndarray
    clipped: np.ndarray
    clipped_shifts: np.ndarray
    clipped_fraction: np.ndarray
    near_black_fraction: np.ndarray
    dark_pixels: int
    files: tuple[tuple[Path, ...], ...]
    dark_frame: bool = False

    def summary(self) -> str:
        j = len(self.times)
        threshold = (
            ""
            if self.dark_frame
            else f"; without a dark frame z < {', '.join(f'{v:.3g}' for v in self.near_black)}"
        )
        clipped = ", ".join(
            f"{t * 1e3:g} ms {100 * float(c.mean()):.1f}%/{100 * float(b.mean()):.1f}%"
            for t, c, b in zip(
                self.times, self.clipped_fraction, self.near_black_fraction, strict=True
            )
        )
        return (
            f"HDR: {len(self.files)} brackets of {j} exposures merged, "
            f"{self.response.kind} response; samples dropped as clipped (>= {self.clip:g}) / "
            "near black (one code over 5 % of the signal the longest unclipped exposure "
            f"predicts{threshold}), of the whole frame's samples (pixels outside the medium "
            f"are near black at every exposure): {clipped}; "
            f"{int(self.clipped_shifts.sum())} value(s) clipped in every exposure (masked; "
            f"{int(self.clipped.sum())} pixel(s)), "
            f"{self.dark_pixels} merged from one dark sample"
        )

    def to_dict(self) -> dict:
        return {
            "exposure_times": list(self.times),
            "response": self.response.to_dict(),
            "clip": self.clip,
            "near_black": list(self.near_black),
            "clipped_fraction": [float(c.mean()) for c in self.clipped_fraction],
            "near_black_fraction": [float(b.mean()) for b in self.near_black_fraction],
            "clipped_pixels": int(self.clipped.sum()),
            "clipped_values": int(self.clipped_shifts.sum()),
            "dark_pixels": self.dark_pixels,
            "dark_frame": self.dark_frame,
        }


def merge_capture(
    images: np.ndarray,
    times: Sequence[float],
    response: Response,
    *,
    levels: int | None,
    dark: np.ndarray | None = None,
    clip: float = CLIP,
    files: Sequence[Sequence[Path]] = (),
) -> tuple[np.ndarray, Brackets]:
    """Merge every shift's bracket: ``images`` (P, J, H, W, C) in [0, 1] → radiance
    (P, H, W, C) and the :class:`Brackets` record; ``dark`` (J, H, W, C or 1)."""
    merged = [
        merge_bracket(b, times, response, levels=levels, dark=dark, clip=clip) for b in images
    ]
    record = Brackets(
        times=tuple(float(t) for t in times),
        response=response,
        clip=min(clip, AUTO_CLIP) if response.kind == "auto" else clip,
        near_black=tuple(float(v) for v in response.near_black(levels)),
        exposure=np.stack([m.exposure for m in merged]).astype(np.float32),
        clipped=np.any([m.clipped for m in merged], axis=0),
        clipped_shifts=np.stack([m.clipped for m in merged]),
        clipped_fraction=np.mean([m.clipped_samples for m in merged], axis=(0, 4)),
        near_black_fraction=np.mean([m.near_black_samples for m in merged], axis=(0, 4)),
        dark_pixels=int(sum(m.dark.sum() for m in merged)),
        files=tuple(tuple(row) for row in files),
        dark_frame=dark is not None,
    )
    return np.stack([m.radiance for m in merged]), record


__all__ = [
    "Brackets",
    "Merged",
    "merge_bracket",
    "merge_capture",
]
