"""The cartpole testbed's scenario and offline data (paper Sec. V-A / Appendix D), in JAX.

The intervention schedules, the closed-loop rollouts that make the training and evaluation
data, and the vectorised nominal step the residuals are taken against. The *true* cartpole
(friction, random force disturbance) is driven by the *nominal* MPC (Appendix D): all
trajectories of one batch are simulated together (``vmap`` over trajectories inside a
``scan`` over time), so a 100-trajectory dataset is one compiled program.

Online-adaptation scenario (Sec. V-A "Online Adaptation under Nonstationary Dynamics"):
interventions at steps 0, 40 and 80, each a 2 N lateral push on the cart and a 10 %
reduction of both masses. A push that lasts one sample is not a regime, so each push is
held until the next intervention, alternating in direction (+2 N, -2 N, +2 N); the mass
reductions accumulate (0.9, 0.8, 0.7 of the original masses). Both choices are ours where the
paper is silent.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from arcade_core import mpc
from arcade_core.dynamics.cartpole import cartpole_nominal_step, cartpole_true_step
from arcade_core.dynamics.params import CARTPOLE_DT, CARTPOLE_TRUE

#: Initial states: uniform in [-b, b] per component of [x, xdot, theta, thetadot].
X0_BOUNDS = np.array([0.5, 0.5, 0.3, 0.5])
INTERVENTION_STEPS = (0, 40, 80)
PUSH_N = 2.0
MASS_REDUCTION = 0.1


class Batch(NamedTuple):
    """Trajectories: states ``X (n, T+1, 4)``, inputs ``U (n, T, 1)``."""

    X: np.ndarray
    U: np.ndarray


class Schedule(NamedTuple):
    """Per-step extra cart force ``force (T,)`` [N] and mass scale ``mass_scale (T,)``."""

    force: np.ndarray
    mass_scale: np.ndarray


def stationary_schedule(T: int) -> Schedule:
    return Schedule(np.zeros(T), np.ones(T))


def intervention_schedule(
    T: int = 120,
    steps: tuple[int, ...] = INTERVENTION_STEPS,
    push: float = PUSH_N,
    reduction: float = MASS_REDUCTION,
) -> Schedule:
    """The online-adaptation scenario (module docstring); step ``k`` acts on ``x_k -> x_{k+1}``."""
    force, scale = np.zeros(T), np.ones(T)
    for i, k in enumerate(steps):
        force[k:] = push * (-1.0) ** i
        scale[k:] = 1.0 - reduction * (i + 1)
    return Schedule(force, scale)


def _nominal_controller():
    cfg = mpc.cartpole_mpc_config()

    def step_fn(x, u, model):
        del model
        return cartpole_nominal_step(x, u)

    return mpc.make_controller(step_fn, cfg), cfg


def sample_initial_states(key: jax.Array, n: int) -> jax.Array:
    b = jnp.asarray(X0_BOUNDS)
    return jax.random.uniform(key, (n, 4), minval=-b, maxval=b)


def simulate(key: jax.Array, x0: jax.Array, schedule: Schedule) -> Batch:
    """Roll the true cartpole under the nominal MPC from each row of ``x0`` (n, 4)."""
    controller, cfg = _nominal_controller()
    T = len(schedule.force)
    x_ref = jnp.zeros((cfg.N + 1, 4))
    u_ref = jnp.zeros((cfg.N, 1))
    force = jnp.asarray(schedule.force)
    scale = jnp.asarray(schedule.mass_scale)

    def one(key, x0):
        def body(carry, inp):
            x, u_warm, u_prev = carry
            k_key, f, s = inp
            sol = controller.solve(x, x_ref, u_ref, u_warm, u_prev, jnp.zeros(()))
            u = sol.u[0]
            params = CARTPOLE_TRUE._replace(M=CARTPOLE_TRUE.M * s, m=CARTPOLE_TRUE.m * s)
            x_next = cartpole_true_step(k_key, x, u, params, CARTPOLE_DT, force=f)
            return (x_next, mpc.shift_warm_start(sol.u), u), (x_next, u)

        init = (x0, jnp.zeros((cfg.N, 1)), jnp.zeros(1))
        keys = jax.random.split(key, T)
        _, (xs, us) = jax.lax.scan(body, init, (keys, force, scale))
        return jnp.concatenate([x0[None], xs]), us

    keys = jax.random.split(key, x0.shape[0])
    X, U = jax.jit(jax.vmap(one))(keys, x0)
    X, U = np.asarray(X), np.asarray(U)
    if not (np.isfinite(X).all() and np.isfinite(U).all()):
        raise RuntimeError("cartpole simulation produced non-finite states")
    return Batch(X, U)


def transitions(batch: Batch, idx: np.ndarray | None = None):
    """Stack ``(x_k, u_k, x_{k+1})`` of the selected trajectories into flat arrays."""
    X, U = (batch.X, batch.U) if idx is None else (batch.X[idx], batch.U[idx])
    return (
        X[:, :-1].reshape(-1, X.shape[-1]),
        U.reshape(-1, U.shape[-1]),
        X[:, 1:].reshape(-1, X.shape[-1]),
    )


def nominal_next(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Vectorised nominal step ``f_nom(x, u)`` (Appendix D)."""
    return np.asarray(jax.vmap(cartpole_nominal_step)(jnp.asarray(x), jnp.asarray(u)))
