"""Valid wire records for the message tests: Hypothesis strategies of every record type, one
fixed sample of each, and the check that a payload is rejected with a given reason (by the
decoder, and counted by a safe handler without reaching its callback)."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

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
)
from services.reception import Receiver, RejectCounter, safe_handler

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


@st.composite
def _reference(draw: st.DrawFn) -> Reference:
    x = draw(_state()).x
    u = np.concatenate([draw(_vec(1, 0.0, 1e3)), draw(_vec(3, -100.0, 100.0))])
    return draw(st.builds(Reference, x=st.just(x), u=st.just(u), t=_floats(0.0, 1e6), **_header()))


STRATEGIES: dict[type, st.SearchStrategy] = {
    Mocap: _mocap(),
    Imu: st.builds(
        Imu, gyro=_vec(3, -100.0, 100.0), accel=st.none() | _vec(3, -1e3, 1e3), **_header()
    ),
    State: _state(),
    Setpoint: _setpoint(),
    Reference: _reference(),
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
        Reference: lambda: Reference(
            x=np.r_[1.0, 2, 3, 0.1, 0.2, 0.3, q, 0.5, -0.5, 0.1],
            u=[5.4, 0.1, -0.1, 0.0],
            t=4.25,
            **head,
        ),
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
