"""Injectable effects: validation, and each effect moves the dynamics the documented way."""

from __future__ import annotations

import numpy as np
import pytest

from arcade_io.vehicle import load_vehicle
from simulator import EFFECTS, GyroConfig, QuadrotorSim, load_effects
from simulator.effects import ground_effect_gain

QUIET_GYRO = GyroConfig(noise_rad_s=0.0, bias_std_rad_s=0.0)
DRAG = {"d": [0.4, 0.1, 0.05]}


def coast(effects, duration, **reset):
    """Hold hover thrust (commanded for the nominal vehicle) and zero rates."""
    sim = QuadrotorSim(effects=effects, gyro=QUIET_GYRO)
    sim.reset(**reset)
    sim.set_setpoint([sim.hover_thrust(), 0.0, 0.0, 0.0])
    return sim, sim.step(duration)


# ---------------------------------------------------------------- validation


def test_effect_table_is_complete_data():
    assert set(EFFECTS) == {
        "rotor_drag",
        "quadratic_drag",
        "ground_effect",
        "thrust_scale",
        "motor_lag",
        "rate_lag",
        "com_offset",
        "wind",
        "induced_inflow",
        "battery_sag",
    }
    for params in EFFECTS.values():
        for spec in params.values():
            assert spec.low < spec.high and spec.unit and spec.description
            if spec.default is not None:
                assert np.all(spec.low <= np.asarray(spec.default) <= spec.high)


@pytest.mark.parametrize(
    ("tables", "message"),
    [
        ({"rotor_dragg": {"d": [0.1, 0.1, 0.1]}}, "unknown effect 'rotor_dragg'"),
        ({"rotor_drag": {"dx": 0.1}}, "unknown parameter"),
        ({"rotor_drag": {}}, "missing required parameter 'd'"),
        ({"rotor_drag": {"d": [0.1, 0.1]}}, "list of 3 numbers"),
        ({"thrust_scale": {"scale": 3.0}}, "outside the plausible range"),
        ({"thrust_scale": {"scale": "x"}}, "expected a number"),
        ({"wind": {"velocity_mps": [1.0, 0.0, 0.0]}}, "acts through the drag terms"),
    ],
)
def test_bad_effects_are_rejected_with_a_clear_error(tables, message):
    with pytest.raises(ValueError, match=message):
        load_effects(tables)
    with pytest.raises(ValueError, match=message):
        QuadrotorSim(effects=tables)


def test_effects_file_and_vehicle_table(tmp_path):
    path = tmp_path / "effects.toml"
    path.write_text("[rotor_drag]\nd = [0.4, 0.4, 0.05]\n\n[rate_lag]\ndelay_s = 0.02\n")
    eff = load_effects(path)
    np.testing.assert_allclose(eff.get("rotor_drag", "d"), [0.4, 0.4, 0.05])
    assert eff.get("rate_lag", "time_constant_s") == 0.0  # default filled in
    assert load_effects(eff.to_dict()).to_dict() == eff.to_dict()
    with pytest.raises(FileNotFoundError):
        load_effects(tmp_path / "missing.toml")
    # A vehicle file's [effects] table is applied; an explicit effect replaces it by name.
    vehicle = load_vehicle()
    vehicle["effects"] = {"thrust_scale": {"scale": 0.9}, "rotor_drag": DRAG}
    sim = QuadrotorSim(vehicle, effects={"thrust_scale": {"scale": 1.1}})
    assert sim.effects.get("thrust_scale", "scale") == 1.1
    assert "rotor_drag" in sim.effects


# ---------------------------------------------------------------- directions


def test_rotor_drag_decelerates_along_each_body_axis():
    _, x0 = coast(None, 0.5, velocity=(2.0, 0.0, 0.0))
    assert x0[3] == pytest.approx(2.0, rel=0.01)
    _, x = coast({"rotor_drag": DRAG}, 0.5, velocity=(2.0, 0.0, 0.0))
    assert x[3] == pytest.approx(2.0 * np.exp(-0.4 * 0.5), rel=0.01)  # body x, d_x
    # Yawed 90 deg the world x motion is along body -y: the d_y coefficient acts.
    _, x = coast({"rotor_drag": DRAG}, 0.5, velocity=(2.0, 0.0, 0.0), yaw=np.pi / 2)
    assert x[3] == pytest.approx(2.0 * np.exp(-0.1 * 0.5), rel=0.01)


def test_rotor_drag_grows_with_the_rotor_speed():
    # 1.44 x the hover thrust: every rotor turns 1.2 x as fast, the drag is 1.2 x as large.
    sim = QuadrotorSim(effects={"rotor_drag": DRAG}, gyro=QUIET_GYRO)
    sim.reset(velocity=(2.0, 0.0, 0.0))
    sim.set_setpoint([1.44 * sim.hover_thrust(), 0.0, 0.0, 0.0])
    x = sim.step(0.5)
    assert x[3] == pytest.approx(2.0 * np.exp(-0.4 * 1.2 * 0.5), rel=0.01)


def test_induced_inflow_loses_thrust_climbing_and_with_air_speed():
    eff = {"induced_inflow": {"climb_loss": 0.1, "airspeed_loss": 0.0}}
    sim, _ = coast(eff, 0.02, velocity=(0.0, 0.0, 2.0))
    np.testing.assert_allclose(sim.rotor_thrusts().sum(), 0.8 * sim.hover_thrust(), rtol=0.01)
    eff = {"induced_inflow": {"climb_loss": 0.0, "airspeed_loss": 0.01}}
    sim, _ = coast(eff, 0.02, velocity=(3.0, 0.0, 0.0))
    np.testing.assert_allclose(sim.rotor_thrusts().sum(), 0.91 * sim.hover_thrust(), rtol=0.01)
    eff["wind"] = {"velocity_mps": [3.0, 0.0, 0.0]}  # flying with the wind: no air speed
    eff["rotor_drag"] = DRAG
    sim, _ = coast(eff, 0.02, velocity=(3.0, 0.0, 0.0))
    np.testing.assert_allclose(sim.rotor_thrusts().sum(), sim.hover_thrust(), rtol=1e-3)


