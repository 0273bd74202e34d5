"""The simulator service acts on the controller's failsafe (hover without position feedback
for too long) as a flight controller does: it holds position, and resumes offboard control
only once the controller answers out of ``hover`` again.

In process: the service is wired as ``Service.run`` wires it, on a loopback session; a
scripted controller answers each ``imu`` control instant synchronously (setpoint modes and
the failsafe event per instant), and the physics is a vehicle at rest.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from loopback import LoopbackSession

from services import options, sim_node
from services.bus import Bus
from services.messages import Event, Setpoint, decode, encode

PERIOD = 0.05
START = np.array([0.0, 0.0, 1.0])


class RestingSim:
    """A vehicle that stays where it is: the physics is not under test here."""

    setpoint = np.zeros(4)
    payload_attached = False
    max_thrust = 10.0

    def __init__(self) -> None:
        self.time = 0.0
        self.x = np.r_[START, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        self.mocap = SimpleNamespace(read=lambda _until: [])
        self.gyro = SimpleNamespace(read=lambda _until: [])

    def state(self) -> np.ndarray:
        return self.x.copy()

    def read_mocap(self) -> list:
        return []

    def read_gyro(self) -> list:
        return []

    def set_setpoint(self, u: np.ndarray) -> np.ndarray:
        return np.asarray(u, dtype=float)

    def step(self, dt: float) -> None:
        self.time += dt

    def hover_thrust(self) -> float:
        return 0.5 * 9.81

    def carried_mass(self) -> float:
        return 0.5


class ScriptedController:
    """Answers the ``i``-th control instant in ``mode(i)``; with the answers to the
    instants in ``failsafe_at``, raises the controller's failsafe: its reason on the
    setpoint, and the failsafe event (the controller publishes it first; on the bus it has
    a lower priority than setpoints, so it may arrive after, ``event="last"``, or be lost,
    ``event="lost"``)."""

    def __init__(
        self, session, mode: Callable[[int], str], failsafe_at=(), src="controller/c0",
        event="first",
    ):  # fmt: skip
        self.session, self.mode, self.failsafe_at, self.src = session, mode, failsafe_at, src
        self.event_last = event == "last"
        self.event_lost = event == "lost"
        self.seq = {"setpoint": 0, "event": 0}
        self.instants: list[float] = []
        session.on_put["arcade/test/imu"] = self.answer

    def send(self, topic: str, record) -> None:
        self.seq[topic] += 1
        record = record.replace(seq=self.seq[topic], src=self.src)
        self.session.deliver(f"arcade/test/{topic}", encode(record))

    def answer(self, payload: bytes) -> None:
        i, stamp = len(self.instants), decode("imu", payload).stamp
        self.instants.append(stamp)
        mode = self.mode(i)
        failsafe = i in self.failsafe_at and self.src.startswith("controller/")
        if mode != "silent" and self.event_last:
            self.send("setpoint", self.setpoint(i, stamp, mode, failsafe))
        if i in self.failsafe_at and not self.event_lost:
            self.send(
                "event",
                Event(
                    kind="failsafe",
                    severity="error",
                    text="hovering for 1.00 s: the vehicle link must fail safe",
                    data={"reason": "hover_timeout", "hover_s": 1.0},
                    stamp=stamp,
                ),
            )
        if mode != "silent" and not self.event_last:
            self.send("setpoint", self.setpoint(i, stamp, mode, failsafe))

    @staticmethod
    def setpoint(i: int, stamp: float, mode: str, failsafe: bool = False) -> Setpoint:
        return Setpoint(
            u=[4.9, 0.0, 0.0, 0.0],
            state_seq=i,
            stamp=stamp,
            mode=mode,
            failsafe="hover_timeout" if failsafe else "",
        )


def make_node(
    *argv: str, n_steps: int = 30, out: Path | None = None
) -> tuple[sim_node.SimNode, LoopbackSession]:
    parser = options.common_parser("sim", "test")
    sim_node._extra(parser)
    if out is not None:
        argv = ("--out", str(out), *argv)
    node = sim_node.SimNode(parser.parse_args(["--vehicle", "test", "--wait-for", "", *argv]))
    session = LoopbackSession(echo=True)
    node.bus = Bus("test", "sim").open(session=session)
    node.bus.subscribe("command", node._on_command)
    node.bus.publisher("event")
    node.setup(node.bus)
    node.sim = RestingSim()
    node.n_steps, node.k_release = n_steps, -1
    node._ref_t, node._ref_p = np.array([0.0, 1e3]), np.array([START, START])
    return node, session


def truth_rows(node: sim_node.SimNode) -> np.ndarray:
    """The rows of the node's ``truth.csv`` once the flight is over."""
    node.truth.close()
    return np.loadtxt(node.truth.path, delimiter=",", skiprows=1, ndmin=2)


