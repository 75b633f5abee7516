"""Seeing the transport without code: the paper's figures of a RenderResult,
``simulate --plot``, ``render RESULTS.json`` (checked against the simulation it
re-renders) and what ``fit --plot`` shows (masked pixels, the crop, the truth)."""

import dataclasses
import json
import math

import numpy as np
import pytest
import yaml

import lightfield_jax as lfj
import lightfield_jax.viz as viz
from lightfield_jax.app.cli import main
from lightfield_jax.inverse.options import FitResult

MEDIUM = {"sigma_t": 0.12, "sigma_s": 0.05, "g": 0.3}
SIM = {
    "grid": {"width": 32, "height": 24, "n_theta": 16},
    "medium": {**MEDIUM, "phase": "paper"},
    "illumination": {"kind": "stripes", "period": 6, "lit": 3, "shifts": 6},
    "bounces": 6,
    "gain": 2.0,
}


@pytest.fixture(scope="module")
def rendered():
    medium = lfj.Medium(MEDIUM["sigma_t"], MEDIUM["sigma_s"], MEDIUM["g"])
    grid = lfj.Grid(32, 24, 16, 1)
    full = lfj.render(medium, grid, lfj.Full(), 5, lightfield=True)
    stripes = lfj.render(medium, grid, lfj.Stripes(6, 3, (0, 2, 4)), 5, lightfield=True)
    return full, stripes


def test_paper_figures_take_a_render_result(rendered):
    full, stripes = rendered
    figure = viz.plot_lightfield(full)
    # L_0..L_4 and their sum; each panel has a colour bar.
    titles = [ax.get_title() for ax in figure.axes if ax.get_title()]
    assert titles[0].startswith("$L_{0}$") and titles[4].startswith("$L_{4}$")
    assert titles[5].startswith(r"$\Sigma_{k=0}^{5} L_k$")
    # A stripe render: the patterns summed (each row lit once over phases 0, 2, 4).
    figure = viz.plot_bounce_images(stripes, show=2)
    image = figure.axes[0].images[0].get_array()
    summed = np.asarray(stripes.images).sum(axis=0)[0]
    top = summed.max()
    np.testing.assert_allclose(image, np.maximum(summed, top / 1e4), rtol=1e-6)
    assert viz.plot_bounce_profiles(full).axes[0].get_lines()


def test_plot_lightfield_says_when_the_render_has_no_light_fields(rendered):
    images_only = lfj.render(lfj.Medium(0.1, 0.05, 0.3), lfj.Grid(16, 12, 8, 1), lfj.Full(), 3)
    with pytest.raises(ValueError, match="render with lightfield=True"):
        viz.plot_lightfield(images_only)


def test_plot_transport_writes_the_three_figures(rendered, tmp_path):
    files = viz.plot_transport(rendered[0], tmp_path, illumination=lfj.Full(), title="t")
    assert [f.name for f in files] == ["bounce_images.png", "bounce_profiles.png", "lightfield.png"]
    assert all(f.stat().st_size > 10_000 for f in files)


