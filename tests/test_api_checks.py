"""Hostile values given to the Python API (issue: a clear one-line error naming the
argument, the value and the allowed range, before any work; never a silent wrong
answer). Each case was accepted before (or failed deep inside), as its comment says."""

import dataclasses
import math
import re

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
        # separate took "0.5" as 0.5 and False as a black level of 0
        (
            lambda: lfj.separate(np.ones((3, 4, 4)), lit_fraction="0.5"),
            "separate.lit_fraction: must be a number, got '0.5'",
        ),
        (
            lambda: lfj.separate(np.ones((3, 4, 4)), black_level=False),
            "separate.black_level: must be a number, got False",
        ),
        # an AutoGeometry took any slab and threshold
        (lambda: lfj.AutoGeometry("slab"), "geometry.slab: must be a Slab"),
        (lambda: lfj.AutoGeometry(lfj.Slab(5.0), threshold=True), "geometry.threshold: must be a"),
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
    # Before: width 1e-20 rendered all-zero images (the lit length and the float32 images).
    for narrow in (1e-20, 1e-7):
        with pytest.raises(ValueError, match=r"illumination.width: must be at least 1e-06 pixels"):
            lfj.Beam(0.0, 8.0, width=narrow)
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
        ({"coarse_after": 1}, r"coarse_after: must be an integer in \[2, 10000\]"),
        ({"coarse_after": 8.5}, "coarse_after: must be an integer"),
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
    assert number_problem(math.nan, allow_inf=True) == "must be finite, got nan"
    assert number_problem(0.0, low=0, low_open=True, unit=" px") == (
        "must be a number > 0 px, got 0.0"
    )
    assert number_problem(9, integer=True, low=1, high=8) == ("must be an integer in [1, 8], got 9")
    assert number_problem(np.zeros((1000, 1000))) == (
        "must be a single number, got an array of shape (1000, 1000)"
    )


def test_a_gain_that_underflows_the_images_is_refused():
    """Before: render(gain=1e-40) and a simulation with gain 1e-40 gave all-zero images
    (float32 flushes them to zero), silently; a SimulationConfig made in code took a
    black level of 5 (negative images) and a string gain."""
    medium, grid = lfj.Medium(0.2, 0.1, 0.3), lfj.Grid(16, 12, 8, 1)
    with pytest.raises(ValueError, match=r"render: gain: must be a number in \[1e-30, 1e\+30\]"):
        lfj.render(medium, grid, lfj.Stripes(), 2, gain=1e-40)
    assert np.asarray(lfj.render(medium, grid, lfj.Full(), 2, gain=1e-30).images).max() > 0
    config = {
        "grid": {"width": 16, "height": 12, "n_theta": 8, "refine": 1},
        "medium": {"sigma_t": 0.2, "sigma_s": 0.1, "g": 0.3, "phase": "paper"},
        "illumination": {"kind": "stripes", "period": 6, "lit": 3},
        "bounces": 2,
    }
    from lightfield_jax.forward.simulate_config import MediumConfig, parse_simulation_config
    from lightfield_jax.schema import ConfigError

    with pytest.raises(ConfigError, match=r"gain: must be a number in \[1e-30, 1e\+30\]"):
        parse_simulation_config({**config, "gain": 1e-40})
    good = parse_simulation_config(config)
    for change, match in [
        ({"gain": 1e-40}, r"gain: must be a number in \[1e-30"),
        ({"gain": "2"}, r"gain: must be a number in \[1e-30"),
        ({"black_level": 5.0}, r"black_level: must be a number in \[0, 1\), got 5.0"),
        ({"dark_level": -1.0}, r"dark_level: must be a number in \[0, 1e\+30\]"),
        ({"bounces": True}, "bounces: must be an integer, got True"),
        ({"tolerance": 0.0}, r"tolerance: must be a number in \(0, 1\)"),
        ({"grid": (16, 12)}, "grid: must be a Grid"),
        ({"medium": lfj.Medium(0.2, 0.1, 0.3)}, "medium: must be a MediumConfig"),
        ({"illumination": "stripes"}, "illumination: must be a Beam or Stripes or Full"),
    ]:
        with pytest.raises(ValueError, match=match) as err:
            lfj.simulate_capture(dataclasses.replace(good, **change))
        _one_line(err)
    with pytest.raises(ValueError, match="medium.sigma_t: must be a number, got '0.2'"):
        MediumConfig("0.2", 0.1, 0.3)
    # Before: a bare TypeError of os.fspath, light fields for lightfield="no", a
    # TypeError at the first stage.
    for kwargs, match in [
        ({"config": 5}, "simulate_capture: config: must be a SimulationConfig or the path"),
        ({"lightfield": "no"}, "simulate_capture: lightfield: must be True or False"),
        ({"stage": 3}, "simulate_capture: stage: must be callable, got int"),
    ]:
        with pytest.raises(ValueError, match=match) as err:
            lfj.simulate_capture(**{"config": good, **kwargs})
        _one_line(err)


# ------------------------------------------------------------------------- figures


@pytest.fixture(scope="module")
def small():
    medium, grid = lfj.Medium(0.2, 0.1, 0.3), lfj.Grid(16, 12, 8, 1)
    return lfj.render(medium, grid, lfj.Full(), 3, lightfield=True)


