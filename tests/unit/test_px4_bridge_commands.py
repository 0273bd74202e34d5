"""PX4 bridge, the pure parts: the attitude-rate command's conversion and clamps, the
geofence. The bridge process against a fake PX4 is in ``tests/integration/test_px4_bridge.py``."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.px4_bridge import Geofence, Limits, attitude_rate_command

VEHICLE = {
    "rotors": {"max_thrust_n": 4.0},
    "thrust_curve": {"thr_mdl_fac": 0.3},
    "rate_loop": {"max_rate_rad_s": [3.5, 3.5, 3.0]},
}


def test_attitude_rate_command_converts_and_clamps():
    limits = Limits.from_vehicle(VEHICLE, max_throttle=0.8)
    hover = 0.57 * 9.81
    deg_s, s, clamped = attitude_rate_command([hover, 1.0, -0.5, 0.25], limits)
    # FLU -> FRD: roll kept, pitch and yaw negated; rad/s -> deg/s.
    np.testing.assert_allclose(deg_s, np.degrees([1.0, 0.5, -0.25]))
    # Thrust: linear, T / T_max = 5.5917 / 16 (PX4 applies THR_MDL_FAC 0.3 itself; the
    # quadratic applied here too would send 0.42269).
    assert s == pytest.approx(hover / 16.0, rel=1e-15) and not clamped
    assert s == pytest.approx(0.34948, abs=1e-5)
    # Above --max-throttle but below T_max: cut to --max-throttle.
    deg_s, s, clamped = attitude_rate_command([0.9 * 16.0, 0.0, 0.0, 0.0], limits)
    assert s == 0.8 and clamped
    deg_s, s, clamped = attitude_rate_command([30.0, 10.0, -10.0, 9.0], limits)
    np.testing.assert_allclose(deg_s, np.degrees([3.5, 3.5, -3.0]))
    assert s == 0.8 and clamped
    deg_s, s, clamped = attitude_rate_command([0.0, 0.0, 0.0, 0.0], limits)
    assert s == 0.0 and not clamped
    for bad in ([math.nan, 0, 0, 0], [1.0, math.inf, 0, 0], [1.0, 0, 0]):
        with pytest.raises(ValueError):
            attitude_rate_command(bad, limits)


@pytest.mark.parametrize("fac", [0.0, 0.3, 0.7, 1.0])
def test_half_the_maximum_thrust_is_half_throttle_for_any_thr_mdl_fac(fac):
    vehicle = {**VEHICLE, "thrust_curve": {"thr_mdl_fac": fac}}
    limits = Limits.from_vehicle(vehicle)
    for thrust_n, expect in ((8.0, 0.5), (4.0, 0.25), (12.0, 0.75), (16.0, 1.0)):
        _, s, clamped = attitude_rate_command([thrust_n, 0.0, 0.0, 0.0], limits)
        assert s == pytest.approx(expect, rel=1e-15) and not clamped
    # Above the vehicle's maximum thrust: full throttle, and flagged.
    _, s, clamped = attitude_rate_command([16.5, 0.0, 0.0, 0.0], limits)
    assert s == 1.0 and clamped


def test_geofence():
    g = Geofence.parse("-1,1,-2,2,0,3")
    assert g.contains([0, 0, 1]) and g.contains([1, 2, 3])
    assert not g.contains([1.01, 0, 1]) and not g.contains([0, -2.5, 1])
    assert not g.contains([0, 0, -0.1]) and not g.contains([0, 0, math.nan])
    for bad in ("1,2,3", "1,0,0,1,0,1", "0,1,0,1,0,nan"):
        with pytest.raises(ValueError):
            Geofence.parse(bad)
