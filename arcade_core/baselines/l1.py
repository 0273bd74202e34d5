"""L1-adaptive augmentation of a quadrotor controller: the L1 baseline (Sec. V).

Clean-room from the published equations of Hovakimyan & Cao ("L1 Adaptive Control
Theory", 2010; piecewise-constant adaptation law) and Wu et al. ("L1Quad", 2023). The
baseline controller (nominal MPC) computes ``u_b``; this module estimates the lumped
uncertainty and returns an additive correction, ``u = u_b + correction(...)``.

Project conventions: ``x = [p(3) ENU, v(3), q(4, w first), omega(3) body FLU]``,
``u = [collective thrust N, body-rate setpoints rad/s (3)]``. The nominal model is

    vdot     = (T / m) R(q) e3 - g e3
    omegadot = (omega_cmd - omega) / tau           (closed PX4 rate loop, first order)

Uncertain model (L1Quad's decomposition, with the rate loop as rotational channel):

    vdot     = (T + sigma_m) / m  R e3 + (1/m) R [e1 e2] sigma_um - g e3 + ...
    omegadot = (omega_cmd + sigma_w - omega) / tau

``sigma_m`` (N, along the thrust axis) and ``sigma_w`` (rad/s, in the rate-setpoint
channel) are *matched*: the thrust/rate commands can cancel them. ``sigma_um`` (N, body x
and y) is *unmatched*: reported as part of a lumped acceleration estimate an MPC may add
to its prediction model. Together ``sigma_f = [sigma_um, sigma_m]`` is the disturbance
force in body axes.

Per call (sampling time ``T_s`` = the ``dt`` of :func:`update`):

1. state predictor (forward Euler over the last interval, with the applied input and the
   previous estimates): ``zhat' = f(x) + B(u + sigma_hat) + A_s (zhat - z)``, z = [v, omega];
2. piecewise-constant adaptation law with ``A_s = a_s I``:
   ``sigma_hat = -B^-1 Phi^-1 e^{A_s T_s} (zhat - z)``, ``Phi = A_s^-1 (e^{A_s T_s} - I)``;
   here ``B^-1`` is ``m R^T`` for the translational and ``tau I`` for the rotational
   channel;
3. first-order low-pass filter ``C(s) = w_c / (s + w_c)`` (exact zero-order-hold
   discretisation) on the negated matched estimates: the correction.

Property worth knowing: for a constant disturbance the law settles at
``exp(a_s T_s) * sigma`` (the estimate lags by one sample); with the defaults
(``a_s = -2``) this is a 2 % underestimate at 100 Hz and 4 % at 50 Hz. The rotational
channel is estimated always but only applied when ``rotational`` is set.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from arcade_core import frames


class L1Params(NamedTuple):
    """Model and tuning of the L1 augmentation (SI units)."""

    mass: float | Array  # [kg]
    gravity: float | Array = 9.81  # [m/s^2]
    rate_tau: float | Array = 0.05  # closed rate-loop time constant [s]
    a_s: float | Array = -2.0  # translational predictor pole (Hurwitz, < 0) [1/s]
    a_s_rot: float | Array = -2.0  # rotational predictor pole (< 0) [1/s]
    cutoff_thrust: float | Array = 5.0  # low-pass bandwidth, thrust channel [rad/s]
    cutoff_rates: float | Array = 5.0  # low-pass bandwidth, rate channels [rad/s]
    rotational: bool | Array = False  # also correct the body-rate setpoints


class L1State(NamedTuple):
    """Predictor, estimates and filter states. Build with :func:`init`."""

    v_hat: Array  # (3,) predicted world velocity
    w_hat: Array  # (3,) predicted body rates
    sigma_force: Array  # (3,) body-axis disturbance force estimate [N]
    sigma_rates: Array  # (3,) rate-channel disturbance estimate [rad/s]
    thrust_adj: Array  # () filtered matched thrust correction [N]
    rate_adj: Array  # (3,) filtered rate-setpoint correction [rad/s]
    x_prev: Array  # (13,) state at the previous update
    started: Array  # () bool: has seen a first state
    params: L1Params


def init(params: L1Params, dtype: jnp.dtype | None = None) -> L1State:
    """Zero estimates; the first :func:`update` call synchronises the predictor."""
    return _init(params, jnp.dtype(jnp.result_type(float) if dtype is None else dtype))


# Jitted: one compiled program instead of a dozen eager operations (each a compilation or a
# cache read in a fresh process, tens of milliseconds) wherever a service starts one.
@functools.partial(jax.jit, static_argnums=1)
def _init(params: L1Params, dtype) -> L1State:
    z3 = jnp.zeros(3, dtype)
    params = L1Params(*(jnp.asarray(p, dtype) for p in params))
    return L1State(
        v_hat=z3,
        w_hat=z3,
        sigma_force=z3,
        sigma_rates=z3,
        thrust_adj=jnp.zeros((), dtype),
        rate_adj=z3,
        x_prev=jnp.zeros(13, dtype).at[6].set(1.0),
        started=jnp.zeros((), bool),
        params=params,
    )


def _lowpass(y: Array, target: Array, cutoff: Array, dt: Array) -> Array:
    """First-order low-pass ``w_c / (s + w_c)``, exact ZOH step (Hovakimyan & Cao C(s))."""
    return y + (1.0 - jnp.exp(-cutoff * dt)) * (target - y)


def _adaptation_gain(a_s: Array, dt: Array) -> Array:
    """``Phi^-1 e^{A_s T_s}`` for ``A_s = a_s I`` (piecewise-constant law, scalar form)."""
    e = jnp.exp(a_s * dt)
    phi = (e - 1.0) / a_s
    return e / phi


def update(
    state: L1State,
    x: Array,
    u_applied: Array,
    dt: float | Array,
    known_accel: Array | None = None,
) -> L1State:
    """One L1 step at a new measured state (state predictor + adaptation + filter).

    Hovakimyan & Cao (2010), Ch. 2.4 (piecewise-constant adaptation) as used for
    quadrotors by Wu et al. (L1Quad, Eqs. for the predictor, adaptation law and
    low-pass filter). ``u_applied`` is the input that was applied over the interval
    ending at ``x`` (baseline command plus the previous correction); it is ignored on
    the very first call, which only synchronises the predictor with ``x``.

    ``known_accel`` (world frame, m/s^2, (3,)): an acceleration the controller's model
    already predicts over the interval beyond the nominal model (a learned residual), added
    to the predictor as in L1-GP (Gahlawat et al., 2020), so the estimate is what that model
    misses; ``None``: zero (the plain augmentation).
    """
    p = state.params
    dt = jnp.asarray(dt, x.dtype)
    e3 = jnp.array([0.0, 0.0, 1.0], x.dtype)
    v, w = x[3:6], x[10:13]

    # 1. predictor over the last interval, from the previous measurement and estimates
    xp = state.x_prev
    rp = frames.to_rotation_matrix(frames.normalize(xp[6:10]))
    vp, wp = xp[3:6], xp[10:13]
    v_dot = (
        u_applied[0] / p.mass * (rp @ e3)
        - p.gravity * e3
        + rp @ state.sigma_force / p.mass
        + p.a_s * (state.v_hat - vp)
    )
    if known_accel is not None:
        v_dot = v_dot + known_accel
    w_dot = (u_applied[1:4] + state.sigma_rates - wp) / p.rate_tau + p.a_s_rot * (state.w_hat - wp)
    v_hat = jnp.where(state.started, state.v_hat + dt * v_dot, v)
    w_hat = jnp.where(state.started, state.w_hat + dt * w_dot, w)

    # 2. piecewise-constant adaptation law: B^-1 = m R^T (translation), tau I (rates)
    r = frames.to_rotation_matrix(frames.normalize(x[6:10]))
    sigma_force = -p.mass * (r.T @ (_adaptation_gain(p.a_s, dt) * (v_hat - v)))
    sigma_rates = -p.rate_tau * _adaptation_gain(p.a_s_rot, dt) * (w_hat - w)

    # 3. low-pass filtered matched corrections
    thrust_adj = _lowpass(state.thrust_adj, -sigma_force[2], p.cutoff_thrust, dt)
    rate_adj = _lowpass(state.rate_adj, -sigma_rates, p.cutoff_rates, dt)
    return L1State(
        v_hat=v_hat,
        w_hat=w_hat,
        sigma_force=sigma_force,
        sigma_rates=sigma_rates,
        thrust_adj=thrust_adj,
        rate_adj=rate_adj,
        x_prev=x,
        started=jnp.ones((), bool),
        params=p,
    )


def correction(state: L1State, x: Array) -> Array:
    """Additive input correction ``[dT (N), d omega_cmd (rad/s, 3)]`` (Hovakimyan & Cao).

    ``u_ad = -C(s) sigma_m``: the filtered matched estimate. The rate part is zero unless
    ``params.rotational``. ``x`` is not needed by the matched law (which works in body
    axes); it is part of the signature so alternatives with state-dependent projections
    are drop-in replacements.
    """
    del x
    rot = jnp.asarray(state.params.rotational, state.rate_adj.dtype)
    return jnp.concatenate([state.thrust_adj[None], rot * state.rate_adj])


def acceleration_estimate(state: L1State, x: Array, include_matched: bool = True) -> Array:
    """Lumped world-frame disturbance acceleration ``R(q) sigma_f / m`` (m/s^2, (3,)).

    An MPC running with the L1 correction should add only the unmatched part
    (``include_matched=False``): the matched part is being cancelled through the thrust.
    """
    r = frames.to_rotation_matrix(frames.normalize(x[6:10]))
    sigma = state.sigma_force
    sigma = jnp.where(include_matched, sigma, sigma.at[2].set(0.0))
    return r @ sigma / state.params.mass
