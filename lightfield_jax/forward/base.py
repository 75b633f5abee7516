"""The bounce loop every geometry shares: :class:`AbstractRenderer`.

A renderer turns (σt, σs, g, gain) into per-bounce images I_k (and light fields L_k)
of one grid, illumination and bounce count. The base class owns everything that does
not depend on the geometry (the diffrax/exponax pattern: the base owns the loop, a
geometry supplies its steps):

- refinement: the render runs on a working grid f times finer (σ/f per working
  pixel), whose images and fields are averaged back over f×f blocks;
- the source: the pixel-averaged unscattered fluence S of the illumination;
- the march: I_1, then the bounce step Q_k ↦ (Q_{k+1}, I_{k+1}, L_k) in a ``lax.scan``;
- stacking: images "patterns bounces H W", light fields "bounces+1 patterns H W
  n_theta" (radiance per radian of azimuth);
- the tail Σ_{k>K0} from one Krylov solve over the same bounce step
  (:mod:`lightfield_jax.forward.tail`);
- the coarse tail: the bounces after ``coarse_after`` marched on the native grid (a
  geometry says whether it has one coarser than its working grid,
  :meth:`AbstractRenderer.coarse_grid`, restricts its source to it,
  :meth:`AbstractRenderer.restrict`, and gives the bounce step there,
  :meth:`AbstractRenderer.coarse_step`);
- the images' slope along g (:meth:`AbstractRenderer.images_and_g_slope`).

A geometry (the plane: :class:`~lightfield_jax.forward.plane.PlaneRenderer`; the slab:
:class:`~lightfield_jax.forward.slab.SlabRenderer`) supplies its first orders
(:meth:`AbstractRenderer.first_orders`: I_1 and, from the first scatter, I_2, L_1,
Q_2 and the bounce step), how its light field of one order is integrated into the
output layout, and the depth of its direct light field.
"""

from __future__ import annotations

import abc
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from lightfield_jax.checks import check_int, number_problem
from lightfield_jax.forward.pattern_basis import (
    PatternBasis,
    every_pattern_output,
    marched_patterns,
)
from lightfield_jax.forward.tail import TailSolution, check_tail, mapped_output, solve_tail
from lightfield_jax.scene.grid import Grid
from lightfield_jax.scene.illumination import Illumination, Stripes, scaled, source_moments

_TRACES = {"renderer": 0}


def count_trace() -> None:
    """Called once per trace of a render (a Python side effect that runs at trace time
    only): tests use it to prove new values never recompile."""
    _TRACES["renderer"] += 1


def trace_count() -> int:
    """How many times a renderer has been traced (compiled) in this process."""
    return _TRACES["renderer"]


def check_physical(sigma_t, sigma_s, g, gain, where: str = "renderer") -> None:
    """Refuse concrete values no medium has, as :class:`~lightfield_jax.Medium` does
    (``ValueError("WHERE: medium.KEY: ...")``), and a gain that is not a finite number;
    traced values pass unchecked. Unchecked, a renderer called with σs > σt, g = 1, NaN
    or a gain of -1 returns NaN or negative images, and '0.2' or None a JAX traceback."""
    from lightfield_jax.scene.medium import Medium

    try:
        Medium(sigma_t, sigma_s, g)
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from None
    if not isinstance(gain, jax.core.Tracer):
        problem = number_problem(gain, low=0.0, low_open=True)
        if problem is not None:
            raise ValueError(f"{where}: gain: {problem}")


def as_physical(sigma_t, sigma_s, g, gain):
    """(σt, σs, g, gain) as arrays of one floating dtype. Python scalars would be static
    under ``filter_jit`` (a recompile per value): every physical value becomes an array."""
    values = [jnp.asarray(v) for v in (sigma_t, sigma_s, g, gain)]
    dtype = jnp.result_type(*values[:3])
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    return tuple(v.astype(dtype) for v in values)