def sim_events(session: LoopbackSession) -> list[Event]:
    return [
        e
        for e in (decode("event", p) for p in session.published["arcade/test/event"])
        if e.kind in ("failsafe", "failsafe_cleared")
    ]


def hover_between(first: int, last: int) -> Callable[[int], str]:
    return lambda i: "hover" if first <= i <= last else "track"


LOCKSTEP = ("--lockstep", "--rate", str(1 / PERIOD), "--failsafe-resume", "3")


@pytest.mark.parametrize("event", ["first", "last", "lost"])
def test_lockstep_the_controllers_failsafe_holds_until_it_tracks_again(event, tmp_path):
    node, session = make_node(*LOCKSTEP, out=tmp_path)
    # Hover from instant 5; the failsafe comes with the answer to instant 10; tracking
    # from 15, interrupted once by a hover answer at 17.
    ScriptedController(
        session,
        lambda i: "hover" if 5 <= i <= 14 or i == 17 else "track",
        failsafe_at=(10,),
        event=event,
    )
    node._lockstep()
    engaged, cleared = sim_events(session)
    # At the instant after the answer that carried it, whenever the event arrives (it is
    # not needed in lockstep).
    assert engaged.kind == "failsafe" and engaged.stamp == pytest.approx(11 * PERIOD)
    assert engaged.src.startswith("sim/") and engaged.severity == "error"
    assert engaged.text.startswith("controller failsafe: hover_timeout")
    assert engaged.data["reason"] == "controller_failsafe"
    assert engaged.data["controller_reason"] == "hover_timeout"
    # Hover answers (11-14, 17) do not count; 18, 19, 20 are the three in a row.
    assert cleared.kind == "failsafe_cleared" and cleared.stamp == pytest.approx(20 * PERIOD)
    assert node.stats["controller_failsafes"] == 1 and len(node.stats["failsafes"]) == 1
    assert node.stats["failsafes"][0]["controller_reason"] == "hover_timeout"
    assert node.stats["steps"] == 30 and not node.stats["crashed"]
    held = list(truth_rows(node)[:, -1])  # the truth log's failsafe column
    assert held == [float(11 <= i < 20) for i in range(30)]


def test_lockstep_failsafe_events_of_other_services_are_not_the_controllers():
    node, session = make_node(*LOCKSTEP, n_steps=15)
    ScriptedController(session, hover_between(5, 14), failsafe_at=(8,), src="bridge/b0")
    node._lockstep()
    assert sim_events(session) == [] and node.stats["controller_failsafes"] == 0
    assert node._controller_failsafe is None


def test_lockstep_setpoint_watchdog_still_resumes_on_any_answer():
    """The watchdog's hold is about the link: answers in hover end it (the controller's
    own hover bound then asks for the failsafe again)."""
    node, session = make_node(
        *LOCKSTEP, "--step-timeout", "0.001", "--failsafe-after", "0.2", n_steps=20
    )
    ScriptedController(session, lambda i: "silent" if 3 <= i <= 6 else "hover")
    node._lockstep()
    engaged, cleared = sim_events(session)
    assert engaged.text.startswith("no setpoint for") and "reason" not in engaged.data
    assert engaged.stamp == pytest.approx(6 * PERIOD)
    assert cleared.stamp == pytest.approx(9 * PERIOD)  # 7, 8, 9 answered in hover
    assert node.stats["controller_failsafes"] == 0


def test_lockstep_the_controllers_failsafe_during_a_watchdog_hold_waits_for_tracking():
    node, session = make_node(
        *LOCKSTEP, "--step-timeout", "0.001", "--failsafe-after", "0.2", n_steps=25
    )
    ScriptedController(
        session,
        lambda i: "silent" if 3 <= i <= 6 else ("hover" if i <= 12 else "track"),
        failsafe_at=(7,),
    )
    node._lockstep()
    engaged, cleared = sim_events(session)  # one hold: the watchdog's, then both causes
    assert engaged.stamp == pytest.approx(6 * PERIOD) and "reason" not in engaged.data
    assert cleared.stamp == pytest.approx(15 * PERIOD)  # 13, 14, 15 track
    assert node.stats["controller_failsafes"] == 1


