"""The stack through the ACL router: every process a client with its own user.

The shipped ``deploy/zenoh/router-acl.json5`` runs in this process (a Python Zenoh session
in router mode) on a free loopback port with a dictionary file of test passwords. Each
process of the stack (launcher, recorder, estimator, adapter, controller, simulator) gets
its own client configuration file (``StackConfig.bus_configs``, ``--bus-config``) and
flies a short lockstep take-off and hover. Checks: the flight completes cleanly, state,
setpoints, models and residuals flowed (one setpoint per control instant, the adapter
learned at every step), nothing was rejected, no process logged an error, and every
(topic, writer) pair recorded is one the ACL allows, each of the flight's writers seen
(the launcher's event included).

Plus a service's error on an unreadable ``--bus-config``; the usage errors of
``arcade up --bus-configs`` are in ``tests/unit/test_bus_configs.py``.
"""

from __future__ import annotations

import json
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh
from mcap.reader import make_reader

from arcade.demo_stack import read_truth
from deploy.launcher import REPO, SERVICES, StackConfig, run_flight
from services.bus import config_path, load_config

#: The user of each process (the ACL's subjects name users, not processes).
USERS = {
    "launcher": "launcher",
    "recorder": "recorder",
    "estimator": "estimator",
    "adapter": "adapter",
    "controller": "controller",
    "sim": "simulator",
}
DURATION = 2.0
RATE = 20.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def allowed_puts(config: zenoh.Config) -> set[tuple[str, str]]:
    """``(topic, user)`` pairs the ACL of ``config`` lets put (ingress)."""
    acl = json.loads(config.get_json("access_control"))
    rules = {
        r["id"]: r
        for r in acl["rules"]
        if r["permission"] == "allow" and "ingress" in r["flows"] and "put" in r["messages"]
    }
    users = {s["id"]: s["usernames"] or [] for s in acl["subjects"]}
    pairs = set()
    for policy in acl["policies"]:
        for rule in (rules[r] for r in policy["rules"] if r in rules):
            for key in rule["key_exprs"]:
                assert key.startswith("arcade/*/") and key.count("/") == 2, key
                for subject in policy["subjects"]:
                    pairs |= {(key.rsplit("/", 1)[1], user) for user in users[subject]}
    return pairs


def client_configs(folder: Path, endpoint: str, passwords: dict[str, str]) -> dict[str, Path]:
    """One client configuration per process: ``folder/<process>.json5``."""
    folder.mkdir(parents=True, exist_ok=True)
    files = {}
    for process, user in USERS.items():
        tree = {
            "mode": "client",
            "connect": {"endpoints": [endpoint]},
            "scouting": {"multicast": {"enabled": False}},
            "transport": {"auth": {"usrpwd": {"user": user, "password": passwords[user]}}},
        }
        files[process] = folder / f"{process}.json5"
        files[process].write_text(json.dumps(tree, indent=1))
    return files


@pytest.fixture
def acl_router(tmp_path):
    """The shipped ACL router on a free loopback port; yields ``(bus_configs, allowed)``:
    a client configuration per process and the ``(topic, user)`` puts the ACL allows."""
    passwords = {user: f"pw-{user}" for user in USERS.values()}
    users = tmp_path / "users.txt"
    users.write_text("".join(f"{u}:{p}\n" for u, p in passwords.items()))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = load_config(
        config_path("router-acl.json5"),
        {"listen/endpoints": [endpoint], "transport/auth/usrpwd/dictionary_file": str(users)},
    )
    with zenoh.open(config):
        yield client_configs(tmp_path / "bus", endpoint, passwords), allowed_puts(config)


def fly(out: Path, bus_configs: dict[str, Path], lockstep: bool) -> dict:
    """A short take-off and hover through the router (the launcher puts one event)."""
    cfg = StackConfig(
        out=out,
        lockstep=lockstep,
        method="ours",
        rate=RATE,
        duration=DURATION,
        hover_s=1000.0,
        realtime_priority=False,
        max_restarts=0,
        ready_timeout=120.0,
        bus_configs=bus_configs,
    )
    assert "--hub" not in cfg.args("controller")
    result = run_flight(
        cfg,
        timeout=120.0,
        on_ready=lambda stack: stack.emit("info", "launcher event through the router"),
    )
    assert all(code == 0 for code in result["codes"].values()), result["codes"]
    assert result["restarts"] == {}
    for name in SERVICES:
        stats = json.loads((out / "stats" / f"{name}.json").read_text())
        assert stats.get("rejects", {}) == {}, (name, stats.get("rejects"))
    for log in (out / "logs").glob("*.log"):
        text = log.read_text()
        assert " ERROR " not in text and "Traceback" not in text, log.name
    return {name: json.loads((out / "stats" / f"{name}.json").read_text()) for name in SERVICES}


def recorded(out: Path) -> list[tuple[str, str, dict]]:
    """``(topic, user of the writer, wire map)`` of every message in the recording."""
    rows = []
    with (out / "bus.mcap").open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            if channel.message_encoding != "json":  # the Foxglove drawing beside
                continue
            wire = json.loads(message.data)
            rows.append((channel.topic.rsplit("/", 1)[-1], USERS[wire["src"].split("/")[0]], wire))
    return rows


