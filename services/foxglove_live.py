"""Foxglove service: the live flight over the Foxglove WebSocket protocol.

Subscribes ``state``, ``reference``, ``mocap`` and ``event`` and serves what
:class:`arcade_io.foxglove_scene.FoxgloveScene` makes of them (the same conversion the
recorder writes into ``bus.mcap``): the vehicle's ``foxglove.FrameTransform``,
``foxglove.PoseInFrame`` and ``foxglove.SceneUpdate``, the payload (its transform, a sphere
and the cable while it hangs), the reference path and the geofence, on
``arcade/<vehicle>/foxglove/<name>``. Foxglove opens
it as a "Foxglove WebSocket" connection to ``ws://HOST:PORT``. It listens on loopback
unless ``--host`` says otherwise (the server has no authentication: anyone who reaches the
port sees the flight). The server is ``foxglove-sdk``'s; messages go out as they arrive,
with the receive time as their log time.

The reference path is the controller's reference flown so far (its ``reference`` records);
the geofence is ``--geofence`` (the PX4 bridge's box by default); the cable hangs from the
vehicle's rigid body ``--mocap-body``, as long as ``--vehicle-file`` says.
"""

from __future__ import annotations

import argparse
import threading
import time
from typing import Any

from services import options, runtime
from services.messages import VEHICLE_BODY
from services.px4_bridge_options import DEFAULT_GEOFENCE

#: Foxglove's usual WebSocket port.
DEFAULT_PORT = 8765


def add_scene_arguments(p: argparse.ArgumentParser) -> None:
    """What the scene draws besides the vehicle and its reference: the geofence, the
    payload's cable (from which rigid body, how long)."""
    p.add_argument(
        "--geofence",
        default=DEFAULT_GEOFENCE,
        metavar="BOX",
        help="xmin,xmax,ymin,ymax,zmin,zmax of the box drawn as the geofence, ENU metres "
        "('none': not drawn)",
    )
    options.add_mocap_body_argument(p)
    p.add_argument(
        "--vehicle-file",
        default=None,
        metavar="FILE",
        help="the vehicle file whose cable the payload hangs on (the cable is drawn while "
        "the payload is within its reach) (default: the shipped vehicle)",
    )


def scene_for(args: argparse.Namespace) -> Any:
    """The :class:`~arcade_io.foxglove_scene.FoxgloveScene` of these options (without
    ``geofence``: no fence; without ``mocap_body`` and ``vehicle_file``: the defaults)."""
    from arcade_core.px4_command import Geofence
    from arcade_io.foxglove_scene import FoxgloveScene
    from arcade_io.vehicle import cable_length_m, load_vehicle

    fence = None
    box = getattr(args, "geofence", "none")
    if str(box).lower() != "none":
        g = Geofence.parse(box)
        fence = (g.lo, g.hi)
    return FoxgloveScene(
        getattr(args, "vehicle", "default"),
        None,
        fence,
        vehicle_body=getattr(args, "mocap_body", VEHICLE_BODY),
        cable_m=cable_length_m(load_vehicle(getattr(args, "vehicle_file", None))),
    )


class FoxgloveLive(runtime.Service):
    """Foxglove: the live flight over the Foxglove WebSocket protocol."""

    name = "foxglove"
    uses_jax = False

    def setup(self, bus) -> None:
        import foxglove

        from arcade_io.foxglove_scene import CHANNELS

        a = self.args
        self.scene = scene_for(a)
        self._lock = threading.Lock()
        self.context = foxglove.Context()
        self.server = foxglove.start_server(
            name=f"arcade {a.vehicle}", host=a.host, port=a.port, context=self.context
        )
        self.channels = {
            name: foxglove.Channel(
                self.scene.topic(name),
                schema=cls.get_schema(),
                message_encoding="protobuf",
                context=self.context,
            )
            for name, cls in CHANNELS.items()
        }
        self.stats.update(port=self.server.port, messages=dict.fromkeys(CHANNELS, 0))
        self.log.info("Foxglove WebSocket server on ws://%s:%d", a.host, self.server.port)
        bus.subscribe("state", self.on_record)
        bus.subscribe("reference", self.on_record)
        # The payload's frames (and the vehicle's), drawn as they come like the recorder
        # does (a jumped mocap clock is the estimator's to judge); events come from several
        # publishers, each with its own clock: no order check on either.
        bus.subscribe("mocap", self.on_record, check_order=False)
        bus.subscribe("event", self.on_record, check_order=False)

    def ready(self) -> None:
        self.event(
            "info",
            f"Foxglove: open ws://{self.args.host}:{self.server.port}",
            port=self.server.port,
        )

    def on_record(self, m) -> None:
        """A ``state``, ``reference``, ``mocap`` or ``event`` record: what the scene draws
        of it (of a reference or an event nothing at once: the path and the cable change)."""
        with self._lock:
            for name, msg in self.scene.messages(m.TOPIC, m.to_wire()):
                self.channels[name].log(msg.encode(), log_time=time.time_ns())
                self.stats["messages"][name] += 1

    def teardown(self) -> None:
        self.server.stop()


def _extra(p: argparse.ArgumentParser) -> None:
    add_scene_arguments(p)
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address the WebSocket server listens on (loopback: this machine only)",
    )
    p.add_argument(
        "--port",
        type=int,
        default=DEFAULT_PORT,
        help="the server's TCP port (0: any free one, said in the log and an info event)",
    )


def main(argv: list[str] | None = None) -> int:
    return runtime.main_for(FoxgloveLive, argv, _extra)
