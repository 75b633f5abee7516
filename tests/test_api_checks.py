"""Hostile values given to the Python API (issue: a clear one-line error naming the
argument, the value and the allowed range, before any work; never a silent wrong
answer). Each case was accepted before (or failed deep inside), as its comment says."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lightfield_jax as lfj
from lightfield_jax.checks import number_problem


def _one_line(err: pytest.ExceptionInfo) -> str:
    text = str(err.value)
    assert "\n" not in text, text
    return text


@pytest.mark.parametrize(
    ("make", "match"),
    [
        # bool is an int to Python and "0" a number to float(): both were taken.
        (lambda: lfj.Beam(True, 3.0), "illumination.x: must be a number, got True"),
        (lambda: lfj.Beam("0", 3.0), "illumination.x: must be a number, got '0'"),
        (lambda: lfj.Beam(np.str_("0"), 3.0), "illumination.x: must be a number"),
        (lambda: lfj.Beam(0.0, 3.0, width=True), "illumination.width: must be a number"),
        (lambda: lfj.Beam(0.0, 3.0, 1e20), r"direction_deg: must be a number in \[-360, 360\]"),
        (lambda: lfj.Stripes(direction_deg=True), "illumination.direction_deg: must be a number"),
        (lambda: lfj.Stripes(direction_deg="5"), "illumination.direction_deg: must be a number"),
        (lambda: lfj.Full(direction_deg="0"), "illumination.direction_deg: must be a number"),
        # a bare int or a string of digits as the phases: a TypeError, or '0' as a phase
        (lambda: lfj.Stripes(phases=3), "illumination.phases: must be a sequence of integers"),
        (lambda: lfj.Stripes(phases="012"), "illumination.phases: must be a sequence"),
        # shifts=True made one shift; shifts past the period a phase error
        (lambda: lfj.Stripes.shifted(shifts=True), "illumination.shifts: must be a positive"),
        (lambda: lfj.Stripes.shifted(shifts=7), r"shifts: must be an integer in \[1, period\]"),
        (lambda: lfj.Medium(0.2 + 0j, 0.1, 0.3), "medium.sigma_t: must be a real number"),
        (lambda: lfj.Medium(np.ones(2) * 0.2, 0.1, 0.3), "medium.sigma_t: must be a single"),
        (lambda: lfj.Medium([0.2], 0.1, 0.3), "medium.sigma_t: must be a single number"),
        (lambda: lfj.Medium(0.2, 0.1, np.bool_(False)), "medium.g: must be a number"),
        (lambda: lfj.Medium(0.2, None, 0.3), "medium.sigma_s: must be a number, got None"),
        (lambda: lfj.Slab(5.0, n=True), "geometry.n: must be a number, got True"),
        (lambda: lfj.Slab(5.0, n="1.3"), "geometry.n: must be a number, got '1.3'"),
        (lambda: lfj.Slab(np.array([5.0])), "geometry.thickness: must be a single number"),
        (lambda: lfj.Grid(32, 24.0), r"grid.height: must be an integer >= 2, got 24.0"),
        (lambda: lfj.Grid(32, True), r"grid.height: must be an integer >= 2, got True"),
    ],
)
def test_constructors_refuse_values_that_are_not_numbers(make, match):
    with pytest.raises(ValueError, match=match) as err:
        make()
    _one_line(err)


def test_a_beam_wider_than_any_medium_is_refused():
    """Before: Beam(width=1e20) rendered all-zero images (the lit length of each wall
    cell cancelled to 0 in float64)."""
    with pytest.raises(ValueError, match=r"illumination.width: must be at most 100000 pixels"):
        lfj.Beam(0.0, 8.0, width=1e20)
    # The widest beam taken lights the whole wall, as full illumination does.
    medium, grid = lfj.Medium(0.2, 0.1, 0.3), lfj.Grid(16, 12, 8, 1)
    wide = lfj.render(medium, grid, lfj.Beam(0.0, 6.0, width=1e5), 2).images
    full = lfj.render(medium, grid, lfj.Full(), 2).images
    np.testing.assert_allclose(np.asarray(wide), np.asarray(full), rtol=1e-5)


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        # Before: True taken as 1, "no" as true, a float count or np.int64 refused or
        # taken, a string compared with an int (a bare TypeError), 'slab' accepted.
        ({"tail_max_steps": True}, "tail_max_steps: must be an integer, got True"),
        ({"correction_renders": True}, "correction_renders: must be an integer, got True"),
        ({"max_render_cells": "x"}, "max_render_cells: must be an integer, got 'x'"),
        ({"max_render_cells": 1e7 + 0.5}, "max_render_cells: must be an integer"),
        ({"crop": "no"}, "crop: must be True or False, got 'no'"),
        ({"basin_search": "no"}, "basin_search: must be True or False"),
        ({"model_error": 0}, "model_error: must be True or False"),
        ({"geometry": "slab"}, "geometry: must be None, a Plane or a Slab"),
        ({"bounces": np.ones(2)}, "bounces: must be an integer >= 1 or 'auto'"),
        ({"tail": np.ones(2)}, "tail: must be auto, None or one of"),
    ],
)
def test_fit_options_refuse_values_of_the_wrong_kind(bad, match):
    with pytest.raises(ValueError, match=match) as err:
        lfj.FitOptions(**bad)
    _one_line(err)


def test_numpy_scalars_and_ints_are_numbers():
    """What worked keeps working; np.int64 counts were refused by Stripes and
    FitOptions(tail_bounces=)."""
    assert lfj.Medium(np.float32(0.2), np.float64(0.1), 0).sigma_s == pytest.approx(0.1)
    assert lfj.Medium(jnp.asarray(0.2), np.asarray(0.1), 0.3).sigma_t == pytest.approx(0.2)
    beam = lfj.Beam(np.int64(0), np.float32(3.5), width=np.int32(2))
    assert (beam.x, beam.y, beam.width) == (0.0, 3.5, 2.0)
    stripes = lfj.Stripes(np.int64(6), np.int64(3), np.arange(6))
    assert stripes.as_dict()["period"] == 6 and type(stripes.period) is int
    assert stripes.phases == (0, 1, 2, 3, 4, 5)
    assert lfj.Stripes(direction_deg=-360.0 + 10.0).direction_deg == -350.0
    assert lfj.Slab(np.float32(5.0), n=1).n == 1.0
    assert lfj.FitOptions(tail_bounces=np.int64(8), max_steps=np.int64(5), rtol=np.float32(1e-4))
    assert lfj.FitOptions(basin_tolerance=math.inf, max_chi2=math.inf, crop=np.bool_(False))


def test_medium_values_still_differentiate_and_trace():
    def f(st, ss, g):
        return lfj.Medium(st, ss, g).rho

    grads = jax.grad(f, argnums=(0, 1, 2))(0.2, 0.1, 0.3)
    assert all(np.isfinite(float(v)) for v in grads)
    assert np.isfinite(float(jax.jit(f)(0.2, 0.1, 0.3)))


def test_a_sigma_s_that_underflows_float32_is_refused():
    """Before: sigma_s = 1e-45 became a subnormal float32, flushed to zero on the
    device: all-zero images from a medium that scatters."""
    with jax.enable_x64(False):
        with pytest.raises(ValueError, match="medium.sigma_s: 1e-45 underflows float32"):
            lfj.Medium(0.2, 1e-45, 0.3)
        assert float(lfj.Medium(0.2, 0.0, 0.3).sigma_s) == 0.0


def test_number_problem_names_what_is_wrong():
    assert number_problem(np.float32(0.5), low=0, high=1) is None
    assert number_problem(2, integer=True, low=1, high=3) is None
    assert number_problem(math.inf, allow_inf=True) is None
    assert number_problem(math.inf) == "must be finite, got inf"
    assert number_problem(math.nan, allow_inf=True) == "must be a number, got nan"
    assert number_problem(0.0, low=0, low_open=True, unit=" px") == (
        "must be a number > 0 px, got 0.0"
    )
    assert number_problem(9, integer=True, low=1, high=8) == ("must be an integer in [1, 8], got 9")
    assert number_problem(np.zeros((1000, 1000))) == (
        "must be a single number, got an array of shape (1000, 1000)"
    )
