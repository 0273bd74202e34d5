"""The stack's records as ROS 2 messages: type hashes against the published ones, CDR bytes
decoded (and re-encoded byte for byte) by an independent CDR library (pycdr2), frames and
covariances against brute force (scipy's rotations, finite differences)."""

from __future__ import annotations

import numpy as np
import pytest
import ros2_idl as idl
from scipy.spatial.transform import Rotation

from arcade_io import ros2_messages as rm

#: REP-2016 hashes of ROS 2 Jazzy's common_interfaces as rosidl generates them (std_msgs
#: String: rmw_zenoh's docs/design.md; the others as published with the packages).
PUBLISHED = {
    "std_msgs/msg/String": "df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    rm.ODOMETRY: "3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    rm.VECTOR3_STAMPED: "d4829622288cbb443886e7ea94ea5671a3b1be6bab4ad04224432a65f7d7887a",
    rm.DIAGNOSTICS: "5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e",
}


@pytest.mark.parametrize("ros_type", sorted(PUBLISHED))
def test_type_hashes_are_the_published_ones(ros_type):
    assert rm.type_hash(ros_type) == "RIHS01_" + PUBLISHED[ros_type]


def _decode(cls, data: bytes):
    """pycdr2's reading of ``data``, which pycdr2 must write back byte for byte."""
    assert data[:4] == b"\x00\x01\x00\x00"  # little-endian plain CDR encapsulation
    msg = cls.deserialize(data)
    assert msg.serialize() == data
    return msg


def _state(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return np.r_[rng.normal(size=3), rng.normal(size=3), q, rng.normal(size=3)]


def _xyz(v) -> np.ndarray:
    return np.array([v.x, v.y, v.z])


def test_odometry_decodes_with_body_twist_and_brute_force_covariances():
    rng = np.random.default_rng(3)
    x = _state(rng)
    var = rng.uniform(1e-6, 1e-2, size=13)
    msg = _decode(idl.Odometry, rm.cdr(rm.odometry(12.345678901, x, var), rm.ODOMETRY))
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (12, 345678901)
    assert (msg.header.frame_id, msg.child_frame_id) == ("world", "base_link")
    pose, twist = msg.pose.pose, msg.twist.twist
    np.testing.assert_array_equal(_xyz(pose.position), x[0:3])
    o = pose.orientation
    np.testing.assert_array_equal([o.w, o.x, o.y, o.z], x[6:10])
    rot = Rotation.from_quat([o.x, o.y, o.z, o.w])  # scipy: x, y, z, w; body -> world
    np.testing.assert_allclose(_xyz(twist.linear), rot.inv().apply(x[3:6]), atol=1e-14)
    np.testing.assert_array_equal(_xyz(twist.angular), x[10:13])
    pose_cov = np.reshape(msg.pose.covariance, (6, 6))
    twist_cov = np.reshape(msg.twist.covariance, (6, 6))
    np.testing.assert_array_equal(np.diag(pose_cov)[:3], var[0:3])
    np.testing.assert_array_equal(np.diag(twist_cov)[3:], var[10:13])
    r = rot.as_matrix()
    np.testing.assert_allclose(twist_cov[:3, :3], r.T @ np.diag(var[3:6]) @ r, atol=1e-16)
    # the attitude block: the world-frame rotation vector of q ⊗ q̂* to first order, its
    # Jacobian by central differences of scipy's rotation vector
    q_hat = x[6:10]

    def theta(q):
        d = (
            Rotation.from_quat(np.r_[q[1:], q[0]])
            * Rotation.from_quat(np.r_[q_hat[1:], q_hat[0]]).inv()
        )
        return d.as_rotvec()

    h = 1e-6
    jac = np.stack([(theta(q_hat + h * e) - theta(q_hat - h * e)) / (2 * h) for e in np.eye(4)], 1)
    np.testing.assert_allclose(pose_cov[3:, 3:], jac @ np.diag(var[6:10]) @ jac.T, rtol=1e-6)
    for cov in (pose_cov, twist_cov):  # symmetric, positive semi-definite
        np.testing.assert_allclose(cov, cov.T, atol=1e-18)
        assert np.linalg.eigvalsh(cov).min() > -1e-15
    assert not pose_cov[:3, 3:].any() and not twist_cov[:3, 3:].any()


def test_odometry_without_variances_has_zero_covariances():
    x = _state(np.random.default_rng(4))
    msg = _decode(idl.Odometry, rm.cdr(rm.odometry(0.0, x), rm.ODOMETRY))
    assert not any(msg.pose.covariance) and not any(msg.twist.covariance)


def test_setpoint_thrust_and_rates_decode():
    thrust = _decode(idl.Vector3Stamped, rm.cdr(rm.thrust_setpoint(2.5, 9.81), rm.VECTOR3_STAMPED))
    assert thrust.header.frame_id == "base_link"
    assert (thrust.header.stamp.sec, thrust.header.stamp.nanosec) == (2, 500000000)
    np.testing.assert_array_equal(_xyz(thrust.vector), [0.0, 0.0, 9.81])
    rates = _decode(
        idl.Vector3Stamped, rm.cdr(rm.rate_setpoint(2.5, [0.1, -0.2, 0.3]), rm.VECTOR3_STAMPED)
    )
    np.testing.assert_array_equal(_xyz(rates.vector), [0.1, -0.2, 0.3])


def test_changepoint_diagnostics_decode_with_level_and_exact_values():
    data = {"changepoint_step": 412, "changepoint_stamp": 20.650000000000002, "src": "adapter/ab"}
    msg = _decode(
        idl.DiagnosticArray,
        rm.cdr(
            rm.changepoint_diagnostics(
                20.7, "changepoint detected", "warning", data, hardware_id="q1"
            ),
            rm.DIAGNOSTICS,
        ),
    )
    (status,) = msg.status
    assert (status.level, status.message, status.hardware_id) == (1, "changepoint detected", "q1")
    values = {kv.key: kv.value for kv in status.values}
    assert values == {
        "changepoint_step": "412",
        "changepoint_stamp": "20.650000000000002",
        "src": "adapter/ab",
    }
    assert float(values["changepoint_stamp"]) == data["changepoint_stamp"]


@pytest.mark.parametrize("stamp", [-1.0, float("nan"), float("inf"), 2.0**31])
def test_stamps_ros_cannot_hold_are_refused(stamp):
    with pytest.raises(ValueError, match="not a ROS 2 time"):
        rm.ros_time(stamp)


def test_stamp_rounds_to_the_nanosecond_and_carries():
    t = rm.ros_time(0.9999999999)
    assert (t.sec, t.nanosec) == (1, 0)
