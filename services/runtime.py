"""Shared scaffolding of the service processes (``python -m services <name> ...``).

Every service is a :class:`Service`: common command-line options (:func:`common_parser`),
a log file per service (``<out>/logs/<name>.log``), JAX set-up (persistent compilation
cache, optional float64, synchronous dispatch for small low-latency calls), a warm-up
(compile everything) *before* the liveliness token is declared, and a clean shutdown on
SIGINT/SIGTERM (or a ``shutdown`` command on the bus). Statistics a service wants to
report (latencies, counters) go to ``<out>/stats/<name>.json`` at exit.

The bus session: by default a peer on loopback that meets the others through ``--hub``
(:func:`services.bus.peer_config`); with ``--bus-config FILE`` the Zenoh configuration in
``FILE`` instead, e.g. a client of a router with its user/password or TLS settings
(``deploy/zenoh/router-acl.json5``). A message a pinned subscription refuses (another
session than its writer's, :class:`services.reception.SourcePins`) is counted, and the
service raises one ``fault`` event per refused session and topic.
"""

from __future__ import annotations

import argparse
import faulthandler
import gc
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

from arcade_io import atomicfile, jsonout, signals
from services.bus import DEFAULT_HUB, Bus, peer_config, read_config, zenoh_reason
from services.options import common_parser, link_delay_problem
from services.timing import GcPauses, cpu_wakeup_latency, realtime_scheduling

log = logging.getLogger("arcade.service")


def bus_config(args: argparse.Namespace) -> Any:
    """The Zenoh configuration of a service's session: ``--bus-config`` if given (a
    ``ValueError`` naming the file if it cannot be read), else a peer on ``--hub``."""
    path = getattr(args, "bus_config", None)
    if path is not None:
        return read_config(path)
    hub = getattr(args, "hub", None)
    return peer_config(hub if hub is not None else DEFAULT_HUB)


def setup_logging(name: str, out: Path | None, level: str = "INFO") -> Path | None:
    """Log to ``<out>/logs/<name>.log`` (and stderr); returns the file path."""
    root = logging.getLogger()
    root.setLevel(level.upper())
    fmt = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
    err = logging.StreamHandler(sys.stderr)
    err.setFormatter(fmt)
    err.setLevel(logging.WARNING)
    root.addHandler(err)
    path = None
    if out is not None:
        path = Path(out) / "logs" / f"{name}.log"
        path.parent.mkdir(parents=True, exist_ok=True)
        fh = logging.FileHandler(path)
        fh.setFormatter(fmt)
        root.addHandler(fh)
    return path


def setup_jax(x64: bool) -> None:
    """Persistent cache, precision and synchronous dispatch (faster for small calls)."""
    from arcade_io import jaxsetup

    jaxsetup.configure(x64=x64)
    import jax

    jax.config.update("jax_cpu_enable_async_dispatch", False)


class _SeqOnly:
    """``receiver`` (without order checks) plus a per-publisher increasing-``seq`` check,
    counting what it accepts and the sequence numbers skipped (messages lost)."""

    def __init__(self, receiver: Any, max_publishers: int = 64):
        self.receiver, self.max_publishers = receiver, max_publishers
        self._last: dict[str, int] = {}
        self._lock = threading.Lock()
        self.accepted = 0
        self.gaps = 0

    def __call__(self, payload: bytes) -> Any:
        from services.messages import MessageError, Reason

        record = self.receiver(payload)
        with self._lock:
            prev = self._last.pop(record.src, None)  # re-inserted below: least recently used
            if prev is not None and record.seq <= prev:
                self._last[record.src] = prev
                raise MessageError(
                    Reason.OUT_OF_ORDER, f"seq {record.seq} after {prev} from {record.src!r}"
                )
            if prev is not None:
                self.gaps += record.seq - prev - 1
            self._last[record.src] = record.seq
            if len(self._last) > self.max_publishers:
                self._last.pop(next(iter(self._last)))
            self.accepted += 1
        return record

    def stats(self) -> dict[str, int]:
        with self._lock:
            return {"accepted": self.accepted, "gaps": self.gaps}


