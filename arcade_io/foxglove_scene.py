"""The bus's records as Foxglove's well-known schemas, for the 3D panel without set-up.

One conversion for every writer of them: the recorder (``bus.mcap``) and the live
WebSocket server (``arcade up --foxglove``) both call :meth:`FoxgloveScene.messages` with
each record's wire map (``Message.to_wire()``: plain numbers and lists) and write what it
returns on the channels of :data:`CHANNELS` (``arcade/<vehicle>/foxglove/<name>``,
protobuf, the schemas of ``foxglove-sdk``).

Per ``state`` (world ENU, body FLU, SI; quaternion ``w`` first on the bus, ``x, y, z, w``
in Foxglove):

- ``transform``: ``foxglove.FrameTransform`` world -> ``<vehicle>/body``;
- ``pose``: ``foxglove.PoseInFrame`` of the body in the world frame;
- ``vehicle``: ``foxglove.SceneUpdate``, the airframe (body, four rotors, a thrust-axis
  arrow) locked to the body frame.

Every :data:`STATIC_EVERY_S` seconds of state stamps (from the first state on):
``reference`` (the controller's reference flown so far, from its ``reference`` records, as
a line strip, world frame) and ``geofence`` (the box's twelve edges), so that a player that
seeks into the log shows them too.

Per ``mocap`` frame of the payload (body ``payload``; stamped with its capture time):

- ``payload_transform``: ``foxglove.FrameTransform`` world -> ``<vehicle>/payload``;
- ``payload``: ``foxglove.SceneUpdate``, entity ``payload`` in the world frame: a sphere of
  the payload's size (:data:`~arcade_io.vehicle.PAYLOAD_RADIUS_M`) at its pose and, while
  it hangs, the cable: a line from the vehicle's frame of the same capture (the vehicle's
  rigid body, default ``vehicle``; :data:`ANCHOR_AGE_S`) to the payload. It hangs while

  - the release was not seen: the release is the ``event`` whose data holds
    ``payload="released"`` (the simulator's, stamped on the frames' clock); frames captured
    from its stamp on have no line, those captured before keep it, also when they arrive
    after the event (which travels at a lower priority than the frames);
  - and the payload is within the cable's reach of the vehicle's origin (the cable's length
    plus :data:`REACH_MARGIN_M`): a drawing that starts after the release (a Foxglove
    server or recorder that joins or restarts late never sees the event) draws no cable to
    a payload lying on the floor.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from foxglove import messages as fm

from arcade_io.vehicle import (
    DEFAULT_CABLE_LENGTH_M,
    PAYLOAD_BODY,
    PAYLOAD_RADIUS_M,
    PAYLOAD_RELEASED,
    VEHICLE_BODY,
)

#: Channel name -> Foxglove message type (the topic is ``arcade/<vehicle>/foxglove/<name>``).
CHANNELS: Mapping[str, Any] = {
    "transform": fm.FrameTransform,
    "pose": fm.PoseInFrame,
    "vehicle": fm.SceneUpdate,
    "reference": fm.SceneUpdate,
    "geofence": fm.SceneUpdate,
    "payload_transform": fm.FrameTransform,
    "payload": fm.SceneUpdate,
}
#: The cable hangs from the vehicle's frame captured at most this long from the payload's
#: [s] (a mocap system sends both of one capture with the same stamp).
ANCHOR_AGE_S = 0.05
#: How much farther than the cable's length the payload's centre may be from the vehicle's
#: origin and still hang from it [m]: the electromagnet under the airframe, the payload's
#: radius, the cable's give (the simulated vehicle's payload hangs 0.55 m from it on a
#: 0.5 m cable, at most 0.57 m when swung hard).
REACH_MARGIN_M = 0.15
#: The world frame's id (ENU).
WORLD = "world"
#: The static scenes (reference path, geofence) are sent again this often [s of stamps].
STATIC_EVERY_S = 1.0
#: Spacing of the reference path's points [s], and how many it keeps at most.
PATH_DT = 0.1
PATH_POINTS = 4096
#: Airframe drawn for the vehicle: arm length (centre to rotor) and rotor radius [m].
ARM_M, ROTOR_M = 0.12, 0.06


def topic(vehicle: str, name: str) -> str:
    """The topic of channel ``name`` of ``vehicle``."""
    return f"arcade/{vehicle}/foxglove/{name}"


def body_frame(vehicle: str) -> str:
    """The vehicle's body frame id (FLU)."""
    return f"{vehicle}/body"


def payload_frame(vehicle: str) -> str:
    """The frame id of the vehicle's payload."""
    return f"{vehicle}/payload"


def timestamp(stamp: float) -> fm.Timestamp:
    sec = int(np.floor(stamp))
    return fm.Timestamp(sec, min(round((stamp - sec) * 1e9), 999_999_999))


def _vec(v: Sequence[float]) -> fm.Vector3:
    return fm.Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _quat(q_wxyz: Sequence[float]) -> fm.Quaternion:
    w, x, y, z = (float(c) for c in q_wxyz)
    return fm.Quaternion(x=x, y=y, z=z, w=w)


