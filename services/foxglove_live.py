"""Foxglove service: the live flight over the Foxglove WebSocket protocol.

Subscribes ``state`` and serves what :class:`arcade_io.foxglove_scene.FoxgloveScene` makes
of it (the same conversion the recorder writes into ``bus.mcap``): the vehicle's
``foxglove.FrameTransform``, ``foxglove.PoseInFrame`` and ``foxglove.SceneUpdate``, the
reference path and the geofence, on ``arcade/<vehicle>/foxglove/<name>``. Foxglove opens
it as a "Foxglove WebSocket" connection to ``ws://HOST:PORT``. It listens on loopback
unless ``--host`` says otherwise (the server has no authentication: anyone who reaches the
port sees the flight). The server is ``foxglove-sdk``'s; messages go out as they arrive,
with the receive time as their log time.

The reference path is the flight plan's (the plan options, as the controller gets them),
sampled every :data:`PATH_DT` seconds; the geofence is ``--geofence`` (the PX4 bridge's
box by default).
"""

from __future__ import annotations

import argparse
import threading
import time
from typing import Any

import numpy as np

from services import options, runtime
from services.px4_bridge_options import DEFAULT_GEOFENCE

#: Sampling of the planned path drawn as the reference [s].
PATH_DT = 0.1
#: Foxglove's usual WebSocket port.
DEFAULT_PORT = 8765


def add_scene_arguments(p: argparse.ArgumentParser) -> None:
    """What the scene draws besides the vehicle: the plan (its path) and the geofence."""
    options.add_plan_arguments(p)
    p.add_argument(
        "--geofence",
        default=DEFAULT_GEOFENCE,
        metavar="BOX",
        help="xmin,xmax,ymin,ymax,zmin,zmax of the box drawn as the geofence, ENU metres "
        "('none': not drawn)",
    )


def planned_path(args: argparse.Namespace) -> np.ndarray:
    """Positions ``(n, 3)`` of the flight plan of the plan options, every :data:`PATH_DT`
    (compiled once, then from the persistent compilation cache)."""
    from arcade_io import jaxsetup

    jaxsetup.configure()
    import jax
    import jax.numpy as jnp

    scen = options.scenario(args)
    t_end = args.duration if args.duration is not None else scen.t_end
    times = jnp.arange(0.0, t_end + PATH_DT / 2, PATH_DT)
    return np.asarray(jax.jit(jax.vmap(scen.path().position))(times), dtype=float)


def scene_for(args: argparse.Namespace, log: Any = None) -> Any:
    """The :class:`~arcade_io.foxglove_scene.FoxgloveScene` of these options. The planned
    path is computed in a thread (JAX: about 1 s of CPU, off the start-up path); the
    scene draws it from the next second of stamps on. Options without a plan (a recorder
    built in a test): no path; without ``geofence``: no fence."""
    from arcade_core.px4_command import Geofence
    from arcade_io.foxglove_scene import FoxgloveScene

    fence = None
    box = getattr(args, "geofence", "none")
    if str(box).lower() != "none":
        g = Geofence.parse(box)
        fence = (g.lo, g.hi)
    scene = FoxgloveScene(getattr(args, "vehicle", "default"), None, fence)
    if getattr(args, "speed", None) is not None:

        def compute() -> None:
            try:
                scene.set_reference(planned_path(args))
            except Exception:  # a drawing aid: the flight and the log go on without it
                if log is not None:
                    log.exception("could not compute the planned path: not drawn")

        threading.Thread(target=compute, daemon=True, name="planned-path").start()
    return scene


class FoxgloveLive(runtime.Service):
    """Foxglove: the live flight over the Foxglove WebSocket protocol."""

    name = "foxglove"
    uses_jax = False  # the planned path only, computed once in a thread

    def setup(self, bus) -> None:
        import foxglove

        from arcade_io.foxglove_scene import CHANNELS

        a = self.args
        self.scene = scene_for(a, self.log)
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
        bus.subscribe("state", self.on_state)

    def ready(self) -> None:
        self.event(
            "info",
            f"Foxglove: open ws://{self.args.host}:{self.server.port}",
            port=self.server.port,
        )

    def on_state(self, s) -> None:
        with self._lock:
            for name, msg in self.scene.messages("state", s.to_wire()):
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