def subscribe_ordered(
    bus: Bus,
    topics: dict[str, Any],
    seq_only: tuple[str, ...] = (),
    transit: dict[str, Any] | None = None,
    sources: dict[str, str] | None = None,
) -> list[Any]:
    """Subscribe ``{topic: callback}`` with callbacks run on Zenoh's receiving thread.

    :meth:`Bus.subscribe` runs each subscription's callback on its own thread, so two
    topics from one publisher (mocap frames, then the control-instant imu sample) may be
    handled out of order. Here the callbacks run in arrival order (Zenoh keeps order per
    priority on a link); they must be quick (enqueue, or a few hundred microseconds of work).
    Validation and reject counting are those of :meth:`Bus.subscribe`, except that the
    topics in ``seq_only`` are order-checked on ``seq`` alone: their stamps are judged by
    the service (a jumped sensor clock must reach the estimator, which re-stamps it).
    With ``transit``, each topic's bus transit times (see :mod:`services.bus`) are appended
    to ``transit[topic]`` (a bounded deque). ``sources``: ``{topic: service}`` accepted only
    from that service's session (``source=`` of :meth:`Bus.subscribe`).
    """
    from collections import deque

    import zenoh

    from services.bus import TRANSIT_SAMPLES, transit_time
    from services.reception import Receiver, safe_handler

    subs = []
    for topic, callback in topics.items():
        receiver: Any
        if topic in seq_only:
            receiver = _SeqOnly(Receiver(topic, check_order=False))
            bus.track_stream(topic, receiver)
        else:
            receiver = Receiver(topic)
            bus.track_stream(topic, receiver.checker)
        hops = None
        if transit is not None:
            hops = transit.setdefault(topic, deque(maxlen=TRANSIT_SAMPLES))

        def decode(sample, r=receiver, hops=hops, topic=topic):
            if hops is not None and (hop := transit_time(sample)) is not None:
                hops.append(hop)
            if sources and topic in sources:
                bus.check_source(topic, sources[topic], sample)
            return r(sample.payload.to_bytes())

        handler = safe_handler(decode, callback, bus.rejects, topic=topic)
        subs.append(
            bus.session.declare_subscriber(
                bus.key(topic), zenoh.handlers.Callback(handler, indirect=False)
            )
        )
    return subs


class BusOpenError(RuntimeError):
    """The bus session of a service cannot be opened (its configuration or its links)."""


class StatsNotWritten(RuntimeError):
    """``stats/<service>.json`` could not be written (the message says where and why)."""


