"""rmw_zenoh's names on a Zenoh network: topic keys, liveliness tokens, QoS, attachments.

What a ROS 2 host that runs rmw_zenoh (``RMW_IMPLEMENTATION=rmw_zenoh_cpp``, ROS 2 Jazzy and
later) expects of a publisher on the same Zenoh network, so that ``ros2 topic list`` and
``ros2 topic echo`` see it. Followed exactly from ros2/rmw_zenoh (branch ``rolling``):
``docs/design.md`` at commit 99a6a2bd10b949052f4f12c5854825dc005e95a5, and the code it
describes, ``rmw_zenoh_cpp/src/detail/liveliness_utils.cpp`` at 3411fdec149f,
``attachment_helpers.cpp`` at 534747dca92a, ``qos.cpp`` at 7efeee2b9009 and
``rmw_publisher_data.cpp`` at 3e19ec730c52:

- topic key: ``<domain_id>/<fully qualified topic name without its leading '/'>/<type
  name>/<type hash>``, e.g. ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df66...``;
  the type name as DDS declares it (``pkg::msg::dds_::Name_``), the type hash REP-2016's
  ``RIHS01_<sha256 hex>`` (:mod:`arcade_io.ros2_messages` computes it);
- liveliness token of a node:
  ``@ros2_lv/<domain_id>/<zid>/<node_id>/<node_id>/NN/<enclave>/<namespace>/<node_name>``;
- of a publisher: ``@ros2_lv/<domain_id>/<zid>/<node_id>/<entity_id>/MP/<enclave>/
  <namespace>/<node_name>/<topic>/<type name>/<type hash>/<qos>``, where enclave, namespace
  and topic are *mangled*: every ``/`` replaced by ``%`` (the root namespace ``/`` is ``%``);
- ``<qos>``: ``reliability:durability:history,depth:deadline_s,deadline_ns:lifespan_s,
  lifespan_ns:liveliness,lease_s,lease_ns``, each field empty where it equals rmw_zenoh's
  default (reliable, volatile, keep-last, depth 42, infinite durations, automatic), else
  the number of its ``rmw_qos_*`` enumerator; a keep-last depth-10 publisher is
  ``::,10:,:,:,,``;
- the entity's GID: the 128-bit XXH3 hash of its token, low 64 bits first, each half in
  little-endian byte order (``Entity::Entity``); a publisher sends its entity's GID;
- every sample's attachment (33 bytes): the sequence number (int64, little-endian, from 1),
  the source timestamp (int64 ns since the UNIX epoch, little-endian), the GID's length
  (one byte, 16) and the 16 GID bytes (zenoh-ext's serialisation of ``int64, int64,
  std::array<uint8_t, 16>``).

I/O-free: strings and bytes only; the service (:mod:`services.ros2_mirror`) declares them.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

__all__ = [
    "ADMIN_SPACE",
    "DEFAULT_QOS",
    "GID_SIZE",
    "RosNode",
    "RosPublication",
    "RosQoS",
    "attachment",
    "check_domain_id",
    "check_name",
    "dds_type_name",
    "entity_gid",
    "mangle",
    "parse_attachment",
    "qos_keyexpr",
    "topic_key",
]

ADMIN_SPACE = "@ros2_lv"
#: ``RMW_GID_STORAGE_SIZE``.
GID_SIZE = 16
#: ``RMW_DURATION_INFINITE``: seconds, nanoseconds.
INFINITE = (9223372036, 854775807)

# rmw/types.h enumerators.
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
AUTOMATIC = 1

#: ROS 2 domain ids (the DDS port mapping's range; rmw_zenoh takes any, ROS tools not).
MAX_DOMAIN_ID = 232
_TOKEN = r"[A-Za-z_][A-Za-z0-9_]*"
_FQ_NAME = re.compile(rf"(/{_TOKEN})+")
_NODE = re.compile(_TOKEN)
_TYPE = re.compile(rf"({_TOKEN})/msg/({_TOKEN})")


@dataclass(frozen=True)
class RosQoS:
    """A publisher's QoS profile (``rmw_qos_profile_t``), as rmw_zenoh adapts it."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 10
    deadline: tuple[int, int] = INFINITE
    lifespan: tuple[int, int] = INFINITE
    liveliness: int = AUTOMATIC
    lease: tuple[int, int] = INFINITE


#: rmw_zenoh's defaults (``QoS::QoS`` in qos.cpp): the fields left empty in a token.
DEFAULT_QOS = RosQoS(depth=42)


def qos_keyexpr(qos: RosQoS) -> str:
    """The ``<qos>`` chunk of a token (``qos_to_keyexpr``)."""
    d = DEFAULT_QOS

    def field(value: object, default: object) -> str:
        return "" if value == default else str(value)

    return ":".join(
        [
            field(qos.reliability, d.reliability),
            field(qos.durability, d.durability),
            f"{field(qos.history, d.history)},{field(qos.depth, d.depth)}",
            ",".join(field(a, b) for a, b in zip(qos.deadline, d.deadline)),
            ",".join(field(a, b) for a, b in zip(qos.lifespan, d.lifespan)),
            ",".join(
                [field(qos.liveliness, d.liveliness)]
                + [field(a, b) for a, b in zip(qos.lease, d.lease)]
            ),
        ]
    )


