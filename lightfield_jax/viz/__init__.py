"""Figures (matplotlib, imported lazily by ``import lightfield_jax.viz`` only).

- :func:`plot_fit`: measured against fitted decay profiles (direct and multiple, per
  bounce) and the residual map of a fit.
- :func:`plot_channels`: σt, σs and g of each colour channel with error bars.
- :func:`plot_inspect`: what the pipeline sees in a capture before a fit (ROI, entry
  wall, direction, separated images, masked pixels, SNR along the beam).
- The paper's figures (Mukaigawa, Raskar & Yagi 2010), for any result:
  :func:`plot_direct_decay` (Fig. 11, σt from the direct component's decay),
  :func:`plot_bounce_profiles` (Fig. 12, each bounce along the light),
  :func:`plot_lightfield` (Fig. 13, light fields with direction glyphs),
  :func:`plot_bounce_images` (Fig. 14, per-bounce images, e.g. of an oblique beam);
  these three also take a :class:`~lightfield_jax.RenderResult`, and
  :func:`plot_transport` writes all three of one render into a folder.
"""

from ._capture_plot import plot_channels as plot_channels
from ._capture_plot import plot_inspect as plot_inspect
from ._common import light_path_coordinates as light_path_coordinates
from ._fields import plot_bounce_images as plot_bounce_images
from ._fields import plot_lightfield as plot_lightfield
from ._fit_plot import plot_fit as plot_fit
from ._paper import MAX_SHOWN_BOUNCES as MAX_SHOWN_BOUNCES
from ._paper import plot_bounce_profiles as plot_bounce_profiles
from ._paper import plot_direct_decay as plot_direct_decay
from ._paper import shown_bounces as shown_bounces
from ._transport import plot_transport as plot_transport
