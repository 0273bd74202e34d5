"""Flights that make logs for the discrepancy workflow: the standard exciting trajectory with
effects injected (``arcade simulate``, design §6).

Quadrotor (:func:`fly_quadrotor`): the MuJoCo simulator
(:class:`~simulator.quadrotor.QuadrotorSim`) with effect tables by canonical name (what an
effects file holds, e.g. ``{"rotor_drag": {"d": [0.4, 0.4, 0.05]}}``) on top of the vehicle
file's own ``[effects]``. The pilot is the
expert pilot of the offline datasets (``arcade_control.expert.ExpertPilot``: cascaded
position/attitude control emitting thrust + body rates at 20 Hz, unaware of the effects)
with its low-pass setpoint excitation, following the datasets' random spline
(``RandomPath``), with three changes (:class:`GroundPassPath`):

- **ground passes**: every :data:`GROUND_PERIOD_S` the reference height blends down to
  :data:`APPROACH_HEIGHT_M`, then slowly on to :data:`GROUND_HEIGHT_M`, holds there for
  :data:`GROUND_HOLD_S` and climbs back, so that effects that live near the floor show in
  every part of the log. Near the floor the excitation is turned down to
  :data:`GROUND_EXCITATION` of its size, the horizontal path slowed to
  :data:`GROUND_SPEED` of its pace, and the pilot pulls up harder below
  :data:`FLOOR_GUARD_M`: the vehicle never touches the floor (contacts are not part of any
  model);
- **pace**: slow random paths are flown faster, towards :data:`TARGET_RMS_SPEED`, so that
  speed-dependent effects (drag) are excited in every flight;
- a :data:`WARMUP_S` hover before the log starts (integrators settled, as in a log that
  starts in flight);
- **a pilot tuned to the vehicle as it flies** (:func:`pilot_gains`), as a pilot tunes
  after the first hover: it trims the actual hover throttle, limits its bank angle to the
  thrust it has, and with a slow rate channel or slow motors lowers its loop bandwidths
  (and the excitation, and keeps higher above the floor) to keep its phase margin, so
  that every vehicle in the library's plausible ranges flies the trajectory. Without such
  effects nothing changes.

Sensor noise (``noise_scale`` 1, the default; 0 logs the ground truth). What a motion-capture
based state estimate looks like: position white ``N(0, 0.3 mm)`` and attitude white
``0.2 deg`` per body axis (the simulator's motion-capture defaults), velocity an estimator's
correlated error (AR(1), :data:`VEL_NOISE_MPS`, correlation time :data:`VEL_NOISE_TAU_S`),
body rates the gyro's white noise (0.005 rad/s) plus a constant bias drawn once
(0.002 rad/s std). The inputs are logged exactly (the commands that were sent); the log is
100 Hz.

Cartpole (:func:`fly_cartpole`): the Appendix D system with the effects (relative to the
nominal model) simulated by :func:`arcade_core.discrepancy.cartpole.true_step` at 20 Hz,
driven by a soft cart-position PD plus a low-pass random force (the pole swings freely:
rich excitation), sensor noise 1 mm / 1 mrad / 0.01 m/s / 0.01 rad/s white.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from arcade_control.expert import START, ExpertPilot, RandomPath
from arcade_control.nominal import CONTROL_DT, LOG_DT, LOG_PER_CONTROL
from arcade_core import frames
from arcade_core.discrepancy import cartpole as cp
from arcade_core.discrepancy.tables import validate_tables
from arcade_core.dynamics.params import CARTPOLE_DT, CARTPOLE_NOMINAL, CARTPOLE_TRUE
from arcade_io.flightlog import FlightLog, from_arrays
from arcade_io.vehicle import load_vehicle, quadrotor_params
from simulator.expert_flights import EXCITATION_STD, EXCITATION_TAU_S
from simulator.mocap import GyroConfig, MocapConfig
from simulator.quadrotor import QuadrotorSim

#: Hover before the log starts [s].
WARMUP_S = 5.0
#: Ground passes of the quadrotor trajectory (module docstring); the period is chosen
#: incommensurate with the workflow's 2 s held-out blocks.
GROUND_PERIOD_S = 23.0
GROUND_FIRST_S = 6.0
GROUND_RAMP_S = 2.5
GROUND_HOLD_S = 4.0
APPROACH_HEIGHT_M = 0.6
GROUND_HEIGHT_M = 0.15
GROUND_EXCITATION = 0.15
GROUND_SPEED = 0.3
#: Pace of the random path: sped up (at most MAX_PACE times) towards TARGET_RMS_SPEED
#: (drag effects need speed), but no more than keeps its peak acceleration below
#: PACE_MAX_ACCEL for the pilot.
TARGET_RMS_SPEED = 1.5
MAX_PACE = 1.6
PACE_MAX_ACCEL = 8.0
#: Below this height [m] the pilot adds an upward acceleration (gain [1/s^2] per metre).
FLOOR_GUARD_M = 0.1
FLOOR_GUARD_GAIN = 150.0
#: Quadrotor sensor noise at noise_scale 1 (module docstring).
VEL_NOISE_MPS = 0.005
VEL_NOISE_TAU_S = 0.1
#: Cartpole excitation and sensor noise.
CARTPOLE_KP, CARTPOLE_KD = 2.0, 2.0
CARTPOLE_EXCITATION_N, CARTPOLE_EXCITATION_TAU_S = 4.0, 0.3
CARTPOLE_NOISE = np.array([1e-3, 0.01, 1e-3, 0.01])


# --------------------------------------------------------------------------- quadrotor


def _raised_cosine(s: float, r: float) -> tuple[float, float, float]:
    """0 -> 1 over ``[0, r]`` (raised cosine) and its first two derivatives."""
    if s <= 0.0:
        return 0.0, 0.0, 0.0
    if s >= r:
        return 1.0, 0.0, 0.0
    w = np.pi / r
    return 0.5 - 0.5 * np.cos(w * s), 0.5 * w * np.sin(w * s), 0.5 * w * w * np.cos(w * s)


def _plateau(t: float, start: float, ramp: float, hold: float) -> tuple[float, float, float]:
    """Up over ``ramp`` from ``start``, ``hold``, down over ``ramp``; value and derivatives."""
    up = _raised_cosine(t - start, ramp)
    down = _raised_cosine(t - start - ramp - hold, ramp)
    return up[0] - down[0], up[1] - down[1], up[2] - down[2]


class GroundPassPath:
    """``RandomPath`` whose height dips to the floor periodically (module docstring).

    Each pass descends to :data:`APPROACH_HEIGHT_M` over :data:`GROUND_RAMP_S`, then
    slowly to :data:`GROUND_HEIGHT_M` over the same time, holds :data:`GROUND_HOLD_S`
    and climbs back the same way. The random path is flown faster than the datasets fly
    it where it is slow (towards :data:`TARGET_RMS_SPEED`, so that every flight excites
    speed-dependent effects alike), and slowed down to :data:`GROUND_SPEED` of its pace
    below the approach height (time warp), so that the vehicle does not bank hard next to
    the floor.
    """

    def __init__(
        self, rng: np.random.Generator, duration: float, ground_height: float = GROUND_HEIGHT_M
    ):
        self.ground_height = ground_height

        self.path = RandomPath(rng, MAX_PACE * duration)
        # Pace: as fast as needed for the target RMS speed, as slow as the pilot needs.
        pace = 1.0
        for _ in range(3):
            ts = np.arange(0.0, pace * duration, 0.05)
            vel = self.path.spline(ts, 1)
            rms = float(np.sqrt(np.mean(np.sum(vel**2, axis=1))))
            acc = float(np.max(np.linalg.norm(self.path.spline(ts, 2), axis=1)))
            pace = min(max(1.0, TARGET_RMS_SPEED / rms), np.sqrt(PACE_MAX_ACCEL / acc), MAX_PACE)
        self.pace = max(pace, 1.0)
        # Warped path time tau(t) = int_0^t pace (1 - (1 - GROUND_SPEED) c(s)) ds on a grid.
        self._grid = np.arange(0.0, duration + 5.0, 1e-3)
        rate = self.pace * (
            1.0 - (1.0 - GROUND_SPEED) * np.array([self._weights(t)[1][0] for t in self._grid])
        )
        self._tau = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * 1e-3)])

    @staticmethod
    def _weights(t: float, widen: float = 0.0):
        if t < GROUND_FIRST_S - widen:
            z = (0.0, 0.0, 0.0)
            return z, z
        r, h = GROUND_RAMP_S, GROUND_HOLD_S
        s = (t - GROUND_FIRST_S) % GROUND_PERIOD_S
        s = s - GROUND_PERIOD_S if s > GROUND_PERIOD_S - widen else s
        outer = _plateau(s, -widen, r, 2 * r + h + 2 * widen)
        inner = _plateau(s, r, r, h)
        return outer, inner

    def excitation_scale(self, t: float) -> float:
        """Excitation multiplier: 1 in free flight, ``GROUND_EXCITATION`` near the floor."""
        outer, _ = self._weights(t, GROUND_RAMP_S)
        return 1.0 - (1.0 - GROUND_EXCITATION) * outer[0]

    def __call__(self, t: float):
        (b, db, ddb), (c, dc, ddc) = self._weights(t)
        # Time warp of the horizontal path: tau' = pace (1 - k c), tau'' = -pace k c'.
        k = 1.0 - GROUND_SPEED
        tau = float(np.interp(t, self._grid, self._tau))
        d1, d2 = self.pace * (1.0 - k * c), -self.pace * k * dc
        p, v, a, yaw = self.path(tau)
        p, v, a = p.copy(), v * d1, a * d1 * d1 + v * d2
        z, vz, az = p[2], v[2], a[2]
        gap, step = APPROACH_HEIGHT_M - z, self.ground_height - APPROACH_HEIGHT_M
        p[2] = z + b * gap + c * step
        v[2] = vz + db * gap - b * vz + dc * step
        a[2] = az + ddb * gap - 2.0 * db * vz - b * az + ddc * step
        return p, v, a, yaw


class VerticalFigureEight:
    """A figure-eight in a vertical plane, as a flight plan flies it (no floor passes).

    Along the heading ``heading`` [rad, ENU] through ``center``: horizontal offset
    ``half_length sin(phi)``, height offset ``half_height sin(2 phi)`` (a lemniscate of
    Gerono standing upright), ``phi = 2 pi s(t) / period``. The clock ``s`` ramps up from
    rest over ``ramp_s`` (``ds/dt`` a quintic smoothstep, as
    :class:`arcade_control.scenario.RampedPath`), so the flight starts from a hover.
    The heading of the vehicle stays 0.
    """

    def __init__(
        self,
        center=START,
        half_length: float = 2.0,
        half_height: float = 0.75,
        period: float = 6.0,
        heading: float = 0.0,
        ramp_s: float = 2.0,
    ):
        self.center = np.asarray(center, dtype=float)
        self.half_length, self.half_height = float(half_length), float(half_height)
        self.omega, self.ramp = 2.0 * np.pi / float(period), float(ramp_s)
        self.along = np.array([np.cos(heading), np.sin(heading), 0.0])

    def __call__(self, t: float):
        r = min(max(t / self.ramp, 0.0), 1.0)
        if t < self.ramp:
            s = self.ramp * r**4 * (2.5 - 3.0 * r + r * r)
            ds, dds = r**3 * (10.0 - 15.0 * r + 6.0 * r * r), 30.0 * r * r * (1.0 - r) ** 2
            dds /= self.ramp
        else:
            s, ds, dds = 0.5 * self.ramp + (t - self.ramp), 1.0, 0.0
        phi, dphi, ddphi = self.omega * s, self.omega * ds, self.omega * dds
        L, H = self.half_length, self.half_height
        x = L * np.sin(phi)
        dx = L * np.cos(phi) * dphi
        ddx = -L * np.sin(phi) * dphi**2 + L * np.cos(phi) * ddphi
        z = H * np.sin(2.0 * phi)
        dz = 2.0 * H * np.cos(2.0 * phi) * dphi
        ddz = -4.0 * H * np.sin(2.0 * phi) * dphi**2 + 2.0 * H * np.cos(2.0 * phi) * ddphi
        up = np.array([0.0, 0.0, 1.0])
        return (
            self.center + x * self.along + z * up,
            dx * self.along + dz * up,
            ddx * self.along + ddz * up,
            0.0,
        )


def hover_path(point=START):
    """A reference that holds ``point`` (a hover-only flight)."""
    p, zero = np.asarray(point, dtype=float), np.zeros(3)
    return lambda _t: (p.copy(), zero.copy(), zero.copy(), 0.0)


#: Largest phase lag [deg] the pilot's loops accept from the vehicle at their crossover
#: (attitude: rate loop, rate-setpoint delay and filter, motors; vertical: motors).
PILOT_MAX_PHASE_DEG = (35.0, 30.0)


def _crossover(nominal: float, phase) -> float:
    """Largest crossover ``<= nominal`` [rad/s] at which ``phase(w)`` [rad] is acceptable."""
    lo, hi = 0.05 * nominal, nominal
    if phase(hi) <= 0.0:
        return hi
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if phase(mid) <= 0.0 else (lo, mid)
    return lo


def pilot_gains(vehicle: dict[str, Any], effects: dict[str, Any]) -> dict[str, Any]:
    """Gains of the expert pilot for the vehicle as it actually flies (module docstring).

    The pilot is tuned like a pilot tunes after the first hover: to the vehicle's lags and
    thrust margin, not to its model (the workflow that reads the log is told nothing).
    The attitude loop (default crossover ``k_att = 6 rad/s``) accepts at most
    :data:`PILOT_MAX_PHASE_DEG` of phase lag from the rate loop, the rate-setpoint delay
    and filter and the motors at its crossover; a slower vehicle gets a lower crossover,
    and the horizontal position loop, which acts through the attitude, is scaled with it
    (``s = k_att / 6``: ``kd ~ s``, ``kp ~ s^2``, ``ki ~ s^3`` keeps its damping). The
    vertical loop acts through the thrust, which only the motors lag, and is scaled by
    its own phase budget. On the default vehicle without lag effects nothing changes. The
    tilt limit leaves 30 % of the thrust for manoeuvring vertically (a vehicle with half
    its thrust must not be banked at 50 deg). ``slowdown`` is ``(s_horizontal,
    s_vertical)``.
    """
    rl, rot = vehicle["rate_loop"], vehicle["rotors"]
    tau_rate = float(rl["time_constant_s"])
    tau_motor = float(effects.get("motor_lag", {}).get("time_constant_s", 0.0)) or float(
        rot["motor_time_constant_s"]
    )
    lag = effects.get("rate_lag", {})
    delay, tau_f = float(lag.get("delay_s", 0.0)), float(lag.get("time_constant_s", 0.0))
    att_max, vert_max = np.deg2rad(PILOT_MAX_PHASE_DEG)

    def att_phase(w):
        lags = np.arctan(w * tau_rate) + np.arctan(w * tau_f) + np.arctan(w * tau_motor)
        return lags + w * delay - att_max

    s_h = _crossover(6.0, att_phase) / 6.0
    s_v = _crossover(4.0, lambda w: np.arctan(w * tau_motor) - vert_max) / 4.0
    s = np.array([s_h, s_h, s_v])
    scale = float(effects.get("thrust_scale", {}).get("scale", 1.0))
    par = quadrotor_params(vehicle)
    weight = float(par.mass) * float(par.gravity)
    thrust_to_weight = 4.0 * float(rot["max_thrust_n"]) * scale / weight
    max_tilt = float(np.arccos(min(1.0, 1.3 / thrust_to_weight)))
    return {
        "kp": 6.0 * s * s,
        "kd": 4.0 * s,
        "ki": 2.0 * s**3,
        "k_att": 6.0 * s_h,
        "max_tilt": min(np.deg2rad(50.0), max_tilt),
        "slowdown": (s_h, s_v),
    }


def fly_quadrotor(
    effects: dict[str, Any] | None = None,
    duration: float = 60.0,
    seed: int = 0,
    *,
    vehicle: dict[str, Any] | str | Path | None = None,
    noise_scale: float = 1.0,
    path: Callable[[float], tuple] | None = None,
    excitation: float = 1.0,
) -> FlightLog:
    """Fly the standard exciting trajectory with ``effects`` injected; the noisy 100 Hz log.

    ``effects`` are tables by canonical name (merged over the vehicle file's ``[effects]``).
    ``path``: another reference for the pilot, ``path(t) -> (p, v, a, yaw)`` from ``t = 0``
    (e.g. :class:`VerticalFigureEight`, :func:`hover_path`; the flight starts at
    ``path(0)``); ``excitation``: multiplier of the pilot's setpoint excitation (0: the
    path alone, as a flight plan is flown). The thrust excitation scales with the vehicle's
    mass (the same acceleration as on the default vehicle). Returns a
    :class:`arcade_io.flightlog.FlightLog`.
    """
    veh = vehicle if isinstance(vehicle, dict) else load_vehicle(vehicle)
    merged = {**veh.get("effects", {}), **(effects or {})}
    params = quadrotor_params(veh)
    ss = np.random.SeedSequence(seed)
    path_ss, exc_ss, sim_ss, noise_ss = ss.spawn(4)
    # The log's noise is added below (add_quadrotor_noise): no motion-capture frames.
    sim = QuadrotorSim(
        veh, effects=merged, seed=int(sim_ss.generate_state(1)[0]), motion_capture=False
    )
    gains = pilot_gains(veh, merged)
    s_h, s_v = gains.pop("slowdown")
    # A slow pilot keeps farther from the floor (a sluggish attitude loop banks for longer),
    # pulls up as hard as its loop allows and excites less (its position loop would let
    # the excitation carry it away).
    ground = min(GROUND_HEIGHT_M / min(s_h, s_v), APPROACH_HEIGHT_M)
    if path is None:
        path = GroundPassPath(np.random.default_rng(path_ss), duration, ground)
    excitation_scale = getattr(path, "excitation_scale", lambda _t: 1.0)
    guard = FLOOR_GUARD_GAIN * s_v * s_v
    heavier = float(params.mass) / float(quadrotor_params(load_vehicle()).mass)
    excitation_std = excitation * EXCITATION_STD * np.array([s_v * heavier, s_h, s_h, s_h])
    rng_exc = np.random.default_rng(exc_ss)
    pilot = ExpertPilot(float(params.mass), float(params.gravity), **gains)
    x = sim.reset(tuple(float(c) for c in path(0.0)[0]))
    # The pilot trims the hover *command* (what the throttle reads at hover), as a pilot
    # does after take-off; with a thrust mismatch that is not the weight.
    pilot.trim(sim.hover_thrust() / float(merged.get("thrust_scale", {}).get("scale", 1.0)))
    a = np.exp(-CONTROL_DT / EXCITATION_TAU_S)
    exc = np.zeros(4)

    def control(x, t):
        nonlocal exc
        p_ref, v_ref, a_ref, yaw = path(max(t, 0.0))
        # Like a pilot near the floor: pull up harder the closer the vehicle gets.
        a_ref = a_ref + np.array([0.0, 0.0, guard * max(0.0, FLOOR_GUARD_M - x[2])])
        u = pilot(x, (p_ref, v_ref, a_ref, yaw), CONTROL_DT)
        w = np.clip(rng_exc.standard_normal(4), -2.0, 2.0)
        exc = a * exc + np.sqrt(1.0 - a * a) * w
        return sim.set_setpoint(u + excitation_scale(t) * exc * excitation_std)

    # Hover before the log starts (rate-loop integrator and pilot trim settle), like a log
    # that starts in flight.
    for k in range(round(WARMUP_S / CONTROL_DT)):
        control(x, -WARMUP_S + k * CONTROL_DT)
        x = sim.step(CONTROL_DT)
    steps = round(duration / CONTROL_DT)
    n = steps * LOG_PER_CONTROL + 1
    X = np.empty((n, 13))
    U = np.empty((n, 4))
    X[0] = x
    for k in range(steps):
        u = control(x, k * CONTROL_DT)
        for j in range(LOG_PER_CONTROL):
            U[k * LOG_PER_CONTROL + j] = u
            x = sim.step(LOG_DT)
            X[k * LOG_PER_CONTROL + j + 1] = x
    U[-1] = U[-2]
    if not np.isfinite(X).all():
        raise RuntimeError("the simulated flight diverged (non-finite state)")
    X = add_quadrotor_noise(X, np.random.default_rng(noise_ss), noise_scale, LOG_DT)
    return from_arrays("quadrotor", np.arange(n) * LOG_DT, X, U)


def add_quadrotor_noise(
    X: np.ndarray, rng: np.random.Generator, scale: float, dt: float
) -> np.ndarray:
    """Sensor noise of the module docstring on ground-truth states ``X (n, 13)``."""
    X = np.array(X, dtype=float)
    if scale <= 0.0:
        return X
    n = X.shape[0]
    mc, gc = MocapConfig(), GyroConfig()
    X[:, 0:3] += scale * mc.position_noise_m * rng.standard_normal((n, 3))
    a = np.exp(-dt / VEL_NOISE_TAU_S)
    w = rng.standard_normal((n, 3)) * np.sqrt(1.0 - a * a)
    e = np.empty((n, 3))
    e[0] = rng.standard_normal(3)
    for k in range(1, n):
        e[k] = a * e[k - 1] + w[k]
    X[:, 3:6] += scale * VEL_NOISE_MPS * e
    dq = scale * mc.attitude_noise_rad * rng.standard_normal((n, 3))
    for k in range(n):
        q = frames.multiply_np(X[k, 6:10], frames.from_rotation_vector_np(dq[k]))
        X[k, 6:10] = q / np.linalg.norm(q)
    bias = gc.bias_std_rad_s * rng.standard_normal(3)
    X[:, 10:13] += scale * (bias + gc.noise_rad_s * rng.standard_normal((n, 3)))
    return X


# --------------------------------------------------------------------------- cartpole


def paper_true_effects() -> dict[str, dict[str, float]]:
    """The paper's "true" cartpole (Appendix D) as effects on its nominal model."""
    T = CARTPOLE_TRUE
    return {
        "cart_viscous_friction": {"mu_c": float(T.mu_c)},
        "pole_viscous_friction": {"mu_p": float(T.mu_p)},
        "force_bias": {"mean_n": float(T.dist_mean), "std_n": float(T.dist_std)},
        "mass_mismatch": {"cart_mass_kg": float(T.M), "pole_mass_kg": float(T.m)},
        "length_mismatch": {"pole_length_m": float(T.L)},
    }


