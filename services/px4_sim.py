"""Simulated PX4 vehicle service: the MuJoCo quadrotor as a PX4 autopilot on MAVLink, and
the motion-capture system on the bus.

The bus side is that of the simulator service (:mod:`services.sim_node`, realtime mode):
``mocap`` frames and one ``imu`` sample per control period on ``arcade/<vehicle>/...``,
the same plan options, payload release (``--release`` or the ``release_payload``
command), ``start`` command, events, ``<out>/truth.csv`` and ``<out>/stats/px4sim.json``.
The control input is different: it comes **only** from MAVLink (a PX4 bridge flying the
vehicle in offboard attitude-rate mode, see :mod:`simulator.px4`); ``setpoint`` messages
on the bus are ignored and counted (``ignored_setpoints``).

The vehicle starts hovering at the plan's start pose, armed, in Hold (``--on-ground``:
disarmed on the floor below it). The MAVLink link is up from the start so that the bridge
can connect before the mission; the mission clock starts (``start`` command) at the first
control instant after ``--preroll`` at which the vehicle is armed in Offboard. A flight
control instant in Offboard without a new SET_ATTITUDE_TARGET since the previous one
counts as a missed deadline. MAVLink carries no bus stamps; what is measured instead is
the actuation delay: simulated time from a control instant to the first new
SET_ATTITUDE_TARGET after it (``actuation_delay``, resolution one ``--substep``). PX4's
offboard-loss failsafe (``--of-loss-s``) switches to Hold or Land and is reported as a
``failsafe`` event. Whenever PX4 flies by itself (its failsafe, or the bridge's Hold or
Land), crash detection measures the distance to PX4's own target instead of the reference
(:meth:`Px4Vehicle.own_target`), and a landed vehicle is not a crash. Realtime only
(MAVLink runs on the wall clock): ``--lockstep`` is refused; ``--wait-for`` is not used
(the mission waits for offboard instead).

At the plan's end the service emits ``flight finished`` and keeps the vehicle running
(mocap, imu and MAVLink) until it is stopped or ``--linger-s`` passed: a real vehicle does
not vanish when the mission ends, and the launcher stops the bridge first, whose Hold
command must still be answered.

With the PX4 bridge (:mod:`services.px4_bridge`) on the same bus exactly one of the two may
publish ``imu`` and the ``start`` command: either this service (default; run the bridge
with ``--imu off --no-start-mission``) or, closer to a real vehicle where only the mocap
system is simulated, the bridge (run this service with ``--no-imu --no-start-command``).
"""

from __future__ import annotations

import argparse
import math
import time

from arcade_io.px4_failsafe import add_failsafe_arguments, failsafe_settings
from arcade_io.runs import number
from services import runtime, timing
from services.messages import Command, Setpoint
from services.sim_node import SimNode
from services.sim_node import _extra as _sim_options
from simulator.px4.modes import FlightMode

#: STATUSTEXT severity (MAV_SEVERITY) -> event severity.
_SEVERITY = {
    0: "critical",
    1: "critical",
    2: "critical",
    3: "error",
    4: "warning",
    5: "info",
    6: "info",
    7: "debug",
}


