"""Launcher of the service stack (``arcade up``): start, supervise and stop the processes.

One OS process per service (``python -m services <name>``): recorder, estimator, adapter,
controller and the vehicle link (profile ``sim``: the MuJoCo simulator). Start-up is
event-driven: each service compiles before it declares its liveliness token, the launcher
waits for all tokens (:meth:`Stack.wait_ready`), and the simulator waits for the consumers'
tokens before it takes off. Supervision: if any service exits before the flight is over,
the stack is stopped and the failure reported. Stop: SIGINT to every service in data-flow
order (vehicle first, recorder last so it records the end), then SIGTERM and SIGKILL for
those that do not exit in time.

Run folder (``--out``): ``logs/<service>.log`` (each service's log), ``logs/<service>.out``
(its stdout/stderr), ``stats/<service>.json``, ``events.jsonl`` (every event seen by the
launcher), ``truth.csv`` (simulator ground truth), ``flight_log.csv`` and ``bus.mcap``
(recorder).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
#: Start order; stop order is the reverse of the data flow (vehicle first, recorder last).
SERVICES = ("recorder", "estimator", "adapter", "controller", "sim")
STOP_ORDER = ("sim", "controller", "adapter", "estimator", "recorder")
PROFILES = ("sim", "px4")
#: Realtime scheduling: the sense-to-actuate path (vehicle link, estimator, controller)
#: ahead of the adapter, the recorder last (``nice`` offsets; raising a priority needs
#: privileges and is skipped with a warning without them).
PRIORITY = {"sim": -5, "estimator": -5, "controller": -5, "recorder": 5}


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
    x64: bool = False
    weights: Path | None = None
    checkpoint: Path | None = None
    ready_timeout: float = 600.0
    log_level: str = "INFO"
    #: Diagnostic: the simulator publishes the ground-truth state, no estimator runs.
    truth_state: bool = False
    extra: dict[str, list[str]] = field(default_factory=dict)

    def services(self) -> tuple[str, ...]:
        """The processes of this configuration, in start order."""
        if self.truth_state:
            return tuple(s for s in SERVICES if s != "estimator")
        return SERVICES

    def args(self, service: str) -> list[str]:
        common = ["--vehicle", self.vehicle, "--hub", self.hub, "--out", str(self.out),
                  "--rate", f"{self.rate:g}", "--log-level", self.log_level]
        if self.lockstep:
            common.append("--lockstep")
        if self.x64:
            common.append("--x64")
        plan = ["--payload-g", f"{self.payload_g:g}", "--speed", f"{self.speed:g}",
                "--seed", str(self.seed), "--release", f"{self.release:g}"]
        if self.duration is not None:
            plan += ["--duration", f"{self.duration:g}"]
        own: list[str] = []
        if service in ("sim", "controller"):
            own += plan
        if service in ("adapter", "controller") and self.weights is not None:
            own += ["--weights", str(self.weights)]
        if service == "adapter" and self.checkpoint is not None:
            own += ["--checkpoint", str(self.checkpoint)]
        if service == "sim":
            own += ["--ready-timeout", f"{self.ready_timeout:g}"]
            consumers = [s for s in self.services() if s != "sim"]  # incl. the recorder
            own += ["--wait-for", ",".join(consumers)]
            if self.truth_state:
                own.append("--truth-state")
        if not self.lockstep and service in PRIORITY:
            own += ["--nice", str(PRIORITY[service])]
        return [*common, *own, *self.extra.get(service, [])]


class StackError(RuntimeError):
    """A service failed to start or died during the run."""


class Stack:
    """The running stack; use as a context manager (stops everything on exit)."""

    def __init__(self, config: StackConfig, services: tuple[str, ...] | None = None):
        if config.profile not in PROFILES:
            raise ValueError(f"unknown profile {config.profile!r} (one of {PROFILES})")
        if config.profile == "px4":
            raise StackError("profile px4 needs the PX4 bridge service, which this build does "
                             "not include; use --profile sim")
        self.config = config
        self.services = services if services is not None else config.services()
        self.procs: dict[str, subprocess.Popen] = {}
        self.events: list[dict[str, Any]] = []
        self._events_lock = threading.Lock()
        self._bus: Any = None
        self.last_stamp = 0.0
        self.out = Path(config.out)

    # -- lifecycle
    def start(self) -> Stack:
        from services.bus import Bus, peer_config

        (self.out / "logs").mkdir(parents=True, exist_ok=True)
        self._bus = Bus(self.config.vehicle, "launcher", peer_config(self.config.hub)).open()
        self._bus.subscribe("event", self._on_event, check_order=False)
        self._bus.subscribe("state", self._on_state, check_order=False)
        env = dict(os.environ)
        env.setdefault("JAX_PLATFORMS", "cpu")
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
        for name in self.services:
            cmd = [sys.executable, "-m", "services", name, *self.config.args(name)]
            with (self.out / "logs" / f"{name}.out").open("w") as log:
                self.procs[name] = subprocess.Popen(
                    cmd, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT,
                    start_new_session=True)  # Ctrl-C goes to the launcher, which stops them
        return self

    def _on_event(self, e: Any) -> None:
        rec = {"stamp": e.stamp, "src": e.src, "kind": e.kind, "severity": e.severity,
               "text": e.text, "data": dict(e.data)}
        with self._events_lock:
            self.events.append(rec)
            with (self.out / "events.jsonl").open("a") as f:
                f.write(json.dumps(rec) + "\n")

    def _on_state(self, s: Any) -> None:
        self.last_stamp = s.stamp

    def _check_alive(self, until_exit: str | None = None) -> None:
        for name, p in self.procs.items():
            code = p.poll()
            if code is not None and name != until_exit:
                raise StackError(f"service {name} exited with code {code}; see "
                                 f"{self.out / 'logs' / (name + '.out')}")

    def wait_ready(self, timeout: float | None = None) -> float:
        """Block until every service declared its liveliness token; returns seconds."""
        timeout = self.config.ready_timeout if timeout is None else timeout
        t0 = time.monotonic()
        pending = set(self.services)
        while pending:
            left = timeout - (time.monotonic() - t0)
            if left <= 0:
                raise StackError(f"not ready after {timeout:.0f} s: {sorted(pending)}")
            self._check_alive()
            with contextlib.suppress(TimeoutError):  # short slices: notice a dead service
                self._bus.wait_alive(pending, timeout=min(left, 0.5))
            pending -= self._bus.alive
        return time.monotonic() - t0

    def wait(self, timeout: float | None = None,
             progress: Callable[[float], None] | None = None) -> int:
        """Wait for the vehicle process (the flight) to end; returns its exit code."""
        t0 = time.monotonic()
        sim = self.procs.get("sim")
        if sim is None:
            raise StackError("no vehicle process to wait for")
        while True:
            try:
                code = sim.wait(timeout=0.5)
                break
            except subprocess.TimeoutExpired:
                pass
            self._check_alive(until_exit="sim")
            if progress is not None:
                progress(self.last_stamp)
            if timeout is not None and time.monotonic() - t0 > timeout:
                raise StackError(f"flight not finished after {timeout:.0f} s")
        if progress is not None:
            progress(self.last_stamp)
        return code

    def stop(self, grace: float = 20.0) -> dict[str, int | None]:
        """SIGINT everything (data-flow order), then SIGTERM/SIGKILL stragglers."""
        for name in STOP_ORDER:
            p = self.procs.get(name)
            if p is None or p.poll() is not None:
                continue
            p.send_signal(signal.SIGINT)
            try:
                p.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                p.terminate()
                try:
                    p.wait(timeout=5.0)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        if self._bus is not None:
            self._bus.close()
            self._bus = None
        return {name: p.returncode for name, p in self.procs.items()}

    def __enter__(self) -> Stack:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def run_flight(config: StackConfig, progress: Callable[[str], None] = lambda m: None,
               on_time: Callable[[float], None] | None = None,
               timeout: float | None = None) -> dict[str, Any]:
    """Start the stack, fly the plan to the end, stop; returns codes, events and timings."""
    config.out.mkdir(parents=True, exist_ok=True)
    with Stack(config) as stack:
        progress("starting services (compiling on first use) ...")
        ready_s = stack.wait_ready()
        progress(f"all services ready after {ready_s:.1f} s; flying")
        t0 = time.monotonic()
        sim_code = stack.wait(timeout=timeout, progress=on_time)
        flight_s = time.monotonic() - t0
        codes = stack.stop()
    codes["sim"] = sim_code
    return {"codes": codes, "events": list(stack.events), "ready_s": ready_s,
            "flight_wall_s": flight_s, "out": str(config.out)}
