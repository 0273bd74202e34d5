"""The "true" cartpole as a stateful system (paper Appendix D), for the cartpole testbed.

A thin, seeded wrapper around :func:`arcade_core.dynamics.cartpole.cartpole_true_step`, so
that the system a controller runs against is exactly the one the datasets come from:
viscous friction, a random force disturbance ``u_dist ~ N(mean, std^2)`` drawn once per
control period (held over it), and the paper's interventions (Sec. V-A): a lateral impulse
on the cart (:meth:`CartpoleSim.push`) and a change of the cart and pole masses
(:meth:`CartpoleSim.scale_masses`).

State ``[x, xdot, theta, thetadot]`` (theta from upright), input the cart force [N].
"""

from __future__ import annotations

import jax
import numpy as np

from arcade_core.dynamics.cartpole import cartpole_true_step
from arcade_core.dynamics.params import CARTPOLE_DT, CARTPOLE_TRUE, CartpoleParams

_step = jax.jit(cartpole_true_step, static_argnames=("dt",))


class CartpoleSim:
    """Seeded "true" cartpole stepping one control period ``dt`` per :meth:`step`."""

    def __init__(
        self, params: CartpoleParams = CARTPOLE_TRUE, *, dt: float = CARTPOLE_DT, seed: int = 0
    ):
        self._initial_params = params
        self.dt = float(dt)
        self._rng = np.random.default_rng(seed)
        self.reset()

    def reset(self, state=(0.0, 0.0, 0.0, 0.0)) -> np.ndarray:
        """Restart at ``state`` with the initial parameters; returns the state."""
        self.params = self._initial_params
        self._x = np.asarray(state, dtype=float).reshape(4).copy()
        self._k = 0
        self._extra_force = 0.0
        self.last_disturbance = 0.0
        return self.state()

    def step(self, u: float) -> np.ndarray:
        """Apply force ``u`` [N] for one period (zero-order hold); returns the new state."""
        p = self.params
        u_dist = float(p.dist_mean) + float(p.dist_std) * self._rng.standard_normal()
        self.last_disturbance = u_dist
        x = _step(None, self._x, float(u), p, self.dt, self._extra_force, u_dist)
        self._x = np.asarray(x, dtype=float)
        self._extra_force = 0.0
        self._k += 1
        return self.state()

    def push(self, force: float) -> None:
        """Add ``force`` [N] to the cart during the next period (an impulse of force * dt)."""
        self._extra_force += float(force)

    def scale_masses(self, factor: float) -> None:
        """Multiply cart and pole masses by ``factor`` (a parametric regime shift)."""
        if factor <= 0.0:
            raise ValueError(f"mass factor must be > 0, got {factor}")
        self.params = self.params._replace(
            M=float(self.params.M) * factor, m=float(self.params.m) * factor
        )

    def state(self) -> np.ndarray:
        """``[x, xdot, theta, thetadot]`` (a copy)."""
        return self._x.copy()

    @property
    def time(self) -> float:
        """Time since the last reset [s]."""
        return self._k * self.dt
