"""The ``release_payload`` command on the bus, and what the adapter makes of the release.

Lockstep hover with the 175 g payload, no planned release: an operator (this test) puts
a ``release_payload`` command stamped at 4 s of simulated time. The simulator releases at
exactly that control instant (event, ground-truth column), the commanded thrust drops by
about the payload's weight (the adaptive MPC follows the lighter vehicle), and the
adapter's changepoint detector raises no event in the steady hover and one within 0.25 s
of the release.

With the shipped quadrotor weights (seed 0, lockstep) the learner's own MAP path gains no
changepoint at a 175 g release in hover: the release is a ~3 sigma innovation of the
vertical velocity for one step against the learner's noise, which its posterior absorbs
within a few steps. The detector (a joint-scored beam that watches the vertical outputs,
:func:`arcade_control.detection.detection_config`) accumulates that evidence over its window
and declares it.
"""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest

from arcade.demo_stack import free_hub, read_truth
from deploy.launcher import StackConfig, run_flight
from services.bus import Bus, peer_config
from services.messages import Command

T_RELEASE = 4.0
PAYLOAD_KG = 0.175


def test_release_payload_command_in_hover(tmp_path):
    cfg = StackConfig(
        out=tmp_path,
        hub=free_hub(),
        lockstep=True,
        duration=6.0,
        hover_s=1000.0,
        release=-1.0,
        x64=True,
        method="ours",
    )
    sent = threading.Event()
    buses: list[Bus] = []

    def on_ready(stack):
        bus = Bus(cfg.vehicle, "operator", peer_config(cfg.hub)).open()
        buses.append(bus)

        def on_state(s):
            # Put once, ahead of time: the command carries the instant it is for.
            if s.stamp >= 2.0 and not sent.is_set():
                sent.set()
                bus.put(Command(name="release_payload", target="sim", stamp=T_RELEASE))

        bus.subscribe("state", on_state)

    try:
        result = run_flight(cfg, on_ready=on_ready)
    finally:
        for bus in buses:  # an open session keeps the interpreter from exiting
            bus.close()
    assert sent.is_set()
    assert all(c == 0 for c in result["codes"].values()), result["codes"]
    sim = json.loads((tmp_path / "stats" / "sim.json").read_text())
    assert not sim["crashed"] and sim["timeouts"] == 0
    assert sim["released_at"] == pytest.approx(T_RELEASE)
    released = [e for e in result["events"] if e["text"] == "payload released"]
    assert len(released) == 1 and released[0]["stamp"] == pytest.approx(T_RELEASE)

    truth = read_truth(tmp_path / "truth.csv")
    t = truth["t"]
    assert np.all(truth["released"][t < T_RELEASE - 1e-9] == 0)
    assert np.all(truth["released"][t >= T_RELEASE - 1e-9] == 1)
    # The thrust the controller commands drops by about the payload's weight.
    before = truth["u0"][(t >= 3.0) & (t < T_RELEASE)].mean()
    after = truth["u0"][t >= T_RELEASE + 1.0].mean()
    drop = before - after
    assert 0.6 * PAYLOAD_KG * 9.81 <= drop <= 1.4 * PAYLOAD_KG * 9.81, drop

    cps = np.array([e["stamp"] for e in result["events"] if e["kind"] == "changepoint"])
    # Steady hover (after take-off, before the release): no changepoint event; the release
    # is declared within 0.25 s, once.
    assert np.sum((cps >= 3.0) & (cps < T_RELEASE)) == 0, cps
    assert np.sum((cps > T_RELEASE) & (cps <= T_RELEASE + 0.25 + 1e-9)) == 1, cps
    assert np.sum(cps > T_RELEASE + 0.25 + 1e-9) == 0, cps
