"""Zenoh bus: real sessions on loopback, liveliness readiness, rejects (routers, ACL, TLS:
test_access_control.py)."""

from __future__ import annotations

import json
import queue
import socket
import struct
import threading

import msgpack
import numpy as np
import pytest
import zenoh

from services import bus as zbus
from services.bus import Bus, load_config, peer_config
from services.messages import Event, Mocap, Reason, Setpoint, State, encode

TIMEOUT = 10.0  # generous upper bound for a loaded machine; never a sleep


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def hub() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


def state(stamp: float, z: float = 1.0) -> State:
    return State(x=np.r_[0.0, 0.0, z, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0], stamp=stamp)


def get(q: queue.Queue, what: str):
    try:
        return q.get(timeout=TIMEOUT)
    except queue.Empty:
        raise AssertionError(f"no {what} within {TIMEOUT} s") from None


# ------------------------------------------------------------------- names, configs


def test_key_expressions_and_names():
    assert zbus.key_expr("quad1", "setpoint") == "arcade/quad1/setpoint"
    assert zbus.alive_key("quad1", "controller") == "arcade/quad1/alive/controller"
    assert zbus.alive_key("quad1", "*") == "arcade/quad1/alive/*"
    for bad in ("a/b", "*", "", "q$1", "x y"):
        with pytest.raises(ValueError):
            zbus.key_expr(bad, "state")
        with pytest.raises(ValueError):
            Bus("quad1", bad)
    with pytest.raises(ValueError):
        zbus.key_expr("quad1", "telemetry")


def test_qos_table():
    assert set(zbus.QOS) == set(zbus.TOPICS)
    for topic in ("state", "setpoint"):
        qos = zbus.QOS[topic]
        assert qos.priority == zenoh.Priority.REAL_TIME
        assert qos.congestion_control == zenoh.CongestionControl.DROP
    # express samples could be lost just after a link comes up (see services.bus.QOS)
    assert not any(q.express for q in zbus.QOS.values())
    for topic in ("mocap", "imu", "model", "residual"):
        assert zbus.QOS[topic].congestion_control == zenoh.CongestionControl.DROP
    for topic in ("event", "command"):
        assert zbus.QOS[topic].congestion_control == zenoh.CongestionControl.BLOCK


def test_a_lossless_bus_blocks_on_congestion_on_every_topic():
    # Lockstep services open their bus lossless: no sample of the loop may be dropped.
    h = hub()
    with Bus("quad1", "lockstep", peer_config(h), lossless=True) as bus:
        for topic in zbus.TOPICS:
            cc = bus.publisher(topic)._pub.congestion_control
            assert cc == zenoh.CongestionControl.BLOCK, topic
    with Bus("quad1", "realtime", peer_config(h)) as bus:
        assert bus.publisher("setpoint")._pub.congestion_control == zenoh.CongestionControl.DROP


def test_shipped_configs_parse_and_default_matches_builder():
    names = sorted(p.name for p in zbus.config_path().parent.glob("*.json5"))
    assert names == [
        "client-tls.json5",
        "peer-loopback.json5",
        "router-acl.json5",
        "router-tls.json5",
        "router-userpass.json5",
        "router.json5",
    ]
    configs = {n: load_config(zbus.config_path(n)) for n in names}  # unknown keys would raise
    assert json.loads(configs["router-acl.json5"].get_json("access_control/enabled"))
    built, shipped = peer_config(), configs["peer-loopback.json5"]
    for key in (
        "mode",
        "listen",
        "connect",
        "scouting/multicast/enabled",
        "scouting/gossip/enabled",
    ):
        assert json.loads(built.get_json(key)) == json.loads(shipped.get_json(key)), key
    assert json.loads(shipped.get_json("scouting/multicast/enabled")) is False
    over = load_config(zbus.config_path(), {"listen/endpoints": ["tcp/127.0.0.1:1"]})
    assert json.loads(over.get_json("listen/endpoints")) == ["tcp/127.0.0.1:1"]


# ----------------------------------------------------------------- peer exchange


