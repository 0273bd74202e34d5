"""Nominal dynamics models (Appendix D): the cartpole testbed and the 13-state quadrotor."""

from arcade_core.dynamics.cartpole import (
    CARTPOLE_NU,
    CARTPOLE_NX,
    cartpole_accel,
    cartpole_deriv,
    cartpole_nominal_step,
    cartpole_step,
    cartpole_true_step,
    sample_disturbance,
)
from arcade_core.dynamics.params import (
    CARTPOLE_DT,
    CARTPOLE_NOMINAL,
    CARTPOLE_TRUE,
    CartpoleParams,
    QuadrotorParams,
)
from arcade_core.dynamics.quadrotor import (
    QUADROTOR_NU,
    QUADROTOR_NX,
    hover_input,
    hover_state,
    predict_over_delay,
    quadrotor_deriv,
    quadrotor_step,
)

__all__ = [
    "CARTPOLE_DT",
    "CARTPOLE_NOMINAL",
    "CARTPOLE_NU",
    "CARTPOLE_NX",
    "CARTPOLE_TRUE",
    "QUADROTOR_NU",
    "QUADROTOR_NX",
    "CartpoleParams",
    "QuadrotorParams",
    "cartpole_accel",
    "cartpole_deriv",
    "cartpole_nominal_step",
    "cartpole_step",
    "cartpole_true_step",
    "hover_input",
    "hover_state",
    "predict_over_delay",
    "quadrotor_deriv",
    "quadrotor_step",
    "sample_disturbance",
]
