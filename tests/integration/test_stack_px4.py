"""Hardware-in-the-loop style: the service stack flying a simulated PX4 through MAVLink.

MuJoCo quadrotor as PX4 (``px4sim``) <-> MAVLink over UDP loopback <-> MAVSDK <-> bridge
<-> Zenoh <-> estimator, adapter, controller, all real processes started by the launcher
(profile ``px4 --simulate``), on the wall clock.

1. The figure-eight with a payload release tracks as well through the PX4 chain as the
   ``sim`` profile does with the same seed and plan (median RMSE of three flights each
   within 15 %; every flight alone on the host).
2. Failsafes: the bridge killed -> the simulated PX4's own ``COM_OF_LOSS_T`` failsafe
   fires; after the supervisor restarted the bridge and offboard is engaged again, the
   controller killed -> the bridge leaves offboard within 0.3 s (+ one PX4 heartbeat for
   the mode to show) and PX4 holds, before its own offboard-loss timeout; the restarted
   controller rejoins under Hold (learning stays paused) and offboard engages again.
3. An operator's ``hold`` leaves offboard and pauses the adapter's learning; arming again
   resumes it.
4. A 4 s mocap dropout: the controller's hover failsafe, PX4 denying Hold (no position
   estimate without vision), the bridge's Land; ``arm`` is refused until the controller
   tracks again.
5. A figure-eight crossing a tight geofence: the bridge leaves offboard, PX4 holds near the
   fence.
6. From the floor: ``arm`` with a take-off height, PX4's take-off, offboard from the hover,
   the operator's ``land``, PX4's landing and disarm.

Both compare flights fly ARCADE with the shipped weights. Before offboard is engaged PX4
holds the vehicle and the controller's setpoints are not applied; the adapter learns only
from the mission ``start`` (sent when offboard is engaged) on.
"""

from __future__ import annotations

import csv
import json
import socket
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from arcade.demo_stack import free_hub
from deploy.launcher import Stack, StackConfig, run_flight
from deploy.px4_profile import EventWaiter, Px4StackConfig, arm
from services.bus import Bus
from services.messages import Command

# Flown on the wall clock, with timing assertions: run alone (``make test``).
pytestmark = pytest.mark.realtime

PLAN = {"speed": 1.0, "duration": 14.0, "release": 0.3, "seed": 0, "rate": 20.0, "method": "ours"}
FLIGHTS = 3
#: Each profile's median tracking RMSE over the figure-eight must stay below this [m].
MAX_RMSE_M = 0.25
COM_OF_LOSS_T = 1.0
HEARTBEAT_S = 1.0
#: The simulated PX4's MAVLink system id (simulator.px4.mavlink_vehicle, as PX4's).
PX4_SYSTEM_ID = 1


def _udp_url() -> str:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return f"udpin://127.0.0.1:{s.getsockname()[1]}"


def _px4_config(out: Path, **options) -> Px4StackConfig:
    """The stack through a simulated PX4 on a fresh hub and UDP port; by default a hover
    plan (the reference stays put) long enough for any fault sequence, no release."""
    plan = {"duration": 60.0, "hover_s": 120.0, "release": -1.0, "method": "ours"}
    return Px4StackConfig(
        out=out,
        hub=free_hub(),
        simulate=True,
        connect=_udp_url(),
        **{**plan, **options},
    )


def _truth(path: Path) -> dict[str, np.ndarray]:
    with path.open() as f:
        rows = list(csv.reader(f))
    data = np.array(rows[1:], dtype=float)
    return {name: data[:, i] for i, name in enumerate(rows[0])}


def _rmse(truth: dict[str, np.ndarray], t_max: float) -> float:
    keep = truth["t"] <= t_max + 1e-9
    err = np.stack([truth[a][keep] - truth[f"ref_{a}"][keep] for a in ("px", "py", "pz")])
    return float(np.sqrt(np.mean(np.sum(err**2, axis=0))))


def _fly_sim_profile(out: Path) -> float:
    result = run_flight(StackConfig(out=out, hub=free_hub(), **PLAN), timeout=120.0)
    assert all(c == 0 for c in result["codes"].values()), result["codes"]
    sim_stats = json.loads((out / "stats" / "sim.json").read_text())
    assert not sim_stats["crashed"] and sim_stats["released_at"] is not None
    return _rmse(_truth(out / "truth.csv"), PLAN["duration"])


def _fly_armed(cfg: Px4StackConfig) -> dict:
    """Fly the plan, armed as soon as the stack is ready; every process exits cleanly."""
    events = EventWaiter()
    armed: list[bool] = []
    result = run_flight(
        cfg, on_event=events, timeout=120.0, on_ready=lambda stack: armed.append(arm(events, cfg))
    )
    assert armed == [True]
    assert all(c == 0 for c in result["codes"].values()), result["codes"]
    return result


