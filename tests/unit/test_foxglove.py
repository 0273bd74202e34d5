"""The flight in Foxglove's schemas: the conversion, the recorder's channels read back with
the schemas' own protobuf decoder, and the live server answering a WebSocket client."""

from __future__ import annotations

import argparse
import asyncio
import base64
import dataclasses
import json

import numpy as np
import pytest

from services.messages import PAYLOAD_BODY, VEHICLE_BODY, Event, Mocap, State

#: A 30-degree yaw (w first), for a rotation that cannot pass by accident.
Q_YAW30 = np.array([np.cos(np.pi / 12), 0.0, 0.0, np.sin(np.pi / 12)])
FENCE = "-5,5,-4,4,-0.5,3"
PATH = np.array([[0.0, 0.0, 1.5], [0.0, 0.0, 2.0], [1.0, 0.5, 2.0]])


def _state(t: float) -> State:
    return State.from_parts(
        p=[1.0, -2.0, 1.5 + t], v=[0.1, 0, 0], q=Q_YAW30, omega=[0, 0, 0.2], stamp=t
    )


def _capture(t: float) -> tuple[Mocap, Mocap]:
    """The vehicle's and the payload's mocap frames of the capture at ``t`` (the payload
    hangs 0.6 m below the vehicle)."""
    p = np.array([1.0, -2.0, 1.5 + t])
    one = {"capture_stamp": t, "stamp": t + 0.007}
    return (
        Mocap(position=p, quaternion=Q_YAW30, **one),
        Mocap(position=p - [0, 0, 0.6], quaternion=[1.0, 0, 0, 0], body=PAYLOAD_BODY, **one),
    )


def _decoded_msg(msg):
    """A Foxglove message as the schemas' own protobuf decoder reads it."""
    from mcap.records import Schema
    from mcap_protobuf.decoder import DecoderFactory

    s = type(msg).get_schema()
    schema = Schema(id=1, name=s.name, encoding=s.encoding, data=s.data)
    return DecoderFactory().decoder_for("protobuf", schema)(msg.encode())


RELEASED = Event(kind="info", text="payload released", data={"payload": "released"}, stamp=9.0)


def test_the_payload_is_a_sphere_with_its_cable_from_the_vehicle_until_the_release():
    from arcade_io import foxglove_scene as fs
    from arcade_io.vehicle import PAYLOAD_RADIUS_M

    scene = fs.FoxgloveScene("quad1")
    vehicle, payload = _capture(8.0)
    assert scene.messages("mocap", vehicle.to_wire()) == []  # the vehicle: its state draws it
    got = {n: _decoded_msg(m) for n, m in scene.messages("mocap", payload.to_wire())}
    assert set(got) == {"payload_transform", "payload"}
    tf = got["payload_transform"]
    assert (tf.parent_frame_id, tf.child_frame_id) == ("world", "quad1/payload")
    assert tf.translation.z == pytest.approx(1.5 + 8.0 - 0.6) and tf.timestamp.seconds == 8
    (entity,) = got["payload"].entities
    assert entity.id == "payload" and entity.frame_id == "world"
    (sphere,) = entity.spheres
    assert sphere.size.x == sphere.size.z == 2 * PAYLOAD_RADIUS_M
    assert sphere.pose.position.z == pytest.approx(tf.translation.z)
    (cable,) = entity.lines
    ends = [[p.x, p.y, p.z] for p in cable.points]
    np.testing.assert_allclose(ends, [vehicle.position, payload.position])
    other = dataclasses.replace(payload, body="wand")
    assert scene.messages("mocap", other.to_wire()) == []  # a body drawn nowhere
    assert scene.messages("event", RELEASED.to_wire()) == [] and scene.released_at == 9.0
    for t, cables in ((8.99, 1), (9.0, 0), (9.1, 0)):  # a frame of before, arriving late
        for frame in _capture(t):
            got = dict(scene.messages("mocap", frame.to_wire()))
        (entity,) = _decoded_msg(got["payload"]).entities
        assert len(entity.spheres) == 1 and len(entity.lines) == cables, t  # then it is gone


