"""Pieces of the simulated PX4: the default vehicle's thrust range, mode encoding, parameter
encoding, and the commander's rules (arming, offboard entry, offboard loss, the offboard
thrust) on simulated time. The frame and thrust conversions themselves are tested in
test_px4_frames.
Then the PX4 bridge's offboard logic (engaging, every exit, watchdog, send errors) with
MAVSDK's plugins and the bus replaced by recording fakes, and px4sim's mission start."""

from __future__ import annotations

import argparse
import math
import time
from types import SimpleNamespace

import numpy as np
import pytest

from arcade_core import frames
from arcade_core.frames import enu_to_ned, quat_enu_flu_to_ned_frd
from arcade_core.px4_command import ThrustCurve
from arcade_io.vehicle import load_vehicle
from services import options, px4_bridge
from services.messages import Command, Event, Setpoint
from services.px4_bridge import Px4Bridge
from simulator.px4 import FlightMode, Px4Vehicle
from simulator.px4.airframe import Px4Airframe
from simulator.px4.link import parse_url
from simulator.px4.mavlink_vehicle import _param_from_wire, _param_wire

# ------------------------------------------------------------------ thrust


def test_thrust_of_the_default_vehicle():
    curve = ThrustCurve.from_vehicle(load_vehicle())
    # THR_MDL_FAC 0.3 is the motors' model, inverted by PX4's mixer: the normalised thrust
    # is linear in force.
    assert curve.max_thrust_n == 16.0 and curve.fac == 0.3
    assert curve.thrust(0.5) == pytest.approx(8.0)
    assert curve.thrust(1.0) == pytest.approx(16.0)
    assert curve.throttle(0.0) == 0.0
    assert curve.throttle(4.0) == pytest.approx(0.25)
    # Out-of-range requests saturate instead of extrapolating.
    assert curve.throttle(40.0) == 1.0
    assert curve.thrust(-0.2) == 0.0


# ------------------------------------------------------------------ protocol encodings


def test_px4_custom_mode_encoding():
    assert FlightMode.OFFBOARD.custom_mode == 6 << 16
    assert FlightMode.HOLD.custom_mode == (4 << 16) | (3 << 24)
    assert FlightMode.LAND.custom_mode == (4 << 16) | (6 << 24)
    for mode in FlightMode:
        assert FlightMode.from_custom_mode(mode.custom_mode) is mode
    assert FlightMode.from_px4(4, 4) is None  # Mission: not flown here
    assert FlightMode.from_px4(6, 0) is FlightMode.OFFBOARD


def test_int_params_travel_bytewise():
    value, ptype = _param_wire(5)
    assert ptype == 6  # MAV_PARAM_TYPE_INT32
    assert _param_from_wire(value, ptype) == 5
    value, ptype = _param_wire(0.75)
    assert ptype == 9 and _param_from_wire(value, ptype) == pytest.approx(0.75)


def test_link_urls():
    assert parse_url("udpout://127.0.0.1:14540") == ("out", "127.0.0.1", 14540)
    assert parse_url("udpin://0.0.0.0:14550") == ("in", "0.0.0.0", 14550)
    assert parse_url("udp://:14550") == ("in", "0.0.0.0", 14550)
    with pytest.raises(ValueError):
        parse_url("serial:///dev/ttyACM0:57600")


# ------------------------------------------------------------------ commander


@pytest.fixture(scope="module")
def airframe():
    return Px4Airframe()


def fly(v: Px4Vehicle, seconds: float, each=None) -> None:
    for _ in range(round(seconds / 0.005)):
        if each is not None:
            each()
        v.step(0.005)


def test_arming_needs_fresh_vision_and_disarmed_motors_are_off(airframe):
    v = Px4Vehicle(airframe, vision_required=True, vision_timeout_s=0.5)
    assert v.landed and not v.armed
    ok, why = v.arm()
    assert not ok and "position" in why
    assert v.set_vision(enu_to_ned(v.state()[0:3]))
    assert v.position_ok() and v.arm()[0]
    fly(v, 0.6)  # no more vision: stale after the timeout
    assert not v.position_ok()
    assert v.disarm()[0] and not v.armed
    fly(v, 0.5)
    assert np.allclose(airframe.rotor_thrusts(), 0.0, atol=1e-6)
    assert v.state()[2] == pytest.approx(v.ground_z, abs=1e-3)  # still on the floor
    assert not v.set_vision([math.nan, 0.0, 0.0]) and v.rejected == 1


