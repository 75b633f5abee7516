"""The tail of the bounce series from one Krylov solve: equal to the long series, exact
explicit bounces, reported non-convergence (its derivatives and no recompiles: with the
other renderers' in test_renderers.py)."""

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lightfield_jax as lfj
from lightfield_jax.app.experiment import run_experiment
from lightfield_jax.forward.render import EXPLICIT_WITH_TAIL, Renderer, renderer_for
from lightfield_jax.forward.tail import TailNotConvergedWarning

# A small scene that leaks little per bounce: 24x16 px at sigma_t 0.6 (14 x 10 mean
# free paths), so the series at rho 0.99 still needs ~150 bounces to reach 1e-10.
SIGMA_T = 0.6
LONG = 400  # bounces of the reference series: its neglected part is below 1e-12


def _relative_l1(a, b):
    return float(np.abs(np.asarray(a) - np.asarray(b)).sum() / np.abs(np.asarray(b)).sum())


@pytest.mark.parametrize(
    "rho, method, illum, refine",
    [
        (0.9, "bicgstab", lfj.Beam(0.0, 8.0, 10.0, 2.0), 1),
        (0.99, "bicgstab", lfj.Beam(0.0, 8.0, 10.0, 2.0), 1),
        pytest.param(
            0.99, "gmres", lfj.Stripes(period=6, lit=3, phases=(0, 3)), 2, marks=pytest.mark.slow
        ),
    ],
)
def test_tail_equals_the_long_series(rho, method, illum, refine):
    grid = lfj.Grid(24, 16, 16, refine=refine)
    medium = lfj.Medium(SIGMA_T, rho * SIGMA_T, 0.5, "normalized")
    k0, tol = 3, 1e-8
    res = lfj.render(medium, grid, illum, k0, lightfield=True, tail=method, tail_tol=tol)
    ref = lfj.render(medium, grid, illum, LONG, lightfield=True)
    ref_images = np.asarray(ref.images)
    per_bounce = ref_images.sum(axis=(-2, -1))
    # the reference really is converged, and the tail is most of the light
    assert per_bounce[..., -1].max() < 1e-12 * per_bounce.sum(axis=-1).min()
    tail_ref = ref_images[..., k0:, :, :].sum(axis=-3)
    assert tail_ref.sum() > 0.3 * ref_images.sum()
    assert res.tail_converged and res.tail_method == method and res.tail_steps >= 1
    # explicit bounces unchanged, the tail and the total equal the long series
    np.testing.assert_allclose(res.images, ref_images[..., :k0, :, :], rtol=1e-12, atol=1e-300)
    assert _relative_l1(res.tail, tail_ref) < 20 * tol
    assert _relative_l1(res.total, ref.total) < 20 * tol
    # light fields: L_0..L_K0 explicit, the tail's field is sum_{k>K0} L_k
    lf_ref = np.asarray(ref.lightfields)
    axis = 1 if isinstance(illum, lfj.Stripes) else 0
    np.testing.assert_allclose(
        res.lightfields, np.take(lf_ref, range(k0 + 1), axis=axis), rtol=1e-12, atol=1e-300
    )
    lf_tail = np.take(lf_ref, range(k0 + 1, LONG + 1), axis=axis).sum(axis=axis)
    assert _relative_l1(res.tail_lightfield, lf_tail) < 20 * tol