def test_a_live_scene_that_missed_the_release_draws_no_cable_to_a_payload_out_of_reach():
    """A Foxglove server that joins after the release never sees its event: the cable is
    drawn only to a payload within the cable's reach of the vehicle's rigid body (here
    ``cf1``: ``--mocap-body``), not to one lying on the floor far below it."""
    from arcade_io.foxglove_scene import REACH_MARGIN_M
    from services import foxglove_live, options

    parser = options.common_parser("foxglove", "test")
    foxglove_live._extra(parser)
    args = parser.parse_args(["--vehicle", "quad1", "--mocap-body", "cf1"])
    scene = foxglove_live.scene_for(args)
    assert scene.reach == pytest.approx(0.5 + REACH_MARGIN_M)  # the shipped vehicle's cable
    vehicle_at = np.array([1.0, -2.0, 2.0])

    def cable(t: float, below: float) -> list:
        """The cable's ends drawn for the capture at ``t``, the payload ``below`` the
        vehicle (a body named ``vehicle`` elsewhere: not the anchor)."""
        one = {"capture_stamp": t, "stamp": t + 0.007, "quaternion": [1.0, 0, 0, 0]}
        frames = [
            Mocap(position=vehicle_at, body="cf1", **one),
            Mocap(position=[0.0, 0.0, 1.0], body=VEHICLE_BODY, **one),
            Mocap(position=vehicle_at - [0, 0, below], body=PAYLOAD_BODY, **one),
        ]
        got = [dict(scene.messages("mocap", f.to_wire())) for f in frames]
        assert got[:2] == [{}, {}]
        (entity,) = _decoded_msg(got[2]["payload"]).entities
        assert len(entity.spheres) == 1
        return [[[p.x, p.y, p.z] for p in line.points] for line in entity.lines]

    assert cable(20.0, 1.98) == []  # on the floor, without a release event
    (ends,) = cable(20.01, 0.55)  # hanging
    np.testing.assert_allclose(ends, [vehicle_at, vehicle_at - [0, 0, 0.55]])
    assert len(cable(20.02, 0.5 + REACH_MARGIN_M - 0.01)) == 1
    assert cable(20.03, 0.5 + REACH_MARGIN_M + 0.01) == []
    assert scene.released_at == np.inf


def test_a_state_becomes_the_transform_pose_and_vehicle_and_every_second_the_static_scenes():
    from arcade_io.foxglove_scene import FoxgloveScene, box_edges

    scene = FoxgloveScene("quad1", PATH, (np.array([-1.0, -2, 0]), np.array([1.0, 2, 3])))
    first = dict(scene.messages("state", _state(10.0).to_wire()))
    assert set(first) == {"transform", "pose", "vehicle", "reference", "geofence"}
    assert scene.topic("transform") == "arcade/quad1/foxglove/transform"
    later = dict(scene.messages("state", _state(10.5).to_wire()))
    assert set(later) == {"transform", "pose", "vehicle"}  # the static ones once a second
    assert set(dict(scene.messages("state", _state(11.0).to_wire()))) == set(first)
    assert scene.messages("event", Event(kind="info", stamp=1.0).to_wire()) == []
    edges = box_edges([-1, -2, 0], [1, 2, 3]).reshape(12, 2, 3)
    lengths = sorted(np.linalg.norm(e[1] - e[0]) for e in edges)
    assert lengths == [2.0] * 4 + [3.0] * 4 + [4.0] * 4  # twelve axis-aligned edges


def test_the_reference_path_is_the_controllers_reference_flown_so_far():
    from arcade_io.foxglove_scene import PATH_DT, FoxgloveScene
    from services.messages import Reference

    scene = FoxgloveScene("quad1")
    assert "reference" not in dict(scene.messages("state", _state(0.0).to_wire()))
    x = np.r_[0.0, 0.0, 1.5, np.zeros(3), 1.0, np.zeros(6)]
    for k in range(30):  # 20 ms apart: a point every PATH_DT is kept
        p = x + np.r_[0.01 * k, np.zeros(12)]
        ref = Reference(x=p, u=[9.0, 0, 0, 0], t=0.02 * k, stamp=0.02 * k)
        assert scene.messages("reference", ref.to_wire()) == []
    assert "reference" in dict(scene.messages("state", _state(1.0).to_wire()))
    points = scene.reference  # what that scene draws
    assert points.shape == (int(0.02 * 29 / PATH_DT) + 1, 3)
    assert tuple(points[0]) == (0.0, 0.0, 1.5) and points[-1, 0] == pytest.approx(0.25)


class _Bus:
    """What the recorder and the live server need of a bus: subscriptions kept."""

    def __init__(self):
        self.subscribed = {}

    def key(self, topic):
        return f"arcade/quad1/{topic}"

    def subscribe(self, topic, callback, check_order=True):
        self.subscribed[topic] = callback


