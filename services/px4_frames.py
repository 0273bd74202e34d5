"""Frame, unit and thrust conversions between ARCADE and PX4 (one place, both directions).

ARCADE (design §4): world ENU (x east, y north, z up), body FLU (x forward, y left, z up),
quaternions ``w`` first and body-to-world, SI units, input ``u = [collective thrust N,
body rates rad/s (3)]``.

PX4 / MAVLink: world NED (x north, y east, z down), body FRD (x forward, y right, z down),
quaternions ``w`` first and body-FRD-to-world-NED, body rates in rad/s on the wire but
deg/s in MAVSDK's offboard API, thrust normalised to ``[0, 1]``.

Both changes of axes are proper rotations by 180 degrees, hence their own inverses:

- ENU <-> NED swaps x and y and negates z: ``(e, n, u) -> (n, e, -u)``;
- FLU <-> FRD negates y and z: ``(f, l, u) -> (f, -l, -u)``.

The attitude quaternion changes as ``q_ned_frd = q_ned_enu * q_enu_flu * q_flu_frd`` with
the two constant rotations above (``*`` the Hamilton product). On a motion-capture world
frame that is not aligned with north, "NED" here is the mocap frame with its axes changed
this way: tell PX4 it is an arbitrary-heading frame (``LOCAL_FRD``), see docs/px4.md.

Thrust: PX4 maps normalised throttle ``s`` to thrust with the ``THR_MDL_FAC`` model
``T / T_max = fac * s^2 + (1 - fac) * s`` with ``T_max`` = 4 x the rotor's maximum thrust.
:class:`ThrustCurve` evaluates it and its inverse (the root of the quadratic in the
cancellation-free form ``s = 2 r / ((1 - fac) + sqrt((1 - fac)^2 + 4 fac r))``, exact for
``fac = 0`` too). Everything here is plain numpy in float64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Rotation ENU -> NED (180 degrees about (1, 1, 0)/sqrt 2), w first; its own inverse.
Q_NED_ENU = np.array([0.0, math.sqrt(0.5), math.sqrt(0.5), 0.0])
#: Rotation FRD -> FLU (180 degrees about x), w first; its own inverse.
Q_FLU_FRD = np.array([0.0, 1.0, 0.0, 0.0])

_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_FLU_FRD = np.diag([1.0, -1.0, -1.0])


def _vec(v: Any) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.shape[-1:] != (3,):
        raise ValueError(f"expected (..., 3) vectors, got shape {a.shape}")
    return a


def enu_to_ned(v: Any) -> np.ndarray:
    """World vector(s) (position, velocity, ...) ENU -> NED: ``(e, n, u) -> (n, e, -u)``."""
    return _vec(v) @ _ENU_NED.T


def ned_to_enu(v: Any) -> np.ndarray:
    """World vector(s) NED -> ENU: ``(n, e, d) -> (e, n, -d)`` (the same permutation)."""
    return _vec(v) @ _ENU_NED.T


def flu_to_frd(v: Any) -> np.ndarray:
    """Body vector(s) (rates, forces, ...) FLU -> FRD: ``(f, l, u) -> (f, -l, -u)``."""
    return _vec(v) @ _FLU_FRD.T


def frd_to_flu(v: Any) -> np.ndarray:
    """Body vector(s) FRD -> FLU (the same sign change)."""
    return _vec(v) @ _FLU_FRD.T


def quat_mul(a: Any, b: Any) -> np.ndarray:
    """Hamilton product ``a * b`` of ``w``-first quaternions (broadcasts over leading axes)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_enu_flu_to_ned_frd(q: Any) -> np.ndarray:
    """Attitude body-FLU-to-world-ENU -> body-FRD-to-world-NED (``w`` first)."""
    return quat_mul(quat_mul(Q_NED_ENU, q), Q_FLU_FRD)


