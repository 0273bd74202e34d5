"""Checks of a stack flight's run folder that need no flight of their own: the Foxglove
channels of its ``bus.mcap`` (read back with the schemas' protobuf decoder; the vehicle and
the payload with its cable until the release), the live
Foxglove service's statistics, and ``arcade replay`` reproducing the recorded adapter and
controller (and changing the adapter's predictions with another knob)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def check_foxglove(out: Path, vehicle: str = "default") -> dict[str, int]:
    """Returns the number of mocap frames recorded per rigid body."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    records: dict[str, list] = {"state": [], "mocap": [], "event": []}
    got: dict[str, list] = {}
    with (out / "bus.mcap").open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        topics = [c.topic for c in reader.get_summary().channels.values()]
        for t in topics:
            kind = t.rsplit("/", 1)[-1]
            if kind in records and "/foxglove/" not in t:
                records[kind] = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=[t])]
        states = records["state"]
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
    counts = _check_payload(got, records["mocap"], records["event"], vehicle)
    assert live["messages"]["payload"] == counts["payload"]
    return counts


def _check_payload(got: dict, mocap: list, events: list, vehicle: str) -> dict[str, int]:
    """The payload's channels: one transform and one sphere per payload frame at its pose;
    the cable from the vehicle's frame of the same capture for the frames captured before
    the release, none for those captured after it."""
    frames = {b: [m for m in mocap if m["body"] == b] for b in ("vehicle", "payload")}
    assert len(frames["vehicle"]) + len(frames["payload"]) == len(mocap)  # no other body
    payload, scenes = frames["payload"], got["payload"]
    assert len(got["payload_transform"]) == len(scenes) == len(payload) > 0
    assert {name for name, _ in scenes} == {"foxglove.SceneUpdate"}
    assert got["payload_transform"][-1][1].child_frame_id == f"{vehicle}/payload"
    (released,) = [e["stamp"] for e in events if e["data"].get("payload") == "released"]
    anchors = {m["capture_stamp"]: m["position"] for m in frames["vehicle"]}
    hanging = after = 0
    for m, (_, update) in zip(payload, scenes, strict=True):
        (entity,) = update.entities
        (sphere,) = entity.spheres
        c = sphere.pose.position
        np.testing.assert_allclose([c.x, c.y, c.z], m["position"])
        if m["capture_stamp"] < released:
            (cable,) = entity.lines
            ends = [[p.x, p.y, p.z] for p in cable.points]
            np.testing.assert_allclose(ends, [anchors[m["capture_stamp"]], m["position"]])
            hanging += 1
        else:
            assert not entity.lines, m["capture_stamp"]
            after += 1
    assert hanging > 0 and after > 0  # tracked before and after the release
    return {b: len(v) for b, v in frames.items()}


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
