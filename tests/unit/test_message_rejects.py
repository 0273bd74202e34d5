"""Wire messages: every class of malformed payload rejected with its reason and counted."""

from __future__ import annotations

import contextlib
import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from message_samples import ALL, FAST, assert_rejected, pack, wire

from services import message_fields as mf
from services import messages as wm
from services.messages import (
    Command,
    Event,
    Imu,
    MessageError,
    Mocap,
    Model,
    Reason,
    Reference,
    Residual,
    Setpoint,
    State,
    decode,
    encode,
)

# --------------------------------------------------------------- rejection classes


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_reject_not_msgpack_and_not_map(cls):
    for junk in (
        b"\xc1",
        b"\x92\x01",
        b"\xff" * 40,
        pack(wire(cls)) + b"\x00",
        pack(wire(cls))[:-3],
    ):
        assert_rejected(cls, junk, Reason.NOT_MSGPACK)
    assert_rejected(cls, b"", Reason.NOT_MSGPACK)
    for obj in ([1, 2], 3, "state", None, list(wire(cls).values())):
        assert_rejected(cls, pack(obj), Reason.NOT_MAP)
    with pytest.raises(MessageError) as info:
        decode(cls, "not bytes")
    assert info.value.reason is Reason.NOT_MSGPACK


@FAST
@given(st.binary(max_size=200))
def test_random_bytes_only_ever_raise_message_error(payload):
    for cls in (None, *ALL):
        with contextlib.suppress(MessageError):
            decode(cls, payload)


_json = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=5),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=5), inner, max_size=4)
    ),
    max_leaves=12,
)


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_field_mutations_only_ever_raise_message_error(cls):
    names = [f.name for f in dataclasses.fields(cls)]

    @FAST
    @given(st.sampled_from(names), _json)
    def check(name, value):
        w = wire(cls)
        w[name] = value
        with contextlib.suppress(MessageError):
            assert type(decode(cls, pack(w))) is cls

    check()


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_reject_oversize_before_unpacking(cls):
    # Garbage one byte over the cap: rejected for size, so it was never unpacked.
    assert_rejected(cls, b"\xc1" * (cls.MAX_BYTES + 1), Reason.OVERSIZE)
    w = wire(cls)
    w["src"] = "x" * cls.MAX_BYTES
    assert_rejected(cls, pack(w), Reason.OVERSIZE)


def test_reject_huge_arrays():
    w = wire(Residual)
    for k in ("delta", "mean", "var_param", "var_between", "var_noise", "var_encoder"):
        w[k] = [0.0] * (wm.MAX_DIMS["d"] + 1)  # fits the byte cap, exceeds the dimension cap
    assert_rejected(Residual, pack(w), Reason.BAD_SHAPE)
    w = wire(Model)
    w["theta"] = [[0.0] * 10] * 10**5
    assert_rejected(Model, pack(w), Reason.OVERSIZE)
    d, l = wm.MAX_DIMS["d"], wm.MAX_DIMS["l"] + 1
    with pytest.raises(MessageError) as info:
        Model(theta=np.zeros((d, l)), sigma_tot2=np.zeros(d), stamp=0)
    assert info.value.reason is Reason.BAD_SHAPE


def test_largest_legal_model_fits_its_byte_cap():
    """Every shape MAX_DIMS allows can be sent: the byte cap follows from the dimensions."""
    d, l = wm.MAX_DIMS["d"], wm.MAX_DIMS["l"]
    big = Model(
        theta=np.full((d, l), -MAX_F),
        theta_var=np.full((d, l), 0.5),
        theta_cov=np.broadcast_to(np.eye(l) * 0.5, (d, l, l)),
        sigma_tot2=np.full(d, 0.5),
        step=2**63,
        changepoints=2**63,
        state_seq=2**63,
        seq=2**64 - 1,
        stamp=wm.MAX_STAMP_S,
        src="s" * 128,
    )
    payload = encode(big)  # raised OVERSIZE when l could reach 256
    assert len(payload) <= Model.MAX_BYTES
    assert decode("model", payload) == big


MAX_F = -1.2345678901234567e5  # a float64 that needs all 9 bytes of msgpack


