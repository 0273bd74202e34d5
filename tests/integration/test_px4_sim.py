"""The simulator impersonating PX4, flown by the real MAVSDK library over UDP loopback:
in-process (:class:`simulator.px4.Px4Sim`), as ``arcade sim --px4`` and as the ``px4sim``
service on a Zenoh bus (where MAVSDK plays the PX4 bridge).

Every wait polls MAVSDK telemetry, the vehicle or a message queue with a deadline; nothing
sleeps to synchronise. Each test gets its own free UDP port (and Zenoh hub).
"""

from __future__ import annotations

import csv
import json
import math
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mavsdk import ComponentType, Configuration, Mavsdk
from mavsdk.autopilot import Autopilot
from mavsdk.plugins.action.action import Action, ActionError, ActionResult
from mavsdk.plugins.mavlink_direct.mavlink_direct import MavlinkDirect, MavlinkMessage
from mavsdk.plugins.mocap.mocap import (
    AngularVelocityBody,
    Covariance,
    Mocap,
    Odometry,
    PositionBody,
    Quaternion,
    SpeedBody,
)
from mavsdk.plugins.offboard.offboard import (
    AttitudeRate,
    Offboard,
    OffboardError,
    OffboardResult,
)
from mavsdk.plugins.param.param import Param
from mavsdk.plugins.telemetry.telemetry import FlightMode, LandedState, Telemetry

from arcade.demo_stack import free_hub
from arcade_core.frames import enu_to_ned, quat_enu_flu_to_ned_frd
from arcade_core.px4_command import ThrustCurve
from services.bus import Bus, peer_config
from services.messages import PAYLOAD_BODY, VEHICLE_BODY, Command, Setpoint
from simulator.px4 import Px4Sim

# Flown on the wall clock, with timing assertions: run alone (``make test``).
pytestmark = pytest.mark.realtime

REPO = Path(__file__).resolve().parents[2]
NAN21 = [math.nan] * 21


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(pred, timeout: float, what: str):
    """Poll ``pred`` until it returns something truthy; fail after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        value = pred()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.02)  # polling interval, not synchronisation


def connect(port: int):
    """A MAVSDK ground station listening where the vehicle sends (PX4 SITL style)."""
    mav = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    assert mav.add_any_connection(f"udpin://127.0.0.1:{port}") == 0  # SUCCESS
    system = mav.first_autopilot(10.0)
    assert system is not None, "no autopilot discovered"
    return mav, system


@pytest.fixture
def vehicle_link(request):
    """``(sim, mavsdk, system)``: a running simulated PX4 and a connected MAVSDK client."""
    port = free_udp_port()
    sim = Px4Sim(f"udpout://127.0.0.1:{port}", **request.param).start()
    mav, system = connect(port)
    yield sim, mav, system
    mav.destroy()
    sim.close()


def truth(sim: Px4Sim) -> np.ndarray:
    with sim.lock:
        return sim.vehicle.state()


def stream_mocap(sim: Px4Sim, mocap: Mocap, stop: threading.Event) -> None:
    """The bridge's job in the stack: ground truth (as mocap) to PX4 as ODOMETRY, 50 Hz."""
    while not stop.is_set():
        x = truth(sim)
        q = quat_enu_flu_to_ned_frd(x[6:10])
        mocap.set_odometry(
            Odometry(
                time_usec=0,
                frame_id=Odometry.MavFrame.MOCAP_NED,
                position_body=PositionBody(*enu_to_ned(x[0:3])),
                q=Quaternion(*q),
                speed_body=SpeedBody(math.nan, math.nan, math.nan),
                angular_velocity_body=AngularVelocityBody(math.nan, math.nan, math.nan),
                pose_covariance=Covariance(NAN21),
                velocity_covariance=Covariance(NAN21),
                estimator_type=Odometry.MavEstimatorType.MOCAP,
            )
        )
        stop.wait(0.02)  # stream rate


