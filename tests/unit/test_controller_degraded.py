"""Controller degraded modes, in-process on a stand-in bus (no weights file: the hover
paths need no MPC solve): a failing control step, and the time bound of hover."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pytest

from services import controller as mod
from services import options
from services.messages import Event, Setpoint, State

X_HOVER = np.r_[0, 0, 1.0, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0]


class FakeBus:
    """What the controller uses of :class:`services.bus.Bus`: everything put is kept."""

    def __init__(self) -> None:
        self.alive: set[str] = set()
        self.sent: list[Any] = []
        self.fail = False

    def subscribe(self, topic: str, callback: Any, **_: Any) -> Any:
        return type("Subscription", (), {"transit_s": []})()

    def publisher(self, topic: str) -> FakeBus:
        return self

    def put(self, record: Any) -> None:
        if self.fail and isinstance(record, Setpoint):
            raise RuntimeError("session closed")
        self.sent.append(record)

    def events(self, kind: str) -> list[Event]:
        return [e for e in self.sent if isinstance(e, Event) and e.kind == kind]

    def setpoints(self) -> list[Setpoint]:
        return [m for m in self.sent if isinstance(m, Setpoint)]


@pytest.fixture(scope="module")
def parser():
    p = options.common_parser("controller", "test")
    mod._extra(p)
    return p


def make_controller(parser, *argv: str) -> mod.Controller:
    svc = mod.Controller(
        parser.parse_args(["--weights", "/nonexistent/vld.eqx", "--lockstep", *argv])
    )
    svc.bus = FakeBus()
    svc.setup(svc.bus)
    return svc


def state(stamp: float, seq: int, meas_stamp: float | None = None) -> State:
    return State(x=X_HOVER, stamp=stamp, meas_stamp=meas_stamp, seq=seq, src="estimator/1")


# ------------------------------------------------------------------ failing control step


def run_main(svc: mod.Controller, states: list[State], handle) -> None:
    """The controller's loop over ``states`` (queued as received), stopped after the last."""
    last = states[-1].seq

    def step(s: State) -> None:
        if s.seq == last:
            svc.stop.set()
        handle(s)

    svc.handle = step
    for s in states:
        svc.on_state(s)
    svc.main()


def test_a_failing_step_hovers_through_the_mode_change_with_rate_limited_logs(parser, caplog):
    svc = make_controller(parser)

    def fail(s: State) -> None:
        raise ValueError("broken step")

    with caplog.at_level(logging.INFO, logger="arcade.controller"):
        run_main(svc, [state(1.0 + 0.05 * k, k + 1) for k in range(30)], fail)
    sps = svc.bus.setpoints()
    assert len(sps) == 30 and {sp.mode for sp in sps} == {"hover"}
    (degraded,) = svc.bus.events("degraded")
    assert "control step failed" in degraded.text and degraded.data["mode"] == "hover"
    tracebacks = [r for r in caplog.records if r.exc_info is not None]
    assert len(tracebacks) == 1  # the first in full; the rest only counted
    assert svc.stats["step_errors"] == 30 and svc._mode == "hover"


def test_a_failing_fallback_publish_does_not_end_the_loop(parser):
    svc = make_controller(parser)
    svc.bus.fail = True

    def fail(s: State) -> None:
        svc.bus.fail = s.seq == 1  # the fallback of the first step cannot be published
        raise ZeroDivisionError

    run_main(svc, [state(1.0, 1), state(1.05, 2)], fail)  # must not raise
    assert len(svc.bus.setpoints()) == 1
    assert svc.stats["step_errors"] == 2 and svc.stats["fallback_errors"] == 1


# ------------------------------------------------------------------ hover bound


def stale_mocap(svc: mod.Controller, t0: float, seconds: float, seq0: int = 0) -> int:
    """States every 0.05 s for ``seconds`` whose newest mocap frame is 0.5 s old."""
    n = round(seconds / 0.05)
    for k in range(n):
        t = t0 + 0.05 * k
        svc.handle(state(t, seq0 + k + 1, meas_stamp=t - 0.5))
    return seq0 + n