def _viz_cases(small, tmp_path):
    import lightfield_jax.viz as viz

    images = np.asarray(small.images)
    fields = np.asarray(small.lightfields)
    fit = lfj.fit_decay(images[0])
    nan = images.copy()
    nan[1, 2, 3] = np.nan
    return [
        # Before: 7.7e8 glyphs (minutes, then memory).
        (
            lambda: viz.plot_lightfield(small, spacing=1e-3),
            r"plot_lightfield.spacing: must be a number in \[1, 16\] px",
        ),
        (
            lambda: viz.plot_lightfield(small, spacing=math.nan),
            "plot_lightfield.spacing: must be finite, got nan",
        ),
        (
            lambda: viz.plot_lightfield(small, glyph_radius=-1.0),
            "plot_lightfield.glyph_radius: must be a number in",
        ),
        # points off the panel wrapped round to the other side (negative indices)
        (
            lambda: viz.plot_lightfield(small, points=[(-5.0, -5.0)]),
            "plot_lightfield.points: must lie on the 16x12 panel",
        ),
        (
            lambda: viz.plot_lightfield(small, points=[(math.nan, 1.0)]),
            "plot_lightfield.points: must be finite",
        ),
        (
            lambda: viz.plot_lightfield(small, points=np.ones((5000, 2))),
            "plot_lightfield.points: must be at most 1024",
        ),
        (
            lambda: viz.plot_lightfield(small, show=-1),
            "plot_lightfield.show: must be an integer >= 0, got -1",
        ),
        (
            lambda: viz.plot_lightfield(small, columns=0),
            r"plot_lightfield.columns: must be an integer in \[1, 48\]",
        ),
        (
            lambda: viz.plot_lightfield(small, labels="abcde"),
            "plot_lightfield.labels: must be a list of 5 titles",
        ),
        (lambda: viz.plot_lightfield(np.ones((100, 12, 16, 8))), "plot_lightfield: 100 panels"),
        (
            lambda: viz.plot_lightfield(fields[:, :0]),
            "plot_lightfield.lightfield: must not be empty",
        ),
        (
            lambda: viz.plot_lightfield(fields > 0),
            "plot_lightfield.lightfield: must be an array of real numbers",
        ),
        (
            lambda: viz.plot_lightfield(small, dynamic_range=0.0),
            "plot_lightfield.dynamic_range: must be a number > 1",
        ),
        (
            lambda: viz.plot_lightfield(small, glyph_scale=None),
            "plot_lightfield.glyph_scale: must be 'local' or 'global'",
        ),
        # show=-1 silently dropped the last bounce, show=0 drew the sum alone
        (
            lambda: viz.plot_bounce_images(small, show=-1),
            "plot_bounce_images.show: must be an integer >= 1",
        ),
        (
            lambda: viz.plot_bounce_images(small, show=True),
            "plot_bounce_images.show: must be an integer, got True",
        ),
        (
            lambda: viz.plot_bounce_images(nan),
            "plot_bounce_images.images: must be finite, got 1 of 576",
        ),
        (lambda: viz.plot_bounce_images(np.ones((100, 12, 16))), "plot_bounce_images: 101 panels"),
        (
            lambda: viz.plot_bounce_images(images, total="no"),
            "plot_bounce_images.total: must be True or False",
        ),
        (
            lambda: viz.plot_bounce_images(fit),
            "plot_bounce_images.images: must be an array of real numbers .* got DecayFit",
        ),
        (
            lambda: viz.plot_bounce_images(images, illumination="full"),
            "plot_bounce_images.illumination: must be a Beam",
        ),
        # bin_width 1e-9: a profile of 1e10 bins (memory); the NaN range drew nothing
        (
            lambda: viz.plot_bounce_profiles(small, bin_width=1e-9),
            "plot_bounce_profiles.bin_width: must be a number >= 0.01 px",
        ),
        (
            lambda: viz.plot_bounce_profiles(small, dynamic_range=math.nan),
            "plot_bounce_profiles.dynamic_range: must be finite, got nan",
        ),
        (
            lambda: viz.plot_bounce_profiles(images[0]),
            r"plot_bounce_profiles.images: must have 3 dimensions",
        ),
        (
            lambda: viz.plot_bounce_profiles(images, mask=np.ones((12, 16))),
            "mask: must be a boolean array",
        ),
        # a KeyError, a numpy broadcast error, an AttributeError before
        (
            lambda: viz.plot_direct_decay(images[0], fit, entry="west"),
            "plot_direct_decay.entry: must be one of",
        ),
        (
            lambda: viz.plot_direct_decay(images[0], fit, unseparated=images[0, :5]),
            r"plot_direct_decay.unseparated: must have the direct image's shape \(12, 16\)",
        ),
        (
            lambda: viz.plot_direct_decay(images[0], small),
            "plot_direct_decay.fit: must be a DecayFit",
        ),
        (
            lambda: viz.plot_direct_decay(np.full((12, 16), np.nan), fit),
            "plot_direct_decay.direct: has no finite value",
        ),
        (
            lambda: viz.plot_direct_decay(images[0], fit, direction_deg=90.0),
            "plot_direct_decay.direction_deg: 90.0 degrees does not point into",
        ),
        (
            lambda: viz.plot_direct_decay(images[0], fit, true_sigma_t="0.2"),
            "plot_direct_decay.true_sigma_t: must be a number",
        ),
        (
            lambda: viz.plot_direct_decay(images[0], fit, path=5),
            "plot_direct_decay.path: must be a file path or None, got 5",
        ),
        (
            lambda: viz.plot_transport(images, tmp_path),
            "plot_transport.result: must be a RenderResult",
        ),
        (
            lambda: viz.plot_transport(small, tmp_path / "missing"),
            "plot_transport.folder: must be an existing folder",
        ),
        (lambda: viz.plot_channels(small), "plot_channels.fit: must be a CaptureFit"),
        (lambda: viz.plot_inspect(str(tmp_path)), "plot_inspect.inspection: must be an Inspection"),
        (
            lambda: viz.plot_fit(images, lfj.Stripes(), small),
            "plot_fit.result: must be a FitResult",
        ),
        (lambda: viz.plot_fit(images, "stripes", small), "plot_fit.pattern: must be a Stripes"),
        (
            lambda: viz.light_path_coordinates((12,)),
            r"light_path_coordinates.shape: must be \(height, width\)",
        ),
    ]


def test_figures_check_their_arguments_before_drawing(small, tmp_path):
    import time

    for make, match in _viz_cases(small, tmp_path):
        start = time.perf_counter()
        with pytest.raises(ValueError, match=match) as err:
            make()
        _one_line(err)
        assert time.perf_counter() - start < 2.0, match


def test_figures_still_draw_valid_arguments(small, tmp_path):
    import lightfield_jax.viz as viz

    figure = viz.plot_lightfield(small, spacing=2, glyph_radius=1.0, points=None, show=0)
    assert len([ax for ax in figure.axes if ax.get_title()]) == 2
    figure = viz.plot_lightfield(np.asarray(small.lightfields)[1], points=np.array([[1.0, 2.0]]))
    assert figure.axes
    assert viz.plot_bounce_images(small, show=10, columns=np.int64(2)).axes
    assert viz.plot_bounce_profiles(np.asarray(small.images), bin_width=np.float32(0.5)).axes
    files = viz.plot_transport(small, str(tmp_path), illumination=lfj.Full())
    assert len(files) == 3


def test_render_refuses_sizes_from_a_typo_before_the_work(monkeypatch):
    """Before: Grid(32000, 24000) went on to build the renderer's tables (a MemoryError
    or the OOM killer, minutes later), bounces=10**6 marched for many minutes and a
    string illumination failed deep inside."""
    import time

    from lightfield_jax.runtime.memory import MAX_MEMORY_ENV

    monkeypatch.setenv(MAX_MEMORY_ENV, "4G")
    medium = lfj.Medium(0.2, 0.1, 0.3)
    start = time.perf_counter()
    with pytest.raises(ValueError, match=r"render: the 32000x24000 grid .* needs about 5.7 TiB"):
        lfj.render(medium, lfj.Grid(32000, 24000, 16, 1), lfj.Stripes(), 3)
    with pytest.raises(ValueError, match="bounces: at most 10000 bounces are marched"):
        lfj.render(medium, lfj.Grid(16, 12, 8, 1), lfj.Full(), 10**6)
    with pytest.raises(ValueError, match="render: illumination: must be a Beam, Stripes or Full"):
        lfj.render(medium, lfj.Grid(16, 12, 8, 1), "full", 3)
    assert time.perf_counter() - start < 5.0


def test_render_and_its_helpers_name_arguments_of_the_wrong_kind():
    """Before: a FitResult or a tuple as the medium/grid failed deep inside (an
    AttributeError), lightfield="no" rendered light fields (a truthy string), a string
    tolerance or a NaN rho a bare TypeError/ValueError of Python, a NumPy tail_tol was
    refused, single_scatter_closed_form(width=True) drew one column and
    default_n_theta("0.5") took the string."""
    medium, grid = lfj.Medium(0.2, 0.1, 0.3), lfj.Grid(16, 12, 8, 1)
    for kwargs, match in [
        ({"medium": (0.2, 0.1, 0.3)}, "render: medium: must be a Medium, got tuple"),
        ({"grid": (16, 12)}, "render: grid: must be a Grid, got tuple"),
        ({"lightfield": "no"}, "render: lightfield: must be True or False, got 'no'"),
        ({"tolerance": "1e-4"}, r"render: tolerance: must be a number, got '1e-4'"),
        ({"tail": "gmress"}, "tail: must be None or one of gmres, bicgstab"),
        ({"tail": "gmres", "tail_tol": math.nan}, r"tail_tol: must be a number in \(0, 1\)"),
    ]:
        args = {"medium": medium, "grid": grid, "illumination": lfj.Full(), "bounces": 2}
        with pytest.raises(ValueError, match=match) as err:
            lfj.render(**{**args, **kwargs})
        _one_line(err)
    result = lfj.render(
        medium,
        grid,
        lfj.Full(),
        2,
        tail="gmres",
        tail_tol=np.float32(1e-4),
        tail_max_steps=np.int64(50),
    )
    assert result.tail is not None
    for call, match in [
        (lambda: lfj.single_scatter_closed_form(0.2, 0.1, 0.3, True), "width: must be an integer"),
        (
            lambda: lfj.single_scatter_closed_form(0.2, 0.3, 0.3, 8),
            r"sigma_s: must be a number in \[0, 0.2\]",
        ),
        (lambda: lfj.default_n_theta("0.5"), "g: must be a number, got '0.5'"),
        (lambda: lfj.default_refine(1.5), r"g: must be a number in \(-1, 1\), got 1.5"),
        (lambda: lfj.bounces_for_tolerance(math.nan), "rho: must be finite, got nan"),
        (lambda: lfj.bounces_for_tolerance(0.5, "0.1"), r"bounce tolerance must be in \(0, 1\)"),
        (lambda: lfj.Medium(0.2, 0.1, 0.3, phase=np.array(["paper"])), "medium.phase: unknown"),
    ]:
        with pytest.raises(ValueError, match=match) as err:
            call()
        _one_line(err)
    assert lfj.single_scatter_closed_form(np.float32(0.2), 0.1, 0, np.int64(8)).shape == (8,)


