"""Scene geometry objects: one spelling of the plane, and each geometry answering for its
renderer, its ρ bound, its discretisation and its model size (no type dispatch)."""

import pytest

import lightfield_jax as lfj
from lightfield_jax.forward.base import AbstractRenderer
from lightfield_jax.forward.render import geometry_renderer
from lightfield_jax.forward.simulate_config import MediumConfig
from lightfield_jax.scene.geometry import as_geometry
from lightfield_jax.scene.geometry_spec import parse_geometry

GRID = lfj.Grid(12, 8, 8, refine=1)
BEAM = lfj.Beam(0.0, 4.0)


def test_the_plane_is_spelt_once():
    assert as_geometry(None) == lfj.Plane() == parse_geometry(None)
    assert parse_geometry({"kind": "plane"}) == lfj.Plane()
    slab = lfj.Slab(4.0)
    assert as_geometry(slab) is slab
    medium = MediumConfig(0.2, 0.1, 0.4)
    config = lfj.SimulationConfig(grid=GRID, medium=medium, illumination=BEAM, geometry=None)
    assert config.geometry == lfj.Plane()
    for bad in ({"kind": "plane"}, "plane", 1.0):
        with pytest.raises(ValueError, match="geometry: must be None, a Plane or a Slab"):
            as_geometry(bad)


def test_each_geometry_gives_its_renderer_bound_and_size():
    plane, slab = lfj.Plane(), lfj.Slab(4.0, "refractive", n_mu=4, n_z=2)
    medium = lfj.Medium(0.3, 0.27, 0.7)  # phase paper: rho = omega * A(0.7) > 1 on the plane
    renderers = [
        geometry_renderer(geometry, GRID, BEAM, 2, "paper", tail="gmres")
        for geometry in (plane, slab)
    ]
    assert type(renderers[0]) is lfj.Renderer and type(renderers[1]) is lfj.SlabRenderer
    assert all(isinstance(r, AbstractRenderer) and r.tail == "gmres" for r in renderers)
    assert float(plane.rho_bound(medium)) == pytest.approx(float(medium.rho))
    assert float(slab.rho_bound(medium)) == pytest.approx(0.9)
    assert plane.phase_convention("paper") == "paper"
    assert slab.phase_convention("paper") == "normalized"
    assert plane.fields_per_bin(0.7, 0.3, 0.9) == 1
    # 4 elevation nodes × 2 layers × 2 coefficients of the linear depth profile
    assert slab.fields_per_bin(0.7, 0.3, 0.9) == 16
    assert plane.slab_or_none is None and slab.slab_or_none is slab
    grid, resolved, _ = lfj.Slab(4.0).resolve_model(medium, lfj.Grid(12, 8))
    assert grid.n_theta is not None and resolved.n_mu is not None and resolved.n_z is not None


def test_auto_is_chosen_by_a_fit_and_does_not_render():
    auto = lfj.AutoGeometry(lfj.Slab(4.0))
    assert auto.chosen_by_fit and not lfj.Plane().chosen_by_fit
    assert auto.slab_or_none is None
    with pytest.raises(ValueError, match="geometry: must be None, a Plane or a Slab"):
        geometry_renderer(auto, GRID, BEAM, 2, "paper")
