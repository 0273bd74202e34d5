"""Process faults: services killed with SIGKILL mid-flight through the launcher.

The supervisor restarts each killed service (``fault`` and ``restart`` events), the
simulator's setpoint watchdog holds the position while no setpoint arrives, and the
restarted services rejoin the running flight:

- lockstep: the controller, then the estimator, die; each time the vehicle fails safe
  within the bound (0.3 s of simulated time after the last setpoint, plus one control
  period), the service comes back and the failsafe clears; the flight ends normally;
- realtime: the adapter dies: the controller keeps flying on the last model and flags it,
  then falls back to the nominal model; while the adapter restarts, the controller dies
  (failsafe delay measured on the wall clock by an independent subscriber); the restarted
  adapter restores its checkpoint (written atomically, so a SIGKILL never leaves a torn
  file), the restarted controller picks up the mission clock, the failsafe clears and the
  controller tracks on fresh models again; then the adapter alone dies, and the restarted
  one learns again (the simulator re-sends it the mission clock, with ``flying``).

Every kill is triggered by what the bus says (stamps, events), never by a sleep.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from arcade.demo_stack import free_hub, read_truth
from deploy.launcher import Stack, StackConfig
from services.bus import Bus, peer_config

RATE = 20.0
FAILSAFE_S = 0.3
CHECKPOINT_EVERY = 20  # the adapter's default --checkpoint-every
WAIT = 180.0  # upper bound on any wait (restarts compile on a loaded machine), never a sleep


class Monitor:
    """An independent observer on the bus: state stamps, setpoint and event arrivals."""

    def __init__(self, hub: str, vehicle: str = "default"):
        self.bus = Bus(vehicle, "monitor", peer_config(hub)).open()
        self.cond = threading.Condition()
        self.stamp = -1.0
        self.setpoints: list[tuple[float, float]] = []  # (arrival wall time, stamp)
        self.modes: list[tuple[float, str]] = []  # (arrival wall time, setpoint mode)
        self.events: list[tuple[float, Any]] = []  # (arrival wall time, event)
        self.model_step = -1  # the newest model's learning step
        self.bus.subscribe("state", self._on_state, check_order=False)
        self.bus.subscribe("model", self._on_model, check_order=False)
        self.bus.subscribe("setpoint", self._on_setpoint, check_order=False)
        self.bus.subscribe("event", self._on_event, check_order=False)

    def _on_state(self, s: Any) -> None:
        with self.cond:
            self.stamp = max(self.stamp, s.stamp)
            self.cond.notify_all()

    def _on_model(self, m: Any) -> None:
        with self.cond:
            self.model_step = max(self.model_step, m.step)
            self.cond.notify_all()

    def _on_setpoint(self, sp: Any) -> None:
        with self.cond:
            self.setpoints.append((time.monotonic(), sp.stamp))
            self.modes.append((time.monotonic(), sp.mode))
            self.cond.notify_all()

    def _on_event(self, e: Any) -> None:
        with self.cond:
            self.events.append((time.monotonic(), e))
            self.cond.notify_all()

    def wait(self, what: str, pred: Callable[[], bool]) -> None:
        with self.cond:
            assert self.cond.wait_for(pred, WAIT), f"timed out waiting for {what}"

    def find(self, pred: Callable[[Any], bool]) -> list[tuple[float, Any]]:
        with self.cond:
            return [(t, e) for t, e in self.events if pred(e)]

    def wait_event(self, what: str, pred: Callable[[Any], bool], after: int = 0) -> Any:
        """The first event (index ``>= after``) matching ``pred``; returns (index, t, e)."""

        def found() -> bool:
            return any(pred(e) for _, e in self.events[after:])

        self.wait(what, found)
        with self.cond:
            for i, (t, e) in enumerate(self.events[after:], after):
                if pred(e):
                    return i, t, e
        raise AssertionError(what)

    def close(self) -> None:
        self.bus.close()


def is_event(kind: str, src: str | None = None, **data: Any) -> Callable[[Any], bool]:
    def pred(e: Any) -> bool:
        return (
            e.kind == kind
            and (src is None or e.src.startswith(src + "/"))
            and all(e.data.get(k) == v for k, v in data.items())
        )

    return pred


def cleared(e: Any) -> bool:
    return e.src.startswith("sim/") and e.kind == "failsafe_cleared"


def check_logs(out: Path, codes: dict) -> None:
    assert all(c == 0 for c in codes.values()), codes
    for name in ("estimator", "adapter", "controller", "recorder"):
        stats = json.loads((out / "stats" / f"{name}.json").read_text())
        assert stats["rejects"] == {}, (name, stats["rejects"])
    sim = json.loads((out / "stats" / "sim.json").read_text())
    assert not sim["crashed"]
    return sim


def config(out: Path, **kw: Any) -> StackConfig:
    # A take-off and hover plan: the failsafe holds near the reference.
    return StackConfig(
        out=out, hub=free_hub(), rate=RATE, hover_s=1000.0, x64=True, method="ours", **kw
    )


def test_lockstep_controller_and_estimator_killed(tmp_path):
    # Lockstep time stands still while the simulator waits for a setpoint: with 0.2 s per
    # missing setpoint the bound (6 instants) passes after ~1.2 s of wall time, well before
    # a killed service can be back (2 s back-off, then its start-up).
    cfg = config(
        tmp_path,
        lockstep=True,
        duration=12.0,
        restart_backoff_s=2.0,
        extra={"sim": ["--step-timeout", "0.2"]},
    )
    with Stack(cfg) as stack:
        mon = Monitor(cfg.hub)
        try:
            stack.wait_ready()
            for victim, at in (("controller", 3.0), ("estimator", 7.0)):
                mon.wait(f"state at {at} s", lambda at=at: mon.stamp >= at)
                n = len(mon.events)
                stack.kill(victim)
                _, _, fs = mon.wait_event("failsafe", is_event("failsafe", "sim"), n)
                mon.wait_event(
                    f"{victim} restart", is_event("restart", "launcher", service=victim), n
                )
                mon.wait_event("failsafe cleared", cleared, n)
                # Lockstep: the stale setpoint is held at most the bound (simulated time).
                assert fs.data["since_last_setpoint_s"] <= FAILSAFE_S + 1.0 / RATE + 1e-9
                assert stack.alive >= {victim}
            assert stack.wait(timeout=WAIT) == 0
        finally:
            mon.close()
    codes = {n: p.returncode for n, p in stack.procs.items()}
    sim = check_logs(tmp_path, codes)
    assert stack.restarts == {**dict.fromkeys(stack.services, 0), "controller": 1, "estimator": 1}
    assert len(sim["failsafes"]) == 2 and all("cleared_t" in f for f in sim["failsafes"])
    # Ground truth: the failsafe engaged no later than the bound after the last
    # setpoint the simulator applied (flight log: one row per answered state).
    truth = read_truth(tmp_path / "truth.csv")
    fs_rows = np.flatnonzero(np.diff(truth["failsafe"]) > 0) + 1
    assert fs_rows.size == 2
    answered = np.genfromtxt(
        tmp_path / "flight_log.csv", delimiter=",", names=True, dtype=None, encoding=None
    )["t"]
    for row in fs_rows:
        t_fs = truth["t"][row]
        last = answered[answered < t_fs - 1e-9].max()
        assert t_fs - last <= FAILSAFE_S + 1.0 / RATE + 1e-9, (t_fs, last)
    # While it holds, the vehicle stays near its hover reference (no drift, no fall).
    hold = truth["failsafe"] > 0
    p = np.stack([truth[c] for c in ("px", "py", "pz")], axis=1)
    ref = np.stack([truth[c] for c in ("ref_px", "ref_py", "ref_pz")], axis=1)
    assert np.max(np.linalg.norm(p[hold] - ref[hold], axis=1)) < 0.5
    # Both kills are in the launcher's event log, with the signal that ended the process.
    events = [json.loads(line) for line in (tmp_path / "events.jsonl").read_text().splitlines()]
    faults = [e for e in events if e["src"] == "launcher" and e["kind"] == "fault"]
    assert [(e["data"]["service"], e["data"]["code"]) for e in faults] == [
        ("controller", -9),
        ("estimator", -9),
    ]


@pytest.mark.realtime
def test_realtime_adapter_and_controller_killed(tmp_path):
    # Long enough for both restarts on a loaded machine; stopped once all is seen.
    cfg = config(tmp_path, lockstep=False, duration=120.0, restart_backoff_s=0.2)
    with Stack(cfg) as stack:
        mon = Monitor(cfg.hub)
        try:
            stack.wait_ready()
            mon.wait("a second of flight", lambda: len(mon.setpoints) > 2 * RATE)
            # A learned posterior in the checkpoint (written every CHECKPOINT_EVERY steps):
            # how long the flight takes to get there depends on the host.
            mon.wait("a checkpoint", lambda: mon.model_step >= 2 * CHECKPOINT_EVERY)
            # Adapter: the controller keeps the last model, flags it, then goes nominal.
            n = len(mon.events)
            stack.kill("adapter")
            _, t_stale, _ = mon.wait_event(
                "stale model", is_event("degraded", "controller", flag="stale_model"), n
            )
            _, t_nom, _ = mon.wait_event(
                "nominal model", is_event("degraded", "controller", mode="nominal_model"), n
            )
            assert t_nom > t_stale
            # Controller (while the adapter restarts): the vehicle fails safe within the
            # bound after the last setpoint, both measured here on the wall clock.
            n = len(mon.events)
            stack.kill("controller")
            _, t_fs, fs = mon.wait_event("failsafe", is_event("failsafe", "sim"), n)
            with mon.cond:
                last_sp = max(t for t, _ in mon.setpoints if t < t_fs)
            delay = t_fs - last_sp
            assert delay <= FAILSAFE_S + 1.0 / RATE, delay
            assert FAILSAFE_S <= fs.data["since_last_setpoint_s"] <= FAILSAFE_S + 0.02
            # Both come back: the adapter with the posterior of before its crash, the
            # controller on the mission clock; the failsafe clears and the controller
            # tracks on fresh models again.
            _, t_restored, restored = mon.wait_event("restored", is_event("restart", "adapter"), n)
            assert restored.data["steps"] > 0
            mon.wait_event("failsafe cleared", cleared, n)
            mon.wait(
                "tracking on a fresh model",
                lambda: any(t > t_restored and mode == "track" for t, mode in mon.modes),
            )
            # The adapter alone, killed while it learns: restarted, it saw neither the
            # mission's start nor the failsafes; the simulator's re-sent clock says whether
            # the setpoints are flown now (the restart's load may have the simulator hold
            # again), and it learns again.
            mon.wait_event(
                "the restored adapter learning",
                lambda e: e.src == restored.src and e.data.get("learning") is True,
                n,
            )
            n = len(mon.events)
            stack.kill("adapter")
            _, _, back = mon.wait_event("restored again", is_event("restart", "adapter"), n)

            def of_new(e: Any) -> bool:
                return e.src == back.src and e.kind == "info"

            _, _, first = mon.wait_event("its first word on learning", of_new, n)
            assert "mission started" in first.text or "under a failsafe" in first.text, first
            mon.wait_event(
                "learning again", lambda e: of_new(e) and e.data.get("learning") is True, n
            )
        finally:
            mon.close()
    codes = {n: p.returncode for n, p in stack.procs.items()}
    check_logs(tmp_path, codes)
    assert stack.restarts["controller"] == 1 and stack.restarts["adapter"] == 2
    # The last incarnation learned from the flight (its stats are written at shutdown).
    stats = json.loads((tmp_path / "stats" / "adapter.json").read_text())
    assert stats["learned"] > 0, stats


def test_supervisor_restarts_with_backoff_then_gives_up(tmp_path):
    """The supervisor alone, on the recorder (quick to start): SIGKILL, restart after the
    back-off with ``--incarnation 1`` (its recording goes to ``bus.1.mcap``), liveliness
    back; a second SIGKILL with no restart left: a critical event and :attr:`Stack.failed`."""
    seen = threading.Condition()
    events: list[dict] = []

    def on_event(rec: dict) -> None:
        with seen:
            events.append(rec)
            seen.notify_all()

    def wait_for(what: str, pred: Callable[[], bool]) -> None:
        with seen:
            assert seen.wait_for(pred, WAIT), what

    cfg = StackConfig(out=tmp_path, hub=free_hub(), max_restarts=1, restart_backoff_s=0.3)
    with Stack(cfg, services=("recorder",), on_event=on_event) as stack:
        stack.wait_ready()
        first = stack.kill("recorder")
        wait_for("restart", lambda: any(e["kind"] == "restart" for e in events))
        stack.wait_ready()  # the new incarnation's liveliness token
        assert stack.procs["recorder"].pid != first and stack.alive == {"recorder"}
        stack.kill("recorder")
        wait_for("give up", lambda: any(e["severity"] == "critical" for e in events))
    kinds = [(e["kind"], e["severity"]) for e in events if e["src"] == "launcher"]
    assert kinds == [("fault", "error"), ("restart", "warning"), ("fault", "critical")]
    assert events[0]["data"] == {"service": "recorder", "code": -9, "restarts": 0, "backoff_s": 0.3}
    assert "recorder" in stack.failed and (tmp_path / "bus.1.mcap").is_file()
    logged = [json.loads(line) for line in (tmp_path / "events.jsonl").read_text().splitlines()]
    assert [(e["kind"], e["severity"]) for e in logged] == kinds
