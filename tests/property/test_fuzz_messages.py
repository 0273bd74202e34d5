"""Fuzzing of every wire decoder: a payload decodes to a valid record or raises MessageError.

For every record type in the registry (:data:`services.messages.MESSAGE_TYPES`, so a new
type is fuzzed without touching this file) at least ``FUZZ_CASES`` payloads (default
10 000; ``ARCADE_FUZZ_CASES`` overrides it) are generated: random bytes, valid records built
from the field specs (:func:`services.messages.field_specs`), and valid records with
mutations (wrong types, wrong and huge shapes, NaN/Inf, wrong schema name or version,
missing and extra fields, replayed and older headers, deep nesting, huge integers,
non-UTF-8 and binary strings, msgpack extension types, bit flips, truncation, lying
length headers). Each payload goes through :func:`decode` (typed and schema-agnostic) and
through the subscription path of the bus (a :class:`~services.reception.Receiver` with
order checks inside :func:`~services.reception.safe_handler`): the decoder returns a record
that passes its own validation again, or raises :class:`MessageError` (nothing else), and
the handler counts exactly one reject, with its reason, for every payload it does not
deliver.

Hypothesis draws a recipe (kind of payload, mutation and a seed) per example and a batch of
payloads is made from it with NumPy (``fuzz_payloads``, shared with
``test_fuzz_handlers.py``); with ``derandomize=True`` a failure names a reproducible recipe.
"""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
from fuzz_payloads import (
    BATCH,
    deep,
    fuzz_settings,
    lying_headers,
    make_payloads,
    non_utf8,
    pack,
    recipes,
    valid_record,
)
from hypothesis import given

from services import messages as wm
from services.messages import MessageError, Reason, decode
from services.reception import Receiver, RejectCounter, safe_handler

ALL = tuple(wm.MESSAGE_TYPES.values())
#: Fuzz payloads per record type (``test_fuzz_handlers.py`` has its own count per service).
FUZZ_CASES = int(os.environ.get("ARCADE_FUZZ_CASES", "10000"))


# --------------------------------------------------------------------- checking


def assert_valid(record: wm.Message, cls: type[wm.Message] | None, roundtrip: bool = True) -> None:
    """A decoded record is of the asked type and valid by its own rules, again."""
    if cls is not None:
        assert type(record) is cls
    dims: dict[str, int] = {}
    for name, spec in wm.field_specs(type(record)).items():
        value = getattr(record, name)
        if isinstance(value, np.ndarray):
            assert value.dtype == np.float64 and not value.flags.writeable, name
            assert np.isfinite(value).all(), name
        spec.coerce(name, value, dims)  # raises MessageError if not valid
    if not roundtrip:
        return
    try:
        again = decode(type(record), wm.encode(record))
    except MessageError as e:  # a compact (float32 or integer) payload re-encodes as float64
        assert e.reason is Reason.OVERSIZE, e
    else:
        assert again == record


