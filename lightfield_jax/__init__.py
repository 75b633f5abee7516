"""lightfield_jax: differentiable light transport in thin scattering media.

The method of Mukaigawa, Raskar & Yagi, "Analysis of Light Transport in Scattering
Media" (CVPR 2010) in JAX. Pipeline: medium & grid → illumination → render
(bounce propagator) → separate → fit → report.
"""

from ._calibration import BlackLevel as BlackLevel
from ._calibration import estimate_black_level as estimate_black_level
from ._capture import Capture as Capture
from ._capture import CaptureWarning as CaptureWarning
from ._capture import load_capture as load_capture
from ._capture import write_capture_yaml as write_capture_yaml
from ._config import ConfigError as ConfigError
from ._config import SimulationConfig as SimulationConfig
from ._config import load_simulation_config as load_simulation_config
from ._decay import DecayFit as DecayFit
from ._decay import fit_decay as fit_decay
from ._fit import CaptureFit as CaptureFit
from ._fit import FitOptions as FitOptions
from ._fit import FitResult as FitResult
from ._fit import fit_capture as fit_capture
from ._fit import fit_images as fit_images
from ._fit import fitted_images as fitted_images
from ._geometry import Geometry as Geometry
from ._geometry import detect_geometry as detect_geometry
from ._grid import Grid as Grid
from ._grid import default_n_theta as default_n_theta
from ._grid import default_refine as default_refine
from ._illumination import Beam as Beam
from ._illumination import Full as Full
from ._illumination import Stripes as Stripes
from ._inspect import Inspection as Inspection
from ._inspect import inspect_capture as inspect_capture
from ._io import CaptureError as CaptureError
from ._medium import Medium as Medium
from ._medium import bounces_for_tolerance as bounces_for_tolerance
from ._medium import phase_function as phase_function
from ._medium import phase_integral as phase_integral
from ._pattern import stripe_patterns as stripe_patterns
from ._pattern import write_patterns as write_patterns
from ._programs import clear_compiled as clear_compiled
from ._programs import enable_compilation_cache as enable_compilation_cache
from ._render import DivergentSeriesWarning as DivergentSeriesWarning
from ._render import Renderer as Renderer
from ._render import RenderResult as RenderResult
from ._render import make_renderer as make_renderer
from ._render import render as render
from ._render import single_scatter_closed_form as single_scatter_closed_form
from ._separate import Separation as Separation
from ._separate import separate as separate
from ._simulate import SimulatedCapture as SimulatedCapture
from ._simulate import simulate_capture as simulate_capture
from ._slab import AutoGeometry as AutoGeometry
from ._slab import Plane as Plane
from ._slab import Slab as Slab
from ._slab import SlabRenderer as SlabRenderer
from ._tail import TailNotConvergedWarning as TailNotConvergedWarning
from ._tail import TailSolution as TailSolution

__version__ = "0.1.0"