def quat_ned_frd_to_enu_flu(q: Any) -> np.ndarray:
    """Attitude body-FRD-to-world-NED -> body-FLU-to-world-ENU (``w`` first).

    Exact inverse of :func:`quat_enu_flu_to_ned_frd` (both constant rotations are 180
    degrees, so each equals its inverse up to a sign that cancels in the product).
    """
    return quat_mul(quat_mul(-Q_NED_ENU, q), -Q_FLU_FRD)


def quat_to_euler_zyx(q: Any) -> np.ndarray:
    """Roll, pitch, yaw [rad] (intrinsic z-y'-x'', aerospace) of a ``w``-first quaternion.

    For a body-FRD-to-NED attitude these are PX4's Euler angles (yaw 0 = facing north).
    """
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    roll = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2.0 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return np.stack([roll, pitch, yaw], axis=-1)


def euler_zyx_to_quat(euler: Any) -> np.ndarray:
    """Inverse of :func:`quat_to_euler_zyx`: roll, pitch, yaw [rad] -> ``w``-first quaternion."""
    r, p, y = np.moveaxis(np.asarray(euler, dtype=np.float64) / 2.0, -1, 0)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        axis=-1,
    )


def rad_to_deg(x: Any) -> np.ndarray:
    """rad (or rad/s) -> deg (or deg/s)."""
    return np.degrees(np.asarray(x, dtype=np.float64))


def deg_to_rad(x: Any) -> np.ndarray:
    """deg (or deg/s) -> rad (or rad/s)."""
    return np.radians(np.asarray(x, dtype=np.float64))


@dataclass(frozen=True)
class ThrustCurve:
    """PX4's ``THR_MDL_FAC`` thrust model of the whole vehicle.

    Attributes:
        fac: ``THR_MDL_FAC`` in ``[0, 1]`` (0: thrust linear in throttle, 1: quadratic).
        max_thrust_n: collective thrust at full throttle, N (4 x the rotor maximum).
    """

    fac: float
    max_thrust_n: float

    def __post_init__(self) -> None:
        if not 0.0 <= self.fac <= 1.0:
            raise ValueError(f"thr_mdl_fac {self.fac} not in [0, 1]")
        if not self.max_thrust_n > 0.0:
            raise ValueError(f"max thrust {self.max_thrust_n} N must be positive")

    @classmethod
    def from_vehicle(cls, vehicle: dict[str, Any]) -> ThrustCurve:
        """From a vehicle file (``[thrust_curve] thr_mdl_fac``, ``[rotors] max_thrust_n``)."""
        rotors = vehicle["rotors"]
        n_rotors = int(rotors.get("count", 4))
        fac = float(vehicle.get("thrust_curve", {}).get("thr_mdl_fac", 0.0))
        return cls(fac=fac, max_thrust_n=n_rotors * float(rotors["max_thrust_n"]))

    def thrust(self, s: Any) -> np.ndarray:
        """Collective thrust [N] at normalised throttle ``s`` (clipped to ``[0, 1]``)."""
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)
        return self.max_thrust_n * (self.fac * s * s + (1.0 - self.fac) * s)

    def throttle(self, thrust_n: Any) -> np.ndarray:
        """Normalised throttle in ``[0, 1]`` that gives ``thrust_n`` (clipped to the range)."""
        r = np.clip(np.asarray(thrust_n, dtype=np.float64) / self.max_thrust_n, 0.0, 1.0)
        a = 1.0 - self.fac
        den = a + np.sqrt(a * a + 4.0 * self.fac * r)
        # den = 0 only for fac = 1 and r = 0, where the root is 0.
        return np.divide(2.0 * r, den, out=np.zeros_like(r), where=den > 0.0)


__all__ = [
    "Q_FLU_FRD",
    "Q_NED_ENU",
    "ThrustCurve",
    "deg_to_rad",
    "enu_to_ned",
    "euler_zyx_to_quat",
    "flu_to_frd",
    "frd_to_flu",
    "ned_to_enu",
    "quat_enu_flu_to_ned_frd",
    "quat_mul",
    "quat_ned_frd_to_enu_flu",
    "quat_to_euler_zyx",
    "rad_to_deg",
]