# The absorbing slab's GMRES is slow-marked (the default suite's time): the plane's GMRES
# tails and the refractive slab's BiCGStab tail cover the same solve.
@pytest.mark.parametrize(
    "boundary, method",
    [pytest.param("absorbing", "gmres", marks=pytest.mark.slow), ("refractive", "bicgstab")],
)
def test_slab_tail_equals_the_long_series(boundary, method):
    """The slab's bounce goes through the same tail solve (albedo 0.9): K0 explicit
    bounces unchanged, the tail and its light field equal the long series."""
    grid = lfj.Grid(16, 12, 8, refine=1)
    slab = lfj.Slab(4.0, boundary, n_mu=4, n_z=2)
    medium = lfj.Medium(0.5, 0.45, 0.4, "normalized")
    beam = lfj.Beam(0.0, 6.0)
    k0, tol, long = 3, 1e-8, 100
    res = lfj.render(
        medium, grid, beam, k0, lightfield=True, geometry=slab, tail=method, tail_tol=tol
    )
    ref = lfj.render(medium, grid, beam, long, lightfield=True, geometry=slab)
    ref_images = np.asarray(ref.images)
    per_bounce = ref_images.sum(axis=(-2, -1))
    assert per_bounce[-1] < 1e-12 * per_bounce.sum()
    tail_ref = ref_images[k0:].sum(axis=0)
    assert tail_ref.sum() > 0.25 * ref_images.sum()
    assert res.tail_converged and res.tail_method == method and res.tail_steps >= 1
    np.testing.assert_allclose(res.images, ref_images[:k0], rtol=1e-12, atol=1e-300)
    assert _relative_l1(res.tail, tail_ref) < 20 * tol
    assert _relative_l1(res.total, ref.total) < 20 * tol
    lf_ref = np.asarray(ref.lightfields)
    np.testing.assert_allclose(res.lightfields, lf_ref[: k0 + 1], rtol=1e-12, atol=1e-300)
    assert _relative_l1(res.tail_lightfield, lf_ref[k0 + 1 :].sum(axis=0)) < 20 * tol


def test_auto_keeps_a_few_explicit_bounces_and_paper_phase_works():
    # phase paper with rho = omega * A(0.8) = 0.95 < 1
    g = 0.8
    omega = 0.95 / float(lfj.phase_integral(g))
    medium = lfj.Medium(SIGMA_T, omega * SIGMA_T, g)
    grid = lfj.Grid(24, 16, 16, refine=1)
    res = lfj.render(medium, grid, lfj.Beam(0.0, 8.0), "auto", tail="bicgstab", tail_tol=1e-8)
    assert res.bounces == EXPLICIT_WITH_TAIL
    ref = lfj.render(medium, grid, lfj.Beam(0.0, 8.0), LONG)
    assert _relative_l1(res.total, ref.total) < 2e-7


def test_float32_tail_converges_without_x64():
    # The package runs float32 with x64 off; there lineax's own BiCGStab tests breakdown
    # as alpha < 1e-16 (signed) and stops after two steps on this scene. The solve
    # written here converges, to the float64 answer.
    grid = lfj.Grid(48, 32, 32, refine=1)
    renderer = renderer_for(grid, lfj.Full(), 4, "normalized", None, "bicgstab", 1e-5)
    values = (0.5, 0.99 * 0.5, 0.7)
    with jax.enable_x64(False):
        i32, _, t32 = renderer(*(np.float32(v) for v in values))
        assert t32.image.dtype == jnp.float32 and bool(t32.converged)
        total32 = np.asarray(i32.sum(axis=1) + t32.image, np.float64)
    i64, _, t64 = renderer(*(jnp.float64(v) for v in values))
    assert _relative_l1(total32, i64.sum(axis=1) + t64.image) < 1e-4


def test_non_convergence_is_reported():
    grid = lfj.Grid(18, 12, 16, refine=1)
    medium = lfj.Medium(0.6, 0.59, 0.5, "normalized")
    kw = dict(tail="bicgstab", tail_tol=1e-10, tail_max_steps=1)
    renderer = renderer_for(grid, lfj.Beam(0.0, 6.0), 2, "normalized", None, **kw)
    _, _, tail = renderer(medium.sigma_t, medium.sigma_s, medium.g)
    assert not bool(tail.converged) and int(tail.steps) == 1
    with pytest.warns(TailNotConvergedWarning, match="bicgstab solve stopped after 1"):
        res = lfj.render(medium, grid, lfj.Beam(0.0, 6.0), 2, **kw)
    assert res.tail_converged is False


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda g, b: Renderer(g, b, 2, tail="cg"), "tail: must be None or one of"),
        (lambda g, b: Renderer(g, b, 2, tail="gmres", tail_tol=0.0), "tail_tol"),
        (lambda g, b: Renderer(g, b, 2, tail="gmres", tail_max_steps=0), "tail_max_steps"),
        (
            lambda g, b: lfj.render(lfj.Medium(0.2, 0.15, 0.9), g, b, 2, tail="gmres"),
            "diverges",
        ),
        (
            lambda g, b: lfj.make_renderer(
                g, b, 2, "normalized", lfj.Slab(4.0, n_mu=4, n_z=1), tail="cg"
            ),
            "tail: must be None or one of",
        ),
        (
            lambda g, b: Renderer(g, b, 2, tail="gmres").images_and_g_slope(0.2, 0.1, 0.3),
            "per-bounce images only",
        ),
    ],
)
def test_bad_tail_settings_raise_clear_errors(call, match):
    with pytest.raises(ValueError, match=match):
        call(lfj.Grid(12, 8, 16, refine=1), lfj.Beam(0.0, 4.0))


