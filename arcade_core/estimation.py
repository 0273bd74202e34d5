"""State estimation from motion capture and a gyro: the estimator service's filter.

The stack needs the 13-state ``x = [p, v, q (w first), omega]`` at each control instant
(design §3, §4). Motion capture measures position and attitude at ~120 Hz with a few ms
of latency and occasional dropped frames; the gyro measures body rates. The filter:

- **position/velocity/acceleration**: a Kalman filter with a constant-acceleration model
  driven by white jerk (spectral density ``jerk_psd``), one per world axis. All axes
  share the same model and measurement noise and are always updated together, so they
  share one ``3 x 3`` covariance (exact, and much cheaper than the ``9 x 9`` form). The
  acceleration state keeps the velocity unbiased through the smooth accelerations of
  flight with a low noise level (a constant-velocity model must trade one for the other);
- **attitude**: integrated with the gyro at every control instant (``q <- q (x) exp(omega
  dt / 2)``, the mean of the last two readings over the period), through dropouts too,
  and pulled towards each mocap quaternion with a fixed complementary gain;
- **gating**: a frame whose position innovation has a squared Mahalanobis distance above
  ``gate_chi2`` (3 dof) or whose attitude differs by more than ``gate_angle_rad`` from
  the prediction is rejected as an outlier. After ``max_rejects`` consecutive rejects the
  filter re-initialises on the measurement (a persistent jump is real, e.g. a re-zeroed
  mocap system, not an outlier);
- **dropouts**: without frames the filter just predicts, its covariance grows, and the
  output is flagged (``predicted_through_dropout``) when the newest fused frame is older
  than ``dropout_s``;
- **latency compensation**: the filter state lives at the capture time of the newest fused
  frame; the output at a control instant ``t`` is the constant-acceleration / gyro prediction
  from there to ``t`` (mocap latency is typically 5-10 ms: ~1-2 cm at 2 m/s).

Everything is pure JAX with static shapes: :func:`fuse_and_predict` takes a fixed-size,
masked batch of frames (the ones that arrived since the last control instant), so one
jitted call per control period does all the work.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from arcade_core import frames as quat

#: Frames fused per control period at most (120 Hz mocap at >= 20 Hz control: <= 6).
MAX_FRAMES = 16


class FilterConfig(NamedTuple):
    """Noise model and thresholds (defaults suit 120 Hz optical mocap, 0.3 mm noise).

    Attributes:
        jerk_psd: white-jerk spectral density of the constant-acceleration model
            [(m/s^3)^2 / Hz]; trades velocity noise against lag in manoeuvres. 20 is
            tuned for the closed loop (the adaptive controllers on the estimate:
            ``python -m benchmarks.quadrotor_variants estimator``).
        accel_std: standard deviation of the acceleration at initialisation [m/s^2].
        position_std: mocap position noise [m].
        attitude_gain: complementary-filter gain towards each mocap quaternion, in (0, 1].
        gate_chi2: squared Mahalanobis gate of the 3-D position innovation (99.9 %: 16.3).
        gate_floor_m: innovations shorter than this always pass the gate [m]: unmodelled
            manoeuvres must not look like outliers (mocap outliers, e.g. swapped markers,
            are centimetres to metres off).
        gate_angle_rad: attitude innovation gate [rad].
        max_rejects: consecutive rejects after which the filter re-initialises.
        dropout_s: newest fused frame older than this -> ``predicted_through_dropout``.
        init_velocity_std: velocity standard deviation at initialisation [m/s].
        gyro_std: gyro noise [rad/s] (reported variance of ``omega``).
    """

    jerk_psd: float = 20.0
    accel_std: float = 5.0
    position_std: float = 3e-4
    attitude_gain: float = 0.5
    gate_chi2: float = 16.27
    gate_floor_m: float = 0.02
    gate_angle_rad: float = 0.35
    max_rejects: int = 10
    dropout_s: float = 0.03
    init_velocity_std: float = 0.5
    gyro_std: float = 0.005


class FilterState(NamedTuple):
    """Filter state: position, velocity and acceleration at ``t`` (capture time of the
    newest fused frame), the attitude ``q`` at ``q_t``.

    ``cov`` is the ``(3, 3)`` covariance of ``[p_i, v_i, a_i]`` shared by the three axes.
    The attitude has its own time because the gyro moves it forward at every control
    instant, frames or not (the position model needs no such step: its prediction is
    exact for any horizon); ``omega`` is the gyro reading at ``q_t``.
    ``initialised`` is False until the first frame; ``rejects`` counts consecutive
    gated-out frames; ``accepted``/``rejected`` are running totals.
    """

    t: Array
    p: Array
    v: Array
    a: Array
    q: Array
    q_t: Array
    omega: Array
    cov: Array
    initialised: Array
    rejects: Array
    accepted: Array
    rejected: Array


class Frames(NamedTuple):
    """A masked batch of mocap frames, oldest first: ``stamp (M,)``, ``position (M, 3)``,
    ``quaternion (M, 4)``, ``valid (M,)`` bool."""

    stamp: Array
    position: Array
    quaternion: Array
    valid: Array


class Estimate(NamedTuple):
    """Output at a control instant: ``x (13,)``, ``var (13,)`` marginal variances, flags."""

    x: Array
    var: Array
    fused: Array  # () int: frames fused in this call
    dropout: Array  # () bool: newest fused frame older than dropout_s
    age: Array  # () s since the newest fused frame


def init(dtype=None) -> FilterState:
    """An uninitialised filter (the first valid frame initialises it)."""
    return _init(jnp.dtype(dtype or jnp.result_type(float)))


# Jitted: one compiled program instead of a dozen eager operations (each a compilation or a
# cache read in a fresh process, tens of milliseconds) at every start of the estimator.
@functools.partial(jax.jit, static_argnums=0)
def _init(dtype) -> FilterState:
    z = jnp.zeros((), dtype)
    i = jnp.zeros((), jnp.int32)
    return FilterState(
        t=z,
        p=jnp.zeros(3, dtype),
        v=jnp.zeros(3, dtype),
        a=jnp.zeros(3, dtype),
        q=jnp.array([1.0, 0.0, 0.0, 0.0], dtype),
        q_t=z,
        omega=jnp.zeros(3, dtype),
        cov=jnp.eye(3, dtype=dtype),
        initialised=jnp.zeros((), bool),
        rejects=i,
        accepted=i,
        rejected=i,
    )


def empty_frames(max_frames: int = MAX_FRAMES, dtype=None) -> Frames:
    """An all-invalid batch (fill the first rows, set ``valid``)."""
    return _empty_frames(int(max_frames), jnp.dtype(dtype or jnp.result_type(float)))


@functools.partial(jax.jit, static_argnums=(0, 1))
def _empty_frames(max_frames: int, dtype) -> Frames:
    return Frames(
        jnp.zeros(max_frames, dtype),
        jnp.zeros((max_frames, 3), dtype),
        jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0], dtype), (max_frames, 1)),
        jnp.zeros(max_frames, bool),
    )


def propagate_attitude(q: Array, omega: Array, dt: ArrayLike) -> Array:
    """``q (x) exp(omega dt / 2)``: body-rate integration over ``dt`` (FLU rates)."""
    half = 0.5 * omega * dt
    angle = jnp.linalg.norm(half)
    small = angle < 1e-9
    safe = jnp.where(small, 1.0, angle)
    s = jnp.where(small, 1.0, jnp.sin(safe) / safe)
    dq = jnp.concatenate([jnp.cos(angle)[None], s * half])
    out = quat.multiply(q, dq)
    return out / jnp.linalg.norm(out)


def ca_transition(dt: ArrayLike, jerk_psd: ArrayLike) -> tuple[Array, Array]:
    """Constant-acceleration model over ``dt``: ``F`` (3, 3) and the white-jerk noise ``Q``."""
    dt = jnp.asarray(dt)
    one, zero = jnp.ones_like(dt), jnp.zeros_like(dt)
    F = jnp.stack(
        [
            jnp.stack([one, dt, 0.5 * dt**2]),
            jnp.stack([zero, one, dt]),
            jnp.stack([zero, zero, one]),
        ]
    )
    Q = jerk_psd * jnp.stack(
        [
            jnp.stack([dt**5 / 20.0, dt**4 / 8.0, dt**3 / 6.0]),
            jnp.stack([dt**4 / 8.0, dt**3 / 3.0, dt**2 / 2.0]),
            jnp.stack([dt**3 / 6.0, dt**2 / 2.0, dt]),
        ]
    )
    return F, Q.astype(dt.dtype)


def predict(state: FilterState, t: ArrayLike, config: FilterConfig) -> FilterState:
    """Kalman prediction of position/velocity/acceleration from ``state.t`` to ``t``."""
    t = jnp.asarray(t, state.p.dtype)
    dt = jnp.maximum(t - state.t, 0.0)
    F, Q = ca_transition(dt, config.jerk_psd)
    return state._replace(
        t=jnp.maximum(state.t, t),
        p=state.p + dt * state.v + 0.5 * dt**2 * state.a,
        v=state.v + dt * state.a,
        cov=F @ state.cov @ F.T + Q,
    )


def update(
    state: FilterState,
    stamp: ArrayLike,
    position: Array,
    quaternion: Array,
    omega: Array,
    config: FilterConfig,
) -> tuple[FilterState, Array]:
    """Fuse one frame captured at ``stamp``; returns ``(state, accepted)``.

    Predicts to ``stamp`` (attitude with ``omega``), gates the innovation, then applies
    the Kalman update per axis and the complementary attitude correction. A frame not
    newer than the filter state is ignored (and counted as rejected): an older one is out
    of order, and one at ``state.t`` repeats the capture instant of the frame fused last
    (only a fused frame moves ``state.t``), so fusing it again would count the same
    measurement twice. The first frame (or one after ``max_rejects`` consecutive rejects)
    initialises the filter.
    """
    dtype = state.p.dtype
    stamp = jnp.asarray(stamp, dtype)
    r = jnp.asarray(config.position_std, dtype) ** 2
    pred = predict(state, stamp, config)
    # From the attitude's own time (forwards, or back over a few ms of mocap latency).
    q_pred = propagate_attitude(state.q, omega, stamp - state.q_t)
    nu = position - pred.p
    S = pred.cov[0, 0] + r
    d2 = jnp.sum(nu * nu) / S
    q_meas = quat.align(quaternion, q_pred)
    # A first frame starts in the identity's hemisphere (q_pred of an uninitialised filter
    # is the identity propagated over the whole stamp, i.e. arbitrary); a re-initialisation
    # continues the hemisphere of the estimate it replaces.
    q_first = jnp.where(
        state.initialised, q_meas, quat.align(quaternion, jnp.array([1.0, 0.0, 0.0, 0.0], dtype))
    )
    close = (d2 <= config.gate_chi2) | (jnp.sum(nu * nu) <= config.gate_floor_m**2)
    in_gate = close & (quat.angle_between(q_pred, q_meas) <= config.gate_angle_rad)
    in_order = (stamp > state.t) | ~state.initialised
    reinit = ~state.initialised | (state.rejects + 1 >= config.max_rejects)
    accept = in_order & (in_gate | reinit)

    K = pred.cov[:, 0] / S  # (3,) gain, same for every axis
    p_new = pred.p + K[0] * nu
    v_new = pred.v + K[1] * nu
    a_new = pred.a + K[2] * nu
    cov_new = pred.cov - jnp.outer(K, pred.cov[0])
    cov_new = 0.5 * (cov_new + cov_new.T)
    q_blend = q_pred + config.attitude_gain * (q_meas - q_pred)
    q_new = q_blend / jnp.linalg.norm(q_blend)

    var0 = jnp.stack(
        [
            r,
            jnp.asarray(config.init_velocity_std, dtype) ** 2,
            jnp.asarray(config.accel_std, dtype) ** 2,
        ]
    )
    fresh = FilterState(
        t=stamp,
        p=position,
        v=jnp.where(state.initialised, pred.v, 0.0),
        a=jnp.zeros(3, dtype),
        q=q_first,
        q_t=stamp,
        omega=omega,
        cov=jnp.diag(var0),
        initialised=jnp.ones((), bool),
        rejects=jnp.zeros((), jnp.int32),
        accepted=state.accepted + 1,
        rejected=state.rejected,
    )
    fused = FilterState(
        t=stamp,
        p=p_new,
        v=v_new,
        a=a_new,
        q=q_new,
        q_t=stamp,
        omega=omega,
        cov=cov_new,
        initialised=state.initialised,
        rejects=jnp.zeros((), jnp.int32),
        accepted=state.accepted + 1,
        rejected=state.rejected,
    )
    use_fresh = reinit & ~in_gate | ~state.initialised
    new = jax.tree.map(lambda a, b: jnp.where(use_fresh, a, b), fresh, fused)
    bad = state._replace(
        rejects=state.rejects + in_order.astype(jnp.int32), rejected=state.rejected + 1
    )
    out = jax.tree.map(lambda a, b: jnp.where(accept, a, b), new, bad)
    return out, accept


def output(state: FilterState, t: ArrayLike, omega: Array, config: FilterConfig) -> Estimate:
    """State at the control instant ``t``: latency-compensated prediction (no update).

    The attitude is integrated from ``q_t`` with the mean of ``state.omega`` and
    ``omega`` (the trapezoid rule over the period; with a frame fused at ``q_t`` both are
    this period's reading)."""
    dtype = state.p.dtype
    t = jnp.asarray(t, dtype)
    age = jnp.maximum(t - state.t, 0.0)
    pred = predict(state, t, config)
    q = propagate_attitude(state.q, 0.5 * (state.omega + omega), t - state.q_t)
    x = jnp.concatenate([pred.p, pred.v, q, omega])
    att_var = jnp.full(4, (config.gyro_std * age) ** 2 + 1e-6, dtype)
    var = jnp.concatenate(
        [
            jnp.full(3, pred.cov[0, 0]),
            jnp.full(3, pred.cov[1, 1]),
            att_var,
            jnp.full(3, config.gyro_std**2, dtype),
        ]
    )
    return Estimate(x, var, jnp.zeros((), jnp.int32), age > config.dropout_s, age)


def fuse_and_predict(
    state: FilterState, frames: Frames, t: ArrayLike, omega: ArrayLike, config: FilterConfig
) -> tuple[FilterState, Estimate]:
    """One control period: fuse the valid ``frames`` in order, then :func:`output` at ``t``.

    ``omega`` (3,) is the latest gyro reading; it propagates the attitude between frames
    and to ``t``, and is the output body rate. The attitude output at ``t`` becomes the
    state's (``q_t = t``): without frames (a dropout) the gyro alone carries it.
    """
    omega = jnp.asarray(omega, state.p.dtype)

    def body(s, frame):
        stamp, pos, q, valid = frame
        new, ok = update(s, stamp, pos, q, omega, config)
        s = jax.tree.map(lambda a, b: jnp.where(valid, a, b), new, s)
        return s, valid & ok

    state, ok = jax.lax.scan(body, state, tuple(frames))
    est = output(state, t, omega, config)
    t = jnp.asarray(t, state.p.dtype)
    ahead = state.initialised & (t > state.q_t)
    state = state._replace(
        q=jnp.where(ahead, est.x[6:10], state.q),
        q_t=jnp.where(ahead, t, state.q_t),
        omega=jnp.where(ahead, omega, state.omega),
    )
    return state, est._replace(fused=jnp.sum(ok.astype(jnp.int32)))
