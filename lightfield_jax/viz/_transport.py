"""The paper's figures of one rendered scene, written into a folder in one call."""

from __future__ import annotations

import os
from pathlib import Path

from lightfield_jax.checks import shown as brief
from lightfield_jax.forward.render import RenderResult
from lightfield_jax.scene.illumination import Illumination

from ._common import (
    check_common,
    check_illumination,
)
from ._fields import plot_bounce_images, plot_lightfield
from ._paper import plot_bounce_profiles


def plot_transport(
    result: RenderResult,
    folder,
    *,
    illumination: Illumination | None = None,
    title: str = "",
) -> list[Path]:
    """Write the transport of a render into ``folder`` (which must exist):

    - ``bounce_images.png`` (Fig. 14): I_1..I_6 and Σ_k I_k;
    - ``bounce_profiles.png`` (Fig. 12): each bounce's decay along the light;
    - ``lightfield.png`` (Fig. 13): L_0..L_4 and Σ_k L_k with direction glyphs, when
      the render holds light fields.

    ``illumination`` is the light the render used (sets the path coordinate of the
    profiles); ``title`` prefixes each figure's title (e.g. the medium's values).
    """
    if not isinstance(result, RenderResult):
        raise ValueError(
            f"plot_transport.result: must be a RenderResult (lightfield_jax.render), got "
            f"{type(result).__name__}"
        )
    if not isinstance(folder, (str, os.PathLike)) or not Path(folder).is_dir():
        raise ValueError(f"plot_transport.folder: must be an existing folder, got {brief(folder)}")
    check_illumination(illumination, "plot_transport")
    check_common("plot_transport", None, title=title)
    folder = Path(folder)
    prefix = f"{title}: " if title else ""
    k = result.bounces
    files = [
        plot_bounce_images(
            result,
            folder / "bounce_images.png",
            show=6,
            illumination=illumination,
            title=f"{prefix}images of light that scattered k times (of K = {k})",
        ),
        plot_bounce_profiles(
            result,
            folder / "bounce_profiles.png",
            illumination=illumination,
            title=f"{prefix}each bounce along the light",
        ),
    ]
    if result.lightfields is not None:
        files.append(
            plot_lightfield(
                result,
                folder / "lightfield.png",
                title=f"{prefix}light fields L_k (colour: fluence; glyphs: L(θ), θ from +x "
                "toward +y)",
            )
        )
    return files