def test_phase_function_refuses_g_outside_minus_one_to_one():
    """Before: phase_function(θ, 1.0) gave 0 everywhere, g = 1.5 a negative p(θ), g =
    True was taken as 1 (finite nonsense, no error)."""
    for g, got in ((1.0, "1.0"), (-1.5, "-1.5"), (math.nan, "nan"), (jnp.asarray(2.0), "2.0")):
        with pytest.raises(
            ValueError, match=rf"phase_function: g: must satisfy -1 < g < 1, got {got}$"
        ) as err:
            lfj.phase_function(0.3, g)
        _one_line(err)
    with pytest.raises(ValueError, match="got 1 of 2 values outside, e.g. 1.2") as err:
        lfj.phase_function(0.3, np.array([0.2, 1.2]))
    _one_line(err)
    with pytest.raises(ValueError, match="phase_function: g: must be a real number, got True"):
        lfj.phase_function(0.3, True)
    with pytest.raises(ValueError, match="phase_integral: g: must satisfy -1 < g < 1, got 1.0"):
        lfj.phase_integral(1.0)
    # Tracers pass unchecked: jit, grad and vmap still work.
    p = (1 - 0.16) / (4 * math.pi * (1 + 0.16 - 0.8 * math.cos(0.3)) ** 1.5)
    assert float(jax.jit(lambda g: lfj.phase_function(0.3, g))(0.4)) == pytest.approx(p)
    slope = jax.jit(jax.grad(lambda g: lfj.phase_function(0.3, g)))(0.4)
    assert math.isfinite(float(slope)) and float(slope) > 0
    both = jax.jit(jax.vmap(lambda g: lfj.phase_function(0.3, g)))(jnp.array([0.4, -0.9]))
    assert float(both[0]) == pytest.approx(p)


def test_fit_images_refuses_stripes_longer_than_the_images():
    """Before: render refused them, but fit_images fitted 32x24 images of period-40
    stripes for 31 s (shifts that light no row) and ended "not trustworthy"."""
    stripes = lfj.Stripes(period=60, lit=3, phases=(0, 15, 30, 45))
    images = np.ones((4, 36, 48), np.float32)
    message = "60 rows is longer than the 48x36 images: a stripe period is a few rows"
    with pytest.raises(ValueError, match=f"^pattern.period: {message}$") as err:
        lfj.fit_images(images, stripes)
    _one_line(err)


def test_stripes_longer_than_the_grid_are_refused_by_the_api():
    """Before: only a simulate config refused them; render drew all-zero images for the
    shifts whose stripe missed the 16x12 grid, and a SimulationConfig made in code
    simulated them."""
    from lightfield_jax.forward.simulate_config import SimulationConfig, parse_simulation_config

    medium, grid = lfj.Medium(0.2, 0.03, 0.4), lfj.Grid(16, 12, 8, 1)
    stripes = lfj.Stripes(period=40, lit=3, phases=(0, 10, 20, 30))
    message = "40 rows is longer than the 16x12 grid: a stripe period is a few rows"
    with pytest.raises(ValueError, match=f"^render: illumination.period: {message}$") as err:
        lfj.render(medium, grid, stripes, 2)
    _one_line(err)
    config = parse_simulation_config(
        {
            "grid": {"width": 16, "height": 12},
            "medium": {"sigma_t": 0.2, "sigma_s": 0.03, "g": 0.4, "phase": "paper"},
            "illumination": {"kind": "stripes", "period": 6},
        }
    )
    assert isinstance(config, SimulationConfig)
    with pytest.raises(ValueError, match=f"^illumination.period: {message}$"):
        dataclasses.replace(config, illumination=stripes)
    with pytest.raises(ValueError, match=f"illumination.period: {message}$"):
        parse_simulation_config({**config.raw, "illumination": {"kind": "stripes", "period": 40}})
    # A period as long as the grid's longer side still renders.
    full = lfj.Stripes(period=16, lit=3, phases=(0,))
    assert np.asarray(lfj.render(medium, grid, full, 1).images).shape == (1, 1, 12, 16)


def test_the_albedo_error_of_a_fit_with_sigma_s_0_is_finite():
    # to_dict() of a fit at sigma_s = 0 (e.g. a grid search of negated images) raised
    # ZeroDivisionError in the albedo's error; at sigma_t = 0 it is NaN.
    from lightfield_jax.inverse.options import FitResult

    fit = FitResult(
        method="grid", sigma_t=0.2, sigma_s=0.0, g=0.0, gain=1.0, black_level=0.0,
        uncertainty={"sigma_t": 0.01, "sigma_s": 0.004}, correlation={}, converged=False,
        message="", iterations=1, residual=0.0, seconds={"total": 0.0}, model={},
    )  # fmt: skip
    d = fit.to_dict()
    assert d["albedo"] == 0.0
    assert d["uncertainty"]["albedo"] == pytest.approx(0.004 / 0.2)
    nothing = dataclasses.replace(fit, sigma_t=0.0)
    assert math.isnan(nothing.albedo)
    assert nothing.to_dict()["uncertainty"]["albedo"] is None or math.isnan(
        nothing.to_dict()["uncertainty"]["albedo"]
    )


def test_a_masked_arrays_mask_is_honoured_by_fit_images(monkeypatch):
    # Before: np.asarray dropped the mask, and the masked (hot) pixels entered the fit.
    import lightfield_jax.inverse.fit as fit_module

    seen = {}
    monkeypatch.setattr(fit_module, "fit_one", lambda images, *a, mask, **k: seen.update(
        images=images, mask=mask))  # fmt: skip
    images = np.ones((3, 4, 5))
    bad = np.zeros(images.shape, bool)
    bad[1, 2, 3] = True
    pattern = lfj.Stripes(6, 3, (0, 2, 4))
    lfj.fit_images(np.ma.masked_array(images, mask=bad), pattern)
    assert type(seen["images"]) is np.ndarray and (seen["mask"] == ~bad).all()
    pixels = np.ones((4, 5), bool)
    pixels[0, 0] = False
    lfj.fit_images(np.ma.masked_array(images, mask=bad), pattern, mask=pixels)
    assert seen["mask"].shape == images.shape
    assert (seen["mask"] == (~bad & pixels)).all()
    lfj.fit_images(images, pattern, mask=pixels)  # a plain array: as given
    assert seen["mask"] is pixels
    # A 0/1 mask (not bool) is combined too: before, the masked array's mask was dropped.
    lfj.fit_images(np.ma.masked_array(images, mask=bad), pattern, mask=pixels.astype(int))
    assert (seen["mask"] == (~bad & pixels)).all()


def test_separate_and_fit_decay_skip_a_masked_arrays_masked_values():
    images = np.stack([np.full((4, 5), v) for v in (1.0, 3.0)])
    bad = np.zeros(images.shape, bool)
    bad[0, 1, 2] = True
    images[0, 1, 2] = -100.0  # a dead pixel, masked
    sep = lfj.separate(np.ma.masked_array(images, mask=bad))
    direct = np.asarray(sep.direct)
    assert np.isnan(direct[1, 2]) and np.isfinite(np.delete(direct.ravel(), 7)).all()
    from lightfield_jax.checks import masked_to_nan

    assert np.isnan(masked_to_nan(np.ma.masked_array(np.arange(3), mask=[0, 1, 0]))[1])


