"""lightfield_jax: differentiable light transport in thin scattering media.

The method of Mukaigawa, Raskar & Yagi, "Analysis of Light Transport in Scattering
Media" (CVPR 2010) in JAX. Pipeline: medium & grid → illumination → render
(bounce propagator) → separate → fit → report.
"""

# First: JAX imported with its environment checked (a JAX_* variable it cannot read).
import lightfield_jax._jax_environment  # noqa: F401  # isort: skip
from lightfield_jax.capture.calibration import BlackLevel as BlackLevel
from lightfield_jax.capture.calibration import estimate_black_level as estimate_black_level
from lightfield_jax.capture.capture import Capture as Capture
from lightfield_jax.capture.capture import CaptureWarning as CaptureWarning
from lightfield_jax.capture.detect import Geometry as Geometry
from lightfield_jax.capture.detect import detect_geometry as detect_geometry
from lightfield_jax.capture.inspect import Inspection as Inspection
from lightfield_jax.capture.inspect import inspect_capture as inspect_capture
from lightfield_jax.capture.io import CaptureError as CaptureError
from lightfield_jax.capture.loading import load_capture as load_capture
from lightfield_jax.capture.pattern import stripe_patterns as stripe_patterns
from lightfield_jax.capture.pattern import write_patterns as write_patterns
from lightfield_jax.capture.write import write_capture_yaml as write_capture_yaml
from lightfield_jax.forward.cell import CellRenderer as CellRenderer
from lightfield_jax.forward.render import DivergentSeriesWarning as DivergentSeriesWarning
from lightfield_jax.forward.render import Renderer as Renderer
from lightfield_jax.forward.render import RenderResult as RenderResult
from lightfield_jax.forward.render import make_renderer as make_renderer
from lightfield_jax.forward.render import render as render
from lightfield_jax.forward.render import single_scatter_closed_form as single_scatter_closed_form
from lightfield_jax.forward.simulate import SimulatedCapture as SimulatedCapture
from lightfield_jax.forward.simulate import simulate_capture as simulate_capture
from lightfield_jax.forward.simulate_config import SimulationConfig as SimulationConfig
from lightfield_jax.forward.simulate_config import load_simulation_config as load_simulation_config
from lightfield_jax.forward.slab import SlabRenderer as SlabRenderer
from lightfield_jax.forward.slab_cell import SlabCellRenderer as SlabCellRenderer
from lightfield_jax.forward.tail import TailNotConvergedWarning as TailNotConvergedWarning
from lightfield_jax.forward.tail import TailSolution as TailSolution
from lightfield_jax.inverse.capture_fit import CaptureFit as CaptureFit
from lightfield_jax.inverse.capture_fit import fit_capture as fit_capture
from lightfield_jax.inverse.decay import DecayFit as DecayFit
from lightfield_jax.inverse.decay import fit_decay as fit_decay
from lightfield_jax.inverse.fit import fit_images as fit_images
from lightfield_jax.inverse.fit import fitted_images as fitted_images
from lightfield_jax.inverse.method_base import FitMethod as FitMethod
from lightfield_jax.inverse.methods import GridSearch as GridSearch
from lightfield_jax.inverse.methods import Joint as Joint
from lightfield_jax.inverse.methods import TwoStep as TwoStep
from lightfield_jax.inverse.options import FitOptions as FitOptions
from lightfield_jax.inverse.options import FitResult as FitResult
from lightfield_jax.inverse.programs import clear_compiled as clear_compiled
from lightfield_jax.inverse.programs import enable_compilation_cache as enable_compilation_cache
from lightfield_jax.inverse.separate import Separation as Separation
from lightfield_jax.inverse.separate import separate as separate
from lightfield_jax.inverse.settings import ModelOptions as ModelOptions
from lightfield_jax.inverse.settings import SolverOptions as SolverOptions
from lightfield_jax.inverse.settings import TrustOptions as TrustOptions
from lightfield_jax.scene.geometry import AutoGeometry as AutoGeometry
from lightfield_jax.scene.geometry import Plane as Plane
from lightfield_jax.scene.geometry import Slab as Slab
from lightfield_jax.scene.grid import Grid as Grid
from lightfield_jax.scene.grid import default_n_theta as default_n_theta
from lightfield_jax.scene.grid import default_refine as default_refine
from lightfield_jax.scene.illumination import Beam as Beam
from lightfield_jax.scene.illumination import Full as Full
from lightfield_jax.scene.illumination import Stripes as Stripes
from lightfield_jax.scene.medium import Medium as Medium
from lightfield_jax.scene.medium import bounces_for_tolerance as bounces_for_tolerance
from lightfield_jax.scene.phase import phase_function as phase_function
from lightfield_jax.scene.phase import phase_integral as phase_integral
from lightfield_jax.schema import ConfigError as ConfigError

__version__ = "0.1.0"