def test_simulate_plot_and_render_a_fit(tmp_path, capsys):
    """simulate --plot writes the figures; render re-renders a results file's medium in
    its capture's geometry: at the true values it gives the simulation's bounces."""
    (tmp_path / "sim.yaml").write_text(yaml.safe_dump(SIM))
    sim, figs = tmp_path / "sim", tmp_path / "figs"
    assert (
        main(["simulate", str(tmp_path / "sim.yaml"), "--out", str(sim), "--plot", str(figs)]) == 0
    )
    assert sorted(p.name for p in figs.iterdir()) == [
        "bounce_images.png",
        "bounce_profiles.png",
        "lightfield.png",
    ]
    model = {"width": 32, "height": 24, "n_theta": 16, "refine": 1, "bounces": 6}
    results = {
        **MEDIUM,
        "gain": 2.0,
        "phase": "paper",
        "channel": "Y",
        "model": {**model, "crop": [0, 0, 32, 24], "geometry": {"kind": "plane"}},
        "capture": str(sim / "capture.yaml"),
    }
    (tmp_path / "results.json").write_text(json.dumps(results))
    out = tmp_path / "rendered"
    # (Its --plot draws with plot_transport, as simulate --plot does above.)
    assert main(["render", str(tmp_path / "results.json"), "--out", str(out)]) == 0
    assert "lightfield.npy" in capsys.readouterr().out
    bounces = np.load(out / "bounces.npy")
    # Σ over the six shifts of period-6, lit-3 stripes is three times full illumination.
    expected = np.load(sim / "bounces.npy").sum(axis=0) / 3
    np.testing.assert_allclose(bounces, expected, rtol=1e-4, atol=1e-6 * expected.max())
    assert np.load(out / "lightfield.npy").shape == (7, 24, 32, 16)
    about = json.loads((out / "render.json").read_text())
    assert about["illumination"] == "full, left wall, 0 deg" and about["bounces"] == 6
    # --compact: what a user keeps of a large render or simulation (a 128x96 render of
    # 238 bounces wrote 104 MB, its simulation 129 MB), nothing the fit needs left out.
    small = tmp_path / "small"
    argv = ["render", str(tmp_path / "results.json"), "--out", str(small), "--compact"]
    assert main(argv) == 0
    assert sorted(p.name for p in small.iterdir()) == ["bounces.npy", "render.json"]
    np.testing.assert_array_equal(np.load(small / "bounces.npy"), bounces)
    argv = ["simulate", str(tmp_path / "sim.yaml"), "--out", str(small / "s"), "--compact"]
    assert main(argv) == 0
    kept = sorted(p.name for p in (small / "s").iterdir())
    assert kept == ["capture.yaml", "metadata.json"] + [f"shift_{i:02d}.exr" for i in range(6)]
    assert lfj.load_capture(small / "s" / "capture.yaml").n_images == 6