def _fly_through_px4(out: Path) -> float:
    result = _fly_armed(_px4_config(out, hover_s=None, **PLAN))
    px4 = json.loads((out / "stats" / "px4sim.json").read_text())
    bridge = json.loads((out / "stats" / "bridge.json").read_text())
    assert not px4["crashed"] and px4["released_at"] is not None
    assert px4["px4_failsafes"] == []
    assert px4["mavlink_rx"]["SET_ATTITUDE_TARGET"] >= 0.9 * PLAN["rate"] * PLAN["duration"]
    assert px4["vision_received"] and bridge["mocap_forwarded"] > 0
    assert bridge["rejects"] == {} and bridge["send_errors"] == 0
    # The vehicle outlives its plan, so the bridge's Hold at shutdown is answered.
    faults = [e for e in result["events"] if e["kind"] == "fault"]
    assert faults == [], faults
    return _rmse(_truth(out / "truth.csv"), PLAN["duration"])


def test_figure_eight_through_px4_tracks_like_the_sim_profile(tmp_path):
    # Realtime flights differ from run to run (scheduling): how fast the model adapts after
    # the release varies, and one flight in several tracks the rest of the lap a few cm
    # worse in either profile. Each profile's tracking is the median of FLIGHTS flights.
    # The flights fly one after the other, each alone on the host as a user's stack does.
    # Two stacks side by side on 2 cores starved both adapters: their realtime processes
    # (simulator, estimator, controller at SCHED_FIFO) took nearly both cores, the adapter
    # made 15-160 of 300 updates, the controllers flew the nominal model for most steps
    # and tracked 0.3-0.6 m in both profiles.
    sim, px4 = [], []
    for i in range(FLIGHTS):
        sim.append(_fly_sim_profile(tmp_path / f"sim{i}"))
        px4.append(_fly_through_px4(tmp_path / f"px4{i}"))
    rmse_sim, rmse_px4 = float(np.median(sim)), float(np.median(px4))
    print(
        f"tracking RMSE (median of {FLIGHTS}): sim profile {rmse_sim:.3f} m "
        f"{np.round(sim, 3).tolist()}, through PX4 {rmse_px4:.3f} m "
        f"{np.round(px4, 3).tolist()} ({100 * (rmse_px4 / rmse_sim - 1):+.1f} %)"
    )
    # Both profiles track: an adapter starved on a loaded host made both fly the nominal
    # model (0.37-0.66 m), which a comparison of the two alone did not catch.
    assert rmse_sim <= MAX_RMSE_M and rmse_px4 <= MAX_RMSE_M
    # Through PX4 no worse than in the sim profile: by at most 15 %, or by what tells apart
    # two sets of FLIGHTS realtime flights of one profile (2.5 standard errors of the
    # difference of their means). Alone on the host the flights tracked 0.039-0.046 m; two
    # stacks side by side varied by +-5 cm, where 15 % of a median of three was within the
    # noise and failed on equal profiles.
    diff = float(np.mean(px4) - np.mean(sim))
    se = float(np.sqrt((np.var(px4, ddof=1) + np.var(sim, ddof=1)) / FLIGHTS))
    assert diff <= max(0.15 * float(np.mean(sim)), 2.5 * se), (diff, se)


def _wait(events: EventWaiter, pred, timeout: float, after: int, what: str) -> dict:
    rec = events.wait(pred, timeout, after=after)
    assert rec is not None, f"no {what} within {timeout} s"
    return rec


def _from(service: str, kind: str):
    """Predicate: an event of ``kind`` from ``service``."""
    return lambda r: r["kind"] == kind and r["src"].startswith(f"{service}/")


def _px4_mode(mode: str):
    """Predicate: the bridge reports PX4 in flight mode ``mode``."""
    return lambda r: _from("bridge", "mode_change")(r) and r["data"]["mode"] == mode


def _learning(value: bool):
    """Predicate: the adapter starts (True) or pauses (False) learning."""
    return lambda r: _from("adapter", "info")(r) and r["data"].get("learning") is value


def _engage(events: EventWaiter, cfg: Px4StackConfig, learning: bool = True) -> None:
    """Arm through the bridge; PX4 in Offboard (and the adapter learning) afterwards."""
    n = events.mark()
    assert arm(events, cfg)
    if learning:
        _wait(events, _learning(True), 5.0, n, "adapter learning")
    _wait(events, _px4_mode("OFFBOARD"), 5.0, n, "PX4 in Offboard")


