"""The simulated vehicle on MAVLink, speaking as a PX4 autopilot (common dialect).

:class:`MavlinkVehicle` connects a :class:`~simulator.px4.vehicle.Px4Vehicle` to one UDP
link (:mod:`simulator.px4.link`). A receive thread decodes what the client sends; the
simulation loop calls :meth:`MavlinkVehicle.send_due` after each physics chunk to stream
telemetry. Both hold :attr:`MavlinkVehicle.lock` while they touch the vehicle.

Streams (rates of PX4's onboard link, changeable with MAV_CMD_SET_MESSAGE_INTERVAL):
HEARTBEAT 1 Hz (MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4, base mode with armed / custom-mode
flags, PX4 ``custom_mode``), SYS_STATUS and EXTENDED_SYS_STATE 5 Hz, ATTITUDE_QUATERNION
50 Hz, ATTITUDE 20 Hz, LOCAL_POSITION_NED 30 Hz, HOME_POSITION 0.5 Hz, ODOMETRY off by
default; STATUSTEXT when something happens. The vehicle is a vision-only PX4: SYS_STATUS
reports no GPS and the vision sensor healthy while mocap is fresh; there is no global
position (GLOBAL_POSITION_INT is not sent; HOME_POSITION has lat/lon/alt 0). As PX4 does,
LOCAL_POSITION_NED (and ODOMETRY) stream only while the local position is valid, and
HOME_POSITION only once home is set: MAVSDK 4 derives ``health.is_local_position_ok`` and
``is_home_position_ok`` from receiving them, not from SYS_STATUS.

Accepted: COMMAND_LONG / COMMAND_INT (arm/disarm, DO_SET_MODE with PX4 custom modes,
NAV_TAKEOFF, NAV_LAND, REQUEST_MESSAGE, SET_MESSAGE_INTERVAL,
REQUEST_AUTOPILOT_CAPABILITIES; anything else is acknowledged UNSUPPORTED),
SET_ATTITUDE_TARGET (the offboard input), ODOMETRY, VISION_POSITION_ESTIMATE and
ATT_POS_MOCAP (external vision in NED/FRD; ODOMETRY frames in ENU/FLU are rejected, as PX4
does), the parameter protocol
for :data:`~simulator.px4.vehicle.PARAM_DEFAULTS` (INT32 values byte-wise, as PX4),
TIMESYNC and PING requests. Malformed or unexpected input is counted in
:attr:`MavlinkVehicle.rejects`, never fatal.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from collections import Counter
from collections.abc import Callable

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from arcade_core import frames
from arcade_core.frames import enu_to_ned, flu_to_frd, quat_enu_flu_to_ned_frd
from simulator.px4.link import UdpLink
from simulator.px4.modes import FlightMode
from simulator.px4.vehicle import PARAM_DEFAULTS, Px4Vehicle

log = logging.getLogger("arcade.px4sim")

#: Default stream rates [Hz] by message name (0: off until requested).
STREAM_RATES_HZ = {
    "HEARTBEAT": 1.0,
    "SYS_STATUS": 5.0,
    "EXTENDED_SYS_STATE": 5.0,
    "ATTITUDE_QUATERNION": 50.0,
    "ATTITUDE": 20.0,
    "LOCAL_POSITION_NED": 30.0,
    "HOME_POSITION": 0.5,
    "ODOMETRY": 0.0,
}
#: PX4 v1.15.0 release, as AUTOPILOT_VERSION encodes it (major, minor, patch, type).
FLIGHT_SW_VERSION = (1 << 24) | (15 << 16) | (0 << 8) | 255
FORCE_MAGIC = 21196  # param2 of ARM_DISARM that skips the checks

# External-vision frames PX4 takes as NED-aligned / FRD (deprecated ids kept numerically).
NED_FRAMES = {
    mavlink.MAV_FRAME_LOCAL_NED: "LOCAL_NED",
    14: "MOCAP_NED",
    16: "VISION_NED",
    18: "ESTIM_NED",
    mavlink.MAV_FRAME_LOCAL_FRD: "LOCAL_FRD",
}

_S = mavlink  # short alias for the many enum names below
SENSORS_PRESENT = (
    _S.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | _S.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | _S.MAV_SYS_STATUS_SENSOR_3D_MAG
    | _S.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | _S.MAV_SYS_STATUS_SENSOR_VISION_POSITION
    | _S.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | _S.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | _S.MAV_SYS_STATUS_SENSOR_YAW_POSITION
    | _S.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | _S.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
    | _S.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | _S.MAV_SYS_STATUS_AHRS
    | _S.MAV_SYS_STATUS_SENSOR_BATTERY
    | _S.MAV_SYS_STATUS_PREARM_CHECK
)
CAPABILITIES = (
    _S.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
    | _S.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | _S.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | _S.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | _S.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    | _S.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
    | _S.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | _S.MAV_PROTOCOL_CAPABILITY_MAVLINK2
)


def _param_wire(value: float | int) -> tuple[float, int]:
    """PARAM_VALUE payload: REAL32 as is, INT32 byte-wise in the float field (PX4)."""
    if isinstance(value, int):
        return struct.unpack("<f", struct.pack("<i", value))[0], mavlink.MAV_PARAM_TYPE_INT32
    return float(value), mavlink.MAV_PARAM_TYPE_REAL32


def _param_from_wire(value: float, param_type: int) -> float | int:
    if param_type in (
        mavlink.MAV_PARAM_TYPE_INT32,
        mavlink.MAV_PARAM_TYPE_UINT32,
        mavlink.MAV_PARAM_TYPE_INT8,
        mavlink.MAV_PARAM_TYPE_UINT8,
        mavlink.MAV_PARAM_TYPE_INT16,
        mavlink.MAV_PARAM_TYPE_UINT16,
    ):
        return struct.unpack("<i", struct.pack("<f", value))[0]
    return float(value)


def _int(x: float, default: int = 0) -> int:
    """Integer command parameter; unused parameters arrive as NaN."""
    return round(x) if math.isfinite(x) else default


class MavlinkVehicle:
    """PX4 impersonation of ``vehicle`` on the UDP link ``url`` (module docstring).

    Args:
        vehicle: the simulated vehicle.
        url: ``udpout://HOST:PORT`` or ``udpin://HOST:PORT``.
        system_id, component_id: our MAVLink address (PX4: 1, 1).
        on_text: called with ``(severity, text)`` for every STATUSTEXT sent (logging,
            bus events).
    """

    def __init__(
        self,
        vehicle: Px4Vehicle,
        url: str,
        *,
        system_id: int = 1,
        component_id: int = 1,
        on_text: Callable[[int, str], None] | None = None,
    ):
        self.vehicle = vehicle
        self.link = UdpLink(url)
        self.mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        self.mav.robust_parsing = True
        self.system_id, self.component_id = system_id, component_id
        self.on_text = on_text
        self.lock = threading.RLock()
        self._send_lock = threading.Lock()
        self.rx: Counter[str] = Counter()
        self.rejects: Counter[str] = Counter()
        self.commands: Counter[int] = Counter()  # COMMAND_LONG/INT ids received
        self._builders: dict[int, Callable[[], object]] = {
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: self._heartbeat,
            mavlink.MAVLINK_MSG_ID_SYS_STATUS: self._sys_status,
            mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: self._extended_sys_state,
            mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: self._attitude_quaternion,
            mavlink.MAVLINK_MSG_ID_ATTITUDE: self._attitude,
            mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: self._local_position_ned,
            mavlink.MAVLINK_MSG_ID_HOME_POSITION: self._home_position,
            mavlink.MAVLINK_MSG_ID_ODOMETRY: self._odometry,
            mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self._autopilot_version,
        }
        self._default_interval = {
            getattr(mavlink, f"MAVLINK_MSG_ID_{name}"): (1.0 / hz if hz > 0 else math.inf)
            for name, hz in STREAM_RATES_HZ.items()
        }
        self._interval = dict(self._default_interval)
        self._next_due = dict.fromkeys(self._interval, 0.0)
        self._home_sent = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.client: tuple[int, int] | None = None  # (sysid, compid) of the last client

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> MavlinkVehicle:
        self._thread = threading.Thread(target=self._rx_loop, name="px4-mavlink-rx", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.link.close()

    def __enter__(self) -> MavlinkVehicle:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ sending

    def _send(self, msg) -> None:
        with self._send_lock:
            data = msg.pack(self.mav)
        self.link.send(data)

    def send_due(self) -> None:
        """Send the streams that are due and queued STATUSTEXTs (call with the lock)."""
        t = self.vehicle.time
        if self.vehicle.home_version != self._home_sent:  # PX4 announces a new home at once
            self._home_sent = self.vehicle.home_version
            self._next_due[mavlink.MAVLINK_MSG_ID_HOME_POSITION] = t
        for msg_id, interval in self._interval.items():
            if interval != math.inf and t >= self._next_due[msg_id]:
                self._next_due[msg_id] = max(self._next_due[msg_id] + interval, t)
                msg = self._builders[msg_id]()
                if msg is not None:
                    self._send(msg)
        texts = self.vehicle.texts
        while texts:
            severity, text = texts.popleft()
            log.info("statustext %d: %s", severity, text)
            if self.on_text is not None:
                self.on_text(severity, text)
            self._send(self.mav.statustext_encode(severity, text.encode()[:50]))

    # ------------------------------------------------------------------ telemetry

    def _boot_ms(self) -> int:
        return int(self.vehicle.time * 1e3) & 0xFFFFFFFF

    def _heartbeat(self):
        v = self.vehicle
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
        if v.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        if v.mode is FlightMode.OFFBOARD or v.mode.is_auto:
            base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
        if v.mode.is_auto:
            base |= mavlink.MAV_MODE_FLAG_AUTO_ENABLED
        status = mavlink.MAV_STATE_ACTIVE if v.armed else mavlink.MAV_STATE_STANDBY
        if v.failsafe and v.armed:
            status = mavlink.MAV_STATE_CRITICAL
        return self.mav.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base, v.mode.custom_mode, status
        )

    def _sys_status(self):
        v = self.vehicle
        health = SENSORS_PRESENT
        if not v.position_ok():
            health &= ~(
                mavlink.MAV_SYS_STATUS_SENSOR_VISION_POSITION | mavlink.MAV_SYS_STATUS_PREARM_CHECK
            )
        if not v.landed and not v.armed:
            health &= ~mavlink.MAV_SYS_STATUS_PREARM_CHECK
        return self.mav.sys_status_encode(
            SENSORS_PRESENT,
            SENSORS_PRESENT,
            health,
            250,
            16000,
            500 if v.armed else 10,
            90,
            0,
            0,
            0,
            0,
            0,
            0,
        )

    def _extended_sys_state(self):
        return self.mav.extended_sys_state_encode(
            mavlink.MAV_VTOL_STATE_UNDEFINED, self.vehicle.landed_state
        )

    def _attitude_quaternion(self):
        x = self.vehicle.state()
        q = quat_enu_flu_to_ned_frd(x[6:10])
        w = flu_to_frd(x[10:13])
        return self.mav.attitude_quaternion_encode(self._boot_ms(), *q, *w)

    def _attitude(self):
        x = self.vehicle.state()
        rpy = frames.to_rpy_np(quat_enu_flu_to_ned_frd(x[6:10]))
        return self.mav.attitude_encode(self._boot_ms(), *rpy, *flu_to_frd(x[10:13]))

    def _local_position_ned(self):
        if not self.vehicle.position_ok():
            return None  # PX4 streams the local position only while it is valid
        x = self.vehicle.state()
        return self.mav.local_position_ned_encode(
            self._boot_ms(), *enu_to_ned(x[0:3]), *enu_to_ned(x[3:6])
        )

    def _home_position(self):
        if self.vehicle.home is None:
            return None  # no home before the estimator had a position
        home = enu_to_ned(self.vehicle.home)
        return self.mav.home_position_encode(
            0, 0, 0, *home, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, int(self.vehicle.time * 1e6)
        )

    def _odometry(self):
        if not self.vehicle.position_ok():
            return None
        x = self.vehicle.state()
        q = quat_enu_flu_to_ned_frd(x[6:10])
        v_body = frames.to_rotation_matrix_np(x[6:10] / np.linalg.norm(x[6:10])).T @ x[3:6]
        nan21 = [math.nan] * 21
        return self.mav.odometry_encode(
            int(self.vehicle.time * 1e6),
            mavlink.MAV_FRAME_LOCAL_NED,
            mavlink.MAV_FRAME_BODY_FRD,
            *enu_to_ned(x[0:3]),
            q,
            *flu_to_frd(v_body),
            *flu_to_frd(x[10:13]),
            nan21,
            nan21,
            0,
            mavlink.MAV_ESTIMATOR_TYPE_VISION,
            100,
        )

    def _autopilot_version(self):
        return self.mav.autopilot_version_encode(
            CAPABILITIES,
            FLIGHT_SW_VERSION,
            0,
            0,
            0,
            list(b"arcadesi"),
            [0] * 8,
            [0] * 8,
            0,
            0,
            0x415243414445,
        )

    # ------------------------------------------------------------------ receiving

    def _rx_loop(self) -> None:
        while not self._stop.is_set():
            data = self.link.recv(0.1)
            if not data:
                continue
            try:
                msgs = self.mav.parse_buffer(data) or []
            except Exception:  # a corrupt datagram must not end the link
                self.rejects["unparsable"] += 1
                continue
            for msg in msgs:
                try:
                    with self.lock:
                        self.handle(msg)
                except Exception:
                    self.rejects["handler_error"] += 1
                    log.exception("error handling %s", msg.get_type())

    def _for_us(self, msg) -> bool:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, self.system_id) and tc in (0, self.component_id)

    def handle(self, msg) -> None:
        """Act on one decoded message (call with the lock)."""
        kind = msg.get_type()
        self.rx[kind] += 1
        if kind == "BAD_DATA":
            self.rejects["bad_data"] += 1
            return
        if kind == "HEARTBEAT":
            self.client = (msg.get_srcSystem(), msg.get_srcComponent())
        elif kind in ("COMMAND_LONG", "COMMAND_INT"):
            if self._for_us(msg):
                self._command(msg, kind == "COMMAND_INT")
        elif kind == "SET_ATTITUDE_TARGET":
            if self._for_us(msg) and not self.vehicle.set_attitude_target(
                msg.type_mask,
                msg.q,
                (msg.body_roll_rate, msg.body_pitch_rate, msg.body_yaw_rate),
                msg.thrust,
            ):
                self.rejects["set_attitude_target"] += 1
        elif kind == "ODOMETRY":
            self._odometry_in(msg)
        elif kind == "VISION_POSITION_ESTIMATE":
            q = frames.from_rpy_py(msg.roll, msg.pitch, msg.yaw)
            if not self.vehicle.set_vision(
                (msg.x, msg.y, msg.z),
                q,
                source="vision_position_estimate",
                frame_id=mavlink.MAV_FRAME_LOCAL_NED,
            ):
                self.rejects["vision_position_estimate"] += 1
        elif kind == "ATT_POS_MOCAP":
            if not self.vehicle.set_vision(
                (msg.x, msg.y, msg.z),
                msg.q,
                source="att_pos_mocap",
                frame_id=mavlink.MAV_FRAME_LOCAL_NED,
            ):
                self.rejects["att_pos_mocap"] += 1
        elif kind.startswith("PARAM_"):
            self._param(msg, kind)
        elif kind == "PING" and msg.target_system == 0:  # a ping request: answer it
            self._send(
                self.mav.ping_encode(
                    msg.time_usec, msg.seq, msg.get_srcSystem(), msg.get_srcComponent()
                )
            )
        elif kind == "TIMESYNC" and msg.tc1 == 0:
            self._send(self.mav.timesync_encode(time.monotonic_ns(), msg.ts1))

    def _odometry_in(self, msg) -> None:
        if msg.frame_id not in NED_FRAMES:
            self.rejects["odometry_frame"] += 1
            return
        q = np.asarray(msg.q, dtype=float)
        if not self.vehicle.set_vision(
            (msg.x, msg.y, msg.z),
            q if np.isfinite(q[0]) else None,
            source="odometry",
            frame_id=msg.frame_id,
        ):
            self.rejects["odometry"] += 1

    # ------------------------------------------------------------------ commands

    def _ack(self, msg, command: int, result: int) -> None:
        self._send(
            self.mav.command_ack_encode(
                command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
            )
        )

    def _command(self, msg, is_int: bool) -> None:
        cmd = msg.command
        p = [msg.param1, msg.param2, msg.param3, msg.param4]
        p += [msg.x, msg.y, msg.z] if is_int else [msg.param5, msg.param6, msg.param7]
        v = self.vehicle
        A, D, U = (
            mavlink.MAV_RESULT_ACCEPTED,
            mavlink.MAV_RESULT_DENIED,
            mavlink.MAV_RESULT_UNSUPPORTED,
        )
        follow = None
        if cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            force = _int(p[1]) == FORCE_MAGIC
            ok, why = v.arm(force) if _int(p[0]) == 1 else v.disarm(force)
            if not ok:
                v.text(4, why)
            result = A if ok else D
        elif cmd == mavlink.MAV_CMD_DO_SET_MODE:
            mode = None
            if _int(p[0]) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                mode = FlightMode.from_px4(_int(p[1]), _int(p[2]))
            result = D if mode is None else (A if v.set_mode(mode)[0] else D)
        elif cmd == mavlink.MAV_CMD_NAV_TAKEOFF:
            result = A if v.takeoff()[0] else D
        elif cmd == mavlink.MAV_CMD_NAV_LAND:
            result = A if v.set_mode(FlightMode.LAND)[0] else D
        elif cmd == mavlink.MAV_CMD_REQUEST_MESSAGE:
            msg_id = _int(p[0], -1)
            builder = self._builders.get(msg_id)
            msg_now = builder() if builder is not None else None
            result = U if builder is None else (A if msg_now is not None else D)
            follow = msg_now
        elif cmd == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            result, follow = A, self._autopilot_version()
        elif cmd == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id, us = _int(p[0], -1), _int(p[1])
            if msg_id in self._interval and msg_id in self._default_interval:
                if us < 0:
                    self._interval[msg_id] = math.inf
                elif us == 0:
                    self._interval[msg_id] = self._default_interval[msg_id]
                else:
                    self._interval[msg_id] = max(us * 1e-6, 1e-3)
                self._next_due[msg_id] = v.time
                result = A
            else:
                result = U
        else:
            result = U
        log.debug("command %d %s -> result %d", cmd, p, result)
        self.commands[cmd] += 1
        self._ack(msg, cmd, result)
        if follow is not None:
            self._send(follow)

    # ------------------------------------------------------------------ parameters

    def _param_value(self, name: str) -> None:
        names = list(PARAM_DEFAULTS)
        value, ptype = _param_wire(self.vehicle.params[name])
        self._send(
            self.mav.param_value_encode(name.encode(), value, ptype, len(names), names.index(name))
        )

    def _param(self, msg, kind: str) -> None:
        if not self._for_us(msg):
            return
        names = list(PARAM_DEFAULTS)
        if kind == "PARAM_REQUEST_LIST":
            for name in names:
                self._param_value(name)
        elif kind == "PARAM_REQUEST_READ":
            name = (
                msg.param_id
                if msg.param_index < 0
                else (names[msg.param_index] if msg.param_index < len(names) else "")
            )
            if name in names:
                self._param_value(name)
            else:
                self.rejects["param_unknown"] += 1
        elif kind == "PARAM_SET":
            name = msg.param_id
            if name in names and self.vehicle.set_param(
                name, _param_from_wire(msg.param_value, msg.param_type)
            ):
                self._param_value(name)
            else:
                self.rejects["param_set"] += 1
