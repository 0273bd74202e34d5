"""PX4 bridge service: the controller's setpoints to a PX4 vehicle in offboard mode (MAVSDK).

Replaces the simulator as the vehicle link (design §3). Connects with MAVSDK (``--connect``,
any MAVSDK URL: ``udpin://0.0.0.0:14540`` for SITL or a telemetry radio bridge,
``serial:///dev/ttyACM0:921600`` for USB), waits for a connected, healthy autopilot, then:

- ``setpoint`` -> ``set_attitude_rate``: body rates FLU rad/s -> FRD deg/s clamped to the
  vehicle file's ``max_rate_rad_s``; collective thrust N -> normalised throttle through the
  vehicle's ``THR_MDL_FAC`` thrust curve, clamped to ``[0, --max-throttle]``
  (:mod:`services.px4_frames`). Only while offboard control is engaged by this bridge.
- ``mocap`` -> PX4 ``ODOMETRY`` (MAVSDK mocap plugin): position NED, attitude FRD-to-NED, in
  a ``LOCAL_FRD`` world frame (the mocap frame need not face north), estimator type vision,
  so that PX4's EKF2 has the external-vision position it needs to hold or land by itself.
- PX4 telemetry -> bus: ``imu`` at the control rate (PX4's body rates, FLU; each sample is
  a control instant for the estimator, as the simulator's are), ``event`` on every arming,
  flight-mode, offboard and health change, and a ``vehicle_status`` event (severity
  ``debug``, ``--status-rate``) with PX4's own attitude, local position and velocity (ENU/FLU).

Engaging. Never automatic: an ``arm`` command (``arcade up --profile px4 --arm``) checks
that controller setpoints stream steadily (``--min-stream``), the vehicle is armable and
inside the geofence, and no controller failsafe since it last tracked; then it sends the
newest setpoint, arms and starts offboard, emits ``failsafe_cleared`` (the vehicle flies
the stack's setpoints again: the adapter learns from here on) and puts a ``start`` command
(mission clock of the controller; not with ``--no-start-mission``), which an adapter
that (re)joins later gets again, with ``flying`` (offboard engaged at that moment). With
``args.takeoff_m`` and the vehicle on the ground, PX4 first takes off by itself to that
height (Takeoff mode, then Hold) and offboard starts from the hover. ``hold`` / ``stop``
leave offboard to Hold, ``land`` to Land, ``disarm`` is refused unless PX4 reports the
vehicle on the ground.

Every exit from offboard is announced by a ``failsafe`` event with its ``reason`` (the
vehicle no longer flies the stack's setpoints: the adapter stops learning); an operator's
``hold``/``land``/``stop`` (``reason: command``) and the shutdown (``shutdown``) have
severity ``info`` and are not counted as failsafes. The failsafes (``stats.failsafes``):

- setpoints stop for more than ``--setpoint-timeout`` (0.3 s) or the controller's
  liveliness token disappears: leave offboard (``--failsafe hold|land``);
- the controller reports a ``failsafe`` (it hovered without position feedback for longer
  than its ``--max-hover-s``): leave offboard (``--failsafe``);
- ``--max-send-errors`` consecutive ``set_attitude_rate`` failures (MAVSDK would keep
  re-sending the last accepted setpoint): leave offboard (``--failsafe``);
- the vehicle (mocap or PX4 position) leaves the ``--geofence`` box: leave offboard
  (``--geofence-action hold|land``);
- PX4 leaves offboard by itself (RC override, its own failsafe): stop streaming.

When PX4 denies or does not answer the Hold of a failsafe (it has no position estimate
without mocap), the bridge commands Land (``hold_denied_landings``): otherwise the vehicle
would fly its last setpoint until PX4's own ``COM_OF_LOSS_T``. An operator's denied
``hold`` is only reported.

The setpoint watchdog thread survives its own errors (``fault`` event, ``watchdog_errors``).

MAVSDK's offboard plugin re-sends the last setpoint every 50 ms on its own thread (it
keeps PX4's 2 Hz offboard requirement met) for as long as offboard is "active" in MAVSDK,
whatever Python does. A stale setpoint must not keep the vehicle in offboard, so the
bridge ends that stream itself: ``Offboard.stop`` (removes the re-send timer, then commands
Hold) when it leaves offboard, and dropping the plugin instance (whose destructor removes
the timer without a mode command) when PX4 already left offboard. If the bridge process
dies, the re-send thread dies with it and PX4's ``COM_OF_LOSS_T`` failsafe takes over.

Shutdown (SIGINT/SIGTERM, ``shutdown`` command): leave offboard to Hold; never disarm.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from services import px4_frames as fr
from services import runtime
from services.messages import Command, Event, Imu, Mocap, Setpoint

DEFAULT_URL = "udpin://0.0.0.0:14540"
MAX_GYRO = 99.0  # the Imu message accepts |w| <= 100 rad/s
#: MAVSDK flight mode names (telemetry.FlightMode) as they appear in events.
OFFBOARD, HOLD, LAND = "OFFBOARD", "HOLD", "LAND"


# ------------------------------------------------------------------- pure helpers


@dataclass(frozen=True)
class Limits:
    """What the bridge lets through to PX4."""

    curve: fr.ThrustCurve
    max_rate: np.ndarray  # (3,) rad/s, FLU axes
    max_throttle: float = 1.0

    @classmethod
    def from_vehicle(cls, vehicle: dict[str, Any], max_throttle: float = 1.0) -> Limits:
        rate = np.asarray(vehicle["rate_loop"]["max_rate_rad_s"], dtype=float).reshape(3)
        if not 0.0 < max_throttle <= 1.0:
            raise ValueError(f"max throttle {max_throttle} not in (0, 1]")
        return cls(fr.ThrustCurve.from_vehicle(vehicle), rate, float(max_throttle))


def attitude_rate_command(u: Any, limits: Limits) -> tuple[np.ndarray, float, bool]:
    """``u = [thrust N, rates FLU rad/s]`` -> (rates FRD deg/s, throttle, clamped?).

    Rates are clamped per axis to the vehicle's ``max_rate`` and thrust to the throttle
    range ``[0, max_throttle]`` (non-finite input is an error: it never reaches PX4).
    """
    u = np.asarray(u, dtype=float)
    if u.shape != (4,) or not np.all(np.isfinite(u)):
        raise ValueError(f"bad setpoint {u!r}")
    rates = np.clip(u[1:], -limits.max_rate, limits.max_rate)
    s = float(limits.curve.throttle(u[0]))
    throttle = min(max(s, 0.0), limits.max_throttle)
    clamped = bool(np.any(rates != u[1:]) or throttle != s or u[0] > limits.curve.max_thrust_n)
    return fr.rad_to_deg(fr.flu_to_frd(rates)), throttle, clamped


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


def odometry_from_mocap(m: Mocap) -> tuple[np.ndarray, np.ndarray]:
    """Mocap frame (ENU/FLU) -> (position NED, quaternion FRD-to-NED) for PX4."""
    return fr.enu_to_ned(m.position), fr.quat_enu_flu_to_ned_frd(m.quaternion)


# ------------------------------------------------------------------------ service


class Px4Bridge(runtime.Service):
    """PX4 bridge: setpoints to PX4 offboard, mocap to PX4 vision, PX4 telemetry to the bus."""

    name = "bridge"

    _closed = False

    # -- set-up
    def setup(self, bus) -> None:
        self._init_state()
        self._connect()
        bus.subscribe("setpoint", self.on_setpoint)
        bus.subscribe("event", self.on_event, check_order=False)
        if self.args.vision != "off":
            bus.subscribe("mocap", self.on_mocap)
        bus.on_alive_change(self._on_alive_change)
        self.pub_imu = bus.publisher("imu")
        self._wait_healthy()

    def _init_state(self) -> None:
        """Limits, offboard state and counters (everything but the MAVLink link)."""
        from arcade_io.vehicle import load_vehicle

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
        )
        self._fwd = runtime.LatencySamples()

    def _connect(self) -> None:
        from mavsdk import ComponentType, Configuration, ConnectionResult, Mavsdk
        from mavsdk.plugins import mocap as mc
        from mavsdk.plugins.action import Action
        from mavsdk.plugins.offboard import Offboard
        from mavsdk.plugins.telemetry import Telemetry

        a = self.args
        # A ground station (system id 245): PX4's data-link-loss checks watch its heartbeat.
        self.mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        result = self.mavsdk.add_any_connection(a.connect)
        if result != ConnectionResult.SUCCESS:
            raise RuntimeError(
                f"cannot open the MAVLink connection {a.connect!r}: {ConnectionResult(result).name}"
            )
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
            self._set_tel(q_enu_flu=fr.quat_ned_frd_to_enu_flu(q / np.linalg.norm(q)))

    def _on_rates(self, w: Any, _ud: Any) -> None:
        w = np.array([w.roll_rad_s, w.pitch_rad_s, w.yaw_rad_s], dtype=float)
        if np.all(np.isfinite(w)):
            self._set_tel(
                gyro_flu=np.clip(fr.frd_to_flu(w), -MAX_GYRO, MAX_GYRO), gyro_rx=time.monotonic()
            )

    def _on_position(self, pv: Any, _ud: Any) -> None:
        p = np.array([pv.position.north_m, pv.position.east_m, pv.position.down_m])
        v = np.array([pv.velocity.north_m_s, pv.velocity.east_m_s, pv.velocity.down_m_s])
        if np.all(np.isfinite(p)):
            self._set_tel(p_enu=fr.ned_to_enu(p), v_enu=fr.ned_to_enu(v))
            self._check_geofence(fr.ned_to_enu(p), "PX4 local position")

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

    def _send(self, deg_s: np.ndarray, throttle: float) -> None:
        """One ``set_attitude_rate`` (caller holds the lock). After ``--max-send-errors``
        failures in a row offboard is left: MAVSDK keeps re-sending the last setpoint it
        accepted, so PX4 would fly a stale one."""
        from mavsdk.plugins.offboard import AttitudeRate

        try:
            self.offboard.set_attitude_rate(
                AttitudeRate(float(deg_s[0]), float(deg_s[1]), float(deg_s[2]), float(throttle))
            )
            self.stats["sent"] += 1
            self._send_error_run = 0
        except Exception as err:
            self.stats["send_errors"] += 1
            self._send_error_run += 1
            self.log.warning("set_attitude_rate failed: %s", err)
            if self._send_error_run >= self.args.max_send_errors:
                self.leave_offboard(
                    f"{self._send_error_run} setpoints in a row not sent ({err})",
                    self.args.failsafe,
                    reason="send_errors",
                )

    def on_mocap(self, m: Mocap) -> None:
        if self._closed:
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

    # -- offboard control
    def _silence_offboard(self) -> None:
        """End MAVSDK's re-send of the last setpoint without a mode command: the plugin's
        destructor removes its timer; a fresh instance takes its place."""
        with self._lock:
            if self._engaged:  # engaged again meanwhile: the stream is wanted
                return
            self._drop_offboard()

    def _drop_offboard(self) -> None:
        """Replace the offboard plugin instance (caller holds the lock): its destructor
        removes MAVSDK's re-send timer."""
        old, self.offboard = self.offboard, self._offboard_cls(self.system)
        old.destroy()

    def leave_offboard(
        self,
        why: str,
        action: str,
        *,
        reason: str,
        failsafe: bool = True,
        wait: bool = False,
        **data: Any,
    ) -> bool:
        """Stop streaming and command Hold (then Land if ``action == "land"``).

        The stream ends before this returns; the mode commands' answers are awaited on a
        worker thread (``wait``: here), so that this is safe on MAVSDK's callback thread.
        Announced by a ``failsafe`` event (severity ``info`` when not ``failsafe``: an
        operator's command or the shutdown), whatever the reason: the vehicle no longer
        flies the stack's setpoints. Returns False when offboard was not engaged by this
        bridge (nothing done).
        """
        done = threading.Event()
        result: list[str] = []

        def on_result(r: Any, _ud: Any = None) -> None:
            result.append(r.name)
            done.set()

        with self._lock:
            if not self._engaged:
                return False
            self._engaged = False
            # stop_async removes MAVSDK's re-send timer before it returns, then commands
            # Hold; under the lock, so no setpoint can restart the stream after it.
            try:
                self.offboard.stop_async(on_result)
            except Exception as err:
                # The re-send timer may still run: drop the plugin (PX4's offboard-loss
                # failsafe then acts), and report the Hold as failed.
                result.append(f"not sent ({err})")
                done.set()
                try:
                    self._drop_offboard()
                except Exception as err2:
                    self.log.exception("could not drop the offboard plugin")
                    result[0] += f"; offboard stream not stopped ({err2})"
            self._cond.notify_all()
        self.stats["offboard_exits"] += 1
        if failsafe:
            self.stats["failsafes"] += 1
        self.event(
            "failsafe",
            f"leaving offboard: {why} -> {action}",
            "warning" if failsafe else "info",
            reason=reason,
            action=action,
            **data,
        )

        def finish() -> None:
            held = False
            if not done.wait(self.args.command_timeout):
                self.event("fault", "PX4 did not answer the Hold command", "error")
            elif result[0] != "SUCCESS":
                self.event("fault", f"Hold command: {result[0]}", "error")
            else:
                held = True
            land = action == "land"
            if failsafe and not held and not land:
                # PX4 refuses Hold without a position estimate (e.g. mocap lost): a failsafe
                # must not leave it on the last setpoint until its own offboard-loss timeout.
                self.stats["hold_denied_landings"] += 1
                self.event("fault", "no Hold after a failsafe: commanding Land", "error")
                land = True
            if land:
                try:
                    self.action.land()
                except Exception as err:
                    self.event("fault", f"land command failed: {err}", "error")

        if wait:
            finish()
        else:
            self.leave_worker = threading.Thread(target=finish, name="leave-offboard", daemon=True)
            self.leave_worker.start()
        return True

    def _check_geofence(self, p_enu: np.ndarray, source: str) -> None:
        if self._engaged and not self.geofence.contains(p_enu):
            x, y, z = (float(v) for v in p_enu)
            self.leave_offboard(
                f"{source} ({x:.2f}, {y:.2f}, {z:.2f}) m outside the geofence",
                self.args.geofence_action,
                reason="geofence",
            )

    def _watchdog_loop(self) -> None:
        """Leave offboard once setpoints are older than ``--setpoint-timeout``; an error
        is reported (``fault`` event) and the watch goes on."""
        while not self.stop.is_set():
            try:
                self._watchdog_check()
            except Exception as err:
                n = self.stats["watchdog_errors"] = self.stats["watchdog_errors"] + 1
                if n == 1:
                    self.log.exception("setpoint watchdog failed")
                if n % 50 == 1:  # the first, then every 5 s while it persists
                    self.event("fault", f"setpoint watchdog failed: {err!r}", "error", errors=n)
                self.stop.wait(0.1)  # back off: a persistent error must not spin

    def _watchdog_check(self) -> None:
        """One round of the setpoint watchdog (waits at most until the next deadline)."""
        with self._lock:
            if not self._engaged:
                self._cond.wait(0.1)
                return
            left = self._last_rx + self.args.setpoint_timeout - time.monotonic()
            if left > 0:
                self._cond.wait(left)
                return
            age = time.monotonic() - self._last_rx
        self.leave_offboard(
            f"no controller setpoint for {age:.3f} s",
            self.args.failsafe,
            reason="setpoint_timeout",
            age_s=age,
        )

    def _command_worker(self) -> None:
        while not self.stop.is_set():
            with self._cmd_cond:
                self._cmd_cond.wait_for(lambda: self._commands or self.stop.is_set(), 0.5)
                todo, self._commands = self._commands, []
            for cmd in todo:
                try:
                    self._do_command(cmd)
                except Exception as err:
                    self.log.exception("command %s failed", cmd.name)
                    self.event("fault", f"command {cmd.name} failed: {err}", "error")

    def _do_command(self, cmd: Command) -> None:
        if cmd.name == "arm":
            takeoff = cmd.args.get("takeoff_m")
            self.engage(float(takeoff) if isinstance(takeoff, int | float) else None)
        elif cmd.name in ("hold", "stop", "land"):
            action = "land" if cmd.name == "land" else "hold"
            if (
                not self.leave_offboard(
                    f"{cmd.name} command", action, reason="command", failsafe=False
                )
                and cmd.name == "land"
            ):
                self.action.land()  # not in offboard: land from whatever mode PX4 is in
        elif cmd.name == "disarm":
            landed = self._telemetry.get("landed")
            if landed != "ON_GROUND":
                self.event(
                    "info", f"disarm refused: vehicle not on the ground ({landed})", "warning"
                )
                return
            self.action.disarm()
            self.event("info", "disarmed on command")

    def engage(self, takeoff_m: float | None = None) -> None:
        """Arm and start offboard control (refused with an event when unsafe).

        With ``takeoff_m`` and the vehicle on the ground, PX4 takes off by itself first
        (its Takeoff mode, to ``takeoff_m`` above the ground, vision-aided) and offboard
        control starts once it holds there.
        """
        problems = self._engage_problems()
        if problems:
            self.event("info", "arm refused: " + "; ".join(problems), "warning")
            return
        if takeoff_m is not None and self._telemetry.get("landed") == "ON_GROUND":
            if not self._px4_takeoff(float(takeoff_m)):
                return
            problems = self._engage_problems()
            if problems:
                self.event(
                    "info", "offboard refused after take-off: " + "; ".join(problems), "warning"
                )
                return
        with self._lock:
            self._engaged = True  # setpoints stream to PX4 from now on; the watchdog runs
            self._send_error_run = 0
            self._send(*self._latest)
            self._cond.notify_all()
        try:
            if not self._telemetry.get("armed"):
                self.action.arm()
            self._start_offboard()
        except Exception as err:
            with self._lock:
                was = self._engaged
                self._engaged = False
                if was:
                    self.offboard.stop_async(lambda *_: None)
            self.event("fault", f"could not engage offboard control: {err}", "error")
            if self._telemetry.get("landed") == "ON_GROUND" and self._telemetry.get("armed"):
                self.action.disarm()
            return
        self.stats["engagements"] += 1
        stamp = time.monotonic()
        self.event("offboard", "offboard control engaged: mission clock starts", t0=stamp)
        # Whether or not this bridge starts the mission: the setpoints are flown again.
        self.event("failsafe_cleared", "offboard control engaged: setpoints flown", stamp=stamp)
        if self.args.start_mission:
            self._mission_t0 = stamp
            self.bus.put(Command(name="start", args={"t0": stamp}, stamp=stamp))

    def _engage_problems(self) -> list[str]:
        with self._lock:
            if self._engaged:
                return ["offboard control already engaged"]
            age = time.monotonic() - self._last_rx
        problems = [p for p in self._health_problems() if "telemetry" not in p]
        steady = time.monotonic() - self._stream_since
        if self._latest is None or age > self.args.setpoint_timeout:
            problems.append("controller setpoints are not streaming")
        elif steady < self.args.min_stream:
            problems.append(
                f"controller setpoints are not streaming steadily yet "
                f"({steady:.2f} of {self.args.min_stream:g} s without a gap)"
            )
        if self._controller_failsafe:
            problems.append("the controller reported a failsafe and has not tracked since")
        p = self._telemetry.get("p_enu")
        if p is not None and not self.geofence.contains(p):
            problems.append("vehicle outside the geofence")
        return problems

    def _px4_takeoff(self, altitude_m: float) -> bool:
        """Arm and let PX4 take off to ``altitude_m``; True once it holds in the air."""
        try:
            self.action.set_takeoff_altitude(altitude_m)
        except Exception as err:  # not fatal: PX4 then climbs to its MIS_TAKEOFF_ALT
            self.log.warning("could not set the take-off altitude: %s", err)
        try:
            self.action.arm()
            self.action.takeoff()
        except Exception as err:
            self.event("fault", f"PX4 take-off failed: {err}", "error")
            return False
        self.event("info", f"PX4 taking off to {altitude_m:g} m")
        with self._tel_cond:
            ok = self._tel_cond.wait_for(
                lambda: (
                    self.stop.is_set()
                    or (
                        self._telemetry.get("mode") == HOLD
                        and self._telemetry.get("landed") == "IN_AIR"
                    )
                ),
                self.args.takeoff_timeout,
            )
        if not ok or self.stop.is_set():
            self.event(
                "fault",
                "PX4 take-off did not complete: offboard not engaged",
                "error",
                mode=self._telemetry.get("mode"),
                landed=self._telemetry.get("landed"),
            )
            return False
        return True

    def _start_offboard(self) -> None:
        from mavsdk.plugins.offboard import OffboardError, OffboardResult

        deadline = time.monotonic() + self.args.command_timeout
        while True:
            with self._lock:
                if not self._engaged:
                    raise RuntimeError("setpoints stopped while engaging")
                offboard = self.offboard
            try:
                offboard.start()
                return
            except OffboardError as err:
                # PX4 refuses offboard until it has seen the setpoint stream for a moment.
                if err.result != OffboardResult.COMMAND_DENIED or time.monotonic() > deadline:
                    raise
            self.stop.wait(0.1)

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


