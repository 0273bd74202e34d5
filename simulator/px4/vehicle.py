"""PX4's commander, in small: arming, flight modes, offboard input and its loss failsafe.

:class:`Px4Vehicle` owns a :class:`~simulator.px4.airframe.Px4Airframe` and decides each
step what its rate loop gets: the offboard attitude-rate setpoint, the position
controller of the vehicle's own modes (hold, take-off, land) or nothing (disarmed: motors
off). It has no I/O: :mod:`simulator.px4.mavlink_vehicle` feeds it MAVLink input and
reads its state. All times are simulation time [s].

Behaviour, after PX4 (v1.14/1.15):

- **Estimator health.** The vehicle is set up like a PX4 that fuses external vision only
  (no GPS, no global origin): its local position is valid while vision (ODOMETRY or
  VISION_POSITION_ESTIMATE) arrived within ``vision_timeout_s``. With
  ``vision_required=False`` the estimator counts as always valid (a stand-alone vehicle
  without motion capture). The telemetry it reports is the ground truth, i.e. a perfect
  estimator. Home is set when the position first becomes valid and again on arming.
- **Arming** is denied without a valid local position and when not landed (``force``
  overrides both, like PX4's 21196 magic). Disarming in the air is denied unless forced.
  Landed and armed without taking off for ``COM_DISARM_PRFLT`` [s] disarms; so does a
  landing (after ``COM_DISARM_LAND`` [s] on the ground).
- **Offboard** is entered only while an offboard setpoint stream is present (a
  SET_ATTITUDE_TARGET within ``COM_OF_LOSS_T``); otherwise the mode change is denied.
  When the stream stops for longer than ``COM_OF_LOSS_T`` the vehicle leaves offboard for
  ``COM_OBL_RC_ACT`` (0: Position, 4: Land, 5: Hold; default Hold) and says so.
- **Hold / Position** keep the position where the mode was entered; on the ground the
  motors idle. **Take-off** climbs ``MIS_TAKEOFF_ALT`` above the ground and switches to
  Hold. **Land** descends at ``MPC_LAND_SPEED``; without a valid position it is PX4's
  Descend: level, no horizontal correction (the vehicle keeps its drift).
- **Thrust.** The offboard thrust setpoint is PX4's normalised thrust, linear in force:
  ``s`` gives ``T_max * s`` (:class:`~arcade_core.px4_command.ThrustCurve`). The simulated
  PX4's mixer inverts the motors' thrust curve exactly, i.e. its ``THR_MDL_FAC`` equals the
  vehicle file's ``[thrust_curve] thr_mdl_fac``; a real PX4 with a wrong ``THR_MDL_FAC``
  would be off by the mismatch, which this vehicle does not model.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from arcade_core import frames
from arcade_core.frames import flu_to_frd, frd_to_flu, ned_to_enu, quat_ned_frd_to_enu_flu
from arcade_core.px4_command import ThrustCurve
from arcade_io.px4_failsafe import LOSS_ACTIONS
from simulator.px4.airframe import Px4Airframe
from simulator.px4.modes import FlightMode
from simulator.px4.position_control import PositionController, attitude_to_rates

#: PX4 parameters the vehicle honours: name -> default (int params are INT32 on MAVLink).
PARAM_DEFAULTS: dict[str, float | int] = {
    "COM_OF_LOSS_T": 1.0,  # offboard loss timeout [s]
    "COM_OBL_RC_ACT": 5,  # offboard loss action: 0 Position, 4 Land, 5 Hold
    "COM_DISARM_LAND": 2.0,  # disarm this long after landing [s] (<= 0: never)
    "COM_DISARM_PRFLT": 10.0,  # disarm when armed on the ground without take-off [s]
    "MIS_TAKEOFF_ALT": 2.5,  # take-off height above the ground [m]
    "MPC_LAND_SPEED": 0.7,  # descent speed of Land [m/s]
}
#: COM_OBL_RC_ACT value -> the mode an offboard loss switches to.
OFFBOARD_LOSS_ACTIONS = {code: FlightMode[name.upper()] for name, code in LOSS_ACTIONS.items()}

# SET_ATTITUDE_TARGET type_mask bits.
IGNORE_ROLL_RATE, IGNORE_PITCH_RATE, IGNORE_YAW_RATE = 1, 2, 4
IGNORE_THROTTLE, IGNORE_ATTITUDE = 64, 128

# MAV_LANDED_STATE.
LANDED_ON_GROUND, LANDED_IN_AIR, LANDED_TAKEOFF, LANDED_LANDING = 1, 2, 3, 4

#: Land detector: near the ground (above the resting height), slow, thrust below hover.
LAND_HEIGHT_M = 0.05
LAND_SPEED_MPS = 0.3
LAND_THRUST_FRAC = 0.9
LAND_TIME_S = 0.3

# STATUSTEXT severities (MAV_SEVERITY).
SEV_CRITICAL, SEV_WARNING, SEV_NOTICE, SEV_INFO = 2, 4, 5, 6


@dataclass
class OffboardSetpoint:
    """Latest SET_ATTITUDE_TARGET, converted: thrust [N], body rates FLU [rad/s] and,
    unless ignored, the attitude (body FLU -> ENU) to hold."""

    thrust: float
    rates: np.ndarray
    attitude: np.ndarray | None
    time: float


@dataclass
class VisionSample:
    """Latest external-vision input as received (NED/FRD) and its receive time."""

    position_ned: np.ndarray
    quaternion_ned_frd: np.ndarray | None
    source: str
    frame_id: int
    time: float

    @property
    def position_enu(self) -> np.ndarray:
        return ned_to_enu(self.position_ned)


class Px4Vehicle:
    """Flight-mode logic around a simulated airframe (module docstring).

    Args:
        sim: the airframe (a :class:`Px4Airframe`).
        start: start position ENU [m]; on the ground its height is ignored.
        yaw: start heading (ENU yaw) [rad].
        airborne: start hovering at ``start``, armed, in Hold (a vehicle that has already
            taken off); otherwise disarmed on the floor below ``start``.
        vision_required: the local position needs fresh vision (module docstring).
        vision_timeout_s: vision older than this no longer counts.
        params: overrides of :data:`PARAM_DEFAULTS`.
    """

    def __init__(
        self,
        sim: Px4Airframe,
        *,
        start=(0.0, 0.0, 0.0),
        yaw: float = 0.0,
        airborne: bool = False,
        vision_required: bool = True,
        vision_timeout_s: float = 0.5,
        params: dict[str, Any] | None = None,
    ):
        self.sim = sim
        self.curve = ThrustCurve.from_vehicle(sim.vehicle)
        self.pos_ctl = PositionController(gravity=sim.gravity)
        self.params: dict[str, float | int] = dict(PARAM_DEFAULTS)
        for name, value in (params or {}).items():
            if not self.set_param(name, value):
                raise ValueError(f"unknown or invalid PX4 parameter {name}={value!r}")
        self.vision_required = bool(vision_required)
        self.vision_timeout_s = float(vision_timeout_s)
        self.texts: deque[tuple[int, str]] = deque(maxlen=64)
        self.offboard_sp: OffboardSetpoint | None = None
        self.vision: VisionSample | None = None
        self.rejected = 0
        start = np.asarray(start, dtype=float)
        self.ground_z = sim.rest_on_ground(start[:2], yaw)
        if airborne:
            sim.reset(position=start, yaw=yaw)
            self.armed, self.landed = True, False
        else:
            self.armed, self.landed = False, True
        sim.motors_enabled = self.armed
        sim.landed = self.landed
        self.mode = FlightMode.HOLD
        self.failsafe = False
        self._hold_p, self._hold_yaw = self._pose()
        self._target_p = self._hold_p.copy()
        self._landed_since = 0.0 if self.landed else math.inf
        self._armed_since = 0.0
        self._took_off = airborne
        #: Home (ENU), set once the estimator first has a position and again on arming.
        self.home: np.ndarray | None = self._hold_p.copy() if self.position_ok() else None
        self.home_version = 0  # bumped whenever home is (re)set

    # ------------------------------------------------------------------ state

    @property
    def time(self) -> float:
        return self.sim.time

    def state(self) -> np.ndarray:
        """Ground-truth state ``[p, v, q, omega]`` (ENU/FLU)."""
        return self.sim.state()

    def _pose(self) -> tuple[np.ndarray, float]:
        x = self.sim.state()
        return x[0:3].copy(), frames.yaw_py(x[6:10])

    @property
    def hold_position(self) -> np.ndarray:
        """Where Hold / Position keep the vehicle (ENU) [m]."""
        return self._hold_p.copy()

    def own_target(self) -> np.ndarray | None:
        """Where PX4's own controller steers the vehicle (ENU) [m], or None in Offboard:
        the hold position in Hold / Position, the take-off point, in Land the landing point
        at the current height (the descent is not an error), and disarmed where it is."""
        if not self.armed:
            return self.sim.state()[:3].copy()
        if self.mode is FlightMode.OFFBOARD:
            return None
        if self.mode is FlightMode.TAKEOFF:
            return self._target_p.copy()
        if self.mode is FlightMode.LAND:
            x = self.sim.state()
            # Without a position estimate the descent drifts (see _control): no target.
            return x[:3].copy() if not self.position_ok() else np.r_[self._target_p[:2], x[2]]
        return self._hold_p.copy()

    def position_ok(self) -> bool:
        """Whether the (vision-aided) estimator has a valid local position."""
        if not self.vision_required:
            return True
        return self.vision is not None and self.time - self.vision.time <= self.vision_timeout_s

    def offboard_signal(self) -> bool:
        """Whether an offboard setpoint arrived within ``COM_OF_LOSS_T``."""
        sp = self.offboard_sp
        return sp is not None and self.time - sp.time <= float(self.params["COM_OF_LOSS_T"])

    @property
    def landed_state(self) -> int:
        if self.mode is FlightMode.TAKEOFF and self.armed:
            return LANDED_TAKEOFF
        if self.landed:
            return LANDED_ON_GROUND
        return LANDED_LANDING if self.mode is FlightMode.LAND else LANDED_IN_AIR

    def text(self, severity: int, text: str) -> None:
        """Queue a STATUSTEXT for the ground station."""
        self.texts.append((severity, text))

    # ------------------------------------------------------------------ parameters

    def set_param(self, name: str, value: float) -> bool:
        """Set a known parameter (ints stay ints); False if unknown or invalid."""
        if name not in PARAM_DEFAULTS or not math.isfinite(float(value)):
            return False
        if isinstance(PARAM_DEFAULTS[name], int):
            value = int(value)
            if name == "COM_OBL_RC_ACT" and value not in OFFBOARD_LOSS_ACTIONS:
                return False
        self.params[name] = value if isinstance(value, int) else float(value)
        return True

    # ------------------------------------------------------------------ inputs

    def set_attitude_target(self, type_mask: int, q_ned_frd, rates_frd, thrust: float) -> bool:
        """A SET_ATTITUDE_TARGET: rates FRD [rad/s], normalised thrust [0, 1] (linear in
        force: ``s`` gives ``T_max * s``, the motors' curve is inverted by the mixer)."""
        rates = np.asarray(rates_frd, dtype=float)
        rates = np.where(
            [bool(type_mask & b) for b in (IGNORE_ROLL_RATE, IGNORE_PITCH_RATE, IGNORE_YAW_RATE)],
            0.0,
            rates,
        )
        attitude = None
        if not type_mask & IGNORE_ATTITUDE:
            q = np.asarray(q_ned_frd, dtype=float)
            if not np.all(np.isfinite(q)) or np.linalg.norm(q) < 0.5:
                self.rejected += 1
                return False
            attitude = quat_ned_frd_to_enu_flu(q)
        if not np.all(np.isfinite(rates)) or not math.isfinite(thrust):
            self.rejected += 1
            return False
        if type_mask & IGNORE_THROTTLE:
            thrust_n = self.offboard_sp.thrust if self.offboard_sp else 0.0
        else:
            # PX4's mixer inverts the motors' THR_MDL_FAC curve: the force is T_max * s.
            thrust_n = float(self.curve.thrust(thrust))
        self.offboard_sp = OffboardSetpoint(thrust_n, frd_to_flu(rates), attitude, self.time)
        return True

    def set_vision(
        self, position_ned, quaternion_ned_frd=None, *, source: str = "odometry", frame_id: int = 0
    ) -> bool:
        """External vision (mocap) in PX4's frames; non-finite positions are rejected."""
        p = np.asarray(position_ned, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            self.rejected += 1
            return False
        q = None
        if quaternion_ned_frd is not None and np.all(np.isfinite(quaternion_ned_frd)):
            q = np.asarray(quaternion_ned_frd, dtype=float)
        self.vision = VisionSample(p, q, source, int(frame_id), self.time)
        return True

    # ------------------------------------------------------------------ commands

    def arm(self, force: bool = False) -> tuple[bool, str]:
        if self.armed:
            return True, "already armed"
        if not force and not self.landed:
            return False, "Arming denied: vehicle not landed"
        if not force and not self.position_ok():
            return False, "Arming denied: no valid position estimate (vision)"
        self.armed = True
        self._armed_since = self.time
        self._took_off = False
        self.home, _ = self._pose()
        self.home_version += 1
        self.text(SEV_INFO, "Armed by external command")
        if self.mode is FlightMode.HOLD or self.mode is FlightMode.POSITION:
            self._hold_p, self._hold_yaw = self._pose()
        return True, "armed"

    def disarm(self, force: bool = False) -> tuple[bool, str]:
        if not self.armed:
            return True, "already disarmed"
        if not force and not self.landed:
            return False, "Disarming denied: not landed"
        self.armed = False
        self.text(SEV_INFO, "Disarmed by external command")
        return True, "disarmed"

    def set_mode(self, mode: FlightMode) -> tuple[bool, str]:
        """Request a mode change (PX4's mode-switch checks)."""
        if mode is FlightMode.OFFBOARD and not self.offboard_signal():
            self.text(SEV_CRITICAL, "Switching to Offboard is currently not possible")
            return False, "no offboard setpoint stream"
        if mode in (FlightMode.HOLD, FlightMode.POSITION) and not self.position_ok():
            return False, "no valid position estimate"
        if mode is FlightMode.TAKEOFF:
            return self.takeoff()
        self._enter(mode)
        return True, mode.name

    def takeoff(self, altitude_m: float | None = None) -> tuple[bool, str]:
        """Climb to ``altitude_m`` (default ``MIS_TAKEOFF_ALT``) above the ground."""
        if not self.armed:
            return False, "Takeoff denied: disarmed"
        if not self.position_ok():
            return False, "Takeoff denied: no valid position estimate"
        alt = float(self.params["MIS_TAKEOFF_ALT"]) if altitude_m is None else altitude_m
        p, yaw = self._pose()
        self._target_p = np.array([p[0], p[1], self.ground_z + alt])
        self._hold_yaw = yaw
        self._enter(FlightMode.TAKEOFF)
        return True, "takeoff"

    def _enter(self, mode: FlightMode) -> None:
        if mode is self.mode:
            return
        if mode in (FlightMode.HOLD, FlightMode.POSITION):
            self._hold_p, self._hold_yaw = self._pose()
        elif mode is FlightMode.LAND:
            self._target_p, self._hold_yaw = self._pose()
        if mode is FlightMode.OFFBOARD:
            self.failsafe = False
        self.mode = mode

    # ------------------------------------------------------------------ stepping

    def step(self, dt: float) -> None:
        """Run the commander and the controllers for ``dt`` seconds of simulation."""
        self._commander()
        self.sim.motors_enabled = self.armed
        self.sim.landed = self.landed
        self.sim.set_setpoint(self._control())
        self.sim.step(dt)

    def _commander(self) -> None:
        t = self.time
        if self.home is None and self.position_ok():
            self.home, _ = self._pose()
            self.home_version += 1
        if self.mode is FlightMode.OFFBOARD and not self.offboard_signal():
            action = OFFBOARD_LOSS_ACTIONS[int(self.params["COM_OBL_RC_ACT"])]
            self._enter(action)
            self.failsafe = True
            self.text(
                SEV_CRITICAL, f"Failsafe: offboard signal lost, switching to {action.name.title()}"
            )
        self._detect_land(t)
        if self.mode is FlightMode.TAKEOFF and abs(self.sim.state()[2] - self._target_p[2]) < 0.1:
            self._enter(FlightMode.HOLD)
            self._hold_p = self._target_p.copy()
            self.text(SEV_INFO, "Takeoff complete")
        if self.armed and self.landed:
            flew = self._took_off
            limit = float(self.params["COM_DISARM_LAND" if flew else "COM_DISARM_PRFLT"])
            since = max(self._landed_since, self._armed_since)
            if limit > 0.0 and t - since > limit:
                self.armed = False
                self.text(
                    SEV_INFO,
                    "Landing detected: disarmed" if flew else "Disarmed: no take-off after arming",
                )

    def _detect_land(self, t: float) -> None:
        x = self.sim.state()
        hover = self.sim.hover_thrust()
        near = x[2] < self.ground_z + LAND_HEIGHT_M
        quiet = (
            np.linalg.norm(x[3:6]) < LAND_SPEED_MPS
            and self.sim.setpoint[0] < LAND_THRUST_FRAC * hover
        )
        if near and (quiet or not self.armed):
            if self._landed_since == math.inf:
                self._landed_since = t
            if not self.landed and t - self._landed_since >= LAND_TIME_S:
                self.landed = True
                if self.armed:
                    self.text(SEV_INFO, "Landing detected")
        else:
            self._landed_since = math.inf
            if self.landed and not near:
                self.landed = False
                self._took_off = self._took_off or self.armed

    def _control(self) -> np.ndarray:
        """``[collective N, body rates FLU]`` for the rate loop."""
        if not self.armed:
            return np.zeros(4)
        x = self.sim.state()
        # The carried mass is known exactly: an ideal version of PX4's hover-thrust estimator.
        hover = self.sim.hover_thrust()
        if self.mode is FlightMode.OFFBOARD:
            sp = self.offboard_sp
            rates = sp.rates
            if sp.attitude is not None:
                q = x[6:10] / np.linalg.norm(x[6:10])
                rates = rates + attitude_to_rates(q, sp.attitude, self.pos_ctl.g.att_p)
            return np.array([sp.thrust, *rates])
        if self.mode is FlightMode.TAKEOFF:
            return self.pos_ctl.control(x, self._target_p, self._hold_yaw, hover)
        if self.landed:
            return np.zeros(4)  # auto modes idle on the ground
        if self.mode is FlightMode.LAND:
            v_sp = [math.nan, math.nan, -float(self.params["MPC_LAND_SPEED"])]
            if not self.position_ok():
                # PX4's Descend: no horizontal position to hold, so no horizontal
                # correction (level, the vehicle keeps its drift); height rate only.
                v_sp[:2] = x[3:5]
            return self.pos_ctl.control(x, self._target_p, self._hold_yaw, hover, v_sp=v_sp)
        return self.pos_ctl.control(x, self._hold_p, self._hold_yaw, hover)

    # ------------------------------------------------------------------ telemetry

    def release_payload(self) -> bool:
        """Switch the electromagnet off (see :meth:`QuadrotorSim.release_payload`)."""
        return self.sim.release_payload()

    def rates_frd(self) -> np.ndarray:
        return flu_to_frd(self.sim.state()[10:13])
