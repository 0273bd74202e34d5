"""PX4 ULog import (arcade_io.ulog, arcade_io.resample, arcade_io.ulog_seed): the array
steps on their own, synthetic ULog-like inputs, and the two real sample logs in
tests/data/ulog (BSD-licensed, from pyulog's tests)."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from arcade_core.frames import from_rpy_np, to_rotation_matrix_np, to_rpy_np
from arcade_io import resample
from arcade_io.ulog import (
    MASS_MISSING,
    ULogError,
    collective_thrust,
    convert,
    looks_like_ulog,
    read_ulog,
    scan_messages,
    state_enu_flu,
)
from arcade_io.ulog_seed import seed_toml, vehicle_seed
from arcade_io.vehicle import DEFAULT_VEHICLE, load_vehicle

DATA = Path(__file__).resolve().parents[1] / "data" / "ulog"
EVENTS = DATA / "sample_px4_events.ulg"  # v1.14 topics, 31 s, one flight to ~2.1 m
SMALL = DATA / "sample_log_small.ulg"  # older topics (actuator_controls_0), a 1.1 s hop
G = 9.81

# ------------------------------------------------------------------ array steps


def test_clean_sorts_drops_repeats_and_non_finite_rows():
    t = np.array([0.0, 0.2, 0.1, 0.2, 0.3, np.nan, 0.4])
    y = np.array([0.0, 2.0, 1.0, 2.5, 3.0, 9.0, np.inf])
    c = resample.clean(t, y)
    np.testing.assert_array_equal(c.t, [0.0, 0.1, 0.2, 0.3])
    # Of the two rows stamped 0.2 the one logged last is kept.
    np.testing.assert_array_equal(c.y[:, 0], [0.0, 1.0, 2.5, 3.0])
    assert (c.out_of_order, c.duplicates, c.non_finite) == (1, 1, 2)


def test_a_gap_splits_the_segment_and_the_longest_piece_is_kept():
    t = np.concatenate([np.arange(0.0, 4.0, 0.01), np.arange(4.5, 12.0, 0.01)])
    dense = np.arange(0.0, 12.0, 0.005)
    assert resample.coverage(t, 0.25) == [(0.0, pytest.approx(3.99)), (4.5, pytest.approx(11.99))]
    airborne = [(1.0, 11.0)]
    seg, flight = resample.usable_segment(airborne, [t, dense], 0.25)
    assert seg == (4.5, 11.0) and flight == (1.0, 11.0)
    # Without the gap the whole airborne interval is usable.
    assert resample.usable_segment(airborne, [dense], 0.25)[0] == (1.0, 11.0)


def test_airborne_intervals_and_the_longest_of_several():
    t = np.array([0.0, 1.0, 2.0, 5.0, 6.0, 9.0])
    landed = np.array([1, 0, 0, 1, 0, 0])
    air = resample.airborne_intervals(t, landed, t_end=20.0)
    assert air == [(1.0, 5.0), (6.0, 20.0)]  # the last one lasts to the end of the log
    assert resample.longest(air) == (6.0, 20.0)
    assert resample.airborne_intervals(t, np.ones(6), 20.0) == []


def test_grid_linear_and_hold():
    g = resample.grid((1.0, 1.05), 100.0)
    np.testing.assert_allclose(g, [1.0, 1.01, 1.02, 1.03, 1.04, 1.05])
    t = np.array([0.0, 1.0, 2.0])
    y = np.array([[0.0, 10.0], [1.0, 20.0], [4.0, 30.0]])
    np.testing.assert_allclose(resample.linear(t, y, [0.5, 1.5]), [[0.5, 15.0], [2.5, 25.0]])
    # Zero-order hold: the last sample at or before each time.
    np.testing.assert_array_equal(resample.hold(t, y, [0.0, 0.99, 1.0, 2.5])[:, 0], [0, 0, 1, 4])


def test_quaternions_are_unit_sign_continuous_and_interpolated_on_the_arc():
    t = np.array([0.0, 1.0, 2.0])
    q90 = from_rpy_np([0.0, 0.0, math.pi / 2])
    q180 = from_rpy_np([0.0, 0.0, math.pi])
    # The middle sample comes with the other sign (a tracker that keeps w >= 0 flips).
    q = np.array([[1.0, 0.0, 0.0, 0.0], -q90, q180])
    out = resample.quaternions(t, q, np.linspace(0.0, 2.0, 9))
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-12)
    assert np.all(np.sum(out[1:] * out[:-1], axis=1) > 0.9)
    np.testing.assert_allclose(to_rpy_np(out[2])[2], math.pi / 4, atol=1e-12)  # halfway
    np.testing.assert_allclose(np.abs(to_rpy_np(out[4])[2]), math.pi / 2, atol=1e-12)


# ------------------------------------------------------------- frames and thrust


def test_heading_east_in_ned_is_yaw_zero_in_enu():
    """PX4 yaw 90 degrees (NED, body FRD) = facing east = the ENU x axis."""
    q_ned = from_rpy_np([0.0, 0.0, math.pi / 2])
    X = state_enu_flu([[1.0, 2.0, -3.0, 0.1, 0.2, -0.3]], q_ned[None], [[0.1, 0.2, 0.3]])
    np.testing.assert_allclose(X[0, :3], [2.0, 1.0, 3.0])  # (n, e, d) -> (e, n, u)
    np.testing.assert_allclose(X[0, 3:6], [0.2, 0.1, 0.3])
    R = to_rotation_matrix_np(X[0, 6:10])
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], atol=1e-12)  # forward: east
    np.testing.assert_allclose(R @ [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)  # left: north
    np.testing.assert_allclose(R @ [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], atol=1e-12)  # up: up
    np.testing.assert_allclose(X[0, 10:], [0.1, -0.2, -0.3])  # FRD -> FLU rates
    assert X[0, 6] > 0.0


def test_nose_up_and_right_roll_keep_their_meaning():
    # PX4: pitch > 0 is nose up, roll > 0 is right side down.
    R = to_rotation_matrix_np(state_enu_flu(np.zeros((1, 6)), from_rpy_np([0, 0.2, 0])[None],
                                            np.zeros((1, 3)))[0, 6:10])  # fmt: skip
    assert (R @ [1.0, 0.0, 0.0])[2] == pytest.approx(math.sin(0.2))  # the nose goes up
    R = to_rotation_matrix_np(state_enu_flu(np.zeros((1, 6)), from_rpy_np([0.2, 0, 0])[None],
                                            np.zeros((1, 3)))[0, 6:10])  # fmt: skip
    assert (R @ [0.0, 1.0, 0.0])[2] == pytest.approx(math.sin(0.2))  # the left side goes up


def test_thrust_is_linear_and_scaled_to_hover():
    # PX4's logged normalised thrust is linear in force (its mixer applies THR_MDL_FAC):
    # the hover command gives m g, twice it 2 m g, whatever the motors' model.
    m = 1.5
    np.testing.assert_allclose(collective_thrust([0.0, 0.4, 0.8], 0.4, m, G),
                               [0.0, m * G, 2 * m * G], rtol=1e-15)  # fmt: skip
    s, h = np.array([0.2, 0.45, 0.9]), 0.45
    np.testing.assert_allclose(collective_thrust(s, h, m, G), m * G * s / h, rtol=1e-15)
    # Clipped to [0, 1] like PX4's setpoint.
    np.testing.assert_allclose(collective_thrust([-0.1, 1.2], 0.5, m, G), [0.0, 2 * m * G])
    for bad in (0.0, -0.2, 1.01):
        with pytest.raises(ULogError, match="hover thrust"):
            collective_thrust(s, bad, m, G)


# ---------------------------------------------------------- synthetic ULog-like logs


def _topic(name, t_s, **fields):
    data = {"timestamp": (np.asarray(t_s) * 1e6).astype(np.uint64) + np.uint64(10**6)}
    data.update({k: np.asarray(v, dtype=float) for k, v in fields.items()})
    return SimpleNamespace(name=name, multi_id=0, data=data)


def _fake_ulog(duration=40.0, air=(5.0, 35.0), rates_sp=True, yaw=math.pi / 2, extra=()):
    """A hover at 2 m, facing east (PX4 yaw 90 degrees), hover thrust 0.5."""
    t50, t100 = np.arange(0, duration, 0.02), np.arange(0, duration, 0.01)
    q = np.tile(from_rpy_np([0.0, 0.0, yaw]), (len(t50), 1))
    n50, n100 = np.zeros(len(t50)), np.zeros(len(t100))
    topics = [
        _topic("vehicle_local_position", t50, x=n50 + 1, y=n50 + 2, z=n50 - 2, vx=n50,
               vy=n50, vz=n50),
        _topic("vehicle_attitude", t50, **{f"q[{i}]": q[:, i] for i in range(4)}),
        _topic("vehicle_angular_velocity", t100, **{"xyz[0]": n100 + 0.1, "xyz[1]": n100 + 0.2,
                                                    "xyz[2]": n100 + 0.3}),
        _topic("vehicle_thrust_setpoint", t100, **{"xyz[2]": n100 - 0.5}),
        _topic("vehicle_land_detected", [0.0, air[0], air[1]], landed=[1, 0, 1]),
        *extra,
    ]  # fmt: skip
    if rates_sp:
        topics.append(_topic("vehicle_rates_setpoint", t50, roll=n50, pitch=n50, yaw=n50 + 0.5))
    return SimpleNamespace(data_list=topics, start_timestamp=10**6, msg_info_dict={},
                           initial_parameters={"MPC_THR_HOVER": 0.5, "MAV_TYPE": 2},
                           changed_parameters=[])  # fmt: skip


def test_synthetic_hover_facing_east():
    imp = convert(_fake_ulog(), 1.2, rate_hz=50.0, min_airborne_s=10.0)
    log, meta = imp.log, imp.meta
    assert meta["segment_s"] == [5.0, pytest.approx(35.0)]
    assert log.dt == pytest.approx(0.02) and log.t[0] == 5.0
    np.testing.assert_allclose(log.X[:, :3], np.tile([2.0, 1.0, 2.0], (len(log), 1)))
    np.testing.assert_allclose(log.X[:, 6:10], np.tile([1.0, 0, 0, 0], (len(log), 1)), atol=1e-12)
    np.testing.assert_allclose(log.X[:, 10:], np.tile([0.1, -0.2, -0.3], (len(log), 1)))
    np.testing.assert_allclose(log.U[:, 0], 1.2 * G)
    np.testing.assert_allclose(log.U[:, 1:], np.tile([0.0, 0.0, -0.5], (len(log), 1)))
    assert meta["thrust_conversion"]["hover_thrust_source"] == "parameter MPC_THR_HOVER"
    assert meta["stand_ins"] == [] and meta["warnings"] == []


@pytest.mark.parametrize("fac", [0.0, 0.6, 1.0])
def test_thrust_import_is_independent_of_thr_mdl_fac(fac):
    """Hover command 0.4 for 15 s, then 0.8: m g, then 2 m g, for any THR_MDL_FAC; the
    parameter is reported, not used."""
    ulog = _fake_ulog()
    ulog.initial_parameters.update({"MPC_THR_HOVER": 0.4, "THR_MDL_FAC": fac})
    ulog.changed_parameters = [("THR_MDL_FAC", 10**7, fac / 2)]
    thr = ulog.data_list[3].data
    t = (thr["timestamp"].astype(np.int64) - 10**6) * 1e-6
    thr["xyz[2]"] = np.where(t < 20.0, -0.4, -0.8)
    imp = convert(ulog, 1.2, rate_hz=50.0, min_airborne_s=10.0)
    log, th = imp.log, imp.meta["thrust_conversion"]
    np.testing.assert_allclose(log.U[log.t < 19.9, 0], 1.2 * G, rtol=1e-12)
    np.testing.assert_allclose(log.U[log.t > 20.1, 0], 2 * 1.2 * G, rtol=1e-12)
    assert th["thr_mdl_fac"] == fac and th["hover_thrust"] == 0.4
    assert th["hover_force_n"] == pytest.approx(1.2 * G)
    assert any("THR_MDL_FAC changes" in w and "does not use it" in w
               for w in imp.meta["warnings"])  # fmt: skip


def test_missing_rate_setpoints_are_stood_in_by_the_measured_rates_and_flagged():
    imp = convert(_fake_ulog(rates_sp=False), 1.0, min_airborne_s=10.0)
    np.testing.assert_allclose(imp.log.U[:, 1:], imp.log.X[:, 10:])
    assert len(imp.meta["stand_ins"]) == 1 and "measured body rates" in imp.meta["stand_ins"][0]
    assert any("stand in for the rate setpoints" in w for w in imp.meta["warnings"])
    assert "rate_setpoints" not in imp.meta["signals"]


def test_out_of_order_and_repeated_stamps_are_repaired_and_reported():
    ulog = _fake_ulog()
    pos = ulog.data_list[0].data
    order = np.arange(len(pos["timestamp"]))
    order[100:102] = [101, 100]  # two samples swapped
    order = np.concatenate([order[:300], [299, 299], order[300:]])  # one repeated twice
    for k in pos:
        pos[k] = pos[k][order]
    imp = convert(ulog, 1.0, min_airborne_s=10.0)
    np.testing.assert_allclose(imp.log.X[:, :3], np.tile([2.0, 1.0, 2.0], (len(imp.log), 1)))
    warn = " ".join(imp.meta["warnings"])
    assert "1 out-of-order samples sorted" in warn
    assert "2 samples with a repeated timestamp dropped" in warn


def test_a_gap_in_a_signal_keeps_the_longest_piece_and_says_so():
    ulog = _fake_ulog()
    att = ulog.data_list[1].data
    t = (att["timestamp"].astype(np.int64) - 10**6) * 1e-6
    keep = (t < 12.0) | (t > 12.5)
    for k in att:
        att[k] = att[k][keep]
    imp = convert(ulog, 1.0, min_airborne_s=10.0)
    a, b = imp.meta["segment_s"]
    assert a == pytest.approx(12.5, abs=0.021) and b == pytest.approx(35.0)
    assert any("is cut to" in w for w in imp.meta["warnings"])


def test_several_airborne_segments_keep_the_longest():
    extra = _topic("vehicle_land_detected", [0.0, 2.0, 6.0, 10.0, 30.0], landed=[1, 0, 1, 0, 1])
    ulog = _fake_ulog()
    ulog.data_list[4] = extra
    imp = convert(ulog, 1.0, min_airborne_s=10.0)
    assert imp.meta["segment_s"] == [10.0, pytest.approx(30.0)]
    assert "2 airborne segments: kept the longest usable one" in imp.meta["warnings"]


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda u: u.data_list.pop(1), "no attitude in the log"),
        (lambda u: u.data_list.pop(3), "no thrust setpoint in the log"),
        (lambda u: u.data_list.pop(4), "no land detector in the log"),
        (lambda u: u.data_list.pop(0), "no position in the log"),
        (lambda u: u.data_list.__setitem__(4, _topic("vehicle_land_detected", [0.0], landed=[1])),
         "never airborne"),
    ],
)  # fmt: skip
def test_unusable_synthetic_logs_raise_one_error(change, match):
    ulog = _fake_ulog()
    change(ulog)
    with pytest.raises(ULogError, match=match):
        convert(ulog, 1.0, min_airborne_s=10.0)


def test_too_short_an_airborne_segment_names_the_option():
    with pytest.raises(ULogError, match=r"30.0 s .*less than the 40 s .*--min-airborne-s"):
        convert(_fake_ulog(), 1.0, min_airborne_s=40.0)


# ------------------------------------------------------------------ the samples


@pytest.fixture(scope="module")
def events():
    return read_ulog(EVENTS, mass_kg=2.0, min_airborne_s=5.0)


@pytest.fixture(scope="module")
def small():
    return read_ulog(SMALL, mass_kg=2.0, min_airborne_s=1.0)


def _check_common(imp):
    log = imp.log
    assert log.system == "quadrotor" and log.dt == pytest.approx(0.01)
    np.testing.assert_allclose(np.diff(log.t), 0.01, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(log.X[:, 6:10], axis=1), 1.0, atol=1e-12)
    assert np.all(np.sum(log.X[1:, 6:10] * log.X[:-1, 6:10], axis=1) > 0.99)  # no sign flip
    assert np.all(np.isfinite(log.X)) and np.all(np.isfinite(log.U))
    a, b = imp.meta["segment_s"]
    assert a == log.t[0] and log.t[-1] <= b  # only the airborne segment
    assert any(x <= a and b <= y for x, y in imp.meta["airborne_segments_s"])


def test_events_sample_v114_topics(events):
    _check_common(events)
    log, meta = events.log, events.meta
    assert meta["signals"]["thrust"] == "vehicle_thrust_setpoint.xyz[2]"
    assert meta["signals"]["rate_setpoints"] == "vehicle_rates_setpoint.roll,pitch,yaw"
    assert meta["stand_ins"] == []
    # One flight: take-off at 16.7 s, landing detected at 28.1 s (of a 31 s log).
    assert meta["segment_s"] == [pytest.approx(16.74, abs=0.01), pytest.approx(28.13, abs=0.01)]
    assert len(log) == 1140
    z = log.X[:, 2]
    mid = (log.t > 20.5) & (log.t < 24.0)
    assert np.all(z[mid] > 1.0)  # ENU: up is positive
    # The climb to ~2.1 m above the take-off point: a peak between 1.8 and 2.5 m.
    assert z.max() == pytest.approx(2.15, abs=0.35)
    climb = (log.t > 19.5) & (log.t < 20.5)
    assert np.all(log.X[climb, 5] > 0.5)  # climbing: vz up
    hover = (log.t > 23.5) & (log.t < 26.0)  # steady descent at 0.7 m/s: about hover thrust
    assert np.median(log.U[hover, 0]) == pytest.approx(2.0 * G, rel=0.05)
    th = meta["thrust_conversion"]
    assert th["hover_thrust"] == pytest.approx(0.49, abs=0.01)
    assert th["hover_thrust_source"].startswith("hover_thrust_estimate")
    # SITL: the vehicle faces north (PX4 yaw ~0), i.e. ENU yaw ~90 degrees.
    assert np.degrees(np.median(to_rpy_np(log.X[:, 6:10])[:, 2])) == pytest.approx(90, abs=3)
    assert any("quat_reset_counter" in w for w in meta["warnings"])


def test_small_sample_old_topics(small):
    _check_common(small)
    log, meta = small.log, small.meta
    assert meta["signals"]["thrust"] == "actuator_controls_0.control[3]"
    assert meta["thrust_conversion"]["hover_thrust_source"] == "parameter MPC_THR_HOVER"
    # Its only "airborne" stretch is a 1.1 s hop of a VTOL (MAV_TYPE 22) without GPS.
    assert meta["segment_s"] == [pytest.approx(2.36, abs=0.01), pytest.approx(3.51, abs=0.01)]
    assert np.all(log.X[:, 2] > 0.0)
    warn = " ".join(meta["warnings"])
    assert "MAV_TYPE 22" in warn and "xy_valid is false" in warn
    # Not a hover: the command is mostly 0.08 of a 0.45 hover thrust, 0.18 m g.
    assert np.median(log.U[:, 0]) == pytest.approx(2.0 * G * 0.08 / 0.45, rel=0.01)


def test_the_default_minimum_airborne_time_refuses_the_samples():
    with pytest.raises(ULogError, match="less than the 30 s"):
        read_ulog(EVENTS, mass_kg=2.0)


def test_mass_from_a_vehicle_file_is_the_models_mass():
    imp = read_ulog(EVENTS, vehicle=DEFAULT_VEHICLE, min_airborne_s=5.0)
    vehicle = load_vehicle()
    mass = vehicle["body"]["mass_kg"] + vehicle["payload"]["electromagnet_mass_kg"]
    assert imp.meta["thrust_conversion"]["mass_kg"] == pytest.approx(mass)  # 0.57 kg
    assert imp.meta["thrust_conversion"]["mass_source"].startswith("vehicle file")
    with pytest.raises(ULogError, match="mass is not in a ULog"):
        read_ulog(EVENTS, min_airborne_s=5.0)
    assert "--mass" in MASS_MISSING and "--vehicle" in MASS_MISSING
    with pytest.raises(ULogError, match="positive"):
        read_ulog(EVENTS, mass_kg=-1.0, min_airborne_s=5.0)


def test_unreadable_files_raise_one_error(tmp_path):
    with pytest.raises(ULogError, match="not found"):
        read_ulog(tmp_path / "none.ulg", mass_kg=1.0)
    (tmp_path / "a.ulg").write_text("t,px\n0,1\n")
    with pytest.raises(ULogError, match="not a ULog file"):
        read_ulog(tmp_path / "a.ulg", mass_kg=1.0)
    with pytest.raises(ULogError, match="directory"):
        read_ulog(tmp_path, mass_kg=1.0)
    assert not looks_like_ulog(tmp_path / "a.ulg") and looks_like_ulog(EVENTS)


def test_truncated_file_is_an_error_unless_allowed(tmp_path):
    data = EVENTS.read_bytes()
    assert scan_messages(data) == (None, None) == scan_messages(SMALL.read_bytes())
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(data[: int(0.97 * len(data))])
    assert scan_messages(cut.read_bytes())[1] is not None
    with pytest.raises(ULogError, match="truncated"):
        read_ulog(cut, mass_kg=2.0, min_airborne_s=5.0)
    imp = read_ulog(cut, mass_kg=2.0, min_airborne_s=5.0, allow_damaged=True)
    assert imp.meta["warnings"][0].startswith("damaged log: the file is truncated")
    assert imp.meta["duration_s"] > 5.0
    (tmp_path / "header.ulg").write_bytes(data[:40])
    with pytest.raises(ULogError):
        read_ulog(tmp_path / "header.ulg", mass_kg=2.0, allow_damaged=True)


def test_damaged_headers_and_data_are_errors(tmp_path):
    data = EVENTS.read_bytes()
    # Random bytes after the magic: refused before pyulog (which can loop forever on them).
    rng = np.random.default_rng(0)
    junk = tmp_path / "junk.ulg"
    junk.write_bytes(data[:16] + b"\x05\x00Z" + rng.bytes(5000))
    with pytest.raises(ULogError, match="corrupted ULog: unknown message type"):
        read_ulog(junk, mass_kg=2.0, allow_damaged=True)
    # Bytes flipped in the data section: pyulog's corruption flag.
    flipped = bytearray(data)
    for i in rng.integers(len(data) // 2, len(data), 200):
        flipped[i] ^= 0xFF
    (tmp_path / "flipped.ulg").write_bytes(bytes(flipped))
    with pytest.raises(ULogError, match="corrupted data"):
        read_ulog(tmp_path / "flipped.ulg", mass_kg=2.0, min_airborne_s=5.0)


def test_the_converted_sample_passes_the_discrepancy_workflows_log_check(events):
    from arcade_core.discrepancy.settings import Settings, check_log

    check_log("quadrotor", len(events.log), events.log.dt, Settings())


# ----------------------------------------------------------------- vehicle seed


def test_vehicle_seed_holds_what_the_log_has_and_lists_the_rest(tmp_path):
    seed = vehicle_seed(EVENTS)
    veh, missing = seed["vehicle"], " ".join(seed["missing"])
    assert veh["rotors"]["count"] == 4 and veh["rotors"]["layout"] == "x"
    assert veh["thrust_curve"]["thr_mdl_fac"] == 0.0
    np.testing.assert_allclose(veh["rate_loop"]["max_rate_rad_s"], np.radians([220, 220, 200]))
    assert veh["px4"]["hover_thrust"] == pytest.approx(0.49, abs=0.01)
    for entry in ("mass_kg", "inertia_kgm2", "motor_time_constant_s", "max_thrust_n"):
        assert entry in missing
    # With the mass, each rotor's maximum thrust: m g / (hover thrust x 4), linear.
    seed = vehicle_seed(EVENTS, 2.0)
    h = seed["vehicle"]["px4"]["hover_thrust"]
    assert seed["vehicle"]["rotors"]["max_thrust_n"] == pytest.approx(2.0 * G / h / 4)
    assert "mass_kg" not in " ".join(seed["missing"])
    # The TOML parses; the project refuses it until what is missing is filled in.
    path = tmp_path / "seed.toml"
    text = seed_toml(seed, "sample")
    path.write_text(text)
    assert tomllib.loads(text)["body"]["mass_kg"] == 2.0
    with pytest.raises(ValueError, match="inertia_kgm2"):
        load_vehicle(path)
    path.write_text(text.replace("[body]\n", "[body]\ninertia_kgm2 = [0.02, 0.02, 0.04]\n"
                                 "size_m = [0.5, 0.5, 0.2]\n")
                    .replace("[rotors]\n", "[rotors]\nmotor_time_constant_s = 0.03\n")
                    .replace("[rate_loop]\n", "[rate_loop]\ntime_constant_s = 0.05\n"))  # fmt: skip
    assert load_vehicle(path)["body"]["mass_kg"] == 2.0


def test_vehicle_seed_of_the_old_vtol_log_says_what_it_cannot_derive():
    seed = vehicle_seed(SMALL)
    missing = " ".join(seed["missing"])
    assert "count" in missing and "arm_length_m" in missing
    assert any("MAV_TYPE 22" in n for n in seed["notes"])


@pytest.mark.parametrize("fac", [0.0, 0.6])
def test_vehicle_seed_keeps_thr_mdl_fac_as_the_motor_model_and_scales_linearly(fac):
    ulog = _fake_ulog()
    ulog.initial_parameters.update({"MPC_THR_HOVER": 0.4, "THR_MDL_FAC": fac})
    veh = vehicle_seed(ulog, 1.2)["vehicle"]
    assert veh["thrust_curve"]["thr_mdl_fac"] == fac
    # m g / (s_hover x rotors): full throttle is m g / s_hover, whatever THR_MDL_FAC.
    assert veh["rotors"]["max_thrust_n"] == pytest.approx(1.2 * G / 0.4 / 4, rel=1e-15)