def fly_cartpole(
    effects: dict[str, Any] | None = None,
    duration: float = 60.0,
    seed: int = 0,
    *,
    noise_scale: float = 1.0,
    system=None,
) -> FlightLog:
    """The cartpole with ``effects`` under the exciting controller; a noisy 20 Hz log.

    ``system``: drive this stateful cartpole instead (``reset(state)``, ``step(u)``, ``dt``,
    e.g. ``simulator.cartpole.CartpoleSim``, the paper's true system); ``effects`` are then
    ignored.
    """
    tables = validate_tables("cartpole", effects or {})
    model = cp.CartpoleModel.from_params(CARTPOLE_NOMINAL)
    theta = cp.theta_from_effects(model, tables)
    std = float(tables.get("force_bias", {}).get("std_n", 0.0))
    n = round(duration / CARTPOLE_DT) + 1
    # Independent streams: excitation, disturbance, sensor noise.
    rng, rng_dist, rng_noise = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3)
    )
    a = np.exp(-CARTPOLE_DT / CARTPOLE_EXCITATION_TAU_S)
    w = rng.standard_normal(n) * np.sqrt(1.0 - a * a)
    exc = np.empty(n)
    exc[0] = rng.standard_normal()
    for k in range(1, n):
        exc[k] = a * exc[k - 1] + w[k]
    dist = std * rng_dist.standard_normal(n)
    x0 = np.array([0.0, 0.0, 0.3 * rng.standard_normal(), 0.0])

    def body(x, inp):
        e, d = inp
        u = -CARTPOLE_KP * x[0] - CARTPOLE_KD * x[1] + CARTPOLE_EXCITATION_N * e
        xn = cp.true_step(model, theta, x, u, CARTPOLE_DT, d)
        return xn, (x, u)

    if system is None:
        _, (X, U) = jax.jit(lambda x, e, d: jax.lax.scan(body, x, (e, d)))(
            jnp.asarray(x0), jnp.asarray(exc), jnp.asarray(dist)
        )
        X, U = np.asarray(X), np.asarray(U)
    else:
        X, U = np.empty((n, 4)), np.empty(n)
        x = system.reset(x0)
        for k in range(n):
            X[k] = x
            U[k] = -CARTPOLE_KP * x[0] - CARTPOLE_KD * x[1] + CARTPOLE_EXCITATION_N * exc[k]
            x = system.step(U[k])
    if not np.isfinite(X).all():
        raise RuntimeError("the simulated cartpole diverged (non-finite state)")
    X = X + noise_scale * CARTPOLE_NOISE * rng_noise.standard_normal(X.shape)
    return from_arrays("cartpole", np.arange(n) * CARTPOLE_DT, X, U[:, None])
