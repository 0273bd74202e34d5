"""PX4 bridge: the service process against a fake PX4 (its pure parts are in
``tests/unit/test_px4_bridge_commands.py``).

The fake is a small MAVLink peer (pymavlink over UDP loopback) that speaks what MAVSDK needs
from PX4: heartbeats with PX4 custom modes, SYS_STATUS health, attitude and local-position
streams, COMMAND_ACK for arming and mode changes, and offboard acceptance only while
SET_ATTITUDE_TARGET streams. It records every setpoint and command with its arrival time,
so the tests can check what reached "PX4" and when. The bridge runs as its real process
(``python -m services bridge``) with real MAVSDK and a real Zenoh session.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mav

from arcade_core import frames
from services.bus import Bus, peer_config
from services.messages import Command, Setpoint

REPO = Path(__file__).resolve().parents[2]

# --------------------------------------------------------------------- fake PX4

MAIN_POSCTL, MAIN_AUTO, MAIN_OFFBOARD = 3, 4, 6
AUTO_LOITER, AUTO_LAND = 3, 6
HEARTBEAT_S = 1.0  # PX4's heartbeat period


class FakePx4:
    """A minimal PX4 on MAVLink/UDP that records what it receives (module docstring)."""

    def __init__(self, bridge_port: int):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.peer = ("127.0.0.1", bridge_port)
        self.mav = mav.MAVLink(self, srcSystem=1, srcComponent=1)
        self.lock = threading.Condition()
        self.main, self.sub, self.armed = MAIN_AUTO, AUTO_LOITER, False
        self.position_ned = np.array([0.0, 0.0, -1.5])
        self.sat: list[tuple[float, float, np.ndarray]] = []  # (t, thrust, rates FRD)
        self.commands: list[tuple[float, int, tuple]] = []
        self.odometry: list = []
        self.modes: list[tuple[float, int, int]] = []
        self.systems: set[int] = set()  # MAVLink system ids heard from
        self.stop = threading.Event()
        self.threads = [
            threading.Thread(target=self._rx, daemon=True),
            threading.Thread(target=self._tx, daemon=True),
        ]
        for t in self.threads:
            t.start()

    def write(self, buf: bytes) -> None:  # pymavlink's file interface
        with contextlib.suppress(OSError):
            self.sock.sendto(buf, self.peer)

    def set_mode(self, main: int, sub: int = 0) -> None:
        with self.lock:
            self.main, self.sub = main, sub
            self.modes.append((time.monotonic(), main, sub))
            self.lock.notify_all()
        self._heartbeat()  # PX4 announces a mode change at once

    def _heartbeat(self) -> None:
        base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (
            mav.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0
        )
        self.mav.heartbeat_send(
            mav.MAV_TYPE_QUADROTOR,
            mav.MAV_AUTOPILOT_PX4,
            base,
            (self.main << 16) | (self.sub << 24),
            mav.MAV_STATE_STANDBY,
        )

    def _tx(self) -> None:
        bits = (
            mav.MAV_SYS_STATUS_SENSOR_3D_GYRO
            | mav.MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | mav.MAV_SYS_STATUS_SENSOR_3D_MAG
            | mav.MAV_SYS_STATUS_PREARM_CHECK
            | mav.MAV_SYS_STATUS_SENSOR_VISION_POSITION
        )
        k = 0
        while not self.stop.is_set():
            if k % 50 == 0:
                self._heartbeat()
                self.mav.sys_status_send(bits, bits, bits, 0, 12000, -1, -1, 0, 0, 0, 0, 0, 0)
                self.mav.extended_sys_state_send(0, 2 if self.armed else 1)
            t_ms = int(time.monotonic() * 1e3) & 0xFFFFFFFF
            self.mav.attitude_quaternion_send(t_ms, 1.0, 0.0, 0.0, 0.0, 0.1, -0.2, 0.3)
            if k % 2 == 0:
                n, e, d = self.position_ned
                self.mav.local_position_ned_send(t_ms, n, e, d, 0.0, 0.0, 0.0)
            k += 1
            self.stop.wait(0.02)  # 50 Hz telemetry

    def _rx(self) -> None:
        parser = mav.MAVLink(None)
        while not self.stop.is_set():
            try:
                data, _ = self.sock.recvfrom(65535)
            except (TimeoutError, OSError):
                continue
            for msg in parser.parse_buffer(data) or []:
                if msg.get_srcSystem() not in self.systems:
                    with self.lock:
                        self.systems.add(msg.get_srcSystem())
                        self.lock.notify_all()
                self._handle(msg)

    def _handle(self, msg) -> None:
        now = time.monotonic()
        t = msg.get_type()
        if t == "SET_ATTITUDE_TARGET":
            with self.lock:
                self.sat.append(
                    (
                        now,
                        msg.thrust,
                        np.array([msg.body_roll_rate, msg.body_pitch_rate, msg.body_yaw_rate]),
                    )
                )
                self.lock.notify_all()
        elif t == "ODOMETRY":
            with self.lock:
                self.odometry.append(msg)
                self.lock.notify_all()
        elif t in ("COMMAND_LONG", "COMMAND_INT"):
            params = (msg.param1, msg.param2, msg.param3)
            with self.lock:
                self.commands.append((now, msg.command, params))
                self.lock.notify_all()
            ok = True
            if msg.command == mav.MAV_CMD_COMPONENT_ARM_DISARM:
                self.armed = msg.param1 > 0.5
            elif msg.command == mav.MAV_CMD_DO_SET_MODE:
                main, sub = int(msg.param2), int(msg.param3)
                streaming = self.sat and now - self.sat[-1][0] < 0.5
                ok = main != MAIN_OFFBOARD or bool(streaming)
                if ok:
                    self.set_mode(main, sub)
            elif msg.command == mav.MAV_CMD_NAV_LAND:
                self.set_mode(MAIN_AUTO, AUTO_LAND)
            result = mav.MAV_RESULT_ACCEPTED if ok else mav.MAV_RESULT_DENIED
            self.mav.command_ack_send(
                msg.command, result, 255, 0, msg.get_srcSystem(), msg.get_srcComponent()
            )

    def wait(self, predicate, timeout: float) -> bool:
        with self.lock:
            return self.lock.wait_for(predicate, timeout)

    def close(self) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(2.0)
        self.sock.close()


class GroundStation:
    """A ground station's UDP port (QGroundControl's 14550): the bridge forwards to it."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.mav = mav.MAVLink(self, srcSystem=255, srcComponent=190)  # QGroundControl's ids
        self.peer: tuple[str, int] | None = None

    def write(self, buf: bytes) -> None:  # pymavlink's file interface
        if self.peer is not None:
            self.sock.sendto(buf, self.peer)

    def heartbeat_from(self, system: int, timeout: float):
        """The first HEARTBEAT of ``system`` that arrives within ``timeout`` s, or None."""
        parser = mav.MAVLink(None)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                data, self.peer = self.sock.recvfrom(65535)
            except TimeoutError:
                continue
            for msg in parser.parse_buffer(data) or []:
                if msg.get_type() == "HEARTBEAT" and msg.get_srcSystem() == system:
                    return msg
        return None

    def close(self) -> None:
        self.sock.close()