class Service:
    """Base of a service process: subclasses implement :meth:`setup` and may override
    :meth:`warmup`, :meth:`main` (default: wait for the stop signal) and :meth:`teardown`.
    """

    name = "service"
    #: Whether the service says its command line in a ``ready`` event once it serves (the
    #: recording then tells ``arcade replay`` how it ran).
    announce_options = False
    #: The command line the service was started with (:func:`main_for`).
    argv: list[str] | None = None
    #: Whether the service computes with JAX (its cache and precision set up at start);
    #: one that does not never imports it, and starts in a fraction of the time.
    uses_jax = True

    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.stop = threading.Event()
        self.out: Path | None = args.out
        self.stats: dict[str, Any] = {}
        self.log = logging.getLogger(f"arcade.{self.name}")
        self.bus: Bus | None = None
        self._gc: GcPauses | None = None
        self._pm_qos: int | None = None  # the CPU wake-up latency request, while open

    # -- hooks
    def setup(self, bus: Bus) -> None:
        """Declare publishers/subscriptions (before the liveliness token)."""

    def warmup(self) -> None:
        """Compile everything so that the first real message is served on time."""

    def ready(self) -> None:
        """Called right after the liveliness token is declared (announcements go here)."""

    def main(self) -> None:
        """The service's own loop; the default just waits for the stop signal."""
        self.stop.wait()

    def teardown(self) -> None:
        """Release resources (after the loop ended, bus still open)."""

    # -- helpers
    def now(self) -> float:
        return time.monotonic()

    def event(
        self, kind: str, text: str, severity: str = "info", stamp: float | None = None, **data: Any
    ) -> None:
        """Publish an :class:`~services.messages.Event` and log it."""
        from services.messages import Event

        level = {"debug": 10, "info": 20, "warning": 30, "error": 40, "critical": 50}[severity]
        self.log.log(level, "event %s: %s %s", kind, text, data or "")
        if self.bus is None:
            return
        if stamp is None:  # lockstep stamps are simulated time, which starts at 0
            stamp = 0.0 if getattr(self.args, "lockstep", False) else self.now()
        # Never older than the previous event: receivers reject out-of-order stamps.
        stamp = self._event_stamp = max(stamp, self._event_stamp)
        try:
            self.bus.put(
                Event(kind=kind, severity=severity, text=text[:1024], data=data, stamp=stamp)
            )
        except Exception:
            self.log.exception("could not publish event %s", kind)

    _event_stamp = 0.0

    def _on_command(self, cmd: Any) -> None:
        if cmd.name == "shutdown" and cmd.target in ("", self.name):
            self.log.info("shutdown command received")
            self.stop.set()
        else:
            self.on_command(cmd)

    def _on_foreign(self, topic: str, service: str, session: str) -> None:
        text = f"{topic} from a session that is not the {service}'s refused (foreign_publisher)"
        self.event("fault", text, "error", topic=topic, source=service, session=session)

    def on_command(self, cmd: Any) -> None:
        """Commands other than ``shutdown`` (default: ignored)."""

    def write_stats(self) -> None:
        """``<out>/stats/<name>.json``: :attr:`stats` plus the bus counts: ``rejects`` (by
        reason), ``rejects_by_topic`` (topic -> reason -> n), ``callback_failures`` (topic
        -> n: this service failed on a valid message) and ``streams`` (topic ->
        ``accepted``, ``gaps``: messages lost on the way, ``reanchored``)."""
        if self.out is None:
            return
        if self._gc is not None:
            self.stats["gc_pauses"] = self._gc.summary()
        stats = dict(self.stats)
        if self.bus is not None:
            rejects = self.bus.rejects
            stats["rejects"] = rejects.counts
            by_topic: dict[str, dict[str, int]] = {}
            for (topic, reason), n in sorted(rejects.by_topic.items()):
                by_topic.setdefault(topic, {})[reason] = n
            stats["rejects_by_topic"] = by_topic
            stats["callback_failures"] = rejects.failures
            stats["streams"] = self.bus.stream_stats()
        path = Path(self.out) / "stats" / f"{self.name}.json"
        try:
            atomicfile.write_text(path, jsonout.dumps(stats, indent=1, default=float))
        except OSError as err:  # a full disk after the flight: one line, not a traceback
            raise StatsNotWritten(
                f"cannot write {path}: {err.strerror or err}; this run's statistics of "
                f"{self.name} are lost"
            ) from None

    # -- lifecycle
    def _open_bus(self) -> Bus:
        """This service's bus, open (:class:`BusOpenError` if it cannot be)."""
        import zenoh

        try:
            config = bus_config(self.args)
        except ValueError as err:
            raise BusOpenError(str(err)) from None
        lockstep = bool(getattr(self.args, "lockstep", False))
        bus = Bus(self.args.vehicle, self.name, config, lossless=lockstep)
        try:
            return bus.open()
        except zenoh.ZError as err:
            path = getattr(self.args, "bus_config", None)
            where = f"bus config {path}" if path is not None else "peer session"
            raise BusOpenError(f"could not open the bus ({where}): {zenoh_reason(err)}") from None

    def run(self) -> int:
        """Set up, warm up, announce liveliness, run, shut down cleanly. Returns an exit code."""
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: signals.set_from_handler(self.stop))
        watch_parent(self.stop, self.log)
        t0 = time.perf_counter()
        code = 0
        try:
            with self._open_bus() as bus:
                self.bus = bus
                bus.on_foreign(self._on_foreign)
                bus.subscribe("command", self._on_command)
                bus.publisher("event")  # declared now, not on the first (timed) event
                self.setup(bus)
                try:
                    self._serve(bus, t0)
                finally:
                    self.stop.set()
                    self._shut_down(bus)
        except BusOpenError as err:
            self.log.error("%s", err)
            code = 1
        except Exception:
            self.log.exception("%s failed", self.name)
            code = 1
        finally:
            logging.shutdown()
        return 1 if self._stats_lost else code

    def _serve(self, bus: Bus, t0: float) -> None:
        """Warm up, announce liveliness (unless a stop came meanwhile) and run."""
        self.warmup()
        if self.stop.is_set():  # a signal or shutdown during warm-up: never ready
            self.log.info("stop requested during warm-up: not announcing ready")
            return
        # Everything imported and compiled so far (JAX, Zenoh, MuJoCo: millions of
        # objects) lives as long as the process: out of the collector's sight, a
        # full collection takes a few milliseconds instead of ~100 ms (a stall of
        # five control periods at 50 Hz).
        gc.collect()
        gc.freeze()
        self._gc = GcPauses()  # the pauses while serving
        if getattr(self.args, "realtime_priority", 0):
            self.stats["scheduling"] = realtime_scheduling(self.args.realtime_priority, self.log)
        if getattr(self.args, "cpu_wakeup_latency_us", None) is not None:
            self._pm_qos, self.stats["cpu_wakeup_latency"] = cpu_wakeup_latency(
                self.args.cpu_wakeup_latency_us, self.log
            )
        self._serving = True
        bus.declare_alive()
        # CPU the process used to get here (imports, tracing, cache reads): what a stack
        # start costs the host, whatever else runs on it.
        self.stats["ready_cpu_s"] = round(time.process_time(), 3)
        self.log.info(
            "ready after %.1f s (%.1f s of CPU)",
            time.perf_counter() - t0,
            self.stats["ready_cpu_s"],
        )
        if self.announce_options and self.argv is not None:
            self._announce(self.argv)
        self.ready()
        self.main()

    def _announce(self, argv: list[str]) -> None:
        """The ``ready`` event with the command line (an event's text holds 1024
        characters: a longer one is said in the log only)."""
        import shlex

        line = shlex.join(argv)
        if len(line) > 1024:
            self.log.warning("command line of %d characters: not announced", len(line))
            return
        self.event("ready", line, service=self.name)

    _serving = False  # warm-up done, liveliness declared
    _stats_lost = False  # stats/<name>.json could not be written: the exit code says so

    def _shut_down(self, bus: Bus) -> None:
        """Teardown (if the service got to serve), statistics, then the process-wide
        requests: each step runs even when an earlier one raised (the first error
        propagates afterwards)."""
        try:
            if self._serving:
                self.teardown()
        finally:
            try:
                self.write_stats()
            except StatsNotWritten as err:  # said here: a teardown error may propagate
                self.log.error("%s", err)
                self._stats_lost = True
            finally:
                if self._gc is not None:
                    self._gc.close()
                if self._pm_qos is not None:
                    os.close(self._pm_qos)  # withdraws the request
                    self._pm_qos = None
                self.log.info(
                    "stopped; rejects %s, callback failures %s",
                    bus.rejects.counts,
                    bus.rejects.failures,
                )


