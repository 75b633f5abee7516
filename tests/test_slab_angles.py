"""How many angles the slab's later bounces need far from the entry wall
(docs/slab_depth.md section 8): the default azimuth bins against twice as many, what the
cell cap lowers first, and what the error term's finer model refines first."""

from __future__ import annotations

import numpy as np
import pytest

import lightfield_jax as lfj
from lightfield_jax.forward.slab import SlabRenderer
from lightfield_jax.inverse.joint_fit import finer as error_term
from lightfield_jax.inverse.model_size import size_model
from lightfield_jax.inverse.options import FitOptions
from lightfield_jax.inverse.slab_caps import finer_order
from lightfield_jax.scene.geometry import Slab, default_slab_n_theta

TANK = Slab(6.4, "refractive", 1.33)


def far_half(n_theta: int, g: float) -> float:
    """The far half's light of a 32×12 tank under full light from the left wall."""
    slab = TANK.resolve(g, sigma_t=0.25, albedo=0.95)
    renderer = SlabRenderer(lfj.Grid(32, 12, n_theta, 1), lfj.Full(entry="left"), 16, slab)
    image = np.asarray(renderer(0.25, 0.2375, g)[0], np.float64).sum(axis=(0, 1))
    return float(image[:, 16:].sum())


@pytest.mark.slow
def test_the_default_azimuth_bins_keep_the_far_half_of_a_forward_medium():
    """g 0.8: the default's bins within 1.5 % of twice as many in the far half of the
    tank (1.1 % measured), where half the default's lose more than 3 % (4.5 %)."""
    n = default_slab_n_theta(0.8, "refractive", 0.95)
    finer = far_half(2 * n, 0.8)
    assert abs(far_half(n, 0.8) / finer - 1) < 0.015
    assert far_half(n // 2, 0.8) / finer - 1 < -0.03


def test_the_cell_cap_keeps_16_azimuth_bins_before_it_takes_nodes_below_8():
    """A 128×96 capture of a g 0.8 medium: the correction's cap (max_render_cells) leaves
    16 bins and 8 nodes, not 8 bins and 12 nodes (far half −5.4 % at 16 × 8 in
    docs/slab_depth.md section 8; 8 bins lose 9 % even at 16 nodes); a 48×36 capture keeps
    32 bins."""
    opts = FitOptions(geometry=TANK, phase="normalized")
    render_cap = FitOptions(
        geometry=TANK, phase="normalized", max_cells=opts.model.max_render_cells
    )
    images = np.zeros((6, 96, 128))
    big = size_model(images, lfj.Stripes(), 0.95, 0.8, render_cap, 1.03, 0.2, (0, 0, 128, 96))
    assert (big.grid.n_theta, big.geometry.slab.n_mu) == (16, 8)
    small = size_model(images, lfj.Stripes(), 0.95, 0.8, render_cap, 1.03, 0.2, (0, 0, 48, 36))
    assert (small.grid.n_theta, small.geometry.slab.n_mu) == (32, 24)
    # The error term's finer model doubles what the cap lowered first: bins and nodes.
    fine = error_term.finer(big, opts, 0.8)
    assert (fine.grid.n_theta, fine.geometry.slab.n_mu) == (32, 16)
    assert fine.geometry.slab.n_z == big.geometry.slab.n_z  # no room for the layers too
    # A count the options fix is never lowered.
    fixed = FitOptions(
        geometry=Slab(6.4, "refractive", 1.33, n_mu=24),
        phase="normalized",
        max_cells=opts.model.max_render_cells,
    )
    kept = size_model(images, lfj.Stripes(), 0.95, 0.8, fixed, 1.03, 0.2, (0, 0, 128, 96))
    assert kept.geometry.slab.n_mu == 24 and kept.grid.n_theta == 8


def test_the_finer_model_doubles_the_layers_first_where_the_nodes_are_the_rules():
    """Behind absorbing faces at g 0.2 the rule's own 4 elevation nodes are enough (no
    cap lowered them): on a 256×192 capture, where the finer model has room for one of
    nodes and layers, it doubles the layers (4 to 8), not the nodes."""
    opts = FitOptions(geometry=Slab(6.4), phase="normalized")
    images = np.zeros((6, 192, 256))
    model = size_model(images, lfj.Stripes(), 0.9, 0.2, opts, 1.03, 0.2, (0, 0, 256, 192))
    slab = model.geometry.slab
    assert (model.grid.n_theta, slab.n_mu, slab.n_z) == (8, 4, 4)
    fine = error_term.finer(model, opts, 0.2)
    assert (fine.grid.n_theta, fine.geometry.slab.n_mu, fine.geometry.slab.n_z) == (8, 4, 8)


def test_the_finer_models_order_reads_the_rules_as_the_sizing_does():
    """The order read the rules at |g| without the sizing's margin and with no albedo:
    at g 0.58 the sizing asks 32 azimuth bins (0.63 with the margin), so a model with 16
    doubles them first, not the layers; a dim medium (albedo 0.1) behind refractive
    faces is sized with 8 bins at g 0.2, so its 8 are not doubled first."""
    slab = Slab(6.4, "refractive", 1.33, n_mu=16, n_z=2)
    assert finer_order(16, slab, 0.58, 0.9)[0] == "n_theta"
    assert finer_order(16, slab, 0.5, 0.9)[0] == "n_z"
    assert finer_order(8, slab, 0.2, 0.1)[0] == "n_z"
    assert finer_order(8, slab, 0.2, 0.9)[0] == "n_theta"  # light guided: 16 bins
