"""rmw_zenoh's key expressions, liveliness tokens, QoS chunks and attachments, against the
examples of ros2/rmw_zenoh's docs/design.md (commit 99a6a2bd10b9) and its code."""

from __future__ import annotations

import struct

import pytest
import xxhash
import zenoh
import zenoh.ext as zx

from arcade_io import rmw_zenoh as rz
from arcade_io import ros2_messages as rm

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
STRING_DDS = "std_msgs::msg::dds_::String_"


def test_topic_keys_are_the_documented_examples():
    assert rz.dds_type_name("std_msgs/msg/String") == STRING_DDS
    assert (
        rz.topic_key(0, "/chatter", STRING_DDS, STRING_HASH)
        == f"0/chatter/{STRING_DDS}/{STRING_HASH}"
    )
    node = rz.RosNode(domain_id=0, zid="aac3178e146ba6f1fc6e6a4085e77f21", namespace="/robot1",
                      name="talker")  # fmt: skip
    pub = node.publication(10, "chatter", "std_msgs/msg/String", STRING_HASH)
    assert pub.topic == "/robot1/chatter"
    assert pub.key == f"0/robot1/chatter/{STRING_DDS}/{STRING_HASH}"


def test_tokens_are_the_documented_examples():
    listener = rz.RosNode(domain_id=2, zid="aac3178e146ba6f1fc6e6a4085e77f21", namespace="/",
                          name="listener")  # fmt: skip
    assert listener.token() == "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    talker = rz.RosNode(domain_id=2, zid="8b20917502ee955ac4476e0266340d5c", namespace="/",
                        name="talker")  # fmt: skip
    pub = talker.publication(10, "/chatter", "std_msgs/msg/String", STRING_HASH, rz.RosQoS(depth=7))
    assert pub.token == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
        f"{STRING_DDS}/{STRING_HASH}/::,7:,:,:,,"
    )


def test_namespaced_token_mangles_every_slash():
    node = rz.RosNode(domain_id=0, zid="f00d", namespace="/arcade/quad1", name="arcade_mirror")
    assert node.token() == "@ros2_lv/0/f00d/0/0/NN/%/%arcade%quad1/arcade_mirror"
    pub = node.publication(3, "setpoint/thrust", rm.VECTOR3_STAMPED, "RIHS01_x")
    assert pub.token.split("/")[9:] == [
        "%arcade%quad1%setpoint%thrust",
        "geometry_msgs::msg::dds_::Vector3Stamped_",
        "RIHS01_x",
        "::,10:,:,:,,",
    ]
    assert (
        pub.key
        == "0/arcade/quad1/setpoint/thrust/geometry_msgs::msg::dds_::Vector3Stamped_/RIHS01_x"
    )


def test_qos_chunk_writes_only_what_differs_from_rmw_zenohs_defaults():
    assert rz.qos_keyexpr(rz.DEFAULT_QOS) == "::,:,:,:,,"
    assert rz.qos_keyexpr(rz.RosQoS()) == "::,10:,:,:,,"  # the listener example's
    sensor = rz.RosQoS(reliability=rz.BEST_EFFORT, durability=rz.TRANSIENT_LOCAL, depth=5)
    assert rz.qos_keyexpr(sensor) == "2:1:,5:,:,:,,"
    timed = rz.RosQoS(history=rz.KEEP_ALL, deadline=(1, 500), lifespan=(0, 7), lease=(3, 0))
    assert rz.qos_keyexpr(timed) == "::2,10:1,500:0,7:,3,0"


def test_attachment_is_the_documented_33_bytes_and_zenoh_ext_reads_it():
    gid = bytes(range(16))
    data = rz.attachment(42, 1_700_000_000_123_456_789, gid)
    assert len(data) == 33
    assert data[:16] == struct.pack("<qq", 42, 1_700_000_000_123_456_789)
    assert data[16] == 16 and data[17:] == gid
    # zenoh-ext's deserialiser of (int64, int64, std::array<uint8_t, 16>), as rmw_zenoh reads it
    assert zx.z_deserialize(tuple[zx.Int64, zx.Int64, list[zx.UInt8]], zenoh.ZBytes(data)) == (
        42,
        1_700_000_000_123_456_789,
        list(gid),
    )
    assert rz.parse_attachment(data) == (42, 1_700_000_000_123_456_789, gid)
    with pytest.raises(ValueError, match="not an rmw_zenoh attachment"):
        rz.parse_attachment(data[:-1])
    with pytest.raises(ValueError, match="16 bytes"):
        rz.attachment(1, 0, b"short")


def test_gid_is_the_tokens_xxh3_128_low_half_first():
    token = "@ros2_lv/0/f00d/0/1/MP/%/%arcade%default/arcade_mirror/%arcade%default%odom/x/y/q"
    gid = rz.entity_gid(token)
    assert len(gid) == rz.GID_SIZE
    # canonical digest: high then low 64 bits, big-endian; rmw_zenoh copies low, then high,
    # each in the machine's (little-endian) byte order: the digest reversed
    assert gid == xxhash.xxh3_128_digest(token.encode())[::-1]
    assert rz.entity_gid(token + "x") != gid


@pytest.mark.parametrize(
    ("kind", "name"),
    [("namespace", "arcade/x"), ("namespace", "/a-b"), ("namespace", "/1a"), ("topic", "/"),
     ("topic", "/a//b"), ("topic", "/a/"), ("node", "a/b"), ("node", "")],
)  # fmt: skip
def test_invalid_ros_names_are_refused(kind, name):
    with pytest.raises(ValueError, match=f"invalid ROS 2 {kind} name"):
        rz.check_name(kind, name)


def test_valid_names_domains_and_type_names():
    assert rz.check_name("namespace", "/") == "/"
    assert rz.check_name("topic", "/arcade/quad_1/odom") == "/arcade/quad_1/odom"
    assert rz.check_domain_id(232) == 232
    for bad in (-1, 233, 1.5):
        with pytest.raises(ValueError, match="domain id"):
            rz.check_domain_id(bad)
    with pytest.raises(ValueError, match="pkg/msg/Name"):
        rz.dds_type_name("nav_msgs/Odometry")
    with pytest.raises(ValueError, match="session id"):
        rz.RosNode(domain_id=0, zid="", namespace="/", name="n")