def _decaying_stripes(pattern, height=12, width=32) -> np.ndarray:
    """Noise-free stripe images: a direct light decaying at σt 0.2 per px under the lit
    rows (row y lit in phase p where (y + p) mod period < lit, as Stripes renders),
    plus a smooth multiple light."""
    x, y = np.arange(width) + 0.5, np.arange(height)[:, None]
    lit = [((y + p) % pattern.period) < pattern.lit for p in pattern.phases]
    return np.stack([np.exp(-0.2 * x) * on + 0.05 * np.exp(-0.1 * x) for on in lit])


def test_masked_exposure_and_split_values_are_not_used():
    # Before: np.asarray dropped their masks, and the fill values entered the fit (a
    # masked T's fill as the exposure, a masked direct value as the direct light).
    from lightfield_jax.inverse.data import prepare_data

    pattern = lfj.Stripes()
    images = _decaying_stripes(pattern)
    out = np.zeros(images.shape, bool)
    out[2, 3, 4] = True
    exposure = np.ma.masked_array(np.where(out, 50.0, 2.0), mask=out)
    data = prepare_data(images, pattern, exposure=exposure)
    assert not data.samples[2, 3, 4] and data.samples.sum() == images.size - 1
    assert not data.mask[3, 4] and np.isfinite(data.exposure).all()
    assert (data.exposure[~out] == 2.0).all()
    with pytest.raises(ValueError, match="^exposure: must be finite and > 0 .* not masked$"):
        prepare_data(images, pattern, exposure=np.ma.masked_array(-exposure.data, mask=out))
    direct, multiple = data.direct, data.multiple
    hot = np.zeros(direct.shape, bool)
    hot[5, 6] = True
    for split in (
        (np.ma.masked_array(np.where(hot, 1e6, direct), mask=hot), multiple),
        np.ma.masked_array(np.stack([direct, np.where(hot, -1e6, multiple)]), mask=[hot, hot]),
    ):
        given = prepare_data(images, pattern, split=split)
        assert not given.mask[5, 6] and given.mask.sum() == hot.size - 1
        assert given.direct[5, 6] == 0 and abs(given.direct).max() < 2
        assert given.sigma_t0 == pytest.approx(0.2, rel=1e-3)
    with pytest.raises(ValueError, match=r"^split: must be a pair \(direct, multiple\) .*"):
        prepare_data(images, pattern, split=(direct,))


def test_render_under_a_transformation_names_the_traced_value():
    """Before: render, Beam, Slab or Full given values traced by jax.jit, grad or vmap
    failed inside with JAX's many-line ConcretizationTypeError (float() of a tracer)."""
    grid = lfj.Grid(16, 12, 8, 1)

    def total(sigma_t):
        return lfj.render(lfj.Medium(sigma_t, 0.05, 0.4), grid, lfj.Full(), 2).images.sum()

    for transform in (jax.jit, jax.grad, jax.vmap):
        with pytest.raises(ValueError, match="render: medium.sigma_t: got a traced value") as err:
            transform(total)(jnp.asarray([0.2]) if transform is jax.vmap else 0.2)
        assert "lfj.make_renderer" in _one_line(err)
    for make, match in [
        (lambda y: lfj.Beam(0.0, y), "illumination.y: must be a number, got a traced value"),
        (
            lambda d: lfj.Full(direction_deg=d),
            "illumination.direction_deg: must be a number, got a",
        ),
        (lambda t: lfj.Slab(t), "geometry.thickness: must be a number, got a traced value"),
    ]:
        with pytest.raises(ValueError, match=match) as err:
            jax.jit(make)(5.0)
        _one_line(err)
    # The transformable path: the renderer, whose values are traced.
    renderer = lfj.make_renderer(grid, lfj.Full(), 2, "paper", None)
    slope = jax.grad(lambda st: renderer(st, 0.05, 0.4, 1.0)[0].sum())(0.2)
    assert math.isfinite(float(slope))


def test_make_renderer_checks_its_arguments_before_the_tables(monkeypatch):
    """Before: make_renderer(Grid(30000, 30000, 8, 1), ...) tried to allocate 429 GiB (a
    MemoryError from numpy), a string illumination or a tuple grid failed in an
    AttributeError, and stripes longer than the grid were rendered (all-zero shifts)."""
    from lightfield_jax.runtime.memory import MAX_MEMORY_ENV

    monkeypatch.setenv(MAX_MEMORY_ENV, "4G")
    grid = lfj.Grid(16, 12, 8, 1)
    for args, match in [
        ((lfj.Grid(30000, 30000, 8, 1), lfj.Full()), r"make_renderer: the 30000x30000 grid .*"),
        (((16, 12), lfj.Full()), "make_renderer: grid: must be a Grid, got tuple"),
        ((grid, "full"), "make_renderer: illumination: must be a Beam, Stripes or Full, got str"),
        (
            (grid, lfj.Stripes(period=40, lit=3, phases=(0, 10))),
            "make_renderer: illumination.period: 40 rows is longer than the 16x12 grid",
        ),
    ]:
        with pytest.raises(ValueError, match=match) as err:
            lfj.make_renderer(*args, 2, "paper", None)
        _one_line(err)
    slab = lfj.Slab(4.0, n_mu=4, n_z=2)
    images, _ = lfj.make_renderer(grid, lfj.Full(), np.int64(2), "paper", slab)(0.2, 0.1, 0.3, 1.0)
    assert np.asarray(images).shape == (1, 2, 12, 16)


def test_compiled_programs_are_forgotten_before_the_memory_maps_run_out(monkeypatch):
    """Before: a process that compiled programs until the kernel's memory-map limit was
    near (the whole test suite in one process) crashed in XLA's compiler. A fit first
    forgets the compiled programs where more than half the limit is in use."""
    from lightfield_jax.inverse import programs

    square = jax.jit(lambda x: x * x)
    square(jnp.ones(3))
    assert square._cache_size() == 1
    monkeypatch.setattr(programs, "memory_maps", lambda: (1000, 65530))
    assert not programs.forget_if_crowded() and square._cache_size() == 1
    said = []
    monkeypatch.setattr(programs, "memory_maps", lambda: (40000, 65530))
    assert programs.forget_if_crowded(said.append) and square._cache_size() == 0
    assert said == [
        "compiled programs forgotten (they held 40000 of the system's 65530 memory maps): "
        "this fit compiles its own again"
    ]
    monkeypatch.setattr(programs, "memory_maps", lambda: (0, 0))  # not Linux: nothing
    square(jnp.ones(3))
    assert not programs.forget_if_crowded() and square._cache_size() == 1
    monkeypatch.undo()
    used, limit = programs.memory_maps()  # this machine's own count and limit
    assert (used, limit) == (0, 0) or 0 < used < limit


def test_enable_compilation_cache_names_a_path_that_is_not_one(tmp_path, monkeypatch):
    """Before: "" cached every program into the current folder, silently; None, bytes
    or 5 raised Python's bare TypeError and a NUL 'embedded null byte', naming no
    argument."""
    monkeypatch.chdir(tmp_path)
    for path in ("", "  ", None, 5, b"/tmp/x", "a\0b"):
        with pytest.raises(ValueError, match="enable_compilation_cache: path: must be a") as err:
            lfj.enable_compilation_cache(path)
        _one_line(err)
    assert list(tmp_path.iterdir()) == []


def test_fit_options_of_another_type_are_named():
    """Before: fit_images(options={"max_steps": 3}) ended in dataclasses' bare
    'replace() should be called on dataclass instances', options={} or 0 was taken as
    the defaults, and fit_capture alike."""
    images = np.ones((6, 8, 16))
    for options in ({"max_steps": 3}, {}, 0, "joint"):
        with pytest.raises(ValueError, match="fit_images: options: must be a FitOptions or None"):
            lfj.fit_images(images, lfj.Stripes(), options=options)
        with pytest.raises(ValueError, match="fit_capture: options: must be a FitOptions or None"):
            lfj.fit_capture(object(), options=options)