@pytest.mark.slow
def test_tail_acceleration_experiment_reduced(tmp_path):
    config = Path(__file__).resolve().parent.parent / "configs" / "tail_acceleration.yaml"
    record = run_experiment(config, tmp_path, reduced=True)
    assert (tmp_path / "tail_acceleration.png").stat().st_size > 0
    data = json.loads((tmp_path / "tail_acceleration.json").read_text())
    assert {"versions", "machine", "date_utc"} <= set(data)
    rows = data["rows"]
    assert {(r["phase"], r["method"]) for r in rows} == {
        (p, m)
        for p in ("normalized", "paper")
        for m in ("series_auto", "series_needed", "gmres", "bicgstab")
    }
    for r in rows:
        assert r["seconds"] > 0
        if r["method"] in ("gmres", "bicgstab"):
            assert r["converged"] and r["error_explicit"] < 1e-6
            assert r["error_total"] < 10 * data["tail_tol"], r
    assert {r["geometry"] for r in rows} == {"plane", "slab absorbing", "slab refractive"}
    for geometry, phase in (
        ("plane", "normalized"),
        ("plane", "paper"),
        ("slab absorbing", "normalized"),
        ("slab refractive", "normalized"),
    ):
        by = {r["method"]: r for r in rows if r["phase"] == phase and r["geometry"] == geometry}
        # the tail bound is conservative: more bounces than needed, and within target
        assert by["series_auto"]["bounces"] >= by["series_needed"]["bounces"]
        assert by["series_auto"]["error_total"] <= data["target"]
    assert len(record["summary"]["table"]) == len(rows)


# The coarse tail (coarse_after): the later bounces on the native grid. A forward medium
# whose model is refined, 40% of whose light is past the fourth bounce.
_COARSE_SCENE = dict(
    grid=lfj.Grid(48, 32, 64, refine=2),
    illumination=lfj.Stripes(period=6, lit=3, phases=(0, 3)),
    medium=lfj.Medium(0.25, 0.22, 0.7, "normalized"),
)


def test_the_coarse_tail_keeps_the_explicit_bounces_and_the_series_within_its_error():
    grid, illum, medium = (_COARSE_SCENE[k] for k in ("grid", "illumination", "medium"))
    k, k0 = 24, 4
    full = np.asarray(lfj.render(medium, grid, illum, k).images)
    result = lfj.render(medium, grid, illum, k, coarse_after=k0)
    assert result.coarse_after == k0
    coarse = np.asarray(result.images)
    assert coarse.shape == full.shape
    later = full[:, k0:].sum() / full.sum()
    assert later > 0.3  # the coarse bounces carry much of the light
    # The first K0 bounces are the renderer's own, the later ones the coarse grid's.
    np.testing.assert_allclose(coarse[:, :k0], full[:, :k0], rtol=1e-6, atol=0)
    assert not np.allclose(coarse[:, k0:], full[:, k0:], rtol=1e-6, atol=0)
    # Measured: 7e-4 of the peak at most; per-bounce sums within 0.1 % of the full's.
    peak = full.sum(axis=1).max()
    assert np.abs(coarse.sum(axis=1) - full.sum(axis=1)).max() < 1e-3 * peak
    per_bounce = coarse.sum(axis=(0, 2, 3)) / full.sum(axis=(0, 2, 3))
    np.testing.assert_allclose(per_bounce[k0:], 1.0, atol=1e-2)


