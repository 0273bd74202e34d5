"""Wire messages: exact round trips, and every class of malformed payload rejected and counted."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math

import jax.numpy as jnp
import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from arcade_core import adaptation
from services import messages as wm
from services.messages import (
    Command,
    Event,
    Imu,
    MessageError,
    Mocap,
    Model,
    Reason,
    Receiver,
    RejectCounter,
    Residual,
    Setpoint,
    State,
    StreamChecker,
    decode,
    encode,
    safe_handler,
)

ALL = tuple(wm.MESSAGE_TYPES.values())
FAST = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# ------------------------------------------------------------------ valid records


def _floats(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


def _vec(n: int | tuple[int, ...], lo: float, hi: float) -> st.SearchStrategy[np.ndarray]:
    return hnp.arrays(np.float64, n, elements=_floats(lo, hi))


@st.composite
def _quat(draw: st.DrawFn) -> np.ndarray:
    q = draw(_vec(4, -1.0, 1.0).filter(lambda a: np.linalg.norm(a) > 0.1))
    return q / np.linalg.norm(q)


_stamp = _floats(0.0, 1e9)
_ident = st.from_regex(r"[A-Za-z0-9_.\-]{1,20}", fullmatch=True)
_scalars = st.dictionaries(
    st.from_regex(r"[a-z_]{1,10}", fullmatch=True),
    st.one_of(
        st.none(),
        st.booleans(),
        st.integers(-(2**63), 2**64 - 1),
        _floats(-1e300, 1e300),
        st.text(max_size=20),
    ),
    max_size=5,
)


def _header() -> dict[str, st.SearchStrategy]:
    return {
        "seq": st.integers(0, 2**64 - 1),
        "stamp": _stamp,
        "src": st.from_regex(r"[A-Za-z0-9_.:/@\-]{0,40}", fullmatch=True),
    }


@st.composite
def _residual(draw: st.DrawFn) -> Residual:
    d = draw(st.integers(1, 6))
    var = _vec(d, 0.0, 1e6)
    return draw(
        st.builds(
            Residual,
            delta=_vec(d, -1e3, 1e3),
            mean=_vec(d, -1e3, 1e3),
            var_param=var,
            var_between=var,
            var_noise=var,
            var_encoder=var,
            cp_prob=_floats(0.0, 1.0),
            changepoint=st.booleans(),
            state_seq=st.none() | st.integers(0, 2**64 - 1),
            **_header(),
        )
    )


@st.composite
def _model(draw: st.DrawFn) -> Model:
    d, l = draw(st.integers(1, 5)), draw(st.integers(1, 4))
    cov = draw(st.none() | _vec((d, l, l), -10.0, 10.0))
    if cov is not None:
        cov = cov @ np.swapaxes(cov, 1, 2)  # PSD
    return draw(
        st.builds(
            Model,
            theta=_vec((d, l), -1e3, 1e3),
            theta_var=st.none() | _vec((d, l), 0.0, 1e3),
            theta_cov=st.just(cov),
            sigma_tot2=_vec(d, 0.0, 1e3),
            step=st.integers(0, 2**40),
            changepoints=st.integers(0, 1000),
            state_seq=st.none() | st.integers(0, 2**64 - 1),
            **_header(),
        )
    )


@st.composite
def _mocap(draw: st.DrawFn) -> Mocap:
    head = {k: draw(v) for k, v in _header().items()}
    return Mocap(
        position=draw(_vec(3, -1e4, 1e4)),
        quaternion=draw(_quat()),
        body=draw(_ident),
        frame=draw(_ident),
        capture_stamp=draw(_floats(0.0, head["stamp"])),  # captured before it is sent
        **head,
    )


@st.composite
def _state(draw: st.DrawFn) -> State:
    x = np.concatenate(
        [
            draw(_vec(3, -1e4, 1e4)),
            draw(_vec(3, -1e3, 1e3)),
            draw(_quat()),
            draw(_vec(3, -100.0, 100.0)),
        ]
    )
    head = {k: draw(v) for k, v in _header().items()}
    return draw(
        st.builds(
            State,
            x=st.just(x),
            cov_diag=st.none() | _vec(13, 0.0, 1e6),
            mocap_stale=st.booleans(),
            predicted_through_dropout=st.booleans(),
            meas_stamp=st.none() | _floats(0.0, head["stamp"]),
            **{k: st.just(v) for k, v in head.items()},
        )
    )


@st.composite
def _setpoint(draw: st.DrawFn) -> Setpoint:
    u = np.concatenate([draw(_vec(1, 0.0, 1e3)), draw(_vec(3, -100.0, 100.0))])
    return draw(
        st.builds(
            Setpoint,
            u=st.just(u),
            state_seq=st.integers(0, 2**64 - 1),
            mode=st.sampled_from(wm.MODES),
            solve_ms=_floats(0.0, 1e3),
            **_header(),
        )
    )


STRATEGIES: dict[type, st.SearchStrategy] = {
    Mocap: _mocap(),
    Imu: st.builds(
        Imu, gyro=_vec(3, -100.0, 100.0), accel=st.none() | _vec(3, -1e3, 1e3), **_header()
    ),
    State: _state(),
    Setpoint: _setpoint(),
    Residual: _residual(),
    Model: _model(),
    Event: st.builds(
        Event,
        kind=st.sampled_from(wm.EVENT_KINDS)
        | st.from_regex(r"[a-z][a-z0-9_]{0,10}", fullmatch=True),
        severity=st.sampled_from(wm.SEVERITIES),
        text=st.text(max_size=100),
        data=_scalars,
        **_header(),
    ),
    Command: st.builds(
        Command,
        name=st.sampled_from(wm.COMMANDS),
        target=st.just("") | _ident,
        args=_scalars,
        **_header(),
    ),
}


def sample(cls: type) -> wm.Message:
    """One fixed valid record of each type."""
    q = np.array([0.9, 0.1, -0.3, 0.2])
    q /= np.linalg.norm(q)
    head = {"seq": 7, "stamp": 12.5, "src": "svc/abc"}
    d, l = 3, 2
    return {
        Mocap: lambda: Mocap(position=[1.0, 2.0, 0.5], quaternion=q, capture_stamp=12.4, **head),
        Imu: lambda: Imu(gyro=[0.1, -0.2, 0.3], accel=[0.0, 0.0, 9.81], **head),
        State: lambda: State(x=np.r_[1.0, 2, 3, 0.1, 0.2, 0.3, q, 0.5, -0.5, 0.1], **head),
        Setpoint: lambda: Setpoint(u=[5.4, 0.1, -0.1, 0.0], state_seq=6, **head),
        Residual: lambda: Residual(
            delta=np.arange(d) * 0.1,
            mean=np.ones(d),
            var_param=np.full(d, 0.1),
            var_between=np.full(d, 0.2),
            var_noise=np.full(d, 0.3),
            var_encoder=np.full(d, 0.4),
            cp_prob=0.25,
            **head,
        ),
        Model: lambda: Model(
            theta=np.arange(d * l, dtype=float).reshape(d, l),
            theta_var=np.ones((d, l)),
            theta_cov=np.broadcast_to(np.eye(l), (d, l, l)),
            sigma_tot2=np.full(d, 0.5),
            step=10,
            **head,
        ),
        Event: lambda: Event(kind="changepoint", text="payload", data={"p": 0.9, "k": 3}, **head),
        Command: lambda: Command(name="release_payload", target="simulator", **head),
    }[cls]()


def wire(cls: type) -> dict:
    return sample(cls).to_wire()


def pack(obj: object) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def assert_rejected(cls: type, payload: bytes, reason: Reason) -> None:
    """``decode`` raises ``reason`` and a safe handler counts it without calling back."""
    with pytest.raises(MessageError) as info:
        decode(cls, payload)
    assert info.value.reason is reason, str(info.value)
    counter, got = RejectCounter(), []
    handler = safe_handler(Receiver(cls), got.append, counter, topic=cls.TOPIC)
    handler(payload)  # must not raise
    assert got == []
    assert counter.counts == {reason.value: 1}
    assert counter.by_topic == {(cls.TOPIC, reason.value): 1}


# ------------------------------------------------------------------------ round trip


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_roundtrip_exact(cls):
    @FAST
    @given(STRATEGIES[cls])
    def check(record):
        payload = encode(record)
        back = decode(cls.TOPIC, payload)
        assert type(back) is cls
        assert back == record
        assert encode(back) == payload  # bit-exact floats, same field order
        assert decode(None, payload) == record
        for f in dataclasses.fields(cls):
            value = getattr(back, f.name)
            if isinstance(value, np.ndarray):
                assert value.dtype == np.float64
                assert not value.flags.writeable

    check()


def test_wire_layout_is_documented_map():
    s = sample(State)
    data = msgpack.unpackb(encode(s))
    assert list(data)[:2] == ["schema", "version"]
    assert data["schema"] == "arcade.State" and data["version"] == 1
    assert set(data) == {"schema", "version"} | {f.name for f in dataclasses.fields(State)}
    assert data["x"] == s.x.tolist() and data["cov_diag"] is None
    m = msgpack.unpackb(encode(sample(Model)))
    assert np.array(m["theta_cov"]).shape == (3, 2, 2)  # nested lists, row-major


def test_special_floats_roundtrip_bitwise():
    x = np.r_[-0.0, 5e-324, 1e4, np.nextafter(1.0, 2.0), 0, 0, 1.0, 0, 0, 0, 0, 0, 0]
    back = decode("state", encode(State(x=x, stamp=0.0)))
    assert back.x.tobytes() == x.tobytes()


def test_integers_accepted_where_floats_expected():
    w = wire(Setpoint)
    w["stamp"], w["u"] = 5, [3, 0, 0, 0]
    back = decode(Setpoint, pack(w))
    assert back.stamp == 5.0 and isinstance(back.stamp, float)
    assert back.u.dtype == np.float64 and back.thrust == 3.0


def test_records_are_immutable_copies():
    x = sample(State).x.copy()
    s = State(x=x, stamp=1.0)
    x[0] = 99.0
    assert s.x[0] == 1.0
    with pytest.raises(ValueError):
        s.x[0] = 5.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.stamp = 2.0  # type: ignore[misc]
    e = sample(Event)
    with pytest.raises(TypeError):
        e.data["p"] = 1.0  # type: ignore[index]
    assert s.replace(stamp=2.0).stamp == 2.0 and s.stamp == 1.0


def test_message_type_lookup():
    for name in ("state", "arcade.State", "arcade/quad1/state", State):
        assert wm.message_type(name) is State
    assert wm.TOPICS == (
        "mocap",
        "imu",
        "state",
        "setpoint",
        "residual",
        "model",
        "event",
        "command",
    )
    with pytest.raises(KeyError):
        wm.message_type("telemetry")


# ---------------------------------------------------------- numpy / JAX helpers


def test_build_from_jax_and_back():
    q = jnp.array([1.0, 0.0, 0.0, 0.0], dtype=jnp.float32)
    omega = jnp.array([0.1, 0.2, 0.3], dtype=jnp.float32)
    s = State.from_parts(p=jnp.ones(3), v=jnp.zeros(3), q=q, omega=omega, stamp=2.0)
    assert s.x.dtype == np.float64 and s.x.shape == (13,)
    np.testing.assert_array_equal(s.q, [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(s.omega, np.float32([0.1, 0.2, 0.3]).astype(np.float64))
    np.testing.assert_array_equal(jnp.asarray(decode("state", encode(s)).p), jnp.ones(3))
    sp = Setpoint(u=jnp.array([4.0, 0.1, 0.2, 0.3]), state_seq=jnp.int32(3), stamp=jnp.array(1.5))
    assert sp.thrust == 4.0 and sp.state_seq == 3 and sp.stamp == 1.5
    np.testing.assert_array_equal(sp.rates, [0.1, 0.2, 0.3])


def test_residual_and_model_from_adaptation():
    d, l = 4, 3
    config = adaptation.AdaptationConfig(K=3, pi=0.05, beta=0.99, tau2=0.1, sigma2=0.1)
    beam = adaptation.init(jnp.zeros((d, l)), config)
    z = jnp.array([0.5, -1.0, 2.0])
    pred = adaptation.predict(beam, z)
    delta = jnp.array([0.1, 0.0, -0.2, 0.3])
    r = Residual.from_prediction(delta, pred, cp_prob=0.1, changepoint=False, stamp=1.0)
    np.testing.assert_allclose(r.sigma_tot2, np.asarray(pred.sigma_tot2), rtol=1e-12)
    np.testing.assert_allclose(r.variance, np.asarray(pred.variance), rtol=1e-12)
    theta, cov = adaptation.marginal_decoder(beam)
    m = Model.from_marginal(theta, cov, pred.sigma_tot2, step=1, stamp=1.0)
    assert m.theta.shape == (d, l) and m.theta_cov.shape == (d, l, l)
    np.testing.assert_array_equal(m.theta_var, np.diagonal(np.asarray(cov), 0, 1, 2))
    # The controller's z^T Sigma z from the message equals the adapter's parameter variance.
    zs = np.asarray(z)
    np.testing.assert_allclose(
        np.einsum("i,dij,j->d", zs, decode("model", encode(m)).theta_cov, zs),
        np.asarray(pred.param),
        rtol=1e-12,
    )
    assert (
        Model.from_marginal(theta, cov, pred.sigma_tot2, full_cov=False, stamp=1.0).theta_cov
        is None
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
        "_Float": ["1.0", True, [1.0], None],
        "_Int": [1.5, "1", True, -0.0, [1]],
        "_Bool": [1, 0.0, "true", None],
        "_Str": [5, b"bytes", None, ["a"]],
        "_Array": ["abc", 1.0, {"a": 1}],
        "_Scalars": [[1, 2], "x", 3],
    }
    w0 = wire(cls)
    for f in dataclasses.fields(cls):
        kind = type(f.metadata["spec"]).__name__
        values = list(wrong[kind])
        if kind == "_Array" and w0[f.name] is not None:
            flat = np.asarray(w0[f.name])
            for bad in ("1.0", True, None):
                elems = flat.tolist()
                target = elems
                while isinstance(target[0], list):
                    target = target[0]
                target[0] = bad
                values.append(elems)
        if kind == "_Scalars":
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
    arrays = [n for n in _fields_of(cls, "_Array") if w0[n] is not None]
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
        for name in _fields_of(cls, "_Float"):
            w = dict(w0)
            w[name] = bad
            assert_rejected(cls, pack(w), Reason.NON_FINITE)
        for name in _fields_of(cls, "_Array"):
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
        {"data": {f"k{i}": i for i in range(wm.MAX_MAP_ITEMS + 1)}},
        {"data": {"s": "x" * (wm.MAX_MAP_STR + 1)}},
    ],
    Command: [
        {"name": "self_destruct"},
        {"target": "a b"},
        {"args": {"s": "x" * (wm.MAX_MAP_STR + 1)}},
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