def test_offboard_needs_a_stream_and_loss_lands_with_land_action(airframe):
    v = Px4Vehicle(
        airframe,
        vision_required=False,
        params={"COM_OF_LOSS_T": 0.4, "COM_OBL_RC_ACT": 4, "COM_DISARM_LAND": 1.0},
    )
    assert v.arm()[0]
    assert not v.set_mode(FlightMode.OFFBOARD)[0] and v.mode is FlightMode.HOLD
    hover = float(v.curve.throttle(airframe.hover_thrust()))

    def stream(s):
        return lambda: v.set_attitude_target(128, [1, 0, 0, 0], [0.0, 0.0, 0.0], s)

    stream(hover + 0.05)()
    assert v.set_mode(FlightMode.OFFBOARD)[0]
    fly(v, 1.2, stream(hover + 0.05))
    assert v.mode is FlightMode.OFFBOARD and v.state()[2] > v.ground_z + 0.5
    assert not v.landed and v.landed_state == 2  # MAV_LANDED_STATE_IN_AIR
    # Stream stops: after COM_OF_LOSS_T (simulated time) the vehicle lands.
    t_last = v.time
    while v.mode is FlightMode.OFFBOARD:
        fly(v, 0.005)
    assert v.time - t_last == pytest.approx(0.4, abs=0.011)
    assert v.mode is FlightMode.LAND and v.failsafe
    assert any("offboard signal lost" in text for _, text in v.texts)
    # What PX4 steers to by itself (the simulator's crash check): the landing point at the
    # current height while it descends.
    target = v.own_target()
    np.testing.assert_allclose(target, v.state()[0:3], atol=1e-3)
    fly(v, 8.0)
    assert v.landed and not v.armed  # landed, then disarmed after COM_DISARM_LAND
    assert v.state()[2] == pytest.approx(v.ground_z, abs=0.01)
    np.testing.assert_allclose(v.own_target(), v.state()[0:3])  # disarmed: where it is


def test_land_without_a_position_estimate_is_a_level_descent_that_keeps_its_drift(airframe):
    # PX4's Descend: no vision, so no horizontal position to steer to (the bridge lands a
    # vehicle whose mocap is gone); the height rate is still controlled.
    v = Px4Vehicle(airframe, start=(0.0, 0.0, 2.0), airborne=True, vision_required=True)
    airframe.reset(position=(0.0, 0.0, 2.0), velocity=(0.4, 0.0, 0.0))
    assert not v.position_ok() and v.set_mode(FlightMode.LAND)[0]
    fly(v, 1.5)
    x = v.state()
    assert x[3] == pytest.approx(0.4, abs=0.05)  # drifting on, not braked back
    assert x[5] == pytest.approx(-float(v.params["MPC_LAND_SPEED"]), abs=0.1)
    tilt = math.degrees(math.acos(1 - 2 * (x[7] ** 2 + x[8] ** 2)))
    assert tilt < 2.0
    np.testing.assert_allclose(v.own_target(), x[0:3])  # no target of its own


def test_parameters_are_checked(airframe):
    with pytest.raises(ValueError, match="COM_OBL_RC_ACT"):
        Px4Vehicle(airframe, params={"COM_OBL_RC_ACT": 3})  # Return: not flown here
    with pytest.raises(ValueError, match="NOT_A_PARAM"):
        Px4Vehicle(airframe, params={"NOT_A_PARAM": 1.0})
    v = Px4Vehicle(airframe)
    assert v.set_param("COM_OF_LOSS_T", 0.25) and v.params["COM_OF_LOSS_T"] == 0.25
    assert not v.set_param("COM_OF_LOSS_T", math.nan)


def test_takeoff_then_hold_keeps_the_height(airframe):
    v = Px4Vehicle(airframe, vision_required=False, params={"MIS_TAKEOFF_ALT": 1.0})
    assert not v.takeoff()[0]  # disarmed
    v.arm()
    assert v.takeoff()[0] and v.landed_state == 3  # MAV_LANDED_STATE_TAKEOFF
    target = v.own_target()
    assert target[2] == pytest.approx(v.ground_z + 1.0)
    fly(v, 4.0)
    assert v.mode is FlightMode.HOLD
    assert v.state()[2] == pytest.approx(v.ground_z + 1.0, abs=0.1)
    np.testing.assert_allclose(v.own_target(), target)  # holds where the take-off ended
    assert not v.disarm()[0]  # not in the air


