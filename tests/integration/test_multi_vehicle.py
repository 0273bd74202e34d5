"""Four vehicles on one bus: one stack (five processes) per vehicle name, no cross-talk.

Every stack uses the same Zenoh hub; the vehicle name is the first key segment
(``arcade/<vehicle>/...``), so each service hears only its own vehicle. Each vehicle flies
a short lockstep take-off and hover around its own origin. Checks: each recording holds
only its own vehicle's channels, one publisher per topic (nobody else's estimator or
controller got in), each vehicle flew its own reference, no message was rejected anywhere,
each launcher saw its own services alive and a liveliness token of one vehicle reaches no
other vehicle's launcher.
"""

from __future__ import annotations

import contextlib
import json

import numpy as np
from mcap.reader import make_reader

from arcade.demo_stack import free_hub, read_truth
from deploy.launcher import Stack, StackConfig
from services.bus import Bus, peer_config

ORIGINS = {"quad1": (-0.5, -0.5), "quad2": (0.5, -0.5), "quad3": (-0.5, 0.5), "quad4": (0.5, 0.5)}


def test_four_vehicles_share_one_bus_without_cross_talk(tmp_path):
    hub = free_hub()
    stacks: dict[str, Stack] = {}
    with contextlib.ExitStack() as running:
        for name, origin in ORIGINS.items():
            cfg = StackConfig(
                out=tmp_path / name,
                vehicle=name,
                hub=hub,
                lockstep=True,
                method="ours",
                duration=3.0,
                hover_s=1000.0,
                origin=origin,
                max_restarts=0,
            )
            stacks[name] = running.enter_context(Stack(cfg))
        for stack in stacks.values():
            stack.wait_ready()  # each launcher saw its own services' tokens
        # Liveliness is per vehicle: a token declared under quad1 reaches quad1's launcher
        # only. (A vehicle may already have landed and its simulator left: compare names
        # seen, not the full set.)
        with Bus("quad1", "probe", peer_config(hub)) as probe:
            probe.declare_alive()
            stacks["quad1"].wait_alive(["probe"], timeout=10.0)
            for name, stack in stacks.items():
                assert stack.alive <= {*stack.services, "probe"}, (name, stack.alive)
                assert ("probe" in stack.alive) == (name == "quad1"), (name, stack.alive)
        for stack in stacks.values():
            assert stack.wait(timeout=600.0) == 0
        # Flights over, simulators gone: each stack still was ready (a short lockstep flight
        # may end before the caller asks).
        for stack in stacks.values():
            assert stack.wait_ready(timeout=5.0) >= 0.0
    for name, stack in stacks.items():
        out = tmp_path / name
        codes = {n: p.returncode for n, p in stack.procs.items()}
        assert all(c == 0 for c in codes.values()), (name, codes)
        for f in (out / "stats").glob("*.json"):
            assert json.loads(f.read_text()).get("rejects", {}) == {}, (name, f.stem)
        # The recording: only this vehicle's keys, one publisher per topic.
        srcs: dict[str, set[str]] = {}
        with (out / "bus.mcap").open("rb") as f:
            for _, channel, message in make_reader(f).iter_messages():
                assert channel.topic.startswith(f"arcade/{name}/"), (name, channel.topic)
                if channel.message_encoding != "json":  # the Foxglove drawing beside
                    continue
                topic = channel.topic.rsplit("/", 1)[-1]
                srcs.setdefault(topic, set()).add(json.loads(message.data)["src"])
        for topic in ("mocap", "imu", "state", "setpoint", "model", "residual"):
            assert len(srcs.get(topic, ())) == 1, (name, topic, srcs.get(topic))
        # Its own reference, flown: hovering over its own origin at the end.
        truth = read_truth(out / "truth.csv")
        ox, oy = ORIGINS[name]
        np.testing.assert_allclose([truth["ref_px"][-1], truth["ref_py"][-1]], [ox, oy], atol=1e-9)
        assert abs(truth["px"][-1] - ox) < 0.1 and abs(truth["py"][-1] - oy) < 0.1, name
        assert truth["t"].size == 61  # 3 s at 20 Hz, both ends included