@pytest.mark.parametrize("vehicle_link", [{"vision_required": True}], indirect=True)
def test_mavsdk_sees_a_healthy_px4_once_mocap_arrives_in_ned(vehicle_link):
    sim, _, system = vehicle_link
    assert system.is_connected() and system.has_autopilot()
    assert system.autopilot_type() == Autopilot.PX4
    tel, action, mocap = Telemetry(system), Action(system), Mocap(system)

    # Vision-only PX4 without vision: no local position, arming refused by the vehicle.
    wait_for(lambda: tel.health().is_gyrometer_calibration_ok, 5.0, "SYS_STATUS health")
    health = tel.health()
    assert not health.is_local_position_ok and not health.is_armable
    with pytest.raises(ActionError) as err:
        action.arm()
    assert err.value.result == ActionResult.COMMAND_DENIED
    assert not sim.vehicle.armed

    stop = threading.Event()
    streamer = threading.Thread(target=stream_mocap, args=(sim, mocap, stop), daemon=True)
    streamer.start()
    try:
        h = wait_for(
            lambda: (
                (h := tel.health()).is_local_position_ok
                and h.is_armable
                and h.is_home_position_ok
                and h
            ),
            5.0,
            "local position and home ok",
        )
        assert not h.is_global_position_ok  # vision only: no GPS, no global origin
        # The ODOMETRY MAVSDK sent arrived, in NED/FRD, as the ground truth.
        vision = wait_for(lambda: sim.vehicle.vision, 2.0, "vision at the vehicle")
        assert vision.source == "odometry" and vision.frame_id == 14  # MAV_FRAME_MOCAP_NED
        x = truth(sim)  # resting on the floor: the truth does not move
        np.testing.assert_allclose(vision.position_ned, enu_to_ned(x[0:3]), atol=1e-4)
        np.testing.assert_allclose(
            vision.quaternion_ned_frd, quat_enu_flu_to_ned_frd(x[6:10]), atol=1e-4
        )
        # Telemetry is the NED of the ENU truth.
        pv = tel.position_velocity_ned()
        np.testing.assert_allclose(
            [pv.position.north_m, pv.position.east_m, pv.position.down_m],
            enu_to_ned(x[0:3]),
            atol=1e-4,
        )
        assert pv.position.down_m == pytest.approx(-sim.vehicle.ground_z, abs=1e-4)

        action.arm()
        wait_for(tel.armed, 3.0, "armed in telemetry")
        assert sim.vehicle.armed and tel.flight_mode() == FlightMode.HOLD
        action.disarm()
        wait_for(lambda: not tel.armed(), 3.0, "disarmed in telemetry")
    finally:
        stop.set()
        streamer.join()
    # Mocap gone: the position goes invalid (LOCAL_POSITION_NED stops, as on PX4).
    wait_for(
        lambda: not (h := tel.health()).is_local_position_ok and not h.is_armable,
        5.0,
        "local position lost",
    )


def set_mode_offboard(system) -> int:
    """DO_SET_MODE(custom, OFFBOARD) sent raw: MAVSDK's own offboard.start() refuses
    locally without a setpoint, so this asks the vehicle itself. Returns MAV_RESULT."""
    import json

    ack = MavlinkDirect(system).send_command(
        MavlinkMessage(
            message_name="COMMAND_LONG",
            system_id=245,
            component_id=190,
            target_system_id=1,
            target_component_id=1,
            fields_json=json.dumps(
                {
                    "target_system": 1,
                    "target_component": 1,
                    "command": 176,
                    "confirmation": 0,
                    "param1": 1,
                    "param2": 6,
                    "param3": 0,
                    "param4": 0,
                    "param5": 0,
                    "param6": 0,
                    "param7": 0,
                }
            ),
        )
    )
    return int(json.loads(ack.fields_json)["result"])


OF_LOSS_S = 0.5