def test_fit_images_names_its_own_black_level():
    """Before: 'separate.black_level: must be in [0, 1), got nan', the helper's name."""
    images = np.ones((6, 8, 16))
    for black, got in ((math.nan, "must be finite, got nan"), (1.0, "got 1.0"), (-1e-5, "-1e-05")):
        with pytest.raises(ValueError, match=f"^fit_images: black_level: .*{got}") as err:
            lfj.fit_images(images, lfj.Stripes(), black_level=black)
        _one_line(err)


def test_separate_and_fit_decay_refuse_values_that_are_not_intensities():
    """Before: separate() took complex images (their real part, a ComplexWarning) and
    bool or object ones, and fit_decay() fitted a bool image (True as 1); fit_images
    refused them."""
    for images in (np.ones((3, 4, 4), complex), np.ones((3, 4, 4), bool)):
        with pytest.raises(ValueError, match="^separate.images: must be real numbers, got"):
            lfj.separate(images)
    with pytest.raises(ValueError, match="^separate.dark_frame: must be real numbers, got dtype"):
        lfj.separate(np.ones((3, 4, 4)), dark_frame=np.ones((4, 4), bool))
    with pytest.raises(ValueError, match="^fit_decay.direct: must be real numbers, got dtype bool"):
        lfj.fit_decay(np.ones((24, 32), bool))
    assert lfj.separate(np.ones((3, 4, 4), np.uint16)).direct.shape == (4, 4)


def test_a_renderer_refuses_concrete_values_no_medium_has():
    """Before: make_renderer(...)(0.2, 0.3, 0.4) (sigma_s > sigma_t) rendered, g = 1 or
    a NaN sigma_t gave NaN images and gain -1 negative ones, silently; '0.2' or None
    ended in JAX's own message. Traced values still pass (jit, grad, vmap)."""
    renderer = lfj.make_renderer(lfj.Grid(16, 12, 8, 1), lfj.Full(), 2, "paper", None)
    for args, match in [
        ((0.2, 0.3, 0.4), r"renderer: medium.sigma_s: must satisfy 0 <= sigma_s <= sigma_t"),
        ((0.2, 0.05, 1.0), "renderer: medium.g: must satisfy -1 < g < 1, got 1.0"),
        ((math.nan, 0.05, 0.4), "renderer: medium.sigma_t: must be finite, got nan"),
        (("0.2", 0.05, 0.4), "renderer: medium.sigma_t: must be a number, got '0.2'"),
        ((0.2, 0.05, 0.4, -1.0), "renderer: gain: must be a number > 0, got -1.0"),
        ((0.2, 0.05, 0.4, None), "renderer: gain: must be a number, got None"),
    ]:
        with pytest.raises(ValueError, match=match) as err:
            renderer(*args)
        _one_line(err)
    batch = jax.vmap(lambda st: renderer(st, 0.05, 0.4, 1.0)[0].sum())(jnp.array([0.2, 0.3]))
    assert np.all(np.isfinite(np.asarray(batch)))


def test_a_grid_of_very_many_directions_is_refused_by_its_memory(monkeypatch):
    """Before: Grid(2, 2, 80000) passed the memory check (its fields are small) and the
    renderer's n_theta x n_theta direction table ended in a MemoryError (47.7 GiB)
    after 11 s; FitOptions(n_theta=80000) in a fit, after 47 s."""
    from lightfield_jax.runtime.memory import MAX_MEMORY_ENV

    monkeypatch.setenv(MAX_MEMORY_ENV, "256M")
    grid = lfj.Grid(2, 2, 4096, 1)  # the most bins a grid takes: 400 MB of tables
    with pytest.raises(ValueError, match=r"render: the 2x2 grid \(4096 directions.* needs about"):
        lfj.render(lfj.Medium(0.2, 0.1, 0.3), grid, lfj.Full(), 2)
    with pytest.raises(ValueError, match=r"make_renderer: the 2x2 grid \(4096 directions"):
        lfj.make_renderer(grid, lfj.Full(), 2, "paper", None)
    # More are refused by the grid and the fit's options, before any work.
    limit = r"n_theta: must be at most 4096 direction bins"
    with pytest.raises(ValueError, match=f"^grid.{limit}"):
        lfj.Grid(2, 2, 8 * 10**4, 1)
    with pytest.raises(ValueError, match=f"^{limit}"):
        lfj.FitOptions(n_theta=8 * 10**4)


def test_a_python_int_beyond_float64_is_named_not_an_overflow():
    """Before: Medium(10**400, ...), render(gain=10**400) and FitOptions(basin_tolerance=
    10**400) raised a bare 'OverflowError: int too large to convert to float', naming
    neither the argument nor the range."""
    huge = 10**400
    assert number_problem(huge, low=0, high=1).startswith("must be a number in [0, 1], got 1")
    for make, match in [
        (lambda: lfj.Medium(huge, 0.1, 0.3), "medium.sigma_t: must be a number of magnitude at"),
        (lambda: lfj.Medium(0.2, 0.1, -huge), "medium.g: must be a number of magnitude at most"),
        (lambda: lfj.FitOptions(basin_tolerance=huge), "basin_tolerance: must be a number of"),
        (
            lambda: lfj.render(lfj.Medium(0.2, 0.1, 0.3), lfj.Grid(16, 12, 8, 1), lfj.Full(), 2,
                               gain=huge),
            r"render: gain: must be a number in \[1e-30, 1e\+30\]",
        ),
    ]:  # fmt: skip
        with pytest.raises(ValueError, match=match) as err:
            make()
        _one_line(err)


def test_images_of_different_shapes_in_one_list_are_named():
    """Before: a list of shifted images of two sizes ended in numpy's 'setting an array
    element with a sequence ... inhomogeneous shape', naming no argument."""
    images = [np.ones((24, 32))] * 5 + [np.ones((24, 30))]
    with pytest.raises(ValueError, match=r"^images: must be an array \(6, height, width\)"):
        lfj.fit_images(images, lfj.Stripes())


def test_a_mask_of_values_that_are_not_flags_is_refused():
    """Before: a mask of NaN (or of 2s, or of strings) was taken as all true and the fit
    ran on every pixel; an object array of None as all false ('no pixel is valid ... by
    mask'). Flags are bools, or numbers 0 and 1 (ints and floats still taken)."""
    images = np.random.default_rng(0).random((6, 24, 32))
    for mask, match in [
        (np.full((24, 32), np.nan), r"^mask: .* got 768 of 768 values that are neither, e.g. nan"),
        (np.full((24, 32), 2), r"^mask: must be flags \(bool, or 0 and 1\), got 768 of 768"),
        (np.full((24, 32), "x"), r"^mask: must be flags \(bool, or 0 and 1\), got dtype <U1"),
        (np.full((24, 32), None), r"^mask: must be flags \(bool, or 0 and 1\), got dtype object"),
    ]:
        for given in (images, np.ma.masked_array(images, mask=images > 0.99)):
            with pytest.raises(ValueError, match=match):
                lfj.fit_images(given, lfj.Stripes(), mask=mask)
    from lightfield_jax.checks import check_mask

    assert check_mask(np.eye(3)).dtype == bool and check_mask([[1, 0], [0, 1]]).sum() == 2


def test_a_saturation_beyond_float64_is_named():
    """Before: fit_images(saturation=10**400) ended in numpy's "ufunc 'isfinite' not
    supported for the input types", naming no argument."""
    images = np.random.default_rng(0).random((6, 24, 32))
    with pytest.raises(ValueError, match=r"^saturation: must be a positive number, got 1000"):
        lfj.fit_images(images, lfj.Stripes(), saturation=10**400)


