"""Cartpole models of Appendix D: the "true" system and the nominal MPC model.

State ``x = [x, xdot, theta, thetadot]`` (``theta`` from the upright vertical), input
``u`` the horizontal force on the cart [N]. Both models use the same equations of motion
(Appendix D) and forward-Euler discretisation; the true system adds viscous friction
``mu_c``, ``mu_p`` and an additive force disturbance ``u_dist ~ N(mean, std^2)``.

The equations are implemented exactly as printed in Appendix D. Note that they are not
the textbook upright pendulum: in the cart equation the gravity term enters as
``+ m sin(theta) g cos(theta)`` (the sign of the hanging pendulum). Both the true system
and the nominal model share this form, so the benchmark is self-consistent.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

from arcade_core.dynamics.params import (
    CARTPOLE_DT,
    CARTPOLE_NOMINAL,
    CARTPOLE_TRUE,
    CartpoleParams,
)

#: State and input dimensions.
CARTPOLE_NX = 4
CARTPOLE_NU = 1


def _force(u: Array | float) -> Array:
    # The input may arrive as shape (1,) (MPC) or as a scalar (simulation scripts).
    u = jnp.asarray(u)
    return u.reshape(()) if u.ndim else u


def cartpole_accel(
    x: Array, u: Array | float, params: CartpoleParams, u_dist: Array | float = 0.0
) -> tuple[Array, Array]:
    """Cart and pole accelerations ``(xddot, thetaddot)`` (Appendix D equations of motion).

    ``params.mu_c``/``params.mu_p`` are the viscous friction coefficients (zero for the
    nominal model) and ``u_dist`` the additive force disturbance.
    """
    M, m, L, g = params.M, params.m, params.L, params.g
    _, xdot, th, thdot = x[0], x[1], x[2], x[3]
    f = _force(u) + u_dist
    s, c = jnp.sin(th), jnp.cos(th)
    den = M + m * s**2
    xddot = (f - params.mu_c * xdot + m * s * (L * thdot**2 + g * c)) / den
    thddot = (-f * c - params.mu_p * thdot - m * L * thdot**2 * s * c + (M + m) * g * s) / (L * den)
    return xddot, thddot


def cartpole_deriv(
    x: Array, u: Array | float, params: CartpoleParams, u_dist: Array | float = 0.0
) -> Array:
    """Continuous-time state derivative ``xdot = f(x, u)`` (Appendix D)."""
    xddot, thddot = cartpole_accel(x, u, params, u_dist)
    return jnp.stack([x[1], xddot, x[3], thddot])


def cartpole_step(
    x: Array,
    u: Array | float,
    params: CartpoleParams,
    dt: float = CARTPOLE_DT,
    u_dist: Array | float = 0.0,
) -> Array:
    """One forward-Euler step ``x + dt f(x, u)`` (Appendix D discretisation)."""
    return x + dt * cartpole_deriv(x, u, params, u_dist)


def sample_disturbance(key: Array, params: CartpoleParams = CARTPOLE_TRUE) -> Array:
    """Draw ``u_dist ~ N(dist_mean, dist_std^2)`` (Appendix D external disturbance)."""
    return params.dist_mean + params.dist_std * jax.random.normal(key, ())


def cartpole_true_step(
    key: Array | None,
    x: Array,
    u: Array | float,
    params: CartpoleParams = CARTPOLE_TRUE,
    dt: float = CARTPOLE_DT,
    force: Array | float = 0.0,
    u_dist: Array | float | None = None,
) -> Array:
    """One step of the "true" cartpole (Appendix D): friction plus a random force.

    The disturbance is drawn from ``key`` unless ``u_dist`` is given explicitly
    (``key`` may then be ``None``). ``force`` is an extra additive force on the cart, for
    impulse interventions and regime shifts.
    """
    if u_dist is None:
        if key is None:
            raise ValueError("cartpole_true_step needs a PRNG key or an explicit u_dist")
        u_dist = sample_disturbance(key, params)
    return cartpole_step(x, u, params, dt, u_dist + force)


def cartpole_nominal_step(
    x: Array, u: Array | float, dt: float = CARTPOLE_DT, params: CartpoleParams = CARTPOLE_NOMINAL
) -> Array:
    """One step of the nominal model used by MPC (Appendix D): no friction, no disturbance."""
    nominal = params._replace(mu_c=0.0, mu_p=0.0, dist_mean=0.0, dist_std=0.0)
    return cartpole_step(x, u, nominal, dt)
