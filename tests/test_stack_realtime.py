"""The whole stack on the wall clock: a short realtime flight at 30 Hz."""

from __future__ import annotations

import json

import pytest

from arcade.demo_stack import free_hub
from deploy.launcher import StackConfig, run_flight

pytestmark = pytest.mark.integration


def test_realtime_flight_at_30hz_meets_deadlines(tmp_path):
    cfg = StackConfig(out=tmp_path, lockstep=False, hub=free_hub(), rate=30.0, duration=6.0)
    result = run_flight(cfg)
    assert all(code == 0 for code in result["codes"].values()), result["codes"]
    sim = json.loads((tmp_path / "stats" / "sim.json").read_text())
    assert sim["mode"] == "realtime" and not sim["crashed"]
    ticks = sim["steps"]
    assert ticks == 181  # 6 s at 30 Hz, both ends included
    # Fewer than 1 % of the control instants without their setpoint before the next one.
    assert sim["missed_deadlines"] < 0.01 * ticks, sim["missed_deadlines"]
    assert sim["sense_to_actuate"]["n"] >= 0.99 * ticks
    assert sim["wall_s"] - sim["preroll_s"] == pytest.approx(6.0, abs=0.5)  # wall clock
    for name in ("estimator", "adapter", "controller", "recorder"):
        stats = json.loads((tmp_path / "stats" / f"{name}.json").read_text())
        assert stats["rejects"] == {}, name
    for log in (tmp_path / "logs").glob("*.log"):
        text = log.read_text()
        assert " ERROR " not in text and "Traceback" not in text, log.name