def _decoded(path):
    """``topic -> [(log_time, decoded message)]`` of the Foxglove channels of an MCAP file,
    decoded from the schemas the file holds (as Foxglove reads them)."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        topics = [c.topic for c in reader.get_summary().channels.values()]
        ours = [t for t in topics if "/foxglove/" in t]
        for schema, channel, _, decoded in reader.iter_decoded_messages(topics=ours):
            assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf"
            out.setdefault(channel.topic, []).append((schema.name, decoded))
    return out


def test_the_recorder_writes_foxglove_channels_that_decode_to_the_state(tmp_path):
    from services.recorder import Recorder

    rec = Recorder(argparse.Namespace(out=tmp_path, incarnation=0, vehicle="quad1", geofence=FENCE))
    rec.setup(_Bus())
    rec.scene.set_reference(PATH)
    for k in range(30):
        rec.record("state", _state(5.0 + 0.05 * k))
        if k == 19:  # the release at 6.0 s, recorded before the frame captured at 5.95 s
            rec.record("event", RELEASED.replace(stamp=6.0))
        for frame in _capture(5.0 + 0.05 * k):
            rec.record("mocap", frame)
    rec.teardown()
    got = _decoded(tmp_path / "bus.mcap")
    tf = got["arcade/quad1/foxglove/transform"]
    assert len(tf) == 30 and {name for name, _ in tf} == {"foxglove.FrameTransform"}
    last = tf[-1][1]
    assert (last.parent_frame_id, last.child_frame_id) == ("world", "quad1/body")
    t = last.translation
    np.testing.assert_allclose([t.x, t.y, t.z], [1.0, -2.0, 1.5 + 5.0 + 0.05 * 29])
    r = last.rotation
    np.testing.assert_allclose([r.w, r.x, r.y, r.z], Q_YAW30)
    assert last.timestamp.seconds == 6 and abs(last.timestamp.nanos - 450_000_000) < 10
    pose = got["arcade/quad1/foxglove/pose"][-1][1]
    assert pose.frame_id == "world" and pose.pose.position.z == pytest.approx(t.z)
    vehicle = got["arcade/quad1/foxglove/vehicle"]
    assert len(vehicle) == 30 and vehicle[0][0] == "foxglove.SceneUpdate"
    body = vehicle[-1][1].entities[0]
    assert body.frame_id == "quad1/body" and body.frame_locked
    assert len(body.cylinders) == 4 and len(body.cubes) == 1
    ref = got["arcade/quad1/foxglove/reference"]
    assert len(ref) == 2  # at 5.0 s and 6.0 s
    line = ref[0][1].entities[0].lines[0]
    np.testing.assert_allclose([[p.x, p.y, p.z] for p in line.points], PATH)
    fence = got["arcade/quad1/foxglove/geofence"][0][1].entities[0].lines[0]
    corners = np.array([[p.x, p.y, p.z] for p in fence.points])
    assert len(corners) == 24
    np.testing.assert_allclose(corners.min(0), [-5, -4, -0.5])
    np.testing.assert_allclose(corners.max(0), [5, 4, 3])
    payload = got["arcade/quad1/foxglove/payload"]
    assert len(payload) == len(got["arcade/quad1/foxglove/payload_transform"]) == 30
    assert {name for name, _ in payload} == {"foxglove.SceneUpdate"}
    cables = [len(update.entities[0].lines) for _, update in payload]
    assert cables == [1] * 20 + [0] * 10  # hanging until the release event
    sphere = payload[0][1].entities[0].spheres[0].pose.position
    assert sphere.z == pytest.approx(1.5 + 5.0 - 0.6)
    assert rec.stats["foxglove_messages"] == 30 * 3 + 2 * 2 + 30 * 2


def test_the_live_server_sends_the_channels_to_a_websocket_client():
    """Foxglove's WebSocket protocol: the client subscribes to the advertised channels and
    receives the vehicle's transform and scene as protobuf that decodes with the schema."""
    import websockets
    from mcap.records import Schema
    from mcap_protobuf.decoder import DecoderFactory

    from arcade_io.foxglove_scene import CHANNELS
    from services.foxglove_live import FoxgloveLive

    args = argparse.Namespace(
        out=None, vehicle="quad1", geofence=FENCE, host="127.0.0.1", port=0, lockstep=True
    )
    live = FoxgloveLive(args)
    bus = _Bus()
    live.setup(bus)
    try:

        async def client():
            url = f"ws://127.0.0.1:{live.server.port}"
            async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"]) as ws:
                channels = {}
                while len(channels) < len(CHANNELS):
                    msg = json.loads(await asyncio.wait_for(ws.recv(), 5))
                    if msg["op"] == "advertise":
                        channels.update({c["topic"]: c for c in msg["channels"]})
                wanted = [f"arcade/quad1/foxglove/{n}" for n in ("transform", "vehicle", "payload")]
                subs = [{"id": i, "channelId": channels[t]["id"]} for i, t in enumerate(wanted)]
                await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                got = {}
                k = 0
                while len(got) < 3:
                    await asyncio.sleep(0.05)  # the subscription reaches the server
                    bus.subscribed["state"](_state(1.0 + 0.05 * k))
                    for frame in _capture(1.0 + 0.05 * k):
                        bus.subscribed["mocap"](frame)
                    k += 1
                    try:
                        while True:
                            frame = await asyncio.wait_for(ws.recv(), 0.2)
                            if isinstance(frame, bytes) and frame[0] == 1:  # message data
                                sub = int.from_bytes(frame[1:5], "little")
                                got.setdefault(wanted[sub], frame[13:])
                    except TimeoutError:
                        pass
                    assert k < 50, "no message data from the server"
                return channels, got

        channels, got = asyncio.run(client())
    finally:
        live.teardown()
    factory = DecoderFactory()
    decoded = {}
    for i, (topic, payload) in enumerate(got.items()):
        c = channels[topic]
        assert c["encoding"] == "protobuf" and c["schemaEncoding"] == "protobuf"
        schema = Schema(
            id=i + 1, name=c["schemaName"], encoding="protobuf", data=base64.b64decode(c["schema"])
        )
        decoded[topic] = factory.decoder_for("protobuf", schema)(payload)
    tf = decoded["arcade/quad1/foxglove/transform"]
    assert tf.child_frame_id == "quad1/body" and tf.translation.x == 1.0
    assert decoded["arcade/quad1/foxglove/vehicle"].entities[0].id == "vehicle"
    payload = decoded["arcade/quad1/foxglove/payload"].entities[0]
    assert payload.id == "payload" and len(payload.spheres) == len(payload.lines) == 1
    assert live.stats["messages"]["transform"] >= 1


