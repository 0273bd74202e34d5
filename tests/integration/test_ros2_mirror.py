"""The ROS 2 mirror as a process on a private Zenoh hub: what a ROS 2 host on rmw_zenoh would
receive (keys, liveliness tokens, attachments, CDR payloads), read here without the mirror's
own code: literal keys and tokens of rmw_zenoh's format, pycdr2 for the payloads."""

from __future__ import annotations

import contextlib
import json
import queue
import signal
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import xxhash
import zenoh
from ros2_idl import DiagnosticArray, Odometry, Vector3Stamped

from services.bus import Bus, peer_config
from services.messages import Event, Setpoint, State

REPO = Path(__file__).resolve().parents[2]
TIMEOUT = 60.0  # start-up on a loaded machine; an upper bound, never a sleep
NS = "%arcade%quad1"
ODOM_KEY = (
    "7/arcade/quad1/odom/nav_msgs::msg::dds_::Odometry_/"
    "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"
)
VEC3 = (
    "geometry_msgs::msg::dds_::Vector3Stamped_/"
    "RIHS01_d4829622288cbb443886e7ea94ea5671a3b1be6bab4ad04224432a65f7d7887a"
)
DIAG_KEY = (
    "7/arcade/quad1/changepoint/diagnostic_msgs::msg::dds_::DiagnosticArray_/"
    "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e"
)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def take(q: queue.Queue, what: str, pred=lambda m: True, timeout: float = TIMEOUT):
    """The first item of ``q`` that ``pred`` accepts within ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        with contextlib.suppress(queue.Empty):
            if pred(m := q.get(timeout=left)):
                return m
    raise AssertionError(f"no {what}")


def test_mirror_puts_rmw_zenoh_samples_and_tokens(tmp_path):
    hub, ros_port = f"tcp/127.0.0.1:{free_port()}", free_port()
    tokens: queue.Queue = queue.Queue()
    samples: queue.Queue = queue.Queue()
    # One session plays both sides: a peer of the stack's bus, and the ROS 2 hosts' router
    # that the mirror's ROS 2 side connects to.
    config = peer_config(hub, listen=(f"tcp/127.0.0.1:{ros_port}",))
    with Bus("quad1", "estimator", config) as bus:
        session = bus.session
        lv = session.liveliness().declare_subscriber(
            "@ros2_lv/7/**", lambda s: tokens.put((str(s.key_expr), s.kind)), history=True
        )
        sub = session.declare_subscriber(
            "7/**",
            lambda s: samples.put(
                (str(s.key_expr), s.payload.to_bytes(), s.attachment.to_bytes(), time.time_ns())
            ),
        )
        log = (tmp_path / "ros2.out").open("w")
        cmd = [sys.executable, "-m", "services", "ros2", "--vehicle", "quad1", "--hub", hub,
               "--out", str(tmp_path), "--domain-id", "7",
               "--router", f"tcp/127.0.0.1:{ros_port}"]  # fmt: skip
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
        try:
            bus.wait_alive(["ros2"], timeout=TIMEOUT)
            node_key, _ = take(tokens, "node token", lambda t: "/NN/" in t[0])
            zid = node_key.split("/")[2]
            assert node_key == f"@ros2_lv/7/{zid}/0/0/NN/%/{NS}/arcade_mirror"
            odom_token = (
                f"@ros2_lv/7/{zid}/0/1/MP/%/{NS}/arcade_mirror/{NS}%odom/"
                + ODOM_KEY.split("/", 4)[4]
                + "/::,10:,:,:,,"
            )
            take(tokens, "odom publisher token", lambda t: t[0] == odom_token)

            # state -> nav_msgs/Odometry; put again until the mirror's ROS 2 side has the
            # subscription (its link to this session is not the bus's link)
            x = np.r_[1.0, 2.0, 3.0, 0.5, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.1, 0.2, 0.3]
            t_put = time.time_ns()
            put = []
            for stamp in np.arange(1, 41) * 0.05:
                bus.put(State(x=x, stamp=stamp))
                put.append(round(stamp * 1e9))
                try:
                    key, payload, att, t_got = take(samples, "odom", timeout=0.5)
                    break
                except AssertionError:
                    continue
            else:
                raise AssertionError("no odometry sample")
            assert key == ODOM_KEY
            odom = Odometry.deserialize(payload)
            np.testing.assert_array_equal(
                [odom.pose.pose.position.x, odom.pose.pose.position.y, odom.pose.pose.position.z],
                x[0:3],
            )
            stamp_ns = odom.header.stamp.sec * 10**9 + odom.header.stamp.nanosec
            assert stamp_ns in put  # one of the states, stamped as it was
            seq, t_src, gid_len = struct.unpack_from("<qqB", att)
            assert len(att) == 33 and gid_len == 16 and seq >= 1
            assert t_put <= t_src <= t_got
            assert att[17:] == xxhash.xxh3_128_digest(odom_token.encode())[::-1]

            # setpoint -> thrust and body rates; only changepoint events are mirrored
            bus.put(Setpoint(u=[6.5, 0.1, -0.2, 0.3], state_seq=1, stamp=stamp))
            bus.put(Event(kind="info", text="not mirrored", stamp=stamp))
            bus.put(Event(kind="changepoint", text="changepoint detected", stamp=stamp,
                          severity="warning", data={"changepoint_step": 40}))  # fmt: skip
            got = {}
            while len(got) < 3:
                key, payload, att, _ = take(samples, "setpoint and changepoint samples")
                got[key] = payload
            thrust = Vector3Stamped.deserialize(got[f"7/arcade/quad1/setpoint/thrust/{VEC3}"])
            rates = Vector3Stamped.deserialize(got[f"7/arcade/quad1/setpoint/body_rates/{VEC3}"])
            assert (thrust.vector.x, thrust.vector.y, thrust.vector.z) == (0.0, 0.0, 6.5)
            assert (rates.vector.x, rates.vector.y, rates.vector.z) == (0.1, -0.2, 0.3)
            (status,) = DiagnosticArray.deserialize(got[DIAG_KEY]).status
            assert (status.level, status.message) == (1, "changepoint detected")
            assert {kv.key: kv.value for kv in status.values}["changepoint_step"] == "40"
        finally:
            proc.send_signal(signal.SIGINT)
            code = proc.wait(timeout=TIMEOUT)
        assert code == 0
        # its tokens leave with it: ros2 node list forgets the node
        take(tokens, "node token removal",
             lambda t: t[0] == node_key and t[1] == zenoh.SampleKind.DELETE)  # fmt: skip
        sub.undeclare()
        lv.undeclare()
    stats = json.loads((tmp_path / "stats" / "ros2.json").read_text())
    assert stats["keys"]["odom"] == ODOM_KEY
    assert stats["published"]["changepoint"] == 1 and stats["published"]["setpoint/thrust"] == 1
    assert stats["unconverted"] == 0 and stats["rejects"] == {}