def _operator(cfg: Px4StackConfig, command: str) -> None:
    """Send an operator's command to the bridge, as ``arcade up``'s console does."""
    with Bus(cfg.vehicle, "operator", cfg.bus_config("operator")) as bus:
        bus.wait_alive(["bridge"], 10.0)
        bus.put(Command(name=command, target="bridge", stamp=time.monotonic()))


def test_failsafes_bridge_killed_then_controller_killed_and_restarted(tmp_path):
    # Hover plan (the reference stays put), long enough for both faults.
    cfg = _px4_config(
        tmp_path,
        weights=tmp_path / "none.eqx",
        of_loss_s=COM_OF_LOSS_T,
        of_loss_action="hold",
    )
    events = EventWaiter()

    with Stack(cfg, on_event=events) as stack:
        stack.wait_ready()
        _engage(events, cfg, learning=False)

        # The bridge dies: the simulated PX4's offboard-loss failsafe (COM_OF_LOSS_T) fires.
        n = events.mark()
        t_kill = time.monotonic()
        stack.kill("bridge")
        fs = _wait(
            events,
            lambda r: r["kind"] == "failsafe" and r["src"].startswith("px4sim"),
            COM_OF_LOSS_T + 5.0,
            n,
            "PX4 offboard-loss failsafe",
        )
        assert "offboard" in fs["text"].lower() and fs["data"]["mode"] == "HOLD"
        assert COM_OF_LOSS_T - 0.1 <= fs["stamp"] - t_kill <= COM_OF_LOSS_T + 0.5

        # The supervisor restarts the bridge; offboard is engaged again (explicitly).
        _wait(
            events,
            lambda r: r["kind"] == "restart" and r["data"].get("service") == "bridge",
            10.0,
            n,
            "bridge restart",
        )
        _wait(
            events,
            lambda r: r["kind"] == "ready" and r["src"].startswith("bridge"),
            60.0,
            n,
            "restarted bridge ready",
        )
        _engage(events, cfg, learning=False)

        # The controller dies: the bridge leaves offboard -> Hold within 0.3 s + one
        # heartbeat, before PX4's own offboard-loss timeout would.
        n = events.mark()
        t_kill = time.monotonic()
        stack.kill("controller")
        fs = _wait(events, _from("bridge", "failsafe"), 5.0, n, "bridge failsafe")
        assert fs["data"]["reason"] in ("controller_lost", "setpoint_timeout")
        hold = _wait(events, _px4_mode("HOLD"), 5.0, n, "PX4 in Hold")
        assert hold["stamp"] - t_kill <= 0.3 + HEARTBEAT_S
        print(
            f"controller killed -> bridge failsafe after {fs['stamp'] - t_kill:.3f} s, "
            f"PX4 reports Hold after {hold['stamp'] - t_kill:.3f} s"
        )
        # PX4 did not need its own failsafe: the bridge acted first; the vehicle holds.
        time_px4_would_fire = t_kill + COM_OF_LOSS_T + 0.5
        late = events.wait(
            lambda r: r["kind"] == "failsafe" and r["src"].startswith("px4sim"),
            max(0.0, time_px4_would_fire - time.monotonic()),
            after=n,
        )
        assert late is None, late

        # The supervisor restarts the controller under Hold; it rejoins the mission (the
        # clock re-sent, which does not resume learning), and offboard engages again.
        _wait(
            events,
            lambda r: r["kind"] == "restart" and r["data"].get("service") == "controller",
            10.0,
            n,
            "controller restart",
        )
        stack.wait_alive(["controller"], 60.0)  # its token: warmed up and answering
        assert events.wait(_learning(True), 0.0, after=n) is None
        _engage(events, cfg)
        stack.stop()
    px4 = json.loads((tmp_path / "stats" / "px4sim.json").read_text())
    assert not px4["crashed"]
    assert [f["mode"] for f in px4["px4_failsafes"]] == ["HOLD"]