@pytest.mark.parametrize("fac", [0.0, 0.3, 1.0])
def test_offboard_thrust_is_max_thrust_times_the_setpoint_for_any_thr_mdl_fac(fac):
    """The simulated PX4's mixer inverts the motors' THR_MDL_FAC curve: ``s`` gives
    ``T_max * s`` whatever the vehicle file's ``thr_mdl_fac``, and ``m g / T_max`` hovers."""
    vehicle = load_vehicle()
    vehicle["thrust_curve"] = {"thr_mdl_fac": fac}
    airframe = Px4Airframe(vehicle)
    v = Px4Vehicle(airframe, start=(0.0, 0.0, 2.0), airborne=True, vision_required=False)
    assert v.curve.fac == fac
    t_max = 4.0 * float(vehicle["rotors"]["max_thrust_n"])
    for s in (0.0, 0.1, 0.25, 0.5, 0.8, 1.0):
        assert v.set_attitude_target(128, [1, 0, 0, 0], [0.0, 0.0, 0.0], s)
        assert v.offboard_sp.thrust == pytest.approx(t_max * s, rel=1e-15, abs=0.0)
    hover = airframe.hover_thrust() / t_max

    def stream():  # attitude ignored (128), zero rates, the hover thrust
        v.set_attitude_target(128, [1, 0, 0, 0], [0.0, 0.0, 0.0], hover)

    stream()
    assert v.set_mode(FlightMode.OFFBOARD)[0]
    z0 = v.state()[2]
    fly(v, 1.0, stream)
    assert v.mode is FlightMode.OFFBOARD
    assert v.state()[2] == pytest.approx(z0, abs=0.05) and abs(v.state()[5]) < 0.1


def test_offboard_attitude_setpoint_is_tracked_in_px4_frames(airframe):
    """SET_ATTITUDE_TARGET with an attitude (NED/FRD): the vehicle takes that attitude."""
    v = Px4Vehicle(airframe, start=(0.0, 0.0, 2.0), airborne=True, vision_required=False)
    hover = float(v.curve.throttle(airframe.hover_thrust()))
    roll, yaw_ned = math.radians(15.0), math.radians(90.0)  # right wing down, facing east
    q_sp = quat_enu_flu_to_ned_frd([1.0, 0.0, 0.0, 0.0])  # level, facing east, in NED/FRD
    q_roll = np.array([math.cos(roll / 2), math.sin(roll / 2), 0.0, 0.0])  # about body x

    def stream():  # rates ignored (type_mask 1|2|4), attitude and thrust used
        v.set_attitude_target(7, frames.multiply_np(q_sp, q_roll), [0.0, 0.0, 0.0], hover)

    stream()
    assert v.set_mode(FlightMode.OFFBOARD)[0]
    fly(v, 0.8, stream)
    rpy = frames.to_rpy_np(quat_enu_flu_to_ned_frd(v.state()[6:10]))
    assert rpy[0] == pytest.approx(roll, abs=math.radians(2.0))
    assert rpy[2] == pytest.approx(yaw_ned, abs=math.radians(2.0))


# ------------------------------------------------------------------ bridge (no MAVLink)


class FakeBus:
    """What the services use of :class:`services.bus.Bus`: everything put is kept."""

    def __init__(self) -> None:
        self.alive: set[str] = set()
        self.sent: list = []

    def put(self, record) -> None:
        self.sent.append(record)

    def events(self, kind: str | None = None) -> list:
        return [e for e in self.sent if isinstance(e, Event) and kind in (None, e.kind)]


class FakeOffboard:
    """MAVSDK's offboard plugin: records what the bridge asks for."""

    def __init__(self) -> None:
        self.sent: list = []
        self.started = self.stopped = 0
        self.destroyed = False
        self.fail_send = self.fail_stop = False
        self.stop_result = "SUCCESS"  # PX4's answer to the Hold that stop() commands

    def set_attitude_rate(self, sp) -> None:
        if self.fail_send:
            raise RuntimeError("plugin destroyed")
        self.sent.append(sp)

    def start(self) -> None:
        self.started += 1

    def stop_async(self, callback) -> None:
        if self.fail_stop:
            raise RuntimeError("plugin destroyed")
        self.stopped += 1
        callback(SimpleNamespace(name=self.stop_result), None)

    def destroy(self) -> None:
        self.destroyed = True


