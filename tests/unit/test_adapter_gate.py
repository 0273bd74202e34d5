"""Adapter, in-process on a stand-in bus: whether a step is learned from (the vehicle flies
the stack's setpoints), which setpoint is a transition's input in realtime, and the
non-finite reset. The learning update itself is replaced by a recording stub (the update
is tested in test_adaptation and through the stack)."""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections import namedtuple
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from arcade_core import adaptation
from services import adapter as mod
from services import options, runtime
from services.messages import Command, Event, Setpoint, State

X_HOVER = np.r_[0, 0, 1.0, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0]
Pred = namedtuple("Pred", "mean var")
Prediction = namedtuple("Prediction", "mean param between noise encoder")


class FakeBus:
    """What the adapter uses of :class:`services.bus.Bus`: everything put is kept."""

    def __init__(self) -> None:
        self.alive: set[str] = set()  # no controller token: no waiting for its setpoints
        self.sent: list[Any] = []

    def subscribe(self, topic: str, callback: Any, **_: Any) -> None:
        pass

    def publisher(self, topic: str) -> FakeBus:
        return self

    def put(self, record: Any) -> None:
        self.sent.append(record)

    def events(self, kind: str | None = None) -> list[Event]:
        return [e for e in self.sent if isinstance(e, Event) and kind in (None, e.kind)]


def make_adapter(*argv: str) -> mod.Adapter:
    """An adapter set up as its process sets it up (no weights file: nothing compiled),
    then given a recording stand-in for the learning update."""
    parser = options.common_parser("adapter", "test")
    mod._extra(parser)
    svc = mod.Adapter(parser.parse_args(["--weights", "/nonexistent/vld.eqx", *argv]))
    svc.bus = FakeBus()
    svc.setup(svc.bus)
    svc.calls = []
    svc.learner = svc._prior = SimpleNamespace(beam=SimpleNamespace(step=0))
    svc.theta = np.zeros((13, 1))

    def adapt(learner, xp, up, x, h, learn, var_p, var_x):
        svc.calls.append(SimpleNamespace(up=np.asarray(up), learn=bool(learn), h=h))
        nan = np.full(13, math.nan)  # no residual published: not needed here
        cov = np.zeros((13, 1, 1))
        return learner, nan, Pred(nan, nan), 0.0, False, svc.theta, cov, nan * 0, -1

    def detect(state, config, learner, *rest):  # declares nothing
        return state, adaptation.Detection(np.asarray(0.0), np.asarray(False), np.asarray(-1))

    svc._adapt, svc._detect = adapt, detect
    svc._detection = svc._detection0 = svc._detect_config = None
    svc._marginal = lambda learner, x, u: (np.zeros((13, 1)), np.zeros((13, 1, 1)), np.zeros(13))
    return svc


def state(stamp: float, seq: int) -> State:
    return State(x=X_HOVER, stamp=stamp, seq=seq, src="estimator/1")


def setpoint(stamp: float, thrust: float, seq: int = 1) -> Setpoint:
    return Setpoint(
        u=[thrust, 0.0, 0.0, 0.0], state_seq=seq, stamp=stamp, seq=seq, src="controller/1"
    )


def event(kind: str, src: str) -> Event:
    return Event(kind=kind, text=kind, stamp=1.0, src=src)


def start(t0: float) -> Command:
    return Command(name="start", args={"t0": t0}, stamp=t0, src="px4sim/1")


# ------------------------------------------------------------------ learning gate


def test_learning_follows_the_vehicle_link_not_the_controller_nor_a_resent_clock():
    svc = make_adapter()
    assert not svc._applied  # realtime: nothing applied before the mission starts
    svc.on_command(start(5.0))
    assert svc._applied
    svc.on_event(event("failsafe", "controller/1"))  # a request to the link: not yet held
    assert svc._applied
    svc.on_event(event("failsafe", "bridge/1"))
    assert not svc._applied
    # A restarted controller gets the mission clock again: the vehicle is still held.
    svc.on_command(start(5.0))
    assert not svc._applied
    svc.on_event(event("failsafe_cleared", "bridge/1"))
    assert svc._applied
    svc.on_event(event("failsafe", "px4sim/1"))
    svc.on_command(start(9.0))  # a new mission
    assert svc._applied
    # Each change of the gate is announced.
    assert [e.data["learning"] for e in svc.bus.events("info")] == [True, False, True, False, True]


