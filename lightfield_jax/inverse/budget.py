"""A fit's error budget (:func:`error_budget`, :class:`Uncertainty`): χ²/dof, the
statistical 1σ, the model's own error and the consistency of parts of the capture.

- χ²/dof = ‖r‖²/(n − p)/α (α: the noise of one weighted residual,
  :func:`~lightfield_jax.inverse.noise.noise_scale`): about 1 when the model explains
  the capture to its noise. A misfit is "far above the noise" when it is far above the
  noise and the model's own discretisation error together: χ²/dof against
  α + ‖r_fine − r‖²/(n − p) (a noiseless synthetic capture is fitted to its model's
  precision, not to zero).
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

Whether the answer is then to be trusted is :mod:`lightfield_jax.inverse.verdict`'s.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from lightfield_jax.inverse.lstsq import gram_inverse
from lightfield_jax.scene.illumination import Stripes

# A split of the capture whose two parts disagree beyond this chance (their noise
# alone) shows a model error.
CONSISTENCY_P = 1e-3
# The physical parameters: the consistency test's χ²₃ and ``model_limited`` are over
# these.
PHYSICAL = ("sigma_t", "sigma_s", "g")


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
    idx = [names.index(k) for k in PHYSICAL if k in names]
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
    physical = [k for k in PHYSICAL if k in names]
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


__all__ = [
    "CONSISTENCY_P",
    "PHYSICAL",
    "Uncertainty",
    "error_budget",
    "split_groups",
]
