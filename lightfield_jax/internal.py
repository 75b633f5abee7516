"""Building blocks below the public API, for experiments and outside comparisons.

Less stable than the top-level :mod:`lightfield_jax` namespace: these names may change
between minor versions. Use them to reuse the package's own pieces (the two-step
residual in another solver, a fit method's prepared data, a renderer on a sized model)
instead of copying them.

- Prepared data and fit records: :class:`FitData` (:func:`prepare_data`),
  :class:`FitProblem`, :class:`FitSolution`.
- The two-step problem (:mod:`lightfield_jax.inverse.two_step`): the residual of the
  paper's eq. 10 with its Jacobian (:func:`two_step_residual`, the images' slope along g
  from :func:`rendered_and_g_slope`), the per-g σs polynomial fit
  (:func:`poly_fit_sigma_s`), the search over g (:func:`search_g`) and the solve's
  parametrisation and start (:func:`to_params`, :func:`search_start`) and the
  program's data arguments (:func:`problem_arrays`).
- The joint problem (:mod:`lightfield_jax.inverse.joint`): its compiled solve
  (:func:`solve_joint`, :class:`JointSettings`), the model at unit gain
  (:func:`unit_model`, :func:`model_at`), the parametrisation (:func:`pack`,
  :func:`unpack`) and the noise weights (:func:`joint_weights`).
- Model size and renderers: :func:`size_model`, :func:`renderer_for`, full
  illumination of a stripe pattern (:func:`full_for`).
- Monte Carlo oracles: :func:`monte_carlo_render`, :func:`monte_carlo_slab`.
"""

from lightfield_jax.forward.render import renderer_for as renderer_for
from lightfield_jax.inverse.basins import reference_sigma_s as reference_sigma_s
from lightfield_jax.inverse.data import FitData as FitData
from lightfield_jax.inverse.data import FitProblem as FitProblem
from lightfield_jax.inverse.data import FitSolution as FitSolution
from lightfield_jax.inverse.data import prepare_data as prepare_data
from lightfield_jax.inverse.jacobian import with_forward_jacobian as with_forward_jacobian
from lightfield_jax.inverse.jacobian import with_jacobian as with_jacobian
from lightfield_jax.inverse.joint import JointSettings as JointSettings
from lightfield_jax.inverse.joint import model_at as model_at
from lightfield_jax.inverse.joint import pack as pack
from lightfield_jax.inverse.joint import solve as solve_joint
from lightfield_jax.inverse.joint import unit_model as unit_model
from lightfield_jax.inverse.joint import unpack as unpack
from lightfield_jax.inverse.joint_fit.stage import joint_weights as joint_weights
from lightfield_jax.inverse.model_size import size_model as size_model
from lightfield_jax.inverse.two_step import TwoStepSettings as TwoStepSettings
from lightfield_jax.inverse.two_step import TwoStepSolution as TwoStepSolution
from lightfield_jax.inverse.two_step import full_for as full_for
from lightfield_jax.inverse.two_step import masked_dot as masked_dot
from lightfield_jax.inverse.two_step import poly_fit_sigma_s as poly_fit_sigma_s
from lightfield_jax.inverse.two_step import problem_arrays as problem_arrays
from lightfield_jax.inverse.two_step import rendered_and_g_slope as rendered_and_g_slope
from lightfield_jax.inverse.two_step import search_g as search_g
from lightfield_jax.inverse.two_step import search_start as search_start
from lightfield_jax.inverse.two_step import sigma_s_max as sigma_s_max
from lightfield_jax.inverse.two_step import solve_two_step as solve_two_step
from lightfield_jax.inverse.two_step import to_params as to_params
from lightfield_jax.inverse.two_step import two_step_residual as two_step_residual
from lightfield_jax.reference.montecarlo import monte_carlo_render as monte_carlo_render
from lightfield_jax.reference.montecarlo_slab import monte_carlo_slab as monte_carlo_slab

__all__ = [
    "FitData",
    "FitProblem",
    "FitSolution",
    "JointSettings",
    "TwoStepSettings",
    "TwoStepSolution",
    "full_for",
    "joint_weights",
    "masked_dot",
    "model_at",
    "monte_carlo_render",
    "monte_carlo_slab",
    "pack",
    "poly_fit_sigma_s",
    "problem_arrays",
    "prepare_data",
    "reference_sigma_s",
    "rendered_and_g_slope",
    "renderer_for",
    "search_g",
    "search_start",
    "sigma_s_max",
    "size_model",
    "solve_joint",
    "solve_two_step",
    "to_params",
    "two_step_residual",
    "unit_model",
    "unpack",
    "with_forward_jacobian",
    "with_jacobian",
]
