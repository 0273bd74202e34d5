"""The whole stack on the wall clock: a short realtime flight at 30 Hz."""

from __future__ import annotations

import json

import numpy as np
import pytest
from mcap.reader import make_reader

from arcade.demo_stack import free_hub
from arcade_io.hostcpu import SlowdownProbe, overlaps
from deploy.launcher import StackConfig, run_flight
from deploy.stack_config import CPU_WAKEUP_LATENCY_US, REALTIME_PRIORITY

# Flown on the wall clock, with timing assertions: run alone (``make test``).
pytestmark = pytest.mark.realtime


def test_realtime_flight_at_30hz_meets_deadlines(tmp_path):
    cfg = StackConfig(
        out=tmp_path, lockstep=False, hub=free_hub(), rate=30.0, duration=6.0, method="ours"
    )
    with SlowdownProbe(tmp_path / "host") as host:
        result = run_flight(cfg)
    assert all(code == 0 for code in result["codes"].values()), result["codes"]
    sim = json.loads((tmp_path / "stats" / "sim.json").read_text())
    assert sim["mode"] == "realtime" and not sim["crashed"]
    ticks = sim["steps"]
    assert ticks == 181  # 6 s at 30 Hz, both ends included
    # Fewer than 1 % of the control instants without their setpoint before the next one,
    # among the periods in which the machine itself ran at its usual speed: no scheduling
    # policy in the guest protects a deadline from the host taking a vCPU away (steal:
    # CI failed once on 2 misses while the host stole 0.38 s) or slowing it down (without
    # steal, every second or two a fixed unit of work runs 3-20 times slower for 10-80 ms,
    # which the probe records; CI failed on 6 misses without steal while the controller's
    # solves took 5 times their usual time, 2 s apart). Those periods are few, or the
    # flight measured the host rather than the stack.
    assert len(sim["missed_periods"]) == sim["missed_deadlines"]
    # A probe that could not take real-time priority waits behind the stack: it excuses
    # nothing then.
    slow = host.episodes if host.summary["fifo"] else []
    host_misses = [
        (round(b - a, 4), stolen, overlaps(slow, a, b)) for a, b, stolen in sim["missed_periods"]
    ]
    stack_misses = sum(1 for _, stolen, slowed in host_misses if not (stolen or slowed))
    assert stack_misses < 0.01 * ticks, (
        host_misses,
        host.summary,
        sim["stolen_periods"],
        sim.get("host_steal_s"),
        sim["sense_to_actuate"],
    )
    assert sim["missed_deadlines_host_steal"] == sum(1 for _, stolen, _ in host_misses if stolen)
    assert host.summary["cpus"] >= 1, host.summary
    assert sim["stolen_periods"] <= 0.5 * ticks, (sim["stolen_periods"], sim["host_steal_s"])
    assert sim["host_steal_s"] >= 0.0
    # Every instant answered, but for fewer than 1 % of them outside those slow periods
    # (an unanswered instant is a missed deadline).
    excused = len(host_misses) - stack_misses
    assert sim["sense_to_actuate"]["n"] >= 0.99 * (ticks - excused), (excused, host.summary)
    assert sim["wall_s"] - sim["preroll_s"] == pytest.approx(6.0, abs=0.5)  # wall clock
    for name in ("estimator", "adapter", "controller", "recorder"):
        stats = json.loads((tmp_path / "stats" / f"{name}.json").read_text())
        assert stats["rejects"] == {}, name
        # Start-up objects are frozen out of the collector: no full collection of them
        # stalls the loop (they took ~100 ms each, five periods at 50 Hz).
        assert stats["gc_pauses"]["gen2"]["max_ms"] < 20.0, (name, stats["gc_pauses"])
    # The sense-to-actuate path runs under SCHED_FIFO, or says why not.
    for name, priority in REALTIME_PRIORITY.items():
        stats = json.loads((tmp_path / "stats" / f"{name}.json").read_text())
        sched = stats["scheduling"]
        assert sched["priority"] == priority and sched["threads"] + sched["refused"] > 0
        assert sched["policy"] == "fifo" or sched["refused"] > 0, (name, sched)
        wake = stats["cpu_wakeup_latency"]  # idle CPUs poll, or the service says why not
        assert wake["requested_us"] == CPU_WAKEUP_LATENCY_US, (name, wake)
        assert wake["applied"] or "error" in wake, (name, wake)
    for log in (tmp_path / "logs").glob("*.log"):
        text = log.read_text()
        assert " ERROR " not in text and "Traceback" not in text, log.name
    # Control instants carry their sample instants (they were the jittered publishing
    # moments once): physics instants, whole 5 ms substeps apart, the first at or after
    # each period's instant; and the estimate starts level, w > 0 (the sign of the first
    # quaternion once depended on the host's uptime).
    states = [
        json.loads(m.data)
        for _, ch, m in make_reader((tmp_path / "bus.mcap").open("rb")).iter_messages()
        if ch.topic.endswith("/state")
    ]
    steps = np.diff([s["stamp"] for s in states])
    substep = 0.005
    np.testing.assert_allclose(steps / substep, np.round(steps / substep), atol=1e-6)
    assert np.all(np.abs(steps - 1.0 / 30.0) < substep), steps
    assert np.mean(steps) == pytest.approx(1.0 / 30.0, abs=1e-3)
    assert states[0]["x"][6] > 0.99
    # The periods the machine ran slowly in are few (see the deadlines above).
    stamps = [s["stamp"] for s in states]
    slowed = sum(overlaps(slow, t, t + 1.0 / 30.0) for t in stamps)
    assert slowed <= 0.5 * len(stamps), (slowed, len(stamps), host.summary)
    # The bus measured the simulator -> estimator hop of every control instant.
    est = json.loads((tmp_path / "stats" / "estimator.json").read_text())
    assert est["hop_imu"]["n"] >= ticks and 0.0 < est["hop_imu"]["p50_ms"] < 50.0
