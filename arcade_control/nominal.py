"""The nominal model at the control period (Appendix D): the one place for ``CONTROL_DT``.

The closed loop runs one MPC solve per control period ``CONTROL_DT = 0.05 s`` (20 Hz) and
holds the setpoint in between; the residual model is learned at that step, so
``f_nom(x, u)`` is the nominal RK4 step of :func:`arcade_core.dynamics.quadrotor_step` over
it, with the parameters of the shipped default vehicle (read once through
:mod:`arcade_io.vehicle`). Flight logs are recorded at :data:`LOG_DT`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from arcade_core.dynamics import quadrotor_step
from arcade_io.vehicle import load_vehicle, quadrotor_params

#: Control (= MPC step = residual) period [s] and log period [s].
CONTROL_DT = 0.05
LOG_DT = 0.01
LOG_PER_CONTROL = round(CONTROL_DT / LOG_DT)


@functools.cache
def nominal_params():
    """Nominal-model parameters of the shipped default vehicle (read once).

    Evaluated eagerly even when first called while a function is being traced, so the
    cached value never holds tracers.
    """
    with jax.ensure_compile_time_eval():
        return quadrotor_params(load_vehicle())


def f_nom(x, u):
    """Nominal RK4 step ``f_nom(x, u)`` over :data:`CONTROL_DT` (Appendix D), one sample."""
    return quadrotor_step(x, u, nominal_params(), CONTROL_DT)


def nominal_next(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """:func:`f_nom` for every row of ``x`` (n, 13) and ``u`` (n, 4)."""
    return np.asarray(jax.jit(jax.vmap(f_nom))(jnp.asarray(x), jnp.asarray(u)), dtype=float)