def _free_port(kind=socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Events:
    """Events seen on the bus, with a wait."""

    def __init__(self, bus: Bus):
        self.items: list = []
        self.cond = threading.Condition()
        bus.subscribe("event", self._on, check_order=False)

    def _on(self, e) -> None:
        with self.cond:
            self.items.append((time.monotonic(), e))
            self.cond.notify_all()

    def wait(
        self, kind: str, timeout: float, after: int = 0, text: str = "", pred=lambda e: True, **data
    ):
        def find():
            for _, e in self.items[after:]:
                if (
                    e.kind == kind
                    and text in e.text
                    and pred(e)
                    and all(e.data.get(k) == v for k, v in data.items())
                ):
                    return e
            return None

        with self.cond:
            self.cond.wait_for(lambda: find() is not None, timeout)
            return find()


class SetpointStream:
    """Publishes setpoints at 20 Hz from a thread; each one's yaw rate encodes its index."""

    def __init__(self, bus: Bus, u: np.ndarray):
        self.bus, self.u, self.n = bus, np.asarray(u, float), 0
        self.last_put = -math.inf
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def yaw(self, n: int) -> float:
        return 0.001 * (n % 1000)

    def _run(self) -> None:
        while not self.stop.wait(0.05):  # the controller's 20 Hz
            self.n += 1
            u = self.u.copy()
            u[3] = self.yaw(self.n)
            try:
                self.bus.put(Setpoint(u=u, state_seq=self.n, stamp=time.monotonic()))
            except RuntimeError:  # the bus closed (end of the test)
                return
            self.last_put = time.monotonic()

    def halt(self) -> float:
        self.stop.set()
        self.thread.join()
        return self.last_put


@pytest.fixture
def rig(tmp_path):
    port, hub = _free_port(), f"tcp/127.0.0.1:{_free_port(socket.SOCK_STREAM)}"
    px4 = FakePx4(port)
    gcs = GroundStation()
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    cmd = [
        sys.executable,
        "-m",
        "services",
        "bridge",
        "--hub",
        hub,
        "--out",
        str(tmp_path),
        "--connect",
        f"udpin://127.0.0.1:{port}",
        "--connect-timeout",
        "20",
        "--geofence=-3,3,-3,3,-0.5,3",
        "--geofence-action",
        "land",
        "--max-throttle",
        "0.8",
        "--status-rate",
        "5",
        "--forward",
        f"udpout://127.0.0.1:{gcs.port}",
    ]
    log = (tmp_path / "bridge.out").open("w")
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)
    # The test's session is the controller's: the bridge takes setpoints from it alone.
    bus = Bus("default", "controller", peer_config(hub)).open()
    events = Events(bus)
    try:
        deadline = time.monotonic() + 60.0
        while "bridge" not in bus.alive:  # short slices: fail at once if it exits
            assert proc.poll() is None, (tmp_path / "bridge.out").read_text()[-3000:]
            assert time.monotonic() < deadline, "bridge not ready after 60 s"
            with contextlib.suppress(TimeoutError):
                bus.wait_alive(["bridge"], timeout=0.5)
        yield px4, proc, bus, events, gcs
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
        bus.close()
        px4.close()
        gcs.close()
        log.close()