class Harness:
    """The bus's subscription path for one topic (a :class:`Receiver` with order checks
    inside :func:`safe_handler`, counting into a :class:`RejectCounter`), plus the
    schema-agnostic decoder. The receiver's order check is wrapped to see each record the
    typed decoder produced, so that every payload is decoded once per decoder."""

    def __init__(self, cls: type[wm.Message]):
        self.cls = cls
        self.counter = RejectCounter(log_interval=math.inf)
        self.delivered: list[wm.Message] = []
        receiver = Receiver(cls)
        check = receiver.checker.check

        def checked(record: wm.Message) -> None:
            self.decoded = record
            check(record)

        receiver.checker.check = checked
        self.handler = safe_handler(receiver, self.delivered.append, self.counter, topic=cls.TOPIC)
        self.cases = 0
        self.valid = 0
        self.decoded: wm.Message | None = None

    def feed(self, payload: bytes) -> None:
        self.cases += 1
        self.decoded = None
        total, n = self.counter.total, len(self.delivered)
        before = self.counter.by_topic
        self.handler(payload)
        typed = self.decoded
        if typed is None:  # refused by the decoder: counted once, under its reason
            assert self.counter.total == total + 1 and len(self.delivered) == n
            reason = self.reason(self.cls, payload)
            assert reason is not None
            key = (self.cls.TOPIC, reason.value)
            assert self.counter.by_topic[key] == before.get(key, 0) + 1
        else:
            assert_valid(typed, self.cls, roundtrip=self.valid % 4 == 0)
            if len(self.delivered) == n + 1:
                assert self.delivered[-1] is typed and self.counter.total == total
                self.valid += 1
            else:  # valid, but refused by the stream checker
                assert self.counter.total == total + 1
        try:  # the schema-agnostic decoder
            anyone = decode(None, payload)
        except MessageError as e:
            assert e.detail and e.reason is not Reason.INTERNAL, e
            assert typed is None
        else:
            assert typed is None or anyone == typed
            if typed is None:  # another type's payload
                assert type(anyone) is not self.cls
                assert_valid(anyone, None, roundtrip=False)

    @staticmethod
    def reason(cls: type[wm.Message], payload: bytes) -> Reason | None:
        try:
            decode(cls, payload)
        except MessageError as e:
            assert e.detail and e.reason is not Reason.INTERNAL, e
            return e.reason
        return None


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_decoders_accept_valid_or_raise_message_error(cls):
    h = Harness(cls)

    @fuzz_settings(-(-FUZZ_CASES // BATCH))
    @given(recipes)
    def run(recipe: tuple[int, int, int]) -> None:
        for payload in make_payloads(cls, recipe):
            h.feed(payload)

    run()
    assert h.cases >= FUZZ_CASES
    # Every payload is either delivered or counted once, under a reason of its topic.
    assert h.valid + h.counter.total == h.cases
    assert {t for t, _ in h.counter.by_topic} == {cls.TOPIC}
    counts = h.counter.counts
    assert Reason.INTERNAL.value not in counts and h.counter.failures == {}
    if FUZZ_CASES >= 10_000:  # the generator reaches every class (guards the fuzzer itself)
        expected = {
            Reason.NOT_MSGPACK,
            Reason.NOT_MAP,
            Reason.OVERSIZE,
            Reason.BAD_SCHEMA,
            Reason.BAD_VERSION,
            Reason.MISSING_FIELD,
            Reason.EXTRA_FIELD,
            Reason.BAD_TYPE,
            Reason.NON_FINITE,
            Reason.OUT_OF_RANGE,
            Reason.OUT_OF_ORDER,
        }
        kinds = {type(s).__name__ for s in wm.field_specs(cls).values()}
        if "ArraySpec" in kinds:
            expected.add(Reason.BAD_SHAPE)
        assert {r.value for r in expected} <= set(counts), counts
        assert h.valid >= FUZZ_CASES // 20, (h.valid, counts)


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_spec_generator_makes_valid_records(cls):
    # The valid base records of the fuzzer come from the field specs: a record type with a
    # constraint its specs do not express (a cross-field `_check` on a required field)
    # makes this fail; declare the constraint in the spec (e.g. `unit=`) instead.
    rng = np.random.default_rng(0)
    records = [valid_record(cls, rng) for _ in range(300)]
    made = [r for r in records if r is not None]
    assert len(made) >= 0.9 * len(records)
    for r in made[:50]:
        assert_valid(r, cls)
    if any(
        type(s).__name__ == "ArraySpec" and s.shape and isinstance(s.shape[0], str)
        for s in wm.field_specs(cls).values()
    ):
        assert len({_dims(r) for r in made}) > 1  # symbolic dimensions vary


def _dims(record: wm.Message) -> tuple[int, ...]:
    return tuple(v.shape for v in vars(record).values() if isinstance(v, np.ndarray))


def test_deep_nesting_and_lying_headers_are_not_msgpack():
    for payload in (deep(3000), *lying_headers(wm.State)):
        with pytest.raises(MessageError) as info:
            decode(wm.State, payload)
        assert info.value.reason is Reason.NOT_MSGPACK, info.value
    with pytest.raises(MessageError) as info:
        decode(wm.State, deep(10_000))
    assert info.value.reason is Reason.OVERSIZE


def test_non_utf8_and_binary_strings_are_rejected():
    w = {
        "schema": "arcade.Command",
        "version": 1,
        "seq": 1,
        "stamp": 1.0,
        "src": "op/1",
        "name": "arm",
        "target": "",
        "args": {},
    }
    assert decode(wm.Command, pack(w)).name == "arm"
    bad = non_utf8(w, wm.Command)
    assert bad is not None and b"\xff\xfe" in bad
    with pytest.raises(MessageError) as info:
        decode(wm.Command, bad)
    assert info.value.reason is Reason.NOT_MSGPACK
    with pytest.raises(MessageError) as info:
        decode(wm.Command, pack({**w, "name": b"arm"}))
    assert info.value.reason is Reason.BAD_TYPE