def test_the_stack_starts_the_live_service_with_the_bridges_geofence(tmp_path):
    """``arcade up --foxglove PORT``: one more process, given the port; in the px4 profile
    it and the recorder draw the bridge's geofence."""
    from deploy.launcher import StackConfig
    from deploy.px4_profile import Px4StackConfig

    assert "foxglove" not in StackConfig(out=tmp_path).services()
    cfg = StackConfig(out=tmp_path, foxglove_port=0, speed=1.5)
    assert cfg.services()[-2:] == ("foxglove", "sim")  # before the vehicle: it sees it all
    args = cfg.args("foxglove")
    assert args[args.index("--port") + 1] == "0"
    # The path drawn is the controller's reference records: no plan to compute.
    assert "--speed" not in args and "--speed" not in cfg.args("recorder")
    px4 = Px4StackConfig(out=tmp_path, foxglove_port=8765, bridge_args=["--geofence=-3,3,-3,3,0,3"])
    assert "foxglove" in px4.services()
    for name in ("recorder", "foxglove"):
        assert px4.args(name)[-1] == "--geofence=-3,3,-3,3,0,3"
    # ... and hang the cable from the vehicle's rigid body, as long as its vehicle file says.
    b = ["--vehicle-file", "lab.toml", "--geofence=-3,3,-3,3,0,3"]
    px4 = Px4StackConfig(out=tmp_path, foxglove_port=8765, bridge_args=b, mocap_body="cf1")
    for name in ("recorder", "foxglove"):
        args = px4.args(name)
        assert args[-2:] == ["--vehicle-file=lab.toml", "--geofence=-3,3,-3,3,0,3"]
        assert args[args.index("--mocap-body") + 1] == "cf1"


def test_foxglove_takes_a_tcp_port_or_none(capsys):
    from arcade.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["up"]).foxglove is None
    assert parser.parse_args(["up", "--foxglove"]).foxglove == 8765
    assert parser.parse_args(["demo", "--foxglove", "0"]).foxglove == 0
    for bad in ("70000", "-1", "ws"):
        with pytest.raises(SystemExit) as exit_:
            parser.parse_args(["up", f"--foxglove={bad}"])
        assert exit_.value.code == 2
        assert "not a TCP port" in capsys.readouterr().err
