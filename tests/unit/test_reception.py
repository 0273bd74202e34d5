"""Reception policy: per-publisher order and staleness checks, reject counts and their
rate-limited logs, handlers that never raise."""

from __future__ import annotations

import contextlib
import logging

import pytest
from message_samples import pack, sample

from services.messages import MessageError, Reason, State, encode
from services.reception import Receiver, RejectCounter, StreamChecker, safe_handler

# ------------------------------------------------------------------ stream checks


def _state(seq: int, stamp: float, src: str = "est/1") -> State:
    return sample(State).replace(seq=seq, stamp=stamp, src=src)


def test_stream_checker_orders_per_publisher():
    c = StreamChecker()
    c.check(_state(1, 1.0))
    c.check(_state(2, 1.0))  # equal stamps are fine
    c.check(_state(5, 2.0))  # a gap is fine, and counted
    assert c.gaps == 2
    for seq, stamp, reason in (
        (5, 3.0, Reason.OUT_OF_ORDER),
        (4, 3.0, Reason.OUT_OF_ORDER),
        (6, 1.5, Reason.STALE),
    ):
        with pytest.raises(MessageError) as info:
            c.check(_state(seq, stamp))
        assert info.value.reason is reason
    c.check(_state(1, 0.0, src="est/2"))  # another publisher is another stream
    c.check(_state(6, 2.0))  # rejected messages did not move the stream
    assert c.accepted == 5
    c.reset("est/1")
    c.check(_state(1, 0.0))  # e.g. after a known restart


def test_one_stamp_from_the_future_does_not_block_its_stream(caplog):
    """After ``reanchor_after`` consecutive stale stamps from one publisher, its next
    message becomes the reference again: counted and logged, never silent."""
    c = StreamChecker(reanchor_after=3)
    c.check(_state(1, 100.0))
    c.check(_state(2, 1e9))  # a stamp from the future (or a clock that went back)
    for seq in (3, 4, 5):
        with pytest.raises(MessageError) as info:
            c.check(_state(seq, 100.0 + seq))
        assert info.value.reason is Reason.STALE
    with caplog.at_level(logging.WARNING, logger="arcade.messages"):
        c.check(_state(6, 106.0))  # re-anchored
    assert c.reanchored == 1 and any("re-anchored" in r.getMessage() for r in caplog.records)
    c.check(_state(7, 107.0))
    with pytest.raises(MessageError):
        c.check(_state(8, 100.0))  # order checks hold again from the new reference
    # Gaps: seq 3-5 never reached the stream (rejected), as lost ones would not.
    assert c.stats() == {"accepted": 4, "gaps": 3, "reanchored": 1}
    # An isolated stale stamp between good ones does not count towards re-anchoring.
    c = StreamChecker(reanchor_after=2)
    c.check(_state(1, 10.0))
    for seq, stamp in ((2, 5.0), (3, 11.0), (4, 5.0), (5, 12.0)):
        with contextlib.suppress(MessageError):
            c.check(_state(seq, stamp))
    assert c.reanchored == 0 and c.accepted == 3


def test_stream_checker_max_age():
    now = [10.0]
    c = StreamChecker(max_age=0.5, clock=lambda: now[0])
    c.check(_state(1, 9.6))
    with pytest.raises(MessageError) as info:
        c.check(_state(2, 9.4))
    assert info.value.reason is Reason.STALE
    with pytest.raises(ValueError):
        StreamChecker(max_age=1.0)


def test_receiver_counts_out_of_order_and_stale():
    counter, got = RejectCounter(), []
    handler = safe_handler(Receiver("state"), got.append, counter, topic="state")
    for seq, stamp in ((1, 1.0), (2, 2.0), (2, 3.0), (1, 4.0), (3, 1.0), (4, 4.0)):
        handler(encode(_state(seq, stamp)))
    assert [m.seq for m in got] == [1, 2, 4]
    assert counter.counts == {"out_of_order": 2, "stale": 1}
    everything = Receiver("state", check_order=False)
    assert everything(encode(_state(1, 1.0))).seq == 1 and everything.checker is None


# ---------------------------------------------------------------- counting, logs


def test_reject_counter_rate_limits_logs(caplog):
    now = [0.0]
    counter = RejectCounter(log_interval=1.0, clock=lambda: now[0])
    handler = safe_handler(Receiver("state"), lambda m: None, counter, topic="state")
    with caplog.at_level(logging.WARNING, logger="arcade.messages"):
        for _ in range(5):
            handler(b"\xc1")
        handler(pack([1]))  # another reason logs at once
        assert len(caplog.records) == 2
        now[0] = 1.5
        handler(b"\xc1")
    assert counter.counts == {"not_msgpack": 6, "not_map": 1} and counter.total == 7
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 3
    assert "not_msgpack" in lines[0] and "not_map" in lines[1]
    assert "4 more suppressed" in lines[2]
    assert counter.wait_total(7, timeout=0.0) and not counter.wait_total(8, timeout=0.0)


def test_safe_handler_contains_callback_and_decoder_failures(caplog):
    counter, seen = RejectCounter(), []

    def callback(m):
        seen.append(m.seq)
        if m.seq == 2:
            raise RuntimeError("bug in service")

    counter = RejectCounter(service="controller")
    handler = safe_handler(Receiver("state"), callback, counter, topic="state")
    with caplog.at_level(logging.ERROR, logger="arcade.messages"):
        for seq in (1, 2, 3):
            handler(encode(_state(seq, float(seq))))
    assert seen == [1, 2, 3]  # the failing callback did not stop the stream
    # The service's own failure, not a rejected input: counted and worded apart.
    assert counter.counts == {} and counter.failures == {"state": 1} and counter.total == 0
    lines = [r.getMessage() for r in caplog.records if r.exc_info]
    assert len(lines) == 1 and "bug in service" in lines[0]
    assert lines[0].startswith("controller failed handling a state message")
    assert not any("rejected" in r.getMessage() for r in caplog.records)

    def broken(payload):
        raise KeyError("decoder bug")

    safe_handler(broken, callback, counter, topic="state")(b"")
    assert counter.counts == {"internal": 1} and counter.failures == {"state": 1}
