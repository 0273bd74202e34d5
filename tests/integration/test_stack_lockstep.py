"""The whole stack as processes over Zenoh on loopback, lockstep clock, one demo flight.

Two flights of the demo scenario (175 g swinging payload, 2.5 m/s figure-eight, release
before the second lap), seed 0, float64:

1. ground-truth state (the simulator publishes it, no estimator): the loop then sees what
   the in-process evaluation (``benchmarks.quadrotor_closedloop``) sees, and its tracking
   RMSE must be within 10 % of the in-process flight with the same seed and config (the
   in-process ``Q`` modulation taken, like the controller's, from the beam marginal the
   ``model`` message carries);
2. the full stack with the estimator in the loop: the estimate must track the ground truth.

Both: the changepoint detector declares the release within 0.25 s, nothing in the steady
take-off and hover, and at most a quarter as many changepoints as the learner's MAP path
gains (this cell, 2.5 m/s with the payload swinging, is where ``arcade eval changepoints``
finds the detector's false alarms); no rejected message, no error in any service log,
every process exits cleanly.

Changepoint events come from the adapter's detector (a joint-scored beam beside the
learner, :func:`arcade_control.detection.detection_config`), not from the learner's MAP path,
which with the tuned temperature gains a changepoint several times a second while the
payload swings (seed 0: 20 such flags in the 5.75 s before the release with the
ground-truth state, 29 with the estimator); ``arcade eval changepoints`` measures both.
"""

from __future__ import annotations

import json
import types
from pathlib import Path

import numpy as np
from foxglove_replay_checks import check_foxglove, check_replay

from arcade.demo_stack import read_truth, run_demo
from arcade_control.scenario import Scenario
from services.adapter import DEFAULT_WEIGHTS

SEED = 0


def check_clean_run(out: Path, summary: dict, detector: bool = True) -> None:
    """Every process exits cleanly, nothing is rejected or logged as an error, the records
    are complete; ``detector``: the detector's checks (module docstring)."""
    assert all(code == 0 for code in summary["exit_codes"].values()), summary["exit_codes"]
    assert summary["rejects"] == {}, summary["rejects"]
    assert summary["sim_timeouts"] == 0
    assert not summary["crashed"]
    for log in (out / "logs").glob("*.log"):
        text = log.read_text()
        assert " ERROR " not in text and "Traceback" not in text, log.name
    assert summary["t_release_s"] is not None
    cps = np.array(summary["changepoints_s"])
    # Nothing declared in the steady take-off and hover.
    assert np.sum(cps < Scenario().t_figure) == 0, cps
    if detector:
        # The payload was released: the detector declares it within 0.25 s (a hit in
        # `arcade eval changepoints`).
        t_rel = summary["t_release_s"]
        assert np.any((cps > t_rel) & (cps <= t_rel + 0.25 + 1e-9)), (t_rel, cps)
    # The recorder's flight log and MCAP exist and are complete.
    rows = (out / "flight_log.csv").read_text().splitlines()
    truth = read_truth(out / "truth.csv")
    assert len(rows) - 1 == truth["t"].size
    from mcap.reader import make_reader

    with (out / "bus.mcap").open("rb") as f:
        stats = make_reader(f).get_summary().statistics
    assert stats.channel_message_counts and stats.message_count > 5 * truth["t"].size
    # The learner's own flags (its MAP path gained a changepoint) ride on the residual
    # messages; the detector declares at most a quarter as many changepoints.
    with (out / "bus.mcap").open("rb") as f:
        flags = sum(
            json.loads(m.data)["changepoint"]
            for _, ch, m in make_reader(f).iter_messages()
            if ch.topic.endswith("/residual")
        )
    if detector:
        assert cps.size <= 0.25 * flags, (cps.size, flags)
    assert json.loads((out / "metrics.json").read_text())["rmse_m"] == summary["rmse_m"]


def in_process_rmse(
    monkeypatch, delay_s: float = 0.0, method: str = "ours", advanced: bool = False
) -> float:
    """The in-process closed loop on the information the ``model`` message carries: its
    ``Q`` modulation from the moment-matched beam marginal (``moment_matched``) instead
    of the full beam, as a deployed controller receives it. ``delay_s``: a link delay,
    compensated (``Runner.fly``'s ``compensate_delay``); ``method``: the one flown, at
    the stack's knobs; ``advanced``: the advanced step (``Runner``'s)."""
    from arcade_control import methods
    from arcade_control.guard import guard_from_metadata
    from arcade_control.scenario import Scenario
    from arcade_control.stack import moment_matched, stack_knobs
    from arcade_io.weights import load_model
    from benchmarks.quadrotor_flights import Runner

    beam_method = methods.beam_method
    monkeypatch.setattr(
        methods,
        "beam_method",
        lambda name="ours", **kw: moment_matched(beam_method(name, **kw)),
    )
    vld, _, extra = load_model(DEFAULT_WEIGHTS)
    # The same trust region as the services: the one the weights file carries.
    models = types.SimpleNamespace(
        vld=vld, guard=guard_from_metadata(extra), closedloop=stack_knobs(method)
    )
    assert models.guard is not None
    scen = Scenario(command_delay_s=delay_s)
    runner = Runner(models, advanced=advanced)
    flight = runner.fly(method, scen, seed=SEED, compensate_delay=delay_s > 0)
    assert not flight.crashed
    return flight.metrics["rmse_m"]


