"""How much a fit can be trusted: noise, χ²/dof, the model's own error, and a verdict.

- The capture's noise is measured from the images without a model: the fourth
  difference along the light's direction removes the smooth decay and leaves white
  noise of variance 70 σ² (as in :mod:`lightfield_jax.inverse.model_choice`). Divided by the
  fit's shot-noise scale √(I + floor), its mean square is the variance α of one
  weighted residual that noise alone would give.
- χ²/dof = ‖r‖²/(n − p)/α: about 1 when the model explains the capture to its noise.
  A misfit is "far above the noise" when it is far above the noise and the model's
  own discretisation error together: χ²/dof against α + ‖r_fine − r‖²/(n − p) (a
  noiseless synthetic capture is fitted to its model's precision, not to zero).
- Statistical 1σ: α·max(1, χ²/dof)·(JᵀJ)⁻¹ (the noise, scaled up where the residual
  says it is larger: Birge's rule).
- Model error: at the solution, the shift a finer model's residual implies,
  δp = −J⁺·(r_fine − r) (one render with a finer grid, more direction bins and more
  bounces; no refit). Where the finer grid is finer in space the error is first order
  in the cell size, so the continuum lies κ·δp away (κ = r_f/(r_f − r)): the answer
  takes that step and the model term is |δp|.
- Consistency between parts of the capture (:func:`split_groups`): the capture is cut
  in two, by the distance from the entry wall (near half, far half) and by the stripes
  (lit rows, dark rows), and each part's own least-squares answer is taken from the
  whole fit's J and r (linearised: δp_A = −(J_AᵀJ_A)⁻¹J_Aᵀr_A; no refit). Where the
  model explains the capture the two answers differ by their noise alone,
  (δp_A − δp_B)ᵀ(C_A + C_B)⁻¹(δp_A − δp_B) ~ χ²₃ over σt, σs, g. Where that is
  significant (p < ``CONSISTENCY_P``) the model misses something the data see (a finer
  discretisation of the same model cannot show it), and the larger shift of either
  part from the whole answer is an error of the model: the model term is the larger
  of this and the finer model's shift. Total = statistical ⊕ model;
  ``model_limited`` when the model term is the larger for σt, σs or g.
- Not trustworthy (``converged: false`` with the reason, never converged): a solution
  at a parameter bound, a misfit far above the noise, one in a basin worse than
  another the scan found, or one whose model summed its bounce series' tail with a
  solve that stopped before its tolerance (the model there is not the series).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from lightfield_jax.scene.illumination import Stripes

# A solution this close to a constraint's edge is at a bound: |g| ≥ G_BOUND, albedo
# below ALBEDO_BOUNDS[0] or above [1], the black level within 0.01 of its range.
G_BOUND = 0.95
ALBEDO_BOUNDS = (0.005, 0.9995)
# A split of the capture whose two parts disagree beyond this chance (their noise
# alone) shows a model error.
CONSISTENCY_P = 1e-3
# The fewest pixels along the light the noise's 4th differences are measured over (a
# fit needs them: inverse/data.py).
MIN_ALONG = 8
_PHYSICAL = ("sigma_t", "sigma_s", "g")


def split_groups(shape: tuple[int, int, int], pattern: Stripes) -> dict[str, np.ndarray]:
    """Two ways to cut a (P, h, w) capture's residuals in two (0/1 per residual, in
    the residual's order): ``near/far`` by the distance from the entry wall (the half
    nearer the wall is 0), ``lit/dark`` by the stripes (pixel rows, or columns for the
    top and bottom walls, whose wall cell is lit in that image: 0). Each cut depends on
    the geometry alone, never on the data, so under a right model the two parts' answers
    differ by their noise alone."""
    n_img, h, w = shape
    across_rows = pattern.along_x
    extent = w if across_rows else h
    along = np.arange(extent)
    if pattern.entry in ("left", "top"):
        near = along < extent // 2
    else:
        near = along >= extent - extent // 2
    cell = np.arange(h if across_rows else w)
    phases = np.asarray(pattern.phases)[:, None]
    lit = (cell[None, :] + phases) % pattern.period < pattern.lit  # (P, cells)
    if across_rows:
        near_img = np.broadcast_to(near[None, None, :], (n_img, h, w))
        lit_img = np.broadcast_to(lit[:, :, None], (n_img, h, w))
    else:
        near_img = np.broadcast_to(near[None, :, None], (n_img, h, w))
        lit_img = np.broadcast_to(lit[:, None, :], (n_img, h, w))
    return {
        "near/far": (~near_img).astype(np.int8).reshape(-1),
        "lit/dark": (~lit_img).astype(np.int8).reshape(-1),
    }


def _chi2_3_sf(x: float) -> float:
    """P(χ²₃ > x)."""
    return math.erfc(math.sqrt(x / 2)) + math.sqrt(2 * x / math.pi) * math.exp(-x / 2)


def _column_norms(jac: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(jac, axis=0)
    return np.where(norms > 0, norms, 1.0)


def scaled_lstsq(jac: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """The least-squares solution of ``jac @ x = rhs``, its columns scaled to unit norm
    first. The gain's column and the coefficients' differ by the image units (their
    ratio grows with the units' scale): unscaled, lstsq's relative cutoff dropped the
    gain's direction for images in units 10⁶× larger and moved σs by 0.8σ."""
    norms = _column_norms(jac)
    x, *_ = np.linalg.lstsq(jac / norms, rhs, rcond=None)
    return x / norms


def gram_inverse(jac: np.ndarray, pseudo: bool = False) -> np.ndarray:
    """(JᵀJ)⁻¹ (or its pseudo-inverse), computed on the column-scaled J (see
    :func:`scaled_lstsq`); raises ``LinAlgError`` where singular (not ``pseudo``)."""
    norms = _column_norms(jac)
    scaled = jac / norms
    gram = scaled.T @ scaled
    inv = np.linalg.pinv(gram) if pseudo else np.linalg.inv(gram)
    return inv / np.outer(norms, norms)


def _part(jac, residual, rows, scale):
    """One part's least-squares shift from the whole answer, linearised
    (−(J_AᵀJ_A)⁻¹J_Aᵀr_A), and its covariance; ``None`` where the part has too few
    rows or a singular JᵀJ."""
    if rows.sum() < 4 * jac.shape[1]:
        return None
    j, r = jac[rows], residual[rows]
    try:
        inv = gram_inverse(j)
    except np.linalg.LinAlgError:
        return None
    return -inv @ (j.T @ r), scale * inv


def _consistency(jac, residual, names, scale, groups) -> dict:
    """Per split: χ²₃ of the two parts' disagreement, its chance, and each parameter's
    larger shift of a part from the whole answer (see the module docstring)."""
    idx = [names.index(k) for k in _PHYSICAL if k in names]
    if len(idx) < 3:
        return {}
    active = np.any(jac != 0, axis=1)  # masked pixels' rows carry nothing
    out = {}
    for label, group in groups.items():
        parts = [_part(jac, residual, active & (group == side), scale) for side in (0, 1)]
        if any(part is None for part in parts):
            continue
        (d0, c0), (d1, c1) = parts
        diff = (d0 - d1)[idx]
        cov = (c0 + c1)[np.ix_(idx, idx)]
        try:
            t = float(diff @ np.linalg.solve(cov, diff))
        except np.linalg.LinAlgError:
            continue
        if not math.isfinite(t):
            continue
        out[label] = {
            "chi2": t,
            "p": _chi2_3_sf(t),
            "shift": {names[i]: float(max(abs(d0[i]), abs(d1[i]))) for i in idx},
        }
    return out


def stencil_centre(x: np.ndarray, axis: int) -> np.ndarray:
    """``x`` without two pixels at each end along ``axis``: the centres of the five-pixel
    stencils of :func:`five_point`."""
    sl = [slice(None)] * x.ndim
    sl[axis] = slice(2, x.shape[axis] - 2)
    return x[tuple(sl)]


def five_point(a: np.ndarray, w: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """The 4th differences of ``a`` along ``axis`` over √70 (the noise's standard
    deviation where the signal is smooth and the noise white) and where all five pixels
    of each have weight ``w > 0``."""
    d4 = np.diff(a, n=4, axis=axis) / math.sqrt(70.0)
    valid = np.ones(d4.shape, bool)
    sl = [slice(None)] * a.ndim
    for s in range(5):  # every one of the five pixels must be valid
        sl[axis] = slice(s, a.shape[axis] - 4 + s)
        valid &= w[tuple(sl)] > 0
    return d4, valid


def _fourth_differences(a: np.ndarray, w: np.ndarray, axis: int) -> np.ndarray | None:
    """The weighted 4th differences along ``axis`` squared, z² (each a χ²₁ times the
    noise's weighted variance where the signal is smooth), where all five pixels are
    valid; ``None`` where fewer than 16."""
    d4, valid = five_point(a, w, axis)
    z2 = (d4 * stencil_centre(w, axis))[valid] ** 2
    return z2 if z2.size >= 16 else None


# The fewest samples per intensity bin of :func:`noise_floor`, and the most bins.
FLOOR_SAMPLES = 64
FLOOR_BINS = 12
# Floors beyond this multiple of the peak make the weights uniform to 0.05 %: read
# noise alone (no growth of the variance with the signal seen).
FLOOR_UNIFORM = 1e3


def _clipped_mean(z2: np.ndarray) -> float:
    """The mean of χ²₁-like samples less outliers: a first scale from the median or,
    where most samples are (near) zero, the 90th percentile; then the mean of those
    below 1000×, then 50× the scale (χ²₁ exceeds 50 with chance 2e-12)."""
    scale = max(float(np.median(z2) / 0.45494), float(np.quantile(z2, 0.9) / 2.7055))
    for limit in (1000.0, 50.0):
        kept = z2[z2 <= limit * scale]
        if kept.size < 16:
            break
        scale = float(np.mean(kept))
    return scale


def noise_floor(images: np.ndarray, mask: np.ndarray, pattern: Stripes) -> float | None:
    """The capture's read-noise floor in image units: b/a of the variance model
    var(I) = a·I + b (shot noise ∝ I, read noise constant), fitted to the squared 4th
    differences along the light (each a χ²₁ times the variance where the signal is
    smooth: the noise dominates them at any photon count a camera gives) binned by the
    stencil's centre intensity (least squares over the bins; each term's error from the
    bins' scatter about the line or their own noise, √(2/n) of a mean of n χ²₁, the
    larger), each bin's mean less outliers (the entry wall's kink;
    :func:`_clipped_mean`; a mean, not a median: dark pixels counting 0 or 1 photon
    are not Gaussian). ``FLOOR_UNIFORM`` × the
    peak where the variance does not grow with the signal (read noise alone); ``None``
    where no read noise is seen (the intercept within 2σ of 0) or where it cannot be
    measured (fewer than two bins of :data:`FLOOR_SAMPLES`, fewer than
    :data:`MIN_ALONG` pixels along the light, or a degenerate fit)."""
    a = np.asarray(images, np.float64)
    axis = 2 if pattern.along_x else 1
    if a.shape[axis] < MIN_ALONG:
        return None
    valid_px = np.broadcast_to(np.asarray(mask, bool)[None], a.shape) & np.isfinite(a)
    d4, valid = five_point(np.where(valid_px, a, 0.0), valid_px.astype(float), axis)
    centre = stencil_centre(a, axis)[valid]
    z2 = d4[valid] ** 2
    n_bins = min(FLOOR_BINS, centre.size // FLOOR_SAMPLES)
    if n_bins < 2:
        return None
    order = np.argsort(centre)
    level, var, sd = [], [], []
    for part in np.array_split(order, n_bins):
        level.append(float(np.mean(centre[part])))
        var.append(_clipped_mean(z2[part]))
        sd.append(var[-1] * math.sqrt(2.0 / part.size))  # a mean of n χ²₁
    level, var, sd = np.array(level), np.array(var), np.array(sd)
    peak = float(np.max(np.where(valid_px, a, -np.inf)))
    design = np.stack([level, np.ones_like(level)], axis=1)
    slope, intercept = scaled_lstsq(design, var)  # the level's column: image units
    # Errors from the bins' scatter about the line or from their own noise, the larger.
    scatter = np.sum((var - design @ np.array([slope, intercept])) ** 2) / max(n_bins - 2, 1)
    noise = np.mean(sd**2)
    cov = gram_inverse(design, pseudo=True) * max(scatter, noise)
    err_slope, err_intercept = np.sqrt(np.diag(cov))
    # Each term only where the data show it (2σ): no read noise seen, the shot-noise
    # weights' own floor (None); no growth with the signal, uniform weights.
    if not (np.isfinite(slope) and np.isfinite(intercept) and err_intercept > 0):
        return None
    if not intercept > 2 * err_intercept:
        return None
    if not slope > 2 * err_slope:
        return FLOOR_UNIFORM * peak
    return float(min(intercept / slope, FLOOR_UNIFORM * peak))


def noise_scale(
    images: np.ndarray, weights: np.ndarray, pattern: Stripes, model: np.ndarray | None = None
) -> float:
    """α: the variance of one weighted residual w·(model − I) that the capture's noise
    gives, measured from 4th differences along the light (NaN where it cannot be
    measured: fewer than 16 pixels along the light).

    χ² compares the mean of (w·r)² with α, so α is a mean. Without ``model``: the
    median of the images' squared differences (that of χ²₁ is 0.4549 of its mean),
    robust to the signal's kinks (the entry wall) but low where pixels differ in
    weighted variance: shot noise is ∝ I while the weights floor at 1e-3 of the peak,
    so where dark pixels are many the median is theirs (a backward medium's capture:
    11× below the mean). With ``model`` (the fitted images, like ``images``): the
    differences of the residual I − model (the signal's curvature and kinks cancel),
    their mean less outliers (a median scale, the mean below 1000× it, the mean below
    50× that: χ²₁ exceeds 50 with chance 2e-12; the first scale is the 90th
    percentile's where that is larger, so that pixels counting no photon do not set
    it to 0); never below the images' median scale,
    which on a noiseless capture (float rounding only) keeps the signal's own 4th
    differences as the floor of what this probe can tell from noise."""
    a = np.asarray(images, np.float64)
    w = np.asarray(weights, np.float64)
    axis = 2 if pattern.along_x else 1
    if a.shape[axis] < MIN_ALONG:
        return math.nan
    z2 = _fourth_differences(a, w, axis)
    if z2 is None:
        return math.nan
    floor = float(np.median(z2) / 0.45494)
    if model is None:
        return floor
    z2 = _fourth_differences(a - np.asarray(model, np.float64), w, axis)
    if z2 is None:
        return floor
    # The first scale: the median's, or the 90th percentile's where more than half of the
    # differences are (near) zero, as in a photon-starved capture whose dark pixels
    # count 0 (their median alone put χ²/dof at 4e8 on a fit within 2 % of the truth).
    return max(_clipped_mean(z2), floor)


@dataclasses.dataclass(frozen=True)
class Uncertainty:
    """The error budget of a fit (per parameter name): ``statistical``, ``model`` (the
    finer model's shift, NaN where not computed), ``total``; χ²/dof and the noise α."""

    statistical: dict
    model: dict
    total: dict
    correlation: dict
    condition_number: float
    chi2_dof: float
    noise: float
    model_limited: bool
    chi2_model: float = math.nan  # χ²/dof against the noise ⊕ the model's own error
    # Per split (split_groups): chi2, p and the parts' shifts; {} where not tested.
    consistency: dict = dataclasses.field(default_factory=dict)
    # ``correlation`` is the total's (the noise's and the model's); this, the noise's.
    correlation_statistical: dict = dataclasses.field(default_factory=dict)
    # Whether ``chi2_model`` holds the finer model's error (False: the noise's χ² alone).
    model_measured: bool = False
    # The step the answer takes to the continuum (``extrapolate`` × the finer model's
    # signed shift, per name); {} where not extrapolated.
    extrapolation: dict = dataclasses.field(default_factory=dict)


def error_budget(
    jac: np.ndarray,
    residual: np.ndarray,
    names: list[str],
    noise: float,
    residual_shift: np.ndarray | None = None,
    groups: dict[str, np.ndarray] | None = None,
    extrapolate: float | None = None,
) -> Uncertainty:
    """Statistical errors from ``jac`` (∂r/∂p, n × p) and the noise α, χ²/dof of
    ``residual``, and the model term: −J⁺·``residual_shift`` (r_fine − r) if given, or
    the shift of a part of the capture whose answer disagrees with the other's (per
    split of ``groups``, :func:`split_groups`; where the noise is known), the larger.

    ``extrapolate`` (κ, with ``residual_shift``): the finer model is that far short of
    the continuum (the model's error is κ·(r_fine − r): :func:`~lightfield_jax.inverse.
    model_size.richardson_factor`); the answer's step to it, κ·δp, is returned in
    ``extrapolation``, the model term stays |δp| (what the extrapolation may miss: its
    first-order rule held to 7 % of the step where measured, a third of κ = 3), and the
    misfit is judged against the noise ⊕ κ·(r_fine − r)."""
    jac = np.asarray(jac, np.float64)
    residual = np.asarray(residual, np.float64)
    # Masked values (weight 0) are rows of zeros: no degrees of freedom.
    n = int(np.sum(np.any(jac != 0, axis=1) | (residual.reshape(-1) != 0)))
    p = jac.shape[1]
    jtj = jac.T @ jac
    nan = {k: math.nan for k in names}
    try:
        d = np.sqrt(np.clip(np.diag(jtj), 1e-300, None))
        cond = float(np.linalg.cond(jtj / np.outer(d, d)))
        inv = gram_inverse(jac)
    except np.linalg.LinAlgError:
        inf = {k: math.inf for k in names}
        return Uncertainty(inf, nan, inf, {}, math.inf, math.nan, noise, False)
    s2 = float(residual @ residual) / max(n - p, 1)
    chi2 = s2 / noise if noise > 0 and math.isfinite(noise) else math.nan
    chi2_model = chi2
    scale = s2 if not math.isfinite(chi2) else noise * max(1.0, chi2)
    cov = scale * inv
    err = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    stat = {k: float(e) for k, e in zip(names, err, strict=True)}
    model = dict(nan)
    shift = np.zeros(p)
    extrapolation = {}
    dr = None if residual_shift is None else np.asarray(residual_shift, np.float64).reshape(-1)
    # A finer model whose render is not finite (a solve at a bound: albedo 0, a huge gain)
    # measures no model error: the misfit is then judged against the noise alone, not
    # left unjudged (χ² NaN hid a misfit 400 times the noise and its offset hint).
    if dr is not None and np.all(np.isfinite(dr)):
        shift = -inv @ (jac.T @ dr)
        model = {k: float(abs(v)) for k, v in zip(names, shift, strict=True)}
        kappa = 1.0 if extrapolate is None else float(extrapolate)
        if extrapolate is not None:
            extrapolation = {k: float(kappa * v) for k, v in zip(names, shift, strict=True)}
        floor = (noise if math.isfinite(noise) else 0.0) + kappa**2 * float(dr @ dr) / max(n - p, 1)
        chi2_model = s2 / floor if floor > 0 else math.nan
    consistency = {}
    if groups and math.isfinite(chi2):
        consistency = _consistency(jac, residual, names, scale, groups)
        for split in consistency.values():
            if split["p"] < CONSISTENCY_P:
                for k, v in split["shift"].items():
                    model[k] = v if not math.isfinite(model[k]) else max(model[k], v)
    total = {
        k: math.hypot(stat[k], model[k]) if math.isfinite(model[k]) else stat[k] for k in names
    }
    physical = [k for k in _PHYSICAL if k in names]
    limited = any(math.isfinite(model[k]) and model[k] > stat[k] for k in physical)
    # The total's covariance: the noise's, the finer model's (signed) shift as a rank-one
    # term, and what the model term holds beyond it (a split's shift) as uncorrelated, so
    # that its diagonal is the total 1σ². Its correlations go with ``total``: paired with
    # the noise's correlations instead, the total 1σ of a forward medium (ω 0.8, g 0.7,
    # its σt–g valley, |r| 0.9) gives joint regions too thin (M² above χ²₃'s 95 % point
    # in 3 of 20 fits; 0 of 20 with these).
    m = np.array([model[k] if math.isfinite(model[k]) else 0.0 for k in names])
    rank_one = np.sign(shift) * np.minimum(np.abs(shift), m)
    cov_total = cov + np.outer(rank_one, rank_one) + np.diag(m**2 - rank_one**2)
    return Uncertainty(
        stat,
        model,
        total,
        _correlations(cov_total, names),
        cond,
        chi2,
        noise,
        limited,
        chi2_model,
        consistency,
        _correlations(cov, names),
        bool(dr is not None and np.all(np.isfinite(dr))),
        extrapolation,
    )


def _correlations(cov: np.ndarray, names: list[str]) -> dict:
    err = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    corr = {}
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            dd = err[i] * err[j]
            corr[f"{names[i]},{names[j]}"] = float(cov[i, j] / dd) if dd > 0 else math.nan
    return corr


def at_bound(values: dict, black_range: tuple[float, float] | None = None) -> list[str]:
    """The parameters of a solution that sit at a bound of the model (empty: none).
    ``values`` holds sigma_t, sigma_s, g (and black_level when ``black_range`` is given:
    it was fitted)."""
    reasons = []
    g = values["g"]
    albedo = values["sigma_s"] / values["sigma_t"]
    if abs(g) >= G_BOUND - 1e-6:  # float32's 0.95 is 0.94999999 (the grid's end)
        reasons.append(f"g = {g:.3f} is at its bound (|g| >= {G_BOUND})")
    lo, hi = ALBEDO_BOUNDS
    if not lo < albedo < hi:
        reasons.append(f"albedo = {albedo:.4f} is at its bound (outside ({lo}, {hi}))")
    if black_range is not None:
        b = values["black_level"]
        if not black_range[0] + 0.01 < b < black_range[1] - 0.01:
            reasons.append(f"black level = {b:.3f} is at its bound {list(black_range)}")
    return reasons


# The largest statistical 1σ of an identified parameter: relative for σt and σs,
# absolute for g (whose range is 2). Beyond it the linearised error does not describe
# the fit: on a capture of ~10³ photons at its peak (the paper's milk, 64×48), fitted
# with first-stage weights from the data's local mean (an experiment, not kept), the
# answer had σs ± 215 %, g −0.88 ± 0.20 with the truth g 0.4, 6σ away.
IDENTIFIED = 0.5


def unidentified(values: dict, budget: Uncertainty) -> list[str]:
    """The parameters whose 1σ exceeds :data:`IDENTIFIED` (relative for σt and σs,
    absolute for g): the statistical one (the capture's noise alone: the capture does
    not determine them), else the total one (noise ⊕ the model's error: the model does
    not, e.g. the parts of the capture disagree by more than that). Empty: all are
    determined (NaN where not measured)."""
    reasons = []
    for name in _PHYSICAL:
        relative = name != "g"
        scale = abs(values[name]) if relative else 1.0
        for part, what in (
            ("statistical", "statistical 1σ (the capture's noise alone)"),
            ("total", "total 1σ (the noise and the model's error)"),
        ):
            sd = getattr(budget, part).get(name, math.nan)
            if math.isfinite(sd) and sd > IDENTIFIED * scale:
                spread = f"{100 * sd / scale:.0f} %" if relative else f"{sd:.2f}"
                reasons.append(
                    f"{name} is not identifiable from this capture: its {what} is ± {spread}"
                )
                break
    return reasons


def negative_gain(values: dict) -> list[str]:
    """The reason a solution is not to be trusted when its gain (the images' scale
    against the model's light) is not positive: the images are darker where the model
    puts light (negated images, or a dark frame brighter than them). Empty: it is
    positive (or not given)."""
    gain = values.get("gain", math.nan)
    if math.isfinite(gain) and gain <= 0:
        return [
            f"the gain is {gain:.4g}, not positive: the images are darker where the model "
            "puts light (negated images, or a dark frame subtracted that is brighter than "
            "them?)"
        ]
    return []


def untrustworthy(
    values: dict,
    budget: Uncertainty,
    max_chi2: float,
    black_range: tuple[float, float] | None = None,
) -> list[str]:
    """The reasons a solution is not to be trusted (empty: none): :func:`at_bound`, a
    parameter the capture's noise does not determine (:func:`unidentified`), a gain
    that is not positive (:func:`negative_gain`), and a misfit far above ``max_chi2``
    judged by ``budget.chi2_model`` (noise ⊕ the model's own error, or the noise alone
    where that error was not measured: said so)."""
    reasons = at_bound(values, black_range) + unidentified(values, budget)
    reasons += negative_gain(values)
    if math.isfinite(budget.chi2_model) and budget.chi2_model > max_chi2:
        if budget.model_measured:
            reasons.append(
                f"misfit far above the capture's noise and the model's own error: chi2/dof "
                f"= {budget.chi2_model:.3g} > {max_chi2:g} (against the noise alone: "
                f"{budget.chi2_dof:.3g})"
            )
        else:  # no finer model's error measured: judged against the noise alone
            reasons.append(
                f"misfit far above the capture's noise: chi2/dof = {budget.chi2_model:.3g} "
                f"> {max_chi2:g} (the model's own error not measured)"
            )
    return reasons


# A misfit far above the noise that one constant added to every image value would take
# to OFFSET_EXPLAINS of itself or less (linearised at the answer, beside the parameters'
# columns) is reported with that constant: a camera's pedestal (black offset) left in
# the images, or a dark frame that subtracts too much, is light the model does not have.
OFFSET_EXPLAINS = 0.25


def constant_offset(jac: np.ndarray, residual: np.ndarray, weights: np.ndarray):
    """The constant d in every image value (images = model + d) that best explains the
    weighted residual r = w·(model − images) beside the columns of ``jac`` (linearised
    at the answer), and the misfit left with it as a fraction of the misfit without:
    ``(d, fraction)`` (``(nan, 1.0)`` where it cannot be told)."""
    r = np.asarray(residual, np.float64).reshape(-1)
    w = np.asarray(weights, np.float64).reshape(-1)
    j = np.asarray(jac, np.float64)
    total = float(r @ r)
    if not (np.all(np.isfinite(j)) and np.all(np.isfinite(r)) and total > 0):
        return math.nan, 1.0
    q, _ = np.linalg.qr(j / _column_norms(j))
    r_left = r - q @ (q.T @ r)
    column = -w - q @ (q.T @ -w)
    norm2 = float(column @ column)
    if not norm2 > 1e-12 * float(w @ w):
        return math.nan, 1.0
    d = float(column @ r_left) / norm2
    left = float(r_left @ r_left)  # what the parameters' columns leave (at an answer: r)
    return d, max(left - d * d * norm2, 0.0) / left if left > 0 else 1.0


def offset_hint(d: float, left: float, where: str, peak: float) -> list[str]:
    """A reason's hint where a constant offset ``d`` leaves at most
    :data:`OFFSET_EXPLAINS` of a misfit (``left``: the fraction it leaves of ``where``'s
    misfit), ``[]`` otherwise; ``peak``: the images' peak value."""
    if not (math.isfinite(d) and left <= OFFSET_EXPLAINS):
        return []
    cause = (
        "a camera pedestal (black offset) left in the images? (a capture file removes it "
        "with a dark_frame or dark_level)"
        if d > 0
        else "a dark frame or dark_level that subtracts too much?"
    )
    share = f" ({d / peak:+.1%} of the peak)" if peak > 0 and math.isfinite(peak) else ""
    return [
        f"a constant {d:+.4g} in every image value{share} would leave {left:.1%} of the "
        f"{where} misfit: {cause}"
    ]


def tail_unconverged(tail: dict | None, max_steps: int, what: str) -> list[str]:
    """The reason a solution is not to be trusted when ``what``'s tail solve (``tail``:
    its ``steps``, ``converged`` and, where a tangent solve raised, ``error``; ``None``
    without a tail) did not converge (empty: it did, or there is none)."""
    if tail is None or tail["converged"]:
        return []
    detail = tail.get("error") or f"{tail['steps']} iterations"
    return [
        f"the tail solve of {what} did not converge within tail_max_steps = {max_steps} ({detail})"
    ]


__all__ = [
    "Uncertainty",
    "at_bound",
    "error_budget",
    "negative_gain",
    "noise_scale",
    "split_groups",
    "tail_unconverged",
    "unidentified",
    "untrustworthy",
]
