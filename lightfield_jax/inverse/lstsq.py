"""Least squares on a Jacobian whose columns differ in scale by orders of magnitude
(the gain's column and the coefficients' differ by the image units): each solve scales
the columns to unit norm first (:func:`column_norms`), solves, and scales back.
Shared by the noise floor's line fit (:mod:`lightfield_jax.inverse.noise`), the error
budget (:mod:`lightfield_jax.inverse.budget`), the verdict's constant offset
(:mod:`lightfield_jax.inverse.verdict`) and the joint fit's linearised steps."""

from __future__ import annotations

import numpy as np


def column_norms(jac: np.ndarray) -> np.ndarray:
    """The norms of ``jac``'s columns, 1 where a column is zero (scaling it is then a
    no-op)."""
    norms = np.linalg.norm(jac, axis=0)
    return np.where(norms > 0, norms, 1.0)


def scaled_lstsq(jac: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """The least-squares solution of ``jac @ x = rhs``, its columns scaled to unit norm
    first. The gain's column and the coefficients' differ by the image units (their
    ratio grows with the units' scale): unscaled, lstsq's relative cutoff dropped the
    gain's direction for images in units 10⁶× larger and moved σs by 0.8σ."""
    norms = column_norms(jac)
    x, *_ = np.linalg.lstsq(jac / norms, rhs, rcond=None)
    return x / norms


def gram_inverse(jac: np.ndarray, pseudo: bool = False) -> np.ndarray:
    """(JᵀJ)⁻¹ (or its pseudo-inverse), computed on the column-scaled J (see
    :func:`scaled_lstsq`); raises ``LinAlgError`` where singular (not ``pseudo``)."""
    norms = column_norms(jac)
    scaled = jac / norms
    gram = scaled.T @ scaled
    inv = np.linalg.pinv(gram) if pseudo else np.linalg.inv(gram)
    return inv / np.outer(norms, norms)


__all__ = ["column_norms", "gram_inverse", "scaled_lstsq"]
