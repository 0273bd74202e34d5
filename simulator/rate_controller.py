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
_I_FACTOR_RATE = float(np.deg2rad(400.0))


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

    The loop runs on three numbers at 500 Hz or more, where NumPy's per-call cost would
    dominate, so it works per axis on Python floats: every operation is elementwise, in
    the order the vector form above has, so the results are the same to the last bit.
    """

    def __init__(self, gains: RateGains, dt: float):
        self.gains = gains
        self.dt = float(dt)
        # First-order low-pass on the gyro derivative (PX4's D-term filter).
        self._d_alpha = float(1.0 - np.exp(-2.0 * np.pi * gains.d_cutoff_hz * self.dt))
        self._axes = tuple(
            zip(
                *(
                    np.asarray(v, dtype=float).tolist()
                    for v in (gains.p, gains.i, gains.d, gains.ff, gains.integrator_limit)
                ),
                strict=True,
            )
        )
        self.reset()

    @property
    def integral(self) -> np.ndarray:
        """Integrator state per axis (normalised torque)."""
        return np.array(self._integral)

    def reset(self, omega: np.ndarray | None = None) -> None:
        self._integral = [0.0, 0.0, 0.0]
        self._prev_omega = [0.0, 0.0, 0.0] if omega is None else np.asarray(omega, float).tolist()
        self._domega = [0.0, 0.0, 0.0]

    def update(self, omega_sp: np.ndarray, omega: np.ndarray, saturation: np.ndarray) -> np.ndarray:
        """Normalised torque setpoint (3,) from the rate setpoint and measured rate."""
        return np.array(
            self.update_values(
                np.asarray(omega_sp, float).tolist(),
                np.asarray(omega, float).tolist(),
                np.asarray(saturation, float).tolist(),
            )
        )

    def update_values(
        self, omega_sp: list[float], omega: list[float], saturation: list[float]
    ) -> list[float]:
        """:meth:`update` on lists of three floats (the simulator's rate loop)."""
        dt, alpha = self.dt, self._d_alpha
        prev, domega, integral = self._prev_omega, self._domega, self._integral
        torque = [0.0, 0.0, 0.0]
        for k, (p, i, d, ff, limit) in enumerate(self._axes):
            sp, om = omega_sp[k], omega[k]
            err = sp - om
            raw_d = (om - prev[k]) / dt
            dom = domega[k] + alpha * (raw_d - domega[k])
            domega[k] = dom
            torque[k] = p * err + integral[k] - d * dom + ff * sp
            # Integrate unless that deepens a saturation the mixer reported for this axis.
            if saturation[k] * err > 0.0:
                step = 0.0
            else:
                q = err / _I_FACTOR_RATE
                step = i * max(0.0, 1.0 - q * q) * err * dt
            integral[k] = min(max(integral[k] + step, -limit), limit)
        self._prev_omega = list(omega)
        return torque


class Mixer:
    """Allocation of (collective thrust N, normalised torques) to four rotor thrusts.

    Saturation handling (PX4 style, air-mode off): roll/pitch first — if their differential
    demand does not fit in ``[0, max_thrust]`` it is scaled down; then the collective is
    shifted only as far as needed to bring every rotor into range (so it is kept whenever
    possible); yaw gets whatever headroom is left. ``mix`` also returns, per axis, +1/-1
    when the positive/negative torque demand was cut, for the controller's anti-windup.

    Like :class:`RateController` it works on Python floats (the roll/pitch allocation
    stays a NumPy product, whose rounding is that of the vector form).
    """

    def __init__(self, geometry: RotorGeometry, yaw_moment_coeff: float, max_thrust: float):
        pos, s = geometry.positions, geometry.yaw_signs
        # Rows: collective, roll torque y*f, pitch torque -x*f, yaw torque k*s*f (FLU).
        self.effectiveness = np.stack([np.ones(4), pos[:, 1], -pos[:, 0], yaw_moment_coeff * s])
        self.max_thrust = float(max_thrust)
        rows = self.effectiveness[1:]
        self.torque_max = self.max_thrust * np.clip(rows, 0.0, None).sum(axis=1)
        alloc = np.linalg.inv(self.effectiveness)
        self._a_thrust = alloc[:, 0].tolist()
        self._a_rp = alloc[:, 1:3] * self.torque_max[:2]
        self._a_yaw = (alloc[:, 3] * self.torque_max[2]).tolist()

    def mix(self, thrust: float, torque_norm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotor thrusts (4,) in ``[0, max_thrust]`` and saturation flags (3,)."""
        f, sat = self.mix_values(float(thrust), np.asarray(torque_norm, float).tolist())
        return np.array(f), np.array(sat)

    def mix_values(self, thrust: float, torque_norm: list[float]) -> tuple[list, list]:
        """:meth:`mix` on a list of three torques; lists of four thrusts and three flags."""
        fmax = self.max_thrust
        sat = [0.0, 0.0, 0.0]
        f_rp = (self._a_rp @ np.array(torque_norm[:2])).tolist()
        spread = max(f_rp) - min(f_rp)
        if spread > fmax:
            scale = fmax / spread
            f_rp = [v * scale for v in f_rp]
            sat[0], sat[1] = _sign(torque_norm[0]), _sign(torque_norm[1])
        f = [a * thrust + r for a, r in zip(self._a_thrust, f_rp, strict=True)]
        low, high = min(f), max(f)
        if low < 0.0:
            f = [v - low for v in f]
        elif high > fmax:
            shift = high - fmax
            f = [v - shift for v in f]
        yaw = torque_norm[2]
        f_yaw = [a * yaw for a in self._a_yaw]
        # Largest yaw fraction in [0, 1] that keeps every rotor within its limits.
        alpha = 1.0
        for v, y in zip(f, f_yaw, strict=True):
            if y > 1e-12:
                alpha = min(alpha, (fmax - v) / y)
            elif y < -1e-12:
                alpha = min(alpha, -v / y)
        alpha = max(alpha, 0.0)
        if alpha < 1.0:
            sat[2] = _sign(yaw)
        return [min(max(v + alpha * y, 0.0), fmax) for v, y in zip(f, f_yaw, strict=True)], sat

    def wrench(self, rotor_thrusts: np.ndarray) -> np.ndarray:
        """(collective N, torques N m) that rotor thrusts produce on the nominal geometry."""
        return self.effectiveness @ rotor_thrusts


def _sign(x: float) -> float:
    return float((x > 0.0) - (x < 0.0))


class SetpointLag:
    """Transport delay followed by a first-order filter on the body-rate setpoint.

    Implements the ``rate_lag`` effect; with zero delay and time constant it is the
    identity. Runs at the rate-loop period ``dt``.
    """

    def __init__(self, delay_s: float, time_constant_s: float, dt: float):
        self._n_delay = round(delay_s / dt)
        self._alpha = 1.0 if time_constant_s <= 0.0 else float(1.0 - np.exp(-dt / time_constant_s))
        self.reset(np.zeros(3))

    def reset(self, value: np.ndarray) -> None:
        value = np.asarray(value, dtype=float).tolist()
        n = self._n_delay + 1
        self._buf: deque[list[float]] = deque([value] * n, maxlen=n)
        self._out = value

    def update(self, value: np.ndarray) -> np.ndarray:
        return np.array(self.update_values(np.asarray(value, dtype=float).tolist()))

    def update_values(self, value: list[float]) -> list[float]:
        """:meth:`update` on a list of three floats (kept as a copy while it is delayed)."""
        self._buf.append(list(value))
        a = self._alpha
        self._out = [o + a * (v - o) for o, v in zip(self._out, self._buf[0], strict=True)]
        return self._out
