"""Checks of a stack flight's run folder that need no flight of their own: the Foxglove
channels of its ``bus.mcap`` (read back with the schemas' protobuf decoder), the live
Foxglove service's statistics, and ``arcade replay`` reproducing the recorded adapter and
controller (and changing the adapter's predictions with another knob)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def check_foxglove(out: Path, vehicle: str = "default") -> None:
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    states, got = [], {}
    with (out / "bus.mcap").open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        topics = [c.topic for c in reader.get_summary().channels.values()]
        for t in topics:
            if t.endswith("/state"):
                states = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=[t])]
        ours = [t for t in topics if "/foxglove/" in t]
        for schema, channel, _, msg in reader.iter_decoded_messages(topics=ours):
            got.setdefault(channel.topic.rsplit("/", 1)[-1], []).append((schema.name, msg))
    tf = got["transform"]
    assert len(tf) == len(states) > 0 and tf[0][0] == "foxglove.FrameTransform"
    last, x = tf[-1][1], np.asarray(states[-1]["x"])
    assert last.child_frame_id == f"{vehicle}/body"
    t, r = last.translation, last.rotation
    np.testing.assert_allclose([t.x, t.y, t.z, r.w, r.x, r.y, r.z], x[[0, 1, 2, 6, 7, 8, 9]])
    assert got["vehicle"][-1][0] == "foxglove.SceneUpdate"
    assert got["vehicle"][-1][1].entities[0].frame_id == f"{vehicle}/body"
    assert len(got["pose"]) == len(states)
    path = got["reference"][-1][1].entities[0].lines[0].points  # the planned path
    assert len(path) > 10 and abs(path[0].z - 1.5) < 1e-6  # it starts at the take-off point
    assert len(got["geofence"][-1][1].entities[0].lines[0].points) == 24
    live = json.loads((out / "stats" / "foxglove.json").read_text())
    assert live["port"] > 0 and live["messages"]["transform"] == len(states)


def check_replay(out: Path, other_knob: str) -> None:
    """``arcade replay --service controller`` reproduces the recorded residuals and
    setpoints; ``other_knob`` changes the predictions."""
    from arcade.commands.replay import replay

    same = replay(out / "bus.mcap", "controller", [], out / "replay", progress=False)
    r = same["residuals"]
    assert r["recorded"] == r["replayed"] == r["matched"] > 0, r
    assert same["max_abs_mean_difference"] <= 1e-9, same
    assert same["changepoints"]["replayed"] == same["changepoints"]["recorded"]
    s = same["setpoints"]
    assert s["recorded"] == s["replayed"] == s["matched"] > 0, s
    assert s["max_abs_difference"] <= 1e-6, s
    assert all(not n for n in same["rejects"].values()), same["rejects"]
    other = replay(out / "bus.mcap", "adapter", [other_knob], out / "replay_knob", progress=False)
    assert other["residuals"]["matched"] == r["recorded"]
    assert other["max_abs_mean_difference"] > 1e-3, other
