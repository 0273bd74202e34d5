"""Reception policy of the service stack: what a subscriber does with a stream of records.

:mod:`services.messages` says whether one payload is a valid record; this module says
whether a valid record is accepted from its stream and what happens to the rest.
:class:`StreamChecker` rejects out-of-order and stale messages per publisher (``seq`` and
``stamp`` order, an optional maximum age, re-anchoring after a stamp from the future),
:class:`Receiver` decodes one topic and applies those checks, :class:`RejectCounter` counts
rejects by reason and topic and logs them (rate limited), apart from the receiving
service's own failures on valid messages, and :func:`safe_handler` turns a decoder and a
callback into a function that never raises. :class:`SourcePins` accepts a topic only from the
bus session of the one service that writes it (the ``setpoint`` from the controller's).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from typing import Any, TypeVar

from services.messages import Message, MessageError, Reason, decode, message_type

__all__ = ["Receiver", "RejectCounter", "SourcePins", "StreamChecker", "safe_handler"]

log = logging.getLogger("arcade.messages")  # the wire layer's logger

M = TypeVar("M", bound=Message)


# ------------------------------------------------------------------- stream checks


class StreamChecker:
    """Rejects out-of-order and stale messages, per publisher (``src``).

    A message is accepted when its ``seq`` is larger than the last accepted ``seq`` of the
    same publisher and its ``stamp`` is not older than the last accepted ``stamp``
    (equal stamps are fine: several messages may share one lockstep instant). With
    ``max_age`` and a ``clock`` on the stamps' time base, messages older than ``max_age``
    seconds are stale too. A restarted publisher has a new ``src`` (the bus appends its
    session id), so it starts a new stream. Thread-safe.

    One message stamped in the future would otherwise make every later one of its
    publisher stale: after ``reanchor_after`` consecutive stale stamps from one publisher
    (its ``seq`` still increasing), the next one is accepted and becomes the reference
    (counted in :attr:`reanchored`, logged). This needs no clock shared with the
    publisher: realtime stamps are ``time.monotonic()`` of the publisher's host, lockstep
    stamps simulated time.
    """

    def __init__(
        self,
        *,
        max_age: float | None = None,
        clock: Callable[[], float] | None = None,
        max_publishers: int = 64,
        reanchor_after: int = 10,
    ):
        if (max_age is None) != (clock is None):
            raise ValueError("max_age and clock go together")
        if reanchor_after < 1:
            raise ValueError(f"reanchor_after must be >= 1, not {reanchor_after}")
        self.max_age, self.clock, self.max_publishers = max_age, clock, max_publishers
        self.reanchor_after = reanchor_after
        self._last: OrderedDict[str, tuple[int, float]] = OrderedDict()
        self._stale_run: dict[str, int] = {}  # consecutive stale stamps per publisher
        self._lock = threading.Lock()
        self.accepted = 0
        #: Sequence numbers skipped by accepted messages (messages lost on the way).
        self.gaps = 0
        #: Streams whose stamp reference was reset after ``reanchor_after`` stale stamps.
        self.reanchored = 0

    def stats(self) -> dict[str, int]:
        """``accepted``, ``gaps`` and ``reanchored`` counts (for the statistics files)."""
        with self._lock:
            return {"accepted": self.accepted, "gaps": self.gaps, "reanchored": self.reanchored}

    def check(self, record: Message) -> None:
        """Accept ``record`` (and remember it) or raise :class:`MessageError`."""
        if self.max_age is not None and self.clock is not None:
            age = self.clock() - record.stamp
            if age > self.max_age:
                raise MessageError(Reason.STALE, f"{age:.3f} s old > {self.max_age} s")
        with self._lock:
            last = self._last.get(record.src)
            if last is not None:
                seq, stamp = last
                if record.seq <= seq:
                    raise MessageError(
                        Reason.OUT_OF_ORDER, f"seq {record.seq} after {seq} from {record.src!r}"
                    )
                if record.stamp < stamp:
                    run = self._stale_run.get(record.src, 0)
                    if run < self.reanchor_after:
                        self._stale_run[record.src] = run + 1
                        raise MessageError(
                            Reason.STALE,
                            f"stamp {record.stamp} after {stamp} from {record.src!r}",
                        )
                    self.reanchored += 1
                    log.warning(
                        "stamps from %r re-anchored at %s after %d stale ones (reference %s "
                        "was from the future or the publisher's clock went back)",
                        record.src,
                        record.stamp,
                        run,
                        stamp,
                    )
                self.gaps += record.seq - seq - 1
            self._stale_run.pop(record.src, None)
            self._last[record.src] = (record.seq, record.stamp)
            self._last.move_to_end(record.src)
            if len(self._last) > self.max_publishers:
                src, _ = self._last.popitem(last=False)
                self._stale_run.pop(src, None)
            self.accepted += 1

    def reset(self, src: str | None = None) -> None:
        """Forget one publisher (or all)."""
        with self._lock:
            if src is None:
                self._last.clear()
                self._stale_run.clear()
            else:
                self._last.pop(src, None)
                self._stale_run.pop(src, None)


class Receiver:
    """``payload -> record`` decoder for one topic with per-publisher order checks.

    ``check_order=False`` skips the :class:`StreamChecker` (e.g. for a recorder that wants
    everything); ``max_age``/``clock`` are passed to it.
    """

    def __init__(
        self,
        topic_or_schema: str | type[Message],
        *,
        check_order: bool = True,
        max_age: float | None = None,
        clock: Callable[[], float] | None = None,
    ):
        self.type = message_type(topic_or_schema)
        self.checker = StreamChecker(max_age=max_age, clock=clock) if check_order else None

    def __call__(self, payload: Any) -> Message:
        record = decode(self.type, payload)
        if self.checker is not None:
            self.checker.check(record)
        return record


# ------------------------------------------------------------------ source pinning


class SourcePins:
    """Which bus session each service speaks from, and the check that a message comes from it.

    The bus tells the sessions (:meth:`owner_up`/:meth:`owner_down`, from the liveliness
    tokens ``arcade/<vehicle>/alive/<service>/<session id>``) and the session a message came
    from (the Zenoh source id the publisher's session puts on each sample); the message's own
    ``src`` field plays no part. A service is pinned to the oldest of its sessions whose token
    is still alive: a second process under the same name cannot take over a live one, and a
    restarted service is pinned to its new session as soon as the old token is gone.

    :meth:`check` raises ``foreign_publisher`` for any other session (or none), and calls
    every ``listener(topic, service, session)`` the first time a session is refused on a
    topic (a ``fault`` event of the receiving service). Thread-safe.
    """

    def __init__(self) -> None:
        self._owners: dict[str, list[str]] = {}
        self._refused: set[tuple[str, str]] = set()
        self._lock = threading.Lock()
        self.listeners: list[Callable[[str, str, str], None]] = []

    def owner_up(self, service: str, session: str) -> None:
        with self._lock:
            owners = self._owners.setdefault(service, [])
            if session not in owners:
                owners.append(session)

    def owner_down(self, service: str, session: str) -> None:
        with self._lock:
            owners = self._owners.get(service, [])
            if session in owners:
                owners.remove(session)

    def pinned(self, service: str) -> str | None:
        """The session ``service`` is pinned to (None: no token of it alive)."""
        with self._lock:
            owners = self._owners.get(service)
            return owners[0] if owners else None

    def check(self, topic: str, service: str, session: str | None) -> None:
        """Accept a ``topic`` message from bus session ``session`` (None: the sample said
        none) if ``service`` is pinned to it, else raise :class:`MessageError`."""
        pinned = self.pinned(service)
        if session is not None and session == pinned:
            return
        who = session or "unknown"
        with self._lock:
            # Bounded: past 1024 refused sessions the rest are counted, not announced.
            first = (topic, who) not in self._refused and len(self._refused) < 1024
            if first:
                self._refused.add((topic, who))
                listeners = list(self.listeners)
        if first:
            for listener in listeners:
                try:
                    listener(topic, service, who)
                except Exception:
                    log.exception("foreign-publisher listener failed")
        raise MessageError(
            Reason.FOREIGN_PUBLISHER,
            f"{topic} from session {who}, not the {service}'s ({pinned or 'none alive'})",
        )


# -------------------------------------------------------------------- reject counts


class RejectCounter:
    """Counts rejected messages by reason (and topic) and logs them, rate limited.

    Each ``(topic, reason)`` pair logs at most one line per ``log_interval`` seconds; the
    next line says how many were suppressed meanwhile. Thread-safe; :meth:`wait_total`
    lets a caller block until a number of rejects has been counted.

    A callback that fails on a valid message is the receiving ``service``'s own failure,
    not a rejected input: :meth:`failure` counts it apart (:attr:`failures`, per topic)
    and logs "<service> failed handling a <topic> message", rate limited the same way.
    """

    def __init__(
        self,
        *,
        logger: logging.Logger | None = None,
        log_interval: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
        service: str = "",
    ):
        self.logger = logger or log
        self.log_interval = log_interval
        self.clock = clock
        self.service = service
        self._counts: Counter[tuple[str, Reason]] = Counter()
        self._failures: Counter[str] = Counter()
        self._last_log: dict[tuple[str, Reason | None], float] = {}
        self._suppressed: Counter[tuple[str, Reason | None]] = Counter()
        self._cond = threading.Condition()

    def _due(self, key: tuple[str, Reason | None]) -> tuple[bool, int]:
        """Whether ``key`` logs now, and how many of its lines were suppressed (locked)."""
        now = self.clock()
        last = self._last_log.get(key)
        if last is None or now - last >= self.log_interval:
            self._last_log[key] = now
            return True, self._suppressed.pop(key, 0)
        self._suppressed[key] += 1
        return False, 0

    def reject(
        self, error: MessageError, *, topic: str = "", exc: BaseException | None = None
    ) -> None:
        """Count one reject and log it unless this ``(topic, reason)`` logged recently."""
        key = (topic, error.reason)
        with self._cond:
            self._counts[key] += 1
            emit, suppressed = self._due(key)
            self._cond.notify_all()
        if emit:
            more = f" ({suppressed} more suppressed)" if suppressed else ""
            self.logger.warning(
                "rejected %s message: %s%s", topic or "a", error, more, exc_info=exc
            )

    def failure(self, exc: BaseException, *, topic: str = "") -> None:
        """Count one failure of this service's own callback on a valid ``topic`` message
        and log it with its traceback unless that topic's failures logged recently."""
        with self._cond:
            self._failures[topic] += 1
            emit, suppressed = self._due((topic, None))
            self._cond.notify_all()
        if emit:
            more = f" ({suppressed} more suppressed)" if suppressed else ""
            self.logger.error(
                "%s failed handling a %s message: %r%s",
                self.service or "service",
                topic or "",
                exc,
                more,
                exc_info=exc,
            )

    @property
    def failures(self) -> dict[str, int]:
        """Callback failures by topic (see :meth:`failure`)."""
        with self._cond:
            return dict(self._failures)

    @property
    def counts(self) -> dict[str, int]:
        """Rejects by reason code."""
        with self._cond:
            out: Counter[str] = Counter()
            for (_, reason), n in self._counts.items():
                out[reason.value] += n
            return dict(out)

    @property
    def by_topic(self) -> dict[tuple[str, str], int]:
        """Rejects by ``(topic, reason code)``."""
        with self._cond:
            return {(t, r.value): n for (t, r), n in self._counts.items()}

    @property
    def total(self) -> int:
        with self._cond:
            return sum(self._counts.values())

    def wait_total(self, n: int, timeout: float) -> bool:
        """Block until at least ``n`` rejects were counted; ``False`` on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: sum(self._counts.values()) >= n, timeout)

    def wait_failures(self, n: int, timeout: float) -> bool:
        """Block until at least ``n`` callback failures were counted; ``False`` on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: sum(self._failures.values()) >= n, timeout)


def safe_handler(
    decoder: Callable[[Any], M],
    callback: Callable[[M], Any],
    counter: RejectCounter,
    *,
    topic: str = "",
) -> Callable[[Any], None]:
    """``payload -> None`` that decodes, calls ``callback`` and never raises.

    A :class:`MessageError` from ``decoder`` is counted under its reason and any other
    exception of the decoder as ``internal`` (rejected input); an exception of the
    callback is the service's own failure, counted by :meth:`RejectCounter.failure`
    (logged with its traceback).
    """

    def handle(payload: Any) -> None:
        try:
            record = decoder(payload)
        except MessageError as e:
            counter.reject(e, topic=topic)
            return
        except Exception as e:
            counter.reject(MessageError(Reason.INTERNAL, repr(e)), topic=topic, exc=e)
            return
        try:
            callback(record)
        except Exception as e:
            counter.failure(e, topic=topic)

    return handle