def test_operator_hold_pauses_learning_until_offboard_is_engaged_again(tmp_path):
    # The adapter learns only while PX4 flies the stack's setpoints: an operator's hold
    # leaves offboard (the bridge's failsafe event, reason "command"), the adapter pauses
    # and counts the steps it does not learn from; an adapter restarted under the hold
    # waits as well; arming again resumes it.
    cfg = _px4_config(tmp_path)
    events = EventWaiter()

    with Stack(cfg, on_event=events) as stack:
        stack.wait_ready()
        _engage(events, cfg)

        n = events.mark()
        _operator(cfg, "hold")
        fs = _wait(events, _from("bridge", "failsafe"), 5.0, n, "bridge leaving offboard")
        assert fs["data"]["reason"] == "command" and fs["data"]["action"] == "hold"
        _wait(events, _learning(False), 5.0, n, "adapter pausing")
        _wait(events, _px4_mode("HOLD"), 5.0, n, "PX4 in Hold")
        # The adapter dies under Hold: the restarted one saw neither the start nor the
        # exit from offboard. The simulated PX4 re-sends it the mission's clock with
        # ``flying`` false, and it says that it waits.
        m = events.mark()
        stack.kill("adapter")
        waiting = _wait(events, _learning(False), 60.0, m, "restarted adapter waiting")
        assert "under a failsafe" in waiting["text"], waiting
        assert events.wait(_learning(True), 0.0, after=m) is None
        # Arming again waits for a steady setpoint stream (1 s) while PX4 holds: the
        # adapter sees states it must not learn from. Then it learns: its model's step
        # count (the learned steps) moves on from where the hold left it.
        with Bus(cfg.vehicle, "operator", cfg.bus_config("operator")) as bus:
            first_step: list[int] = []
            learned = threading.Event()

            def on_model(model) -> None:
                first_step[:] = first_step or [model.step]
                if model.step > first_step[0]:
                    learned.set()

            bus.subscribe("model", on_model)
            _engage(events, cfg)
            assert events.wait(_from("bridge", "failsafe_cleared"), 0.0, after=n) is not None
            assert learned.wait(10.0), f"no learned step after engaging (step {first_step})"
        stack.stop()
    assert stack.restarts["adapter"] == 1
    adapter = json.loads((tmp_path / "stats" / "adapter.json").read_text())  # the restarted one
    assert adapter["not_applied"] > 0 and adapter["learned"] > 0, adapter
    px4 = json.loads((tmp_path / "stats" / "px4sim.json").read_text())
    assert not px4["crashed"] and px4["px4_failsafes"] == []


def test_long_mocap_dropout_lands_and_arming_waits_for_tracking(tmp_path):
    # Mocap lost for 6 s, 2 s into the mission (long enough that the failsafe chain below
    # is through before it ends, also on a loaded machine): the controller hovers level without
    # position feedback, gives up after its --max-hover-s (1 s, a failsafe event), the
    # bridge leaves offboard; PX4 has no position estimate, so it denies Hold and the
    # bridge commands Land. Arming is refused until the controller tracks again.
    cfg = _px4_config(tmp_path, extra={"px4sim": ["--mocap-fault", "dropout@2.0+6.0"]})
    events = EventWaiter()

    with Stack(cfg, on_event=events) as stack:
        stack.wait_ready()
        _engage(events, cfg)

        n = events.mark()
        ctl = _wait(events, _from("controller", "failsafe"), 10.0, n, "controller failsafe")
        assert ctl["data"]["reason"] == "hover_timeout"
        fs = _wait(events, _from("bridge", "failsafe"), 5.0, n, "bridge leaving offboard")
        assert fs["data"]["reason"] == "controller_failsafe"
        assert fs["data"]["controller_reason"] == "hover_timeout"
        _wait(events, _learning(False), 5.0, n, "adapter pausing")
        _wait(
            events,
            lambda r: r["src"].startswith("bridge/") and r["text"].startswith("no Hold"),
            5.0,
            n,
            "Land after the denied Hold",
        )
        _wait(events, _px4_mode("LAND"), 5.0, n, "PX4 in Land")
        # Still in the dropout: the controller streams hover setpoints, arming is refused.
        m = events.mark()
        assert not arm(events, cfg)
        refused = _wait(
            events, lambda r: r["text"].startswith("arm refused"), 0.0, m, "arm refused"
        )
        assert "has not tracked since" in refused["text"], refused["text"]
        tracked = events.wait(lambda r: r["text"].startswith("tracking resumed"), 0.0, after=n)
        assert tracked is None, "the dropout ended before arming could be checked"

        # Mocap back: the controller tracks again.
        _wait(
            events,
            lambda r: r["src"].startswith("controller/") and r["text"].startswith("tracking"),
            10.0,
            n,
            "controller tracking again",
        )
        stack.stop()
    controller = json.loads((tmp_path / "stats" / "controller.json").read_text())
    assert controller["hover_failsafes"] == 1, controller["hover_failsafes"]
    bridge = json.loads((tmp_path / "stats" / "bridge.json").read_text())
    assert bridge["hold_denied_landings"] == 1
    adapter = json.loads((tmp_path / "stats" / "adapter.json").read_text())
    assert adapter["not_applied"] > 0, adapter
    px4 = json.loads((tmp_path / "stats" / "px4sim.json").read_text())
    # PX4's own offboard-loss failsafe never fired: the bridge acted first.
    assert not px4["crashed"] and px4["px4_failsafes"] == []
    assert px4["mocap_faults"]["dropout"] > 0