def block_mean(a, f: int, axes: tuple[int, int]):
    """Average f×f blocks over two adjacent axes."""
    ay, ax = (ax_ % a.ndim for ax_ in axes)
    shape = a.shape[:ay] + (a.shape[ay] // f, f, a.shape[ax] // f, f) + a.shape[ax + 1 :]
    return a.reshape(shape).mean(axis=(ay + 1, ay + 3))


def restrict_moments(coverage, mean, var, c: int):
    """Source moments (each (P, H, W), depths in pixels) on a grid ``c`` times coarser:
    each c×c block's lit fraction, and the mean and variance of the depth over its lit
    part (within plus between its pixels), in coarse pixels. ``c`` divides H and W."""
    if c == 1:
        return coverage, mean, var

    def blocks(a):
        p, h, w = a.shape
        return a.reshape(p, h // c, c, w // c, c)

    cov, m, v = blocks(coverage), blocks(mean), blocks(var)
    lit = cov.sum(axis=(2, 4))
    safe = np.where(lit > 0, lit, 1.0)
    m1 = (cov * m).sum(axis=(2, 4)) / safe
    m2 = (cov * (v + m * m)).sum(axis=(2, 4)) / safe
    return lit / (c * c), m1 / c, np.maximum(m2 - m1 * m1, 0.0) / (c * c)


def _log_sinhc(x):
    """log(sinh(x)/x) for x ≥ 0, stable for small and large x (and its derivative)."""
    small = x < 0.5
    xl = jnp.where(small, 1.0, x)  # no log(0) in the branch not taken
    large = xl + jnp.log1p(-jnp.exp(-2.0 * xl)) - jnp.log(2.0 * xl)
    x2 = x * x
    return jnp.where(small, x2 / 6.0 - x2 * x2 / 180.0 + x2 * x2 * x2 / 2835.0, large)


# The most bounces a render or a fit marches: each is a transport step whose images
# are kept (a typo of 10**6 bounces ran for many minutes); a longer series is summed
# by a tail solve.
MAX_BOUNCES = 10_000


def check_bounces(bounces) -> int:
    """A bounce count as an int >= 1 (a one-line error naming the value otherwise)."""
    if number_problem(bounces, integer=True, low=1) is not None:
        raise ValueError(f"bounces: must be an integer >= 1, got {bounces!r}")
    if bounces > MAX_BOUNCES:
        raise ValueError(too_many_bounces("bounces", bounces))
    return int(bounces)


def too_many_bounces(key: str, value) -> str:
    """The message refusing a bounce count above :data:`MAX_BOUNCES`."""
    return (
        f"{key}: at most {MAX_BOUNCES} bounces are marched (every image of each is kept; a "
        f"longer series gets the tail: bounces: auto), got {value!r}"
    )


class FirstOrders(eqx.Module):
    """What a geometry's first scatter hands the bounce loop (working-grid units).

    Attributes:
        image: I_1, Float[Array, "patterns H W"].
        step: the bounce step Q_k ↦ (Q_{k+1}, I_{k+1}) (``step.step(q)`` also returns
            L_k; ``step.transport(q)`` is L_k alone; ``step.linear`` is the exactly
            linear step a tail solve iterates), or ``None`` when only I_1 is needed.
        second_image: I_2, "patterns H W" (``None`` with ``step``).
        field: L_1 in the step's layout (``None`` with ``step``).
        source: Q_2 in the step's layout (``None`` with ``step``).
    """

    image: Array
    step: eqx.Module | None = None
    second_image: Array | None = None
    field: Array | None = None
    source: Array | None = None


def coarse_lightfield_refusal(coarse_after: int) -> str:
    """The message refusing light fields of a render with a coarse tail."""
    return (
        f"lightfield: the bounces after coarse_after = {coarse_after} are on a coarse "
        "grid; render light fields without coarse_after"
    )


class AbstractRenderer(eqx.Module):
    """A compiled forward model for one grid, illumination and bounce count.

    Construction precomputes every static table; calling it with (σt, σs, g, gain) runs
    one jit-compiled function in which those values are traced, so new values never
    recompile.

    Call signature: ``renderer(sigma_t, sigma_s, g, gain=1.0, lightfield=False)``
    returns ``(images, lightfields)``: images Float[Array, "patterns bounces H W"]
    (index k−1 holds I_k) and, when requested, lightfields
    Float[Array, "bounces+1 patterns H W n_theta"] (L_0..L_K), else ``None``.

    With ``tail`` (``"gmres"`` or ``"bicgstab"``) the first ``bounces`` = K0 orders stay
    explicit and exact, and the rest of the series Σ_{k>K0} comes from one Krylov solve
    over the geometry's bounce step (:mod:`lightfield_jax.forward.tail`, relative
    tolerance ``tail_tol``, at most ``tail_max_steps`` iterations): the call returns
    ``(images, lightfields, tail)`` with ``tail`` a
    :class:`~lightfield_jax.forward.tail.TailSolution`. The image of all orders is
    ``images.sum(axis=1) + tail.image``.

    With ``coarse_after`` = K0 the first K0 bounces are marched on the renderer's grid
    (exact, as without it) and the later ones on the geometry's coarse grid
    (:meth:`coarse_grid`; the plane: the native grid, not refined): their images are
    those of the coarse grid, repeated over each pixel's working cells. Later bounces
    are smooth in space, so this changes the image of the series by 5e-5 to 6e-4 of its
    peak (docs/tail_acceleration.md) at a fraction of the cost. Not with ``tail`` or
    light fields.

    Subclasses give :meth:`first_orders`, :meth:`integrate`, ``direct_depth``,
    ``image_scale`` and ``field_scale``.
    """

    height: int = eqx.field(static=True)  # of the (refined) working grid
    width: int = eqx.field(static=True)
    n_theta: int = eqx.field(static=True)
    refine: int = eqx.field(static=True)
    bounces: int = eqx.field(static=True)
    phase: str = eqx.field(static=True)
    theta0_bin: int = eqx.field(static=True)
    tail: str | None = eqx.field(static=True)
    tail_tol: float = eqx.field(static=True)
    tail_max_steps: int = eqx.field(static=True)
    coarse_after: int | None = eqx.field(static=True)  # None: every bounce on the working grid
    coverage: Float[Array, "patterns H W"]
    mean_depth: Float[Array, "patterns H W"]
    var_depth: Float[Array, "patterns H W"]
    # Stripes marched as fewer shifts and full light (the source moments'), every shift
    # combined from them at the end; ``None``: every pattern marched.
    marched_basis: PatternBasis | None = eqx.field(static=True)

    def _setup(
        self,
        grid: Grid,
        illumination: Illumination,
        bounces: int,
        phase: str,
        tail: str | None,
        tail_tol: float,
        tail_max_steps: int,
        coarse_after: int | None = None,
        moments=None,
        basis: bool = False,
    ) -> None:
        """The fields every geometry fills alike (called from a subclass's ``__init__``).
        ``moments``: the source moments ``(coverage, mean, var)`` of the working grid,
        given instead of those of ``illumination`` (a coarser grid's restriction of a
        finer one's, :func:`restrict_moments`). ``basis``: march stripes as fewer shifts
        and full light where that is exact (:mod:`~lightfield_jax.forward.pattern_basis`;
        only for ``moments`` not given)."""
        if grid.n_theta is None:
            raise ValueError(
                f"{type(self).__name__} needs grid.n_theta: call Grid.resolve(g) first"
            )
        self.bounces = check_bounces(bounces)
        check_tail(tail, tail_tol, tail_max_steps)
        if coarse_after is not None:
            check_int(coarse_after, "coarse_after", low=2, high=MAX_BOUNCES)
            if tail is not None:
                raise ValueError(
                    f"coarse_after: the later bounces are either marched on a coarse grid "
                    f"or summed by the tail solve, not both (tail: {tail!r})"
                )
        self.tail, self.tail_tol, self.tail_max_steps = tail, float(tail_tol), int(tail_max_steps)
        f = self.refine = 1 if grid.refine is None else grid.refine
        self.height, self.width, self.n_theta = grid.height * f, grid.width * f, grid.n_theta
        self.phase = phase
        illumination.entry_wall(grid.width, grid.height)  # validates the entry point
        self.marched_basis = None
        if moments is None:
            moments = tuple(source_moments(scaled(illumination, f), self.width, self.height))
            if basis and isinstance(illumination, Stripes):  # (the render is linear in them)
                self.marched_basis, moments = marched_patterns(illumination, moments, f)
        cov, mean, var = moments
        self.coverage = jnp.asarray(cov)
        self.mean_depth = jnp.asarray(mean)
        self.var_depth = jnp.asarray(var)
        theta0 = math.radians(illumination.direction_deg)
        self.theta0_bin = int(round(theta0 / grid.dtheta)) % grid.n_theta
        # Only where there is a coarser grid and bounces after K0 to march on it.
        coarse = None if coarse_after is None else self.coarse_grid(grid)
        marched = coarse is not None and self.bounces > coarse_after
        self.coarse_after = int(coarse_after) if marched else None

    # -- what a geometry supplies --------------------------------------------------

    @abc.abstractmethod
    def first_orders(self, sigma_t, sigma_s, g, source, scattered: bool) -> FirstOrders:
        """I_1 of the unscattered fluence ``source`` (patterns, H, W) and, when
        ``scattered``, the bounce step at these values with I_2, L_1 and Q_2."""

    @abc.abstractmethod
    def integrate(self, field) -> Float[Array, "patterns n_theta H W"]:
        """A light field in the step's layout as radiance per radian of azimuth,
        direction-major (the slab integrates it over depth and elevation)."""

    @property
    @abc.abstractmethod
    def direct_depth(self) -> float:
        """The depth the direct light L_0 is integrated over (1 for the plane)."""

    @property
    @abc.abstractmethod
    def image_scale(self) -> float:
        """Images of the working grid × this = images of the model grid."""

    @property
    @abc.abstractmethod
    def field_scale(self) -> float:
        """Light fields of the working grid × this = light fields of the model grid."""

    def coarse_grid(self, grid: Grid) -> Grid | None:
        """The native grid the bounces after ``coarse_after`` are marched on, or ``None``
        where it is no coarser than ``grid``; a geometry without a coarse tail refuses
        ``coarse_after`` here."""
        raise ValueError(f"coarse_after: {type(self).__name__} has no coarse grid")

    def restrict(self, q):
        """A source of the working grid as a source of the coarse grid."""
        raise NotImplementedError

    def coarse_step(self, sigma_t, sigma_s, g):
        """The bounce step on the coarse grid, given σ per working-grid cell."""
        raise NotImplementedError

    # -- the loop -----------------------------------------------------------------

    @property
    def n_patterns(self) -> int:
        """The patterns rendered (the marched ones are fewer with :attr:`marched_basis`)."""
        if self.marched_basis is not None:
            return len(self.marched_basis.coef)
        return self.coverage.shape[0]

    def __call__(self, sigma_t, sigma_s, g, gain=1.0, lightfield: bool = False):
        check_physical(sigma_t, sigma_s, g, gain)
        return self.unchecked(sigma_t, sigma_s, g, gain, lightfield)

    def unchecked(self, sigma_t, sigma_s, g, gain=1.0, lightfield: bool = False):
        """The call without :func:`check_physical` (a fitted result's values, NaN
        included, drawn as they are)."""
        if lightfield and self.coarse_after is not None:
            raise ValueError(coarse_lightfield_refusal(self.coarse_after))
        sigma_t, sigma_s, g, gain = as_physical(sigma_t, sigma_s, g, gain)
        f = self.refine
        out = self._render(sigma_t / f, sigma_s / f, g, gain, lightfield)
        if f == 1:
            return out
        return mapped_output(
            out,
            lambda a: self.image_scale * block_mean(a, f, (-2, -1)),
            self._refined_field,
            self._refined_field,
        )

    def _refined_field(self, field):
        return self.field_scale * block_mean(field, self.refine, (-3, -2))

    def bounce_step(self, sigma_t, sigma_s, g):
        """The one-bounce operator Q_k ↦ (Q_{k+1}, I_{k+1}) at these values, on the
        working grid (σ per working pixel: divide by ``refine`` first)."""
        return self.scattered_orders(sigma_t, sigma_s, g).step

    def scattered_orders(self, sigma_t, sigma_s, g) -> FirstOrders:
        """:meth:`first_orders` of this renderer's source at these values (working-grid
        units): the bounce step, I_1, I_2, L_1 and Q_2, of the marched patterns (with
        :attr:`marched_basis`, the kept shifts then full light)."""
        return self.first_orders(sigma_t, sigma_s, g, self.unscattered(sigma_t), True)

    def unscattered(self, sigma_t) -> Float[Array, "patterns H W"]:
        """The pixel-averaged unscattered fluence of the source moments (see
        :func:`~lightfield_jax.scene.illumination.source_moments`): coverage·e^{−σt·mean}·
        sinh(x)/x with x = σt·√(3·var), the exact average of e^{−σt d} over d uniform on
        an interval of that mean and variance (the case of every pixel of an
        axis-aligned sheet). It agrees with the cumulant form exp(−σt·mean + σt²·var/2)
        to second order and, unlike it, stays exact for dense media (σt of several per
        pixel)."""
        dtype = sigma_t.dtype
        mean = self.mean_depth.astype(dtype)
        var = jnp.maximum(self.var_depth.astype(dtype), 0.0)
        x = sigma_t * jnp.sqrt(3.0 * var)
        return self.coverage.astype(dtype) * jnp.exp(-sigma_t * mean + _log_sinhc(x))

    def _direct_field(self, source):
        """L_0: the unscattered light in the illumination's direction bin."""
        dtheta = 2 * math.pi / self.n_theta
        l0 = jnp.zeros((source.shape[0], self.n_theta) + source.shape[1:], source.dtype)
        return l0.at[:, self.theta0_bin].set(self.direct_depth * source / dtheta)

    @eqx.filter_jit
    def _render(self, sigma_t, sigma_s, g, gain, lightfield: bool):
        out = self._march(sigma_t, sigma_s, g, gain, lightfield)
        return every_pattern_output(self.marched_basis, out)

    def _march(self, sigma_t, sigma_s, g, gain, lightfield: bool):
        count_trace()
        source = self.unscattered(sigma_t)
        # With a tail one more bounce is marched: its source Q_{K0+1} and image
        # I_{K0+1} seed the tail's solve.
        march = self.bounces + (self.tail is not None)
        # With a coarse tail the working grid marches the first coarse_after bounces.
        fine = self.coarse_after or march
        orders = self.first_orders(sigma_t, sigma_s, g, source, march > 1 or lightfield)
        step, q = orders.step, orders.source
        images = [orders.image[None]]
        fields = []
        if lightfield:  # L_0, L_1
            fields.append(jnp.stack([self._direct_field(source), self.integrate(orders.field)]))
        if march > 1:
            images.append(orders.second_image[None])

            def bounce(q, _):
                q_next, image, field = step.step(q)
                return q_next, (image, self.integrate(field) if lightfield else None)

            if fine > 2:
                q, (more, more_fields) = jax.lax.scan(bounce, q, None, length=fine - 2)
                images.append(more)
                if lightfield:
                    fields.append(more_fields)
            if fine < march:
                images.append(self._coarse_march(q, sigma_t, sigma_s, g, march - fine))
            if lightfield and self.tail is None:
                fields.append(self.integrate(step.transport(q))[None])  # L_K
        images = jnp.concatenate(images, axis=0)
        stacked = gain * jnp.moveaxis(images[: self.bounces], 0, 1)
        lf = gain * jnp.moveaxis(jnp.concatenate(fields, axis=0), 2, -1) if lightfield else None
        if self.tail is None:
            return stacked, lf
        tail = solve_tail(
            step.linear, q, images[-1], self.tail, self.tail_tol, self.tail_max_steps, lightfield
        )
        return (
            stacked,
            lf,
            TailSolution(
                image=gain * tail.image,
                lightfield=None
                if tail.lightfield is None
                else gain * jnp.moveaxis(self.integrate(tail.lightfield), 1, -1),
                steps=tail.steps,
                converged=tail.converged,
            ),
        )

    def _coarse_march(self, q, sigma_t, sigma_s, g, length: int):
        """Images of ``length`` bounces from Q_{K0} (working grid) marched on the coarse
        (native) grid, each pixel's value repeated over its working cells, in
        working-grid units (``__call__`` averages them back and scales them by
        ``image_scale``; the native grid's images are the model's)."""
        f = self.refine
        step = self.coarse_step(sigma_t, sigma_s, g)

        def bounce(q, _):
            return step(q)

        images = jax.lax.scan(bounce, self.restrict(q), None, length=length)[1]
        return jnp.repeat(jnp.repeat(images, f, axis=-2), f, axis=-1) / self.image_scale

    # -- the slope along g ----------------------------------------------------------

    def images_and_g_slope(self, sigma_t, sigma_s, g, gain=1.0):
        """Per-bounce images and their derivative in g, ``(images, d images/dg)``, each
        Float[Array, "patterns bounces H W"] (forward mode; a geometry may give it in one
        pass of its own code, see :meth:`_march_g_slope`)."""
        if self.tail is not None:
            raise ValueError(
                f"images_and_g_slope: per-bounce images only; this renderer has tail "
                f"{self.tail!r} (use jax.jvp through the call)"
            )
        sigma_t, sigma_s, g, gain = as_physical(sigma_t, sigma_s, g, gain)
        f = self.refine
        images, slopes = self._render_g_slope(sigma_t / f, sigma_s / f, g, gain)
        if f == 1:
            return images, slopes
        scale = self.image_scale
        return scale * block_mean(images, f, (-2, -1)), scale * block_mean(slopes, f, (-2, -1))

    @eqx.filter_jit
    def _render_g_slope(self, sigma_t, sigma_s, g, gain):
        """The images and their slope along g, every pattern (working grid)."""
        images, slopes = self._march_g_slope(sigma_t, sigma_s, g, gain)
        if self.marched_basis is None:
            return images, slopes
        return self.marched_basis.expand(images, light=True), self.marched_basis.expand(slopes)

    def _march_g_slope(self, sigma_t, sigma_s, g, gain):
        """``jax.jvp`` of the march along g (working grid, the marched patterns); a
        geometry may give it in one pass of its own code."""
        return self._march_g_jvp(sigma_t, sigma_s, g, gain)

    def _march_g_jvp(self, sigma_t, sigma_s, g, gain):
        return jax.jvp(
            lambda g: self._march(sigma_t, sigma_s, g, gain, False)[0], (g,), (jnp.ones_like(g),)
        )