class FakeAction:
    def __init__(self) -> None:
        self.calls: list[str] = []

    def __getattr__(self, name: str):
        return lambda *args: self.calls.append(name)


def bridge(*argv: str) -> Px4Bridge:
    """A bridge as ``setup`` leaves it, on a healthy vehicle armed in Hold, with the MAVSDK
    plugins and the bus replaced by recording fakes."""
    parser = options.common_parser("bridge", "test")
    px4_bridge._extra(parser)
    b = Px4Bridge(parser.parse_args(list(argv)))
    b.bus = FakeBus()
    b._init_state()
    b.system = None
    b._offboard_cls = lambda system: FakeOffboard()
    b.offboard = FakeOffboard()
    b.action = FakeAction()
    health = ("is_gyrometer_calibration_ok", "is_local_position_ok", "is_armable")
    b._telemetry.update(
        connected=True,
        armed=True,
        mode="HOLD",
        landed="IN_AIR",
        gyro_flu=np.zeros(3),
        health=dict.fromkeys(health, True),
    )
    return b


def stream(b: Px4Bridge, mode: str = "track", thrust: float = 6.0) -> None:
    """One controller setpoint, after a steady stream."""
    b.on_setpoint(Setpoint(u=[thrust, 0.0, 0.0, 0.0], state_seq=1, stamp=1.0, mode=mode))
    b._stream_since = time.monotonic() - 10.0


def engaged_bridge(*argv: str) -> Px4Bridge:
    """A bridge flying the vehicle in offboard (its events so far dropped)."""
    b = bridge(*argv)
    stream(b)
    b.engage()
    assert b._engaged, [e.text for e in b.bus.events()]
    b.bus.sent.clear()
    return b


def commands(b: Px4Bridge) -> list[str]:
    return [c.name for c in b.bus.sent if isinstance(c, Command)]


@pytest.mark.parametrize("start_mission", [True, False])
def test_engaging_offboard_clears_the_failsafe_whoever_starts_the_mission(start_mission):
    b = bridge(*(() if start_mission else ("--no-start-mission",)))
    stream(b)
    b.engage()
    assert b._engaged and b.offboard.started == 1
    assert [e.kind for e in b.bus.events()] == ["offboard", "failsafe_cleared"]
    assert commands(b) == (["start"] if start_mission else [])


@pytest.mark.parametrize("name", ["hold", "land", "stop"])
def test_an_operator_exit_from_offboard_is_announced_as_a_failsafe(name):
    b = engaged_bridge()
    b._do_command(Command(name=name, stamp=1.0))
    assert not b._engaged and b.offboard.stopped == 1
    (e,) = b.bus.events("failsafe")
    assert e.severity == "info" and e.data["reason"] == "command"
    assert e.data["action"] == ("land" if name == "land" else "hold")
    assert b.stats["failsafes"] == 0 and b.stats["offboard_exits"] == 1


def test_a_controller_failsafe_makes_the_bridge_leave_offboard():
    b = engaged_bridge("--failsafe", "land")
    b.on_event(Event(kind="failsafe", text="hover", stamp=1.0, src="px4sim/1"))
    assert b._engaged  # not the controller's
    b.on_event(
        Event(kind="failsafe", text="hover", stamp=1.0, src="controller/1", data={"reason": "x"})
    )
    assert not b._engaged
    (e,) = b.bus.events("failsafe")
    assert e.severity == "warning" and e.data["reason"] == "controller_failsafe"
    assert e.data["action"] == "land" and b.stats["failsafes"] == 1


def test_arming_is_refused_after_a_controller_failsafe_until_it_tracks_again():
    b = bridge()
    b.on_event(Event(kind="failsafe", text="hover", stamp=1.0, src="controller/1"))
    stream(b, mode="hover")
    b.engage()
    assert not b._engaged and b.offboard.started == 0
    (e,) = b.bus.events("info")
    assert "controller reported a failsafe" in e.text
    stream(b, mode="track")
    b.engage()
    assert b._engaged