def test_a_restarted_adapter_learns_from_the_clock_it_is_sent_again():
    """An adapter restarted mid-flight saw neither the mission's start nor the link's
    events: the link's re-sent clock says whether the setpoints are flown now."""
    flying = make_adapter()
    flying.on_command(Command(name="start", args={"t0": 5.0, "flying": True}, stamp=7.0))
    assert flying._applied
    assert [e.data["learning"] for e in flying.bus.events("info")] == [True]
    held = make_adapter()
    held.on_command(Command(name="start", args={"t0": 5.0, "flying": False}, stamp=7.0))
    assert not held._applied
    # Announced although the gate did not change: the adapter says why it does not learn.
    (paused,) = held.bus.events("info")
    assert paused.data["learning"] is False and "under a failsafe" in paused.text
    held.on_command(Command(name="start", args={"t0": 5.0, "flying": True}, stamp=7.5))
    assert not held._applied  # the same clock again (a controller rejoining): no change
    held.on_event(event("failsafe_cleared", "sim/1"))
    assert held._applied


def test_steps_not_applied_are_counted_and_not_learned():
    svc = make_adapter()
    for k, t in enumerate((10.0, 10.05, 10.1)):
        svc.on_setpoint(setpoint(t, 5.0, seq=k + 1))
        svc.on_state(state(t, k + 1))
    assert [c.learn for c in svc.calls] == [False, False]
    assert svc.stats["not_applied"] == 2 and svc.stats["learned"] == 0
    svc.on_command(start(10.1))
    svc.on_setpoint(setpoint(10.15, 5.0, seq=4))
    svc.on_state(state(10.15, 4))
    assert svc.calls[-1].learn and svc.stats["not_applied"] == 2


# ------------------------------------------------------------------ input of a transition


def test_missing_setpoint_falls_back_to_the_one_the_vehicle_held():
    svc = make_adapter()
    svc.on_command(start(9.0))
    svc.on_setpoint(setpoint(10.0, 5.0, seq=1))
    svc.on_state(state(10.0, 1))
    svc.on_state(state(10.05, 2))  # the controller skipped this state
    svc.on_setpoint(setpoint(10.1, 9.0, seq=2))
    svc.on_state(state(10.1, 3))
    # 10.05 -> 10.1 was flown with the setpoint of 10.0 (zero-order hold), not 10.1's.
    assert svc.calls[-1].up[0] == pytest.approx(5.0)
    assert svc.stats["input_fallback"] == 1 and svc.stats["input_missing"] == 0


def test_transition_without_a_recent_setpoint_is_skipped():
    svc = make_adapter()
    svc.on_command(start(9.0))
    svc.on_setpoint(setpoint(9.9, 5.0, seq=1))
    svc.on_state(state(10.0, 1))
    svc.on_state(state(10.05, 2))
    svc.on_setpoint(setpoint(10.1, 9.0, seq=2))
    svc.on_state(state(10.1, 3))
    assert svc.calls == []  # 9.9 is three periods before 10.05: nothing known to be held
    assert svc.stats["input_missing"] == 2 and svc.stats["skipped"] == 2
    assert svc.stats["input_fallback"] == 0 and svc.stats["before_first_setpoint"] == 0
    assert len([m for m in svc.bus.sent if type(m).__name__ == "Model"]) == 3


def test_states_before_the_controller_answers_are_not_counted_as_lost_inputs():
    svc = make_adapter()
    svc.on_state(state(10.0, 1))
    svc.on_state(state(10.05, 2))  # warming up: no setpoint yet
    svc.on_setpoint(setpoint(10.1, 5.0, seq=1))
    svc.on_state(state(10.1, 3))
    svc.on_state(state(10.15, 4))
    svc.on_state(state(10.2, 5))
    svc.on_state(state(10.25, 6))  # 10.1 answered; then held (fallback), then lost
    assert svc.stats["before_first_setpoint"] == 2
    assert svc.stats["input_fallback"] == 1 and svc.stats["input_missing"] == 1