class Px4SimNode(SimNode):
    """Simulated PX4 vehicle: MuJoCo quadrotor on MAVLink + motion capture on the bus."""

    name = "px4sim"

    def setup(self, bus) -> None:
        from simulator.px4 import Px4Sim

        a = self.args
        if a.lockstep:
            raise ValueError("px4sim runs on the wall clock only (MAVLink): drop --lockstep")
        super().setup(bus)
        self._finished = False  # the plan flown to its end ("flight finished" emitted)
        start = self.sim.state()[0:3]
        self.px4 = Px4Sim(
            a.px4,
            vehicle=a.vehicle_file,
            payload_g=self.scen.payload_g,
            cable_length=self.scen.cable_length_m,
            start=start,
            airborne=not a.on_ground,
            **failsafe_settings(a),
            seed=self.trial.sim_seed,
            substep=a.substep,
            on_text=self._on_text,
        )
        self.px4.stop = self.stop
        self.sim = self.px4.vehicle.sim  # the helpers of SimNode work on this airframe
        self.stats.update(ignored_setpoints=0, px4_failsafes=[], offboard_at=None, link=a.px4)

    # -- inputs: MAVLink only
    def on_setpoint(self, sp: Setpoint) -> None:
        self.stats["ignored_setpoints"] += 1

    def _on_alive(self, service: str, up: bool) -> None:
        # With --no-start-command the bridge owns the mission's start: not even a rejoining
        # controller gets it from here.
        if not self.args.no_start_command:
            super()._on_alive(service, up)

    def _on_text(self, severity: int, text: str) -> None:
        v = self.px4.vehicle
        if text.startswith("Failsafe"):
            self.stats["px4_failsafes"].append({"t": v.time, "mode": v.mode.name})
            self.event("failsafe", text, "error", sim_time=float(v.time), mode=v.mode.name)
        else:
            self.event(
                "info", f"PX4: {text}", _SEVERITY.get(severity, "info"), sim_time=float(v.time)
            )

    # -- loop
    def main(self) -> None:
        # No waiting for consumers: the MAVLink link must be up for the bridge to connect,
        # and the mission only starts once it flies the vehicle in offboard.
        t0 = time.perf_counter()
        try:
            self._realtime()
        finally:
            self.stats["wall_s"] = time.perf_counter() - t0
        if not self._finished:  # stopped or crashed before the plan's end
            self._finish()

    def _finish(self) -> None:
        self._finished = True
        self.event(
            "info", "flight finished", stamp=max(self._last_stamp, 0.0), steps=self.stats["steps"]
        )

    def _lockstep(self) -> None:  # refused in setup; kept explicit
        raise RuntimeError("px4sim has no lockstep mode")

    def _realtime(self) -> None:
        px4, v, sim = self.px4, self.px4.vehicle, self.sim
        st = {
            "n": 0,
            "t_next": 0.0,
            "k": -1,
            "t_start": 0.0,
            "prev_sp": None,
            "t_tick": math.nan,
            "seen_sp": None,
            "linger_until": math.inf,
        }
        delays = timing.LatencySamples()  # control instant -> first new SET_ATTITUDE_TARGET [s]

        def mono(t_sim: float) -> float:
            return px4.epoch + t_sim  # the vehicle's wall clock, re-anchored after a stall

        def on_chunk(_) -> bool:
            t_sim = sim.time
            first = st["n"] == 0
            with px4.lock:
                sp_now = v.offboard_sp
            if sp_now is not st["seen_sp"]:
                if st["k"] >= 0 and math.isfinite(st["t_tick"]):
                    delays.append(sp_now.time - st["t_tick"])
                    st["t_tick"] = math.nan  # the first one after an instant only
                st["seen_sp"] = sp_now
            self._publish_frames(sim.mocap.read(math.inf) if first else sim.read_mocap(), mono)
            if t_sim < st["t_next"] - 1e-9:
                return False
            stamp = mono(t_sim)  # the sample instant (see sim_node)
            with px4.lock:
                engaged = v.armed and v.mode is FlightMode.OFFBOARD
                sp = v.offboard_sp
                # Off the stack's setpoints (PX4's failsafe, the bridge's Hold or Land),
                # PX4 flies to its own target: crashes are measured against that.
                hold = None if engaged else v.own_target()
                self._on_ground = v.landed
                u = sim.setpoint
            k = st["k"]
            if k < 0 and engaged and t_sim >= self.args.preroll:
                k, st["t_start"] = 0, t_sim
                self._mission0 = t_sim
                if not self.args.no_start_command:
                    self.bus.put(Command(name="start", args={"t0": stamp}, stamp=stamp))
                self._mission_started(stamp)
                self.stats.update(preroll_s=t_sim, offboard_at=t_sim)
            elif k >= 0 and not self._finished:
                k += 1
                if engaged and sp is st["prev_sp"]:
                    self.stats["missed_deadlines"] += 1
            st["k"], st["prev_sp"], st["t_tick"] = k, sp, t_sim
            if k >= 0:
                self._maybe_release(k, stamp)
            self._hold = hold
            gyro = sim.gyro.read(math.inf) if first else sim.read_gyro()
            if not self.args.no_imu:
                self._tick(stamp, gyro, sampled=stamp)
            self._last_stamp = stamp
            st["n"] += 1
            st["t_next"] += self.period
            if k >= 0 and not self._finished:
                if not self._record(u, t_sim - st["t_start"]):
                    return True
                self.stats["steps"] = k + 1
                if k >= self.n_steps - 1:
                    # The vehicle outlives its plan (mocap and imu still flowing) until
                    # stopped or --linger-s passed: a bridge stopped after the flight still
                    # gets its Hold command answered.
                    self._finish()
                    st["linger_until"] = t_sim + self.args.linger_s
            return t_sim >= st["linger_until"]

        px4.run(on_chunk=on_chunk)
        self.stats["epoch"] = px4.epoch  # the last anchor (moved by overruns)
        self.stats["overruns"] = px4.overruns
        # Simulated time at the chunk that saw the setpoint: resolution one --substep.
        self.stats["actuation_delay"] = delays.summary()
        self.stats["actuation_delay_samples_ms"] = delays.samples_ms()

    def teardown(self) -> None:
        super().teardown()
        self.px4.close()
        self.stats["mavlink_rx"] = dict(self.px4.mavlink.rx)
        self.stats["mavlink_rejects"] = dict(self.px4.mavlink.rejects)
        vision = self.px4.vehicle.vision
        self.stats["vision_received"] = vision is not None


#: Options of the simulator service that do not apply here (hidden from --help).
_UNUSED = {"step_timeout", "wait_for", "ready_timeout", "failsafe_after", "failsafe_resume"}


def _extra(p) -> None:
    _sim_options(p)  # same plan, payload, mocap and truth options as the simulator service
    for action in p._actions:
        if action.dest in _UNUSED:
            action.help = argparse.SUPPRESS
    p.add_argument(
        "--px4",
        default="udpout://127.0.0.1:14540",
        metavar="URL",
        help="MAVLink link: udpout://HOST:PORT (PX4 SITL style, the bridge "
        "listens) or udpin://HOST:PORT",
    )
    p.add_argument(
        "--vehicle-file", default=None, help="vehicle file (TOML; default: the shipped one)"
    )
    p.add_argument(
        "--on-ground",
        action="store_true",
        help="start disarmed on the floor instead of hovering armed in Hold",
    )
    add_failsafe_arguments(p)
    p.add_argument(
        "--no-imu",
        action="store_true",
        help="do not publish imu (the PX4 bridge publishes PX4's rates instead, "
        "as with a real vehicle)",
    )
    p.add_argument(
        "--no-start-command",
        action="store_true",
        help="do not put the mission's start command (the PX4 bridge does)",
    )
    p.add_argument(
        "--linger-s",
        type=number(0.0),
        default=5.0,
        help="after the plan's end keep the vehicle running this long, or until stopped, "
        "so that a bridge stopped after the flight gets its Hold answered [s] "
        "(default: %(default)s)",
    )


def main(argv: list[str] | None = None) -> int:
    return runtime.main_for(Px4SimNode, argv, _extra)


__all__ = ["Px4SimNode", "main"]