def test_state_setpoint_exchange_with_liveliness_readiness():
    h = hub()
    setpoints: queue.Queue = queue.Queue()
    with (
        Bus("quad1", "estimator", peer_config(h)) as est,
        Bus("quad1", "controller", peer_config(h)) as ctl,
    ):

        def on_state(s: State) -> None:
            ctl.put(Setpoint(u=[5.0 + s.x[2], 0.0, 0.1, 0.0], state_seq=s.seq, stamp=s.stamp))

        ctl.subscribe("state", on_state)
        ctl.declare_alive()  # after the subscription: seeing it means the subscription is there
        est.subscribe("setpoint", setpoints.put)
        est.declare_alive()
        est.wait_alive(["controller", "estimator"], TIMEOUT)
        ctl.wait_alive(["estimator"], TIMEOUT)
        assert {"controller", "estimator"} <= est.alive

        for k in range(3):
            assert est.put(state(stamp=0.01 * k, z=float(k))) == k + 1
        got = [get(setpoints, "setpoint") for _ in range(3)]
        assert [sp.state_seq for sp in got] == [1, 2, 3]
        assert [sp.seq for sp in got] == [1, 2, 3]
        assert [sp.thrust for sp in got] == [5.0, 6.0, 7.0]
        assert [sp.stamp for sp in got] == [0.0, 0.01, 0.02]
        assert all(sp.src == ctl.src and sp.src.startswith("controller/") for sp in got)
        assert ctl.rejects.total == 0 and est.rejects.total == 0
        with pytest.raises(TypeError):
            est.publisher("state").put(Setpoint(u=[1.0, 0, 0, 0], state_seq=0, stamp=0.0))


def test_qos_on_the_wire():
    h = hub()
    samples: queue.Queue = queue.Queue()
    with Bus("v", "a", peer_config(h)) as a, Bus("v", "b", peer_config(h)) as b:
        b.session.declare_subscriber("arcade/v/*", samples.put)
        b.declare_alive()
        a.wait_alive(["b"], TIMEOUT)
        a.put(state(0.0))
        a.put(Setpoint(u=[1.0, 0, 0, 0], state_seq=1, stamp=0.0))
        for _ in range(2):
            s = get(samples, "sample")
            topic = str(s.key_expr).rsplit("/", 1)[-1]
            assert s.priority == zbus.QOS[topic].priority == zenoh.Priority.REAL_TIME
            assert s.congestion_control == zenoh.CongestionControl.DROP
            assert str(s.encoding).startswith("application/msgpack")


def test_malformed_payloads_are_counted_not_raised():
    h = hub()
    states: queue.Queue = queue.Queue()
    with Bus("v", "est", peer_config(h)) as sub, Bus("v", "evil", peer_config(h)) as pub:

        def on_state(s: State) -> None:
            if s.x[2] < 0:
                raise RuntimeError("service bug")
            states.put(s)

        sub.subscribe("state", on_state)
        sub.declare_alive()
        pub.wait_alive(["est"], TIMEOUT)
        key = pub.key("state")
        nan = state(0.0).to_wire()
        nan["x"][0] = float("nan")
        wrong = Setpoint(u=[1.0, 0, 0, 0], state_seq=0, stamp=0.0).to_wire()
        forged = [state(5.0).replace(seq=9, src="x/1"), state(6.0).replace(seq=3, src="x/1")]
        for payload in (
            b"\x00\xff garbage",
            msgpack.packb(nan),
            msgpack.packb(wrong),
            b"\xc1" * 5000,
            *(encode(f) for f in forged),
        ):
            pub.session.put(key, payload)
        pub.put(state(1.0, z=-1.0))  # the callback raises
        pub.put(state(2.0, z=2.0))
        # The bus's state publisher has a higher priority than the raw puts: any order.
        received = sorted((get(states, "state") for _ in range(2)), key=lambda s: s.src)
        good, forged_ok = received if received[0].src == pub.src else received[::-1]
        assert forged_ok.src == "x/1" and forged_ok.seq == 9
        assert good.src == pub.src and good.x[2] == 2.0 and good.seq == 2
        assert sub.rejects.wait_total(5, TIMEOUT)
        assert sub.rejects.counts == {
            Reason.NOT_MSGPACK: 1,
            Reason.NON_FINITE: 1,
            Reason.BAD_SCHEMA: 1,
            Reason.OVERSIZE: 1,
            Reason.OUT_OF_ORDER: 1,
        }
        # The callback's own failure on a valid message is not a rejected input.
        assert sub.rejects.wait_failures(1, TIMEOUT)
        assert sub.rejects.failures == {"state": 1}
        assert states.empty()