def _extra(p) -> None:
    p.add_argument(
        "--connect",
        default=DEFAULT_URL,
        help="MAVSDK connection URL, e.g. udpin://0.0.0.0:14540 or serial:///dev/ttyACM0:921600",
    )
    p.add_argument(
        "--vehicle-file",
        default=None,
        help="vehicle file (thrust curve, rate limits); default: the shipped one",
    )
    p.add_argument(
        "--connect-timeout",
        type=float,
        default=30.0,
        help="longest wait for an autopilot heartbeat [s]",
    )
    p.add_argument(
        "--health-timeout",
        type=float,
        default=60.0,
        help="longest wait for PX4 to be healthy and armable [s]",
    )
    p.add_argument(
        "--command-timeout",
        type=float,
        default=3.0,
        help="longest wait for PX4 to accept offboard / answer a mode command [s]",
    )
    p.add_argument(
        "--setpoint-timeout",
        type=float,
        default=0.3,
        help="leave offboard when no setpoint arrived for this long [s]",
    )
    p.add_argument(
        "--min-stream",
        type=float,
        default=1.0,
        help="arm only after setpoints streamed this long without a gap [s]",
    )
    p.add_argument(
        "--failsafe",
        choices=("hold", "land"),
        default="hold",
        help="what PX4 does when setpoints stop",
    )
    p.add_argument(
        "--max-send-errors",
        type=int,
        default=3,
        help="leave offboard (--failsafe) after this many setpoints in a row failed to "
        "reach MAVSDK",
    )
    p.add_argument(
        "--geofence",
        default="-5,5,-5,5,-0.5,4",
        help="xmin,xmax,ymin,ymax,zmin,zmax of the allowed box, ENU metres",
    )
    p.add_argument(
        "--geofence-action",
        choices=("hold", "land"),
        default="hold",
        help="what PX4 does when the vehicle leaves the box",
    )
    p.add_argument(
        "--max-throttle",
        type=float,
        default=1.0,
        help="upper clamp of the normalised thrust sent to PX4 (0, 1]",
    )
    p.add_argument(
        "--vision",
        choices=("odometry", "mocap", "off"),
        default="odometry",
        help="forward mocap to PX4 as ODOMETRY for EKF2 (estimator type vision), "
        "as mocap-type ODOMETRY, or not at all",
    )
    p.add_argument(
        "--vision-frame",
        choices=("local_frd", "mocap_ned"),
        default="local_frd",
        help="ODOMETRY world frame id (local_frd: heading arbitrary)",
    )
    p.add_argument(
        "--no-require-local-position",
        dest="require_local_position",
        action="store_false",
        help="be ready without PX4 reporting a local position",
    )
    p.add_argument(
        "--no-start-mission",
        dest="start_mission",
        action="store_false",
        help="do not send the controller's 'start' command when engaged",
    )
    p.add_argument(
        "--takeoff-timeout",
        type=float,
        default=30.0,
        help="longest wait for PX4's take-off (arm command with takeoff_m) [s]",
    )
    p.add_argument(
        "--status-rate", type=float, default=2.0, help="vehicle_status events per second (0: none)"
    )
    p.add_argument(
        "--imu",
        choices=("px4", "off"),
        default="px4",
        help="publish PX4's body rates as imu at the control rate (the estimator's "
        "clock), or not (a simulator on the bus does it)",
    )
    p.add_argument(
        "--max-gyro-age",
        type=float,
        default=0.2,
        help="older PX4 rate telemetry is not published as imu [s]",
    )


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
