"""Eclipse Zenoh bus of the service stack: configurations, key expressions, QoS, :class:`Bus`.

Key expressions are ``arcade/<vehicle>/<topic>`` (topics: :data:`~services.messages.TOPICS`)
and liveliness tokens ``arcade/<vehicle>/alive/<service>``; one vehicle name per vehicle
lets several vehicles share a bus.

Readiness protocol (no sleeps): a service declares its subscriptions first and its
liveliness token last (:meth:`Bus.declare_alive`). Declarations travel in order on a link,
so a peer that sees the token (:meth:`Bus.wait_alive`) knows the subscriptions are in
place and its next ``put`` is delivered.

Default configuration (:func:`peer_config`, ``deploy/zenoh/peer-loopback.json5``): peer
mode on loopback, multicast scouting off, no router. Every peer tries to listen on one
well-known *hub* endpoint (``tcp/127.0.0.1:7450``; failing to bind it is not an error),
listens on an ephemeral loopback port and connects to the hub. Whichever process starts
first owns the hub; gossip then tells every peer about the others' ephemeral endpoints and
they link directly (peers do not route for each other). If the hub owner exits, the next
peer to start binds the hub port and the others reconnect to it. Several independent stacks
on one machine need different hub ports. With ``credentials`` every link authenticates
with one user and password (Zenoh ``transport/auth/usrpwd``; ``arcade up`` makes them per
run): a process without them cannot join.

Source pinning: each publisher puts its Zenoh entity id on every sample (source info), and
each session declares ``arcade/<vehicle>/alive/<service>/<session id>`` when it opens. A
subscription with ``source=`` accepts only samples of the session that token names
(:class:`~services.reception.SourcePins`); the rest are rejected as ``foreign_publisher``.

Bus latency: every ``put`` carries its ``time.monotonic()`` as an 8-byte Zenoh
attachment (outside the message, so the schemas stay as they are); each subscription
records the transit time of what it receives (:attr:`Subscription.transit_s`), one bus hop
measured on its own, independent of what a message's ``stamp`` means. Meaningful between
processes of one host (one monotonic clock).

Multi-host deployments use a router (``mode: "router"`` in a Python session, see
:func:`router_config`; ``zenohd`` is not on PyPI) and clients (:func:`client_config`, or a
JSON5 file per process read by :func:`read_config`: a service's ``--bus-config``) so that
the router's access control applies: ``deploy/zenoh/router-acl.json5`` lets each user put
only the topics its process writes (e.g. only the controller ``setpoint``). The readiness
protocol holds through a router: it forwards what one link declared in order.
"""

from __future__ import annotations

import logging
import math
import re
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Generic, TypeVar

import msgpack
import zenoh

from services.bus_config import *  # noqa: F403  # the configurations, re-exported
from services.bus_config import __all__ as _CONFIGS
from services.bus_config import peer_config
from services.messages import TOPICS, Message, MessageError, Reason, message_type
from services.reception import Receiver, RejectCounter, SourcePins, safe_handler

__all__ = [
    "QOS",
    "Bus",
    "Publisher",
    "QoS",
    "Subscription",
    "alive_key",
    "check_name",
    "key_expr",
    *_CONFIGS,
]

log = logging.getLogger("arcade.bus")

_NAME = re.compile(r"[A-Za-z0-9_.\-]{1,64}")
_ENCODING = "application/msgpack"

M = TypeVar("M", bound=Message)


# --------------------------------------------------------------------------- names


def check_name(kind: str, name: str) -> str:
    """``name`` if it is a valid ``kind`` name (a vehicle, a service) for a key-expression
    chunk: letters, digits, ``_``, ``.``, ``-`` (no ``/``, wildcards or ``$``); otherwise
    ``ValueError`` saying so."""
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise ValueError(f"invalid {kind} name {name!r} (letters, digits, '_', '.', '-')")
    return name


def key_expr(vehicle: str, topic: str) -> str:
    """``arcade/<vehicle>/<topic>``."""
    if topic not in TOPICS:
        raise ValueError(f"unknown topic {topic!r}; topics are {TOPICS}")
    return f"arcade/{check_name('vehicle', vehicle)}/{topic}"


def alive_key(vehicle: str, service: str) -> str:
    """Liveliness token ``arcade/<vehicle>/alive/<service>`` (``service`` may be ``*`` or
    ``**``)."""
    if service not in ("*", "**"):
        check_name("service", service)
    return f"arcade/{check_name('vehicle', vehicle)}/alive/{service}"


# ----------------------------------------------------------------------------- QoS


@dataclass(frozen=True)
class QoS:
    """Publication QoS of a topic."""

    priority: zenoh.Priority
    congestion_control: zenoh.CongestionControl
    express: bool


