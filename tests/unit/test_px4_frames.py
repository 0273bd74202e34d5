"""ENU/FLU <-> NED/FRD conversions and PX4's normalised thrust, against hand-computed cases.

``_rot`` writes the rotation matrix out on purpose: an independent reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from arcade_core import frames as fr
from arcade_core.px4_command import ThrustCurve, deg_to_rad, rad_to_deg

RNG = np.random.default_rng(7)
S = math.sqrt(0.5)


def _random_quats(n):
    q = RNG.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_world_vectors():
    np.testing.assert_array_equal(fr.enu_to_ned([1.0, 2.0, 3.0]), [2.0, 1.0, -3.0])
    np.testing.assert_array_equal(fr.ned_to_enu([2.0, 1.0, -3.0]), [1.0, 2.0, 3.0])
    # Velocity 1 m/s north, climbing 0.5 m/s: NED (1, 0, -0.5).
    np.testing.assert_array_equal(fr.enu_to_ned([0.0, 1.0, 0.5]), [1.0, 0.0, -0.5])
    v = RNG.normal(size=(100, 3))
    np.testing.assert_array_equal(fr.ned_to_enu(fr.enu_to_ned(v)), v)


def test_body_vectors_and_rates():
    # Rolling right (FRD +x) is rolling right in FLU too; pitching nose-up is +y FRD but
    # -y FLU; yawing to the right (clockwise seen from above) is +z FRD, -z FLU.
    np.testing.assert_array_equal(fr.flu_to_frd([0.1, -0.2, 0.3]), [0.1, 0.2, -0.3])
    np.testing.assert_array_equal(fr.frd_to_flu([0.1, 0.2, -0.3]), [0.1, -0.2, 0.3])
    w = RNG.normal(size=(100, 3))
    np.testing.assert_array_equal(fr.frd_to_flu(fr.flu_to_frd(w)), w)
    assert rad_to_deg(math.pi) == pytest.approx(180.0)
    np.testing.assert_allclose(deg_to_rad(rad_to_deg(w)), w, rtol=1e-15)
    with pytest.raises(ValueError):
        fr.flu_to_frd([1.0, 2.0])


@pytest.mark.parametrize(
    "yaw_enu_deg, yaw_ned_deg", [(90, 0), (0, 90), (180, -90), (45, 45), (-90, 180)]
)
def test_heading(yaw_enu_deg, yaw_ned_deg):
    """ENU yaw is from east counter-clockwise, NED yaw from north clockwise."""
    a = math.radians(yaw_enu_deg) / 2
    q_ned = fr.quat_enu_flu_to_ned_frd([math.cos(a), 0.0, 0.0, math.sin(a)])
    roll, pitch, yaw = np.degrees(fr.to_rpy_np(q_ned))
    assert roll == pytest.approx(0.0, abs=1e-9) and pitch == pytest.approx(0.0, abs=1e-9)
    assert math.cos(math.radians(yaw - yaw_ned_deg)) == pytest.approx(1.0)


def test_attitude_hand_cases():
    # Level, facing east (ENU identity) = yaw 90 deg in NED: q = (cos 45, 0, 0, sin 45).
    q = fr.quat_enu_flu_to_ned_frd([1.0, 0.0, 0.0, 0.0])
    assert abs(np.dot(q, [S, 0.0, 0.0, S])) == pytest.approx(1.0)
    # Nose up 30 deg while facing east: FLU pitch is about body +y (left) with the nose
    # going up = negative rotation about FLU y; in FRD the nose-up pitch is positive.
    a = math.radians(-30) / 2
    q = fr.quat_enu_flu_to_ned_frd([math.cos(a), 0.0, math.sin(a), 0.0])
    roll, pitch, yaw = np.degrees(fr.to_rpy_np(q))
    assert (roll, pitch, yaw) == pytest.approx((0.0, 30.0, 90.0), abs=1e-9)
    # Right wing down (FRD roll +20 deg) facing north.
    q_ned = fr.from_rpy_np(np.radians([20.0, 0.0, 0.0]))
    q_enu = fr.quat_ned_frd_to_enu_flu(q_ned)
    right_enu = fr.to_rotation_matrix_np(q_enu) @ [0.0, -1.0, 0.0]  # FLU -y = right wing
    assert right_enu[0] == pytest.approx(math.cos(math.radians(20)))  # points east ...
    assert right_enu[2] == pytest.approx(-math.sin(math.radians(20)))  # ... and down


def test_attitude_maps_vectors_consistently():
    """R_ned_frd = C_w R_enu_flu C_b for every attitude: body vectors rotate alike."""
    for q in _random_quats(50):
        q2 = fr.quat_enu_flu_to_ned_frd(q)
        v_flu = RNG.normal(size=3)
        lhs = fr.to_rotation_matrix_np(q2) @ fr.flu_to_frd(v_flu)
        rhs = fr.enu_to_ned(fr.to_rotation_matrix_np(q) @ v_flu)
        np.testing.assert_allclose(lhs, rhs, atol=1e-12)
        assert np.linalg.norm(q2) == pytest.approx(1.0)


def test_attitude_round_trips_exactly():
    q = _random_quats(200)
    np.testing.assert_allclose(
        fr.quat_ned_frd_to_enu_flu(fr.quat_enu_flu_to_ned_frd(q)), q, atol=1e-15
    )
    np.testing.assert_allclose(
        fr.quat_enu_flu_to_ned_frd(fr.quat_ned_frd_to_enu_flu(q)), q, atol=1e-15
    )
    e = np.column_stack(
        [RNG.uniform(-3, 3, 200), RNG.uniform(-1.5, 1.5, 200), RNG.uniform(-3, 3, 200)]
    )
    np.testing.assert_allclose(fr.to_rpy_np(fr.from_rpy_np(e)), e, atol=1e-12)


def test_normalised_thrust_hand_cases():
    # PX4's normalised thrust is linear in force (its mixer applies THR_MDL_FAC): the
    # vehicle file's thr_mdl_fac is kept but enters neither direction.
    curve = ThrustCurve.from_vehicle(
        {"rotors": {"max_thrust_n": 4.0}, "thrust_curve": {"thr_mdl_fac": 0.3}}
    )
    assert curve.max_thrust_n == 16.0 and curve.fac == 0.3
    assert curve.throttle(0.0) == 0.0 and curve.thrust(0.0) == 0.0
    assert curve.throttle(16.0) == 1.0 and curve.thrust(1.0) == 16.0
    # Hover of the 0.57 kg vehicle: 5.5917 N / 16 N = 0.34948 (by hand), not the 0.42269
    # of the THR_MDL_FAC 0.3 quadratic applied a second time.
    hover = 0.57 * 9.81
    assert curve.throttle(hover) == pytest.approx(0.34948, abs=1e-5)
    # Half throttle: half the maximum thrust, 8 N (not 16 (0.3/4 + 0.35) = 6.8 N).
    assert curve.thrust(0.5) == pytest.approx(8.0, rel=1e-15)
    assert curve.throttle(8.0) == pytest.approx(0.5, rel=1e-15)
    # Out of range: clipped, never extrapolated.
    assert curve.throttle(-1.0) == 0.0 and curve.throttle(100.0) == 1.0
    assert curve.thrust(-0.2) == 0.0 and curve.thrust(1.5) == 16.0
    # Six rotors: T_max is the rotor count x the rotor maximum.
    six = ThrustCurve.from_vehicle({"rotors": {"max_thrust_n": 4.0, "count": 6}})
    assert six.max_thrust_n == 24.0 and six.fac == 0.0 and six.throttle(6.0) == 0.25
    for fac, tmax in ((1.5, 16.0), (-0.1, 16.0), (0.3, 0.0)):
        with pytest.raises(ValueError):
            ThrustCurve(fac=fac, max_thrust_n=tmax)


@pytest.mark.parametrize("fac", [0.0, 0.3, 0.7, 1.0])
def test_normalised_thrust_is_linear_for_any_fac(fac):
    curve = ThrustCurve(fac=fac, max_thrust_n=16.0)
    s = np.concatenate([[0.0, 1e-9, 1.0], RNG.uniform(0, 1, 500)])
    np.testing.assert_allclose(curve.thrust(s), 16.0 * s, rtol=1e-15, atol=0.0)
    np.testing.assert_allclose(curve.throttle(curve.thrust(s)), s, rtol=1e-12, atol=1e-15)
    t = RNG.uniform(0, 16, 500)
    np.testing.assert_allclose(curve.throttle(t), t / 16.0, rtol=1e-15, atol=0.0)
    np.testing.assert_allclose(curve.thrust(curve.throttle(t)), t, rtol=1e-12, atol=1e-12)