def test_consecutive_send_errors_leave_offboard():
    b = engaged_bridge("--max-send-errors", "3")
    b.offboard.fail_send = True
    stream(b)
    stream(b)
    assert b._engaged and b.stats["send_errors"] == 2
    b.offboard.fail_send = False
    stream(b)  # a success resets the run
    b.offboard.fail_send = True
    stream(b)
    stream(b)
    assert b._engaged
    stream(b)
    assert not b._engaged
    (e,) = b.bus.events("failsafe")
    assert e.data["reason"] == "send_errors" and b.stats["failsafes"] == 1


def test_a_failing_offboard_stop_drops_the_plugin_and_is_reported():
    b = engaged_bridge()
    old = b.offboard
    old.fail_stop = True
    assert b.leave_offboard("test", "hold", reason="test", wait=True)
    assert not b._engaged
    assert old.destroyed and b.offboard is not old  # MAVSDK's re-send timer is gone
    assert [e.kind for e in b.bus.events()] == ["failsafe", "fault", "fault"]
    assert "not sent" in b.bus.events("fault")[0].text
    assert b.action.calls == ["land"]  # no Hold: Land (next test)


@pytest.mark.parametrize("operator", [False, True])
def test_a_failsafe_whose_hold_is_denied_lands(operator):
    # PX4 denies Hold without a position estimate (mocap lost): a failsafe must not leave
    # the vehicle on its last setpoint until PX4's own offboard-loss timeout. An operator's
    # hold is only reported: what to do next is the operator's call.
    b = engaged_bridge()
    b.offboard.stop_result = "COMMAND_DENIED"
    if operator:
        b._do_command(Command(name="hold", stamp=1.0))
    else:
        b.on_event(Event(kind="failsafe", text="hover", stamp=1.0, src="controller/1"))
    b.leave_worker.join(5.0)  # PX4's answer is awaited off the caller's thread
    assert not b.leave_worker.is_alive()
    faults = [e.text for e in b.bus.events("fault")]
    assert faults[0] == "Hold command: COMMAND_DENIED"
    if operator:
        assert faults == ["Hold command: COMMAND_DENIED"] and b.action.calls == []
    else:
        assert faults[1] == "no Hold after a failsafe: commanding Land"
        assert b.action.calls == ["land"] and b.stats["hold_denied_landings"] == 1


def test_the_watchdog_survives_its_own_errors():
    b = engaged_bridge()
    b._last_rx = time.monotonic() - 1.0  # setpoints stopped: the watchdog acts at once
    calls = []

    def leave(*args, **kw) -> bool:  # e.g. stop_async on a destroyed plugin
        calls.append(kw["reason"])
        if len(calls) == 1:
            raise RuntimeError("boom")
        b.stop.set()
        return True

    b.leave_offboard = leave
    b._watchdog_loop()
    assert calls == ["setpoint_timeout"] * 2 and b.stats["watchdog_errors"] == 1
    (e,) = b.bus.events("fault")
    assert "boom" in e.text


def test_the_watchdog_leaves_offboard_when_setpoints_stop():
    b = engaged_bridge("--setpoint-timeout", "0.05")
    b._last_rx = time.monotonic() - 1.0
    b._watchdog_check()
    assert not b._engaged
    (e,) = b.bus.events("failsafe")
    assert e.data["reason"] == "setpoint_timeout" and e.severity == "warning"


def test_mocap_that_cannot_be_forwarded_is_a_fault_event_not_a_log_flood():
    from mavsdk.plugins import mocap as mc

    from services.messages import Mocap

    class FailingMocap:
        def set_odometry(self, odom) -> None:
            raise RuntimeError("connection lost")

    b = bridge()
    b._mc, b.mocap = mc, FailingMocap()
    for k in range(200):  # 1 s of frames at 200 Hz
        t = 10.0 + k * 0.005
        b.on_mocap(
            Mocap(position=[0.0, 0.0, 1.0], quaternion=[1.0, 0, 0, 0], capture_stamp=t, stamp=t)
        )
    (fault,) = b.bus.events("fault")  # once, not per frame
    assert "mocap not forwarded to PX4: connection lost" in fault.text
    assert b.stats["mocap_forward_errors"] == 200 and b.stats["mocap_forwarded"] == 0


