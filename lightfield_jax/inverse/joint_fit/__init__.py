"""The joint fit (the ``joint`` method's solve), over one :class:`~.context.FitContext`:

- :mod:`.stage`: one compiled solve of a model from a start (:class:`~.stage.Stage`),
  the renderers and the noise weights;
- :mod:`.scan`: the basin scans on a cheap model and the starts they give;
- :mod:`.slope`: the starts not worth a solve (on the slope of an answer found);
- :mod:`.continuation` and :mod:`.refit`: from a cheap answer to the model it needs
  (defect correction, else a solve on it), refitted with the model's weights;
- :mod:`.search`: the loop over the starts and the rescan;
- :mod:`.finer` and :mod:`.verdict`: the error term of a finer model and why an answer
  is not trustworthy;
- :mod:`.fit` (one fit, :func:`~.fit.fit_once`) and :mod:`.censoring` (the fit of a
  capture, solved again without the values near a clip: :func:`joint_fit`).
"""

from lightfield_jax.inverse.joint_fit.censoring import CLIP_SIGMAS as CLIP_SIGMAS
from lightfield_jax.inverse.joint_fit.censoring import joint_fit as joint_fit
from lightfield_jax.inverse.joint_fit.censoring import near_the_clip as near_the_clip
from lightfield_jax.inverse.joint_fit.context import FitContext as FitContext
from lightfield_jax.inverse.joint_fit.stage import joint_weights as joint_weights

__all__ = ["CLIP_SIGMAS", "FitContext", "joint_fit", "joint_weights", "near_the_clip"]