@pytest.mark.parametrize("vehicle_link", [{"vision_required": False}], indirect=True)
def test_offboard_rates_fly_the_vehicle_and_loss_triggers_hold(vehicle_link):
    sim, _, system = vehicle_link
    v = sim.vehicle
    tel, action, offboard = Telemetry(system), Action(system), Offboard(system)
    # PX4's parameter protocol: the loss timeout COM_OF_LOSS_T, set the way a GCS sets it.
    param = Param(system)
    assert param.get_param_float("COM_OF_LOSS_T") == pytest.approx(1.0)
    assert param.get_param_int("COM_OBL_RC_ACT") == 5  # Hold
    param.set_param_float("COM_OF_LOSS_T", OF_LOSS_S)
    assert v.params["COM_OF_LOSS_T"] == pytest.approx(OF_LOSS_S)
    texts: list[str] = []
    tel.subscribe_status_text(lambda st, _: texts.append(st.text))
    wait_for(lambda: tel.health().is_armable, 5.0, "armable")
    action.arm()
    wait_for(tel.armed, 3.0, "armed")

    # Offboard without a setpoint stream: MAVSDK refuses locally, the vehicle refuses too.
    with pytest.raises(OffboardError) as err:
        offboard.start()
    assert err.value.result == OffboardResult.NO_SETPOINT_SET
    assert set_mode_offboard(system) == 2  # MAV_RESULT_DENIED
    assert v.mode.name == "HOLD"

    # With a stream: accepted. Thrust above hover climbs.
    hover = float(v.curve.throttle(v.sim.hover_thrust()))
    offboard.set_attitude_rate(AttitudeRate(0.0, 0.0, 0.0, hover + 0.12))
    offboard.start()
    wait_for(lambda: tel.flight_mode() == FlightMode.OFFBOARD, 3.0, "OFFBOARD in telemetry")
    z0 = v.ground_z
    wait_for(lambda: truth(sim)[2] > z0 + 0.6, 5.0, "climb above 0.6 m")
    x = truth(sim)
    assert x[5] > 0.3  # climbing (ENU up)
    pv = tel.position_velocity_ned()
    assert pv.position.down_m == pytest.approx(-x[2], abs=0.15)  # 30 Hz stream, moving
    assert pv.velocity.down_m_s < -0.3
    offboard.set_attitude_rate(AttitudeRate(0.0, 0.0, 0.0, hover))

    # Positive FRD roll rate: right wing down (roll angle grows positive in NED/FRD).
    offboard.set_attitude_rate(AttitudeRate(60.0, 0.0, 0.0, hover))
    wait_for(lambda: tel.attitude_euler().roll_deg > 10.0, 3.0, "roll > 10 deg")
    x = truth(sim)
    w, qx, qy, qz = x[6:10]
    left_axis_up = 2 * (qy * qz + w * qx)  # world z of the body y (left) axis
    assert left_axis_up > 0.1  # left side up = right wing down
    offboard.set_attitude_rate(AttitudeRate(-60.0, 0.0, 0.0, hover))
    wait_for(lambda: tel.attitude_euler().roll_deg < 2.0, 3.0, "level again")
    # Positive FRD pitch rate: nose up (FLU pitch is the other way round).
    offboard.set_attitude_rate(AttitudeRate(0.0, 60.0, 0.0, hover))
    wait_for(lambda: tel.attitude_euler().pitch_deg > 10.0, 3.0, "pitch > 10 deg")
    x = truth(sim)
    w, qx, qy, qz = x[6:10]
    nose_up = 2 * (qx * qz - w * qy)  # world z of the body x (forward) axis
    assert nose_up > 0.1
    offboard.set_attitude_rate(AttitudeRate(0.0, -60.0, 0.0, hover))
    wait_for(lambda: tel.attitude_euler().pitch_deg < 2.0, 3.0, "level again")
    offboard.set_attitude_rate(AttitudeRate(0.0, 0.0, 0.0, hover))

    # The client stops streaming (its offboard plugin goes away): PX4's offboard loss.
    offboard.destroy()
    t_stop = time.monotonic()
    wait_for(
        lambda: tel.flight_mode() == FlightMode.HOLD,
        OF_LOSS_S + 1.0 + 0.5,
        "HOLD after offboard loss",
    )
    assert time.monotonic() - t_stop >= OF_LOSS_S - 0.05
    assert v.failsafe and v.armed
    wait_for(lambda: any("offboard signal lost" in t for t in texts), 2.0, "STATUSTEXT")
    # Hold catches the vehicle: it settles at the hold point without falling.
    hold = v.hold_position
    assert hold[2] > z0 + 0.5

    def settled():
        x = truth(sim)
        assert x[2] > z0 + 0.3, "fell"
        return np.linalg.norm(x[0:3] - hold) < 0.2 and np.linalg.norm(x[3:6]) < 0.2

    wait_for(settled, 10.0, "settled at the hold point")
    assert not v.landed and v.mode.name == "HOLD"


