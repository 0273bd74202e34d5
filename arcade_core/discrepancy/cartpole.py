"""Cartpole model with the library's effects (Appendix D equations, JAX).

The nominal model is :func:`arcade_core.dynamics.cartpole.cartpole_accel` with the model
file's ``M, m, L`` (Appendix D nominal by default) and forward-Euler steps of the log
period (Appendix D discretisation). Effects:

- ``cart_viscous_friction`` ``mu_c`` and ``pole_viscous_friction`` ``mu_p``: the
  friction terms of Appendix D's true system;
- ``coulomb_friction`` ``F_c``: cart force ``-F_c tanh(xdot / 0.01 m/s)`` (a smoothed sign,
  so that the model stays differentiable);
- ``force_bias``: a constant cart force (the mean of Appendix D's force disturbance);
- ``mass_mismatch`` / ``length_mismatch``: the actual ``M, m`` and ``L``.

Parameter vector ``theta`` (:data:`GROUPS`): ``mu_c, mu_p, F_c, bias, M, m, L``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from arcade_core.dynamics.cartpole import cartpole_accel
from arcade_core.dynamics.params import CartpoleParams

GROUPS: tuple[tuple[str, tuple[int, ...]], ...] = (
    ("cart_viscous_friction", (0,)),
    ("pole_viscous_friction", (1,)),
    ("coulomb_friction", (2,)),
    ("force_bias", (3,)),
    ("mass_mismatch", (4, 5)),
    ("length_mismatch", (6,)),
)
N_THETA = 7
#: No cartpole effect acts only through another (see the quadrotor's ``CARRIERS``).
CARRIERS: dict[str, tuple[str, ...]] = {}
THETA_LOW = (0.0, 0.0, 0.0, -3.0, 0.1, 0.01, 0.1)
THETA_HIGH = (2.0, 0.5, 3.0, 3.0, 10.0, 2.0, 5.0)
#: Velocity over which the Coulomb friction's sign is smoothed [m/s].
COULOMB_SMOOTHING = 0.01


class CartpoleModel(NamedTuple):
    """The nominal cartpole of a model file: masses, length, gravity."""

    M: float | Array
    m: float | Array
    L: float | Array
    g: float | Array = 9.81

    @classmethod
    def from_params(cls, p: CartpoleParams) -> CartpoleModel:
        return cls(float(p.M), float(p.m), float(p.L), float(p.g))


def theta_off(model: CartpoleModel) -> Array:
    """``theta`` with every effect off: the model file's nominal cartpole."""
    return jnp.array([0.0, 0.0, 0.0, 0.0, model.M, model.m, model.L])


def theta_from_effects(model: CartpoleModel, tables) -> Array:
    """``theta`` of effect tables (canonical names, physical parameters)."""
    th = theta_off(model)
    names = {
        "cart_viscous_friction": ((0, "mu_c"),),
        "pole_viscous_friction": ((1, "mu_p"),),
        "coulomb_friction": ((2, "force_n"),),
        "force_bias": ((3, "mean_n"),),
        "mass_mismatch": ((4, "cart_mass_kg"), (5, "pole_mass_kg")),
        "length_mismatch": ((6, "pole_length_m"),),
    }
    for name, table in tables.items():
        if name not in names:
            raise ValueError(f"unknown cartpole effect {name!r}")
        for i, key in names[name]:
            th = th.at[i].set(float(table[key]))
    return th


def effect_params(theta, name: str) -> dict[str, float]:
    """Physical parameters of effect ``name`` from ``theta`` (library units)."""
    th = [float(v) for v in theta]
    tables = {
        "cart_viscous_friction": {"mu_c": th[0]},
        "pole_viscous_friction": {"mu_p": th[1]},
        "coulomb_friction": {"force_n": th[2]},
        "force_bias": {"mean_n": th[3]},
        "mass_mismatch": {"cart_mass_kg": th[4], "pole_mass_kg": th[5]},
        "length_mismatch": {"pole_length_m": th[6]},
    }
    if name not in tables:
        raise ValueError(f"unknown cartpole effect {name!r}")
    return tables[name]


def _params(model: CartpoleModel, theta: Array) -> CartpoleParams:
    return CartpoleParams(
        M=theta[4], m=theta[5], L=theta[6], g=model.g, mu_c=theta[0], mu_p=theta[1]
    )


def deriv(model: CartpoleModel, theta: Array, x: Array, u) -> Array:
    """``xdot`` of the cartpole with effects (Appendix D equations of motion)."""
    force = theta[3] - theta[2] * jnp.tanh(x[1] / COULOMB_SMOOTHING)
    xdd, thdd = cartpole_accel(x, u, _params(model, theta), force)
    return jnp.stack([x[1], xdd, x[3], thdd])


def step(model: CartpoleModel, theta: Array, x: Array, u, dt: float) -> Array:
    """One forward-Euler step (Appendix D discretisation)."""
    return x + dt * deriv(model, theta, x, u)


def true_step(model: CartpoleModel, theta: Array, x: Array, u, dt: float, noise) -> Array:
    """A step of the "true" system: the model with effects plus a random cart force."""
    return step(model, theta, x, jnp.asarray(u) + noise, dt)


def predict_windows(
    model: CartpoleModel,
    theta: Array,
    X: Array,
    U: Array,
    starts: Array,
    steps: int,
    dt: float,
) -> Array:
    """Predictions ``(len(starts), steps, 4)`` after 1..``steps`` steps from each ``X[start]``."""

    def one(k0):
        def body(x, j):
            x = step(model, theta, x, U[k0 + j, 0], dt)
            return x, x

        return jax.lax.scan(body, X[k0], jnp.arange(steps))[1]

    return jax.vmap(one)(starts)