def test_realtime_the_controllers_failsafe_holds_until_it_tracks_again(tmp_path):
    rate = 100.0
    node, session = make_node(
        "--rate", str(rate), "--preroll", "0", "--substep", "0.005", "--failsafe-after", "30",
        n_steps=25, out=tmp_path,
    )  # fmt: skip
    ctrl = ScriptedController(session, hover_between(5, 14), failsafe_at=(0, 10))
    node._realtime()
    engaged, cleared = sim_events(session)
    # The failsafe at instant 0 came before the mission started (at instant 1): ignored.
    assert node.stats["controller_failsafes_ignored"] == 1
    assert node.stats["controller_failsafes"] == 1
    # Engaged in the physics chunk after instant 10 was answered (mission time 0.09 s).
    assert engaged.data["controller_reason"] == "hover_timeout"
    assert engaged.stamp >= ctrl.instants[10] and cleared.stamp >= ctrl.instants[18]
    (record,) = node.stats["failsafes"]
    # Instant i counts the answer to i - 1: 15, 16, 17 track -> cleared at instant 18.
    assert record["t"] == pytest.approx(9 / rate)
    assert record["cleared_t"] == pytest.approx(17 / rate)
    held = list(truth_rows(node)[:, -1])  # row j: instant j + 1
    assert held == [float(11 <= j + 1 < 18) for j in range(len(held))]
    assert node.stats["missed_deadlines"] == 0


# ------------------------------------------------------------------ the ground-truth log


def test_the_ground_truth_is_on_disk_while_flying(tmp_path):
    """A simulator killed mid-flight leaves its ground truth up to about a second before:
    the rows are written and flushed (every second of flight time) while flying."""
    node, session = make_node(*LOCKSTEP, n_steps=60, out=tmp_path)
    on_disk: dict[int, int] = {}
    ctrl = ScriptedController(session, lambda i: "track")
    answer = ctrl.answer

    def answer_and_look(payload: bytes) -> None:
        i = len(ctrl.instants)
        if i in (25, 45):  # the rows the file holds now (the flight's rows: 0 .. i - 1)
            on_disk[i] = len((tmp_path / "truth.csv").read_text().splitlines()) - 1
        answer(payload)

    session.on_put["arcade/test/imu"] = answer_and_look
    node._lockstep()
    assert node.stats["steps"] == 60
    # Flushed at the rows of t = 0, 1 and 2 s (rows 0, 20, 40), within a row of rounding.
    assert 20 <= on_disk[25] <= 22 and 40 <= on_disk[45] <= 42
    node.teardown()
    assert len(truth_rows(node)) == 60 == node.stats["truth_rows"]
    assert node.stats["unwritten_truth_rows"] == 0


def test_a_full_disk_stops_the_ground_truth_not_the_flight(tmp_path):
    """``truth.csv`` on /dev/full: every write fails with ENOSPC. The simulator says so
    once (a ``fault`` event naming the file), flies on and counts the rows it lost."""
    (tmp_path / "truth.csv").symlink_to("/dev/full")
    node, session = make_node(*LOCKSTEP, n_steps=60, out=tmp_path)
    ScriptedController(session, lambda i: "track")
    node._lockstep()
    node.teardown()
    assert node.stats["steps"] == 60 and not node.stats["crashed"]
    faults = [
        e
        for e in (decode("event", p) for p in session.published["arcade/test/event"])
        if e.kind == "fault"
    ]
    assert len(faults) == 1 and faults[0].severity == "error"
    assert "truth.csv" in faults[0].text and "ground truth not recorded" in faults[0].text
    assert faults[0].data["file"].endswith("truth.csv") and faults[0].data["errno"] == 28
    assert "No space left" in node.stats["truth_error"]
    # The first row was buffered and lost with its failed flush; the 59 after it counted.
    assert node.stats["truth_rows"] + node.stats["unwritten_truth_rows"] == 60
    assert node.stats["unwritten_truth_rows"] == 59


def test_the_simulator_service_emulates_the_links_command_delay():
    parser = options.common_parser("sim", "test")
    sim_node._extra(parser)
    for argv, steps in ((["--command-delay", "0.015"], 15), ([], 0)):
        node = sim_node.SimNode(parser.parse_args(["--vehicle", "test", *argv]))
        node.setup(Bus("test", "sim").open(session=LoopbackSession(echo=True)))
        assert node.sim.command_delay_steps == steps
        assert node.stats["command_delay_s"] == steps / 1000
    for bad in ("-0.01", "2", "nan", "soon"):
        with pytest.raises(SystemExit):
            parser.parse_args(["--command-delay", bad])


def test_a_stop_while_waiting_for_the_consumers_is_answered_at_once():
    # Nobody's token comes: the wait (10 minutes by default) ends with the stop request,
    # and the simulator does not fly (no step, no "flight finished").
    node, session = make_node("--wait-for", "controller")
    threading.Timer(0.2, node.stop.set).start()
    t0 = time.monotonic()
    node.main()
    assert time.monotonic() - t0 < 1.0
    assert node.stats["steps"] == 0
    events = [decode("event", p).text for p in session.published.get("arcade/test/event", [])]
    assert "flight finished" not in events


def test_consumers_that_never_come_time_out_naming_them():
    node, _ = make_node("--wait-for", "estimator,controller", "--ready-timeout", "0.3")
    with pytest.raises(TimeoutError, match=r"not alive after 0.3 s: \['controller', 'estimator'\]"):
        node.main()