@pytest.mark.parametrize(
    "results, message",
    [
        ({"sigma_t": 0.1}, "not a results file of lightfield-jax fit"),
        (
            {**MEDIUM, "gain": None, "model": {"width": 3}},
            "channel Y: no usable gain, model.height",
        ),
    ],
)
def test_render_refuses_a_file_that_is_not_results(tmp_path, capsys, results, message):
    (tmp_path / "r.json").write_text(json.dumps(results))
    assert main(["render", str(tmp_path / "r.json"), "--out", str(tmp_path / "o")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def _fit_result(crop) -> FitResult:
    return FitResult(
        method="joint",
        sigma_t=MEDIUM["sigma_t"] * 1.05,
        sigma_s=MEDIUM["sigma_s"],
        g=MEDIUM["g"],
        gain=1.0,
        black_level=0.0,
        uncertainty={},
        correlation={},
        converged=True,
        message="",
        iterations=3,
        residual=0.0,
        seconds={"total": 0.0},
        model={"width": crop[2] - crop[0], "height": 24, "n_theta": 16, "refine": 1,
               "bounces": 5, "crop": list(crop), "geometry": {"kind": "plane"}},
        pixel_size_mm=0.05,
    )  # fmt: skip


def test_fit_plot_of_a_result_without_finite_values_names_them(rendered):
    """Before: 'separate.images: no pixel is finite in every one of the 3 images' (the NaN
    model's, not the finite images given)."""
    images = np.asarray(rendered[1].images).sum(axis=1)
    for key in ("sigma_t", "g"):
        bad = dataclasses.replace(_fit_result((0, 0, 24, 24)), **{key: math.nan})
        with pytest.raises(ValueError, match=f"^plot_fit.result: {key} is nan: a fit without"):
            viz.plot_fit(images, lfj.Stripes(6, 3, (0, 2, 4)), bad)


def test_fit_plot_shows_masked_pixels_the_crop_and_the_truth(rendered):
    pattern = lfj.Stripes(6, 3, (0, 2, 4))
    images = np.asarray(rendered[1].images).sum(axis=1)
    mask = np.ones((24, 32), bool)
    mask[5:8, 3:6] = False  # e.g. saturated
    figure = viz.plot_fit(images, pattern, _fit_result((0, 0, 24, 24)), mask=mask, truth=MEDIUM)
    direct, multiple, resid = figure.axes[:3]
    shown = resid.images[0].get_array()
    # Masked pixels and the cropped columns are not residual: they are drawn as masked.
    assert shown.mask[5:8, 3:6].all() and shown.mask[:, 24:].all()
    assert not shown.mask[10:, 10:20].any()
    assert "grey: masked (9 px)" in resid.get_title()
    assert "hatched: cropped, model region x 0-24, y 0-24 of 32x24" in resid.get_title()
    assert "px$^{-1}$" in direct.get_title() and "mm$^{-1}$" in direct.get_title()
    assert "truth 0.12 px$^{-1}$" in direct.get_title()
    assert "truth $I_1$" in [t.get_text() for t in direct.get_legend().get_texts()]
    assert "truth 0.05 px$^{-1}$, g 0.300" in multiple.get_title()
    # A mask per value: a pixel masked in one shift keeps its residual over the others;
    # only pixels masked in every shift are grey.
    values = np.ones(images.shape, bool)
    values[0, 5:8, 3:6] = False  # clipped in one shift
    values[:, 12, 12] = False  # in every shift
    figure = viz.plot_fit(images, pattern, _fit_result((0, 0, 24, 24)), mask=values)
    shown = figure.axes[2].images[0].get_array()
    assert not shown.mask[5:8, 3:6].any() and shown.mask[12, 12]
    assert "grey: masked (1 px)" in figure.axes[2].get_title()


@pytest.mark.parametrize("k", [32, 238])
def test_bounce_profiles_stay_readable_at_many_bounces(tmp_path, k):
    """Every bounce of a K 238 render had a legend entry (the legend overflowed the
    figure, constrained layout collapsed the axes and matplotlib warned), and each
    profile was drawn down to its own peak / 1e6 (an axis spanning ρ^238)."""
    import warnings

    s = np.arange(40.0)
    # I_k: ratio 0.95 per bounce, peaking deeper for higher orders (the shape of a
    # forward, high-albedo medium's profiles).
    profiles = np.stack([0.95**j * np.exp(-((s - min(j, 30)) ** 2) / 200.0) for j in range(k)])
    images = np.repeat(profiles[:, None, :], 8, axis=1)
    figure = viz.plot_bounce_profiles(images)
    absolute, normalised = figure.axes[:2]
    entries = [t.get_text() for t in absolute.get_legend().get_texts()]
    assert len(entries) <= viz.MAX_SHOWN_BOUNCES + 1  # and the sum
    assert "$I_{1}$" in entries and f"$I_{{{k}}}$" in entries
    assert len(normalised.get_legend().get_texts()) <= viz.MAX_SHOWN_BOUNCES
    low, high = absolute.get_ylim()
    assert high / low <= 2.1e6  # the brightest profile's dynamic range, not each one's
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        viz.plot_bounce_profiles(images, tmp_path / "profiles.png")
    assert not [w for w in caught if "matplotlib" in str(w.filename)], caught


def test_shown_bounces_are_the_first_and_spread_to_the_last():
    assert viz.shown_bounces(6) == [1, 2, 3, 4, 5, 6]
    chosen = viz.shown_bounces(238)
    assert len(chosen) <= viz.MAX_SHOWN_BOUNCES and chosen[:4] == [1, 2, 3, 4]
    assert chosen[-1] == 238 and chosen == sorted(set(chosen))


def test_fit_plot_labels_the_curve_the_points_are_compared_with(rendered):
    """At high albedo the model's pure I_1 lies far below the separated D: the legend
    says which fitted curve the measured points are to be compared with."""
    pattern = lfj.Stripes(6, 3, (0, 2, 4))
    images = np.asarray(rendered[1].images).sum(axis=1)
    figure = viz.plot_fit(images, pattern, _fit_result((0, 0, 24, 24)))
    for ax in figure.axes[:2]:
        labels = [t.get_text() for t in ax.get_legend().get_texts()]
        assert any("compare with the dots" in t for t in labels), labels
        assert any("alone (not separated)" in t for t in labels), labels