def test_every_sample_carries_its_put_time_and_transit_is_recorded():
    h = hub()
    states: queue.Queue = queue.Queue()
    with Bus("v", "est", peer_config(h)) as sub, Bus("v", "sim", peer_config(h)) as pub:
        subscription = sub.subscribe("state", states.put)
        sub.declare_alive()
        pub.wait_alive(["est"], TIMEOUT)
        for k in range(5):
            pub.put(state(float(k)))
            get(states, "state")
        # A foreign sender's attachment (garbage, NaN) is no transit time and no reject.
        key = pub.key("state")
        pub.session.put(key, encode(state(10.0).replace(src="x/1", seq=1)), attachment=b"abc")
        pub.session.put(
            key,
            encode(state(11.0).replace(src="x/1", seq=2)),
            attachment=struct.pack("<d", float("nan")),
        )
        get(states, "state")
        get(states, "state")
        hops = list(subscription.transit_s)
        assert len(hops) == 5, hops
        assert all(0.0 <= h < TIMEOUT for h in hops), hops
        assert sub.rejects.total == 0


def test_three_peers_find_each_other_through_the_hub():
    h = hub()
    got: queue.Queue = queue.Queue()
    changes: queue.Queue = queue.Queue()
    with Bus("v", "hub", peer_config(h)) as first:
        b = Bus("v", "sim", peer_config(h)).open()
        c = Bus("v", "ctl", peer_config(h)).open()
        try:
            c.subscribe("mocap", got.put)
            c.declare_alive()
            b.wait_alive(["ctl"], TIMEOUT)
            q = [1.0, 0.0, 0.0, 0.0]
            b.put(Mocap(position=[1.0, 2.0, 3.0], quaternion=q, capture_stamp=0.5, stamp=0.5))
            m = get(got, "mocap")
            assert m.src == b.src and list(m.position) == [1.0, 2.0, 3.0]
            # peers link directly, not only through the hub
            assert str(c.session.zid()) in {str(z) for z in b.session.info.peers_zid()}
            first.wait_alive(["ctl"], TIMEOUT)
            first.on_alive_change(lambda service, up: changes.put((service, up)))
        finally:
            c.close()
            b.close()
        assert get(changes, "liveliness change") == ("ctl", False)
        assert "ctl" not in first.alive


def test_wait_alive_times_out_with_missing_names():
    with Bus("v", "lonely", peer_config(hub())) as bus:
        bus.declare_alive()
        bus.wait_alive(["lonely"], TIMEOUT)
        with pytest.raises(TimeoutError, match="nobody"):
            bus.wait_alive(["lonely", "nobody"], timeout=0.05)
        bus.withdraw_alive()
        with pytest.raises(RuntimeError):
            Bus("v", "closed").session  # noqa: B018


# ------------------------------------------------------------------- concurrency


def test_bus_callbacks_may_run_concurrently_with_publishing():
    # A callback that publishes (controller pattern) from Zenoh's thread while the main
    # thread publishes too: seq stays strictly increasing per publisher.
    h = hub()
    seen: queue.Queue = queue.Queue()
    with Bus("v", "a", peer_config(h)) as a, Bus("v", "b", peer_config(h)) as b:
        b.subscribe("event", seen.put)
        b.declare_alive()
        a.wait_alive(["b"], TIMEOUT)

        def burst() -> None:
            for k in range(50):
                a.put(Event(kind="info", text=f"t{k}", stamp=1.0))

        threads = [threading.Thread(target=burst) for _ in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(TIMEOUT)
        seqs = [get(seen, "event").seq for _ in range(100)]
        assert seqs == list(range(1, 101))
        assert b.rejects.total == 0
