"""Wire messages: exact round trips, the wire layout, records built from numpy and JAX."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import msgpack
import numpy as np
import pytest
from hypothesis import given
from message_samples import ALL, FAST, STRATEGIES, pack, sample, wire

from arcade_core import adaptation
from services import messages as wm
from services.messages import Event, Model, Residual, Setpoint, State, decode, encode

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
        "reference",
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
