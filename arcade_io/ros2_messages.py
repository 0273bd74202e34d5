"""The stack's records as ROS 2 messages: conversion, CDR bytes and REP-2016 type hashes.

Standard ROS 2 types only (``common_interfaces``, present on every ROS 2 host), so that a
host sees them without building a package of ours:

- state: ``nav_msgs/msg/Odometry``, pose in ``world`` (ENU), twist in ``base_link``
  (FLU), covariances from the estimator's variances;
- reference: ``nav_msgs/msg/Odometry`` too, the planned state, child frame ``reference``,
  no covariances (overlaid on the state in ROS 2's tools);
- setpoint: two ``geometry_msgs/msg/Vector3Stamped`` in ``base_link``, the collective
  thrust as the body force ``(0, 0, T)`` N and the body-rate setpoints in rad/s;
- changepoint event: ``diagnostic_msgs/msg/DiagnosticArray`` with one status (level, text,
  data).

ROS uses the stack's own frames (REP-103: world ENU, body FLU), so nothing is re-axed; ROS
quaternions are ``x, y, z, w``. ``header.stamp`` is the record's ``stamp`` (simulated
seconds in lockstep, the monotonic clock otherwise). ``px4_msgs`` types were not used: their
type hashes change with the PX4 release a host builds, and ``VehicleRatesSetpoint``'s
thrust is normalised to a vehicle's thrust curve, which the stack's setpoint (newtons) does
not carry.

Messages are built and serialised with ``rosbags`` (its ROS 2 Jazzy type store), whose
REP-2016 type description hashing gives the ``RIHS01_...`` hashes rmw_zenoh puts in its
keys; the tests check them against the published ones. CDR bytes carry the 4-byte
encapsulation header (little-endian CDR), as rmw_zenoh sends them. I/O-free.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = [
    "DIAGNOSTICS",
    "ODOMETRY",
    "VECTOR3_STAMPED",
    "cdr",
    "changepoint_diagnostics",
    "odometry",
    "rate_setpoint",
    "ros_time",
    "thrust_setpoint",
    "type_hash",
]

ODOMETRY = "nav_msgs/msg/Odometry"
VECTOR3_STAMPED = "geometry_msgs/msg/Vector3Stamped"
DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"

#: ``diagnostic_msgs/msg/DiagnosticStatus`` levels by event severity.
LEVELS = {"debug": 0, "info": 0, "warning": 1, "error": 2, "critical": 2}
_INT32_MAX = 2**31 - 1


@functools.cache
def _store() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def _t(name: str) -> Any:
    """The rosbags class of ROS 2 type ``name``."""
    return _store().types[name]


def type_hash(ros_type: str) -> str:
    """REP-2016 hash ``RIHS01_<sha256 hex>`` of a type's description."""
    return _store().hash_rihs01(ros_type)


def cdr(message: Any, ros_type: str) -> bytes:
    """Little-endian CDR of ``message`` with its encapsulation header."""
    return bytes(_store().serialize_cdr(message, ros_type))


def ros_time(stamp: float) -> Any:
    """``builtin_interfaces/msg/Time`` of ``stamp`` seconds (rounded to the nanosecond);
    ``ValueError`` outside what its int32 seconds hold."""
    if not (math.isfinite(stamp) and 0.0 <= stamp <= _INT32_MAX):
        raise ValueError(f"stamp {stamp!r} s: not a ROS 2 time (0 to {_INT32_MAX} s)")
    sec, nanosec = divmod(round(stamp * 1e9), 10**9)
    return _t("builtin_interfaces/msg/Time")(sec=int(sec), nanosec=int(nanosec))


def _header(stamp: float, frame_id: str) -> Any:
    return _t("std_msgs/msg/Header")(stamp=ros_time(stamp), frame_id=frame_id)


def _vector(v: Any) -> Any:
    x, y, z = (float(c) for c in v)
    return _t("geometry_msgs/msg/Vector3")(x=x, y=y, z=z)


def _point(v: Any) -> Any:
    x, y, z = (float(c) for c in v)
    return _t("geometry_msgs/msg/Point")(x=x, y=y, z=z)