_DROP, _BLOCK = zenoh.CongestionControl.DROP, zenoh.CongestionControl.BLOCK
#: Per-topic QoS. The control path (mocap -> state -> setpoint) has the highest
#: priorities; streams drop on congestion (a newer sample supersedes a late one); events
#: and commands block rather than get lost. Nothing is ``express``: with eclipse-zenoh
#: 1.10, express samples sent just after a link came up were sometimes lost for good (a
#: few percent of fresh state/setpoint exchanges on a loaded machine, none without
#: express), and batches leave as soon as the link is idle, so express bought nothing
#: measurable on loopback (state -> setpoint round trip ~0.3-0.4 ms either way). Events
#: stay below every stream: the access-control tests' sentinel event arrives after what
#: was put before it. A lockstep service opens its bus ``lossless``: every topic then
#: blocks instead of dropping.
QOS: Mapping[str, QoS] = MappingProxyType(
    {
        "mocap": QoS(zenoh.Priority.INTERACTIVE_HIGH, _DROP, False),
        "imu": QoS(zenoh.Priority.INTERACTIVE_HIGH, _DROP, False),
        "state": QoS(zenoh.Priority.REAL_TIME, _DROP, False),
        "setpoint": QoS(zenoh.Priority.REAL_TIME, _DROP, False),
        "reference": QoS(zenoh.Priority.DATA, _DROP, False),
        "model": QoS(zenoh.Priority.DATA_HIGH, _DROP, False),
        "residual": QoS(zenoh.Priority.DATA, _DROP, False),
        "event": QoS(zenoh.Priority.DATA, _BLOCK, False),
        "command": QoS(zenoh.Priority.INTERACTIVE_HIGH, _BLOCK, False),
    }
)


# ------------------------------------------------------------------------------ bus


class Publisher(Generic[M]):
    """Publishes one topic: encodes records, assigns ``seq`` (from 1) and ``src``."""

    def __init__(self, bus: Bus, topic: str):
        self.topic = topic
        self.type: type[Message] = message_type(topic)
        self.key = bus.key(topic)
        self._src = bus.src
        qos = QOS[topic]
        self._pub = bus.session.declare_publisher(
            self.key,
            encoding=zenoh.Encoding(_ENCODING).with_schema(
                f"{self.type.SCHEMA}/{self.type.VERSION}"
            ),
            priority=qos.priority,
            congestion_control=_BLOCK if bus.lossless else qos.congestion_control,
            express=qos.express,
        )
        self._seq = 0
        self._lock = threading.Lock()
        #: This publisher's Zenoh entity id, put on every sample (an in-process stand-in
        #: session may have none).
        self._id = getattr(self._pub, "id", None)

    @property
    def seq(self) -> int:
        """``seq`` of the last record put (0: none yet)."""
        return self._seq

    def put(self, record: M) -> int:
        """Publish ``record``; its ``seq`` and ``src`` are replaced. Returns the ``seq``."""
        if type(record) is not self.type:
            raise TypeError(f"{self.topic} carries {self.type.__name__}, not {type(record)}")
        wire = record.to_wire()
        with self._lock:  # seq order == put order
            seq = self._seq + 1
            wire["seq"], wire["src"] = seq, self._src
            payload = msgpack.packb(wire, use_bin_type=True)
            if len(payload) > self.type.MAX_BYTES:
                # Not sent: the number stays free, so receivers count no lost message.
                raise MessageError(Reason.OVERSIZE, f"{len(payload)} > {self.type.MAX_BYTES}")
            source = zenoh.SourceInfo(self._id, seq) if self._id is not None else None
            self._pub.put(payload, attachment=_PUT_TIME.pack(time.monotonic()), source_info=source)
            self._seq = seq
            return seq

    def close(self) -> None:
        self._pub.undeclare()


#: The put time a publisher attaches to each sample (little-endian float64 seconds).
_PUT_TIME = struct.Struct("<d")
#: Transit times a subscription keeps (the newest ones).
TRANSIT_SAMPLES = 100_000


def source_session(sample: zenoh.Sample) -> str | None:
    """The Zenoh session id of the publisher of ``sample`` (its source info), or None."""
    info = getattr(sample, "source_info", None)
    return None if info is None else str(info.source_id.zid)


def transit_time(sample: zenoh.Sample) -> float | None:
    """Seconds from the publisher's ``put`` to now, from the attachment (None if absent)."""
    now = time.monotonic()
    att = getattr(sample, "attachment", None)
    raw = att.to_bytes() if att is not None else b""
    if len(raw) != _PUT_TIME.size:
        return None
    hop = now - _PUT_TIME.unpack(raw)[0]
    return hop if math.isfinite(hop) else None  # any sender may attach anything


