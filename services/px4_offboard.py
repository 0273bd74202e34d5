"""Offboard control of a PX4 vehicle by the bridge (:mod:`services.px4_bridge`): engaging
it, leaving it, the failsafes, the setpoint watchdog and the operator's commands.

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

import threading
import time
from typing import Any

import numpy as np

from services.messages import Command

#: MAVSDK flight mode names (telemetry.FlightMode) as they appear in events.
OFFBOARD, HOLD, LAND = "OFFBOARD", "HOLD", "LAND"


class OffboardControl:
    """The offboard half of :class:`~services.px4_bridge.Px4Bridge` (a base class of it).

    Works on the bridge's state: ``args``, ``stats``, ``event``, ``bus``, ``stop``, the
    lock and condition ``_lock`` / ``_cond``, the MAVSDK plugins ``offboard`` and
    ``action``, the telemetry ``_telemetry`` / ``_tel_cond`` and the setpoint stream
    (``_latest``, ``_last_rx``, ``_stream_since``), all made by the bridge's set-up.
    """

    def _send(self, deg_s: np.ndarray, throttle: float) -> None:
        """One ``set_attitude_rate`` (caller holds the lock). After ``--max-send-errors``
        failures in a row offboard is left: MAVSDK keeps re-sending the last setpoint it
        accepted, so PX4 would fly a stale one."""
        from mavsdk.plugins.offboard import AttitudeRate  # loaded by the bridge's connect

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
        from mavsdk.plugins.offboard import OffboardError, OffboardResult  # as _send's

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