def test_a_short_hover_is_only_degraded(parser):
    svc = make_controller(parser)
    stale_mocap(svc, 10.0, 0.95)  # last state 0.9 s into the hover
    assert {sp.mode for sp in svc.bus.setpoints()} == {"hover"}
    assert len(svc.bus.events("degraded")) == 1
    assert svc.bus.events("failsafe") == [] and svc.stats["hover_failsafes"] == 0


def test_a_long_hover_is_a_failsafe_once_per_episode(parser):
    svc = make_controller(parser, "--max-hover-s", "1.0")
    seq = stale_mocap(svc, 10.0, 2.0)
    assert len(svc.bus.setpoints()) == 40
    assert {sp.mode for sp in svc.bus.setpoints()} == {"hover"}  # still published
    (fs,) = svc.bus.events("failsafe")
    assert fs.stamp == pytest.approx(11.0) and fs.data["reason"] == "hover_timeout"
    assert fs.severity == "error" and svc.stats["hover_failsafes"] == 1
    # The reason rides on the setpoint of the failsafe's instant, and on that one only.
    flagged = [(sp.stamp, sp.failsafe) for sp in svc.bus.setpoints() if sp.failsafe]
    assert flagged == [(pytest.approx(11.0), "hover_timeout")]
    # Tracking again ends the episode; the next hover has its own bound.
    svc._set_mode("track", "fresh state", 12.0)
    stale_mocap(svc, 12.05, 0.9, seq)
    assert len(svc.bus.events("failsafe")) == 1
    stale_mocap(svc, 13.0, 0.3, seq + 100)
    assert len(svc.bus.events("failsafe")) == 2


def test_one_state_stamped_in_the_future_does_not_stamp_every_later_setpoint(parser):
    svc = make_controller(parser)
    svc.publish(state(10.0, 1), svc.u_hover, "hover", 0.0)
    svc.publish(state(10.02, 2), svc.u_hover, "hover", 0.0)  # late by less than a period
    svc.publish(state(9.99, 3), svc.u_hover, "hover", 0.0)
    svc.publish(state(1e6, 4), svc.u_hover, "hover", 0.0)  # a faulty stamp
    svc.publish(state(10.05, 5), svc.u_hover, "hover", 0.0)
    svc.publish(state(10.10, 6), svc.u_hover, "hover", 0.0)
    stamps = [sp.stamp for sp in svc.bus.setpoints()]
    assert stamps == [10.0, 10.02, 10.02, 1e6, 10.05, 10.10]
    assert svc.stats["stamp_reanchored"] == 1


def test_a_link_delay_plans_from_the_predicted_state_against_the_later_reference(
    parser, monkeypatch
):
    """``--link-delay``: the controller's step is the in-process compensated step
    (``make_controller_step``'s ``delay_s``, tested in test_quadrotor_closedloop_links) and its
    reference the plan that much later."""
    from arcade_control.scenario import reference
    from services import controller_steps

    built = []
    real = controller_steps.make_controller_step

    def make_step(method, cfg, hold_residual=False, delay_s=0.0):
        built.append(delay_s)
        return real(method, cfg, hold_residual, delay_s)

    monkeypatch.setattr(controller_steps, "make_controller_step", make_step)
    plain = make_controller(parser)
    delayed = make_controller(parser, "--link-delay", "0.02")
    assert built == [0.0, 0.02]
    scen = options.scenario(delayed.args)
    want = reference(scen, delayed.n_ref, delayed.cfg.N, 0.02)
    for got, expected, before in zip(
        (delayed.x_ref_all, delayed.u_ref_all), want, (plain.x_ref_all, plain.u_ref_all)
    ):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(expected))
        assert np.max(np.abs(np.asarray(got) - np.asarray(before))) > 1e-3