def _pose(p: Sequence[float] = (0.0, 0.0, 0.0), q_wxyz=(1.0, 0.0, 0.0, 0.0)) -> fm.Pose:
    return fm.Pose(position=_vec(p), orientation=_quat(q_wxyz))


def _color(r: float, g: float, b: float, a: float = 1.0) -> fm.Color:
    return fm.Color(r=r, g=g, b=b, a=a)


def _points(points: np.ndarray) -> list[fm.Point3]:
    return [fm.Point3(x=float(x), y=float(y), z=float(z)) for x, y, z in points]


def vehicle_scene(vehicle: str, stamp: float) -> fm.SceneUpdate:
    """The airframe in the body frame (FLU): a flat body, four rotors on the diagonals
    and an arrow along the thrust axis (body z)."""
    grey, rotor = _color(0.3, 0.3, 0.35), _color(0.1, 0.6, 0.9, 0.7)
    arm = ARM_M / np.sqrt(2.0)
    rotors = [
        fm.CylinderPrimitive(
            pose=_pose((sx * arm, sy * arm, 0.03)),
            size=fm.Vector3(x=2 * ROTOR_M, y=2 * ROTOR_M, z=0.01),
            bottom_scale=1.0,
            top_scale=1.0,
            color=rotor,
        )
        for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1))
    ]
    up = (np.cos(np.pi / 4), 0.0, -np.sin(np.pi / 4), 0.0)  # +x rotated onto +z (about y)
    entity = fm.SceneEntity(
        timestamp=timestamp(stamp),
        frame_id=body_frame(vehicle),
        id="vehicle",
        frame_locked=True,
        cubes=[fm.CubePrimitive(pose=_pose(), size=fm.Vector3(x=0.1, y=0.1, z=0.04), color=grey)],
        cylinders=rotors,
        arrows=[
            fm.ArrowPrimitive(
                pose=_pose((0.0, 0.0, 0.02), up),
                shaft_length=0.15,
                shaft_diameter=0.01,
                head_length=0.04,
                head_diameter=0.03,
                color=_color(0.9, 0.3, 0.1),
            )
        ],
    )
    return fm.SceneUpdate(entities=[entity])


def payload_scene(
    stamp: float, position: Sequence[float], q_wxyz: Sequence[float], anchor: Any | None
) -> fm.SceneUpdate:
    """The payload as a sphere at its pose (world frame) and, with an ``anchor`` (where the
    cable hangs from, m), the cable from there to the payload."""
    amber, d = _color(0.95, 0.65, 0.1), 2.0 * PAYLOAD_RADIUS_M
    sphere = fm.SpherePrimitive(
        pose=_pose(position, q_wxyz), size=fm.Vector3(x=d, y=d, z=d), color=amber
    )
    cable = []
    if anchor is not None:
        cable = [
            fm.LinePrimitive(
                type=fm.LinePrimitiveLineType.LineStrip,
                pose=_pose(),
                thickness=1.5,
                scale_invariant=True,
                points=_points(np.array([anchor, position], dtype=float)),
                color=_color(0.2, 0.2, 0.2),
            )
        ]
    entity = fm.SceneEntity(
        timestamp=timestamp(stamp), frame_id=WORLD, id="payload", spheres=[sphere], lines=cable
    )
    return fm.SceneUpdate(entities=[entity])


def line_scene(
    stamp: float, entity_id: str, points: np.ndarray, line_type: Any, color: fm.Color
) -> fm.SceneUpdate:
    """One entity of lines in the world frame (``points`` ``(n, 3)`` m, ENU)."""
    line = fm.LinePrimitive(
        type=line_type,
        pose=_pose(),
        thickness=2.0,
        scale_invariant=True,
        points=_points(np.asarray(points, dtype=float).reshape(-1, 3)),
        color=color,
    )
    entity = fm.SceneEntity(timestamp=timestamp(stamp), frame_id=WORLD, id=entity_id, lines=[line])
    return fm.SceneUpdate(entities=[entity])


def box_edges(lo: Sequence[float], hi: Sequence[float]) -> np.ndarray:
    """The twelve edges of the axis-aligned box ``lo``-``hi`` as 24 points (a line list)."""
    corners = np.array([[(lo, hi)[(i >> k) & 1][k] for k in range(3)] for i in range(8)])
    edges = [(i, i | 1 << k) for i in range(8) for k in range(3) if not i >> k & 1]
    return np.array([corners[j] for edge in edges for j in edge])