def test_covariance_checks_accept_a_float32_posterior():
    """The adapter computes in float32: its (symmetrised) covariances pass the checks."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(13, 8, 8)).astype(np.float32)
    a[:, :, 0] = a[:, :, 1] * 1.0001  # nearly singular: correlations close to 1
    cov = np.einsum("dij,dkj->dik", a, a)
    cov = (0.5 * (cov + np.swapaxes(cov, 1, 2))).astype(np.float64)
    m = Model(theta=np.zeros((13, 8)), theta_cov=cov, sigma_tot2=np.zeros(13), stamp=0.0)
    assert decode("model", encode(m)) == m


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_reject_schema_and_version(cls):
    other = next(t for t in ALL if t is not cls)
    for schema in (None, other.SCHEMA, "arcade.state", 1):
        w = wire(cls)
        if schema is None:
            del w["schema"]
        else:
            w["schema"] = schema
        assert_rejected(cls, pack(w), Reason.BAD_SCHEMA)
    for version in (None, 2, 0, "1", 1.0, True):
        w = wire(cls)
        if version is None:
            del w["version"]
        else:
            w["version"] = version
        assert_rejected(cls, pack(w), Reason.BAD_VERSION)
    # decode(None, ...) dispatches on the schema, and still checks it.
    w = wire(cls)
    w["schema"] = "arcade.Telemetry"
    with pytest.raises(MessageError) as info:
        decode(None, pack(w))
    assert info.value.reason is Reason.BAD_SCHEMA


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_reject_missing_and_extra_fields(cls):
    for f in dataclasses.fields(cls):
        w = wire(cls)
        del w[f.name]
        assert_rejected(cls, pack(w), Reason.MISSING_FIELD)
    w = wire(cls)
    w["extra"] = 1
    assert_rejected(cls, pack(w), Reason.EXTRA_FIELD)


def _spec(cls: type, name: str):
    return next(f for f in dataclasses.fields(cls) if f.name == name).metadata["spec"]


def _fields_of(cls: type, kind: str) -> list[str]:
    return [f.name for f in dataclasses.fields(cls) if type(f.metadata["spec"]).__name__ == kind]


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_reject_wrong_types(cls):
    wrong = {
        "FloatSpec": ["1.0", True, [1.0], None],
        "IntSpec": [1.5, "1", True, -0.0, [1]],
        "BoolSpec": [1, 0.0, "true", None],
        "StrSpec": [5, b"bytes", None, ["a"]],
        "ArraySpec": ["abc", 1.0, {"a": 1}],
        "ScalarsSpec": [[1, 2], "x", 3],
    }
    w0 = wire(cls)
    for f in dataclasses.fields(cls):
        kind = type(f.metadata["spec"]).__name__
        values = list(wrong[kind])
        if kind == "ArraySpec" and w0[f.name] is not None:
            flat = np.asarray(w0[f.name])
            for bad in ("1.0", True, None):
                elems = flat.tolist()
                target = elems
                while isinstance(target[0], list):
                    target = target[0]
                target[0] = bad
                values.append(elems)
        if kind == "ScalarsSpec":
            values += [{"ok": [1.0]}, {"ok": {"a": 1}}, {"bad key": 1}]
        for value in values:
            if value is None and getattr(f.metadata["spec"], "optional", False):
                continue
            w = dict(w0)
            w[f.name] = value
            assert_rejected(cls, pack(w), Reason.BAD_TYPE)


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_reject_wrong_shapes(cls):
    w0 = wire(cls)
    arrays = [n for n in _fields_of(cls, "ArraySpec") if w0[n] is not None]
    for name in arrays:
        value = w0[name]
        variants = [[value], value + value[:1]]  # extra nesting; one element too many
        if isinstance(value[0], list):
            variants += [value[0], [value[0], value[1][:-1], *value[2:]]]  # too flat; ragged
        else:
            variants += [value[:-1], [[v] for v in value]]
        for bad in variants:
            w = dict(w0)
            w[name] = bad
            assert_rejected(cls, pack(w), Reason.BAD_SHAPE)
    if cls in (Residual, Model):  # symbolic dimensions must agree across fields
        w = dict(w0)
        w["sigma_tot2" if cls is Model else "mean"] = [0.0] * 5
        assert_rejected(cls, pack(w), Reason.BAD_SHAPE)


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_reject_non_finite(cls):
    w0 = wire(cls)
    for bad in (math.nan, math.inf, -math.inf):
        for name in _fields_of(cls, "FloatSpec"):
            w = dict(w0)
            w[name] = bad
            assert_rejected(cls, pack(w), Reason.NON_FINITE)
        for name in _fields_of(cls, "ArraySpec"):
            if w0[name] is None:
                continue
            elems = np.asarray(w0[name]).tolist()
            target = elems
            while isinstance(target[-1], list):
                target = target[-1]
            target[-1] = bad
            w = dict(w0)
            w[name] = elems
            assert_rejected(cls, pack(w), Reason.NON_FINITE)
    if cls in (Event, Command):
        w = dict(w0)
        w["data" if cls is Event else "args"] = {"x": math.nan}
        assert_rejected(cls, pack(w), Reason.NON_FINITE)


def _q(scale: float) -> list[float]:
    return [scale, 0.0, 0.0, 0.0]


OUT_OF_RANGE = {
    Mocap: [
        {"quaternion": _q(0.0)},
        {"quaternion": _q(1.0 + 2 * wm.QUAT_NORM_TOL)},
        {"quaternion": [0.5, 0.5, 0.5, 0.6]},
        {"position": [1e5, 0.0, 0.0]},
        {"body": ""},
        {"body": "a/b"},
        {"capture_stamp": -1.0},
        {"capture_stamp": 12.6},  # captured after it was sent (stamp 12.5)
    ],
    Imu: [{"gyro": [0.0, 500.0, 0.0]}, {"accel": [0.0, 0.0, -1e4]}],
    State: [
        {"x": [0.0] * 6 + _q(1.1) + [0.0] * 3},
        {"x": [0.0] * 6 + [0.7, 0.7, 0.0, 0.0] + [0.0] * 3},
        {"x": [2e4] + [0.0] * 5 + _q(1.0) + [0.0] * 3},
        {"x": [0.0] * 3 + [5e3, 0.0, 0.0] + _q(1.0) + [0.0] * 3},
        {"x": [0.0] * 6 + _q(1.0) + [0.0, 0.0, 1e3]},
        {"cov_diag": [-1.0] + [0.0] * 12},
        {"meas_stamp": -0.5},
        {"meas_stamp": 12.6},  # measured after the state's instant (stamp 12.5)
    ],
    Setpoint: [
        {"u": [-0.1, 0.0, 0.0, 0.0]},
        {"u": [1e4, 0.0, 0.0, 0.0]},
        {"u": [5.0, 0.0, 150.0, 0.0]},
        {"mode": "dance"},
        {"solve_ms": -1.0},
        {"state_seq": -1},
        {"failsafe": "x" * 65},
    ],
    Reference: [
        {"x": [0.0] * 6 + _q(1.1) + [0.0] * 3},
        {"x": [2e4] + [0.0] * 5 + _q(1.0) + [0.0] * 3},
        {"u": [-0.1, 0.0, 0.0, 0.0]},
        {"u": [5.0, 0.0, 150.0, 0.0]},
        {"t": -1.0},
    ],
    Residual: [
        {"cp_prob": 1.5},
        {"cp_prob": -0.1},
        {"var_noise": [-1.0, 0.0, 0.0]},
        {"delta": [1e9, 0.0, 0.0]},
        {"state_seq": -3},
    ],
    Model: [
        {"theta_cov": [[[-1.0, 0.0], [0.0, 1.0]]] * 3},
        {"theta_cov": [[[1.0, 0.5], [0.4, 1.0]]] * 3},  # not symmetric
        {"theta_cov": [[[1.0, 2.0], [2.0, 1.0]]] * 3},  # eigenvalue -1: not PSD
        {"theta_var": [[0.0, -1.0]] * 3},
        {"sigma_tot2": [0.0, -1e-3, 0.0]},
        {"theta": [[1e9, 0.0]] * 3},
        {"changepoints": -1},
    ],
    Event: [
        {"severity": "fatal"},
        {"kind": "Bad Kind"},
        {"kind": ""},
        {"text": "x" * 1025},
        {"data": {f"k{i}": i for i in range(mf.MAX_MAP_ITEMS + 1)}},
        {"data": {"s": "x" * (mf.MAX_MAP_STR + 1)}},
    ],
    Command: [
        {"name": "self_destruct"},
        {"target": "a b"},
        {"args": {"s": "x" * (mf.MAX_MAP_STR + 1)}},
    ],
}


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_reject_out_of_range(cls):
    over = 1.01 * wm.MAX_STAMP_S
    cases = [*OUT_OF_RANGE[cls], {"seq": -1}, {"stamp": -1.0}, {"stamp": over}, {"src": "a b"}]
    for change in cases:
        w = wire(cls)
        w.update(change)
        assert_rejected(cls, pack(w), Reason.OUT_OF_RANGE)


def test_stamps_fit_nanosecond_uint64_logs():
    # Recorders write stamps as uint64 nanoseconds (MCAP publish_time).
    assert int(wm.MAX_STAMP_S * 1e9) < 2**64
    assert decode(Imu, pack({**wire(Imu), "stamp": wm.MAX_STAMP_S})).stamp == wm.MAX_STAMP_S


def test_construction_validates_like_decoding():
    with pytest.raises(MessageError) as info:
        Setpoint(u=[-1.0, 0.0, 0.0, 0.0], state_seq=0, stamp=0.0)
    assert info.value.reason is Reason.OUT_OF_RANGE and info.value.field == "u"
    with pytest.raises(MessageError) as info:
        State(x=np.full(13, np.nan), stamp=0.0)
    assert info.value.reason is Reason.NON_FINITE
    with pytest.raises(MessageError) as info:
        Imu(gyro=np.array([True, False, True]), stamp=0.0)
    assert info.value.reason is Reason.BAD_TYPE
    with pytest.raises(MessageError) as info:
        Imu(gyro=np.zeros(3, dtype=np.complex128), stamp=0.0)
    assert info.value.reason is Reason.BAD_TYPE
