"""Quaternions and frames: the one place for their formulas (Appendix D, design §4).

Conventions: ``q = [w, x, y, z]`` (scalar first, Hamilton product) rotates body FLU vectors
into world ENU, i.e. ``v_world = R(q) v_body``. Roll-pitch-yaw are the intrinsic Z-Y-X
angles, ``R = Rz(yaw) Ry(pitch) Rx(roll)``.

Each formula comes in the forms its callers compute it in, side by side:

- JAX (plain names): functions of ``jax`` arrays on the trailing axis, broadcasting over
  leading batch axes, jit-, vmap- and grad-friendly (the nominal model, the estimator, the
  controller's references);
- NumPy (``_np``): float64, for the simulator, the PX4 side and the services;
- Python floats (``_py``): ``math`` on scalars, where a caller works on scalars.

The forms of one formula share its operation order, but XLA, NumPy and ``math`` need not
round alike (a transcendental function above all), so a caller keeps the form it computes
in and its numbers do not change. Two formulas of the same quantity that differ in more
than the backend are two named functions (:func:`from_rotation_matrix`, branch-free, and
:func:`from_rotation_matrix_np`, Shepperd's branches).

The last section changes between these frames and PX4's (MAVLink): world NED (x north,
y east, z down), body FRD (x forward, y right, z down), quaternions ``w`` first and
body-FRD-to-world-NED. Both changes of axes are proper rotations by 180 degrees, hence
their own inverses:

- ENU <-> NED swaps x and y and negates z: ``(e, n, u) -> (n, e, -u)``;
- FLU <-> FRD negates y and z: ``(f, l, u) -> (f, -l, -u)``.

The attitude quaternion changes as ``q_ned_frd = q_ned_enu * q_enu_flu * q_flu_frd`` with
the two constant rotations above (``*`` the Hamilton product). On a motion-capture world
frame that is not aligned with north, "NED" here is the mocap frame with its axes changed
this way: tell PX4 it is an arbitrary-heading frame (``LOCAL_FRD``), see docs/px4.md.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from jax import Array


class _JaxNumpy:
    """``jax.numpy``, imported at the first use of a JAX form: the processes that use only
    the NumPy and float forms (the simulator's PX4 side, the ROS 2 mirror) do not load JAX
    (about a second of CPU). The first use puts the module itself in its place."""

    def __getattr__(self, name: str) -> Any:
        import jax.numpy

        globals()["jnp"] = jax.numpy
        return getattr(jax.numpy, name)


jnp: Any = _JaxNumpy()

# ----------------------------------------------------------------------------- JAX


def multiply(p: Array, q: Array) -> Array:
    """Hamilton product ``p ⊗ q`` (Appendix D, the ``q ⊗ [0, ω]`` kinematics)."""
    pw, px, py, pz = jnp.moveaxis(p, -1, 0)
    qw, qx, qy, qz = jnp.moveaxis(q, -1, 0)
    return jnp.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def conjugate(q: Array) -> Array:
    """Inverse rotation of a unit quaternion."""
    return q * jnp.array([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def normalize(q: Array) -> Array:
    """Project onto the unit sphere S^3 (used after every integration step)."""
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def align(q: Array, q_ref: Array) -> Array:
    """``q`` or ``-q`` (the same rotation), whichever lies in ``q_ref``'s hemisphere.

    The model, the MPC cost and the learned features treat ``q`` as a vector of R^4, so
    the double cover must be resolved before they see it: ``-q`` is far from ``q``.
    """
    return jnp.where(jnp.sum(q * q_ref, axis=-1, keepdims=True) < 0, -q, q)


def to_rotation_matrix(q: Array) -> Array:
    """Rotation matrix ``R(q)`` (body -> world) of a unit quaternion, shape (..., 3, 3)."""
    w, x, y, z = jnp.moveaxis(q, -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def body_z_axis(q: Array) -> Array:
    """``R(q) e3``, the body z axis in the world frame: the third column of
    :func:`to_rotation_matrix` alone, the thrust direction of Appendix D's
    ``vdot = (T/m) R(q) e3 - g e3``."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], axis=-1)


def rotate(q: Array, v: Array) -> Array:
    """Rotate a body vector into the world frame: ``R(q) v``."""
    return jnp.einsum("...ij,...j->...i", to_rotation_matrix(q), v)


def from_rotation_matrix(R: Array) -> Array:
    """Unit quaternion of a rotation matrix (Shepperd's method), with ``w >= 0``.

    All four candidate formulas are evaluated and the best-conditioned one (largest
    pivot) is selected, so the function stays branch-free for jit/vmap.
    """
    r00, r11, r22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    trace = r00 + r11 + r22
    # Each candidate is 4*(component)^2 for the pivot component, always >= 0 for a rotation.
    pivots = jnp.stack(
        [1 + trace, 1 + r00 - r11 - r22, 1 - r00 + r11 - r22, 1 - r00 - r11 + r22], axis=-1
    )
    s = jnp.sqrt(jnp.maximum(pivots, 1e-12))  # = 2 * |pivot component|
    a = R[..., 2, 1] - R[..., 1, 2]
    b = R[..., 0, 2] - R[..., 2, 0]
    c = R[..., 1, 0] - R[..., 0, 1]
    d = R[..., 0, 1] + R[..., 1, 0]
    e = R[..., 0, 2] + R[..., 2, 0]
    f = R[..., 1, 2] + R[..., 2, 1]
    s0, s1, s2, s3 = jnp.moveaxis(s, -1, 0)
    cands = jnp.stack(
        [
            jnp.stack([s0 / 2, a / (2 * s0), b / (2 * s0), c / (2 * s0)], axis=-1),
            jnp.stack([a / (2 * s1), s1 / 2, d / (2 * s1), e / (2 * s1)], axis=-1),
            jnp.stack([b / (2 * s2), d / (2 * s2), s2 / 2, f / (2 * s2)], axis=-1),
            jnp.stack([c / (2 * s3), e / (2 * s3), f / (2 * s3), s3 / 2], axis=-1),
        ],
        axis=-2,
    )
    idx = jnp.argmax(pivots, axis=-1)
    q = jnp.take_along_axis(cands, idx[..., None, None], axis=-2)[..., 0, :]
    q = jnp.where(q[..., :1] < 0, -q, q)
    return normalize(q)


def from_rpy(roll: Array, pitch: Array, yaw: Array) -> Array:
    """Quaternion of intrinsic Z-Y-X angles, ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    cr, sr = jnp.cos(roll / 2), jnp.sin(roll / 2)
    cp, sp = jnp.cos(pitch / 2), jnp.sin(pitch / 2)
    cy, sy = jnp.cos(yaw / 2), jnp.sin(yaw / 2)
    return jnp.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        axis=-1,
    )


def to_rpy(q: Array) -> Array:
    """Intrinsic Z-Y-X angles ``[roll, pitch, yaw]`` of a unit quaternion."""
    w, x, y, z = jnp.moveaxis(q, -1, 0)
    roll = jnp.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = jnp.arcsin(jnp.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return jnp.stack([roll, pitch, yaw], axis=-1)


def error(q: Array, q_ref: Array) -> Array:
    """Small-angle attitude error: rotation vector of ``q_ref* ⊗ q`` in the reference frame.

    Sign-invariant (``q`` and ``-q`` give the same error); ``2 * vec`` of the shortest
    error quaternion, which equals the rotation vector to first order.
    """
    qe = multiply(conjugate(q_ref), q)
    sign = jnp.where(qe[..., :1] < 0, -1.0, 1.0)
    return 2.0 * sign * qe[..., 1:]


def angle_between(a: Array, b: Array) -> Array:
    """Angle [rad] of the rotation between unit quaternions ``a`` and ``b`` (one of each,
    shape (4,)), whatever their signs: ``2 acos |a . b|``."""
    return 2.0 * jnp.arccos(jnp.clip(jnp.abs(jnp.dot(a, b)), 0.0, 1.0))


def vee(S: Array) -> Array:
    """Vector of a 3x3 skew-symmetric matrix (inverse of the hat map)."""
    return jnp.stack([S[..., 2, 1], S[..., 0, 2], S[..., 1, 0]], axis=-1)


# --------------------------------------------------------------------------- NumPy


def multiply_np(a: Any, b: Any) -> np.ndarray:
    """Hamilton product ``a * b`` in float64 (broadcasts over leading axes)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def conjugate_np(q: Any) -> np.ndarray:
    """Inverse rotation of a unit quaternion, float64."""
    q = np.asarray(q, dtype=np.float64)
    return np.stack([q[..., 0], -q[..., 1], -q[..., 2], -q[..., 3]], axis=-1)


def to_rotation_matrix_np(q: Any) -> np.ndarray:
    """Rotation matrix ``R(q)`` (body -> world) of unit quaternion(s), float64, shape
    (..., 3, 3): :func:`to_rotation_matrix`'s formula."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    rows = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    return rows if rows.ndim == 2 else np.moveaxis(rows, (0, 1), (-2, -1))


def world_up_in_body_np(q: Any) -> np.ndarray:
    """``R(q)^T e3``, the world's up axis in body coordinates, of one quaternion: the third
    row of :func:`to_rotation_matrix_np`; its last entry is the cosine of the tilt.

    Squares are spelled ``** 2`` here, as the level-hover law has them: a power need not
    round like ``x * x`` (it differs in the last bit for about one number in a thousand),
    so this is a form of its own and not a row of the matrix above.
    """
    return np.array(
        [
            2 * (q[1] * q[3] - q[0] * q[2]),
            2 * (q[2] * q[3] + q[0] * q[1]),
            1 - 2 * (q[1] ** 2 + q[2] ** 2),
        ]
    )


def from_rotation_matrix_np(r: np.ndarray) -> np.ndarray:
    """``[w, x, y, z]`` of one rotation matrix (Shepperd's method, the branch of the
    largest pivot; the sign of ``w`` is not fixed)."""
    t = np.trace(r)
    if t > 0.0:
        s = 2.0 * np.sqrt(1.0 + t)
        return np.array(
            [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
        )
    i = int(np.argmax(np.diag(r)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = 2.0 * np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
    q = np.empty(4)
    q[0] = (r[k, j] - r[j, k]) / s
    q[1 + i] = 0.25 * s
    q[1 + j] = (r[j, i] + r[i, j]) / s
    q[1 + k] = (r[k, i] + r[i, k]) / s
    return q


def to_rpy_np(q: Any) -> np.ndarray:
    """Roll, pitch, yaw [rad] (intrinsic z-y'-x'', aerospace) of quaternion(s), float64.

    For a body-FRD-to-NED attitude these are PX4's Euler angles (yaw 0 = facing north).
    """
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    roll = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2.0 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return np.stack([roll, pitch, yaw], axis=-1)


def from_rpy_np(euler: Any) -> np.ndarray:
    """Inverse of :func:`to_rpy_np`: ``[roll, pitch, yaw]`` [rad] -> quaternion(s), float64."""
    r, p, y = np.moveaxis(np.asarray(euler, dtype=np.float64) / 2.0, -1, 0)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        axis=-1,
    )


def from_rotation_vector_np(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternion of one rotation vector [rad] (first order below 1e-12 rad)."""
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-12:
        return np.array([1.0, *(0.5 * rotvec)])
    return np.array([np.cos(0.5 * angle), *(np.sin(0.5 * angle) / angle * rotvec)])


# ---------------------------------------------------------------------- Python floats


def from_rpy_py(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """:func:`from_rpy_np` of scalar angles with ``math``'s sine and cosine."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return np.array(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )


def from_yaw_py(yaw: float) -> list[float]:
    """Level attitude facing ``yaw`` [rad]: ``[cos(yaw/2), 0, 0, sin(yaw/2)]``."""
    return [math.cos(0.5 * yaw), 0.0, 0.0, math.sin(0.5 * yaw)]


def yaw_py(q: Any) -> float:
    """Yaw [rad] of one quaternion (:func:`to_rpy`'s third angle) with ``math.atan2``."""
    w, x, y, z = q
    return float(math.atan2(2 * (w * z + x * y), 1 - 2 * (y**2 + z**2)))


# ------------------------------------------------------- ENU/FLU <-> NED/FRD (PX4, NumPy)

#: Rotation ENU -> NED (180 degrees about (1, 1, 0)/sqrt 2), w first; its own inverse.
Q_NED_ENU = np.array([0.0, math.sqrt(0.5), math.sqrt(0.5), 0.0])
#: Rotation FRD -> FLU (180 degrees about x), w first; its own inverse.
Q_FLU_FRD = np.array([0.0, 1.0, 0.0, 0.0])

_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_FLU_FRD = np.diag([1.0, -1.0, -1.0])


def _vec(v: Any) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.shape[-1:] != (3,):
        raise ValueError(f"expected (..., 3) vectors, got shape {a.shape}")
    return a


def enu_to_ned(v: Any) -> np.ndarray:
    """World vector(s) (position, velocity, ...) ENU -> NED: ``(e, n, u) -> (n, e, -u)``."""
    return _vec(v) @ _ENU_NED.T


def ned_to_enu(v: Any) -> np.ndarray:
    """World vector(s) NED -> ENU: ``(n, e, d) -> (e, n, -d)`` (the same permutation)."""
    return _vec(v) @ _ENU_NED.T


def flu_to_frd(v: Any) -> np.ndarray:
    """Body vector(s) (rates, forces, ...) FLU -> FRD: ``(f, l, u) -> (f, -l, -u)``."""
    return _vec(v) @ _FLU_FRD.T


def frd_to_flu(v: Any) -> np.ndarray:
    """Body vector(s) FRD -> FLU (the same sign change)."""
    return _vec(v) @ _FLU_FRD.T


def quat_enu_flu_to_ned_frd(q: Any) -> np.ndarray:
    """Attitude body-FLU-to-world-ENU -> body-FRD-to-world-NED (``w`` first)."""
    return multiply_np(multiply_np(Q_NED_ENU, q), Q_FLU_FRD)


def quat_ned_frd_to_enu_flu(q: Any) -> np.ndarray:
    """Attitude body-FRD-to-world-NED -> body-FLU-to-world-ENU (``w`` first).

    Exact inverse of :func:`quat_enu_flu_to_ned_frd` (both constant rotations are 180
    degrees, so each equals its inverse up to a sign that cancels in the product).
    """
    return multiply_np(multiply_np(-Q_NED_ENU, q), -Q_FLU_FRD)