def test_a_split_of_values_that_are_not_intensities_is_refused():
    """Before: a complex split was cast to real with a warning and fitted (28 s), one of
    strings ended in numpy's DTypePromotionError, one with NaN in 'fit_decay: sigma_t is
    not identifiable: 0 usable pixels'."""
    images = np.random.default_rng(0).random((6, 24, 32))
    one = np.ones((24, 32))
    for split, match in [
        ((one.astype(complex), one), "^split: direct: must be real numbers, got dtype complex"),
        ((one, np.full((24, 32), "x")), "^split: multiple: must be real numbers, got dtype <U1"),
        ((one * np.nan, one), "^split: direct: must be finite where not masked, got 768 of 768"),
    ]:
        with pytest.raises(ValueError, match=match):
            lfj.fit_images(images, lfj.Stripes(), split=split)


def test_a_progress_that_cannot_be_called_is_named_first(tmp_path):
    """Before: fit_images(progress=True) ended in "TypeError: 'bool' object is not
    callable" at its first stage; fit_capture loaded the capture first."""
    images = np.random.default_rng(0).random((6, 24, 32))
    with pytest.raises(ValueError, match="^fit_images: progress: must be a function .* got True"):
        lfj.fit_images(images, lfj.Stripes(), progress=True)
    with pytest.raises(ValueError, match="^fit_capture: progress: must be a function .* got 5"):
        lfj.fit_capture(tmp_path / "missing.yaml", progress=5)


def test_a_result_with_nan_in_its_model_records_is_strict_json():
    """Before: to_dict() passed ``seconds`` and ``model`` through as they were: a NaN or
    inf in them (a tail solve's residual, a correction's misfit; NumPy floats too) made
    the strict JSON write of results.json fail after the fit."""
    import json

    from lightfield_jax.inverse.options import FitResult

    nan = math.nan
    result = FitResult(
        method="joint", sigma_t=0.2, sigma_s=0.03, g=0.4, gain=1.0, black_level=None,
        uncertainty={}, correlation={}, converged=False, message="m", iterations=1,
        residual=nan, seconds={"total": 1.0, "compile": math.inf},
        model={"tail": {"residual": nan, "steps": [np.float32(nan), 1.5]}, "n": 3},
    )  # fmt: skip
    out = json.loads(json.dumps(result.to_dict(), allow_nan=False))
    assert out["seconds"] == {"total": 1.0, "compile": None}
    assert out["model"] == {"tail": {"residual": None, "steps": [None, 1.5]}, "n": 3}
    assert out["residual"] is None


def test_numpy_numbers_in_fit_options_are_stored_as_python_numbers():
    """Before: FitOptions(max_steps=np.int64(2)) passed its check and the fit ended
    seconds in, after the scan, in optimistix's "`max_steps` must be a Python integer"."""
    options = lfj.FitOptions(max_steps=np.int64(2), tolerance=np.array(1e-4), n_theta=np.int32(16))
    assert type(options.solve.max_steps) is int and type(options.model.n_theta) is int
    assert type(options.model.tolerance) is float
    assert type(options.replace(tail_max_steps=np.int64(5)).model.tail_max_steps) is int
    assert (
        type(dataclasses.replace(options, tail_max_steps=np.int64(5)).model.tail_max_steps) is int
    )
    images = np.asarray(
        lfj.render(lfj.Medium(0.2051, 0.0366, 0.4), lfj.Grid(32, 24, 8, 1), lfj.Stripes(), 6).total
    )
    fit = lfj.fit_images(
        images, lfj.Stripes(), options=options, basin_search=False, model_error=False
    )
    assert math.isfinite(fit.sigma_t)


def test_a_start_given_as_a_list_or_an_array_is_stored_as_a_tuple():
    """Before: FitOptions(start=np.array([0.03, 0.4])) == the same raised numpy's 'truth
    value of an array ... is ambiguous', a list made the options (and a Joint) unhashable,
    and start=('0.03', '0.4') or (True, 0.4) was taken as numbers."""
    for given in ([0.03, 0.4], np.array([0.03, 0.4]), (np.float32(0.03), 0.4)):
        options, method = lfj.FitOptions(start=given), lfj.Joint(start=given)
        assert options.method.start == method.start == pytest.approx((0.03, 0.4))
        assert type(options.method.start) is tuple and type(options.method.start[0]) is float
        assert options == lfj.FitOptions(start=given) and hash(options) and hash(method)
    for bad in (("0.03", "0.4"), (True, 0.4), "ab"):
        for make in (lfj.FitOptions, lfj.Joint):
            with pytest.raises(ValueError, match=r"^start: must be \(sigma_s > 0, \|g\| < 1\)"):
                make(start=bad)


def test_fit_capture_refuses_channels_that_are_not_a_list_of_names(tmp_path):
    """Before: channels='red' was split into letters ("channel: 'r' is not in the
    capture"), channels='YY' chose 'Y' twice, channels=0 raised "'int' object is not
    iterable"; each after the capture was loaded."""
    for channels in ("red", b"Y", 0):
        with pytest.raises(ValueError, match=r"^channels: must be a sequence of channel names"):
            lfj.fit_capture(tmp_path / "missing.yaml", channels=channels)


def test_inspect_capture_takes_a_path_and_names_other_things(tmp_path):
    """Before: inspect_capture('capture.yaml') and inspect_capture(5) raised "'str'
    object has no attribute 'images'"; a path is now loaded, as fit_capture does."""
    with pytest.raises(TypeError, match=r"^inspect_capture: expected a capture .* got int$"):
        lfj.inspect_capture(5)
    with pytest.raises(lfj.CaptureError, match="missing.yaml: file not found"):
        lfj.inspect_capture(tmp_path / "missing.yaml")
    images = np.asarray(
        lfj.render(lfj.Medium(0.2051, 0.0366, 0.4), lfj.Grid(32, 24, 8, 1), lfj.Stripes(), 6).total
    )
    from lightfield_jax.capture.image_write import write_exr

    names = []
    for i, image in enumerate(images):
        names.append(f"s{i}.exr")
        write_exr(tmp_path / names[-1], {"Y": image.astype(np.float32)})
    (tmp_path / "capture.yaml").write_text(f"images: {names}\npattern: {{period: 6, lit: 3}}\n")
    assert lfj.inspect_capture(str(tmp_path / "capture.yaml")).direct.shape == (24, 32, 1)


def test_stripe_patterns_too_large_for_memory_are_refused_before_allocating(tmp_path):
    """Before: lfj.stripe_patterns(10**6, 10**6) asked numpy for 931 GiB (a bare
    MemoryError, or the machine swapping where it overcommits); write_patterns alike.
    The command line checked this, the Python API did not."""
    with pytest.raises(ValueError, match=r"^stripe_patterns: 8 images of 1000000x1000000 needs"):
        lfj.stripe_patterns(10**6, 10**6, 6, 3)
    with pytest.raises(ValueError, match=r"^stripe_patterns: 8 images of 1000000x1000000 needs"):
        lfj.write_patterns(tmp_path / "p", 10**6, 10**6)
    assert not (tmp_path / "p").exists()
    assert len(lfj.stripe_patterns(64, 48)[1]) == 6


def test_a_channel_not_in_a_capture_fit_is_named():
    """Before: CaptureFit['Q'] raised tuple.index's 'tuple.index(x): x not in tuple'."""
    from lightfield_jax.inverse.options import FitResult

    result = FitResult(
        method="joint", sigma_t=0.2, sigma_s=0.03, g=0.4, gain=1.0, black_level=None,
        uncertainty={}, correlation={}, converged=True, message="m", iterations=1,
        residual=0.0, seconds={}, model={},
    )  # fmt: skip
    fit = lfj.CaptureFit(("R", "G"), (result, result))
    assert fit["G"] is result
    with pytest.raises(ValueError, match=r"^channel: 'Q' is not in the fit \(it has R, G\)$"):
        fit["Q"]


def test_a_single_shift_is_named_as_too_few():
    """Before: one stripe image was refused as 'the 1 shifts are the same image: the
    stripes moved nothing ... (one image given for every shift?)'."""
    image = np.random.default_rng(0).random((1, 24, 32))
    with pytest.raises(ValueError, match=r"^pattern.phases: a fit needs at least 2 shifted"):
        lfj.fit_images(image, lfj.Stripes(phases=(0,)))


