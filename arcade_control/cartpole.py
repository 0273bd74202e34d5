"""The cartpole testbed's scenario and offline data (paper Sec. V-A / Appendix D), in JAX.

The intervention schedules, the closed-loop rollouts that make the training and evaluation
data, and the vectorised nominal step the residuals are taken against. The *true* cartpole
(friction, random force disturbance) is driven by the *nominal* MPC (Appendix D): all
trajectories of one batch are simulated together (``vmap`` over trajectories inside a
``scan`` over time), so a 100-trajectory dataset is one compiled program.

Online-adaptation scenario (Sec. V-A "Online Adaptation under Nonstationary Dynamics"),
as written: interventions at steps 0, 40 and 80, each a 2 N lateral impulse on the cart and
a 10 % reduction of both masses. The impulse is a pulse of :data:`PULSE_STEPS` control
period (0.05 s, so 0.1 N s), always in +x; the masses are multiplied by 0.9 at each
intervention (0.9, 0.81, 0.729 of the original masses). The disturbance
``u_dist ~ N(-0.5, 0.5)`` is read as mean and standard deviation (std 0.5) and drawn anew
at every step (:data:`TRUE_PARAMS`).

Assumptions where the paper is silent: the control period ``dt = 0.05 s``
(``CARTPOLE_DT``), the pulse's length and sign, and the initial states, uniform in
``±X0_BOUNDS`` per component. The range is wide enough (pole up to ±0.6 rad) that the
nominal MPC's first seconds need forces of several newtons, where the nominal model's
mismatch (masses, length, no friction) and the mass shifts show in the residuals; the
nominal MPC stabilises every such state.

Variants (labelled, not the headline): ``pulse_steps=None`` holds each push until the next
intervention, alternating in direction (+2 N, -2 N, +2 N) — this testbed's earlier reading;
:data:`NOISE_READINGS` ``"variance"`` reads 0.5 as the variance (std 0.71).
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
X0_BOUNDS = np.array([1.0, 1.0, 0.6, 1.0])
INTERVENTION_STEPS = (0, 40, 80)
PUSH_N = 2.0
#: Length of the impulse in control periods (0.05 s each); ``None`` holds it (variant).
PULSE_STEPS = 1
#: Each intervention multiplies both masses by this factor.
MASS_FACTOR = 0.9
#: Standard deviation of ``u_dist`` [N] for each reading of the paper's ``N(-0.5, 0.5)``.
NOISE_READINGS = {"std": 0.5, "variance": float(np.sqrt(0.5))}
#: The true cartpole of the testbed: Appendix D, disturbance std 0.5 (``N(mean, std)``).
TRUE_PARAMS = CARTPOLE_TRUE._replace(dist_std=NOISE_READINGS["std"])


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
    factor: float = MASS_FACTOR,
    pulse_steps: int | None = PULSE_STEPS,
) -> Schedule:
    """The online-adaptation scenario (module docstring); step ``k`` acts on ``x_k -> x_{k+1}``.

    A ``push`` [N] for ``pulse_steps`` periods from each intervention step, or (``None``,
    the held variant) until the next one with alternating sign; the masses are multiplied
    by ``factor`` at each intervention.
    """
    if pulse_steps is not None and pulse_steps < 1:
        raise ValueError(f"pulse_steps must be >= 1 or None, got {pulse_steps}")
    force, scale = np.zeros(T), np.ones(T)
    for i, k in enumerate(steps):
        if pulse_steps is None:
            force[k:] = push * (-1.0) ** i
        else:
            force[k : k + pulse_steps] = push
        scale[k:] = factor ** (i + 1)
    return Schedule(force, scale)


def scaled(params, s):
    """``params`` with cart and pole masses multiplied by ``s``."""
    return params._replace(M=params.M * s, m=params.m * s)


def _nominal_controller():
    cfg = mpc.cartpole_mpc_config()

    def step_fn(x, u, model):
        del model
        return cartpole_nominal_step(x, u)

    return mpc.make_controller(step_fn, cfg), cfg


def sample_initial_states(key: jax.Array, n: int) -> jax.Array:
    b = jnp.asarray(X0_BOUNDS)
    return jax.random.uniform(key, (n, 4), minval=-b, maxval=b)


def simulate(key: jax.Array, x0: jax.Array, schedule: Schedule, params=TRUE_PARAMS) -> Batch:
    """Roll the true cartpole ``params`` under the nominal MPC from each row of ``x0`` (n, 4)."""
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
            x_next = cartpole_true_step(k_key, x, u, scaled(params, s), CARTPOLE_DT, force=f)
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