@pytest.mark.parametrize(
    ("argv", "vehicle", "other"),
    [((), "vehicle", "cf1"), (("--mocap-body", "cf1"), "cf1", "vehicle")],
)
def test_only_the_vehicles_mocap_frames_are_forwarded_and_fenced(argv, vehicle, other):
    """Other rigid bodies on the stream (the payload; ``other``, the body ``--mocap-body``
    does not name; here outside the geofence) are not the vehicle: not forwarded to PX4,
    not checked against the fence, not counted."""
    from mavsdk.plugins import mocap as mc

    from services.messages import PAYLOAD_BODY, Mocap

    class RecordingMocap:
        def __init__(self) -> None:
            self.sent: list = []

        def set_odometry(self, odom) -> None:
            self.sent.append(odom)

    b = engaged_bridge(*argv)
    b._mc, b.mocap = mc, RecordingMocap()
    for body, p in (
        (vehicle, [0.0, 0.0, 1.0]),
        (PAYLOAD_BODY, [50.0, 0.0, 1.0]),
        (other, [50.0, 0.0, 1.0]),
    ):
        b.on_mocap(
            Mocap(position=p, quaternion=[1.0, 0, 0, 0], body=body, capture_stamp=5.0, stamp=5.0)
        )
    assert b._engaged and not b.bus.events()
    assert b.stats["mocap_forwarded"] == 1 and len(b.mocap.sent) == 1
    assert b.mocap.sent[0].position_body.z_m == pytest.approx(-1.0)  # the vehicle's, NED
    # The vehicle itself outside the fence: offboard is left.
    b.on_mocap(
        Mocap(
            position=[50.0, 0, 1.0],
            quaternion=[1.0, 0, 0, 0],
            body=vehicle,
            capture_stamp=5.1,
            stamp=5.1,
        )
    )
    assert not b._engaged and b.bus.events("failsafe")[0].data["reason"] == "geofence"


# ------------------------------------------------------------------ px4sim


@pytest.mark.parametrize("no_start", [True, False])
def test_px4sim_resends_start_to_a_rejoining_controller_only_when_it_owns_it(no_start):
    from services.px4_sim import Px4SimNode

    node = Px4SimNode(argparse.Namespace(out=None, no_start_command=no_start))
    node.bus = FakeBus()
    node._flight_stamp = 12.5
    node._hold = None  # flying the stack's setpoints (offboard)
    node._on_alive("controller", True)
    assert commands(node) == ([] if no_start else ["start"])
    # A rejoining adapter: the clock, and whether PX4 flies the stack's setpoints now.
    node._hold = np.zeros(3)  # PX4 flies to its own target (not in offboard)
    node._on_alive("adapter", True)
    node._hold = None
    node._on_alive("adapter", True)
    sent = [c.args for c in node.bus.sent if isinstance(c, Command)]
    flights = [{"t0": 12.5, "flying": f} for f in (True, False, True)]  # controller first
    assert sent == ([] if no_start else flights)


def test_the_bridge_tells_a_rejoining_adapter_whether_offboard_flies_the_setpoints():
    b = bridge()
    b._on_alive_change("adapter", True)
    assert commands(b) == []  # no mission started by this bridge yet
    stream(b)
    b.engage()
    (t0,) = [c.args["t0"] for c in b.bus.sent if isinstance(c, Command)]
    b.bus.sent.clear()
    b._on_alive_change("adapter", True)
    b._do_command(Command(name="hold", stamp=1.0))
    b._on_alive_change("adapter", True)
    starts = [c.args for c in b.bus.sent if isinstance(c, Command)]
    assert starts == [{"t0": t0, "flying": True}, {"t0": t0, "flying": False}]


def test_the_event_waiter_keeps_the_newest_records_and_numbers_them_all():
    from deploy.px4_profile import EventWaiter

    events = EventWaiter(keep=3)
    for k in range(5):
        events({"kind": "info", "n": k})
    assert events.mark() == 5 and [r["n"] for r in events.events] == [2, 3, 4]
    n_is = lambda k: lambda r: r["n"] == k  # noqa: E731
    assert events.wait(n_is(0), 0.0) is None  # no longer kept
    assert events.wait(n_is(3), 0.0)["n"] == 3
    assert events.wait(n_is(3), 0.0, after=4) is None  # numbered before the mark
    assert events.wait(lambda r: True, 0.0, after=4)["n"] == 4
    assert events.wait(lambda r: True, 0.0, after=1)["n"] == 2  # the oldest kept
