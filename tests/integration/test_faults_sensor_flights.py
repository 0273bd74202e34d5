"""Sensor faults through the whole stack, lockstep: mocap faults injected by the simulator
(dropouts, frozen frames, outliers, a clock jump). The vehicle never crashes, the
controller hovers once a dropout outlasts its bound and tracks again after it; a 3 s
dropout makes the simulator hold position until the controller tracks again. The
in-process checks of the estimator are in ``tests/unit/test_faults_sensor.py``.
"""

from __future__ import annotations

import json

import numpy as np
import pytest


def test_lockstep_flight_through_mocap_faults(tmp_path):
    from arcade.demo_stack import free_hub, read_truth
    from deploy.launcher import StackConfig, run_flight

    faults = [
        "dropout@3.0+0.15",  # predicted through: keeps tracking
        "dropout@4.5+0.9",  # beyond the controller's 0.2 s: hover, then track
        "freeze@6.5+0.15",
        "outliers@7.5+1.0,p=0.2,m=0.5",
        "clockjump@9.0+0.5,offset=3.0",
    ]
    cfg = StackConfig(
        out=tmp_path,
        hub=free_hub(),
        method="ours",
        lockstep=True,
        rate=20.0,
        duration=11.0,
        hover_s=1000.0,
        x64=True,
        extra={"sim": [a for f in faults for a in ("--mocap-fault", f)]},
    )
    result = run_flight(cfg)
    assert all(c == 0 for c in result["codes"].values()), result["codes"]
    sim = json.loads((tmp_path / "stats" / "sim.json").read_text())
    assert not sim["crashed"] and sim["timeouts"] == 0
    assert all(sim["mocap_faults"][k] > 0 for k in ("dropout", "freeze", "outliers", "clockjump"))
    est = json.loads((tmp_path / "stats" / "estimator.json").read_text())
    assert est["rejects"] == {} and est["frozen_frames"] > 0 and est["restamped_frames"] > 0
    assert est["outliers_rejected"] > 0
    # The controller hovered only in the long dropout (after its 0.5 s bound) and tracked
    # again afterwards.
    log = np.genfromtxt(
        tmp_path / "flight_log.csv", delimiter=",", names=True, dtype=None, encoding=None
    )
    hover_t = log["t"][log["mode"] == "hover"]
    assert hover_t.size > 0
    assert hover_t.min() >= 4.5 + 0.2 and hover_t.max() <= 4.5 + 0.9 + 0.1
    assert log["mode"][-1] == "track"
    # The estimate stays close to the truth outside the long dropout.
    truth = read_truth(tmp_path / "truth.csv")
    err = np.linalg.norm(np.stack([log[c] - truth[c] for c in ("px", "py", "pz")], 1), axis=1)
    calm = (truth["t"] < 4.5) | (truth["t"] > 4.5 + 0.9 + 0.5)
    assert err[calm].max() < 0.02, err[calm].max()
    kinds = {(e["kind"], e["data"].get("fault")) for e in result["events"]}
    assert {
        ("fault", "mocap_frozen"),
        ("fault", "mocap_outliers"),
        ("fault", "mocap_clock_jump"),
        ("degraded", None),
    } <= kinds


def test_lockstep_long_dropout_holds_position_then_tracks_again(tmp_path):
    # 3 s without mocap: the controller hovers level, reports its failsafe after 1 s, the
    # simulator holds position (as PX4 would) and hands control back once the controller
    # tracks again; the adapter does not learn from the held steps.
    from arcade.demo_stack import free_hub, read_truth
    from deploy.launcher import StackConfig, run_flight

    cfg = StackConfig(
        out=tmp_path,
        hub=free_hub(),
        method="ours",
        lockstep=True,
        rate=20.0,
        duration=9.0,
        hover_s=1000.0,
        release=-1.0,
        extra={"sim": ["--mocap-fault", "dropout@2.0+3.0"]},
    )
    result = run_flight(cfg)
    assert all(c == 0 for c in result["codes"].values()), result["codes"]
    sim = json.loads((tmp_path / "stats" / "sim.json").read_text())
    assert not sim["crashed"] and sim["controller_failsafes"] == 1
    events = result["events"]

    def first(pred) -> dict:
        found = [e for e in events if pred(e)]
        assert found, "missing event"
        return found[0]

    ctl = first(lambda e: e["kind"] == "failsafe" and e["src"].startswith("controller/"))
    assert ctl["data"]["reason"] == "hover_timeout"
    held = first(lambda e: e["kind"] == "failsafe" and e["src"].startswith("sim/"))
    cleared = first(lambda e: e["kind"] == "failsafe_cleared" and e["src"].startswith("sim/"))
    # Hover from 0.2 s into the dropout, the failsafe 1 s later (lockstep: mission time);
    # control back after the dropout.
    assert held["stamp"] == pytest.approx(3.25) and 5.0 < cleared["stamp"] < 5.5
    learning = [
        e["data"]["learning"]
        for e in events
        if e["src"].startswith("adapter/") and "learning" in e["data"]
    ]
    assert learning[-2:] == [False, True], learning
    adapter = json.loads((tmp_path / "stats" / "adapter.json").read_text())
    assert adapter["not_applied"] > 0
    # The level hover holds the height (its thrust is what tracking needed: the payload's
    # weight included) and drifts sideways with the velocity it started with; the hold
    # stops the drift; the vehicle is back on the reference at the end (within the
    # stack's hover accuracy with the default 175 g payload, a few cm low).
    truth = read_truth(tmp_path / "truth.csv")
    err = np.stack([truth[c] - truth[f"ref_{c}"] for c in ("px", "py", "pz")], 1)
    assert np.abs(err[:, 2]).max() < 0.1, np.abs(err[:, 2]).max()
    assert np.linalg.norm(err[:, :2], axis=1).max() < 0.3
    end = truth["t"] > truth["t"][-1] - 1.0
    assert np.linalg.norm(err[end], axis=1).max() < 0.05
