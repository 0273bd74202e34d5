"""PX4 bridge service: the controller's setpoints to a PX4 vehicle in offboard mode (MAVSDK).

Replaces the simulator as the vehicle link (design §3). Connects with MAVSDK (``--connect``,
any MAVSDK URL: ``udpin://0.0.0.0:14540`` for SITL or a telemetry radio bridge,
``serial:///dev/ttyACM0:921600`` for USB), waits for a connected, healthy autopilot, then:

- ``setpoint`` -> ``set_attitude_rate``: body rates FLU rad/s -> FRD deg/s clamped to the
  vehicle file's ``max_rate_rad_s``; collective thrust N -> PX4's normalised thrust
  ``T / T_max`` (linear: PX4's mixer applies ``THR_MDL_FAC`` itself), clamped to
  ``[0, --max-throttle]`` (:mod:`arcade_core.px4_command`). Only while offboard control is
  engaged by this bridge.
- ``mocap`` -> PX4 ``ODOMETRY`` (MAVSDK mocap plugin): position NED, attitude FRD-to-NED, in
  a ``LOCAL_FRD`` world frame (the mocap frame need not face north), estimator type vision,
  so that PX4's EKF2 has the external-vision position it needs to hold or land by itself.
  The vehicle's frames only (body ``--mocap-body``, default ``vehicle``): other rigid
  bodies on the stream (a payload) are neither forwarded nor checked against the
  geofence, nor counted (the estimator says when only those come).
- ``--forward URL`` (repeatable): every MAVLink message between PX4 and the bridge's
  link is also passed to and from URL (MAVSDK's forwarding connections), e.g.
  ``udpout://127.0.0.1:14550`` for QGroundControl beside the stack.
- PX4 telemetry -> bus: ``imu`` at the control rate (PX4's body rates, FLU; each sample is
  a control instant for the estimator, as the simulator's are), ``event`` on every arming,
  flight-mode, offboard and health change, and a ``vehicle_status`` event (severity
  ``debug``, ``--status-rate``) with PX4's own attitude, local position and velocity (ENU/FLU).

Engaging offboard control, leaving it, the failsafes and the operator's commands:
:mod:`services.px4_offboard`; the command-line options: :mod:`services.px4_bridge_options`;
the conversions and limits themselves (pure NumPy): :mod:`arcade_core.px4_command` and
:mod:`arcade_core.frames`.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np

from arcade_core import frames
from arcade_core.px4_command import Geofence, Limits, attitude_rate_command
from arcade_io.vehicle import load_vehicle
from services import runtime, timing
from services.messages import Command, Event, Imu, Mocap, Setpoint
from services.px4_bridge_options import add_arguments
from services.px4_offboard import OFFBOARD, OffboardControl

MAX_GYRO = 99.0  # the Imu message accepts |w| <= 100 rad/s


def odometry_from_mocap(m: Mocap) -> tuple[np.ndarray, np.ndarray]:
    """Mocap frame (ENU/FLU) -> (position NED, quaternion FRD-to-NED) for PX4."""
    return frames.enu_to_ned(m.position), frames.quat_enu_flu_to_ned_frd(m.quaternion)


class Px4Bridge(OffboardControl, runtime.Service):
    """PX4 bridge: setpoints to PX4 offboard, mocap to PX4 vision, PX4 telemetry to the bus."""

    name = "bridge"
    uses_jax = False  # NumPy's frame changes and limits only

    _closed = False

    # -- set-up
    def setup(self, bus) -> None:
        self._init_state()
        self._connect()
        bus.subscribe("setpoint", self.on_setpoint, source="controller")
        bus.subscribe("event", self.on_event, check_order=False)
        if self.args.vision != "off":
            bus.subscribe("mocap", self.on_mocap, source=self.args.mocap_source)
        bus.on_alive_change(self._on_alive_change)
        self.pub_imu = bus.publisher("imu")
        self._wait_healthy()

    def _init_state(self) -> None:
        """Limits, offboard state and counters (everything but the MAVLink link)."""
        a = self.args
        self.limits = Limits.from_vehicle(load_vehicle(a.vehicle_file), a.max_throttle)
        self.geofence = Geofence.parse(a.geofence)
        self.period = 1.0 / a.rate
        self._lock = threading.RLock()  # offboard state and every offboard call
        self._cond = threading.Condition(self._lock)
        self._engaged = False  # offboard control by this bridge (or being engaged)
        self._mission_t0: float | None = None  # the latest start this bridge put
        self._mocap_error_said = -math.inf  # when a forwarding failure was last an event
        self._last_rx = -math.inf  # arrival time of the newest valid setpoint
        self._stream_since = math.inf  # arrival of the first setpoint without a gap since
        self._latest: tuple[np.ndarray, float] | None = None
        self._controller_failsafe = False  # the controller's failsafe, until it tracks again
        self._send_error_run = 0  # consecutive set_attitude_rate failures
        #: The newest thread awaiting PX4's answer to leaving offboard (then Land if due).
        self.leave_worker: threading.Thread | None = None
        self._telemetry: dict[str, Any] = {}
        self._tel_cond = threading.Condition()
        self._commands: list[Command] = []
        self._cmd_cond = threading.Condition()
        self.stats.update(
            setpoints=0,
            sent=0,
            clamped=0,
            send_errors=0,
            mocap_forwarded=0,
            mocap_forward_errors=0,
            imu=0,
            failsafes=0,
            offboard_exits=0,
            watchdog_errors=0,
            hold_denied_landings=0,
            engagements=0,
            mode_changes=0,
            connect=a.connect,
            forward=list(a.forward),
        )
        self._fwd = timing.LatencySamples()

    def _connect(self) -> None:
        # MAVSDK (gRPC, protobuf) loads here, not at import: start-up cost.
        from mavsdk import ComponentType, Configuration, ConnectionResult, ForwardingOption, Mavsdk
        from mavsdk.plugins import mocap as mc
        from mavsdk.plugins.action import Action
        from mavsdk.plugins.offboard import Offboard
        from mavsdk.plugins.telemetry import Telemetry

        a = self.args
        # A ground station (system id 245): PX4's data-link-loss checks watch its heartbeat.
        self.mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        # With --forward, MAVSDK passes what arrives on one forwarding connection to the
        # others: PX4's messages reach the ground station and the station's reach PX4.
        forwarding = ForwardingOption.ON if a.forward else ForwardingOption.OFF
        for url in [a.connect, *a.forward]:
            result = self.mavsdk.add_any_connection_with_forwarding(url, forwarding)
            if result != ConnectionResult.SUCCESS:
                raise RuntimeError(
                    f"cannot open the MAVLink connection {url!r}: {ConnectionResult(result).name}"
                )
        if a.forward:
            self.log.info("forwarding MAVLink between %s and %s", a.connect, ", ".join(a.forward))
        self.log.info(
            "waiting up to %.0f s for a PX4 autopilot on %s", a.connect_timeout, a.connect
        )
        system = self.mavsdk.first_autopilot(a.connect_timeout)
        if system is None:
            raise RuntimeError(
                f"no autopilot heard on {a.connect} within {a.connect_timeout:g} s: is PX4 "
                "powered and running, is the URL right (udpin:// port, serial device and "
                "baud rate), does PX4 send MAVLink on that link (MAV_x_CONFIG, SER_x_BAUD)?"
            )
        self.system = system
        self._offboard_cls = Offboard
        self.telemetry = Telemetry(system)
        self.action = Action(system)
        self.offboard = Offboard(system)
        self._mc = mc
        self.mocap = mc.Mocap(system)
        t = self.telemetry
        t.subscribe_attitude_quaternion(self._on_attitude)
        t.subscribe_attitude_angular_velocity_body(self._on_rates)
        t.subscribe_position_velocity_ned(self._on_position)
        t.subscribe_armed(self._on_armed)
        t.subscribe_flight_mode(self._on_flight_mode)
        t.subscribe_health(self._on_health)
        t.subscribe_landed_state(self._on_landed)
        system.subscribe_is_connected(self._on_connected)
        # Ask for the streams the bus needs (asynchronously: an autopilot that does not
        # answer SET_MESSAGE_INTERVAL must not delay the start; PX4 streams them anyway).
        fast = max(50.0, 2.0 * a.rate)
        for name, hz in (("attitude_quaternion", fast), ("position_velocity_ned", 30.0)):
            getattr(t, f"set_rate_{name}_async")(
                hz, lambda r, _ud, name=name: self.log.info("rate of %s: %s", name, r.name)
            )

    # -- telemetry (MAVSDK's callback thread: store and notify, nothing slow)
    def _set_tel(self, **kv: Any) -> None:
        with self._tel_cond:
            self._telemetry.update(kv)
            self._tel_cond.notify_all()

    def _on_connected(self, connected: bool, _ud: Any = None) -> None:
        self._set_tel(connected=bool(connected))
        if not connected:
            self.event("fault", "MAVLink link to PX4 lost", "error")

    def _on_attitude(self, q: Any, _ud: Any) -> None:
        q = np.array([q.w, q.x, q.y, q.z], dtype=float)
        if np.all(np.isfinite(q)) and np.linalg.norm(q) > 0.5:
            self._set_tel(q_enu_flu=frames.quat_ned_frd_to_enu_flu(q / np.linalg.norm(q)))

    def _on_rates(self, w: Any, _ud: Any) -> None:
        w = np.array([w.roll_rad_s, w.pitch_rad_s, w.yaw_rad_s], dtype=float)
        if np.all(np.isfinite(w)):
            self._set_tel(
                gyro_flu=np.clip(frames.frd_to_flu(w), -MAX_GYRO, MAX_GYRO),
                gyro_rx=time.monotonic(),
            )

    def _on_position(self, pv: Any, _ud: Any) -> None:
        p = np.array([pv.position.north_m, pv.position.east_m, pv.position.down_m])
        v = np.array([pv.velocity.north_m_s, pv.velocity.east_m_s, pv.velocity.down_m_s])
        if np.all(np.isfinite(p)):
            self._set_tel(p_enu=frames.ned_to_enu(p), v_enu=frames.ned_to_enu(v))
            self._check_geofence(frames.ned_to_enu(p), "PX4 local position")

    def _on_armed(self, armed: bool, _ud: Any) -> None:
        prev = self._telemetry.get("armed")
        self._set_tel(armed=bool(armed))
        if prev is not None and bool(armed) != prev:
            self.event("vehicle", "armed" if armed else "disarmed", armed=bool(armed))

    def _on_landed(self, state: Any, _ud: Any) -> None:
        self._set_tel(landed=state.name)

    def _on_health(self, h: Any, _ud: Any) -> None:
        health = {
            k: bool(getattr(h, k))
            for k in (
                "is_gyrometer_calibration_ok",
                "is_accelerometer_calibration_ok",
                "is_local_position_ok",
                "is_armable",
            )
        }
        prev = self._telemetry.get("health")
        self._set_tel(health=health)
        if prev is not None and prev != health:
            bad = [k for k, ok in health.items() if not ok]
            self.event(
                "vehicle",
                f"PX4 health: {'ok' if not bad else 'not ok: ' + ', '.join(bad)}",
                "info" if not bad else "warning",
                **health,
            )

    def _on_flight_mode(self, mode: Any, _ud: Any) -> None:
        name = mode.name
        prev = self._telemetry.get("mode")
        self._set_tel(mode=name)
        if name == prev:
            return
        self.stats["mode_changes"] += 1
        self.event("mode_change", f"PX4 flight mode {prev} -> {name}", mode=name, previous=prev)
        if prev == OFFBOARD and name != OFFBOARD:
            # PX4 left offboard by itself (pilot, its own failsafe) or on our request.
            with self._lock:
                engaged, self._engaged = self._engaged, False
            if engaged:
                # Not on this (MAVSDK's) thread: the plugin's destructor may wait for it.
                threading.Thread(target=self._silence_offboard, name="silence", daemon=True).start()
                self.stats["offboard_exits"] += 1
                self.stats["failsafes"] += 1
                self.event(
                    "failsafe",
                    f"PX4 left offboard ({name}): setpoint stream stopped",
                    "warning",
                    reason="px4_mode",
                    mode=name,
                )

    # -- readiness
    def _health_problems(self) -> list[str]:
        t = self._telemetry
        health = t.get("health", {})
        problems = []
        if not t.get("connected", True):
            problems.append("not connected")
        if not health.get("is_armable", False):
            problems.append("not armable (PX4 pre-arm checks)")
        if self.args.require_local_position and not health.get("is_local_position_ok", False):
            problems.append("no local position (is vision reaching EKF2?)")
        if "gyro_flu" not in t:
            problems.append("no attitude-rate telemetry")
        if "mode" not in t:
            problems.append("no flight mode (heartbeat)")
        return problems

    def _wait_healthy(self) -> None:
        timeout = self.args.health_timeout
        with self._tel_cond:
            ok = self._tel_cond.wait_for(lambda: not self._health_problems(), timeout)
            problems = self._health_problems()
        if not ok:
            raise RuntimeError(
                f"PX4 on {self.args.connect} not healthy after {timeout:g} s: "
                + "; ".join(problems)
            )
        self.log.info(
            "PX4 connected and healthy: mode %s, armed %s",
            self._telemetry.get("mode"),
            self._telemetry.get("armed"),
        )

    def ready(self) -> None:
        t = self._telemetry
        self.event(
            "ready",
            f"PX4 bridge connected on {self.args.connect}; send 'arm' to fly",
            mode=t.get("mode"),
            armed=t.get("armed"),
        )
        self._cmd_thread = threading.Thread(
            target=self._command_worker, name="commands", daemon=True
        )
        self._cmd_thread.start()
        self._watchdog = threading.Thread(target=self._watchdog_loop, name="watchdog", daemon=True)
        self._watchdog.start()

    # -- bus inputs
    def on_setpoint(self, sp: Setpoint) -> None:
        rx = time.monotonic()
        deg_s, throttle, clamped = attitude_rate_command(sp.u, self.limits)
        with self._lock:
            self.stats["setpoints"] += 1
            self.stats["clamped"] += int(clamped)
            self._latest = (deg_s, throttle)
            if sp.mode != "hover":
                self._controller_failsafe = False
            if rx - self._last_rx > self.args.setpoint_timeout:
                self._stream_since = rx  # a new stream starts after a gap
            self._last_rx = rx
            if self._engaged:
                self._send(deg_s, throttle)
                self._fwd.append(time.monotonic() - rx)
            self._cond.notify_all()

    def on_mocap(self, m: Mocap) -> None:
        if self._closed or not m.of_vehicle(self.args.mocap_body):
            return
        mc = self._mc
        self._check_geofence(m.position, "mocap")
        p, q = odometry_from_mocap(m)
        nan = float("nan")
        frame = (
            mc.Odometry.MavFrame.LOCAL_FRD
            if self.args.vision_frame == "local_frd"
            else mc.Odometry.MavFrame.MOCAP_NED
        )
        est = (
            mc.Odometry.MavEstimatorType.VISION
            if self.args.vision == "odometry"
            else mc.Odometry.MavEstimatorType.MOCAP
        )
        # Pose only: velocity and rates unknown (NaN), covariances from PX4's EKF2_EVP/EVA
        # noise parameters (first element NaN). Time on the monotonic clock, which
        # MAVSDK's TIMESYNC shares with PX4.
        odom = mc.Odometry(
            time_usec=int(m.capture_stamp * 1e6),
            frame_id=frame,
            position_body=mc.PositionBody(*map(float, p)),
            q=mc.Quaternion(*map(float, q)),
            speed_body=mc.SpeedBody(nan, nan, nan),
            angular_velocity_body=mc.AngularVelocityBody(nan, nan, nan),
            pose_covariance=mc.Covariance([nan]),
            velocity_covariance=mc.Covariance([nan]),
            estimator_type=est,
        )
        try:
            self.mocap.set_odometry(odom)
            self.stats["mocap_forwarded"] += 1
        except Exception as err:
            # PX4 without vision loses its position estimate: said at once, then at most
            # every 5 s while it lasts (frames come at 100-240 Hz).
            n = self.stats["mocap_forward_errors"] = self.stats["mocap_forward_errors"] + 1
            now = time.monotonic()
            if now - self._mocap_error_said >= 5.0:
                self._mocap_error_said = now
                self.event("fault", f"mocap not forwarded to PX4: {err}", "error", errors=n)

    def on_command(self, cmd: Command) -> None:
        if cmd.target not in ("", self.name):
            return
        if cmd.name in ("arm", "disarm", "hold", "stop", "land"):
            with self._cmd_cond:
                self._commands.append(cmd)
                self._cmd_cond.notify_all()

    def on_event(self, e: Event) -> None:
        # The controller's failsafe: it hovered without position feedback for too long.
        if e.kind == "failsafe" and e.src.startswith("controller/") and not self._closed:
            self._controller_failsafe = True
            self.leave_offboard(
                f"controller failsafe: {e.text}",
                self.args.failsafe,
                reason="controller_failsafe",
                controller_reason=str(e.data.get("reason", "")),
            )

    def _on_alive_change(self, service: str, up: bool) -> None:
        if service == "adapter" and up and self._mission_t0 is not None:
            # A restarted adapter: the mission's clock, and whether offboard flies the
            # setpoints now (it learns from them only then).
            with self._lock:
                flying = self._engaged
            args = {"t0": self._mission_t0, "flying": flying}
            self.bus.put(Command(name="start", args=args, stamp=time.monotonic()))
        if service == "controller" and not up:
            self.leave_offboard(
                "the controller's liveliness token disappeared",
                self.args.failsafe,
                reason="controller_lost",
            )

    # -- main loop: imu (control instants) and status at their rates
    def main(self) -> None:
        next_tick = time.monotonic()
        next_status = next_tick
        status_period = 1.0 / self.args.status_rate if self.args.status_rate > 0 else math.inf
        while not self.stop.is_set():
            now = time.monotonic()
            tick = min(next_tick, now)  # the scheduled instant: periodic stamps, no jitter
            t = self._telemetry
            gyro = t.get("gyro_flu")
            if (
                self.args.imu == "px4"
                and gyro is not None
                and now - t.get("gyro_rx", -math.inf) < self.args.max_gyro_age
            ):
                self.pub_imu.put(Imu(gyro=gyro, stamp=tick))
                self.stats["imu"] += 1
            if now >= next_status:
                self._status(now)
                next_status = now + status_period
            next_tick += self.period
            if next_tick < now:  # fell behind (a stall): restart the schedule
                next_tick = now + self.period
            self.stop.wait(max(0.0, next_tick - time.monotonic()))

    def _status(self, now: float) -> None:
        t = dict(self._telemetry)
        data: dict[str, Any] = {
            "armed": t.get("armed"),
            "mode": t.get("mode"),
            "landed": t.get("landed"),
            "engaged": self._engaged,
            "setpoints_fresh": now - self._last_rx <= self.args.setpoint_timeout,
            "stream_s": max(0.0, now - self._stream_since),
        }
        for key, names in (
            ("p_enu", ("px", "py", "pz")),
            ("v_enu", ("vx", "vy", "vz")),
            ("q_enu_flu", ("qw", "qx", "qy", "qz")),
            ("gyro_flu", ("wx", "wy", "wz")),
        ):
            if key in t:
                data.update({n: float(v) for n, v in zip(names, t[key]) if math.isfinite(v)})
        self.event("vehicle_status", "PX4 state (ENU/FLU)", "debug", stamp=now, **data)

    def teardown(self) -> None:
        # Hold, never disarm: the vehicle may be in the air.
        self.leave_offboard(
            "bridge shutting down", "hold", reason="shutdown", failsafe=False, wait=True
        )
        self.stats["forward_latency"] = self._fwd.summary()
        self.stats["final_mode"] = self._telemetry.get("mode")
        self._closed = True  # late bus callbacks must not touch the destroyed plugins
        self.mavsdk.destroy()


#: The bridge's own command-line options (on the services' common parser).
_extra = add_arguments


def main(argv: list[str] | None = None) -> int:
    return runtime.main_for(Px4Bridge, argv, _extra)


__all__ = [
    "Geofence",
    "Limits",
    "Px4Bridge",
    "attitude_rate_command",
    "main",
    "odometry_from_mocap",
]