def test_realtime_adapter_behind_the_vehicle_learns_the_newest_transition_only():
    """States that queued while an update ran (a loaded host) are dropped, counted as
    ``behind``; the newest transition is learned, with its own input."""
    svc = make_adapter()
    svc.on_command(start(9.0))
    for k in range(5):
        svc.on_setpoint(setpoint(10.0 + 0.05 * k, 5.0 + k, seq=k + 1))
        svc.receive_state(state(10.0 + 0.05 * k, k + 1))  # queued: the loop is not running
    assert svc.calls == []
    assert svc.handle_newest()  # one turn of the realtime loop
    assert svc.stats["behind"] == 4
    (call,) = svc.calls  # 10.15 -> 10.2, flown with the setpoint answering 10.15
    assert call.up[0] == pytest.approx(8.0) and call.learn and call.h == pytest.approx(0.05)
    assert not svc.handle_newest()  # nothing left: the queue was drained


def test_lockstep_adapter_handles_every_state_in_its_callback():
    svc = make_adapter("--lockstep", "--step-timeout", "0")
    for k in range(3):
        svc.on_setpoint(setpoint(10.0 + 0.05 * k, 5.0, seq=k + 1))
        svc.receive_state(state(10.0 + 0.05 * k, k + 1))
    assert svc.stats["behind"] == 0 and len(svc.calls) == 2  # 10.0 -> 10.05 -> 10.1


def test_lockstep_waits_for_the_exact_setpoint_only():
    svc = make_adapter("--lockstep", "--step-timeout", "0")
    svc.on_setpoint(setpoint(1.0, 5.0))
    assert svc._input_for(state(1.05, 1)) is None
    assert svc.stats["input_fallback"] == 0


def test_lockstep_waits_for_a_controller_whose_token_has_not_arrived_yet():
    """The first states of a lockstep flight can reach the adapter before the controller's
    liveliness token does: the setpoint answering the state is waited for (it is on its
    way: the simulator stepped on it), not given up as if the controller were gone."""
    svc = make_adapter("--lockstep", "--step-timeout", "30")
    assert "controller" not in svc.bus.alive
    late = threading.Timer(0.2, lambda: svc.on_setpoint(setpoint(1.0, 5.0)))
    late.start()
    try:
        t0 = time.monotonic()
        sp = svc._input_for(state(1.0, 1))
    finally:
        late.cancel()
    assert sp is not None and sp.stamp == 1.0
    assert time.monotonic() - t0 < 10.0


def test_lockstep_gives_up_at_once_on_a_controller_that_is_gone():
    svc = make_adapter("--lockstep", "--step-timeout", "30")
    svc.bus.alive.add("controller")
    svc.on_setpoint(setpoint(1.0, 5.0))
    assert svc._input_for(state(1.0, 1)) is not None  # seen alive
    svc.bus.alive.discard("controller")  # its token withdrawn: the process ended
    t0 = time.monotonic()
    assert svc._input_for(state(1.05, 2)) is None
    assert time.monotonic() - t0 < 1.0


def test_with_a_link_delay_it_learns_between_the_states_predicted_over_it():
    """``--link-delay``: the setpoint answering state ``k-1`` is in flight at state ``k``;
    each state is learned as its prediction over the delay with that setpoint, variance
    included, and the first transition (no setpoint in flight known) is skipped."""
    from arcade_core.dynamics import predict_over_delay
    from arcade_io.vehicle import load_vehicle, quadrotor_params

    svc = make_adapter("--lockstep", "--link-delay", "0.02")
    seen = []
    stub = svc._adapt

    def adapt(learner, xp, up, x, h, learn, var_p, var_x):
        seen.append([np.asarray(a, float) for a in (xp, up, x, var_p, var_x)])
        return stub(learner, xp, up, x, h, learn, var_p, var_x)

    svc._adapt = adapt
    params = quadrotor_params(load_vehicle())
    var = np.full(13, 1e-6)
    xs = [X_HOVER + k * np.r_[0.05, 0, 0, 1.0, 0, 0, np.zeros(7)] for k in range(4)]
    thrusts = [5.0, 6.0, 7.0, 8.0]
    for k, (x, thrust) in enumerate(zip(xs, thrusts, strict=True)):
        svc.on_state(State(x=x, cov_diag=var, stamp=1.0 + 0.05 * k, seq=k + 1, src="estimator/1"))
        svc.on_setpoint(setpoint(1.0 + 0.05 * k, thrust, seq=k + 1))
    assert svc.stats["skipped"] == 1 and len(seen) == 2
    for k, (xp, up, x, var_p, var_x) in enumerate(seen, start=1):
        u = [np.r_[t, 0.0, 0.0, 0.0] for t in thrusts]
        want_p = predict_over_delay(xs[k], var, u[k - 1], params, 0.02)
        want = predict_over_delay(xs[k + 1], var, u[k], params, 0.02)
        np.testing.assert_allclose(up, u[k])
        for got, expected in ((xp, want_p[0]), (var_p, want_p[1]), (x, want[0]), (var_x, want[1])):
            np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-15)
    # The prediction moved the states: the delay is not ignored.
    assert seen[0][0][0] > xs[1][0] + 0.015


