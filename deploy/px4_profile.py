"""Profile ``px4`` of the launcher: the service stack flying a PX4 vehicle through the bridge.

Processes: recorder, estimator, adapter, controller and the PX4 bridge
(:mod:`services.px4_bridge`, MAVSDK) -- no simulator. Motion capture comes from the lab's
mocap publisher on the bus (``mocap`` topic, ENU/FLU); the bridge forwards it to PX4 and
publishes PX4's gyro as ``imu`` (the estimator's control instants).

``simulate=True`` (``arcade up --profile px4 --simulate``) adds ``px4sim``
(:mod:`services.px4_sim`): the MuJoCo quadrotor impersonating PX4 on a loopback UDP
MAVLink link and the mocap system on the bus, so that the whole chain (MAVLink, MAVSDK,
bridge, Zenoh, estimator, adapter, controller) runs on one machine. There the simulator is
the vehicle process (the flight ends with its mission) and it starts the mission clock and
streams ``imu`` itself, so the bridge does neither.

Arming is never automatic: :func:`arm` (``--arm``) waits until the bridge reports a
steady controller setpoint stream, then sends the ``arm`` command; without ``--arm``,
``arcade up`` asks on the terminal.

Until offboard is engaged the controller's setpoints are not applied (PX4 flies the
vehicle): the adapter learns only from the mission ``start`` on (sent by the bridge when
offboard is engaged, or by ``px4sim`` with ``simulate``), pauses on a ``failsafe`` event
(the bridge emits one on every exit from offboard, operator commands included) and
resumes on ``failsafe_cleared`` (emitted by the bridge whenever offboard is engaged again).
"""

from __future__ import annotations

import itertools
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from deploy.launcher import EVENTS_KEPT
from deploy.stack_config import CPU_WAKEUP_LATENCY_US, REALTIME_PRIORITY, StackConfig

#: Start order; stop order: the bridge first (it leaves offboard -> Hold), recorder last.
PX4_SERVICES = ("recorder", "estimator", "adapter", "controller", "bridge")
#: The bridge's options (``--bridge-arg``) that the recorder and the live Foxglove server
#: take too: the geofence they draw, the vehicle file whose cable they draw.
SCENE_BRIDGE_OPTIONS = ("--geofence", "--vehicle-file")
PX4_STOP_ORDER = ("bridge", "px4sim", "controller", "adapter", "estimator", "ros2", "recorder")


@dataclass
class Px4StackConfig(StackConfig):
    """``arcade up --profile px4`` options (on top of :class:`StackConfig`'s)."""

    profile: str = "px4"
    #: MAVSDK URL of the vehicle; with ``simulate`` the simulated PX4's loopback link.
    connect: str = "udpin://0.0.0.0:14540"
    simulate: bool = False
    #: Height [m] PX4 takes off to by itself before offboard (vehicle on the ground).
    takeoff_m: float | None = None
    #: The simulated PX4 starts disarmed on the floor (else hovering at the start pose).
    on_ground: bool = False
    #: PX4's COM_OF_LOSS_T [s] and COM_OBL_RC_ACT of the simulated vehicle.
    of_loss_s: float = 1.0
    of_loss_action: str = "hold"
    bridge_args: list[str] = field(default_factory=list)
    stop_order: tuple[str, ...] = PX4_STOP_ORDER

    @property
    def vehicle_process(self) -> str:
        """The process whose end is the end of the flight (never restarted)."""
        return "px4sim" if self.simulate else "bridge"

    def mocap_source(self) -> str | None:
        """The simulated PX4 publishes mocap; a lab's mocap publisher is not pinned."""
        return "px4sim" if self.simulate else None

    def services(self) -> tuple[str, ...]:
        if self.simulate:
            return self.with_optional((*PX4_SERVICES[:-1], "px4sim", "bridge"))
        return self.with_optional(PX4_SERVICES)

    def sim_url(self) -> str:
        """The simulated PX4's side of the link (it sends to the bridge's port)."""
        port = self.connect.rsplit(":", 1)[-1]
        return f"udpout://127.0.0.1:{port}"

    def args(self, service: str) -> list[str]:
        if service == "px4sim":
            own = [
                *super().args("sim"),
                "--px4",
                self.sim_url(),
                "--of-loss-s",
                f"{self.of_loss_s:g}",
                "--of-loss-action",
                self.of_loss_action,
            ]
            if self.on_ground:
                own.append("--on-ground")
            return [*own, *self.extra.get("px4sim", [])]
        if service in ("recorder", "foxglove"):  # the bridge's geofence and vehicle's cable
            drawn: dict[str, str] = {}
            b = self.bridge_args
            for i, a in enumerate(b):
                for name in SCENE_BRIDGE_OPTIONS:
                    if a.startswith(f"{name}="):
                        drawn[name] = a
                    elif a == name and i + 1 < len(b):
                        drawn[name] = f"{name}={b[i + 1]}"
            return [*super().args(service), *drawn.values()]
        if service != "bridge":
            return super().args(service)
        common = [*self.base_args(), "--connect", self.connect, "--mocap-body", self.mocap_body]
        if self.simulate:  # the simulator clocks the estimator and the mission itself
            common += ["--imu", "off", "--no-start-mission", "--mocap-source", "px4sim"]
        if not self.lockstep and self.realtime_priority:
            common += [
                "--realtime-priority",
                str(REALTIME_PRIORITY["sim"]),
                "--cpu-wakeup-latency-us",
                str(CPU_WAKEUP_LATENCY_US),
            ]
        return [*common, *self.bridge_args, *self.extra.get("bridge", [])]