@pytest.mark.parametrize(
    "call, match",
    [
        (
            lambda g, b: Renderer(g, b, 8, coarse_after=1),
            r"coarse_after: must be an integer in \[2",
        ),
        (
            lambda g, b: Renderer(g, b, 8, tail="gmres", coarse_after=4),
            "coarse_after: the later bounces are either",
        ),
        (
            lambda g, b: lfj.make_renderer(
                g, b, 8, "normalized", lfj.Slab(4.0, n_mu=4, n_z=1), coarse_after=4
            ),
            "coarse_after: SlabRenderer has no coarse grid",
        ),
        (
            lambda g, b: Renderer(g, b, 8, coarse_after=4)(0.2, 0.1, 0.7, lightfield=True),
            "lightfield: the bounces after coarse_after = 4",
        ),
    ],
)
def test_bad_coarse_tail_settings_raise_clear_errors(call, match):
    with pytest.raises(ValueError, match=match):
        call(lfj.Grid(16, 8, 64, refine=2), lfj.Beam(0.0, 4.0))


def test_render_refuses_light_fields_with_a_coarse_tail_before_its_tables(monkeypatch):
    import lightfield_jax.forward.render as render_module

    def no_tables(*args, **kwargs):
        raise AssertionError("the renderer's tables were built")

    monkeypatch.setattr(render_module, "renderer_for", no_tables)
    medium = lfj.Medium(0.2, 0.1, 0.7, "normalized")
    with pytest.raises(ValueError, match="lightfield: the bounces after coarse_after = 4"):
        lfj.render(
            medium,
            lfj.Grid(16, 8, 64, refine=2),
            lfj.Beam(0.0, 4.0),
            8,
            lightfield=True,
            coarse_after=4,
        )
    with pytest.raises(ValueError, match=r"coarse_after: must be an integer in \[2"):
        lfj.render(medium, lfj.Grid(16, 8, 64, refine=2), lfj.Beam(0.0, 4.0), 8, coarse_after=1)


def test_coarse_tail_experiment_reduced(tmp_path):
    config = Path(__file__).resolve().parent.parent / "configs" / "coarse_tail.yaml"
    record = run_experiment(config, tmp_path, reduced=True)
    assert (tmp_path / "coarse_tail.png").stat().st_size > 0
    data = json.loads((tmp_path / "coarse_tail.json").read_text())
    assert {"versions", "machine", "date_utc"} <= set(data)
    rows = data["rows"]
    k0s = {None, *data["coarse_after"]}
    assert {(r["medium"], r["coarse_after"]) for r in rows} == {
        (m["name"], k0) for m in data["media"] for k0 in k0s
    }
    for r in rows:
        assert r["refine"] == 2
        assert np.isfinite([r["seconds"], r["first_call_s"], r["compile_s"]]).all()
        assert r["seconds"] > 0
        if r["coarse_after"] is None:
            continue
        numbers = [r[k] for k in ("error_max", "error_l1", "bounce_deviation", "speedup")]
        assert np.isfinite(numbers).all(), r
        assert r["error_max"] < 1e-2, r  # of the full march's peak
        assert r["explicit_deviation"] < 1e-5  # the first K0 bounces are the renderer's own
    assert len(record["summary"]["table"]) == len(rows)


@pytest.mark.parametrize("refine", [None, 1])
def test_a_coarse_tail_on_the_native_grid_marches_as_without_it(refine):
    # Nothing coarser to march on: every bounce on the grid, light fields allowed.
    renderer = Renderer(lfj.Grid(16, 8, 32, refine=refine), lfj.Beam(0.0, 4.0), 6, coarse_after=3)
    assert renderer.coarse_after is None
    images, fields = renderer(0.2, 0.1, 0.3, lightfield=True)
    plain = Renderer(lfj.Grid(16, 8, 32, refine=refine), lfj.Beam(0.0, 4.0), 6)(0.2, 0.1, 0.3)[0]
    np.testing.assert_array_equal(np.asarray(images), np.asarray(plain))
    assert fields is not None
    medium = lfj.Medium(0.2, 0.1, 0.3, "normalized")
    kept = lfj.render(
        medium, lfj.Grid(16, 8, 32, refine=refine), lfj.Beam(0.0, 4.0), 6, coarse_after=3
    )
    assert kept.coarse_after is None  # reported: nothing was marched on a coarse grid