class _GroundStation:
    """A UDP port a ground station would listen on: the MAVLink systems heard there."""

    def __init__(self) -> None:
        from pymavlink.dialects.v20 import common as mav

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.url = f"udpout://127.0.0.1:{self.sock.getsockname()[1]}"
        self.heartbeats: Counter[int] = Counter()  # heartbeats heard per system id
        self._parser = mav.MAVLink(None)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65535)
            except TimeoutError:
                continue
            for msg in self._parser.parse_buffer(data) or []:
                if msg.get_type() == "HEARTBEAT":
                    self.heartbeats[msg.get_srcSystem()] += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.sock.close()


def test_geofence_breach_leaves_offboard_and_px4_holds_inside_reach(tmp_path):
    # A 2 m x 2 m fence around the centre of the 4 m x 2 m figure-eight: the vehicle
    # crosses it on the first lap; the bridge leaves offboard to Hold, PX4 holds where it
    # is (not a crash, although the plan's reference moves on), learning pauses. A ground
    # station beside the bridge (--forward) hears the simulated PX4 meanwhile.
    gcs = _GroundStation()
    duration = 14.0  # the reference ends more than 2 m from the hold point
    cfg = _px4_config(
        tmp_path,
        speed=1.0,
        duration=duration,
        hover_s=None,  # the scenario's: the figure-eight
        bridge_args=["--geofence=-1,1,-1,1,0,3", f"--forward={gcs.url}"],
    )
    try:
        result = _fly_armed(cfg)
    finally:
        gcs.close()
    # PX4's heartbeats (one a second) forwarded to the station all through the flight.
    assert gcs.heartbeats[PX4_SYSTEM_ID] >= duration / (2 * HEARTBEAT_S), gcs.heartbeats
    fences = [r for r in result["events"] if _from("bridge", "failsafe")(r)]
    assert fences and fences[0]["data"]["reason"] == "geofence", fences
    assert "outside the geofence" in fences[0]["text"]
    modes = [r["data"]["mode"] for r in result["events"] if _from("bridge", "mode_change")(r)]
    assert modes[-2:] == ["OFFBOARD", "HOLD"], modes
    assert any(_learning(False)(r) for r in result["events"])
    px4 = json.loads((tmp_path / "stats" / "px4sim.json").read_text())
    assert not px4["crashed"] and px4["px4_failsafes"] == []
    truth = _truth(tmp_path / "truth.csv")
    # Held within a vehicle's reach of the fence (the braking distance at 1 m/s), far from
    # the reference by the end.
    held = truth["failsafe"] == 1.0
    assert held.any()
    end = np.array([truth[f"ref_{a}"][-1] - truth[a][-1] for a in ("px", "py", "pz")])
    assert np.linalg.norm(end) > 2.0
    assert np.abs(truth["px"][held]).max() < 1.5 and np.abs(truth["py"][held]).max() < 1.5


def test_take_off_from_the_ground_fly_then_land_on_command(tmp_path):
    # A real vehicle's day: on the floor, disarmed; `arm` with a take-off height lets PX4
    # take off by itself, offboard starts from the hover; the operator's `land` lands it
    # and PX4 disarms (a landing is not a crash).
    cfg = _px4_config(tmp_path, on_ground=True, takeoff_m=1.5)
    events = EventWaiter()

    with Stack(cfg, on_event=events) as stack:
        stack.wait_ready()
        n = events.mark()
        assert arm(events, cfg)
        _wait(events, _px4_mode("TAKEOFF"), 0.0, n, "PX4 taking off")
        _wait(events, _px4_mode("OFFBOARD"), 5.0, n, "PX4 in Offboard")
        n = events.mark()
        _operator(cfg, "land")
        _wait(events, _px4_mode("LAND"), 5.0, n, "PX4 landing")
        _wait(
            events,
            lambda r: r["src"].startswith("px4sim/") and "Landing detected" in r["text"],
            15.0,
            n,
            "PX4 landed and disarmed",
        )
        stack.stop()
    px4 = json.loads((tmp_path / "stats" / "px4sim.json").read_text())
    assert not px4["crashed"] and px4["px4_failsafes"] == []
    truth = _truth(tmp_path / "truth.csv")
    assert truth["pz"][-1] < 0.1 and truth["pz"].max() > 1.3