def test_cli_vehicle_takes_off_lands_and_stops_cleanly_on_ctrl_c():
    port = free_udp_port()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "arcade",
            "sim",
            "--px4",
            f"udpout://127.0.0.1:{port}",
            "--no-vision-required",
            "--status-every",
            "0.5",
            "--takeoff-alt",
            "0.5",
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        mav, system = connect(port)
        try:
            tel = Telemetry(system)
            wait_for(lambda: tel.health().is_armable, 5.0, "armable")
            action = Action(system)
            action.arm()
            wait_for(tel.armed, 3.0, "armed")
            action.takeoff()
            wait_for(
                lambda: (
                    tel.landed_state() == LandedState.IN_AIR
                    and tel.flight_mode() == FlightMode.HOLD
                ),
                10.0,
                "hovering after take-off",
            )
            assert tel.position_velocity_ned().position.down_m < -0.4
            action.land()
            # Landed, then PX4's auto-disarm (COM_DISARM_LAND, 2 s).
            wait_for(lambda: not tel.armed(), 12.0, "disarmed after landing")
            assert tel.landed_state() == LandedState.ON_GROUND
        finally:
            mav.destroy()
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out
    assert "mode=HOLD" in out and "ARMED" in out
    for text in ("Armed by external command", "Takeoff complete", "Landing detected"):
        assert f"[px4] {text}" in out
    assert "stopped; received" in out and "COMMAND_LONG" in out


START_TIMEOUT = 120.0  # start-up imports and compiles on a loaded machine; never a sleep


def get(q: queue.Queue, what: str, pred=lambda m: True, timeout: float = 30.0):
    deadline = time.monotonic() + timeout
    while True:
        left = deadline - time.monotonic()
        try:
            m = q.get(timeout=max(left, 0.0))
        except queue.Empty:
            raise AssertionError(f"no {what}") from None
        if pred(m):
            return m