class Subscription:
    """A validated subscription; ``receiver.checker`` holds per-publisher order stats and
    :attr:`transit_s` the bus transit time of each sample received (newest
    :data:`TRANSIT_SAMPLES`)."""

    def __init__(self, sub: Any, topic: str, receiver: Receiver, transit: deque[float]):
        self._sub, self.topic, self.receiver = sub, topic, receiver
        self.transit_s = transit

    def close(self) -> None:
        self._sub.undeclare()


class Bus:
    """One service's connection to the bus of one vehicle.

    Use as a context manager (or :meth:`open`/:meth:`close`)::

        with Bus("quad1", "controller", peer_config()) as bus:
            bus.subscribe("state", on_state)
            bus.declare_alive()                    # after the subscriptions
            bus.wait_alive(["estimator"], timeout=10.0)
            bus.put(Setpoint(u=u, state_seq=s.seq, stamp=s.stamp))

    Each subscription's callback runs on its own thread (Zenoh's default for Python
    callbacks), never on the caller's; every payload is validated and order-checked first,
    and nothing a payload or a callback does escapes: rejects and callback failures are
    counted in :attr:`rejects` and logged. Publishing from a callback is fine.
    """

    def __init__(
        self,
        vehicle: str = "default",
        name: str = "service",
        config: zenoh.Config | None = None,
        *,
        rejects: RejectCounter | None = None,
        lossless: bool = False,
    ):
        self.vehicle = check_name("vehicle", vehicle)
        #: Every topic blocks on congestion instead of dropping (lockstep: the simulator
        #: waits for each answer, and a lost sample would stall the loop for the step
        #: timeout; with ``DROP`` Zenoh discards a sample it cannot queue in time).
        self.lossless = lossless
        self.name = check_name("service", name)
        self.config = config
        self.rejects = rejects or RejectCounter(
            logger=logging.getLogger(f"arcade.bus.{name}"), service=name
        )
        self._session: zenoh.Session | None = None
        self._src = ""
        self._publishers: dict[str, Publisher[Any]] = {}
        self._subscriptions: list[Subscription] = []
        self._streams: list[tuple[str, Any]] = []  # (topic, order checker) per subscription
        self._tokens: dict[str, Any] = {}
        self._alive: set[str] = set()
        self._alive_listeners: list[Callable[[str, bool], None]] = []
        self._cond = threading.Condition()  # guards the liveliness view
        self._pub_lock = threading.Lock()
        #: The session each service speaks from (``source=`` subscriptions check it).
        self.pins = SourcePins()

    # -- lifecycle
    def open(self, session: Any = None) -> Bus:
        """Open the Zenoh session (idempotent) and start tracking liveliness.

        ``session``: use this already open session instead of opening one from
        :attr:`config` -- anything with the methods of ``zenoh.Session`` the bus calls, so
        an in-process stand-in can drive a service's handlers without a network. The bus
        closes it on :meth:`close`.
        """
        if self._session is None:
            if session is None:
                session = zenoh.open(self.config if self.config is not None else peer_config())
            self._session = session
            self._src = f"{self.name}/{session.zid()}"
            self._alive_sub = session.liveliness().declare_subscriber(
                alive_key(self.vehicle, "**"), self._on_alive, history=True
            )
            # Which session this service speaks from: declared at once, so that a
            # (restarted) service is pinned long before its first message.
            owner = f"{alive_key(self.vehicle, self.name)}/{session.zid()}"
            self._owner_token = session.liveliness().declare_token(owner)
        return self

    def close(self) -> None:
        """Withdraw tokens, undeclare everything and close the session."""
        if self._session is None:
            return
        session, self._session = self._session, None
        for token in self._tokens.values():
            token.undeclare()
        self._tokens.clear()
        self._owner_token.undeclare()
        with self._cond:
            self._alive.clear()
        self._publishers.clear()
        self._subscriptions.clear()
        session.close()

    def __enter__(self) -> Bus:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def session(self) -> zenoh.Session:
        """The underlying Zenoh session (raises if the bus is not open)."""
        if self._session is None:
            raise RuntimeError("bus is not open")
        return self._session

    @property
    def src(self) -> str:
        """Publisher id stamped on every message: ``<name>/<session id>``."""
        self.session  # noqa: B018  # raises when closed
        return self._src

    def key(self, topic: str) -> str:
        """Key expression of ``topic`` on this vehicle."""
        return key_expr(self.vehicle, topic)

    # -- data
    def publisher(self, topic: str) -> Publisher[Any]:
        """The (cached) publisher of ``topic``; one ``seq`` sequence per topic and bus."""
        with self._pub_lock:  # callbacks publish from Zenoh threads: create each one once
            if topic not in self._publishers:
                self._publishers[topic] = Publisher(self, topic)
            return self._publishers[topic]

    def put(self, record: Message) -> int:
        """Publish ``record`` on its topic (see :meth:`Publisher.put`)."""
        return self.publisher(record.TOPIC).put(record)

    def subscribe(
        self,
        topic: str,
        callback: Callable[[Any], Any],
        *,
        check_order: bool = True,
        max_age: float | None = None,
        clock: Callable[[], float] | None = None,
        source: str | None = None,
    ) -> Subscription:
        """Call ``callback(record)`` for every valid, in-order message on ``topic``.

        Invalid, out-of-order or stale (``max_age`` seconds on ``clock``) messages are
        counted in :attr:`rejects` instead, exceptions of ``callback`` in its
        :attr:`~services.reception.RejectCounter.failures`; with ``source`` (a service
        name) so are messages from any session but that service's (:meth:`check_source`).
        """
        receiver = Receiver(topic, check_order=check_order, max_age=max_age, clock=clock)
        transit: deque[float] = deque(maxlen=TRANSIT_SAMPLES)

        def decode(sample: zenoh.Sample) -> Any:
            hop = transit_time(sample)
            if hop is not None:
                transit.append(hop)
            if source is not None:
                self.check_source(topic, source, sample)
            return receiver(sample.payload.to_bytes())

        handler = safe_handler(decode, callback, self.rejects, topic=topic)
        sub = Subscription(
            self.session.declare_subscriber(self.key(topic), handler),
            topic,
            receiver,
            transit,
        )
        self._subscriptions.append(sub)
        if receiver.checker is not None:
            self.track_stream(topic, receiver.checker)
        return sub

    def check_source(self, topic: str, service: str, sample: zenoh.Sample) -> None:
        """Raise ``foreign_publisher`` unless ``sample`` comes from the session ``service``
        is pinned to (:class:`~services.reception.SourcePins`)."""
        self.pins.check(topic, service, source_session(sample))

    def on_foreign(self, callback: Callable[[str, str, str], None]) -> None:
        """Call ``callback(topic, service, session)`` the first time a session is refused
        on a ``source=`` subscription's topic (Zenoh thread)."""
        self.pins.listeners.append(callback)

    def track_stream(self, topic: str, checker: Any) -> None:
        """Include ``checker`` (anything with a ``stats() -> {name: count}`` method, e.g. a
        :class:`~services.reception.StreamChecker`) in :meth:`stream_stats`."""
        with self._pub_lock:
            self._streams.append((topic, checker))

    def stream_stats(self) -> dict[str, dict[str, int]]:
        """Per topic, the summed counts of its order checkers: messages ``accepted``,
        sequence ``gaps`` (messages lost on the way), ``reanchored`` streams."""
        with self._pub_lock:
            streams = list(self._streams)
        out: dict[str, dict[str, int]] = {}
        for topic, checker in streams:
            into = out.setdefault(topic, {})
            for name, n in checker.stats().items():
                into[name] = into.get(name, 0) + n
        return out

    # -- liveliness
    def declare_alive(self, service: str | None = None) -> None:
        """Declare ``arcade/<vehicle>/alive/<service>`` (default: this bus's name).

        Call after the subscriptions (see the readiness protocol in the module docstring).
        """
        service = self.name if service is None else service
        if service not in self._tokens:
            key = alive_key(self.vehicle, service)
            self._tokens[service] = self.session.liveliness().declare_token(key)

    def withdraw_alive(self, service: str | None = None) -> None:
        """Undeclare a token declared by :meth:`declare_alive`."""
        token = self._tokens.pop(self.name if service is None else service, None)
        if token is not None:
            token.undeclare()

    @property
    def alive(self) -> frozenset[str]:
        """Services of this vehicle whose liveliness token is currently visible."""
        with self._cond:
            return frozenset(self._alive)

    def wait_alive(self, services: Iterable[str], timeout: float) -> None:
        """Block until every service in ``services`` is alive; ``TimeoutError`` otherwise."""
        wanted = set(services)
        with self._cond:
            if not self._cond.wait_for(lambda: wanted <= self._alive, timeout):
                missing = sorted(wanted - self._alive)
                raise TimeoutError(f"not alive after {timeout} s: {missing}")

    def on_alive_change(self, callback: Callable[[str, bool], None]) -> None:
        """Call ``callback(service, alive)`` on every liveliness change (Zenoh thread)."""
        with self._cond:
            self._alive_listeners.append(callback)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        service, _, session = str(sample.key_expr).split("/", 3)[3].partition("/")
        up = sample.kind == zenoh.SampleKind.PUT
        if session:  # arcade/<vehicle>/alive/<service>/<session id>
            (self.pins.owner_up if up else self.pins.owner_down)(service, session)
            return
        with self._cond:
            (self._alive.add if up else self._alive.discard)(service)
            listeners = list(self._alive_listeners)
            self._cond.notify_all()
        for listener in listeners:
            try:
                listener(service, up)
            except Exception:
                log.exception("liveliness listener failed")
