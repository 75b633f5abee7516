"""Batched renders for parameter sweeps: ``vmap`` over (σt, σs, g), sharded over devices.

A sweep renders one scene (grid, illumination, bounce count: the static part of a
:class:`~lightfield_jax.Renderer`) for many media. :func:`batched_render` vectorises the
renderer over a batch of parameters with ``jax.vmap`` (in chunks of ``chunk`` through
``lax.map`` when memory is short) and, when several devices exist, splits the batch
across them with ``jax.sharding``: a one-axis :class:`~jax.sharding.Mesh` over
``jax.devices()`` and a :class:`~jax.sharding.NamedSharding` on the batch axis (the
renderer's tables are replicated). The batch is padded to a multiple of the device
count with copies of its first row and the padding dropped from the result.

On a CPU, ``XLA_FLAGS=--xla_force_host_platform_device_count=N`` (set before JAX is
imported) exposes N host devices: that is how the sharded path is tested.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

import lightfield_jax as lfj

BATCH_AXIS = "batch"


def batch_mesh(devices=None) -> Mesh:
    """A one-axis mesh (``"batch"``) over ``devices`` (default: every device)."""
    return Mesh(np.asarray(devices if devices is not None else jax.devices()), (BATCH_AXIS,))


@eqx.filter_jit
def _render_batch(renderer: lfj.Renderer, params, chunk: int | None, sharding):
    def one(p):
        return renderer(p[0], p[1], p[2])[0]

    if sharding is not None:
        params = jax.lax.with_sharding_constraint(params, sharding)
    images = jax.vmap(one)(params) if chunk is None else jax.lax.map(one, params, batch_size=chunk)
    if sharding is not None:
        images = jax.lax.with_sharding_constraint(images, sharding)
    return images


def batched_render(
    renderer: lfj.Renderer,
    params,
    *,
    shard: bool | None = None,
    chunk: int | None = None,
    devices=None,
):
    """Per-bounce images of ``renderer`` for every row (σt, σs, g) of ``params``.

    Args:
        renderer: the scene's :class:`~lightfield_jax.Renderer` (unit gain).
        params: Float[Array, "N 3"], rows (σt, σs, g) per pixel.
        shard: split the batch across ``devices``; ``None``: when there are several.
        chunk: vectorise ``chunk`` rows at a time (``lax.map``), or all at once.
        devices: the devices to shard over (default ``jax.devices()``).

    Returns:
        Float[Array, "N patterns bounces H W"] (index k−1 of the bounce axis holds I_k),
        sharded along N when ``shard``.
    """
    params = jnp.asarray(params)
    if params.ndim != 2 or params.shape[1] != 3:
        raise ValueError(
            f"params: expected shape (N, 3) rows (sigma_t, sigma_s, g), got {params.shape}"
        )
    devices = list(devices if devices is not None else jax.devices())
    if shard is None:
        shard = len(devices) > 1
    n = params.shape[0]
    if not shard:
        return _render_batch(renderer, params, chunk, None)
    mesh = batch_mesh(devices)
    pad = -n % len(devices)
    if pad:
        params = jnp.concatenate([params, jnp.repeat(params[:1], pad, axis=0)])
    batch = NamedSharding(mesh, PartitionSpec(BATCH_AXIS))
    params = jax.device_put(params, batch)
    arrays, static = eqx.partition(renderer, eqx.is_array)
    arrays = jax.device_put(arrays, NamedSharding(mesh, PartitionSpec()))
    images = _render_batch(eqx.combine(arrays, static), params, chunk, batch)
    return images if pad == 0 else images[:n]
