"""The embedded bus of ``arcade up`` (peers with a password made for the run) and the source
pinning of the vehicle link, flown against a rogue process on the host in both profiles,
with a controller restart in the sim profile.

No sleeps: the test waits on the stack's events (the refusals, the controller's restart)
and reads the services' counters after the run.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh
from message_samples import sample as valid

from arcade.demo_stack import free_hub, read_truth
from deploy.launcher import Stack, StackConfig
from services import bus as zbus
from services.messages import Mocap, Model, Setpoint, decode

TIMEOUT = 10.0  # upper bound for a loaded machine; never a sleep


class Rogue:
    """Another process on the host (its own Zenoh session) that answers every ``state``
    with a valid setpoint that would flip the vehicle: its own ``seq``, the state's
    ``stamp`` and ``seq``, the controller's ``src`` copied from the controller's setpoints,
    and its own publisher's source info; and with a valid mocap frame, model and state
    (1 m off) of the same stamp. Counts the states it saw and what it sent."""

    def __init__(self, vehicle: str, config: zenoh.Config):
        self.session = zenoh.open(config)
        self.zid = str(self.session.zid())
        self.states = self.sent = 0
        self.stamp = -1.0  # of the newest state
        self.src = "controller/rogue"
        self._cond = threading.Condition()
        self._pubs = {
            topic: self.session.declare_publisher(
                f"arcade/{vehicle}/{topic}", priority=zbus.QOS[topic].priority
            )
            for topic in ("setpoint", "mocap", "model", "state")
        }
        for topic, handler in (("setpoint", self._on_setpoint), ("state", self._on_state)):
            self.session.declare_subscriber(f"arcade/{vehicle}/{topic}", handler)

    def _on_setpoint(self, sample) -> None:
        src = decode("setpoint", sample.payload.to_bytes()).src
        if src.startswith("controller/"):
            self.src = src

    def _on_state(self, sample) -> None:
        state = decode("state", sample.payload.to_bytes())
        if state.src == "state/rogue":
            return  # its own
        with self._cond:
            self.states += 1
            self.stamp = max(self.stamp, state.stamp)
            self._cond.notify_all()
        n, t = self.states, state.stamp
        records = {  # the setpoint would flip the vehicle
            "setpoint": Setpoint(u=[0.0, 3.0, -3.0, 0.0], state_seq=state.seq, stamp=t),
            "mocap": valid(Mocap).replace(capture_stamp=t, stamp=t),
            "model": valid(Model).replace(stamp=t),
            "state": state.replace(x=np.r_[state.x[:2], state.x[2] + 1.0, state.x[3:]]),
        }
        for topic, record in records.items():
            src = self.src if topic == "setpoint" else f"{topic}/rogue"
            wire = record.replace(seq=n, src=src).to_wire()
            pub = self._pubs[topic]
            pub.put(msgpack.packb(wire, use_bin_type=True), source_info=zenoh.SourceInfo(pub.id, n))
        self.sent += 1

    def wait_stamp(self, t: float, timeout: float) -> None:
        with self._cond:
            assert self._cond.wait_for(lambda: self.stamp >= t, timeout), (t, self.stamp)

    def close(self) -> None:
        self.session.close()


def _stats(out: Path, name: str) -> dict:
    return json.loads((out / "stats" / f"{name}.json").read_text())


def _refused(event: dict, session: str, topic: str = "setpoint") -> bool:
    data = event["data"]
    return event["kind"] == "fault" and (data.get("topic"), data.get("session")) == (topic, session)


@pytest.mark.parametrize("profile", ["sim", pytest.param("px4", marks=pytest.mark.realtime)])
def test_the_embedded_bus_keeps_a_rogue_out_and_pins_the_controller(tmp_path: Path, profile):
    # The default of `arcade up` (a hub of its own, a password made for the run): a rogue
    # without the password never sees a state; one given the run's configuration is
    # refused by the source pinning (counted, one fault event) and the flight is the
    # controller's. In the sim profile the controller is then killed: the restarted one is
    # pinned through its new token and the flight goes on.
    from deploy.px4_profile import EventWaiter, Px4StackConfig, arm

    plan = {"hub": free_hub(), "credentials": True, "method": "ours", "duration": 5.0}
    plan.update(hover_s=100.0, release=-1.0)
    if profile == "sim":  # lockstep: 1 s per missing setpoint while the controller restarts
        extra = {"sim": ["--step-timeout", "1.0"]}
        plan.update(lockstep=True, duration=6.0, restart_backoff_s=0.1, extra=extra)
        cfg = StackConfig(tmp_path, **plan)
    else:
        cfg = Px4StackConfig(tmp_path, simulate=True, **plan)
    vehicle = cfg.vehicle_process if profile == "px4" else "sim"
    events = EventWaiter()
    with Stack(cfg, on_event=events) as stack:
        outsider = Rogue(cfg.vehicle, zbus.peer_config(cfg.hub))
        insider = Rogue(cfg.vehicle, cfg.bus_config("rogue"))
        try:
            stack.wait_ready()
            assert oct((tmp_path / "bus" / "peer.json5").stat().st_mode & 0o777) == "0o600"
            if profile == "px4":
                assert arm(events, cfg, timeout=60.0)
            first = events.wait(lambda e: _refused(e, insider.zid), TIMEOUT * 6)
            assert first is not None  # whoever takes it first; each is checked below
            if profile == "sim":  # after the take-off (1.5 m -> 2 m, 2.2 s)
                insider.wait_stamp(3.0, 60.0)
                n = events.mark()
                stack.kill("controller")
                restarted = events.wait(lambda e: e["kind"] == "restart", 60.0, n)
                assert restarted is not None and restarted["data"]["service"] == "controller"
            assert stack.wait(timeout=120.0) == 0
        finally:
            outsider.close()
            insider.close()
    assert not (tmp_path / "bus").exists()  # the password died with the run
    codes = {n: p.returncode for n, p in stack.procs.items()}
    assert all(c == 0 for c in codes.values()), codes
    assert outsider.states == 0 and insider.sent > 0
    # Refused and counted by every pinned subscription, announced once.
    takers = [(vehicle, "setpoint"), ("estimator", "mocap"), ("controller", "model")]
    takers += [("controller", "state"), ("adapter", "setpoint"), ("adapter", "state")]
    if profile == "px4":
        takers.append(("bridge", "setpoint"))
    for name, topic in takers:
        refused = _stats(tmp_path, name)["rejects_by_topic"][topic]
        assert set(refused) == {"foreign_publisher"}, (name, refused)
        assert 0 < refused["foreign_publisher"] <= insider.states, (name, refused)
        faults = [
            e
            for e in events.events
            if e["src"].startswith(f"{name}/") and _refused(e, insider.zid, topic)
        ]
        # Once per receiving process (the restarted controller announces it again).
        assert len(faults) == len({e["src"] for e in faults}) >= 1, (name, faults)
    # Nothing else was refused: not the outsider (never linked), not the restarted controller.
    refusals = [e for e in events.events if e["kind"] == "fault" and "session" in e["data"]]
    assert {e["data"]["session"] for e in refusals} == {insider.zid}, refusals
    # The flight is the controller's: the rogue's input was never applied (the ground
    # truth logs the input of every step), and the vehicle stayed near its hover reference
    # (as near as a failsafe hold keeps it: tests/integration/test_faults_process.py).
    assert not _stats(tmp_path, vehicle)["crashed"]
    truth = read_truth(tmp_path / "truth.csv")
    applied = np.stack([truth[f"u{i}"] for i in range(4)], axis=1)
    assert len(applied) > 0 and not np.any(np.all(np.isclose(applied, [0, 3, -3, 0]), axis=1))
    err = np.stack([truth[a] - truth[f"ref_{a}"] for a in ("px", "py", "pz")], axis=1)
    assert np.max(np.linalg.norm(err, axis=1)) < 0.5, np.max(np.linalg.norm(err, axis=1))
    if profile == "sim":
        # The restarted controller took over: every instant of the flight's last second
        # was answered (a miss is a deadline_miss event), and the vehicle flies its
        # setpoints at the end (a hold the restart's missed answers engaged has ended).
        end = float(truth["t"][-1])
        late = [e for e in events.events if e["kind"] == "deadline_miss" and e["stamp"] > end - 1]
        assert late == [] and truth["failsafe"][-1] == 0.0, late
