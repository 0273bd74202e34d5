"""An in-process stand-in for the part of ``zenoh.Session`` that :class:`services.bus.Bus`
uses (``Bus.open(session=...)``), so that services run wired exactly as ``Service.run``
wires them, without a network: ``arcade replay`` runs the recorded adapter and controller
on it, the tests drive a service's handlers with it.

What it delivers comes from one session, :data:`PEER`, which holds the liveliness token of
every service a topic is pinned to (:data:`PINNED`, ``Bus.subscribe(source=...)``): the
stand-in speaks for all of them."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import zenoh

#: The session id of whatever the stand-in delivers, and the services it speaks for.
PEER = "5e55"
PINNED = ("controller", "adapter", "estimator", "sim", "px4sim")


class Payload:
    def __init__(self, data: bytes):
        self._data = data

    def to_bytes(self) -> bytes:
        return self._data


class Sample:
    """A received sample: ``key_expr``, ``payload``, no attachment (no transit time), put
    by the session ``session``."""

    def __init__(self, key: str, data: bytes, session: str = PEER):
        self.key_expr = key
        self.payload = Payload(data)
        self.attachment = None
        self.kind = zenoh.SampleKind.PUT
        self.source_info = SimpleNamespace(source_id=SimpleNamespace(zid=session))


class Declared:
    """A declared publisher, subscriber or token; ``on_put`` receives what is put."""

    def __init__(self, on_put: Callable[[bytes], None] | None = None):
        self._on_put = on_put

    def put(self, payload: bytes, attachment: Any = None, **_: Any) -> None:
        if self._on_put is not None:
            self._on_put(bytes(payload))

    def undeclare(self) -> None:
        pass


class Liveliness:
    """Tokens are recorded; a liveliness subscriber hears the tokens of :data:`PEER` for
    the services of :data:`PINNED`, nothing else."""

    def __init__(self) -> None:
        self.tokens: list[str] = []

    def declare_subscriber(self, key: str, callback: Any, **_: Any) -> Declared:
        prefix = key.removesuffix("*").removesuffix("*")  # arcade/<vehicle>/alive/
        for service in PINNED:
            callback(Sample(f"{prefix}{service}/{PEER}", b""))
        return Declared()

    def declare_token(self, key: str) -> Declared:
        self.tokens.append(key)
        return Declared()


class Session:
    """A session of one service named ``name``: subscriptions kept for :meth:`deliver`,
    puts handed to ``on_put(session, key, payload)``; no liveliness (no other service is
    ever alive to it, so none waits for another)."""

    def __init__(self, name: str, on_put: Callable[[Session, str, bytes], None]) -> None:
        self.name, self._on_put = name, on_put
        self.handlers: dict[str, list[Any]] = defaultdict(list)

    def zid(self) -> str:
        return f"offline{self.name}"

    def liveliness(self) -> Session:
        return self

    def declare_token(self, key: str) -> Declared:
        return Declared()

    def declare_subscriber(self, key: str, handler: Any, **_: Any) -> Declared:
        if key.split("/")[-2:-1] != ["alive"]:  # liveliness subscribers hear nothing
            self.handlers[key].append(handler)
        return Declared()

    def declare_publisher(self, key: str, **_: Any) -> Declared:
        return Declared(lambda payload: self._on_put(self, key, payload))

    def deliver(self, key: str, payload: bytes) -> None:
        """Hand ``payload`` to the subscribers of ``key`` (on the caller's thread)."""
        for handler in self.handlers.get(key, ()):
            handler(Sample(key, payload))

    def close(self) -> None:
        pass
