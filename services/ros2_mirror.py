"""ROS 2 mirror service: the vehicle's state, setpoint, reference and changepoints for ROS 2.

A thin shell: it subscribes to the stack's bus, converts each record to a standard ROS 2
message (:mod:`arcade_io.ros2_messages`) and puts its CDR bytes on the key expression
rmw_zenoh would use, with rmw_zenoh's attachment and a liveliness token per publisher
(:mod:`arcade_io.rmw_zenoh`), so that ``ros2 topic list`` / ``ros2 topic echo`` on a host
running rmw_zenoh (ROS 2 Jazzy or later) see them. Topics, under ``--namespace``
(default ``/arcade/<vehicle>``):

- ``odom`` (``nav_msgs/msg/Odometry``) from ``state``;
- ``setpoint/thrust`` and ``setpoint/body_rates`` (``geometry_msgs/msg/Vector3Stamped``)
  from ``setpoint``;
- ``reference`` (``nav_msgs/msg/Odometry``, child frame ``reference``) from ``reference``,
  when the stack publishes one;
- ``changepoint`` (``diagnostic_msgs/msg/DiagnosticArray``) from the ``changepoint`` events.

The ROS side is its own Zenoh session, as one ROS 2 context is: a peer that connects to
rmw_zenoh's router (``--router``, by default rmw_zenohd's ``tcp/localhost:7447``, retried
until it answers) and whose id names the node in the tokens. Publishers are declared (and
their tokens) before the service's own liveliness token, so a stack that flies has them in
place. docs/ros2.md: the keys and how to see them.
"""

from __future__ import annotations

import argparse
import os
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from arcade_io import ros2_messages as rm
from services import runtime

#: The node's name in the ROS 2 graph.
NODE_NAME = "arcade_mirror"
#: rmw_zenohd's default listening endpoint (rmw_zenoh's default session connects there).
DEFAULT_ROUTER = "tcp/localhost:7447"


@dataclass
class _Output:
    """One ROS 2 publisher: its names, its Zenoh publisher and its sequence number."""

    publication: Any
    publisher: Any
    seq: int = 0


def default_namespace(vehicle: str) -> str:
    """``/arcade/<vehicle>``; ``ValueError`` when the vehicle name is not a ROS 2 name."""
    from arcade_io.rmw_zenoh import check_name

    try:
        return check_name("namespace", f"/arcade/{vehicle}")
    except ValueError:
        raise ValueError(
            f"vehicle name {vehicle!r} makes no ROS 2 namespace (letters, digits, '_')"
        ) from None


#: The ROS 2 topics (relative to the namespace) and their types, in declaration order.
OUTPUTS = {
    "odom": rm.ODOMETRY,
    "setpoint/thrust": rm.VECTOR3_STAMPED,
    "setpoint/body_rates": rm.VECTOR3_STAMPED,
    "changepoint": rm.DIAGNOSTICS,
    "reference": rm.ODOMETRY,
}
#: The bus topic each ROS 2 topic comes from.
SOURCES = {
    "odom": "state",
    "setpoint/thrust": "setpoint",
    "setpoint/body_rates": "setpoint",
    "changepoint": "event",
    "reference": "reference",
}


def ros_messages(topic: str, record: Any, vehicle: str) -> list[tuple[str, Any]]:
    """The ``(ROS 2 topic, message)`` pairs of one record of bus ``topic`` (conversions of
    :mod:`arcade_io.ros2_messages`); none for an event that is not a changepoint.
    ``ValueError`` for a record ROS 2 cannot hold (a stamp past 2038)."""
    if topic == "state":
        return [("odom", rm.odometry(record.stamp, record.x, record.cov_diag))]
    if topic == "reference":  # the planned state, as the state: overlaid in ROS 2's tools
        return [("reference", rm.odometry(record.stamp, record.x, child_frame_id="reference"))]
    if topic == "setpoint":
        return [
            ("setpoint/thrust", rm.thrust_setpoint(record.stamp, record.thrust)),
            ("setpoint/body_rates", rm.rate_setpoint(record.stamp, record.rates)),
        ]
    if topic == "event" and record.kind == "changepoint":
        data = {**record.data, "src": record.src}
        msg = rm.changepoint_diagnostics(
            record.stamp, record.text, record.severity, data, hardware_id=vehicle
        )
        return [("changepoint", msg)]
    return []