def _quaternion(q_wxyz: Any) -> Any:
    w, x, y, z = (float(c) for c in q_wxyz)
    return _t("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w)


def attitude_covariance(q: np.ndarray, var_q: np.ndarray) -> np.ndarray:
    """``(3, 3)`` covariance of the small world-frame rotation ``theta`` with ``q = exp(theta)
    ⊗ q̂``, from the marginal variances of the quaternion's components, to first order:
    ``theta ≈ 2 vec(q ⊗ q̂*)``, linear in ``q``."""
    from arcade_core import frames  # JAX with it: loaded when a state is converted

    conj = frames.conjugate_np(q)
    jac = np.stack([2.0 * frames.multiply_np(e, conj)[1:] for e in np.eye(4)], axis=1)
    return jac @ np.diag(var_q) @ jac.T


def odometry(
    stamp: float,
    x: Any,
    cov_diag: Any | None = None,
    frame_id: str = "world",
    child_frame_id: str = "base_link",
) -> Any:
    """``nav_msgs/msg/Odometry`` of the state ``x = [p, v, q (w first), omega]`` (world
    ENU, body FLU). The twist is in ``child_frame_id``, as the type prescribes: the velocity
    rotated into the body, ``R(q)^T v``. With ``cov_diag`` (the state's marginal variances)
    the covariances' diagonal blocks: position; attitude (:func:`attitude_covariance`, axes
    of ``frame_id``); body velocity ``R^T diag(var_v) R``; body rates. Without, zeros."""
    from arcade_core import frames

    x = np.asarray(x, dtype=np.float64)
    p, v, q, omega = x[0:3], x[3:6], x[6:10], x[10:13]
    rot = frames.to_rotation_matrix_np(q)
    pose_cov = np.zeros((6, 6))
    twist_cov = np.zeros((6, 6))
    if cov_diag is not None:
        var = np.asarray(cov_diag, dtype=np.float64)
        pose_cov[:3, :3] = np.diag(var[0:3])
        pose_cov[3:, 3:] = attitude_covariance(q, var[6:10])
        twist_cov[:3, :3] = rot.T @ np.diag(var[3:6]) @ rot
        twist_cov[3:, 3:] = np.diag(var[10:13])
    pose = _t("geometry_msgs/msg/Pose")(position=_point(p), orientation=_quaternion(q))
    twist = _t("geometry_msgs/msg/Twist")(linear=_vector(rot.T @ v), angular=_vector(omega))
    return _t(ODOMETRY)(
        header=_header(stamp, frame_id),
        child_frame_id=child_frame_id,
        pose=_t("geometry_msgs/msg/PoseWithCovariance")(pose=pose, covariance=pose_cov.ravel()),
        twist=_t("geometry_msgs/msg/TwistWithCovariance")(
            twist=twist, covariance=twist_cov.ravel()
        ),
    )


def thrust_setpoint(stamp: float, thrust_n: float, frame_id: str = "base_link") -> Any:
    """``geometry_msgs/msg/Vector3Stamped``: the collective thrust as a body force
    ``(0, 0, T)`` N (FLU: up the body z axis)."""
    return _t(VECTOR3_STAMPED)(
        header=_header(stamp, frame_id), vector=_vector((0.0, 0.0, float(thrust_n)))
    )


def rate_setpoint(stamp: float, rates: Any, frame_id: str = "base_link") -> Any:
    """``geometry_msgs/msg/Vector3Stamped``: the body-rate setpoints, rad/s, body FLU."""
    return _t(VECTOR3_STAMPED)(header=_header(stamp, frame_id), vector=_vector(rates))


def changepoint_diagnostics(
    stamp: float,
    text: str,
    severity: str,
    data: Mapping[str, Any],
    name: str = "arcade: changepoint",
    hardware_id: str = "",
) -> Any:
    """``diagnostic_msgs/msg/DiagnosticArray`` with one status: level by ``severity``
    (:data:`LEVELS`), the event's text, and its data as key-value strings (``repr`` of
    floats, so they read back exactly)."""
    key_value = _t("diagnostic_msgs/msg/KeyValue")
    values = [
        key_value(key=str(k), value=repr(v) if isinstance(v, float) else str(v))
        for k, v in data.items()
    ]
    status = _t("diagnostic_msgs/msg/DiagnosticStatus")(
        level=LEVELS[severity], name=name, message=text, hardware_id=hardware_id, values=values
    )
    return _t(DIAGNOSTICS)(header=_header(stamp, ""), status=[status])