def test_the_detector_knobs_follow_where_the_state_comes_from():
    # The estimator's state (the default) is an estimate; the simulator's (--truth-state
    # stacks) is the ground truth: the flagship's learner and the detector take their
    # knobs accordingly (arcade_control.knobs.DETECTION_DEFAULTS, DETECTION_TRUE_STATE).
    assert make_adapter().estimated
    assert make_adapter("--state-source", "px4bridge").estimated
    assert not make_adapter("--state-source", "sim").estimated


def test_link_delay_must_be_shorter_than_the_control_period(capsys):
    with pytest.raises(SystemExit) as exit_:
        runtime.main_for(mod.Adapter, ["--rate", "50", "--link-delay", "0.02"], mod._extra)
    assert exit_.value.code == 2
    assert "--link-delay 0.02 s: must be shorter than the control period" in capsys.readouterr().err
    parser = options.common_parser("adapter", "test")
    mod._extra(parser)
    with pytest.raises(SystemExit):
        parser.parse_args(["--link-delay", "-0.01"])


# ------------------------------------------------------------------ changepoint events


def fly_lockstep(svc: mod.Adapter, n: int) -> list[Event]:
    """``n`` lockstep instants 0.05 s apart from 1.0 s, each answered by a setpoint; the
    changepoint events the adapter raised."""
    svc.on_command(start(1.0))
    for k in range(n):
        svc.on_setpoint(setpoint(1.0 + 0.05 * k, 5.0, seq=k + 1))
        svc.on_state(state(1.0 + 0.05 * k, k + 1))
    return svc.bus.events("changepoint")


def test_a_declared_changepoint_is_reported_with_its_date():
    """Events follow the detector's declarations, not the learner's flag: a declaration
    dated to a step is reported with that step's stamp and probability; the learner's
    flag stays in the residual messages and raises no event by itself."""
    svc = make_adapter("--lockstep", "--step-timeout", "0")
    # Per learning step: the learner's flag, and the detector's (declared, dated step).
    flags = iter([False, True, True, False, True, False])
    script = iter([(False, -1), (False, -1), (True, 2), (False, -1), (True, 5), (False, -1)])
    steps = iter(range(1, 7))

    def adapt(learner, xp, up, x, h, learn, var_p, var_x):
        cp = next(flags)
        learner = SimpleNamespace(beam=SimpleNamespace(step=next(steps)))
        z = np.zeros(13)
        pred = Prediction(z, z, z, z, z)
        return learner, z, pred, 0.9 * cp, cp, svc.theta, np.zeros((13, 1, 1)), z, -1

    def detect(state, config, learner, xp, up, x, h, learn, var_p, var_x):
        declared, dated = next(script)
        return state, adaptation.Detection(
            np.asarray(0.8 if declared else 0.1), np.asarray(declared), np.asarray(dated)
        )

    svc._adapt, svc._detect = adapt, detect
    reported = fly_lockstep(svc, 7)
    assert [e.data["changepoint_step"] for e in reported] == [2, 5]
    # Step j is the transition into state j + 1 (stamp 1.0 + 0.05 j).
    assert [e.data["changepoint_stamp"] for e in reported] == pytest.approx([1.1, 1.25])
    assert [e.data["step"] for e in reported] == [3, 5]
    assert [e.data["cp_prob"] for e in reported] == pytest.approx([0.8, 0.8])
    texts = [e.text for e in reported]
    assert texts == ["changepoint detected, dated 0.05 s back", "changepoint detected"]
    assert svc.stats["changepoints"] == 2
    residual_flags = [r.changepoint for r in svc.bus.sent if type(r).__name__ == "Residual"]
    assert residual_flags == [False, True, True, False, True, False]