def test_px4sim_service_flies_from_mavlink_only_and_serves_mocap_on_the_bus(tmp_path):
    hub, port = free_hub(), free_udp_port()
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    cmd = [
        sys.executable,
        "-m",
        "services",
        "px4sim",
        "--hub",
        hub,
        "--out",
        str(tmp_path),
        "--px4",
        f"udpout://127.0.0.1:{port}",
        "--duration",
        "3.0",
        "--preroll",
        "0.5",
        "--release",
        "-1",
        "--payload-g",
        "100",
        "--rate",
        "20",
        "--of-loss-s",
        "0.5",
    ]
    with (tmp_path / "px4sim.out").open("w") as log:
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)
    mocap_q: queue.Queue = queue.Queue()
    events: queue.Queue = queue.Queue()
    commands: queue.Queue = queue.Queue()
    imu_count = [0]
    thrust: list[float] = []  # the bridge's latest offboard setpoint (set once flying)
    mav = None
    stop = threading.Event()
    try:
        with Bus("default", "controller", peer_config(hub)) as bus:
            bus.subscribe("mocap", mocap_q.put)

            def on_imu(_):  # the bridge answers every control instant with a setpoint
                imu_count[0] += 1
                if thrust:
                    offboard.set_attitude_rate(AttitudeRate(0.0, 0.0, 0.0, thrust[-1]))

            bus.subscribe("imu", on_imu)
            bus.subscribe("event", events.put)
            bus.subscribe("command", commands.put)
            bus.wait_alive(["px4sim"], timeout=START_TIMEOUT)
            frame = get(mocap_q, "mocap frame", lambda m: m.of_vehicle(VEHICLE_BODY))
            assert frame.position[2] == pytest.approx(1.5, abs=0.1)  # hovering at the start
            # The payload is a second rigid body of each capture, hanging below the vehicle.
            hanging = get(mocap_q, "payload frame")
            assert hanging.body == PAYLOAD_BODY and hanging.capture_stamp == frame.capture_stamp
            assert hanging.position[2] < frame.position[2] - 0.3

            mav, system = connect(port)
            tel, offboard, mocap = Telemetry(system), Offboard(system), Mocap(system)
            wait_for(tel.armed, 5.0, "armed (airborne start)")
            assert tel.flight_mode() == FlightMode.HOLD

            def bridge_mocap():  # what the bridge does: bus mocap -> ODOMETRY (NED/FRD)
                while not stop.is_set():
                    try:
                        f = mocap_q.get(timeout=0.1)
                    except queue.Empty:
                        continue
                    if not f.of_vehicle(VEHICLE_BODY):  # the payload: not the vehicle's pose
                        continue
                    mocap.set_odometry(
                        Odometry(
                            frame_id=Odometry.MavFrame.MOCAP_NED,
                            position_body=PositionBody(*enu_to_ned(f.position)),
                            q=Quaternion(*quat_enu_flu_to_ned_frd(f.quaternion)),
                            speed_body=SpeedBody(math.nan, math.nan, math.nan),
                            angular_velocity_body=AngularVelocityBody(math.nan, math.nan, math.nan),
                            pose_covariance=Covariance(NAN21),
                            velocity_covariance=Covariance(NAN21),
                        )
                    )

            forwarder = threading.Thread(target=bridge_mocap, daemon=True)
            forwarder.start()
            wait_for(lambda: tel.health().is_local_position_ok, 5.0, "vision-aided position")

            # A setpoint on the bus is not an input of this simulator.
            bus.put(Setpoint(u=np.array([0.0, 0.0, 0.0, 0.0]), state_seq=0, stamp=time.monotonic()))
            # Offboard over MAVLink starts the mission: a start command on the bus.
            curve = ThrustCurve(fac=0.3, max_thrust_n=16.0)  # the default vehicle's
            hover = float(curve.throttle(0.57 * 9.81 + 0.1 * 9.81 + 0.002 * 9.81))
            thrust.append(hover)
            offboard.set_attitude_rate(AttitudeRate(0.0, 0.0, 0.0, hover))
            offboard.start()
            start = get(commands, "start command", lambda c: c.name == "start")
            assert start.args["t0"] > 0
            bus.put(Command(name="release_payload", stamp=time.monotonic()))
            get(events, "payload released", lambda e: "payload released" in e.text)
            thrust.append(float(curve.throttle(0.57 * 9.81)))  # unloaded
            n0 = imu_count[0]
            wait_for(lambda: imu_count[0] >= n0 + 20, 10.0, "a second of offboard flight")
            # The bridge stops streaming: PX4's offboard loss, reported as a failsafe event.
            thrust.clear()
            offboard.destroy()
            ev = get(events, "failsafe event", lambda e: e.kind == "failsafe")
            assert "offboard signal lost" in ev.text and ev.data["mode"] == "HOLD"
            get(events, "flight finished", lambda e: "flight finished" in e.text)
        code = proc.wait(timeout=30)
    finally:
        stop.set()
        if mav is not None:
            mav.destroy()
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=30)
    assert code == 0, (tmp_path / "px4sim.out").read_text()
    stats = json.loads((tmp_path / "stats" / "px4sim.json").read_text())
    assert stats["ignored_setpoints"] == 1 and stats["vision_received"]
    assert stats["mavlink_rx"]["SET_ATTITUDE_TARGET"] > 20
    assert stats["mavlink_rx"]["ODOMETRY"] > 20
    assert stats["steps"] == 61 and not stats["crashed"]  # 3 s at 20 Hz, both ends
    assert stats["released_at"] is not None and len(stats["px4_failsafes"]) == 1
    # Answered control instants until the stream stopped, then COM_OF_LOSS_T (0.5 s = 10
    # instants) of misses in offboard; none once in Hold.
    assert 8 <= stats["missed_deadlines"] <= 12, stats["missed_deadlines"]
    assert imu_count[0] >= 61
    with (tmp_path / "truth.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 61
    z = np.array([float(r["pz"]) for r in rows])
    assert np.all(np.abs(z - 1.5) < 0.5)  # hover thrust, then Hold, keep the height
    assert float(rows[-1]["released"]) == 1.0 and float(rows[-1]["failsafe"]) == 1.0
