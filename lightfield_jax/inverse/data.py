"""What a fit works on, as frozen records: the prepared capture (:class:`FitData`), the
problem a fit method is handed (:class:`FitProblem`) and what it hands back
(:class:`FitSolution`).

:func:`prepare_data` validates one channel's images, masks them, separates direct and
multiple scattering (docs/model.md §5) and fits σt to the decay of the direct image;
:meth:`FitData.cropped` gives the same data inside the model's crop, every image cut
alike (never in place).
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import TYPE_CHECKING

import jax.numpy as jnp
import numpy as np

from lightfield_jax.capture.auto import pattern_contradiction
from lightfield_jax.capture.stripe_phase import across_first as _across_first
from lightfield_jax.capture.stripe_phase import period_contradiction
from lightfield_jax.checks import (
    as_array,
    check_float_range,
    number_problem,
    shown,
    unmask,
    unmasked,
)
from lightfield_jax.inverse.decay import fit_decay
from lightfield_jax.inverse.noise import MIN_ALONG, noise_floor
from lightfield_jax.inverse.separate import real_dtype, separate
from lightfield_jax.scene.illumination import Stripes, period_problem, shifts_problem

if TYPE_CHECKING:
    from lightfield_jax.inverse.model_size import ModelSpec


@dataclasses.dataclass(frozen=True)
class FitData:
    """One channel of a stripe capture, ready to fit.

    Attributes:
        images: the shifted images I_p, ``(P, h, w)``, dark-subtracted, 0 where masked.
        mask: ``(h, w)``, true where a pixel is valid in every shift (the separation,
            the decay and the two-step methods use these pixels only).
        samples: ``(P, h, w)``, true where one shift's value is valid (finite, below
            the saturation): the joint fit uses every valid sample, also of a pixel
            clipped in some shifts (``None``: ``mask`` in every shift).
        clipped: ``(P, h, w)``, true where a value was masked as saturated or clipped
            (censored from above: the joint fit also masks the values its answer puts
            within the noise of the clip), or ``None``.
        clip_level: ``(P, h, w)``, the value at which the clip sits there: the
            ``saturation`` given, or else a pixel's clipped value itself (after the dark
            frame and the flat field: one level per pixel) and the median clipped value
            for pixels never clipped; ``None`` where nothing was clipped.
        floor_level: ``(P, h, w)``, the same for values clamped at a floor (censored
            from below: :func:`floor_pileup`), or ``None`` where none was.
        direct: the separated direct image D, ``(h, w)`` (or the given split's).
        multiple: the separated multiple-scattering image M, ``(h, w)``.
        sigma_t0: σt (per pixel) from the decay of D, and ``sigma_t0_err`` its 1σ.
        decay_converged: whether that decay fit converged.
        exposure: merged exposure brackets' effective exposure T (s), ``(P, h, w)``,
            or ``None``.
        noise_floor: the read-noise floor of the joint fit's weights, in image units
            (:func:`~lightfield_jax.inverse.noise.noise_floor`; ``None``: the
            shot-noise weights' own, 1e-3 of the peak).
    """

    images: np.ndarray
    mask: np.ndarray
    direct: np.ndarray
    multiple: np.ndarray
    sigma_t0: float
    sigma_t0_err: float
    decay_converged: bool
    exposure: np.ndarray | None = None
    noise_floor: float | None = None
    samples: np.ndarray | None = None
    clipped: np.ndarray | None = None
    clip_level: np.ndarray | None = None
    floor_level: np.ndarray | None = None

    @property
    def valid(self) -> np.ndarray:
        """``(P, h, w)``: the samples the joint fit uses."""
        if self.samples is not None:
            return self.samples
        return np.broadcast_to(self.mask[None], self.images.shape)

    def cropped(self, crop: tuple[int, int, int, int]) -> FitData:
        """The data inside ``crop`` = (x0, y0, x1, y1), every image cut alike."""
        x0, y0, x1, y1 = crop
        return dataclasses.replace(
            self,
            images=self.images[:, y0:y1, x0:x1],
            mask=self.mask[y0:y1, x0:x1],
            direct=self.direct[y0:y1, x0:x1],
            multiple=self.multiple[y0:y1, x0:x1],
            exposure=None if self.exposure is None else self.exposure[:, y0:y1, x0:x1],
            samples=None if self.samples is None else self.samples[:, y0:y1, x0:x1],
            clipped=None if self.clipped is None else self.clipped[:, y0:y1, x0:x1],
            clip_level=None if self.clip_level is None else self.clip_level[:, y0:y1, x0:x1],
            floor_level=None if self.floor_level is None else self.floor_level[:, y0:y1, x0:x1],
        )

    @property
    def multiple_ratio(self) -> float:
        """Σ M / Σ D over the mask: ≈ Σ_{k≥2} I_k / I_1 ≈ ρ/(1 − ρ)."""
        m = np.sum(np.where(self.mask, self.multiple, 0.0))
        return float(m / max(np.sum(np.where(self.mask, self.direct, 0.0)), 1e-30))


# The images' scale the fit's float32 arithmetic holds (their 99th percentile of |value|):
# the fit is scale-free in between (1e-20 and 1e12 times the paper's milk measured the
# same to 4 digits), but at 1e-30 times it its noise variances underflowed and the
# fit ended "converged" with g 0.30 ± 0.003 for 0.40, and at 1e38 times it overflowed.
SCALE_RANGE = (1e-15, 1e15)


def _check_scale(values: np.ndarray) -> None:
    """Refuse images whose scale lies outside :data:`SCALE_RANGE` (ValueError)."""
    finite = np.abs(values[np.isfinite(values)]).astype(np.float64)
    level = float(np.percentile(finite, 99)) if finite.size else 0.0
    low, high = SCALE_RANGE
    if level > 0 and not low <= level <= high:
        raise ValueError(
            f"images: their values' 99th percentile is {level:.3g}, outside [{low:g}, "
            f"{high:g}], where the fit's float32 arithmetic holds (its noise variances "
            "underflow or overflow): scale them by a constant (the fit does not depend on "
            "the images' scale)"
        )


def prepare_data(
    images,
    pattern: Stripes,
    *,
    mask=None,
    black_level: float | None = None,
    saturation: float | None = None,
    split=None,
    exposure=None,
    clipped=None,
    floored=None,
) -> FitData:
    """One channel's :class:`FitData` over the whole image (see :func:`fit_images` for
    the arguments). Raises ``ValueError`` for images of the wrong shape, a ``split`` of
    another shape, or a decay that gives no usable σt. ``clipped``: values (like
    ``images``) a capture masked as saturated, besides those at ``saturation``;
    ``floored``: values a capture found clamped at a floor (``None``: found here, by
    :func:`floor_pileup`). Numpy masked arrays for ``images``, ``exposure`` or the
    ``split``'s images are honoured: a masked value is not used (a masked exposure T
    excludes that value, a masked direct or multiple value that pixel in every shift),
    whatever its fill value."""
    if not isinstance(pattern, Stripes):
        raise ValueError(f"pattern: must be a Stripes, got {type(pattern).__name__}")
    images, mask = unmask(images, mask)
    what = f"an array ({pattern.n_patterns}, height, width) of real numbers"
    given = as_array(images, "images", what, items="images of ")
    if not real_dtype(given.dtype):  # bool, complex, strings, objects: not intensities
        raise ValueError(f"images: must be real numbers, got dtype {given.dtype}")
    # Converted to JAX's float: 1e300 would become inf and 1e-300 zero, then refused as
    # "non-finite" or "not above 0" for what is only a scale.
    check_float_range(given, "images")
    images = given.astype(jnp.result_type(float))
    if images.ndim != 3 or images.shape[0] != pattern.n_patterns or min(images.shape[1:]) < 2:
        raise ValueError(
            f"images: expected ({pattern.n_patterns}, height, width) for {pattern.n_patterns} "
            f"phases (height and width >= 2), got shape {images.shape}"
        )
    along_x = pattern.along_x
    along = images.shape[2] if along_x else images.shape[1]
    if along < MIN_ALONG:
        raise ValueError(
            f"images: the medium is {images.shape[2]}x{images.shape[1]} px: a fit needs at "
            f"least {MIN_ALONG} px along the light ({'x' if along_x else 'y'}: the direct "
            f"light's decay and the noise's 4th differences)"
        )
    period = period_problem(pattern, images.shape[2], images.shape[1], "images")
    if period is not None:  # as render refuses them (else: a fit of no stripes)
        raise ValueError(f"pattern.period: {period}")
    finite = np.isfinite(images)
    if mask is not None and np.shape(mask) not in (images.shape, images.shape[1:]):
        raise ValueError(
            f"mask: must have the images' (height, width) {images.shape[1:]} (a pixel valid "
            f"in every shift) or their shape {images.shape} (per sample), got {np.shape(mask)}"
        )
    if exposure is not None:
        t, unknown = unmasked(exposure, "exposure")
        if t.dtype.kind not in "iuf" or t.shape != images.shape:
            raise ValueError(
                f"exposure: must be real numbers of the images' shape {images.shape}, got "
                f"{t.dtype} of shape {t.shape}"
            )
        if unknown.any():  # masked: not used (the largest known T: weights ∝ √(T/max T))
            known = t[~unknown & np.isfinite(t)]
            exposure = np.where(unknown, known.max() if known.size else 1, t)
        else:
            exposure = t
        if not np.all(np.isfinite(exposure) & (exposure > 0)):
            raise ValueError(
                "exposure: must be finite and > 0 (seconds) everywhere"
                + (" it is not masked" if unknown.any() else "")
            )
        mask = _excluding(mask, unknown)
    if split is not None:
        direct, multiple, unknown = _split_images(split, images.shape[1:], images.dtype)
        mask = _excluding(mask, unknown)
    if saturation is not None:  # 10**400 is numpy's "ufunc 'isfinite' not supported"
        if number_problem(saturation, low=0.0, low_open=True) is not None:
            raise ValueError(f"saturation: must be a positive number, got {shown(saturation)}")
        saturation = float(saturation)
    samples, censored, floored = valid_values(images, pattern, mask, saturation, clipped, floored)
    top = censored & ~floored & finite
    level = _clip_level(images, top, saturation)
    floor_level = _clip_level(images, floored & finite, None, low=True)
    pixels = np.all(samples, axis=0)  # valid in every shift
    if not pixels.any():
        causes = [f"{int((~finite).sum())} non-finite"]
        if mask is not None:
            masked = ~np.broadcast_to(np.asarray(mask, bool), finite.shape)
            causes.append(f"{int(masked.sum())} by mask")
        if (censored & ~floored).any():
            causes.append(f"{int((censored & ~floored).sum())} at or above saturation (clipped)")
        if floored.any():
            causes.append(f"{int(floored.sum())} clamped at the floor {images[floored].min():g}")
        raise ValueError(
            f"images: no pixel is valid in every one of the {images.shape[0]} shifts (values "
            f"masked: {', '.join(causes)} of {images.size}): the separation and the decay "
            "fit need pixels valid in every shift"
        )
    _check_scale(images[samples])
    brightest = float(images[samples].max())
    if not brightest > 0:  # else the scan says "no valid model", not why
        raise ValueError(
            f"images: no value is above 0 (the largest is {brightest:.3g}): images of light "
            "are not negative (values must be linear, black at 0)"
        )
    if split is None:
        # Fewer than 2: named as such, not as "the 1 shifts are the same image". A simulate
        # config is refused by the same rule (forward.simulate_config): simulate writes no
        # capture that is refused here.
        n_shifts = images.shape[0]
        same = n_shifts >= 2 and bool(np.all(images[:, pixels] == images[:1, pixels]))
        if (problem := shifts_problem(n_shifts, same)) is not None:
            if n_shifts < 2:
                raise ValueError(f"pattern.phases: {problem}")
            raise ValueError(f"images: {problem} (one image given for every shift?)")
    images = np.where(samples, images, 0.0)
    across = _across_first(images, pattern.entry)  # else: a long fit that does not converge
    if (problem := period_contradiction(across, 0, pattern.period, pattern.entry)) is not None:
        raise ValueError(f"pattern.period: {problem}")
    if (problem := pattern_contradiction(images, pattern, samples)) is not None:
        raise ValueError(f"{problem[0]}: {problem[1]}")  # else a wrong answer
    if split is None:
        sep = separate(
            jnp.asarray(images),
            lit_fraction=pattern.lit_fraction,
            black_level=0.0 if black_level is None else float(black_level),
        )
        direct, multiple = np.asarray(sep.direct), np.asarray(sep.multiple)
    _check_entry(direct, pixels, pattern)
    decay = fit_decay(
        direct,
        direction_deg=pattern.direction_deg,
        entry=pattern.entry,
        mask=jnp.asarray(pixels),
        saturation=saturation,
    )
    sigma_t0 = float(decay.sigma_t)
    if not np.isfinite(sigma_t0) or sigma_t0 <= 0:
        raise ValueError(f"the direct image's decay gives no usable sigma_t ({sigma_t0!r})")
    return FitData(
        images=images,
        mask=pixels,
        direct=direct,
        multiple=multiple,
        sigma_t0=sigma_t0,
        sigma_t0_err=float(decay.sigma_t_stderr),
        decay_converged=bool(decay.converged),
        exposure=exposure,
        samples=None
        if np.array_equal(samples, np.broadcast_to(pixels, samples.shape))
        else samples,
        clipped=censored if censored.any() else None,
        clip_level=level,
        floor_level=floor_level,
    )


def _excluding(mask, unknown: np.ndarray):
    """``mask`` (``None``, per pixel or per value) with the values ``unknown`` (per pixel
    or per value) excluded; ``mask`` itself where nothing is."""
    if not unknown.any():
        return mask
    keep = ~unknown
    return keep if mask is None else np.asarray(mask, bool) & keep


def _split_images(split, shape: tuple[int, int], dtype) -> tuple[np.ndarray, ...]:
    """A ``split=(direct, multiple)`` as ``(direct, multiple, unknown)``: the images, 0
    where masked, and the pixels either one masks (numpy masked arrays)."""
    try:
        direct, multiple = split
    except (TypeError, ValueError):
        got = type(split).__name__
        if hasattr(split, "__len__"):
            got += f" of {len(split)} item(s)"
        raise ValueError(
            f"split: must be a pair (direct, multiple) of images of shape {shape}, got {got}"
        ) from None
    (direct, d_unknown), (multiple, m_unknown) = (
        unmasked(direct, "split: direct"),
        unmasked(multiple, "split: multiple"),
    )
    if direct.shape != shape or multiple.shape != shape:
        raise ValueError(
            f"split: direct and multiple must have the images' shape {shape}, "
            f"got {direct.shape} and {multiple.shape}"
        )
    unknown = d_unknown | m_unknown
    for name, a in (("direct", direct), ("multiple", multiple)):
        # Refused here: otherwise complex values are cast to real (a warning, a fit),
        # strings end in numpy's DTypePromotionError, NaN in "fit_decay: ... 0 usable
        # pixels".
        if a.dtype.kind not in "iuf":
            raise ValueError(f"split: {name}: must be real numbers, got dtype {a.dtype}")
        bad = ~np.isfinite(a) & ~unknown
        if bad.any():
            raise ValueError(
                f"split: {name}: must be finite where not masked, got {int(bad.sum())} of "
                f"{a.size} values NaN or inf"
            )
    direct, multiple = (np.where(unknown, 0.0, a).astype(dtype) for a in (direct, multiple))
    return direct, multiple, unknown


# The direct light decays from the entry wall: where the third of the medium farthest
# from the given wall holds more than ENTRY_GROWTH times the direct light of the third
# nearest it, the light entered through another wall.
ENTRY_GROWTH = 2.0


def _check_entry(direct: np.ndarray, pixels: np.ndarray, pattern: Stripes) -> None:
    """Refuse a ``pattern.entry`` the direct image grows away from (a wrong wall: the
    fit would run for minutes on light it cannot model)."""
    d = np.where(pixels, direct, np.nan)
    profile = d if pattern.along_x else d.T  # (across, along)
    if pattern.entry in ("right", "bottom"):
        profile = profile[:, ::-1]
    third = max(profile.shape[1] // 3, 1)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-masked third: no test
        near = np.nanmean(profile[:, :third])
        far = np.nanmean(profile[:, -third:])
    if np.isfinite(near) and np.isfinite(far) and far > ENTRY_GROWTH * max(near, 0.0):
        raise ValueError(
            f"pattern.entry: the direct light grows away from the {pattern.entry} wall "
            f"(mean {near:.3g} in the third of the medium nearest it, {far:.3g} in the "
            "farthest): the light enters through another wall"
        )


def valid_values(
    images: np.ndarray,
    pattern: Stripes,
    mask=None,
    saturation=None,
    clipped=None,
    floored=None,
):
    """``(valid, censored, floored)``, like ``images``: the values a fit may use (finite,
    inside ``mask``, per pixel or per value, and not censored), the censored ones
    (flagged ``clipped``, at or above ``saturation``, or clamped at a floor) and those
    clamped at a floor: ``floored`` as a capture found them, or (``None``) found here by
    :func:`floor_pileup` where an additive noise could have taken them below it
    (:func:`floor_is_cut`)."""
    valid = np.isfinite(images)
    if mask is not None:
        valid &= np.asarray(mask, bool)  # (h, w) broadcasts over the shifts
    censored = np.zeros(images.shape, bool) if clipped is None else np.asarray(clipped, bool)
    if saturation is not None:
        with np.errstate(invalid="ignore"):
            censored = censored | (images >= saturation)
    usable = valid & ~censored
    if floored is None:
        floored = floor_pileup(images, usable)
        if floored.any() and not floor_is_cut(images, usable & ~floored, usable, pattern):
            floored = np.zeros(images.shape, bool)
    floored = np.asarray(floored, bool) & usable
    censored = censored | floored
    return valid & ~censored, censored, floored


def floor_is_cut(images, above: np.ndarray, usable: np.ndarray, pattern: Stripes) -> bool:
    """Whether values at a floor were cut there: the capture shows an additive noise that
    could take values below it, as values above the floor that vary continuously (its
    200 lowest nearly all distinct) or as read noise (:func:`~lightfield_jax.inverse.
    noise.noise_floor`). Counts of shot noise alone (a lattice of values) cannot fall
    below 0: their zeros are measured, not cut."""
    lowest = np.sort(images[above])[:200]
    if lowest.size >= 20 and np.unique(lowest).size > 0.9 * lowest.size:
        # Continuous, and spread like a noise above the floor (over a few of its σ,
        # linearly), not over decades like a noiseless render's decay, nor within
        # float underflow (a render's zeros flushed from 1e-38: the same light).
        low, high = np.percentile(lowest - lowest[0], [10, 90])
        peak = float(np.max(images[usable]))
        if 1e-9 * peak <= high <= 100 * max(low, np.finfo(np.float64).tiny):
            return True
    return noise_floor(images, np.all(usable, axis=0), pattern) is not None


# Values clamped at a floor: a 16-bit file, or a camera's black subtraction, cut the
# read noise of dark values at 0, which keeps the values its noise pushed up and sets
# the others to the floor (censored from below: the same bias as a clip's, upward). Found
# as a pile-up: at least FLOOR_MIN and FLOOR_SHARE of the finite values equal their
# lowest exactly, more than equal the next value up (the tail of a quantised noise has
# fewer at its lowest code), and that lowest is dark (at most FLOOR_DARK of the largest).
FLOOR_MIN = 16
FLOOR_SHARE = 0.01
FLOOR_DARK = 0.02


def floor_pileup(values: np.ndarray, among: np.ndarray | None = None) -> np.ndarray:
    """True where a value of ``values`` sits at a floor it was clamped at (see above),
    judged among the finite values where ``among`` is true (all where ``None``)."""
    values = np.asarray(values)
    use = np.isfinite(values) if among is None else np.isfinite(values) & among
    finite = values[use]
    none = np.zeros(values.shape, bool)
    if finite.size == 0:
        return none
    low, high = float(finite.min()), float(finite.max())
    at = use & (values == low)
    n = int(at.sum())
    if n < max(FLOOR_MIN, FLOOR_SHARE * finite.size) or not low <= FLOOR_DARK * high:
        return none  # too few, or no light above the floor (high <= 0: a dark channel)
    if not high > low:
        return none
    above = finite[finite > low]
    if above.size and int(np.sum(above == above.min())) >= n:
        return none
    return at


def _clip_level(
    images: np.ndarray, clipped: np.ndarray, saturation, low: bool = False
) -> np.ndarray | None:
    """:attr:`FitData.clip_level` of ``images`` whose ``clipped`` values the clip took
    (``low``: :attr:`FitData.floor_level` of those clamped at a floor)."""
    if not clipped.any():
        return None
    if saturation is not None:
        return np.full(images.shape, float(saturation))
    values = np.where(clipped, images, np.inf if low else -np.inf)
    # a pixel's clipped value (its shifts share its level)
    own = np.min(values, axis=0) if low else np.max(values, axis=0)
    typical = float(np.median(images[clipped]))
    return np.broadcast_to(np.where(np.isfinite(own), own, typical), images.shape).copy()


@dataclasses.dataclass(frozen=True)
class FitProblem:
    """What a fit method solves (:meth:`~lightfield_jax.inverse.method_base.FitMethod.solve`).

    Attributes:
        data: the capture inside ``model``'s crop.
        images: the whole masked images (a method that resizes its model crops anew).
        pattern: the stripes that lit them.
        black_level: the projector's dark-stripe level, or ``None`` (unknown).
        model: the first model, sized at the separation's ρ estimate ``rho0`` and g = 0.
        rho0: that estimate, with its margin.
        floor: the smallest model to use (the channels of a capture share programs),
            or ``None``.
    """

    data: FitData
    images: np.ndarray
    pattern: Stripes
    black_level: float | None
    model: ModelSpec
    rho0: float
    floor: ModelSpec | None = None


@dataclasses.dataclass(frozen=True)
class FitSolution:
    """What a fit method found: the model it ended on, the seconds spent compiling and
    running its programs, and the values the result is built from (σt, σs, g, gain,
    black level, error budget, convergence and its message, iterations, residual)."""

    model: ModelSpec
    seconds: dict
    values: dict


__all__ = ["FitData", "FitProblem", "FitSolution", "prepare_data", "valid_values"]
