"""Figures (matplotlib, imported lazily by ``import lightfield_jax.viz`` only).

- :func:`plot_fit`: measured against fitted decay profiles (direct and multiple, per
  bounce) and the residual map of a fit.
"""

from ._fit_plot import plot_fit as plot_fit
