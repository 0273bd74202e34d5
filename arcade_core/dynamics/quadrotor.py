"""Nominal 13-state quadrotor model (Appendix D, design §4).

State ``x = [p(3), v(3), q(4), omega(3)]``: position and velocity in world ENU, the
unit quaternion ``q = [w, x, y, z]`` rotating body FLU into world, body rates in FLU.
Input ``u = [T, omega_cmd(3)]``: collective thrust [N] and body-rate setpoints [rad/s],
which is what PX4's offboard rate interface accepts.

Departure from Appendix D: the paper's inputs are thrust and body torques with
``omegadot = J^-1 (M - omega x J omega)``. Our vehicle runs its own rate loop, so the
nominal model represents the closed rate loop as a first-order lag
``omegadot = (omega_cmd - omega) / rate_tau`` instead.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

from arcade_core import frames as quat
from arcade_core.dynamics.params import QuadrotorParams

#: State and input dimensions.
QUADROTOR_NX = 13
QUADROTOR_NU = 4

#: Index slices into the state vector.
POS = slice(0, 3)
VEL = slice(3, 6)
QUAT = slice(6, 10)
RATE = slice(10, 13)


def quadrotor_deriv(x: Array, u: Array, params: QuadrotorParams) -> Array:
    """Continuous-time dynamics ``xdot = f(x, u)`` (Appendix D, rate-lag variant).

    ``pdot = v``, ``vdot = (T/m) R(q) e3 - g e3``, ``qdot = 0.5 q ⊗ [0, omega]``,
    ``omegadot = (omega_cmd - omega) / rate_tau``.
    """
    v, q, w = x[VEL], x[QUAT], x[RATE]
    thrust, w_cmd = u[0], u[1:4]
    z_body = quat.body_z_axis(q)
    e3 = jnp.array([0.0, 0.0, 1.0], dtype=x.dtype)
    vdot = (thrust / params.mass) * z_body - params.gravity * e3
    qdot = 0.5 * quat.multiply(q, jnp.concatenate([jnp.zeros((1,), x.dtype), w]))
    wdot = (w_cmd - w) / params.rate_tau
    return jnp.concatenate([v, vdot, qdot, wdot])


def quadrotor_step(x: Array, u: Array, params: QuadrotorParams, dt: float) -> Array:
    """One classical Runge-Kutta (RK4) step with zero-order-hold input (Appendix D).

    The quaternion is renormalised afterwards so it stays on S^3 over long rollouts.
    """
    k1 = quadrotor_deriv(x, u, params)
    k2 = quadrotor_deriv(x + 0.5 * dt * k1, u, params)
    k3 = quadrotor_deriv(x + 0.5 * dt * k2, u, params)
    k4 = quadrotor_deriv(x + dt * k3, u, params)
    x_next = x + (dt / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
    return x_next.at[QUAT].set(quat.normalize(x_next[QUAT]))


def predict_over_delay(
    x: Array, var: Array, u: Array, params: QuadrotorParams, delay: float
) -> tuple[Array, Array]:
    """The state ``delay`` seconds on, when the setpoint sent now reaches the rate loop.

    Not an equation of the paper: a link that delays every setpoint by ``delay`` (< one
    control period) keeps the previous setpoint ``u`` acting until then, so a controller
    that plans, and an adapter that learns, from the predicted state see each input act over
    exactly one period. One RK4 step of the nominal model (:func:`quadrotor_step`) with
    ``u``; ``var`` ``(13,)``, the state's diagonal variance, is carried to first order
    (``diag(J diag(var) J^T)``, ``J = d step / dx``).
    """
    jac = jax.jacfwd(quadrotor_step)(x, u, params, delay)
    return quadrotor_step(x, u, params, delay), jnp.einsum("ij,j,ij->i", jac, var, jac)


def hover_input(params: QuadrotorParams, dtype=None) -> Array:
    """Hover input ``U_0 = [m g, 0, 0, 0]`` (Appendix D MPC table: hover thrust, zero rates)."""
    T = jnp.asarray(params.mass * params.gravity, dtype=dtype)
    return jnp.concatenate([T[None], jnp.zeros((3,), T.dtype)])


def hover_state(position: Array | None = None, dtype=None) -> Array:
    """State at rest, level, at ``position`` (default the origin)."""
    p = jnp.zeros((3,), dtype) if position is None else jnp.asarray(position, dtype)
    q = jnp.array([1.0, 0.0, 0.0, 0.0], dtype=p.dtype)
    return jnp.concatenate([p, jnp.zeros((3,), p.dtype), q, jnp.zeros((3,), p.dtype)])