class Ros2Mirror(runtime.Service):
    """ROS 2 mirror: state, setpoint, reference and changepoints on rmw_zenoh's keys."""

    name = "ros2"
    uses_jax = False

    def setup(self, bus) -> None:
        import zenoh

        from arcade_io import rmw_zenoh
        from services.bus import peer_config, zenoh_reason
        from services.messages import MESSAGE_TYPES

        try:
            namespace = self.args.namespace or _namespace_of(self.args.vehicle)
            self.ros = zenoh.open(peer_config(None, connect=[self.args.router]))
        except (ValueError, zenoh.ZError) as err:
            why = zenoh_reason(err) if isinstance(err, zenoh.ZError) else str(err)
            raise runtime.BusOpenError(f"ROS 2 side: {why}") from None
        self._lock = threading.Lock()
        self._closed = False
        node = rmw_zenoh.RosNode(
            domain_id=self.args.domain_id,
            zid=str(self.ros.zid()),
            namespace=namespace,
            name=NODE_NAME,
        )
        # a bus topic this version of the stack does not have (no reference) has no output
        outputs = {t: ros_type for t, ros_type in OUTPUTS.items() if SOURCES[t] in MESSAGE_TYPES}
        liveliness = self.ros.liveliness()
        self._tokens = [liveliness.declare_token(node.token())]
        self._outputs: dict[str, _Output] = {}
        for entity_id, (topic, ros_type) in enumerate(outputs.items(), start=1):
            pub = node.publication(entity_id, topic, ros_type, rm.type_hash(ros_type))
            self._outputs[topic] = _Output(pub, self.ros.declare_publisher(pub.key))
            self._tokens.append(liveliness.declare_token(pub.token))
            self.log.info("ROS 2 %s (%s) on %s", pub.topic, ros_type, pub.key)
        self.stats.update(
            domain_id=node.domain_id,
            namespace=namespace,
            zid=node.zid,
            keys={topic: out.publication.key for topic, out in self._outputs.items()},
            published=dict.fromkeys(self._outputs, 0),
            unconverted=0,
        )
        for source in dict.fromkeys(SOURCES[t] for t in self._outputs):
            bus.subscribe(source, lambda record, source=source: self.mirror(source, record))

    def warmup(self) -> None:
        """Convert and encode one message of each kind: the first state is then not late
        by the imports and the type store's set-up."""
        from services.messages import Event, Setpoint, State

        x = np.r_[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        samples = {
            "state": State(x=x, stamp=0.0, cov_diag=np.zeros(13)),
            "setpoint": Setpoint(u=[0.0, 0.0, 0.0, 0.0], state_seq=0, stamp=0.0),
            "event": Event(kind="changepoint", stamp=0.0),
        }
        for topic, record in samples.items():
            for ros_topic, message in ros_messages(topic, record, self.args.vehicle):
                rm.cdr(message, OUTPUTS[ros_topic])

    def mirror(self, topic: str, record: Any) -> None:
        """Convert a record of bus ``topic`` and put each message on its key with rmw_zenoh's
        attachment; a record ROS 2 cannot hold is counted (``unconverted``), not sent."""
        from arcade_io import rmw_zenoh

        try:
            messages = ros_messages(topic, record, self.args.vehicle)
        except ValueError as err:
            with self._lock:
                self.stats["unconverted"] += 1
                first = self.stats["unconverted"] == 1
            if first:
                self.log.warning("not mirrored to ROS 2 (%s): %s", topic, err)
            return
        for ros_topic, message in messages:
            out = self._outputs[ros_topic]
            payload = rm.cdr(message, out.publication.ros_type)
            with self._lock:  # one sequence per publisher, from 1, in put order
                if self._closed:  # the bus may still deliver while the service stops
                    return
                out.seq += 1
                attachment = rmw_zenoh.attachment(out.seq, time.time_ns(), out.publication.gid)
                out.publisher.put(payload, attachment=attachment)
                self.stats["published"][ros_topic] += 1

    def teardown(self) -> None:
        with self._lock:
            self._closed = True
        for token in self._tokens:
            token.undeclare()
        for out in self._outputs.values():
            out.publisher.undeclare()
        self.ros.close()


def _namespace_of(vehicle: str) -> str:
    try:
        return default_namespace(vehicle)
    except ValueError as err:
        raise ValueError(f"{err}: give one with --namespace") from None


def _domain_id(text: str) -> int:
    from arcade_io.rmw_zenoh import check_domain_id

    try:
        return check_domain_id(int(text))
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _namespace(text: str) -> str:
    from arcade_io.rmw_zenoh import check_name

    try:
        return check_name("namespace", text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _extra(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--domain-id",
        type=_domain_id,
        default=os.environ.get("ROS_DOMAIN_ID") or "0",  # parsed (and checked) by type
        metavar="N",
        help="ROS 2 domain id, 0-232 (default: $ROS_DOMAIN_ID, else 0; now %(default)s)",
    )
    p.add_argument(
        "--namespace",
        type=_namespace,
        default=None,
        metavar="NS",
        help="ROS 2 namespace of the node and its topics (default: /arcade/<vehicle>)",
    )
    p.add_argument(
        "--router",
        default=DEFAULT_ROUTER,
        metavar="ENDPOINT",
        help="Zenoh endpoint the ROS 2 side connects to, retried until it answers: the "
        "rmw_zenohd router of the ROS 2 hosts (default: %(default)s)",
    )


def main(argv: list[str] | None = None) -> int:
    return runtime.main_for(Ros2Mirror, argv, _extra)