def test_fit_decay_names_an_image_beyond_float32():
    """Before: with JAX's default float32, a float64 direct image of 1e300 became inf (or
    of 1e-300 zero) and fit_decay said 'sigma_t is not identifiable: 0 usable pixels'."""
    x = np.arange(48.0)
    direct = np.exp(-0.2 * x)[None, :] * np.ones((8, 1))
    with jax.enable_x64(False):
        for scale in (1e300, 1e-300):
            with pytest.raises(
                ValueError, match=r"^fit_decay.direct: its largest value .* float32"
            ):
                lfj.fit_decay(scale * direct)
        assert float(lfj.fit_decay(1e30 * direct).sigma_t) == pytest.approx(0.2, rel=1e-3)
    assert float(lfj.fit_decay(1e300 * direct).sigma_t) == pytest.approx(0.2, rel=1e-6)  # x64


def test_fitted_images_checks_its_arguments_before_rendering(monkeypatch):
    """Before: a result's to_dict() or pattern=None raised an AttributeError, shape
    'ab' or (-1, 3) numpy's errors, (10**6, 10**6) a MemoryError for 306 TiB."""
    from lightfield_jax.inverse.options import FitResult
    from lightfield_jax.runtime.memory import MAX_MEMORY_ENV

    model = {"width": 32, "height": 24, "n_theta": 8, "refine": 1, "bounces": 2,
             "crop": [0, 0, 32, 24]}  # fmt: skip
    result = FitResult(
        method="joint", sigma_t=0.2, sigma_s=0.03, g=0.4, gain=1.0, black_level=None,
        uncertainty={}, correlation={}, converged=True, message="m", iterations=1,
        residual=0.0, seconds={}, model=model,
    )  # fmt: skip
    pattern = lfj.Stripes()
    monkeypatch.setenv(MAX_MEMORY_ENV, "1G")
    for args, match in [
        ((result.to_dict(), pattern, (24, 32)), "result: must be a FitResult, got dict"),
        ((result, None, (24, 32)), "pattern: must be a Stripes, got NoneType"),
        ((result, pattern, "ab"), r"shape: must be the images' \(height, width\), holding"),
        ((result, pattern, (-1, 3)), r"shape: .* = \(0, 0, 32, 24\), got \(-1, 3\)"),
        ((result, pattern, (20, 32)), r"shape: .* got \(20, 32\)"),
        ((result, pattern, (10**6, 10**6)), r"7 x 2 images of 1000000x1000000 needs about"),
    ]:
        with pytest.raises(ValueError, match=f"^fitted_images: {match}"):
            lfj.fitted_images(*args)
    stripes, full = lfj.fitted_images(result, pattern, np.array([30, 40]))
    assert stripes.shape == (6, 2, 30, 40) and full.shape == (2, 30, 40)


def test_separate_names_images_beyond_float32():
    """Before: with JAX's default float32, float64 images of 1e300 became inf and
    separate said 'no pixel is finite in every one of the 6 images' (with numpy's
    overflow warning); images of 1e-300 became zeros, separated silently."""
    images = 1.0 + np.random.default_rng(0).random((6, 8, 8))
    with jax.enable_x64(False):
        for scale in (1e300, 1e-300):
            with pytest.raises(ValueError, match=r"^separate.images: its largest value .* float32"):
                lfj.separate(scale * images)
        with pytest.raises(ValueError, match=r"^separate.dark_frame: its largest value"):
            lfj.separate(images, dark_frame=np.full((8, 8), 1e300))
        assert np.isfinite(np.asarray(lfj.separate(1e30 * images).direct)).all()
    assert np.isfinite(np.asarray(lfj.separate(1e300 * images).direct)).all()  # x64


def test_detect_geometry_names_arguments_it_cannot_use():
    """Before: period 0 raised a ZeroDivisionError, entry 'up' a KeyError, a NaN
    direction "cannot convert float NaN to integer", a roi of three values an unpacking
    error, images of strings "could not convert string to float"; complex or bool images,
    lit 0 and floor '0' were taken, and a reference of another shape ended in 'no lit
    medium found'."""
    images = np.zeros((6, 40, 48))
    images[:, 8:32, 8:40] = np.random.default_rng(0).random((6, 24, 32))
    for kwargs, match in [
        ({"period": 0}, "period: must be an integer >= 2, got 0"),
        ({"lit": 0}, r"lit: must be an integer in \[1, 5\], got 0"),
        ({"entry": "up"}, "entry: must be one of left, right, top, bottom, got 'up'"),
        ({"direction_deg": math.nan}, "direction_deg: must be finite, got nan"),
        ({"floor": "0"}, "floor: must be a number, got '0'"),
        ({"roi": (0, 0, 20)}, r"roi: must be \(x0, y0, x1, y1\), integers with 0 <= x0 < x1 <= 48"),
        ({"roi": (30, 30, 2, 2)}, r"roi: must be .* got \(30, 30, 2, 2\)"),
        ({"reference": np.ones((3, 3))}, r"reference: must have the images' \(H, W\[, C\]\)"),
    ]:
        with pytest.raises(ValueError, match="^detect_geometry: " + match):
            lfj.detect_geometry(images, **kwargs)
    for bad in (images.astype(complex), images > 0, "x"):
        with pytest.raises(ValueError, match=r"^detect_geometry: images: must be an array of real"):
            lfj.detect_geometry(bad)
    assert lfj.detect_geometry(images, roi=(8, 8, 40, 32)).roi == (8, 8, 40, 32)


def test_a_setting_the_chosen_method_does_not_use_is_refused():
    """Before: FitOptions(method='grid', start=(0.03, 0.4)) or a solver with the grid
    search was taken and ignored: the fit ran from its own search."""
    import optimistix as optx

    solver = optx.Dogleg(rtol=1e-6, atol=1e-8)
    for kwargs, match in [
        ({"method": "grid", "start": (0.03, 0.4)}, "^start: the grid method does not use it"),
        ({"method": lfj.TwoStep(), "start": (0.03, 0.4)}, "^start: the gradient method does"),
        ({"method": "grid", "solver": solver}, "^solver: the grid method does not use it"),
    ]:
        with pytest.raises(ValueError, match=match):
            lfj.FitOptions(**kwargs)
    with pytest.raises(ValueError, match="^start: the grid method does not use it"):
        lfj.FitOptions(start=(0.03, 0.4)).replace(method="grid")
    assert lfj.FitOptions(method="gradient", solver=solver).method.solver is solver
    assert lfj.FitOptions(method=lfj.Joint(), start=(0.03, 0.4)).method.start == (0.03, 0.4)


def test_fit_images_under_a_transformation_names_the_traced_images():
    """Before: fit_images under jax.jit ended in JAX's many-line
    TracerArrayConversionError (then, briefly, 'images of different shapes')."""
    images = np.random.default_rng(0).random((6, 24, 32))
    for transform in (jax.jit, jax.vmap):
        with pytest.raises(ValueError, match=r"^images: must be an array .* got a traced value"):
            transform(lambda x: lfj.fit_images(x, lfj.Stripes()).sigma_t)(
                images if transform is jax.jit else images[None]
            )