def watch_parent(
    stop: threading.Event, log: logging.Logger = log, interval: float = 0.5
) -> threading.Thread:
    """Set ``stop`` when this process's parent (the launcher) exits.

    Services run in their own session (a Ctrl-C reaches only the launcher), so a launcher
    killed without its shutdown would leave them running. A parent-pid watch rather than
    ``PR_SET_PDEATHSIG``: that signal follows the parent *thread* that forked, and the
    launcher restarts services from short-lived watcher threads.
    """
    parent = os.getppid()

    def watch() -> None:
        while not stop.wait(interval):
            if os.getppid() != parent:
                log.warning("parent process %d exited: stopping", parent)
                stop.set()

    thread = threading.Thread(target=watch, daemon=True, name="parent-watch")
    thread.start()
    return thread


def main_for(
    cls: type[Service], argv: list[str] | None = None, extra: Any = None, *, x64: bool = False
) -> int:
    """Parse the options of ``cls`` (``extra(parser)`` adds its own) and run it.

    ``x64`` forces float64 whatever ``--x64`` says (for numerics that need it).
    """
    parser = common_parser(cls.name, (cls.__doc__ or "").strip().splitlines()[0])
    if extra is not None:
        extra(parser)
    args = parser.parse_args(argv)
    if args.bus_config is not None and args.hub is not None:
        parser.error("--hub and --bus-config exclude each other (the file names the endpoints)")
    problem = link_delay_problem(getattr(args, "link_delay", 0.0), args.rate)
    if problem is not None:
        parser.error(problem)
    setup_logging(cls.name, args.out, args.log_level)
    # `kill -USR1 <pid>` writes every thread's Python stack to stderr (<service>.out):
    # what a hung service is doing, without stopping it.
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    if args.nice:
        try:
            os.nice(args.nice)
        except OSError as err:
            log.warning("could not change the priority by %d: %s", args.nice, err)
    if getattr(cls, "uses_jax", True):  # Service says (True unless it computes nothing)
        setup_jax(args.x64 or x64)
    service = cls(args)
    service.argv = list(sys.argv[1:] if argv is None else argv)
    code = service.run()
    # Shut down: a stop request arriving now is moot. Ignored, not left to the interpreter,
    # which resets a Python-handled SIGINT/SIGTERM to the default action as it exits, so
    # that the launcher's SIGINT racing a vehicle process that ends its flight by itself
    # would kill it (exit -2) instead of letting it return its code.
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    return code