def test_lockstep_flight_matches_in_process_loop(tmp_path, monkeypatch):
    summary = run_demo(
        tmp_path, seed=SEED, x64=True, truth_state=True, progress=False, method="ours"
    )
    check_clean_run(tmp_path, summary)
    assert summary["adaptation"] == "ours"
    reference = in_process_rmse(monkeypatch)
    assert abs(summary["rmse_m"] - reference) <= 0.1 * reference, (summary["rmse_m"], reference)


def test_lockstep_flight_of_the_flagship_matches_in_process_loop(tmp_path, monkeypatch):
    """``--method arcade``: the adapter learns the flagship's model (features with an
    intercept), the controller runs its L1 augmentation on the model messages: the flight
    is the in-process flagship's (within 10 %), whose thrust correction the L1 adds. The
    controller runs the advanced step (``--advanced-step``): it answers the states from
    the plans it prepared, as the in-process advanced step does.

    Not asserted here: the detector's release hit. At the flagship's stack knobs its model
    refits on every step and the thrust chatters at 2.5 m/s (2.8 to 10.4 N within 0.15 s
    before the release with this seed), and the detector declares a change on that, at
    the release instant, before the release shows (the flagship's open problem: its
    thrust increments)."""
    summary = run_demo(
        tmp_path,
        seed=SEED,
        x64=True,
        truth_state=True,
        progress=False,
        method="arcade",
        extra={"controller": ["--advanced-step"]},
    )
    check_clean_run(tmp_path, summary, detector=False)
    assert summary["adaptation"] == "arcade"
    ctl = json.loads((tmp_path / "stats" / "controller.json").read_text())
    assert ctl["plan_errors"] == 0 and ctl["planned_steps"] >= 0.9 * ctl["setpoints"], ctl
    reference = in_process_rmse(monkeypatch, method="arcade", advanced=True)
    assert abs(summary["rmse_m"] - reference) <= 0.1 * reference, (summary["rmse_m"], reference)


def test_lockstep_flight_compensating_a_link_delay_matches_in_process_loop(tmp_path, monkeypatch):
    """The simulator delays every setpoint by 30 ms (``--command-delay``) and the controller
    and the adapter compensate it (``--link-delay``): the in-process loop compensating the
    same delay flies the same flight (within 10 %)."""
    summary = run_demo(
        tmp_path,
        seed=SEED,
        x64=True,
        truth_state=True,
        progress=False,
        extra={"sim": ["--command-delay=0.03"]},
        link_delay_s=0.03,
        method="ours",
    )
    assert all(code == 0 for code in summary["exit_codes"].values()), summary["exit_codes"]
    assert summary["rejects"] == {} and not summary["crashed"]
    sim = json.loads((tmp_path / "stats" / "sim.json").read_text())
    assert sim["command_delay_s"] == 0.03
    reference = in_process_rmse(monkeypatch, delay_s=0.03)
    assert abs(summary["rmse_m"] - reference) <= 0.1 * reference, (summary["rmse_m"], reference)


def test_lockstep_flight_with_estimator(tmp_path):
    """Also: the live Foxglove service flies along (``--foxglove``), the recording's
    Foxglove channels decode to the states and the payload, the estimator fuses the
    vehicle's mocap frames only, and ``arcade replay`` reproduces the recorded adapter and
    controller (``tests/foxglove_replay_checks.py``)."""
    summary = run_demo(
        tmp_path, seed=SEED, x64=True, progress=False, method="ours", foxglove_port=0
    )
    check_clean_run(tmp_path, summary)
    bodies = check_foxglove(tmp_path)
    check_replay(tmp_path, "ours_beta=0.2")
    truth = read_truth(tmp_path / "truth.csv")
    est = np.genfromtxt(
        tmp_path / "flight_log.csv", delimiter=",", names=True, dtype=None, encoding=None
    )
    np.testing.assert_allclose(est["t"], truth["t"], atol=1e-9)
    err_p = np.stack([est[c] - truth[c] for c in ("px", "py", "pz")], axis=1)
    err_v = np.stack([est[c] - truth[c] for c in ("vx", "vy", "vz")], axis=1)
    # Mocap noise 0.3 mm, 7 ms latency compensated; velocity from 120 Hz positions.
    assert np.sqrt(np.mean(err_p**2)) < 2e-3
    assert np.sqrt(np.mean(err_v**2)) < 0.06
    stats = json.loads((tmp_path / "stats" / "estimator.json").read_text())
    assert stats["states"] == truth["t"].size
    # The payload's frames on the mocap stream are not the vehicle's: not fused, no fault.
    assert stats["frames"] == bodies["vehicle"] and stats["other_bodies"] == {
        "payload": bodies["payload"]
    }
