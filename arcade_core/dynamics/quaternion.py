"""Unit-quaternion helpers for the quadrotor model (Appendix D).

Conventions (design §4): ``q = [w, x, y, z]`` (scalar first, Hamilton product) rotates
body FLU vectors into world ENU, i.e. ``v_world = R(q) v_body``. Roll-pitch-yaw are the
intrinsic Z-Y-X angles, ``R = Rz(yaw) Ry(pitch) Rx(roll)``. All functions work on the
trailing axis, so they broadcast over leading batch axes.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array


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


def vee(S: Array) -> Array:
    """Vector of a 3x3 skew-symmetric matrix (inverse of the hat map)."""
    return jnp.stack([S[..., 2, 1], S[..., 0, 2], S[..., 1, 0]], axis=-1)
