"""Source pinning: a pinned topic is accepted only from the bus session of the service that
writes it (named by its liveliness token), whatever the message says of itself; the rest is
refused as ``foreign_publisher``, counted, and announced once per session."""

from __future__ import annotations

import zenoh
from loopback import PEER, LoopbackSession, Sample
from message_samples import sample

from services.bus import Bus
from services.messages import MessageError, Reason, Setpoint, encode
from services.reception import SourcePins


def _refused(pins: SourcePins, topic: str, service: str, session: str | None) -> Reason:
    try:
        pins.check(topic, service, session)
    except MessageError as err:
        return err.reason
    raise AssertionError(f"{topic} from {session} accepted")


def test_pinned_to_the_oldest_live_session_and_repinned_when_it_is_gone():
    pins = SourcePins()
    announced: list[tuple[str, str, str]] = []
    pins.listeners.append(lambda *a: announced.append(a))
    assert _refused(pins, "setpoint", "controller", "c1") is Reason.FOREIGN_PUBLISHER  # none
    pins.owner_up("controller", "c1")
    pins.check("setpoint", "controller", "c1")
    # A second session under the same name does not take over a live one.
    pins.owner_up("controller", "c2")
    assert pins.pinned("controller") == "c1"
    assert _refused(pins, "setpoint", "controller", "c2") is Reason.FOREIGN_PUBLISHER
    # The pinned one's token is gone (a crash, a restart): the next live one is pinned.
    pins.owner_down("controller", "c1")
    pins.check("setpoint", "controller", "c2")
    assert _refused(pins, "setpoint", "controller", "c1") is Reason.FOREIGN_PUBLISHER
    pins.owner_up("controller", "c1")  # back, but younger now
    assert pins.pinned("controller") == "c2"
    # Another service's session, or a sample that names none, is foreign too.
    pins.owner_up("adapter", "a1")
    assert _refused(pins, "setpoint", "controller", "a1") is Reason.FOREIGN_PUBLISHER
    assert _refused(pins, "setpoint", "controller", None) is Reason.FOREIGN_PUBLISHER
    pins.check("model", "adapter", "a1")
    # Announced once per (topic, session), however often refused.
    for _ in range(3):
        _refused(pins, "setpoint", "controller", "a1")
    assert announced == [
        ("setpoint", "controller", "c1"),
        ("setpoint", "controller", "c2"),
        ("setpoint", "controller", "a1"),
        ("setpoint", "controller", "unknown"),
    ]


def _alive(key: str, up: bool) -> Sample:
    s = Sample(key, b"")
    s.kind = zenoh.SampleKind.PUT if up else zenoh.SampleKind.DELETE
    return s


def test_a_subscription_with_a_source_takes_only_that_services_session():
    session = LoopbackSession()  # holds the controller's token as session PEER
    bus = Bus("test", "sim").open(session=session)
    got: list[Setpoint] = []
    foreign: list[tuple[str, str, str]] = []
    bus.on_foreign(lambda *a: foreign.append(a))
    bus.subscribe("setpoint", got.append, source="controller")
    key = "arcade/test/setpoint"
    (handler,) = session.handlers[key]

    def setpoint(seq: int, src: str = "controller/x") -> bytes:
        return encode(sample(Setpoint).replace(seq=seq, stamp=float(seq), src=src))

    handler(Sample(key, setpoint(1)))
    # A valid setpoint from another session, claiming to be the controller: refused.
    handler(Sample(key, setpoint(2, src=f"controller/{PEER}"), session="r0"))
    handler(Sample(key, setpoint(3), session="r0"))
    assert [s.seq for s in got] == [1]
    assert bus.rejects.by_topic == {("setpoint", "foreign_publisher"): 2}
    assert foreign == [("setpoint", "controller", "r0")]
    # The controller restarts: the old session's token goes, the new one's comes.
    bus._on_alive(_alive(f"arcade/test/alive/controller/{PEER}", up=False))
    bus._on_alive(_alive("arcade/test/alive/controller/c2", up=True))
    handler(Sample(key, setpoint(4), session=PEER))  # the old session, late: refused
    handler(Sample(key, setpoint(1, src="controller/c2"), session="c2"))
    assert [s.seq for s in got] == [1, 1]
    assert bus.rejects.counts == {"foreign_publisher": 3}
    # Session tokens are not services: what is alive is unchanged by them.
    assert bus.alive == frozenset()
    # This bus declared its own session's token at open.
    assert session.tokens == ["arcade/test/alive/sim/f0220000"]