def test_battery_sag_lowers_the_thrust_over_the_flight():
    sim, _ = coast({"battery_sag": {"loss_per_min": 0.1}}, 3.0)
    np.testing.assert_allclose(sim.rotor_thrusts().sum(), 0.995 * sim.hover_thrust(), rtol=2e-4)


def test_quadratic_drag_decelerates_like_v_squared():
    c = 0.02
    sim, x = coast({"quadratic_drag": {"c": [c, c, c]}}, 0.5, velocity=(3.0, 0.0, 0.0))
    m = sim.carried_mass()
    assert x[3] == pytest.approx(3.0 / (1.0 + c * 3.0 * 0.5 / m), rel=0.01)


def test_wind_pushes_through_drag():
    eff = {"rotor_drag": {"d": [0.4, 0.4, 0.05]}, "wind": {"velocity_mps": [3.0, -1.0, 0.0]}}
    _, x = coast(eff, 0.5)
    assert x[3] == pytest.approx(3.0 * (1.0 - np.exp(-0.2)), rel=0.02)
    assert x[4] == pytest.approx(-1.0 * (1.0 - np.exp(-0.2)), rel=0.02)


def test_ground_effect_adds_thrust_near_the_floor_only():
    r = 0.0381
    gains = ground_effect_gain(np.array([0.01, 0.05, 0.1, 1.0]), r)
    assert np.all(np.diff(gains) < 0) and gains[-1] == pytest.approx(1.0, abs=1e-3)
    assert ground_effect_gain(np.array([0.0]), r)[0] == pytest.approx(4.0 / 3.0)
    eff = {"ground_effect": {"rotor_radius_m": r}}
    low = {"position": (0.0, 0.0, 0.045)}  # rotor plane 6 cm above the floor
    _, x_nom = coast(None, 0.05, **low)
    _, x = coast(eff, 0.05, **low)
    expected = 9.81 * (ground_effect_gain(np.array([0.06]), r)[0] - 1.0) * 0.05
    assert abs(x_nom[5]) < 1e-3
    assert x[5] == pytest.approx(expected, rel=0.1)
    _, x_high = coast(eff, 0.05)
    assert abs(x_high[5]) < 1e-3


def test_thrust_scale_changes_thrust_for_the_same_command():
    sim, x = coast({"thrust_scale": {"scale": 0.8}}, 0.3)
    np.testing.assert_allclose(sim.rotor_thrusts().sum(), 0.8 * sim.hover_thrust(), rtol=1e-3)
    assert x[5] < -0.3  # sinks at about 0.2 g
    sim.reset()  # reset commands the thrust that hovers the real vehicle
    assert sim.setpoint[0] == pytest.approx(sim.hover_thrust() / 0.8)
    assert abs(sim.step(0.3)[5]) < 1e-2


@pytest.mark.parametrize("tau", [None, 0.1])
def test_motor_lag_sets_the_thrust_time_constant(tau):
    eff = None if tau is None else {"motor_lag": {"time_constant_s": tau}}
    sim = QuadrotorSim(effects=eff, gyro=QUIET_GYRO)
    hover = sim.hover_thrust()
    sim.set_setpoint([hover + 2.0, 0.0, 0.0, 0.0])
    sim.step(0.025)
    tau = 0.025 if tau is None else tau
    rise = sim.rotor_thrusts().sum() - hover
    assert rise == pytest.approx(2.0 * (1.0 - np.exp(-0.025 / tau)), rel=1e-3)


def _roll_response(effects, duration=0.2):
    sim = QuadrotorSim(effects=effects, gyro=QUIET_GYRO)
    sim.set_setpoint([sim.hover_thrust(), 1.0, 0.0, 0.0])
    w = np.array([sim.step(0.002)[10] for _ in range(round(duration / 0.002))])
    return np.arange(1, len(w) + 1) * 0.002, w


def test_rate_lag_delays_and_slows_the_rate_response():
    t, w0 = _roll_response(None)
    _, w1 = _roll_response({"rate_lag": {"delay_s": 0.03}})
    k = int(np.argmin(np.abs(t - 0.03)))
    assert np.all(np.abs(w1[: k - 1]) < 1e-6) and w0[k] > 0.2
    t63 = [t[np.argmax(w >= 0.632)] for w in (w0, w1)]
    assert t63[1] - t63[0] == pytest.approx(0.03, abs=0.003)
    _, w2 = _roll_response({"rate_lag": {"time_constant_s": 0.05}})
    assert t[np.argmax(w2 >= 0.632)] > t63[0] + 0.03


def test_com_offset_pitches_the_vehicle_towards_the_offset():
    _, x0 = coast(None, 0.3)
    sim, x = coast({"com_offset": {"offset_m": [0.01, 0.0, 0.0]}}, 0.3)
    # Centre of mass forward: the rear rotors win, the nose drops (positive FLU pitch).
    assert abs(x0[8]) < 1e-4
    assert x[8] > 5e-3
    assert sim.rate_controller.integral[1] < -0.005  # the integrator pushes back
    _, x2 = coast({"com_offset": {"offset_m": [0.0, -0.01, 0.0]}}, 0.3)
    assert x2[7] > 5e-3  # centre of mass right: right side drops (positive roll)