def _arm(bus: Bus, events: Events) -> None:
    """Arm once the bridge reports a steady setpoint stream; wait until offboard is engaged."""
    n = len(events.items)
    steady = events.wait(
        "vehicle_status",
        5.0,
        after=n,
        setpoints_fresh=True,
        pred=lambda e: e.data["stream_s"] >= 1.0,
    )
    assert steady is not None
    n = len(events.items)
    bus.put(Command(name="arm", target="bridge", stamp=time.monotonic()))
    e = events.wait("offboard", 10.0, after=n)
    assert e is not None, [x.text for _, x in events.items[n:]]


@pytest.mark.realtime
def test_bridge_against_fake_px4(rig):
    px4, proc, bus, events, gcs = rig

    # --forward: a ground station hears PX4 through the bridge, and PX4 hears it.
    heartbeat = gcs.heartbeat_from(1, 10.0)
    assert heartbeat is not None and heartbeat.autopilot == mav.MAV_AUTOPILOT_PX4
    gcs.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    assert px4.wait(lambda: 255 in px4.systems, 5.0)

    # Telemetry reaches the bus: imu at the control rate (PX4 rates FRD -> FLU).
    imu: list = []
    got_imu = threading.Event()
    bus.subscribe("imu", lambda m: (imu.append(m), len(imu) >= 5 and got_imu.set()))
    assert got_imu.wait(10.0)
    np.testing.assert_allclose(imu[-1].gyro, [0.1, 0.2, -0.3], atol=1e-6)
    assert events.wait("vehicle_status", 5.0) is not None

    # Mocap (ENU/FLU) reaches PX4 as ODOMETRY in NED/FRD.
    from services.messages import Mocap

    q_enu = np.array([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])  # facing north
    bus.put(
        Mocap(
            position=[1.0, 2.0, 1.5],
            quaternion=q_enu,
            capture_stamp=time.monotonic(),
            stamp=time.monotonic(),
        )
    )
    assert px4.wait(lambda: px4.odometry, 5.0)
    o = px4.odometry[-1]
    np.testing.assert_allclose([o.x, o.y, o.z], [2.0, 1.0, -1.5], atol=1e-6)
    assert abs(frames.to_rpy_np(np.array(o.q))[2]) < 1e-6  # NED yaw 0 = north

    # Nothing is armed or streamed without an arm command, nor without setpoints.
    bus.put(Command(name="arm", target="bridge", stamp=time.monotonic()))
    assert events.wait("info", 5.0, text="not streaming") is not None
    assert not px4.armed and not px4.sat

    # Setpoints beyond the limits: clamped to the vehicle's rates and --max-throttle.
    stream = SetpointStream(bus, [30.0, 10.0, -0.5, 0.0])
    _arm(bus, events)
    assert px4.armed and px4.main == MAIN_OFFBOARD
    assert px4.wait(lambda: len(px4.sat) >= 10, 5.0)
    _, thrust, rates = px4.sat[-1]
    assert thrust == pytest.approx(0.8)
    np.testing.assert_allclose(rates[:2], [3.5, 0.5], atol=1e-6)  # rad/s, FRD

    # A malformed setpoint (NaN thrust, bypassing the encoder) never reaches PX4.
    bad = Setpoint(u=[5.0, 0.0, 0.0, 0.0], state_seq=10**6, stamp=time.monotonic()).to_wire()
    bad["u"] = [math.nan, 0.0, 0.0, 0.777]
    bad["seq"], bad["src"] = 1, "intruder/0"
    bus.session.put(bus.key("setpoint"), msgpack.packb(bad))
    time.sleep(0.3)  # nothing to wait for: the check is that nothing arrives
    assert all(math.isfinite(t) and abs(r[2] + 0.777) > 1e-3 for _, t, r in px4.sat)

    # Setpoints stop: the bridge leaves offboard (Hold) within 0.3 s (+ one PX4 heartbeat
    # for the mode to show), and MAVSDK's re-sending of the last setpoint ends with it.
    n_modes = len(px4.modes)
    last_put = stream.halt()
    assert px4.wait(lambda: len(px4.modes) > n_modes, 3.0)
    t_hold, main, sub = px4.modes[n_modes]
    assert (main, sub) == (MAIN_AUTO, AUTO_LOITER)
    assert t_hold - last_put <= 0.3 + HEARTBEAT_S
    last_yaw = -stream.yaw(stream.n)
    fresh = [t for t, _, r in px4.sat if abs(r[2] - last_yaw) < 1e-6]
    latency = t_hold - fresh[0]  # from the last fresh setpoint reaching PX4 to Hold
    assert 0.25 <= latency <= 0.3 + HEARTBEAT_S, latency  # not early, not late
    time.sleep(0.3)  # MAVSDK would re-send every 50 ms: check that it stopped
    assert not [t for t, _, _ in px4.sat if t > t_hold + 0.06]
    fs = events.wait("failsafe", 2.0, reason="setpoint_timeout")
    assert fs is not None and fs.data["action"] == "hold"
    print(f"setpoint timeout -> Hold: {1e3 * latency:.0f} ms after the last setpoint")

    # PX4 leaves offboard by itself (pilot): the stream stops, no mode command is sent.
    stream = SetpointStream(bus, [6.0, 0.0, 0.0, 0.0])
    _arm(bus, events)
    n_cmd = len(px4.commands)
    px4.set_mode(MAIN_POSCTL)
    t_pilot = time.monotonic()
    assert events.wait("failsafe", 3.0, reason="px4_mode") is not None
    time.sleep(0.3)  # the re-send stops: nothing arrives afterwards
    n_sat = len(px4.sat)
    time.sleep(0.3)
    assert len(px4.sat) == n_sat and px4.sat[-1][0] < t_pilot + 1.0
    assert not [c for _, c, _ in px4.commands[n_cmd:] if c == mav.MAV_CMD_DO_SET_MODE]

    # Geofence (action land): PX4's position leaves the box -> Hold, then Land.
    px4.set_mode(MAIN_AUTO, AUTO_LOITER)
    _arm(bus, events)
    n_modes = len(px4.modes)
    px4.position_ned = np.array([0.0, 3.5, -1.5])  # east 3.5 m: outside x <= 3
    e = events.wait("failsafe", 3.0, reason="geofence")
    assert e is not None and e.data["action"] == "land"
    assert px4.wait(lambda: (MAIN_AUTO, AUTO_LAND) in [m[1:] for m in px4.modes[n_modes:]], 5)
    px4.position_ned = np.array([0.0, 0.0, -1.5])

    # Shutdown while in offboard: Hold, never disarm.
    px4.set_mode(MAIN_AUTO, AUTO_LOITER)
    _arm(bus, events)
    n_modes, n_cmd = len(px4.modes), len(px4.commands)
    proc.send_signal(signal.SIGINT)
    assert proc.wait(20) == 0
    stream.halt()
    assert (MAIN_AUTO, AUTO_LOITER) in [m[1:] for m in px4.modes[n_modes:]]
    assert not [
        p
        for _, c, p in px4.commands[n_cmd:]
        if c == mav.MAV_CMD_COMPONENT_ARM_DISARM and p[0] < 0.5
    ]
    assert px4.armed