def test_a_learner_with_its_own_detector_declares_the_events():
    """The flagship's learner runs the detector in its step (and restarts on it): its
    declarations, probability and dated step are the events, and no second detector
    runs."""
    svc = make_adapter("--lockstep", "--step-timeout", "0")
    flags = iter([False, True, False, True])
    dated = iter([-1, 1, -1, 4])
    steps = iter(range(1, 5))

    def adapt(learner, xp, up, x, h, learn, var_p, var_x):
        cp = next(flags)
        restart = SimpleNamespace(dated=np.asarray(next(dated)))
        learner = SimpleNamespace(
            beam=SimpleNamespace(step=next(steps)), cp_prob=np.asarray(0.7), restart=restart
        )
        z = np.zeros(13)
        return learner, z, Prediction(z, z, z, z, z), 0.7, cp, svc.theta, z[:, None, None], z, -1

    svc._adapt, svc._detect = adapt, None
    reported = fly_lockstep(svc, 5)
    assert [e.data["changepoint_step"] for e in reported] == [1, 4]
    assert [e.data["step"] for e in reported] == [2, 4]
    assert [e.data["cp_prob"] for e in reported] == pytest.approx([0.7, 0.7])
    assert svc.stats["changepoints"] == 2


# ------------------------------------------------------------------ non-finite reset


def test_non_finite_posterior_resets_with_a_fault_event():
    svc = make_adapter()
    prior = svc._prior
    svc.learner = SimpleNamespace(beam=SimpleNamespace(step=7))
    svc.theta = np.full((13, 1), math.nan)
    svc.on_setpoint(setpoint(1.0, 5.0))
    svc.on_state(state(1.0, 1))
    svc.on_state(state(1.05, 2))
    assert svc.learner is prior
    assert svc.stats["nonfinite_resets"] == 1
    (fault,) = svc.bus.events("fault")
    assert fault.severity == "error" and fault.data["state_seq"] == 2


# ------------------------------------------------------------------ with the PX4 bridge


def test_bridge_exits_and_engagements_drive_the_gate():
    """An operator's hold pauses learning like a failsafe; engaging offboard again resumes
    it, also when the bridge does not start the mission (--no-start-mission)."""
    from test_px4_units import engaged_bridge

    # The adapter first: its set-up takes longer than the bridge's setpoint timeout, which
    # would end the offboard session before the test drives it.
    svc = make_adapter()
    bridge = engaged_bridge("--no-start-mission")
    svc.on_command(start(5.0))

    def forward() -> None:
        for e in bridge.bus.events():
            svc.on_event(dataclasses.replace(e, src="bridge/1"))
        bridge.bus.sent.clear()

    bridge._do_command(Command(name="hold", stamp=6.0, src="operator/1"))
    forward()
    assert not svc._applied
    assert bridge.stats["failsafes"] == 0 and bridge.stats["offboard_exits"] == 1
    bridge.engage()
    assert bridge._engaged
    forward()
    assert svc._applied
    assert not [c for c in bridge.bus.sent if isinstance(c, Command)]  # no start: not ours


# ------------------------------------------------------------------ checkpoint


def test_a_checkpoint_that_cannot_be_written_is_said_once_and_adaptation_goes_on(tmp_path):
    from typing import NamedTuple

    class Beam(NamedTuple):
        step: np.ndarray

    (tmp_path / "file").write_text("")  # a file where the checkpoint's folder should be
    svc = make_adapter(
        "--checkpoint", str(tmp_path / "file" / "ckpt.npz"), "--checkpoint-every", "1"
    )
    svc.learner = SimpleNamespace(beam=Beam(np.int32(3)))
    svc.meta = {}
    nan, zeros = np.full(13, math.nan), np.zeros(13)

    def adapt(learner, xp, up, x, h, learn, var_p, var_x):  # a finite posterior, recorded
        svc.calls.append(SimpleNamespace(learn=bool(learn)))
        cov = np.zeros((13, 1, 1))
        return learner, nan, Pred(nan, nan), 0.0, False, svc.theta, cov, zeros, -1

    svc._adapt = adapt
    svc.on_command(start(9.0))
    for k, t in enumerate((10.0, 10.05, 10.1, 10.15)):
        svc.on_setpoint(setpoint(t, 5.0, seq=k + 1))
        svc.on_state(state(t, k + 1))
    assert len(svc.calls) == 3 and svc.stats["steps"] == 4  # every state answered
    assert svc.stats["checkpoint_errors"] == 4
    (fault,) = [e for e in svc.bus.events("fault") if "checkpoint" in e.text]
    assert fault.severity == "error" and fault.data["errno"] > 0
    svc.teardown()  # never raises; no checkpoint step claimed
    assert svc.stats["checkpoint_errors"] == 5 and "checkpoint_step" not in svc.stats