class FoxgloveScene:
    """The Foxglove messages of one vehicle's bus records.

    ``reference``: a reference path ``(n, 3)`` [m] to start from (None: the ``reference``
    records draw it as they come); ``geofence``: the
    box ``(lo, hi)`` [m] (None: not drawn); ``vehicle_body``: the vehicle's rigid body on
    the ``mocap`` topic; ``cable_m``: the payload's cable [m]. :meth:`messages` is for one
    caller at a time.
    """

    def __init__(
        self,
        vehicle: str,
        reference: np.ndarray | None = None,
        geofence: tuple[Sequence[float], Sequence[float]] | None = None,
        *,
        vehicle_body: str = VEHICLE_BODY,
        cable_m: float = DEFAULT_CABLE_LENGTH_M,
    ):
        self.vehicle = vehicle
        self.vehicle_body = vehicle_body
        #: The farthest the payload hangs from the vehicle's origin [m].
        self.reach = cable_m + REACH_MARGIN_M
        self.reference: np.ndarray | None = None
        self.set_reference(reference)
        self.geofence = geofence
        self._static_at = -np.inf  # stamp of the last static scenes
        self._trail_at = -np.inf  # stamp of the newest reference point kept
        self._vehicle_at: tuple[float, list[float]] | None = None  # newest vehicle frame
        #: Stamp of the payload's release (the cable is drawn for frames captured before).
        self.released_at = np.inf

    def set_reference(self, reference: np.ndarray | None) -> None:
        """The reference path ``(n, 3)`` [m] (None: none); drawn from the next static
        scenes on."""
        self.reference = None if reference is None else np.asarray(reference, dtype=float)
        self._trail = [] if reference is None else list(self.reference)

    def add_reference(self, stamp: float, position: Sequence[float]) -> None:
        """The controller's reference at ``stamp`` (a ``reference`` record): the path drawn
        is the reference flown so far, a point every :data:`PATH_DT` s (at most
        :data:`PATH_POINTS`, then every other one)."""
        if stamp - self._trail_at < PATH_DT - 1e-9:  # stamps a period apart, rounded
            return
        self._trail_at = stamp
        self._trail.append(np.asarray(position, dtype=float)[:3])
        if len(self._trail) > PATH_POINTS:
            self._trail = self._trail[::2]
        self.reference = np.array(self._trail)

    def topic(self, name: str) -> str:
        return topic(self.vehicle, name)

    def messages(self, kind: str, wire: Mapping[str, Any]) -> list[tuple[str, Any]]:
        """``(channel name, Foxglove message)`` for the record ``wire`` of topic ``kind``
        (``"state"``, ...); records without a Foxglove form give none."""
        if kind == "reference":
            self.add_reference(float(wire["stamp"]), wire["x"])
            return []
        if kind == "mocap":
            return self.mocap(wire)
        if kind == "event":
            if (wire.get("data") or {}).get("payload") == PAYLOAD_RELEASED:
                self.released_at = min(self.released_at, float(wire["stamp"]))
            return []
        if kind != "state":
            return []
        stamp = float(wire["stamp"])
        x = np.asarray(wire["x"], dtype=float)
        p, q = x[0:3], x[6:10]
        ts = timestamp(stamp)
        out: list[tuple[str, Any]] = [
            (
                "transform",
                fm.FrameTransform(
                    timestamp=ts,
                    parent_frame_id=WORLD,
                    child_frame_id=body_frame(self.vehicle),
                    translation=_vec(p),
                    rotation=_quat(q),
                ),
            ),
            ("pose", fm.PoseInFrame(timestamp=ts, frame_id=WORLD, pose=_pose(p, q))),
            ("vehicle", vehicle_scene(self.vehicle, stamp)),
        ]
        if abs(stamp - self._static_at) >= STATIC_EVERY_S:
            self._static_at = stamp
            out += self.static(stamp)
        return out

    def mocap(self, wire: Mapping[str, Any]) -> list[tuple[str, Any]]:
        """A ``mocap`` frame: the payload's is drawn, the vehicle's kept as the cable's
        anchor for the payload's frame of the same capture."""
        stamp, p = float(wire["capture_stamp"]), wire["position"]
        if wire["body"] == self.vehicle_body:
            self._vehicle_at = (stamp, p)
            return []
        if wire["body"] != PAYLOAD_BODY:
            return []
        q = wire["quaternion"]
        v = self._vehicle_at
        hangs = (
            v is not None
            and abs(v[0] - stamp) <= ANCHOR_AGE_S
            and stamp < self.released_at
            and float(np.linalg.norm(np.subtract(p, v[1]))) <= self.reach
        )
        anchor = v[1] if hangs else None
        tf = fm.FrameTransform(
            timestamp=timestamp(stamp),
            parent_frame_id=WORLD,
            child_frame_id=payload_frame(self.vehicle),
            translation=_vec(p),
            rotation=_quat(q),
        )
        return [("payload_transform", tf), ("payload", payload_scene(stamp, p, q, anchor))]

    def static(self, stamp: float) -> list[tuple[str, Any]]:
        """The reference path and the geofence at ``stamp`` (those that are known)."""
        out: list[tuple[str, Any]] = []
        path = self.reference  # set by another thread, maybe
        if path is not None and len(path):
            green = _color(0.2, 0.8, 0.3)
            strip = fm.LinePrimitiveLineType.LineStrip
            out.append(("reference", line_scene(stamp, "reference", path, strip, green)))
        if self.geofence is not None:
            edges = box_edges(*self.geofence)
            red, pairs = _color(0.9, 0.2, 0.2, 0.8), fm.LinePrimitiveLineType.LineList
            out.append(("geofence", line_scene(stamp, "geofence", edges, pairs, red)))
        return out