class EventWaiter:
    """Collects the launcher's event records (pass as ``on_event``) and waits for one.

    Records are numbered from 0 as they arrive; the newest ``keep`` are kept (a PX4 flight
    sends a ``vehicle_status`` event twice a second for as long as it runs)."""

    def __init__(self, keep: int = EVENTS_KEPT) -> None:
        self.events: deque[dict[str, Any]] = deque(maxlen=keep)
        self.count = 0  # records received
        self._cond = threading.Condition()

    def __call__(self, rec: dict[str, Any]) -> None:
        with self._cond:
            self.events.append(rec)
            self.count += 1
            self._cond.notify_all()

    def mark(self) -> int:
        """The number the next record will have."""
        with self._cond:
            return self.count

    def wait(
        self, pred: Callable[[dict[str, Any]], bool], timeout: float, after: int = 0
    ) -> dict[str, Any] | None:
        """The first record numbered ``after`` or later that satisfies ``pred`` (or None);
        of the records no longer kept, none."""

        def find() -> dict[str, Any] | None:
            skip = max(0, after - (self.count - len(self.events)))
            return next((r for r in itertools.islice(self.events, skip, None) if pred(r)), None)

        with self._cond:
            self._cond.wait_for(lambda: find() is not None, timeout)
            return find()


def arm(
    events: EventWaiter,
    config: Px4StackConfig,
    timeout: float = 60.0,
    say: Callable[[str], None] = lambda msg: None,
    min_stream_s: float = 1.0,
) -> bool:
    """Send ``arm`` once the bridge reports a steady setpoint stream; True once offboard
    is engaged. Retried while the bridge refuses for lack of a steady stream (start-up).

    ``events`` must be the stack's ``on_event`` hook (it sees the bridge's events).
    """
    from services.bus import Bus
    from services.messages import Command

    def steady(r: dict[str, Any]) -> bool:
        return (
            r["kind"] == "vehicle_status"
            and bool(r["data"].get("setpoints_fresh"))
            and float(r["data"].get("stream_s", 0.0)) >= min_stream_s
        )

    def answer(r: dict[str, Any]) -> bool:
        return r["src"].startswith("bridge/") and (
            r["kind"] in ("offboard", "fault")
            or r["text"].startswith(("arm refused", "offboard refused"))
        )

    args = {} if config.takeoff_m is None else {"takeoff_m": float(config.takeoff_m)}
    deadline = time.monotonic() + timeout
    with Bus(config.vehicle, "operator", config.bus_config("operator")) as bus:
        # Seeing the bridge's token means this new session is linked: the put arrives.
        bus.wait_alive(["bridge"], timeout)
        mark = events.mark()  # only what the bridge says from now on
        while True:
            if events.wait(steady, max(0.0, deadline - time.monotonic()), after=mark) is None:
                say("no steady controller setpoints at the bridge: not arming")
                return False
            mark = events.mark()
            bus.put(Command(name="arm", target="bridge", args=args, stamp=time.monotonic()))
            say("arm command sent")
            wait_s = max(0.0, deadline - time.monotonic()) + (
                120.0 if config.takeoff_m is not None else 5.0
            )
            rec = events.wait(answer, wait_s, after=mark)
            if rec is None:
                say("the bridge did not answer the arm command")
                return False
            say(f"bridge: {rec['text']}")
            if rec["kind"] == "offboard":
                return True
            if "not streaming" not in rec["text"] or time.monotonic() > deadline:
                return False
            mark = events.mark()


