"""Reference trajectories for the quadrotor (Sec. V figure-eight flights, Appendix D).

A *path* is a small NamedTuple with a ``position(t) -> (3,)`` method giving a smooth
world-ENU position. Everything else follows from differential flatness of the nominal
model (``arcade_core.dynamics.quadrotor``): the time derivatives of the position are taken
exactly with nested forward-mode autodiff, the thrust vector ``m (a + g e3)`` fixes the
thrust and the body z axis, the yaw fixes the rest of the attitude, and the body rates
follow from ``omega = vee(R^T Rdot)``. Since the nominal rate loop is a first-order lag,
the rate *setpoint* is ``omega + rate_tau * omegadot``, so the reference input is exact
for the continuous-time nominal model.

Paths are pytrees, so they can be passed to jitted functions without recompiling when
their numbers change.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple, Protocol

import jax
import jax.numpy as jnp
from jax import Array

from arcade_core import frames as quat
from arcade_core.dynamics.params import QuadrotorParams

_ARC_SAMPLES = 2048  # midpoint-rule samples for the figure-eight arc length


class Path(Protocol):
    def position(self, t: Array) -> Array: ...


class FigureEight(NamedTuple):
    """Lemniscate of Gerono in the horizontal plane at height ``center[2]``.

    ``p(t) = center + [a sin(phi), b sin(2 phi), 0]`` with ``phi = 2 pi t / period``:
    it starts at the centre and flies the ``x > 0`` loop first. ``speed`` is the *mean*
    speed along the curve [m/s]; the period is the arc length divided by it.
    """

    center: Array | tuple[float, float, float] = (0.0, 0.0, 1.0)
    half_length: float | Array = 1.5  # a: x extent [m]
    half_width: float | Array = 0.75  # b: y extent [m]
    speed: float | Array = 1.0  # mean speed [m/s]

    def arc_length(self) -> Array:
        """Length of one full figure-eight [m] (fixed-grid midpoint rule, jit-friendly)."""
        phi = (jnp.arange(_ARC_SAMPLES) + 0.5) * (2 * jnp.pi / _ARC_SAMPLES)
        a, b = self.half_length, self.half_width
        dpath = jnp.sqrt((a * jnp.cos(phi)) ** 2 + (2 * b * jnp.cos(2 * phi)) ** 2)
        return jnp.sum(dpath) * (2 * jnp.pi / _ARC_SAMPLES)

    def period(self) -> Array:
        """Time for one figure-eight [s] at the mean ``speed``."""
        return self.arc_length() / self.speed

    def position(self, t: Array) -> Array:
        phi = 2 * jnp.pi * t / self.period()
        c = jnp.asarray(self.center, dtype=phi.dtype)
        offset = jnp.stack(
            [self.half_length * jnp.sin(phi), self.half_width * jnp.sin(2 * phi), 0.0 * phi]
        )
        return c + offset


class Circle(NamedTuple):
    """Circle in the horizontal plane at height ``center[2]``, flown counter-clockwise.

    ``p(t) = center + r [cos(phi), sin(phi), 0]`` with ``phi = speed t / r``: it starts on
    the ``+x`` side of the centre; ``speed`` is constant [m/s].
    """

    center: Array | tuple[float, float, float] = (0.0, 0.0, 1.0)
    radius: float | Array = 1.5
    speed: float | Array = 1.0

    def period(self) -> Array:
        """Time for one circle [s]."""
        return 2 * jnp.pi * jnp.asarray(self.radius) / self.speed

    def position(self, t: Array) -> Array:
        phi = self.speed * t / self.radius
        c = jnp.asarray(self.center, dtype=jnp.result_type(phi, float))
        return c + self.radius * jnp.stack([jnp.cos(phi), jnp.sin(phi), 0.0 * phi])


class Lissajous(NamedTuple):
    """Three-axis Lissajous curve ``p(t) = center + A * sin(n * phi)`` (per axis, integer
    ``n``), ``phi = 2 pi t / period``: it starts at the centre. ``speed`` is the *mean*
    speed along the curve [m/s]; the period is the arc length divided by it.
    """

    center: Array | tuple[float, float, float] = (0.0, 0.0, 1.0)
    amplitude: Array | tuple[float, float, float] = (1.5, 1.0, 0.25)
    frequency: Array | tuple[float, float, float] = (1.0, 3.0, 2.0)
    speed: float | Array = 1.0

    def arc_length(self) -> Array:
        """Length of one period [m] (fixed-grid midpoint rule, jit-friendly)."""
        phi = (jnp.arange(_ARC_SAMPLES) + 0.5) * (2 * jnp.pi / _ARC_SAMPLES)
        a, n = jnp.asarray(self.amplitude), jnp.asarray(self.frequency)
        d = a[:, None] * n[:, None] * jnp.cos(n[:, None] * phi[None, :])
        return jnp.sum(jnp.linalg.norm(d, axis=0)) * (2 * jnp.pi / _ARC_SAMPLES)

    def period(self) -> Array:
        """Time for one period [s] at the mean ``speed``."""
        return self.arc_length() / self.speed

    def position(self, t: Array) -> Array:
        phi = 2 * jnp.pi * t / self.period()
        c = jnp.asarray(self.center, dtype=phi.dtype)
        a = jnp.asarray(self.amplitude, dtype=phi.dtype)
        return c + a * jnp.sin(jnp.asarray(self.frequency, dtype=phi.dtype) * phi)


class PiecewisePolynomial(NamedTuple):
    """A position given piece by piece (a fitted spline; scipy's ``PPoly`` layout).

    On ``[breaks[i], breaks[i+1])`` the position is ``sum_k coeffs[k, i] (t -
    breaks[i])^(K-1-k)`` for ``K`` coefficients per axis; ``t`` is clamped to
    ``[breaks[0], breaks[-1]]`` (the path holds its first and last points outside).
    """

    breaks: Array  # (M+1,) increasing times [s]
    coeffs: Array  # (K, M, 3), highest power first

    def position(self, t: Array) -> Array:
        b = jnp.asarray(self.breaks)
        tc = jnp.clip(t, b[0], b[-1])
        i = jnp.clip(jnp.searchsorted(b, tc, side="right") - 1, 0, b.shape[0] - 2)
        dt = tc - b[i]
        c = jnp.asarray(self.coeffs)[:, i]
        p = c[0]
        for k in range(1, c.shape[0]):  # Horner
            p = p * dt + c[k]
        return p


class Headed(NamedTuple):
    """``path`` flown with a varying heading: the yaw [rad] of ``yaw`` (a one-axis
    :class:`PiecewisePolynomial`) at ``t - t0`` (its first value before ``t0``)."""

    path: Path
    yaw: PiecewisePolynomial
    t0: float | Array

    def position(self, t: Array) -> Array:
        return self.path.position(t)

    def heading(self, t: Array) -> Array:
        return self.yaw.position(t - self.t0)[0]


class Offset(NamedTuple):
    """``path`` moved by ``offset`` [m]."""

    path: Path
    offset: Array | tuple[float, float, float]

    def position(self, t: Array) -> Array:
        p = self.path.position(t)
        return p + jnp.asarray(self.offset, dtype=p.dtype)


class Hover(NamedTuple):
    """Hold a fixed position."""

    point: Array | tuple[float, float, float] = (0.0, 0.0, 1.0)

    def position(self, t: Array) -> Array:
        return jnp.asarray(self.point, dtype=jnp.result_type(t, float)) + 0.0 * t


class Takeoff(NamedTuple):
    """Rest-to-rest straight segment from ``start`` to ``end`` over ``duration`` seconds.

    Uses the degree-7 smoothstep ``35s^4 - 84s^5 + 70s^6 - 20s^7``, whose velocity,
    acceleration and jerk vanish at both ends, so thrust and body rates are continuous
    when it is chained with a hover or a figure-eight starting at rest in attitude.
    """

    start: Array | tuple[float, float, float] = (0.0, 0.0, 0.0)
    end: Array | tuple[float, float, float] = (0.0, 0.0, 1.0)
    duration: float | Array = 3.0

    def position(self, t: Array) -> Array:
        s = jnp.clip(t / self.duration, 0.0, 1.0)
        blend = s**4 * (35 - 84 * s + 70 * s**2 - 20 * s**3)
        p0 = jnp.asarray(self.start, dtype=blend.dtype)
        p1 = jnp.asarray(self.end, dtype=blend.dtype)
        return p0 + blend * (p1 - p0)


class Chain(NamedTuple):
    """``first`` until ``switch_time``, then ``second`` with its clock restarted at zero."""

    first: Path
    second: Path
    switch_time: float | Array

    def position(self, t: Array) -> Array:
        return jnp.where(
            t < self.switch_time,
            self.first.position(t),
            self.second.position(t - self.switch_time),
        )


def _derivative(f):
    """d/dt of a function of the scalar time, by forward-mode autodiff."""

    def df(t):
        return jax.jvp(f, (t,), (jnp.ones_like(t),))[1]

    return df


def flat_state(
    path: Path, t: Array | float, params: QuadrotorParams, yaw: Array | float = 0.0
) -> tuple[Array, Array]:
    """Nominal state (13,) and input (4,) at time ``t`` by differential flatness (App. D model).

    Thrust ``T = m |a + g e3|``; body z axis along the thrust vector; heading fixed by a
    constant ``yaw``, or following the path's own ``heading(t)`` [rad] if it has one
    (:class:`Headed`); ``omega = vee(R^T Rdot)``; rate setpoint ``omega + tau omegadot``.
    """
    t = jnp.asarray(t, dtype=jnp.result_type(t, float))
    e3 = jnp.array([0.0, 0.0, 1.0], dtype=t.dtype)
    x_c = jnp.stack([jnp.cos(yaw), jnp.sin(yaw), 0.0 * yaw]).astype(t.dtype)
    heading = getattr(path, "heading", None)

    def course(s):
        """The heading axis ``[cos yaw, sin yaw, 0]`` at ``s``."""
        if heading is None:
            return x_c
        psi = heading(s)
        return jnp.stack([jnp.cos(psi), jnp.sin(psi), 0.0 * psi]).astype(s.dtype)

    pos = path.position
    vel = _derivative(pos)
    acc = _derivative(vel)

    def thrust_vector(s):
        return params.mass * (acc(s) + params.gravity * e3)

    def attitude(s):
        f = thrust_vector(s)
        z_b = f / jnp.linalg.norm(f)
        y_b = jnp.cross(z_b, course(s))
        y_b = y_b / jnp.linalg.norm(y_b)
        x_b = jnp.cross(y_b, z_b)
        return jnp.stack([x_b, y_b, z_b], axis=-1)

    def body_rates(s):
        R, R_dot = jax.jvp(attitude, (s,), (jnp.ones_like(s),))
        return quat.vee(R.T @ R_dot)

    omega, omega_dot = jax.jvp(body_rates, (t,), (jnp.ones_like(t),))
    x = jnp.concatenate([pos(t), vel(t), quat.from_rotation_matrix(attitude(t)), omega])
    u = jnp.concatenate(
        [jnp.linalg.norm(thrust_vector(t))[None], omega + params.rate_tau * omega_dot]
    )
    return x, u


@partial(jax.jit, static_argnames=("N", "dt"))
def quadrotor_reference(
    t0: Array | float,
    N: int,
    dt: float,
    path: Path,
    params: QuadrotorParams,
    yaw: Array | float = 0.0,
) -> tuple[Array, Array]:
    """MPC references over a horizon: ``x_ref`` (N+1, 13) at ``t0 + i dt`` and ``u_ref`` (N, 4).

    Differential flatness of the nominal quadrotor (Appendix D); see ``flat_state``.
    Jitted (``N`` and ``dt`` static) because it is called at every control step.
    """
    t0 = jnp.asarray(t0, dtype=jnp.result_type(t0, float))
    times = t0 + dt * jnp.arange(N + 1, dtype=t0.dtype)
    xs, us = jax.vmap(lambda s: flat_state(path, s, params, yaw))(times)
    return xs, us[:N]
