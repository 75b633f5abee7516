"""Direct/global separation (docs/model.md section 5) against captures built from known D, M."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import monitoring

from lightfield_jax.inverse.separate import Separation, separate


def _stripe_capture(direct, multiple, period, lit, black_level, dark=0.0):
    """Shifted stripe images of a scene with direct part D and global part M.

    Row r is lit in shift p iff (r + p) mod period < lit; a lit pixel sees D, a dark one
    b·D, and every pixel sees the global part (a + b(1 − a))·M (Nayar et al. 2006).
    """
    a = lit / period
    rows = np.arange(direct.shape[0])
    lit_rows = (rows[None, :] + np.arange(period)[:, None]) % period < lit
    lit_rows = lit_rows.reshape(lit_rows.shape + (1,) * (direct.ndim - 1))
    on = np.where(lit_rows, 1.0, black_level)
    return on * direct[None] + (a + black_level * (1 - a)) * multiple[None] + dark


@pytest.fixture
def scene():
    rng = np.random.default_rng(0)
    return rng.uniform(0.1, 2.0, (12, 10)), rng.uniform(0.0, 1.0, (12, 10))


def test_general_recovers_direct_and_multiple(scene):
    d, m = scene
    dark = np.random.default_rng(1).uniform(0.0, 0.05, d.shape)
    images = _stripe_capture(d, m, period=6, lit=2, black_level=0.1, dark=dark)
    sep = separate(images, lit_fraction=1 / 3, black_level=0.1, dark_frame=dark)
    assert isinstance(sep, Separation)
    np.testing.assert_allclose(sep.direct, d, rtol=1e-12)
    np.testing.assert_allclose(sep.multiple, m, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sep.imax, d + (1 / 3 + 0.1 * 2 / 3) * m, rtol=1e-12)
    np.testing.assert_allclose(sep.imin, 0.1 * d + (1 / 3 + 0.1 * 2 / 3) * m, rtol=1e-12)


def test_channels_and_per_channel_dark_level(scene):
    d, m = scene
    d3 = np.stack([d, 2 * d, 0.5 * d], axis=-1)
    m3 = np.stack([m, 0.3 * m, m**2], axis=-1)
    dark = np.array([0.01, 0.02, 0.03])
    images = _stripe_capture(d3, m3, period=4, lit=2, black_level=0.05, dark=dark)
    sep = separate(images, black_level=0.05, dark_frame=dark)
    assert sep.direct.shape == d3.shape
    np.testing.assert_allclose(sep.direct, d3, rtol=1e-12)
    np.testing.assert_allclose(sep.multiple, m3, rtol=1e-12, atol=1e-12)


def test_paper_form_equals_general_at_half_and_zero_black(scene):
    d, m = scene
    images = _stripe_capture(d, m, period=6, lit=3, black_level=0.0)
    paper = separate(images, method="paper")
    general = separate(images, lit_fraction=0.5, black_level=0.0)
    np.testing.assert_array_equal(paper.direct, general.direct)
    np.testing.assert_array_equal(paper.multiple, general.multiple)
    np.testing.assert_array_equal(paper.direct, images.max(0) - images.min(0))
    np.testing.assert_array_equal(paper.multiple, 2 * images.min(0))
    np.testing.assert_allclose(paper.direct, d, rtol=1e-12)
    np.testing.assert_allclose(paper.multiple, m, rtol=1e-12, atol=1e-12)


def test_integer_frames_are_converted_before_subtracting():
    images = np.array([[[10, 3]], [[2, 8]]], dtype=np.uint16)
    dark = np.array([[4, 4]], dtype=np.uint16)
    sep = separate(images, dark_frame=dark)
    np.testing.assert_allclose(sep.imin, [[-2.0, -1.0]])
    np.testing.assert_allclose(sep.direct, [[8.0, 5.0]])


def test_traceable_and_differentiable(scene):
    # The fits pass model renders through the same separation inside a traced loss.
    d, m = scene
    images = _stripe_capture(d, m, period=6, lit=3, black_level=0.0)

    @jax.jit
    def loss(scale):
        return jnp.sum(separate(scale * images).multiple)

    assert float(jax.grad(loss)(1.0)) == pytest.approx(float(np.sum(m)), rel=1e-12)


def test_new_lit_fraction_and_black_level_never_recompile(scene):
    d, m = scene
    images = _stripe_capture(d, m, period=6, lit=3, black_level=0.0)
    separate(images)
    compiles = []

    def listener(name, secs, **kwargs):
        if name == "/jax/core/compile/backend_compile_duration":
            compiles.append(name)

    monitoring.register_event_duration_secs_listener(listener)
    try:
        for a, b in ((1 / 3, 0.1), (0.25, 0.0), (0.5, 0.2)):
            separate(images * (1 + a), lit_fraction=a, black_level=b)
    finally:
        monitoring.unregister_event_duration_listener(listener)
    assert compiles == []


@pytest.mark.parametrize(
    "images_shape, kwargs, match",
    [
        ((1, 4, 4), {}, "at least 2 shifted images"),
        ((4, 4), {}, r"images: must have shape"),
        ((2, 4, 4, 3, 1), {}, r"images: must have shape"),
        ((3, 4, 4), {"lit_fraction": 0.0}, r"lit_fraction: must be in \(0, 1\)"),
        ((3, 4, 4), {"lit_fraction": 1.0}, r"lit_fraction: must be in \(0, 1\)"),
        ((3, 4, 4), {"lit_fraction": float("nan")}, r"lit_fraction: must be in"),
        ((3, 4, 4), {"lit_fraction": "half"}, "lit_fraction: must be a number"),
        ((3, 4, 4), {"black_level": -0.1}, r"black_level: must be in \[0, 1\)"),
        ((3, 4, 4), {"black_level": 1.0}, r"black_level: must be in \[0, 1\)"),
        ((3, 4, 4), {"dark_frame": np.zeros((5, 4))}, "dark_frame: shape"),
        ((3, 4, 4), {"dark_frame": np.zeros((2, 4, 4))}, "dark_frame: shape"),
        ((3, 4, 4), {"method": "nayar"}, "unknown method 'nayar'"),
        ((3, 4, 4), {"dark_frame": np.full((4, 4), np.nan)}, "no pixel is finite in every"),
        ((3, 4, 4), {"method": "paper", "lit_fraction": 1 / 3}, "'paper'.*use method='general'"),
        ((3, 4, 4), {"method": "paper", "black_level": 0.1}, "'paper'.*use method='general'"),
    ],
)
def test_bad_input_raises(images_shape, kwargs, match):
    with pytest.raises(ValueError, match=match):
        separate(np.ones(images_shape), **kwargs)
