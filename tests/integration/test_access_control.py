"""Access control on the bus: ACL router, user/password, TLS and mutual TLS, on loopback.

Routers are Python Zenoh sessions in router mode started from the shipped configurations
in ``deploy/zenoh/`` (paths and ports overridden); services connect as clients. Certificates
come from the system ``openssl`` (P-256, one CA, plus an unrelated CA for the negative
cases).

No sleeps: a denied message is shown not to be delivered by a *sentinel* the same client
puts afterwards on a topic it may write, with a priority no higher than the denied ones.
Zenoh keeps order per priority on a link and sends higher priorities first, so anything
the router had let through would reach the subscriber (an in-order, on-the-receiving-thread
subscriber of ``arcade/<vehicle>/**``) before the sentinel does.

The embedded bus of ``arcade up`` against a rogue process: ``test_embedded_bus.py``.
"""

from __future__ import annotations

import queue
import socket
from pathlib import Path

import pytest
import zenoh

from services import bus as zbus
from services.bus import Bus, client_config, load_config
from services.messages import Command, Event, Imu, Mocap, Setpoint, decode

TIMEOUT = 10.0  # upper bound for a loaded machine; never a sleep
VEHICLE = "v"
PASSWORDS = {
    "controller": "c-pw",
    "simulator": "s-pw",
    "estimator": "e-pw",
    "adapter": "a-pw",
    "bridge": "b-pw",
    "mocap": "m-pw",
    "recorder": "r-pw",
    "launcher": "l-pw",
    "operator": "o-pw",
    "foxglove": "f-pw",
    "ros2": "r2-pw",
}
#: Who may put what: the table of deploy/zenoh/router-acl.json5 (the writers of both
#: profiles; the recorder writes nothing).
WRITERS = {
    "setpoint": {"controller"},
    "reference": {"controller"},
    "state": {"estimator"},
    "model": {"adapter"},
    "residual": {"adapter"},
    "mocap": {"simulator", "mocap"},
    "imu": {"simulator", "bridge"},
    "event": {
        "controller",
        "estimator",
        "adapter",
        "simulator",
        "bridge",
        "launcher",
        "foxglove",
        "ros2",
    },
    "command": {"simulator", "bridge", "operator"},
}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class RawTap:
    """``(topic, payload)`` of everything on ``arcade/<vehicle>/**``, in arrival order
    (callback on the receiving thread); ``until`` waits for a match and returns those
    before it."""

    def __init__(self, bus: Bus):
        self.q: queue.Queue = queue.Queue()
        handler = zenoh.handlers.Callback(
            lambda s: self.q.put((str(s.key_expr).rsplit("/", 1)[-1], s.payload.to_bytes())),
            indirect=False,
        )
        self._sub = bus.session.declare_subscriber(f"arcade/{VEHICLE}/**", handler)

    def _item(self, topic: str, payload: bytes):
        return topic, payload

    def _matches(self, item, want) -> bool:
        return item[1] == want  # the exact payload

    def until(self, want) -> list:
        seen = []
        while True:
            try:
                got = self.q.get(timeout=TIMEOUT)
            except queue.Empty:
                raise AssertionError(f"not delivered within {TIMEOUT} s; got {seen}") from None
            item = self._item(*got)
            if self._matches(item, want):
                return seen
            seen.append(item)


class Tap(RawTap):
    """As :class:`RawTap`, messages decoded; ``until(pred)`` waits for one that ``pred``
    accepts."""

    def _item(self, topic: str, payload: bytes):
        return decode(topic, payload)

    def _matches(self, item, want) -> bool:
        return want(item)


def _mocap(stamp: float = 0.0) -> Mocap:
    return Mocap(
        position=[0.0, 0.0, 1.0], quaternion=[1.0, 0, 0, 0], capture_stamp=stamp, stamp=stamp
    )


def _setpoint(thrust: float) -> Setpoint:
    return Setpoint(u=[thrust, 0.0, 0.0, 0.0], state_seq=1, stamp=0.0)


# ------------------------------------------------------------------------- ACL


def _acl_router(tmp_path: Path, enabled: bool = True):
    users = tmp_path / "users.txt"
    users.write_text("".join(f"{u}:{p}\n" for u, p in PASSWORDS.items()))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg = load_config(
        zbus.config_path("router-acl.json5"),
        {
            "listen/endpoints": [endpoint],
            "transport/auth/usrpwd/dictionary_file": str(users),
            "access_control/enabled": enabled,
        },
    )
    return zenoh.open(cfg), endpoint