def check_name(kind: str, name: str) -> str:
    """``name`` if it is a valid ROS 2 ``kind`` (``namespace``, ``topic``: fully qualified,
    ``/a/b``; ``node``: one token), else ``ValueError`` saying what a valid one is."""
    if kind == "node":
        ok = isinstance(name, str) and _NODE.fullmatch(name) is not None
        rule = "letters, digits and '_', not starting with a digit"
    else:
        root = kind == "namespace" and name == "/"
        ok = isinstance(name, str) and (root or _FQ_NAME.fullmatch(name) is not None)
        rule = "'/'-separated tokens of letters, digits and '_', each not starting with a digit"
    if not ok:
        raise ValueError(f"invalid ROS 2 {kind} name {name!r} ({rule})")
    return name


def check_domain_id(domain_id: int) -> int:
    """``domain_id`` if it is a ROS 2 domain id (0 to 232), else ``ValueError``."""
    if not (isinstance(domain_id, int) and 0 <= domain_id <= MAX_DOMAIN_ID):
        raise ValueError(f"ROS 2 domain id {domain_id!r}: an integer from 0 to {MAX_DOMAIN_ID}")
    return domain_id


def mangle(name: str) -> str:
    """A name as one key chunk: every ``/`` replaced by ``%`` (``mangle_name``)."""
    return name.replace("/", "%")


def dds_type_name(ros_type: str) -> str:
    """``nav_msgs/msg/Odometry`` -> ``nav_msgs::msg::dds_::Odometry_`` (the name DDS
    declares, which rmw_zenoh puts in keys and tokens)."""
    m = _TYPE.fullmatch(ros_type)
    if m is None:
        raise ValueError(f"not a ROS 2 message type name (pkg/msg/Name): {ros_type!r}")
    return f"{m.group(1)}::msg::dds_::{m.group(2)}_"


def topic_key(domain_id: int, topic: str, type_name: str, type_hash: str) -> str:
    """The key expression samples of ``topic`` are put on (``TopicInfo::TopicInfo``)."""
    return f"{domain_id}/{topic.strip('/')}/{type_name}/{type_hash}"


def entity_gid(token: str) -> bytes:
    """The 16-byte GID rmw_zenoh derives from an entity's liveliness token."""
    import xxhash

    digest = xxhash.xxh3_128_intdigest(token.encode())
    low, high = digest & (2**64 - 1), digest >> 64
    return struct.pack("<QQ", low, high)


def attachment(seq: int, timestamp_ns: int, gid: bytes) -> bytes:
    """The attachment of one sample: sequence number, source timestamp, GID."""
    if len(gid) != GID_SIZE:
        raise ValueError(f"a GID has {GID_SIZE} bytes, not {len(gid)}")
    return struct.pack("<qqB", seq, timestamp_ns, GID_SIZE) + bytes(gid)


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """``(seq, timestamp_ns, gid)`` of an attachment; ``ValueError`` if it is not one."""
    if len(data) != 17 + GID_SIZE or data[16] != GID_SIZE:
        raise ValueError(f"not an rmw_zenoh attachment ({len(data)} bytes)")
    seq, stamp = struct.unpack_from("<qq", data)
    return seq, stamp, bytes(data[17:])


@dataclass(frozen=True)
class RosPublication:
    """One publisher as rmw_zenoh names it: its sample key, its token and its GID."""

    topic: str
    ros_type: str
    key: str
    token: str
    gid: bytes


@dataclass(frozen=True)
class RosNode:
    """A ROS 2 node of one Zenoh session (``zid``: the session's id as Zenoh prints it)."""

    domain_id: int
    zid: str
    namespace: str
    name: str
    node_id: int = 0
    enclave: str = "/"

    def __post_init__(self) -> None:
        check_domain_id(self.domain_id)
        check_name("namespace", self.namespace)
        check_name("node", self.name)
        if not self.zid or "/" in self.zid:
            raise ValueError(f"invalid Zenoh session id {self.zid!r}")

    def _head(self, entity_id: int, kind: str) -> str:
        return "/".join(
            [
                ADMIN_SPACE,
                str(self.domain_id),
                self.zid,
                str(self.node_id),
                str(entity_id),
                kind,
                mangle(self.enclave),
                mangle(self.namespace),
                self.name,
            ]
        )

    def token(self) -> str:
        """The node's own liveliness token (entity kind ``NN``)."""
        return self._head(self.node_id, "NN")

    def topic_name(self, relative: str) -> str:
        """The fully qualified name of ``relative`` in this node's namespace."""
        full = self.namespace.rstrip("/") + "/" + relative
        return check_name("topic", full)

    def publication(
        self, entity_id: int, topic: str, ros_type: str, type_hash: str, qos: RosQoS = RosQoS()
    ) -> RosPublication:
        """Publisher ``entity_id`` of ``topic`` (relative to the namespace, or fully
        qualified) with messages of ``ros_type`` (``pkg/msg/Name``) of hash ``type_hash``."""
        full = check_name("topic", topic) if topic.startswith("/") else self.topic_name(topic)
        dds = dds_type_name(ros_type)
        token = "/".join(
            [self._head(entity_id, "MP"), mangle(full), dds, type_hash, qos_keyexpr(qos)]
        )
        return RosPublication(
            topic=full,
            ros_type=ros_type,
            key=topic_key(self.domain_id, full, dds, type_hash),
            token=token,
            gid=entity_gid(token),
        )
