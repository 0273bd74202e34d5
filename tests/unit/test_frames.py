"""The forms of one quaternion formula (JAX, NumPy, Python floats) agree with each other."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest

from arcade_core import frames

RNG = np.random.default_rng(3)


def _quats(n: int) -> np.ndarray:
    q = RNG.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_rotation_matrix_forms_agree():
    q = _quats(32)
    R = frames.to_rotation_matrix_np(q)
    assert R.shape == (32, 3, 3)
    np.testing.assert_allclose(R, frames.to_rotation_matrix(jnp.asarray(q)), atol=1e-6)
    for qi, Ri in zip(q, R):
        np.testing.assert_array_equal(frames.to_rotation_matrix_np(qi), Ri)  # one or many
    np.testing.assert_allclose(
        R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12
    )
    np.testing.assert_allclose(
        frames.body_z_axis(jnp.asarray(q)), frames.to_rotation_matrix(jnp.asarray(q))[..., :, 2]
    )


def test_product_and_conjugate_forms_agree():
    p, q = _quats(16), _quats(16)
    np.testing.assert_allclose(
        frames.multiply_np(p, q), frames.multiply(jnp.asarray(p), jnp.asarray(q)), atol=1e-6
    )
    np.testing.assert_allclose(frames.conjugate_np(q), frames.conjugate(jnp.asarray(q)), atol=0)
    # q* q is the identity, and the product composes the rotation matrices.
    np.testing.assert_allclose(
        frames.multiply_np(frames.conjugate_np(q), q), np.tile([1.0, 0, 0, 0], (16, 1)), atol=1e-15
    )
    np.testing.assert_allclose(
        frames.to_rotation_matrix_np(frames.multiply_np(p, q)),
        frames.to_rotation_matrix_np(p) @ frames.to_rotation_matrix_np(q),
        atol=1e-12,
    )


def test_matrix_to_quaternion_forms_agree_up_to_sign():
    for q in _quats(64):
        R = frames.to_rotation_matrix_np(q)
        a = frames.from_rotation_matrix_np(R)
        b = np.asarray(frames.from_rotation_matrix(jnp.asarray(R)))
        assert min(np.abs(a - q).max(), np.abs(a + q).max()) < 1e-12
        assert min(np.abs(b - q).max(), np.abs(b + q).max()) < 1e-6


def test_euler_forms_agree():
    rpy = np.column_stack(
        [RNG.uniform(-3, 3, 20), RNG.uniform(-1.5, 1.5, 20), RNG.uniform(-3, 3, 20)]
    )
    q = frames.from_rpy_np(rpy)
    np.testing.assert_allclose(frames.to_rpy_np(q), rpy, atol=1e-12)
    np.testing.assert_allclose(frames.from_rpy(*jnp.asarray(rpy.T)), q, atol=1e-6)
    np.testing.assert_allclose(frames.to_rpy(jnp.asarray(q)), rpy, atol=1e-5)
    for angles, qi in zip(rpy, q):
        np.testing.assert_allclose(frames.from_rpy_py(*map(float, angles)), qi, atol=1e-15)
        assert frames.yaw_py(qi) == pytest.approx(angles[2], abs=1e-12)
    assert frames.from_yaw_py(0.7) == pytest.approx(list(frames.from_rpy_np([0.0, 0.0, 0.7])))


def test_rotation_vector_and_angle_between():
    v = np.array([0.3, -0.2, 0.5])
    q = frames.from_rotation_vector_np(v)
    assert np.linalg.norm(q) == pytest.approx(1.0)
    assert float(frames.angle_between(jnp.asarray(q), jnp.array([1.0, 0, 0, 0]))) == (
        pytest.approx(np.linalg.norm(v), abs=1e-6)
    )
    assert float(frames.angle_between(jnp.asarray(q), jnp.asarray(-q))) == pytest.approx(
        0.0, abs=1e-3
    )
    np.testing.assert_array_equal(frames.from_rotation_vector_np(np.zeros(3)), [1.0, 0, 0, 0])
    # About z by 90 degrees: x goes to y.
    qz = frames.from_rotation_vector_np(np.array([0.0, 0.0, math.pi / 2]))
    np.testing.assert_allclose(
        frames.to_rotation_matrix_np(qz) @ [1.0, 0, 0], [0, 1.0, 0], atol=1e-15
    )