@pytest.fixture
def acl_router(tmp_path: Path):
    router, endpoint = _acl_router(tmp_path)
    with router:
        yield endpoint


def _client(endpoint: str, user: str, password: str | None = None) -> Bus:
    cfg = client_config([endpoint], user=user, password=password or PASSWORDS[user])
    return Bus(VEHICLE, user, cfg)


def test_acl_lets_each_user_put_exactly_its_topics(acl_router):
    # Every user puts every topic (the router does not look into payloads), then a
    # sentinel on a topic it may write at the lowest priority: whatever the router let
    # through arrives before it.
    assert set(WRITERS) == set(zbus.QOS)
    with _client(acl_router, "recorder") as rec:
        tap = RawTap(rec)
        rec.declare_alive()
        for user in sorted(set(PASSWORDS) - {"recorder"}):
            own = sorted(t for t, users in WRITERS.items() if user in users)
            with _client(acl_router, user) as bus:
                bus.wait_alive(["recorder"], TIMEOUT)
                for topic in zbus.QOS:
                    bus.session.put(
                        bus.key(topic),
                        f"{user}:{topic}".encode(),
                        priority=zbus.QOS[topic].priority,
                        congestion_control=zenoh.CongestionControl.BLOCK,
                    )
                sentinel = f"sentinel:{user}".encode()
                bus.session.put(
                    bus.key(own[0]),
                    sentinel,
                    priority=zenoh.Priority.BACKGROUND,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )
                got = tap.until(sentinel)
            assert sorted(t for t, _ in got) == own, (user, got)
            assert all(payload == f"{user}:{t}".encode() for t, payload in got), got


def test_acl_liveliness_tokens_come_and_go(acl_router):
    # Crash detection (a token that disappears) works through the router for every user.
    changes: queue.Queue = queue.Queue()
    with _client(acl_router, "launcher") as launcher:
        launcher.on_alive_change(lambda service, up: changes.put((service, up)))
        for user in sorted(set(PASSWORDS) - {"launcher"}):
            with _client(acl_router, user) as bus:
                bus.declare_alive()
                launcher.wait_alive([user], TIMEOUT)
            assert changes.get(timeout=TIMEOUT) == (user, True)
            assert changes.get(timeout=TIMEOUT) == (user, False)


def test_acl_setpoint_only_from_the_controller(acl_router):
    with (
        _client(acl_router, "recorder") as rec,
        _client(acl_router, "controller") as ctl,
        _client(acl_router, "estimator") as rogue,
        _client(acl_router, "operator") as operator,
    ):
        tap = Tap(rec)
        rec.declare_alive()
        for b in (ctl, rogue, operator):
            b.wait_alive(["recorder"], TIMEOUT)
        # A service that is not the controller (the estimator may put state and events).
        rogue.put(_setpoint(9.0))
        rogue.put(Event(kind="info", text="sentinel", stamp=0.0))  # lower priority
        assert not [m for m in tap.until(lambda m: isinstance(m, Event)) if m.TOPIC == "setpoint"]
        # An operator (may put commands only).
        operator.put(_setpoint(8.0))
        operator.put(Command(name="hold", stamp=0.0))
        assert not [m for m in tap.until(lambda m: isinstance(m, Command)) if m.TOPIC == "setpoint"]
        # The controller's setpoint is delivered.
        ctl.put(_setpoint(1.0))
        assert tap.until(lambda m: isinstance(m, Setpoint) and m.src == ctl.src) == []
        assert rec.rejects.total == 0


def test_acl_sensors_only_from_simulator_or_bridge(acl_router):
    with (
        _client(acl_router, "recorder") as rec,
        _client(acl_router, "simulator") as sim,
        _client(acl_router, "estimator") as rogue,
        _client(acl_router, "controller") as rogue2,
    ):
        tap = Tap(rec)
        rec.declare_alive()
        for b in (sim, rogue, rogue2):
            b.wait_alive(["recorder"], TIMEOUT)
        for bad in (rogue, rogue2):
            bad.put(_mocap())
            bad.put(Imu(gyro=[0.0, 0.0, 0.0], stamp=0.0))
            bad.put(Event(kind="info", text="sentinel", stamp=0.0))
            early = tap.until(lambda m, b=bad: isinstance(m, Event) and m.src == b.src)
            assert not [m for m in early if m.TOPIC in ("mocap", "imu")], early
        sim.put(_mocap(1.0))
        sim.put(Imu(gyro=[0.1, 0.0, 0.0], stamp=1.0))
        got = tap.until(lambda m: isinstance(m, Imu) and m.src == sim.src)
        assert [type(m) for m in got] == [Mocap] and got[0].src == sim.src


