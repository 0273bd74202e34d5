"""Fuzzing of every wire decoder: a payload decodes to a valid record or raises MessageError.

For every record type in the registry (:data:`services.messages.MESSAGE_TYPES`, so a new
type is fuzzed without touching this file) at least ``FUZZ_CASES`` payloads (default
10 000; ``ARCADE_FUZZ_CASES`` overrides it) are generated: random bytes, valid records built
from the field specs (:func:`services.messages.field_specs`), and valid records with
mutations (wrong types, wrong and huge shapes, NaN/Inf, wrong schema name or version,
missing and extra fields, replayed and older headers, deep nesting, huge integers,
non-UTF-8 and binary strings, msgpack extension types, bit flips, truncation, lying
length headers). Each payload goes through :func:`decode` (typed and schema-agnostic) and
through the subscription path of the bus (a :class:`Receiver` with order checks inside
:func:`safe_handler`): the decoder returns a record that passes its own validation again,
or raises :class:`MessageError` (nothing else), and the handler counts exactly one reject,
with its reason, for every payload it does not deliver.

Hypothesis draws a recipe (kind of payload, mutation and a seed) per example and a batch of
:data:`BATCH` payloads is made from it with NumPy: generating through hypothesis' own
strategies costs milliseconds per payload, which 10^4 cases per type cannot afford. With
``derandomize=True`` a failure names a reproducible recipe. The generators are shared
with ``test_fuzz_handlers.py``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import struct
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from services import messages as wm
from services.messages import MessageError, Reason, Receiver, RejectCounter, decode, safe_handler

ALL = tuple(wm.MESSAGE_TYPES.values())
#: Fuzz payloads per record type (and per service handler in ``test_fuzz_handlers.py``).
FUZZ_CASES = int(os.environ.get("ARCADE_FUZZ_CASES", "10000"))
#: Payloads made from one hypothesis example.
BATCH = 4


def fuzz_settings(n: int) -> settings:
    return settings(
        max_examples=n,
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=list(HealthCheck),
    )


#: A hypothesis example: ``(kind, mutation, seed)``.
recipes = st.tuples(st.integers(0, 15), st.integers(0, 15), st.integers(0, 2**63 - 1))

# ---------------------------------------------------------------- valid records

# Half of the records come from a few publishers, so that replays, out-of-order and older
# stamps happen often; the others mostly from new publishers, so that many are delivered.
_SOURCES = ("estimator/a1", "controller/b2", "sim/c3", "")
_ALPHABET = np.array(list("abcxyzABCXYZ0129_.-:/@ "))


def _text(rng: np.random.Generator, max_len: int = 12) -> str:
    """Arbitrary Unicode (no surrogates: those cannot be UTF-8 encoded)."""
    n = int(rng.integers(0, max_len + 1))
    lo, hi = _pick(rng, [(32, 127), (0x80, 0xD7FF), (0xE000, 0x10FFFF)])
    return "".join(map(chr, rng.integers(lo, hi, n)))


def _string(rng: np.random.Generator, spec: Any, default: Any) -> str:
    if spec.choices is not None:
        return _pick(rng, spec.choices)
    if spec.pattern is None:
        return _text(rng, min(spec.max_len, 40))
    if spec.pattern.pattern == wm._SRC.pattern:
        return _pick(rng, _SOURCES) if rng.random() < 0.5 else f"pub/{rng.bytes(6).hex()}"
    if isinstance(default, str) and spec.pattern.fullmatch(default) and rng.random() < 0.5:
        return default  # e.g. the empty target that addresses every service
    for _ in range(20):  # the specs' patterns are simple character classes
        s = "".join(rng.choice(_ALPHABET, int(rng.integers(0, 17))))
        if len(s) <= spec.max_len and spec.pattern.fullmatch(s):
            return s
    return default if isinstance(default, str) else "a"


def _array(rng: np.random.Generator, spec: Any, shape: tuple[int, ...]) -> np.ndarray:
    """An array within the spec's (per-element) bounds, often at the bounds; unit slices
    normalised."""
    lo = np.broadcast_to(np.asarray(spec.lo, np.float64), shape)
    hi = np.broadcast_to(np.asarray(spec.hi, np.float64), shape)
    lo, hi = np.where(np.isfinite(lo), lo, -1e6), np.where(np.isfinite(hi), hi, 1e6)
    u = rng.choice([rng.random(shape), rng.integers(0, 3, shape) / 2.0, rng.random(shape) ** 8])
    a = np.clip(lo + u * (hi - lo), lo, hi)
    if spec.unit is not None:
        q = a[spec.unit[0] : spec.unit[1]]
        norm = np.linalg.norm(q)
        q[:] = q / norm if norm > 1e-3 else np.eye(q.size)[0]
    return a


#: Keys of event data and command arguments that services read (the start command's t0).
_KEYS = ("t0", "mode", "step")


def _scalars(rng: np.random.Generator) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for i in range(int(rng.integers(0, 5))):
        key = _pick(rng, [f"k{i}", f"k{i}_{int(rng.integers(100))}", *_KEYS])
        ordinary = [
            None,
            True,
            int(rng.integers(-(2**62), 2**62)),
            float(rng.normal() * 1e6),
            _text(rng),
            float(rng.random()),
        ]
        extreme = [2**64 - 1, -(2**63), 1e308, -1e308, 5e-324]
        out[key] = _pick(rng, ordinary if rng.random() < 0.5 else extreme)
    return out


def _value(rng: np.random.Generator, spec: Any, dims: dict[str, int], default: Any) -> Any:
    kind = type(spec).__name__
    if getattr(spec, "optional", False) and rng.random() < 0.25:
        return None
    if kind == "_Float":
        lo, hi = max(spec.lo, -1e9), min(spec.hi, 1e9)
        return float(_pick(rng, [lo, hi, lo + (hi - lo) * rng.random()]))
    if kind == "_Int":
        # Mostly small (so that streams stay in order), sometimes the extremes.
        small = min(spec.hi, spec.lo + int(rng.integers(0, 2**40)))
        return _pick(rng, [spec.lo, small, small, small, spec.hi])
    if kind == "_Bool":
        return bool(rng.integers(2))
    if kind == "_Str":
        return _string(rng, spec, default)
    if kind == "_Scalars":
        return _scalars(rng)
    if kind == "_Array":
        return _array(rng, spec, tuple(dims[n] if isinstance(n, str) else n for n in spec.shape))
    raise TypeError(f"no generator for field spec {kind}: add one to the fuzzer")


def _defaults(cls: type[wm.Message]) -> dict[str, Any]:
    return {f.name: f.default for f in dataclasses.fields(cls)}


def valid_fields(
    cls: type[wm.Message], rng: np.random.Generator, dims: dict[str, int] | None = None
) -> dict[str, Any]:
    """Constructor arguments of ``cls`` drawn from its field specs (valid per field);
    ``dims`` fixes symbolic dimensions (random small sizes otherwise)."""
    dims = {"d": int(rng.integers(1, 7)), "l": int(rng.integers(1, 5)), **(dims or {})}
    defaults = _defaults(cls)
    return {
        name: _value(rng, spec, dims, defaults[name]) for name, spec in wm.field_specs(cls).items()
    }


def valid_record(
    cls: type[wm.Message], rng: np.random.Generator, dims: dict[str, int] | None = None
) -> wm.Message | None:
    """A valid record of ``cls``; a field that breaks a cross-field check is dropped if it
    is optional (``None`` where the specs alone cannot make a valid record)."""
    fields = valid_fields(cls, rng, dims)
    if cls is wm.Mocap:  # a frame is captured before it is stamped
        fields["capture_stamp"] = min(fields["capture_stamp"], fields["stamp"])
    specs = wm.field_specs(cls)
    for _ in range(len(fields)):
        try:
            return cls(**fields)
        except MessageError as e:
            spec = specs.get(e.field or "")
            if spec is None or not getattr(spec, "optional", False) or fields[e.field] is None:
                return None
            fields = {**fields, e.field: None}
    return None


# -------------------------------------------------------------------- mutations

_NASTY_FLOATS = (math.nan, -math.nan, math.inf, -math.inf, 1e308, -1e308, 5e-324, -0.0)
_HUGE_INTS = (2**64 - 1, 2**63, -(2**63), 2**63 - 1, -1)


def junk(rng: np.random.Generator, depth: int = 0) -> Any:
    """An arbitrary msgpack-able value (wrong types, containers, extension types)."""
    k = int(rng.integers(0, 13 if depth < 3 else 11))
    return [
        lambda: None,
        lambda: bool(rng.integers(2)),
        lambda: int(rng.integers(-(2**63), 2**63 - 1)),
        lambda: _HUGE_INTS[int(rng.integers(len(_HUGE_INTS)))],
        lambda: float(rng.normal() * 10 ** rng.integers(-300, 300)),
        lambda: _NASTY_FLOATS[int(rng.integers(len(_NASTY_FLOATS)))],
        lambda: _text(rng, 8),
        lambda: rng.bytes(int(rng.integers(0, 9))),
        lambda: msgpack.ExtType(int(rng.integers(0, 128)), rng.bytes(int(rng.integers(0, 5)))),
        lambda: msgpack.Timestamp(int(rng.integers(0, 2**33)), int(rng.integers(0, 10**9))),
        lambda: float(rng.normal()),
        lambda: [junk(rng, depth + 1) for _ in range(int(rng.integers(0, 5)))],
        lambda: {_text(rng, 4): junk(rng, depth + 1) for _ in range(int(rng.integers(0, 4)))},
    ][k]()


def _nested(depth: int, leaf: Any = 0.0) -> Any:
    v = leaf
    for _ in range(depth):
        v = [v]
    return v


def _reshaped(rng: np.random.Generator, value: Any, max_bytes: int) -> Any:
    """An array field with a wrong, ragged, too deep or huge shape."""
    a = np.asarray(value, dtype=np.float64) if isinstance(value, list) else np.zeros(3)
    how = int(rng.integers(0, 9))
    if how == 0:  # one element more or less
        flat = a.reshape(-1).tolist()
        return [*flat, 0.5] if rng.integers(2) or not flat else flat[:-1]
    if how == 1:  # flattened or one level deeper
        return a.reshape(-1).tolist() if a.ndim > 1 else [a.tolist()]
    if how == 2:  # transposed
        return a.T.tolist() if a.ndim > 1 else a[:, None].tolist()
    if how == 3:  # ragged rows
        rows = a.reshape(a.shape[0], -1).tolist() if a.size else [[0.0]]
        return [*rows, [0.0] * (len(rows[0]) + 1)]
    if how == 4:  # huge: as many elements as fit the size cap, or a few more
        n = int(rng.choice([max_bytes // 9 - 20, max_bytes // 9 + 10, 70, 257]))
        return [0.25] * max(n, 1)
    if how == 5:  # far beyond the symbolic dimension limits
        return [[0.0] * 2] * int(rng.choice([65, 257]))
    if how == 6:  # deep nesting
        return _nested(int(rng.integers(3, 100)))
    return [] if how == 7 else [[]]


def _leaves(value: Any) -> list[list[Any]]:
    """The innermost lists of a nested list (to plant bad leaves in)."""
    if not isinstance(value, list) or not value:
        return []
    if not isinstance(value[0], list):
        return [value]
    return [leaf for row in value for leaf in _leaves(row)]


def _pick(rng: np.random.Generator, seq: Any) -> Any:
    return seq[int(rng.integers(len(seq)))]


def mutate(
    rng: np.random.Generator, wire: dict[str, Any], cls: type[wm.Message], how: int | None = None
) -> dict[str, Any]:
    """One to three mutations of a valid wire map (the first one of kind ``how``)."""
    w = {k: (np.asarray(v).tolist() if isinstance(v, list) else v) for k, v in wire.items()}
    names = [*wm.field_specs(cls), "schema", "version"]
    for i in range(1 if rng.random() < 0.5 else int(rng.integers(2, 4))):
        name = _pick(rng, names)
        h = how if (i == 0 and how is not None) else int(rng.integers(0, 10))
        if h == 0:  # wrong type
            w[name] = junk(rng)
        elif h == 1:  # missing field
            w.pop(name, None)
        elif h == 2:  # extra field
            w[_pick(rng, ["Schema", "x ", "seq2", "", _text(rng, 6)])] = junk(rng)
        elif h == 3:  # wrong schema
            w["schema"] = _pick(
                rng,
                [
                    *(t.SCHEMA for t in ALL),
                    "",
                    "arcade.state",
                    "arcade.",
                    _text(rng, 20),
                    junk(rng),
                ],
            )
        elif h == 4:  # wrong version
            w["version"] = _pick(rng, [0, 2, -1, 1.0, True, "1", 2**64 - 1, junk(rng)])
        elif h == 5:  # NaN/Inf/huge in a number or an array element
            bad = _pick(
                rng,
                (math.nan, math.inf, -math.inf)
                if rng.random() < 0.5
                else _NASTY_FLOATS + _HUGE_INTS,
            )
            leaves = _leaves(w.get(name))
            if leaves:
                row = _pick(rng, leaves)
                row[int(rng.integers(len(row)))] = bad
            else:
                w[name] = bad
        elif h == 6:  # wrong or huge shape
            w[name] = _reshaped(rng, w.get(name), cls.MAX_BYTES)
        elif h == 7:  # booleans, strings, None, containers inside arrays
            leaves = _leaves(w.get(name))
            bad = _pick(rng, [True, None, "1.0", b"\x00", [1.0], {"a": 1}, msgpack.ExtType(1, b"")])
            if leaves:
                row = _pick(rng, leaves)
                row[int(rng.integers(len(row)))] = bad
            else:
                w[name] = bad
        elif h == 8:  # replayed or older header: the stream checker's business
            w["seq"] = _pick(rng, [0, 1, 2, int(rng.integers(0, 2**63))])
            w["stamp"] = _pick(rng, [0.0, 1.0, 1e12, 1e12 + 1.0, -1e-9, float(rng.random())])
        elif name in w and isinstance(w[name], dict):  # extreme values under known keys
            w[name] = {_pick(rng, _KEYS): _pick(rng, (*_HUGE_INTS, 1e308, -1e308, 5e-324))}
        else:  # huge integers wherever
            w[name] = _pick(rng, _HUGE_INTS)
    return w


def _pack(w: Any) -> bytes:
    return msgpack.packb(w, use_bin_type=True)


def _byte_mutation(rng: np.random.Generator, payload: bytes) -> bytes:
    """Bit flips, truncation, garbage appended or spliced into a valid payload."""
    b = bytearray(payload)
    how = int(rng.integers(0, 4))
    if how == 0 and b:
        for _ in range(int(rng.integers(1, 5))):
            b[int(rng.integers(len(b)))] ^= 1 << int(rng.integers(8))
    elif how == 1:
        b = b[: int(rng.integers(0, max(len(b), 1)))]
    elif how == 2:
        b += rng.bytes(int(rng.integers(1, 17)))
    elif b:
        i = int(rng.integers(len(b)))
        b[i:i] = rng.bytes(int(rng.integers(1, 9)))
    return bytes(b)


def non_utf8(wire: dict[str, Any], cls: type[wm.Message]) -> bytes | None:
    """The payload with one string field's bytes replaced by invalid UTF-8."""
    marker = "\u00a7" * 3  # a 6-byte string that appears nowhere else
    for name, spec in wm.field_specs(cls).items():
        if type(spec).__name__ == "_Str":
            enc = _pack(marker)
            return _pack({**wire, name: marker}).replace(enc, enc[:1] + b"\xff\xfe\xc0\x80\xed\xa0")
    return None


