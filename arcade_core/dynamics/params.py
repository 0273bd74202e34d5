"""Physical parameters of the nominal models, as immutable pytrees.

The files that hold these numbers (vehicle TOML files) are read outside the core, by
``arcade_io.vehicle``; the core only sees arrays.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

#: JAX's default float (float32, or float64 with ``jax_enable_x64``) when this is imported.
#: The constants below are made on the host in it and put on the device as they are: an
#: operation made at import would be compiled in every process that imports the models,
#: before it has set up the compilation cache. The values are those of the JAX operations
#: (IEEE square root and rounding).
_FLOAT = jnp.result_type(float)


class CartpoleParams(NamedTuple):
    """Cartpole parameters (paper Appendix D).

    ``dist_mean``/``dist_std`` describe the additive force disturbance
    u_dist ~ N(mean, variance) with the paper's N(-0.5, 0.5) read as variance 0.5.
    """

    M: float | Array  # cart mass [kg]
    m: float | Array  # pole mass [kg]
    L: float | Array  # pole length [m]
    g: float | Array = 9.81
    mu_c: float | Array = 0.0  # cart viscous friction [N s/m]
    mu_p: float | Array = 0.0  # pole viscous friction [N m s/rad]
    dist_mean: float | Array = 0.0  # [N]
    dist_std: float | Array = 0.0  # [N]


#: The paper's "true" cartpole (Appendix D): friction and a N(-0.5, 0.5) force disturbance.
CARTPOLE_TRUE = CartpoleParams(
    M=1.0,
    m=0.1,
    L=1.5,
    mu_c=0.25,
    mu_p=0.05,
    dist_mean=-0.5,
    dist_std=float(np.sqrt(_FLOAT.type(0.5))),
)
#: The paper's nominal cartpole (Appendix D): other masses and length, no friction, no disturbance.
CARTPOLE_NOMINAL = CartpoleParams(M=1.7, m=0.25, L=1.7)
#: Cartpole integration step [s] (forward Euler, Appendix D). 20 Hz, as a typical MPC rate.
CARTPOLE_DT = 0.05


class QuadrotorParams(NamedTuple):
    """Nominal quadrotor parameters (design §4), SI units, world ENU / body FLU.

    Input u = [collective thrust N, body-rate setpoints rad/s (3)]; the body rates follow
    their setpoints as a first-order lag with time constant ``rate_tau``.
    """

    mass: float | Array = 0.57  # airframe 0.55 kg + 20 g electromagnet [kg]
    inertia: Array = jax.device_put(np.array([1.1e-3, 1.1e-3, 1.9e-3], _FLOAT))  # FLU [kg m^2]
    gravity: float | Array = 9.81  # [m/s^2]
    rate_tau: float | Array = 0.05  # closed-loop body-rate time constant [s]
