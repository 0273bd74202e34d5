"""The stack's setpoint in the units of PX4's offboard attitude-rate interface, and the
limits a PX4 bridge applies to it (plain NumPy in float64; frames: :mod:`arcade_core.frames`).

ARCADE's input is ``u = [collective thrust N, body rates FLU rad/s (3)]``. PX4 takes body
rates in FRD, in rad/s on the wire but deg/s in MAVSDK's offboard API, and thrust
normalised to ``[0, 1]``.

Thrust: PX4's normalised thrust setpoint ``s`` is linear in force, ``T = T_max * s`` with
``T_max`` = the rotor count x the rotor's maximum thrust. The motors are not linear: their
relative thrust at motor signal ``m`` is ``fac * m^2 + (1 - fac) * m`` (PX4's ``THR_MDL_FAC``
model), and PX4's mixer / control allocation inverts that model at its outputs. So the
thrust curve is applied once, by PX4, and never here: with ``THR_MDL_FAC`` set to the
vehicle file's ``[thrust_curve] thr_mdl_fac`` the setpoint ``s = T / T_max`` gives ``T``.
:class:`ThrustCurve` holds both numbers and converts N <-> ``s``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from arcade_core.frames import flu_to_frd


def rad_to_deg(x: Any) -> np.ndarray:
    """rad (or rad/s) -> deg (or deg/s)."""
    return np.degrees(np.asarray(x, dtype=np.float64))


def deg_to_rad(x: Any) -> np.ndarray:
    """deg (or deg/s) -> rad (or rad/s)."""
    return np.radians(np.asarray(x, dtype=np.float64))


@dataclass(frozen=True)
class ThrustCurve:
    """The vehicle's collective thrust in PX4's normalised thrust (module docstring).

    Attributes:
        fac: the motors' thrust model, what PX4's ``THR_MDL_FAC`` must be set to, in
            ``[0, 1]`` (0: thrust linear in the motor signal, 1: quadratic). PX4 inverts
            it at the motor outputs, so it does not enter :meth:`thrust` or
            :meth:`throttle`.
        max_thrust_n: collective thrust at full throttle, N (rotor count x rotor maximum).
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
        """Collective thrust [N] of PX4's normalised thrust ``s`` (clipped to ``[0, 1]``):
        ``max_thrust_n * s``."""
        return self.max_thrust_n * np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)

    def throttle(self, thrust_n: Any) -> np.ndarray:
        """PX4's normalised thrust in ``[0, 1]`` for ``thrust_n`` [N] (clipped to the range):
        ``thrust_n / max_thrust_n``."""
        return np.clip(np.asarray(thrust_n, dtype=np.float64) / self.max_thrust_n, 0.0, 1.0)


@dataclass(frozen=True)
class Limits:
    """What the bridge lets through to PX4."""

    curve: ThrustCurve
    max_rate: np.ndarray  # (3,) rad/s, FLU axes
    max_throttle: float = 1.0

    @classmethod
    def from_vehicle(cls, vehicle: dict[str, Any], max_throttle: float = 1.0) -> Limits:
        rate = np.asarray(vehicle["rate_loop"]["max_rate_rad_s"], dtype=float).reshape(3)
        if not 0.0 < max_throttle <= 1.0:
            raise ValueError(f"max throttle {max_throttle} not in (0, 1]")
        return cls(ThrustCurve.from_vehicle(vehicle), rate, float(max_throttle))


def attitude_rate_command(u: Any, limits: Limits) -> tuple[np.ndarray, float, bool]:
    """``u = [thrust N, rates FLU rad/s]`` -> (rates FRD deg/s, throttle, clamped?).

    The throttle is PX4's normalised thrust ``T / T_max``, linear (PX4 applies
    ``THR_MDL_FAC`` itself). Rates are clamped per axis to the vehicle's ``max_rate`` and
    the throttle to ``[0, max_throttle]``; ``clamped`` says that a rate or the thrust was
    cut (thrust above ``T_max`` or above ``max_throttle``). Non-finite input is an error: it
    never reaches PX4.
    """
    u = np.asarray(u, dtype=float)
    if u.shape != (4,) or not np.all(np.isfinite(u)):
        raise ValueError(f"bad setpoint {u!r}")
    rates = np.clip(u[1:], -limits.max_rate, limits.max_rate)
    s = float(limits.curve.throttle(u[0]))
    throttle = min(max(s, 0.0), limits.max_throttle)
    clamped = bool(np.any(rates != u[1:]) or throttle != s or u[0] > limits.curve.max_thrust_n)
    return rad_to_deg(flu_to_frd(rates)), throttle, clamped


@dataclass(frozen=True)
class Geofence:
    """An axis-aligned box in the world ENU frame [m]."""

    lo: np.ndarray
    hi: np.ndarray

    @classmethod
    def parse(cls, text: str) -> Geofence:
        """``"xmin,xmax,ymin,ymax,zmin,zmax"`` (ENU metres)."""
        v = [float(x) for x in text.split(",")]
        if len(v) != 6 or not all(math.isfinite(x) for x in v):
            raise ValueError(f"geofence needs 6 finite numbers, got {text!r}")
        lo, hi = np.array(v[0::2]), np.array(v[1::2])
        if np.any(lo >= hi):
            raise ValueError(f"geofence box is empty: {text!r}")
        return cls(lo, hi)

    def contains(self, p: Any) -> bool:
        p = np.asarray(p, dtype=float)
        return bool(np.all(np.isfinite(p)) and np.all(p >= self.lo) and np.all(p <= self.hi))