def test_write_capture_yaml_writes_only_what_load_capture_takes(tmp_path):
    """Before: pattern=None raised an AttributeError, images=5 "'int' object is not
    iterable", a NumPy array or a Slab yaml's RepresenterError; a NaN saturation was
    written into a file load_capture then refused. Arrays and geometries are now written
    as their lists and dicts."""
    images = [f"s{i}.exr" for i in range(6)]
    for kwargs, match in [
        ({"pattern": None}, "pattern: must be a Stripes, got NoneType"),
        ({"images": 5}, "images: must be a list of image files or one .npy stack, got 5"),
        ({"saturation": math.nan}, "saturation: must be finite, got nan"),
        ({"black_level": 1.5}, r"black_level: must be a number in \[0, 1\), got 1.5"),
        ({"pixel_size_mm": -1.0}, "pixel_size_mm: must lie in"),
        ({"truth": {"medium": lfj.Medium(0.2, 0.03, 0.4)}}, "truth: cannot be written to a"),
    ]:
        given = {"images": images, "pattern": lfj.Stripes(), **kwargs}
        with pytest.raises(ValueError, match="^write_capture_yaml: " + match):
            lfj.write_capture_yaml(tmp_path / "c.yaml", **given)
        assert not (tmp_path / "c.yaml").exists()
    lfj.write_capture_yaml(
        tmp_path / "c.yaml", images=images, pattern=lfj.Stripes(), saturation=np.array(2.0),
        medium_roi=np.array([0, 0, 32, 24]), geometry=lfj.Slab(3.0),
    )  # fmt: skip
    text = (tmp_path / "c.yaml").read_text()
    assert "medium_roi: [0, 0, 32, 24]" in text and "saturation: 2.0" in text
    assert "geometry: {kind: slab, thickness: 3.0, boundary: absorbing}" in text


def test_a_capture_fit_pairs_one_result_with_each_channel():
    """Before: CaptureFit(('R', 'G'), (result,)) was made and its to_dict() wrote that
    result as channel R, silently; a dict among the results failed only in to_dict."""
    from lightfield_jax.inverse.options import FitResult

    result = FitResult(
        method="joint", sigma_t=0.2, sigma_s=0.03, g=0.4, gain=1.0, black_level=None,
        uncertainty={}, correlation={}, converged=True, message="m", iterations=1,
        residual=0.0, seconds={}, model={},
    )  # fmt: skip
    with pytest.raises(ValueError, match=r"^CaptureFit: needs one result per channel, got 2"):
        lfj.CaptureFit(("R", "G"), (result,))
    with pytest.raises(ValueError, match="^CaptureFit: results: must be FitResults, got dict"):
        lfj.CaptureFit(("R",), (result.to_dict(),))
    assert lfj.CaptureFit(("R",), (result,)).to_dict()["channel"] == "R"


def test_a_fit_too_large_for_memory_is_refused_by_the_python_api(monkeypatch):
    """Before: only the command line estimated a fit's memory: fit_images with n_theta
    4096 and refine 8 on six 128x96 images (8.4 TiB) ran for minutes toward it."""
    from lightfield_jax.runtime.memory import MAX_MEMORY_ENV

    monkeypatch.setenv(MAX_MEMORY_ENV, "2G")
    images = np.random.default_rng(0).random((6, 96, 128))
    big = {"n_theta": 4096, "refine": 8, "max_cells": 10**12, "max_render_cells": 10**12}
    with pytest.raises(ValueError, match=r"^the fit of 6 images of 128x96 needs about 8.4 TiB"):
        lfj.fit_images(images, lfj.Stripes(), **big)


def test_an_exposure_or_split_of_arrays_of_different_shapes_is_named():
    """Before: a list of exposures (or a split's direct image given as rows) of
    different shapes ended in numpy's 'setting an array element with a sequence ...
    inhomogeneous shape', naming no argument."""
    images = np.random.default_rng(0).random((6, 24, 32))
    ragged = [np.ones((24, 32))] * 5 + [np.ones((24, 30))]
    with pytest.raises(ValueError, match=r"^exposure: must be an array of real numbers, got list"):
        lfj.fit_images(images, lfj.Stripes(), exposure=ragged)
    rows = [np.ones(32)] * 23 + [np.ones(30)]
    with pytest.raises(ValueError, match=r"^split: direct: must be an array of real numbers"):
        lfj.fit_images(images, lfj.Stripes(), split=(rows, np.ones((24, 32))))


def test_a_geometry_does_not_take_its_kind_as_an_argument():
    """Before: lfj.Plane(6.4) was a plane of kind 6.4 (the thickness meant for a slab
    lost, the paper's 2-D model used), lfj.Slab(3.0, kind='plane') a slab named a plane."""
    with pytest.raises(TypeError, match="Plane.__init__.. takes 1 positional argument"):
        lfj.Plane(6.4)
    with pytest.raises(TypeError, match="unexpected keyword argument 'kind'"):
        lfj.Slab(3.0, kind="plane")
    with pytest.raises(TypeError, match="AutoGeometry.__init__.. takes from 2 to 3 positional"):
        lfj.AutoGeometry(lfj.Slab(3.0), 1.0, "plane")
    assert lfj.Plane().kind == "plane" and lfj.Slab(3.0).kind == "slab"
    assert dataclasses.replace(lfj.Slab(3.0), n_mu=4) == lfj.Slab(3.0, n_mu=4)
    assert lfj.AutoGeometry(lfj.Slab(3.0)).kind == "auto"


def test_the_phase_function_holds_in_float32_near_g_of_one():
    """Before: in float32 (JAX's default) 1 + g² − 2g·cos θ cancelled to 0 at the peak:
    phase_integral(0.9999) and phase_function(0, 0.9999) were inf (a render's ρ inf),
    phase_integral(0.999) 8 % low (319.8 for 348.1), with no error."""
    with jax.enable_x64(False):
        a32 = {g: float(lfj.phase_integral(g)) for g in (0.999, 0.9999, -0.9999)}
        p32 = float(lfj.phase_function(0.0, 0.9999)), float(lfj.phase_function(math.pi, -0.9999))
    a64 = {g: float(lfj.phase_integral(g)) for g in a32}  # the tests run x64
    for g in a32:
        assert a32[g] == pytest.approx(a64[g], rel=1e-3), g
    assert p32 == pytest.approx((float(lfj.phase_function(0.0, 0.9999)),) * 2, rel=1e-3)
    assert float(lfj.phase_function(0.3, 0.4)) == pytest.approx(
        (1 - 0.16) / (4 * math.pi * (1 + 0.16 - 0.8 * math.cos(0.3)) ** 1.5), rel=1e-14
    )


def test_bounces_for_tolerance_refuses_a_negative_rho():
    """Before: bounces_for_tolerance(-0.5) returned 1 bounce (rho = albedo*A(g) is never
    negative: a sign error upstream went unnoticed)."""
    with pytest.raises(ValueError, match=r"^rho: must be a number >= 0, got -0.5"):
        lfj.bounces_for_tolerance(-0.5, 1e-3)
    assert lfj.bounces_for_tolerance(0.0, 1e-3) == 1 and lfj.bounces_for_tolerance(0.5) == 15


def test_fit_images_refuses_a_period_the_images_contradict():
    """Before: ``fit_images(images, Stripes(period=24))`` for period-6 stripes fitted for
    about a minute and ended not converged; the command line's capture check (the
    stripes' strongest period) now runs for the Python API too, before the fit."""
    right = lfj.Stripes(period=6, lit=3, phases=tuple(range(6)))
    images = _decaying_stripes(right, height=36, width=32)
    for period, lit in ((24, 12), (9, 4)):
        wrong = lfj.Stripes(period=period, lit=lit, phases=tuple(range(0, period, period // 6))[:6])
        with pytest.raises(ValueError, match=f"pattern.period: {period} contradicts") as err:
            lfj.fit_images(images, wrong, black_level=0.0)
        assert re.search(r"every (5\.9\d|6\.0\d) px", _one_line(err)), err.value
    # A half period (its harmonic is weak) or a period within 10 % is not refused here.
    from lightfield_jax.capture.stripe_phase import other_period

    assert other_period(images, 0, 6) is None and other_period(images, 0, 6.5) is None


def test_stripes_refuse_more_phases_than_images_could_be_given():
    """Before: ``Stripes(phases=range(10**12))`` was made a tuple until memory ran out
    (MemoryError); now the count is checked first."""
    for phases in (range(10**12), np.zeros(5000, int), [0] * 4097):
        with pytest.raises(ValueError, match="at most 4096 phases") as err:
            lfj.Stripes(phases=phases)
        _one_line(err)
    assert lfj.Stripes(phases=[0] * 4096).n_patterns == 4096
