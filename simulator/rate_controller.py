"""PX4-like body-rate controller and quad-x mixer (what runs on the flight controller).

Units. The PID works, as PX4's ``MC_*RATE_*`` parameters do, on *normalised* torque:
an output of 1 about an axis is the largest torque the rotors can produce about that axis
(:attr:`Mixer.torque_max`: roll/pitch ``2 * max_thrust * arm * sin 45deg``, yaw
``2 * yaw_moment_coeff * max_thrust`` for the default quad-x). So ``p`` is normalised
torque per rad/s, ``i`` per rad, ``d`` per rad/s^2 and ``ff`` per rad/s. In physical terms
the closed rate loop has the gain ``p * torque_max / inertia`` [1/s]; the shipped gains put
it near ``1 / rate_loop.time_constant_s`` so that the closed loop behaves like the
first-order lag the nominal model assumes.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from simulator.mjcf import RotorGeometry

# PX4 reduces integration for large rate errors (i_factor) to limit windup in flips.
_I_FACTOR_RATE = np.deg2rad(400.0)


@dataclass(frozen=True)
class RateGains:
    """Per-axis (roll, pitch, yaw; FLU) gains of the rate PID, PX4 normalised units."""

    p: np.ndarray
    i: np.ndarray
    d: np.ndarray
    ff: np.ndarray
    integrator_limit: np.ndarray
    d_cutoff_hz: float = 30.0

    @classmethod
    def from_vehicle(cls, vehicle: dict[str, Any]) -> RateGains:
        rl = vehicle["rate_loop"]

        def vec(key: str, default: float) -> np.ndarray:
            return np.asarray(rl.get(key, [default] * 3), dtype=float).reshape(3)

        return cls(
            p=vec("p", 0.0),
            i=vec("i", 0.0),
            d=vec("d", 0.0),
            ff=vec("ff", 0.0),
            integrator_limit=vec("integrator_limit", 0.3),
            d_cutoff_hz=float(rl.get("d_cutoff_hz", 30.0)),
        )


class RateController:
    """Body-rate PID with feed-forward, derivative on the filtered gyro, clamped integrator.

    ``torque = p * e + integral - d * d(omega)/dt + ff * omega_sp`` with ``e = omega_sp -
    omega``. The integrator is clamped to ``integrator_limit`` and frozen on an axis while
    the mixer reports saturation in the direction the error would push it (PX4's
    anti-windup).
    """

    def __init__(self, gains: RateGains, dt: float):
        self.gains = gains
        self.dt = float(dt)
        # First-order low-pass on the gyro derivative (PX4's D-term filter).
        self._d_alpha = 1.0 - np.exp(-2.0 * np.pi * gains.d_cutoff_hz * self.dt)
        self.reset()

    def reset(self, omega: np.ndarray | None = None) -> None:
        self.integral = np.zeros(3)
        self._prev_omega = np.zeros(3) if omega is None else np.array(omega, dtype=float)
        self._domega = np.zeros(3)

    def update(self, omega_sp: np.ndarray, omega: np.ndarray, saturation: np.ndarray) -> np.ndarray:
        """Normalised torque setpoint (3,) from the rate setpoint and measured rate."""
        g = self.gains
        err = omega_sp - omega
        raw_d = (omega - self._prev_omega) / self.dt
        self._prev_omega = omega
        self._domega = self._domega + self._d_alpha * (raw_d - self._domega)
        torque = g.p * err + self.integral - g.d * self._domega + g.ff * omega_sp
        # Integrate unless that deepens a saturation the mixer reported for this axis.
        frozen = saturation * err > 0.0
        i_factor = np.maximum(0.0, 1.0 - (err / _I_FACTOR_RATE) ** 2)
        step = np.where(frozen, 0.0, g.i * i_factor * err * self.dt)
        self.integral = np.clip(self.integral + step, -g.integrator_limit, g.integrator_limit)
        return torque


class Mixer:
    """Allocation of (collective thrust N, normalised torques) to four rotor thrusts.

    Saturation handling (PX4 style, air-mode off): roll/pitch first — if their differential
    demand does not fit in ``[0, max_thrust]`` it is scaled down; then the collective is
    shifted only as far as needed to bring every rotor into range (so it is kept whenever
    possible); yaw gets whatever headroom is left. ``mix`` also returns, per axis, +1/-1
    when the positive/negative torque demand was cut, for the controller's anti-windup.
    """

    def __init__(self, geometry: RotorGeometry, yaw_moment_coeff: float, max_thrust: float):
        pos, s = geometry.positions, geometry.yaw_signs
        # Rows: collective, roll torque y*f, pitch torque -x*f, yaw torque k*s*f (FLU).
        self.effectiveness = np.stack([np.ones(4), pos[:, 1], -pos[:, 0], yaw_moment_coeff * s])
        self.max_thrust = float(max_thrust)
        rows = self.effectiveness[1:]
        self.torque_max = self.max_thrust * np.clip(rows, 0.0, None).sum(axis=1)
        alloc = np.linalg.inv(self.effectiveness)
        self._a_thrust = alloc[:, 0]
        self._a_rp = alloc[:, 1:3] * self.torque_max[:2]
        self._a_yaw = alloc[:, 3] * self.torque_max[2]

    def mix(self, thrust: float, torque_norm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotor thrusts (4,) in ``[0, max_thrust]`` and saturation flags (3,)."""
        fmax = self.max_thrust
        sat = np.zeros(3)
        f_rp = self._a_rp @ torque_norm[:2]
        spread = f_rp.max() - f_rp.min()
        if spread > fmax:
            f_rp = f_rp * (fmax / spread)
            sat[:2] = np.sign(torque_norm[:2])
        f = self._a_thrust * thrust + f_rp
        low, high = f.min(), f.max()
        if low < 0.0:
            f = f - low
        elif high > fmax:
            f = f - (high - fmax)
        f_yaw = self._a_yaw * torque_norm[2]
        # Largest yaw fraction in [0, 1] that keeps every rotor within its limits.
        alpha = 1.0
        up, down = f_yaw > 1e-12, f_yaw < -1e-12
        if up.any():
            alpha = min(alpha, float(((fmax - f[up]) / f_yaw[up]).min()))
        if down.any():
            alpha = min(alpha, float((-f[down] / f_yaw[down]).min()))
        alpha = max(alpha, 0.0)
        if alpha < 1.0:
            sat[2] = np.sign(torque_norm[2])
        return np.clip(f + alpha * f_yaw, 0.0, fmax), sat

    def wrench(self, rotor_thrusts: np.ndarray) -> np.ndarray:
        """(collective N, torques N m) that rotor thrusts produce on the nominal geometry."""
        return self.effectiveness @ rotor_thrusts


class SetpointLag:
    """Transport delay followed by a first-order filter on the body-rate setpoint.

    Implements the ``rate_lag`` effect; with zero delay and time constant it is the
    identity. Runs at the rate-loop period ``dt``.
    """

    def __init__(self, delay_s: float, time_constant_s: float, dt: float):
        self._n_delay = round(delay_s / dt)
        self._alpha = 1.0 if time_constant_s <= 0.0 else 1.0 - np.exp(-dt / time_constant_s)
        self.reset(np.zeros(3))

    def reset(self, value: np.ndarray) -> None:
        value = np.array(value, dtype=float)
        n = self._n_delay + 1
        self._buf: deque[np.ndarray] = deque([value] * n, maxlen=n)
        self._out = value

    def update(self, value: np.ndarray) -> np.ndarray:
        self._buf.append(np.array(value, dtype=float))
        delayed = self._buf[0]
        self._out = self._out + self._alpha * (delayed - self._out)
        return self._out