def test_lockstep_flight_through_the_acl_router(tmp_path, acl_router):
    bus_configs, allowed = acl_router
    out = tmp_path / "run"
    stats = fly(out, bus_configs, lockstep=True)
    steps = round(DURATION * RATE) + 1
    assert stats["sim"]["mode"] == "lockstep"
    assert not stats["sim"]["crashed"] and stats["sim"]["timeouts"] == 0
    assert stats["sim"]["steps"] == steps
    # A setpoint for every control instant; the adapter learned from each one applied
    # (every step but the first, which has no previous setpoint).
    assert stats["controller"]["setpoints"] == steps
    assert stats["adapter"]["learned"] == steps - 1, stats["adapter"]
    truth = read_truth(out / "truth.csv")
    assert truth["t"].size == steps
    assert abs(truth["pz"][-1] - truth["ref_pz"][-1]) < 0.1
    assert len((out / "flight_log.csv").read_text().splitlines()) - 1 == steps
    # Every (topic, writer) recorded is one the ACL allows, and each writer of the flight
    # got through (a denied put would be missing here).
    seen = {(topic, user) for topic, user, _ in recorded(out)}
    assert seen <= allowed, seen - allowed
    assert {
        ("mocap", "simulator"),
        ("imu", "simulator"),
        ("event", "simulator"),
        ("state", "estimator"),
        ("setpoint", "controller"),
        ("model", "adapter"),
        ("residual", "adapter"),
        ("event", "launcher"),
    } <= seen, seen


@pytest.mark.realtime
def test_realtime_mission_start_passes_the_acl_router(tmp_path, acl_router):
    # On the wall clock the simulator starts the mission with a `start` command once
    # setpoints stream: the controller's mission clock and the adapter's learning wait
    # for it.
    bus_configs, allowed = acl_router
    out = tmp_path / "run"
    stats = fly(out, bus_configs, lockstep=False)
    assert stats["sim"]["mode"] == "realtime" and not stats["sim"]["crashed"]
    assert stats["sim"]["steps"] == round(DURATION * RATE) + 1
    rows = recorded(out)
    assert {(topic, user) for topic, user, _ in rows} <= allowed
    starts = [w for topic, user, w in rows if topic == "command" and user == "simulator"]
    assert [w["name"] for w in starts] == ["start"], starts
    assert "mission clock started" in (out / "logs" / "controller.log").read_text()
    assert "mission started" in (out / "logs" / "adapter.log").read_text()
    assert stats["adapter"]["learned"] >= stats["sim"]["steps"] // 2, stats["adapter"]


def test_relative_tls_paths_resolve_where_the_stack_starts(certs, tmp_path, monkeypatch):
    # Each process's client configuration names the router's CA by a path relative to the
    # folder the stack is started from: the services run there, like the launcher, and a
    # `services` package in that folder is not imported in place of the stack's.
    here = tmp_path / "here"
    (here / "certs").mkdir(parents=True)
    shutil.copy(certs / "ca.pem", here / "certs" / "ca.pem")
    (here / "services").mkdir()
    (here / "services" / "__init__.py").write_text("raise ImportError('not the stack')\n")
    monkeypatch.chdir(here)
    port = free_port()
    router = load_config(
        config_path("router-tls.json5"),
        {
            "listen/endpoints": [f"tls/127.0.0.1:{port}"],
            "transport/link/tls": {
                "listen_certificate": str(certs / "router.pem"),
                "listen_private_key": str(certs / "router.key"),
            },
        },
    )
    (here / "bus").mkdir()
    configs = {}
    for process in USERS:
        tree = {
            "mode": "client",
            "connect": {"endpoints": [f"tls/localhost:{port}"]},
            "scouting": {"multicast": {"enabled": False}},
            "transport": {"link": {"tls": {"root_ca_certificate": "certs/ca.pem"}}},
        }
        configs[process] = Path("bus") / f"{process}.json5"
        configs[process].write_text(json.dumps(tree))
    with zenoh.open(router):
        stats = fly(tmp_path / "run", configs, lockstep=True)
    assert stats["adapter"]["learned"] == round(DURATION * RATE), stats["adapter"]


def test_service_with_an_unreadable_bus_config_says_which_file(tmp_path):
    missing = tmp_path / "nowhere.json5"
    proc = subprocess.run(
        [sys.executable, "-m", "services", "recorder", "--bus-config", str(missing)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 1
    lines = [r for r in proc.stderr.splitlines() if r.strip()]
    assert lines and lines[-1].endswith(
        f"ERROR arcade.recorder: bus config {missing}: No such file or directory (os error 2)"
    ), proc.stderr
    assert "Traceback" not in proc.stderr
    both = subprocess.run(
        [sys.executable, "-m", "services", "recorder", "--bus-config", str(missing), "--hub", "x"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert both.returncode == 2 and "--hub and --bus-config exclude each other" in both.stderr
