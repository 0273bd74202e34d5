"""Launcher of the service stack (``arcade up``): start, supervise and stop the processes.

One OS process per service (``python -m services <name>``): recorder, estimator, adapter,
controller and the vehicle link (profile ``sim``: the MuJoCo simulator). Start-up is
event-driven: each service compiles before it declares its liveliness token, the launcher
waits for all tokens (:meth:`Stack.wait_ready`), and the simulator waits for the consumers'
tokens before it takes off.

Supervision (:class:`Stack`): one watcher thread per process notices its exit at once.
A service that exits before the flight is over (non-zero code, killed by a signal, or
even code 0) is restarted after an exponential back-off (``restart_backoff_s`` doubling up
to ``restart_backoff_max_s``), at most ``max_restarts`` times per service; each crash and
each restart is published as an ``event`` (kinds ``fault`` and ``restart``, source
``launcher``) and written to ``events.jsonl``. A restarted service gets
``--incarnation N`` (its files that would overwrite the first run's get a suffix) and,
for the adapter, the same posterior checkpoint (default ``<out>/adapter_checkpoint.npz``),
which it restores. The vehicle link is not restarted: its process *is* the vehicle (the
simulator's physics state); the flight ends when it ends or says ``flight finished`` (a
simulated PX4 outlives its plan until stopped, so that the bridge's Hold is answered);
:meth:`Stack.wait` returns its exit code (0 on ``flight finished``), :class:`StackError`
when a service runs out of restarts. :attr:`Stack.alive` is the set of services whose
liveliness token is visible on the bus (a crashed process's token disappears with its
session).

Stop: SIGINT to every service in data-flow order (vehicle link first: in the px4 profile
the bridge, then the simulated PX4; the recorder last so it records the end), then SIGTERM
and SIGKILL for those that do not exit in time.

Run folder (``--out``): ``logs/<service>.log`` (each service's log), ``logs/<service>.out``
(its stdout/stderr), ``stats/<service>.json``, ``events.jsonl`` (every event seen by the
launcher), ``truth.csv`` (simulator ground truth), ``flight_log.csv`` and ``bus.mcap``
(recorder). :class:`StackConfig` makes the run folder, the weights file, the checkpoint and
the bus configuration files absolute (relative to the caller's working directory) when it
is built. The services run in the caller's working directory too (with ``python -P``, so
that folder's modules do not shadow the stack's), so a relative path inside a bus
configuration file resolves the same for every process. A :class:`StackError` names the run's
``logs/`` folder and quotes the last output of the process that failed.

Bus: by default every process (and the launcher's own session) is a peer on loopback that
meets the others through ``hub``. With ``StackConfig.bus_configs`` each one opens the Zenoh
configuration file given for it instead (``--bus-config``), e.g. a client of an ACL router
with its own user and password (``deploy/zenoh/router-acl.json5``, which expects the
launcher as user ``launcher``); the router must be up before the stack starts. With
``StackConfig.credentials`` (``arcade up`` and ``arcade demo`` on their own hub) the launcher
makes a password for the run, and every process, its own sessions included, opens the peer
configuration that carries it (``<out>/bus/peer.json5``, owner-only, removed at stop).

The options are :class:`StackConfig` (:mod:`deploy.stack_config`); stopping a process, the
signals around a stop and a process's last output are :mod:`deploy.processes`. This module
exports what ``arcade up`` and scripts use: :class:`Stack`, :func:`run_flight`,
:class:`StackConfig`, :class:`StackError`, :func:`last_output`, :func:`sigterm_interrupts`.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from arcade_io import jsonout
from deploy.processes import end_process, interrupts_deferred, last_output, sigterm_interrupts
from deploy.stack_config import PROFILES, SERVICES, STOP_ORDER, StackConfig

__all__ = [
    "EVENTS_KEPT",
    "REPO",
    "SERVICES",
    "VEHICLE",
    "Stack",
    "StackConfig",
    "StackError",
    "last_output",
    "run_flight",
    "sigterm_interrupts",
]

REPO = Path(__file__).resolve().parents[1]
#: Event records kept in memory (``Stack.events``, the newest; ``events.jsonl`` has them
#: all): a PX4 flight alone sends a ``vehicle_status`` event twice a second.
EVENTS_KEPT = 10_000


class StackError(RuntimeError):
    """A service failed to start, gave up restarting, or the vehicle link died."""


#: The process whose end is the end of the flight (never restarted: it is the vehicle).
VEHICLE = "sim"


class Stack:
    """The running stack; use as a context manager (stops everything on exit).

    ``on_event`` (optional) is called with every event record (bus events and the
    supervisor's own), from a background thread.
    """

    def __init__(
        self,
        config: StackConfig,
        services: tuple[str, ...] | None = None,
        on_event: Callable[[dict[str, Any]], None] | None = None,
    ):
        if config.profile not in PROFILES:
            raise ValueError(f"unknown profile {config.profile!r} (one of {PROFILES})")
        if config.profile == "px4" and not hasattr(config, "vehicle_process"):
            raise ValueError("profile px4 takes a deploy.px4_profile.Px4StackConfig")
        problem = config.bus_config_problem(services if services is not None else config.services())
        if problem is not None:
            raise ValueError(problem)
        #: The vehicle link process (profile px4: see deploy.px4_profile).
        self.vehicle_process: str = getattr(config, "vehicle_process", VEHICLE)
        self.config = config
        self.services = services if services is not None else config.services()
        self.procs: dict[str, subprocess.Popen] = {}
        self.restarts: dict[str, int] = dict.fromkeys(self.services, 0)
        #: The newest :data:`EVENTS_KEPT` event records; ``events_dropped`` counts the older.
        self.events: deque[dict[str, Any]] = deque(maxlen=EVENTS_KEPT)
        self.events_dropped = 0
        self._events_lock = threading.Lock()
        #: Why ``events.jsonl`` is no longer written (a full disk), or None.
        self.events_file_error: str | None = None
        self._on_event_cb = on_event
        self._bus: Any = None
        self._seen: set[str] = set()  # services whose token appeared at least once
        self._env: dict[str, str] = {}
        self._stopping = threading.Event()
        self._changed = threading.Condition()  # a process ended or the supervisor gave up
        self._failed: str | None = None
        self._failed_service: str | None = None
        self._finished = False  # the vehicle process said "flight finished"
        self._event_stamp = 0.0
        self.last_stamp = 0.0
        self.out = Path(config.out)

    # -- lifecycle
    def start(self) -> Stack:
        # Zenoh loads when a stack starts, not when the command line imports this module.
        import zenoh

        from services.bus import Bus, zenoh_reason

        (self.out / "logs").mkdir(parents=True, exist_ok=True)
        self.config.make_credentials()  # with credentials: this run's password, every process
        bus_config = self.config.bus_config("launcher")  # ValueError naming a bad file
        if self.config.checkpoint is None:  # the run's own checkpoint: for restarts only
            self.config.checkpoint_path().unlink(missing_ok=True)
        try:
            self._bus = Bus(self.config.vehicle, "launcher", bus_config).open()
        except zenoh.ZError as err:
            self.config.remove_credentials()
            path = self.config.bus_configs.get("launcher")
            where = f"bus config {path}" if path is not None else "peer session"
            raise StackError(
                f"launcher: could not open the bus ({where}): {zenoh_reason(err)}"
            ) from None
        self._bus.on_alive_change(self._on_alive_change)
        self._bus.subscribe("event", self._on_event, check_order=False)
        self._bus.subscribe("state", self._on_state, check_order=False)
        self._bus.publisher("event")
        # Services run in the caller's folder, as the launcher does: a relative path in a
        # bus configuration (a TLS certificate) means the same file to every process.
        self._cwd = Path.cwd()
        env = dict(os.environ)
        env.setdefault("JAX_PLATFORMS", "cpu")
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
        self._env = env
        for name in self.services:
            self._spawn(name)
        return self

    def _spawn(self, name: str) -> None:
        self._seen.discard(name)  # ready again only once this incarnation says so
        n = self.restarts[name]
        cmd = [
            sys.executable,
            "-P",  # the caller's folder is not on sys.path: its modules do not shadow ours
            "-m",
            "services",
            name,
            *self.config.args(name),
            *self.config.bus_args(name),
        ]
        if n:
            cmd += ["--incarnation", str(n)]
        with (self.out / "logs" / f"{name}.out").open("a" if n else "w") as log:
            proc = subprocess.Popen(
                cmd,
                cwd=self._cwd,
                env=self._env,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )  # Ctrl-C goes to the launcher, which stops them
        self.procs[name] = proc
        threading.Thread(
            target=self._watch, args=(name, proc), daemon=True, name=f"watch-{name}"
        ).start()

    def _watch(self, name: str, proc: subprocess.Popen) -> None:
        """Wait for ``proc`` to end; restart it (back-off) unless the stack is stopping."""
        code = proc.wait()
        with self._changed:
            self._changed.notify_all()
        if self._stopping.is_set() or name == self.vehicle_process:
            return
        n = self.restarts[name]
        how = f"killed by signal {-code}" if code < 0 else f"exited with code {code}"
        if n >= self.config.max_restarts:
            with self._changed:
                if self._failed is None:
                    self._failed = f"service {name} {how} (after {n} restarts)"
                    self._failed_service = name
                self._changed.notify_all()
            self.emit(
                "fault",
                f"{name} {how}; no restart left ({n} used): stopping",
                "critical",
                service=name,
                code=code,
                restarts=n,
            )
            return
        delay = min(self.config.restart_backoff_s * 2.0**n, self.config.restart_backoff_max_s)
        self.emit(
            "fault",
            f"{name} {how}: restarting in {delay:.1f} s",
            "error",
            service=name,
            code=code,
            restarts=n,
            backoff_s=delay,
        )
        if self._stopping.wait(delay):
            return
        self.restarts[name] = n + 1
        self._spawn(name)
        self.emit(
            "restart",
            f"{name} restarted (restart {n + 1} of {self.config.max_restarts})",
            "warning",
            service=name,
            restarts=n + 1,
            pid=self.procs[name].pid,
        )

    # -- events
    def emit(self, kind: str, text: str, severity: str = "info", **data: Any) -> None:
        """Publish a supervisor event on the bus and record it (``events.jsonl``)."""
        from services.messages import Event  # loaded with the first event (start-up cost)

        stamp = self._event_stamp = max(self._event_stamp, self.last_stamp)
        rec = {
            "stamp": stamp,
            "src": "launcher",
            "kind": kind,
            "severity": severity,
            "text": text,
            "data": data,
        }
        self._record(rec)
        bus = self._bus
        if bus is not None:
            with contextlib.suppress(Exception):  # the bus may close under a late watcher
                bus.put(Event(kind=kind, severity=severity, text=text, data=data, stamp=stamp))

    def _record(self, rec: dict[str, Any]) -> None:
        recs = [rec]
        with self._events_lock:
            self._keep(rec)
            if self.events_file_error is None:
                try:
                    with (self.out / "events.jsonl").open("a") as f:
                        f.write(jsonout.dumps(rec) + "\n")
                except OSError as err:  # a full disk must not stop the supervision
                    self.events_file_error = str(err)
                    lost = {
                        **rec,
                        "src": "launcher",
                        "kind": "fault",
                        "severity": "error",
                        "text": f"cannot write events.jsonl: {err.strerror or err}; events "
                        f"from here on are only shown (and the newest {EVENTS_KEPT} kept in "
                        "Stack.events)",
                        "data": {"file": str(self.out / "events.jsonl")},
                    }
                    self._keep(lost)
                    recs.append(lost)
        if self._on_event_cb is not None:
            for r in recs:
                with contextlib.suppress(Exception):
                    self._on_event_cb(r)

    def _keep(self, rec: dict[str, Any]) -> None:
        if len(self.events) == self.events.maxlen:
            self.events_dropped += 1
        self.events.append(rec)

    def _on_event(self, e: Any) -> None:
        if e.src.startswith("launcher/"):
            return  # our own, recorded when emitted
        self._record(
            {
                "stamp": e.stamp,
                "src": e.src,
                "kind": e.kind,
                "severity": e.severity,
                "text": e.text,
                "data": dict(e.data),
            }
        )
        # After recording: what wait() returns to must already hold this event.
        if e.text == "flight finished" and e.src.split("/")[0] == self.vehicle_process:
            with self._changed:
                self._finished = True
                self._changed.notify_all()

    def _on_state(self, s: Any) -> None:
        self.last_stamp = s.stamp

    @property
    def failed(self) -> str | None:
        """Why the supervisor gave up (a service out of restarts), or None."""
        return self._failed

    @property
    def alive(self) -> frozenset[str]:
        """Services whose liveliness token is visible on the bus right now."""
        return self._bus.alive if self._bus is not None else frozenset()

    def _error(self, what: str, service: str | None) -> StackError:
        """``what`` happened to ``service``: the error names the logs and quotes its output."""
        text = f"{what}; see {self.out / 'logs'}"
        tail = last_output(self.out, service) if service is not None else []
        if tail:
            text += f"\n  last output of {service}:\n" + "\n".join(f"    {r}" for r in tail)
        return StackError(text)

    def _check_alive(self) -> None:
        if self._failed is not None:
            raise self._error(self._failed, self._failed_service)
        name = self.vehicle_process
        sim = self.procs.get(name)
        if sim is not None and sim.poll() is not None and not self._stopping.is_set():
            code = sim.returncode
            how = f"killed by signal {-code}" if code < 0 else f"exited with code {code}"
            raise self._error(f"vehicle process {name} {how}", name)

    def wait_alive(self, services: Iterable[str], timeout: float) -> None:
        """Block until each of ``services`` has a liveliness token on this vehicle."""
        if self._bus is None:
            raise StackError("the stack is not started")
        self._bus.wait_alive(services, timeout)

    def _on_alive_change(self, service: str, up: bool) -> None:
        if up:
            self._seen.add(service)

    def wait_ready(self, timeout: float | None = None) -> float:
        """Block until every service declared its liveliness token; returns seconds.

        A service whose current incarnation was ready and has left since counts as ready:
        a short lockstep flight can be over (its vehicle process ended with code 0) before
        the caller asks.
        """
        timeout = self.config.ready_timeout if timeout is None else timeout
        t0 = time.monotonic()
        pending = set(self.services)
        while True:
            pending -= self._bus.alive | set(self._seen)
            if not pending:
                break
            left = timeout - (time.monotonic() - t0)
            if left <= 0:
                raise StackError(f"not ready after {timeout:.0f} s: {sorted(pending)}")
            self._check_alive()
            with contextlib.suppress(TimeoutError):  # short slices: notice a dead service
                self._bus.wait_alive(pending, timeout=min(left, 0.5))
        return time.monotonic() - t0

    def wait(
        self, timeout: float | None = None, progress: Callable[[float], None] | None = None
    ) -> int:
        """Wait for the vehicle process (the flight) to end; returns its exit code, or 0
        once it said ``flight finished`` (a vehicle may outlive its plan until stopped,
        e.g. ``px4sim`` answering the bridge's Hold: :meth:`stop` stops the bridge first).

        Crashed services are restarted meanwhile; :class:`StackError` when one has no
        restart left.
        """
        t0 = time.monotonic()
        sim = self.procs.get(self.vehicle_process)
        if sim is None:
            raise StackError("no vehicle process to wait for")
        while True:
            with self._changed:  # woken by any process end; 0.5 s slices for progress
                self._changed.wait_for(
                    lambda: sim.poll() is not None or self._failed is not None or self._finished,
                    0.5,
                )
            code = sim.poll()
            if code is not None:
                break
            if self._finished:
                code = 0
                break
            if self._failed is not None:
                raise self._error(self._failed, self._failed_service)
            if progress is not None:
                progress(self.last_stamp)
            if timeout is not None and time.monotonic() - t0 > timeout:
                raise StackError(f"flight not finished after {timeout:.0f} s")
        if progress is not None:
            progress(self.last_stamp)
        return code

    def kill(self, service: str, sig: int = signal.SIGKILL) -> int:
        """Send ``sig`` to a service (fault injection); returns its pid."""
        proc = self.procs[service]
        proc.send_signal(sig)
        return proc.pid

    def stop(self, grace: float = 20.0) -> dict[str, int | None]:
        """SIGINT everything (data-flow order), then SIGTERM/SIGKILL stragglers.

        Every service is signalled and reaped whatever happens meanwhile: a Ctrl-C or
        SIGTERM that arrives during the stop only cuts the grace periods short (no more
        waiting for a clean exit), and is delivered once every service has ended.
        """
        self._stopping.set()
        with interrupts_deferred() as hurry:
            try:
                order = getattr(self.config, "stop_order", STOP_ORDER)
                # The processes that only listen (e.g. foxglove) first, then the data flow.
                for name in (*(n for n in self.procs if n not in order), *order):
                    p = self.procs.get(name)
                    if p is None or p.poll() is not None:
                        continue
                    try:
                        end_process(p, grace, hurry)
                    except Exception as err:  # the next services must be stopped still
                        print(f"could not stop {name}: {err}", file=sys.stderr)
            finally:
                if self._bus is not None:
                    bus, self._bus = self._bus, None
                    bus.close()
                self.config.remove_credentials()
        return {name: p.returncode for name, p in self.procs.items()}

    def __enter__(self) -> Stack:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def run_flight(
    config: StackConfig,
    progress: Callable[[str], None] = lambda m: None,
    on_time: Callable[[float], None] | None = None,
    timeout: float | None = None,
    on_event: Callable[[dict[str, Any]], None] | None = None,
    on_ready: Callable[[Stack], None] | None = None,
) -> dict[str, Any]:
    """Start the stack, fly the plan to the end, stop; returns codes, events and timings.

    ``on_event``: see :class:`Stack`; ``on_ready(stack)`` runs once every service is up
    (fault injection hooks in here).
    """
    config.out.mkdir(parents=True, exist_ok=True)
    with Stack(config, on_event=on_event) as stack:
        progress("starting services (compiling on first use) ...")
        ready_s = stack.wait_ready()
        progress(f"all services ready after {ready_s:.1f} s; flying")
        if on_ready is not None:
            on_ready(stack)
        t0 = time.monotonic()
        sim_code = stack.wait(timeout=timeout, progress=on_time)
        flight_s = time.monotonic() - t0
        codes = stack.stop()
    if codes.get(stack.vehicle_process) is None:
        codes[stack.vehicle_process] = sim_code
    return {
        "codes": codes,
        "events": list(stack.events),
        "ready_s": ready_s,
        "flight_wall_s": flight_s,
        "out": str(config.out),
        "restarts": {k: v for k, v in stack.restarts.items() if v},
    }