def test_without_acl_the_rogue_setpoint_arrives_before_the_sentinel(tmp_path: Path):
    # The same exchange as above with access control off: the sentinel method sees it.
    router, endpoint = _acl_router(tmp_path, enabled=False)
    with router, _client(endpoint, "recorder") as rec, _client(endpoint, "estimator") as rogue:
        tap = Tap(rec)
        rec.declare_alive()
        rogue.wait_alive(["recorder"], TIMEOUT)
        rogue.put(_setpoint(9.0))
        rogue.put(_mocap())
        rogue.put(Event(kind="info", text="sentinel", stamp=0.0))
        early = tap.until(lambda m: isinstance(m, Event))
        assert [type(m) for m in early] == [Setpoint, Mocap]


def test_acl_and_userpass_refuse_wrong_or_missing_credentials(acl_router):
    with pytest.raises(zenoh.ZError):
        _client(acl_router, "controller", "wrong-password").open()
    with pytest.raises(zenoh.ZError):
        Bus(VEHICLE, "anon", client_config([acl_router])).open()
    with pytest.raises(zenoh.ZError):
        Bus(VEHICLE, "ghost", client_config([acl_router], user="ghost", password="x")).open()


def test_userpass_router_profile(tmp_path: Path):
    users = tmp_path / "users.txt"
    users.write_text("controller:c-pw\nsimulator:s-pw\n")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg = load_config(
        zbus.config_path("router-userpass.json5"),
        {"listen/endpoints": [endpoint], "transport/auth/usrpwd/dictionary_file": str(users)},
    )
    got: queue.Queue = queue.Queue()
    with (
        zenoh.open(cfg),
        _client(endpoint, "controller") as ctl,
        _client(endpoint, "simulator") as sim,
    ):
        sim.subscribe("setpoint", got.put)
        sim.declare_alive()
        ctl.wait_alive(["simulator"], TIMEOUT)
        ctl.put(_setpoint(2.0))
        assert got.get(timeout=TIMEOUT).thrust == 2.0
        with pytest.raises(zenoh.ZError):
            _client(endpoint, "simulator", "c-pw").open()  # another user's password
        with pytest.raises(zenoh.ZError):
            Bus(VEHICLE, "anon", client_config([endpoint])).open()


# ------------------------------------------ TLS, mTLS (certificates: conftest.py)


def _tls_router(certs: Path, mtls: bool):
    port = free_port()
    cfg = load_config(
        zbus.config_path("router-tls.json5"),
        {
            "listen/endpoints": [f"tls/127.0.0.1:{port}"],
            "transport/link/tls/listen_certificate": str(certs / "router.pem"),
            "transport/link/tls/listen_private_key": str(certs / "router.key"),
            "transport/link/tls/root_ca_certificate": str(certs / "ca.pem"),
            "transport/link/tls/enable_mtls": mtls,
        },
    )
    return zenoh.open(cfg), [f"tls/localhost:{port}"]


def _exchange(a: Bus, b: Bus) -> None:
    got: queue.Queue = queue.Queue()
    b.subscribe("mocap", got.put)
    b.declare_alive()
    a.wait_alive([b.name], TIMEOUT)
    a.put(_mocap(3.0))
    assert got.get(timeout=TIMEOUT).stamp == 3.0


def test_tls_server_certificate_verified_by_clients(certs: Path):
    router, ep = _tls_router(certs, mtls=False)
    with router:
        ca = {"root_ca": certs / "ca.pem"}
        with (
            Bus(VEHICLE, "simulator", client_config(ep, **ca)) as a,
            Bus(VEHICLE, "estimator", client_config(ep, **ca)) as b,
        ):
            _exchange(a, b)
        # A client that trusts another CA refuses the router's certificate.
        with pytest.raises(zenoh.ZError):
            Bus(VEHICLE, "x", client_config(ep, root_ca=certs / "evil-ca.pem")).open()


