"""Fuzz payloads of the wire messages, for the decoder and the service-handler fuzzing.

:func:`make_payloads` makes :data:`BATCH` payloads of one record type from a recipe
``(kind, mutation, seed)`` (:data:`recipes`): random bytes, valid records built from the
field specs (:func:`services.messages.field_specs`), and valid records with mutations
(wrong types, wrong and huge shapes, NaN/Inf, wrong schema name or version, missing and
extra fields, replayed and older headers, deep nesting, huge integers, non-UTF-8 and binary
strings, msgpack extension types, bit flips, truncation, lying length headers).

Hypothesis draws a recipe per example and the batch is made from it with NumPy: generating
through hypothesis' own strategies costs milliseconds per payload, which 10^4 cases per
type cannot afford. With ``derandomize=True`` (:func:`fuzz_settings`) a failure names a
reproducible recipe.
"""

from __future__ import annotations

import dataclasses
import math
import struct
from typing import Any

import msgpack
import numpy as np
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from services import message_fields as mf
from services import messages as wm
from services.messages import MessageError

ALL = tuple(wm.MESSAGE_TYPES.values())
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
    if spec.pattern.pattern == mf.SRC.pattern:
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
    if kind == "FloatSpec":
        lo, hi = max(spec.lo, -1e9), min(spec.hi, 1e9)
        return float(_pick(rng, [lo, hi, lo + (hi - lo) * rng.random()]))
    if kind == "IntSpec":
        # Mostly small (so that streams stay in order), sometimes the extremes.
        small = min(spec.hi, spec.lo + int(rng.integers(0, 2**40)))
        return _pick(rng, [spec.lo, small, small, small, spec.hi])
    if kind == "BoolSpec":
        return bool(rng.integers(2))
    if kind == "StrSpec":
        return _string(rng, spec, default)
    if kind == "ScalarsSpec":
        return _scalars(rng)
    if kind == "ArraySpec":
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


def pack(w: Any) -> bytes:
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
        if type(spec).__name__ == "StrSpec":
            enc = pack(marker)
            return pack({**wire, name: marker}).replace(enc, enc[:1] + b"\xff\xfe\xc0\x80\xed\xa0")
    return None


def deep(depth: int) -> bytes:
    """A map whose one value is nested ``depth`` arrays deep (beyond any pack limit)."""
    return b"\x81\xa1x" + b"\x91" * depth + b"\xc0"


def lying_headers(cls: type[wm.Message]) -> list[bytes]:
    """Containers and strings whose length headers promise far more than is there."""
    return [
        b"\xde\xff\xff" + pack("schema") + pack(cls.SCHEMA),  # map16 of 65535 pairs
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
    valid = pack(wire)
    # Valid (the stream order is random: some are out of order or stale).
    out = [valid if with_valid else _byte_mutation(rng, valid)]
    try:  # a structural mutation
        out.append(pack(mutate(rng, wire, cls, how if how < 10 else None)))
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
                    pack(list(range(10))),
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
                    pack({k.encode(): v for k, v in wire.items()}),
                    pack(list(wire.values())),
                    pack({**wire, b"extra": 1}),
                    b"\x81\x01\x02" + valid,
                    b"\x8f" + valid[1:] if valid[:1] != b"\x8f" else valid[:-1],
                ],
            )
        )
    else:
        out.append(valid)  # a replay of the same message
    return out
