"""Configuration of one service stack (``arcade up``'s options): :class:`StackConfig`.

What the stack is made of (:data:`SERVICES`, their stop order, the profiles), how each
process is scheduled on the realtime clock, and the command line each process gets
(:meth:`StackConfig.args`). :class:`StackConfig` makes the run folder, the weights file, the
checkpoint and the bus configuration files absolute (relative to the caller's working
directory) when it is built, and checks that the bus configuration files name every process
(:meth:`StackConfig.bus_config_problem`). The launcher (:mod:`deploy.launcher`) runs it.

Credentials (``credentials=True``, what ``arcade up`` and ``arcade demo`` use on the peers'
loopback bus): :meth:`StackConfig.make_credentials` writes a new random password for the
run and one peer configuration with it, readable by the owner only, and every process the
launcher starts (and the launcher's own sessions) opens that file (``--bus-config``), so a
process without it cannot join the bus.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from arcade_control.knobs import DEFAULT_STACK_METHOD
from services.messages import VEHICLE_BODY

__all__ = [
    "CPU_WAKEUP_LATENCY_US",
    "MOCAP_BODY_SERVICES",
    "NICE",
    "PROFILES",
    "REALTIME_PRIORITY",
    "SERVICES",
    "STOP_ORDER",
    "StackConfig",
]

#: Start order; stop order is the reverse of the data flow (vehicle first, recorder last).
SERVICES = ("recorder", "estimator", "adapter", "controller", "sim")
STOP_ORDER = ("sim", "controller", "adapter", "estimator", "ros2", "recorder")
PROFILES = ("sim", "px4")
#: Realtime scheduling (realtime clock only): the sense-to-actuate path (vehicle link,
#: estimator, controller) under SCHED_FIFO at these priorities, ahead of the adapter; the
#: recorder niced last. Without the privilege a service warns and keeps the normal policy.
REALTIME_PRIORITY = {"sim": 30, "estimator": 25, "controller": 20}
NICE = {"recorder": 5, "ros2": 5}
#: ... and idle CPUs that poll instead of sleeping (PM QoS; ``timing.cpu_wakeup_latency``).
CPU_WAKEUP_LATENCY_US = 0
#: The services that take ``--mocap-body`` (the PX4 bridge too, and the simulated PX4 as
#: ``sim``): one name on all of them.
MOCAP_BODY_SERVICES = ("sim", "estimator", "recorder", "foxglove")


@dataclass
class StackConfig:
    """Options of one stack (``arcade up`` flags)."""

    out: Path
    profile: str = "sim"
    lockstep: bool = False
    vehicle: str = "default"
    hub: str = "tcp/127.0.0.1:7450"
    rate: float = 20.0
    duration: float | None = None
    payload_g: float = 175.0
    speed: float = 2.5
    seed: int = 0
    release: float = 0.95
    #: Hover before the figure-eight [s] (None: the scenario's); horizontal plan offset [m].
    hover_s: float | None = None
    origin: tuple[float, float] = (0.0, 0.0)
    #: What is flown instead of the figure-eight (``--trajectory`` of the simulator and
    #: the controller): a built-in spec, or a fitted path file with its SHA-256
    #: (:func:`deploy.trajectories.stage`); None: the figure-eight.
    trajectory: str | None = None
    trajectory_sha256: str | None = None
    x64: bool = False
    #: The link's setpoint delay that the controller and the adapter compensate [s]
    #: (``--link-delay``; 0: none).
    link_delay_s: float = 0.0
    #: Realtime clock: SCHED_FIFO for the sense-to-actuate path (``REALTIME_PRIORITY``)
    #: and a CPU wake-up latency request (``CPU_WAKEUP_LATENCY_US``).
    realtime_priority: bool = True
    weights: Path | None = None
    #: The controller the stack flies (``--method`` of the adapter and the controller):
    #: one of ``arcade_control.knobs.STACK_METHODS``.
    method: str = DEFAULT_STACK_METHOD
    checkpoint: Path | None = None
    ready_timeout: float = 600.0
    log_level: str = "INFO"
    #: Diagnostic: the simulator publishes the ground-truth state, no estimator runs.
    truth_state: bool = False
    extra: dict[str, list[str]] = field(default_factory=dict)
    #: Mirror the flight for ROS 2 (the ``ros2`` service, ``services.ros2_mirror``).
    ros2: bool = False
    #: Supervision: restarts per service (0: a crash stops the stack) and the back-off
    #: before restart ``n`` (``restart_backoff_s * 2**n``, at most ``restart_backoff_max_s``).
    max_restarts: int = 3
    restart_backoff_s: float = 0.5
    restart_backoff_max_s: float = 8.0
    #: Zenoh configuration file of each process's bus session, keyed by process name plus
    #: ``launcher`` (the launcher's own session) and optionally ``operator`` (commands
    #: sent on a user's behalf); empty: peers on loopback through ``hub``. Given, it must
    #: name every process and the launcher; ``hub`` is then unused.
    bus_configs: dict[str, Path] = field(default_factory=dict)
    #: The vehicle's rigid body on the ``mocap`` topic (``--mocap-body`` of every service
    #: in :data:`MOCAP_BODY_SERVICES`; the bridge's too).
    mocap_body: str = VEHICLE_BODY
    #: Serve the live flight to Foxglove (the ``foxglove`` service) on this loopback TCP
    #: port (0: any free one); None: no such service.
    foxglove_port: int | None = None
    #: The peers on ``hub`` authenticate with a password made for this run
    #: (:meth:`make_credentials`); not with ``bus_configs``.
    credentials: bool = False
    #: The run's peer configuration with the credentials (a Path), once made; not a field:
    #: copies of the options (``dataclasses.replace``, the px4 profile's) start without it.
    credentials_file = None

    def __post_init__(self) -> None:
        # Absolute paths: what a service is handed does not depend on where it runs.
        self.out = _absolute(self.out)
        if self.weights is not None:
            self.weights = _absolute(self.weights)
        if self.checkpoint is not None:
            self.checkpoint = _absolute(self.checkpoint)
        self.bus_configs = {k: _absolute(v) for k, v in self.bus_configs.items()}

    def bus_config_problem(self, processes: Iterable[str]) -> str | None:
        """Why ``bus_configs`` does not fit ``processes`` (one line), or None."""
        if not self.bus_configs:
            return None
        # The px4 profile's operator session (arm, hold, land, disarm) needs its own.
        wanted = [*processes, "launcher", *(("operator",) if self.profile == "px4" else ())]
        missing = [n for n in wanted if n not in self.bus_configs]
        unknown = sorted(set(self.bus_configs) - set(wanted))
        if missing:
            return f"bus_configs: no configuration for {', '.join(missing)}"
        if unknown:
            return f"bus_configs: not a process of this stack: {', '.join(unknown)}"
        return None

    def bus_config(self, name: str) -> Any:
        """The Zenoh configuration of process ``name``'s session (``launcher``, a service,
        ``operator``): its file in ``bus_configs``, else a peer on ``hub``. ``ValueError``
        naming the file if it cannot be read."""
        from services.bus import peer_config, read_config  # Zenoh: loaded on first use

        if self.credentials_file is not None:
            return read_config(self.credentials_file)
        if not self.bus_configs:
            return peer_config(self.hub)
        if name not in self.bus_configs:
            raise ValueError(f"bus_configs: no configuration for {name}")
        return read_config(self.bus_configs[name])

    def bus_args(self, name: str) -> list[str]:
        """``--bus-config FILE`` of process ``name``: its file in ``bus_configs``, or the
        run's credentials; none for open peers (their ``--hub`` is among :meth:`base_args`)."""
        if self.credentials_file is not None:
            return ["--bus-config", str(self.credentials_file)]
        return ["--bus-config", str(self.bus_configs[name])] if self.bus_configs else []

    def make_credentials(self) -> Path | None:
        """With ``credentials`` (and no ``bus_configs``): a new random password for this run
        in ``<out>/bus/users.txt`` and the peer configuration on ``hub`` that uses it in
        ``<out>/bus/peer.json5`` (folder and files readable by the owner only), which every
        process then opens; returns that file (None: open peers)."""
        if not self.credentials or self.bus_configs:
            return None
        from services.bus import peer_tree

        folder = Path(self.out) / "bus"
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        folder.chmod(0o700)  # an existing folder too
        users, peer = folder / "users.txt", folder / "peer.json5"
        password = secrets.token_urlsafe(32)
        _write_private(users, f"arcade:{password}\n")
        tree = peer_tree(self.hub, credentials=("arcade", password, users))
        _write_private(peer, json.dumps(tree, indent=1) + "\n")
        self.credentials_file = peer
        return peer

    def remove_credentials(self) -> None:
        """Delete the files of :meth:`make_credentials` (the password dies with the run)."""
        if self.credentials_file is not None:
            folder = self.credentials_file.parent
            for name in ("peer.json5", "users.txt"):
                (folder / name).unlink(missing_ok=True)
            with contextlib.suppress(OSError):  # kept if anything else is in it
                folder.rmdir()
            self.credentials_file = None

    def checkpoint_path(self) -> Path:
        """The adapter's posterior checkpoint (restored by a restarted adapter). Without
        ``checkpoint`` it is the run folder's own, removed at start: a new flight starts
        at the prior, a restarted adapter continues from it."""
        return (
            Path(self.checkpoint)
            if self.checkpoint is not None
            else (Path(self.out) / "adapter_checkpoint.npz")
        )

    def mocap_source(self) -> str | None:
        """The service whose session the estimator takes mocap from (None: any)."""
        return "sim"

    def services(self) -> tuple[str, ...]:
        """The processes of this configuration, in start order."""
        if self.truth_state:
            return self.with_optional(tuple(s for s in SERVICES if s != "estimator"))
        return self.with_optional(SERVICES)

    def with_optional(self, services: tuple[str, ...]) -> tuple[str, ...]:
        """``services`` (the vehicle link last) with the optional services this
        configuration asks for (``ros2``, ``foxglove``: they only listen to the bus) started
        just before the vehicle link: a vehicle waits for every other process, so they see
        the whole flight."""
        extra = (*(("ros2",) if self.ros2 else ()), *self.side_services())
        return (*services[:-1], *extra, services[-1])

    def side_services(self) -> tuple[str, ...]:
        """The optional live Foxglove server (``foxglove_port``)."""
        return ("foxglove",) if self.foxglove_port is not None else ()

    def base_args(self) -> list[str]:
        """The arguments every process of the stack takes (vehicle, hub, run folder, rate);
        with ``bus_configs`` no hub: each process gets its own :meth:`bus_args` when it is
        spawned."""
        own_file = self.bus_configs or self.credentials_file is not None
        hub = [] if own_file else ["--hub", self.hub]
        return [
            "--vehicle",
            self.vehicle,
            *hub,
            "--out",
            str(self.out),
            "--rate",
            f"{self.rate:g}",
            "--log-level",
            self.log_level,
        ]

    def args(self, service: str) -> list[str]:
        common = self.base_args()
        if self.lockstep:
            common.append("--lockstep")
        if self.x64:
            common.append("--x64")
        plan = [
            "--payload-g",
            f"{self.payload_g:g}",
            "--speed",
            f"{self.speed:g}",
            "--seed",
            str(self.seed),
            "--release",
            f"{self.release:g}",
        ]
        if self.duration is not None:
            plan += ["--duration", f"{self.duration:g}"]
        if self.hover_s is not None:
            plan += ["--hover-s", f"{self.hover_s:g}"]
        if self.trajectory is not None:
            plan.append(f"--trajectory={self.trajectory}")
            if self.trajectory_sha256 is not None:
                plan += ["--trajectory-sha256", self.trajectory_sha256]
        if tuple(self.origin) != (0.0, 0.0):
            plan.append(f"--origin={self.origin[0]:g},{self.origin[1]:g}")  # may start with "-"
        own: list[str] = []
        if service in ("sim", "controller"):
            own += plan
        if service == "foxglove":
            own += ["--port", str(self.foxglove_port)]
        if service in ("adapter", "controller") and self.weights is not None:
            own += ["--weights", str(self.weights)]
        if service == "adapter":
            own += ["--checkpoint", str(self.checkpoint_path())]
        if service in MOCAP_BODY_SERVICES:
            own += ["--mocap-body", self.mocap_body]
        if service == "estimator" and self.mocap_source() is not None:
            own += ["--mocap-source", self.mocap_source()]
        if service in ("adapter", "controller"):  # one value on both, never one alone
            own += ["--link-delay", f"{self.link_delay_s:g}", "--method", self.method]
            own += ["--state-source", "sim" if self.truth_state else "estimator"]
        if service == "sim":
            own += ["--ready-timeout", f"{self.ready_timeout:g}"]
            consumers = [s for s in self.services() if s != "sim"]  # incl. the recorder
            own += ["--wait-for", ",".join(consumers)]
            if self.truth_state:
                own.append("--truth-state")
        if not self.lockstep and self.realtime_priority and service in REALTIME_PRIORITY:
            own += [
                "--realtime-priority",
                str(REALTIME_PRIORITY[service]),
                "--cpu-wakeup-latency-us",
                str(CPU_WAKEUP_LATENCY_US),
            ]
        if not self.lockstep and service in NICE:
            own += ["--nice", str(NICE[service])]
        return [*common, *own, *self.extra.get(service, [])]


def _write_private(path: Path, text: str) -> None:
    """Write ``path`` anew, readable and writable by the owner only."""
    path.unlink(missing_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)


def _absolute(path: str | os.PathLike[str]) -> Path:
    """``path`` relative to the current directory, made absolute (symlinks kept)."""
    return Path(os.path.abspath(os.fspath(path)))