# ------------------------------------------------------------------ ``arcade up`` hook


def add_arguments(p: Any) -> None:
    """The ``arcade up`` options of the px4 profile."""
    g = p.add_argument_group("profile px4 (PX4 vehicle through MAVSDK)")
    g.add_argument(
        "--connect",
        default=None,
        metavar="URL",
        help="MAVSDK URL of the vehicle (default udpin://0.0.0.0:14540; "
        "e.g. serial:///dev/ttyACM0:921600)",
    )
    g.add_argument(
        "--simulate",
        action="store_true",
        help="a simulated PX4 (MuJoCo on MAVLink over loopback UDP) instead of a real vehicle",
    )
    g.add_argument(
        "--arm",
        action="store_true",
        help="arm and engage offboard once every service is ready (default: ask on the terminal)",
    )
    g.add_argument(
        "--takeoff-m",
        type=float,
        default=None,
        help="on the ground: PX4 takes off to this height above the ground [m], > 0, before "
        "offboard (default: none, offboard engages where the vehicle is)",
    )
    g.add_argument(
        "--on-ground",
        action="store_true",
        help="--simulate: start disarmed on the floor (use with --takeoff-m)",
    )
    from services.px4_bridge_options import mavlink_url

    g.add_argument(
        "--forward",
        action="append",
        type=mavlink_url,
        default=[],
        metavar="URL",
        help="the bridge also passes MAVLink to and from this MAVSDK URL, so that a ground "
        "station watches while the stack flies, e.g. udpout://127.0.0.1:14550 for "
        "QGroundControl on this machine (repeatable)",
    )
    g.add_argument(
        "--bridge-arg",
        action="append",
        default=[],
        metavar="ARG",
        help="extra option for the bridge, e.g. --bridge-arg=--geofence=-3,3,-3,3,0,3",
    )


def config_from_args(args: Any, base: StackConfig) -> Px4StackConfig:
    """The px4 profile's configuration from ``arcade up`` arguments and the common ones."""
    import dataclasses

    if base.lockstep:
        raise ValueError("profile px4 runs on the wall clock: drop --lockstep")
    connect = args.connect
    if connect is None:
        connect = (
            f"udpin://127.0.0.1:{_free_udp_port()}" if args.simulate else "udpin://0.0.0.0:14540"
        )
    fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(StackConfig)}
    fields["profile"] = "px4"
    return Px4StackConfig(
        **fields,
        connect=connect,
        simulate=args.simulate,
        takeoff_m=args.takeoff_m,
        on_ground=args.on_ground,
        bridge_args=[*(f"--forward={url}" for url in args.forward), *args.bridge_arg],
    )


def _free_udp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def flight_hooks(args: Any, config: Px4StackConfig, say: Callable[[str], None]) -> dict[str, Any]:
    """``on_event``/``on_ready`` for :func:`deploy.launcher.run_flight`: arm with ``--arm``,
    else an operator console on the terminal (``arm``, ``hold``, ``land``, ``disarm``)."""
    import sys

    events = EventWaiter()

    def on_ready(stack: Any) -> None:
        if args.arm:
            threading.Thread(
                target=arm, args=(events, config), kwargs={"say": say}, daemon=True, name="arm"
            ).start()
        elif sys.stdin is not None and sys.stdin.isatty():
            say(
                "ready: type arm + Enter to engage offboard control (hold, land, disarm "
                "too); Ctrl-C stops everything"
            )
            threading.Thread(
                target=_console, args=(events, config, say), daemon=True, name="console"
            ).start()
        else:
            say("ready: not arming (no --arm and no terminal)")

    return {"on_event": events, "on_ready": on_ready}


def _console(events: EventWaiter, config: Px4StackConfig, say: Callable[[str], None]) -> None:
    import sys

    from services.bus import Bus
    from services.messages import Command

    for line in sys.stdin:
        word = line.strip().lower()
        if word == "arm":
            arm(events, config, say=say)
        elif word in ("hold", "land", "disarm"):
            with Bus(config.vehicle, "operator", config.bus_config("operator")) as bus:
                bus.wait_alive(["bridge"], 10.0)
                bus.put(Command(name=word, target="bridge", stamp=time.monotonic()))
            say(f"{word} command sent")
        elif word:
            say("commands: arm, hold, land, disarm")


__all__ = [
    "PX4_SERVICES",
    "PX4_STOP_ORDER",
    "EventWaiter",
    "Px4StackConfig",
    "add_arguments",
    "arm",
    "config_from_args",
    "flight_hooks",
]
