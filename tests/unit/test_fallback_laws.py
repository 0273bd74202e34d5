"""The hand-written fallback laws, flown on the MuJoCo quadrotor: the controller's level
hover (no position feedback: stale mocap, failed solves) levels a tilted vehicle and never
feeds the tilt back; the simulator's position hold (its failsafe) returns to the hold
point."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from arcade_control.hover import hold_setpoint, level_hover
from simulator import QuadrotorSim


def _quat(axis, angle: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.r_[math.cos(angle / 2), math.sin(angle / 2) * a]


def _tilt_deg(q: np.ndarray) -> float:
    cos_tilt = 1 - 2 * (q[1] ** 2 + q[2] ** 2)
    return math.degrees(math.acos(np.clip(cos_tilt, -1.0, 1.0)))


@pytest.mark.parametrize(
    ("axis", "rate_index"), [((1, 0, 0), 1), ((0, 1, 0), 2), ((1, 0, 0), None)]
)
def test_level_hover_rates_oppose_the_tilt(axis, rate_index):
    if rate_index is None:  # level: no rates, the hover thrust itself
        np.testing.assert_allclose(level_hover(_quat(axis, 0.0), 6.0), [6.0, 0, 0, 0])
        return
    u = level_hover(_quat(axis, 0.2), 6.0)
    assert u[rate_index] < 0.0 and u[3] == 0.0
    assert u[0] == pytest.approx(6.0 / math.cos(0.2))
    u = level_hover(_quat(axis, -0.2), 6.0)
    assert u[rate_index] > 0.0


def test_level_hover_levels_the_simulated_vehicle():
    # 25 degrees of tilt, the setpoint held over 50 ms control periods like the stack's.
    sim = QuadrotorSim(payload_mass=0.0, seed=0)
    sim.reset((0.0, 0.0, 2.0))
    sim.data.qpos[3:7] = _quat((0.6, 0.8, 0.0), math.radians(25.0))
    mujoco.mj_forward(sim.model, sim.data)
    x = sim.state()
    tilts = [_tilt_deg(x[6:10])]
    for _ in range(40):
        sim.set_setpoint(level_hover(x[6:10], sim.hover_thrust()))
        x = sim.step(0.05)
        tilts.append(_tilt_deg(x[6:10]))
    assert tilts[0] == pytest.approx(25.0, abs=0.5)
    # Gain 2 rad/s per unit tilt: about exp(-2 t) of the tilt, never growing.
    assert np.all(np.diff(tilts) < 0.0) and tilts[10] < 10.0 and tilts[-1] < 1.0, tilts
    assert abs(x[2] - 2.0) < 0.3 and np.linalg.norm(x[10:13]) < 0.05


def test_the_simulators_position_hold_returns_to_the_hold_point():
    sim = QuadrotorSim(payload_mass=0.0, seed=0)
    sim.reset((0.3, -0.2, 1.8))
    sim.data.qpos[3:7] = _quat((0.6, 0.8, 0.0), math.radians(15.0))
    mujoco.mj_forward(sim.model, sim.data)
    x = sim.state()
    hover = sim.hover_thrust()
    goal = np.array([0.0, 0.0, 2.0])
    for _ in range(60):  # 3 s
        sim.set_setpoint(hold_setpoint(x, goal, hover, hover / 9.81, 16.0))
        x = sim.step(0.05)
    assert np.linalg.norm(x[:3] - goal) < 0.02 and np.linalg.norm(x[3:6]) < 0.02
    assert _tilt_deg(x[6:10]) < 1.0