def deep(depth: int) -> bytes:
    """A map whose one value is nested ``depth`` arrays deep (beyond any pack limit)."""
    return b"\x81\xa1x" + b"\x91" * depth + b"\xc0"


def lying_headers(cls: type[wm.Message]) -> list[bytes]:
    """Containers and strings whose length headers promise far more than is there."""
    return [
        b"\xde\xff\xff" + _pack("schema") + _pack(cls.SCHEMA),  # map16 of 65535 pairs
        b"\xdf\xff\xff\xff\xff",  # map32 of 2^32 - 1 pairs
        b"\xdd\x7f\xff\xff\xff",  # array32
        b"\xc6\x7f\xff\xff\xff",  # bin32
        b"\x81\xa6schema\xdb\xff\xff\xff\xff",  # str32
    ]


def make_payloads(
    cls: type[wm.Message],
    recipe: tuple[int, int, int],
    dims: dict[str, int] | None = None,
    with_valid: bool = True,
) -> list[bytes]:
    """:data:`BATCH` payloads for topic ``cls`` from one recipe ``(kind, mutation, seed)``:
    a valid one (another mutation unless ``with_valid``), a structural and a byte-level
    mutation of it, and random bytes or one of the special payloads."""
    kind, how, seed = recipe
    rng = np.random.default_rng(seed)
    record = valid_record(cls, rng, dims)
    wire = (
        record.to_wire() if record is not None else {"schema": cls.SCHEMA, "version": cls.VERSION}
    )
    valid = _pack(wire)
    # Valid (the stream order is random: some are out of order or stale).
    out = [valid if with_valid else _byte_mutation(rng, valid)]
    try:  # a structural mutation
        out.append(_pack(mutate(rng, wire, cls, how if how < 10 else None)))
    except (ValueError, OverflowError, TypeError):  # beyond what msgpack can write
        out.append(_byte_mutation(rng, valid))
    out.append(_byte_mutation(rng, valid))
    if kind < 6:
        out.append(rng.bytes(int(rng.integers(0, 300))))
    elif kind < 9:
        out.append(
            _pick(
                rng,
                [
                    b"",
                    b"\xc1",
                    deep(3000),
                    deep(int(rng.integers(1, 600))),
                    *lying_headers(cls),
                    struct.pack(">Bd", 0xCB, math.nan),
                    b"\x00" * (cls.MAX_BYTES + 1),
                    _pack(list(range(10))),
                    valid + valid,
                ],
            )
        )
    elif kind < 11:
        out.append(non_utf8(wire, cls) or valid)
    elif kind < 13:  # bytes keys, a list instead of a map, a non-string key
        out.append(
            _pick(
                rng,
                [
                    _pack({k.encode(): v for k, v in wire.items()}),
                    _pack(list(wire.values())),
                    _pack({**wire, b"extra": 1}),
                    b"\x81\x01\x02" + valid,
                    b"\x8f" + valid[1:] if valid[:1] != b"\x8f" else valid[:-1],
                ],
            )
        )
    else:
        out.append(valid)  # a replay of the same message
    return out


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
        if "_Array" in kinds:
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
        type(s).__name__ == "_Array" and s.shape and isinstance(s.shape[0], str)
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
    assert decode(wm.Command, _pack(w)).name == "arm"
    bad = non_utf8(w, wm.Command)
    assert bad is not None and b"\xff\xfe" in bad
    with pytest.raises(MessageError) as info:
        decode(wm.Command, bad)
    assert info.value.reason is Reason.NOT_MSGPACK
    with pytest.raises(MessageError) as info:
        decode(wm.Command, _pack({**w, "name": b"arm"}))
    assert info.value.reason is Reason.BAD_TYPE
