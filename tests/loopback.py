"""An in-process stand-in for the part of ``zenoh.Session`` that :class:`services.bus.Bus`
uses, so that a service can be wired exactly as ``Service.run`` wires it, without a network:
subscriptions are kept for :meth:`LoopbackSession.deliver`, puts are captured per key.

What it delivers comes from one session, :data:`PEER`, which holds the liveliness token of
every service a topic is pinned to (:data:`PINNED`): the stand-in speaks for all of them."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from typing import Any

from services.messages import Message, decode
from services.offline_bus import PEER, PINNED, Declared, Liveliness, Sample

__all__ = ["PEER", "PINNED", "LoopbackSession", "RecordingBus", "Sample"]


class LoopbackSession:
    """``echo``: a put also reaches the subscribers of its key (as Zenoh delivers a
    session's own samples), then ``on_put[key]`` if set."""

    def __init__(self, vehicle: str = "test", echo: bool = False) -> None:
        self.vehicle, self.echo = vehicle, echo
        self.handlers: dict[str, list[Callable[[Any], None]]] = defaultdict(list)
        self.published: dict[str, list[bytes]] = defaultdict(list)
        self.on_put: dict[str, Callable[[bytes], None]] = {}
        self._liveliness = Liveliness()

    @property
    def tokens(self) -> list[str]:
        return self._liveliness.tokens

    def zid(self) -> str:
        return "f0220000"

    def liveliness(self) -> Liveliness:
        return self._liveliness

    def key(self, topic: str) -> str:
        return f"arcade/{self.vehicle}/{topic}"

    def declare_subscriber(self, key: str, handler: Any, **_: Any) -> Declared:
        self.handlers[key].append(getattr(handler, "callback", handler))  # zenoh Callback
        return Declared()

    def declare_publisher(self, key: str, **_: Any) -> Declared:
        def put(payload: bytes) -> None:
            self.published[key].append(payload)
            if self.echo:
                self.deliver(key, payload)
            if key in self.on_put:
                self.on_put[key](payload)

        return Declared(put)

    def put(self, key: str, payload: bytes, **_: Any) -> None:
        self.published[key].append(bytes(payload))

    def deliver(self, topic_or_key: str, payload: bytes) -> None:
        """Hand ``payload`` to the subscribers of a topic (``"state"``) or a full key."""
        key = topic_or_key if "/" in topic_or_key else self.key(topic_or_key)
        for handler in self.handlers[key]:
            handler(Sample(key, payload))

    def outputs(self, topic: str) -> list[Message]:
        """Everything published on ``topic``, decoded (raises if anything is invalid)."""
        return [decode(topic, p) for p in self.published[self.key(topic)]]

    def close(self) -> None:
        pass


class RecordingBus:
    """What the estimator service needs of a bus, in process: what it publishes lands in
    ``states`` and ``events``; nothing is subscribed."""

    def __init__(self) -> None:
        from types import SimpleNamespace

        from services.reception import RejectCounter

        self.rejects = RejectCounter()
        self.session = SimpleNamespace(declare_subscriber=lambda *a, **k: None)
        self.states: list[Message] = []
        self.events: list[Message] = []
        self.alive: frozenset[str] = frozenset()

    def key(self, topic: str) -> str:
        return f"arcade/test/{topic}"

    def publisher(self, topic: str) -> RecordingBus:
        return self

    def track_stream(self, topic: str, checker: Any) -> None:
        pass

    def put(self, record: Message) -> int:
        (self.events if record.TOPIC == "event" else self.states).append(record)
        return len(self.states)


def lockstep_estimator(mocap_body: str | None = None) -> tuple[Any, RecordingBus]:
    """The estimator service (lockstep, default screening, the vehicle's rigid body
    ``mocap_body``, else the default) set up on a :class:`RecordingBus`."""
    import argparse

    from arcade_core.estimation import FilterConfig
    from services.estimator import Estimator
    from services.messages import VEHICLE_BODY

    args = argparse.Namespace(
        lockstep=True,
        out=None,
        max_frame_lag=0.25,
        stamp_tolerance=0.005,
        vehicle="test",
        jerk_psd=FilterConfig().jerk_psd,
        mocap_noise=FilterConfig().position_std,
        mocap_body=mocap_body or VEHICLE_BODY,
    )
    est = Estimator(args)
    bus = RecordingBus()
    est.setup(bus)
    est.bus = bus
    return est, bus