def test_mtls_requires_a_client_certificate_of_the_ca(certs: Path):
    router, ep = _tls_router(certs, mtls=True)
    with router:

        def mtls(name: str) -> dict:
            return {
                "root_ca": certs / "ca.pem",
                "cert": certs / f"{name}.pem",
                "key": certs / f"{name}.key",
            }

        with (
            Bus(VEHICLE, "estimator", client_config(ep, **mtls("estimator"))) as a,
            Bus(VEHICLE, "controller", client_config(ep, **mtls("controller"))) as b,
        ):
            _exchange(a, b)
        with pytest.raises(zenoh.ZError):  # no client certificate
            Bus(VEHICLE, "anon", client_config(ep, root_ca=certs / "ca.pem")).open()
        with pytest.raises(zenoh.ZError):  # a certificate from another CA
            Bus(VEHICLE, "intruder", client_config(ep, **mtls("intruder"))).open()


def test_acl_with_passwords_over_tls(certs: Path, tmp_path: Path):
    # The between-hosts profile: router-acl.json5 with the TLS link of router-tls.json5, so
    # that passwords do not travel in clear.
    users = tmp_path / "users.txt"
    users.write_text("".join(f"{u}:{p}\n" for u, p in PASSWORDS.items()))
    port = free_port()
    cfg = load_config(
        zbus.config_path("router-acl.json5"),
        {
            "listen/endpoints": [f"tls/127.0.0.1:{port}"],
            "transport/auth/usrpwd/dictionary_file": str(users),
            "transport/link/tls": {
                "listen_certificate": str(certs / "router.pem"),
                "listen_private_key": str(certs / "router.key"),
            },
        },
    )
    ep = [f"tls/localhost:{port}"]

    def client(user: str, password: str | None = None) -> Bus:
        return Bus(
            VEHICLE,
            user,
            client_config(
                ep, user=user, password=password or PASSWORDS[user], root_ca=certs / "ca.pem"
            ),
        )

    with (
        zenoh.open(cfg),
        client("recorder") as rec,
        client("controller") as ctl,
        client("estimator") as rogue,
    ):
        tap = Tap(rec)
        rec.declare_alive()
        ctl.wait_alive(["recorder"], TIMEOUT)
        rogue.wait_alive(["recorder"], TIMEOUT)
        rogue.put(_setpoint(9.0))
        rogue.put(Event(kind="info", text="sentinel", stamp=0.0))
        assert not [m for m in tap.until(lambda m: isinstance(m, Event)) if m.TOPIC == "setpoint"]
        ctl.put(_setpoint(1.0))
        assert tap.until(lambda m: isinstance(m, Setpoint) and m.src == ctl.src) == []
        with pytest.raises(zenoh.ZError):
            client("controller", "wrong").open()


def test_acl_by_certificate_common_name_over_mtls(certs: Path):
    # router-acl.json5 with mutual TLS instead of passwords: subjects are the client
    # certificates' common names (controller, estimator).
    port = free_port()
    subjects = [
        {"id": "everyone", "cert_common_names": ["controller", "estimator", "recorder"]},
        *(
            {"id": name, "cert_common_names": [name]}
            for name in sorted(set(PASSWORDS) - {"recorder"})
        ),
    ]
    cfg = load_config(
        zbus.config_path("router-acl.json5"),
        {
            "listen/endpoints": [f"tls/127.0.0.1:{port}"],
            "transport/auth": {},
            "transport/link/tls": {
                "listen_certificate": str(certs / "router.pem"),
                "listen_private_key": str(certs / "router.key"),
                "root_ca_certificate": str(certs / "ca.pem"),
                "enable_mtls": True,
            },
            "access_control/subjects": subjects,
        },
    )
    ep = [f"tls/localhost:{port}"]

    def client(name: str) -> Bus:
        return Bus(
            VEHICLE,
            name,
            client_config(
                ep, root_ca=certs / "ca.pem", cert=certs / f"{name}.pem", key=certs / f"{name}.key"
            ),
        )

    with (
        zenoh.open(cfg),
        client("recorder") as rec,
        client("controller") as ctl,
        client("estimator") as est,
    ):
        tap = Tap(rec)
        rec.declare_alive()
        ctl.wait_alive(["recorder"], TIMEOUT)
        est.wait_alive(["recorder"], TIMEOUT)
        est.put(_setpoint(9.0))  # the estimator's certificate may not put setpoints
        est.put(Event(kind="info", text="sentinel", stamp=0.0))
        assert not [m for m in tap.until(lambda m: isinstance(m, Event)) if m.TOPIC == "setpoint"]
        ctl.put(_setpoint(1.0))
        assert tap.until(lambda m: isinstance(m, Setpoint) and m.src == ctl.src) == []
