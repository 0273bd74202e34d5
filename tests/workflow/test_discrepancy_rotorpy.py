"""The discrepancy workflow on flights of an independent simulator (RotorPy).

RotorPy (PyPI ``rotorpy``, a test dependency) models a quadrotor with standard rotor
aerodynamics: rotor drag proportional to each rotor's speed in all three body axes
(``k_d``, ``k_z``), parasitic drag and translational lift (``k_h``). Its own geometric
controller (``SE3Control``, collective thrust and body rates) flies a figure-eight
Lissajous path at up to 3 m/s for 60 s; the states are logged at 100 Hz with the
project's standard sensor noise, the commanded thrust and body rates as the inputs. The
vehicle file is built from RotorPy's AscTec Hummingbird parameters (mass, inertia, arm,
thrust and yaw-moment coefficients, motor time constant, its body-rate loop
``wdot = k_w (w_cmd - w)``) and knows nothing of the aerodynamics. RotorPy's dynamics
(``Multirotor._s_dot_fn``: rigid body, motors, aerodynamics) are integrated with a fixed
RK4 step of 5 ms instead of its adaptive ``solve_ivp`` per control step, which is 2-3x
slower and not more accurate at this step.

With RotorPy's aerodynamics on, the workflow must name a drag effect, add it, and lower
the held-out one-step RMSE of the components it acts on by at least 30 %; with them off
it must name no drag effect. The first flight goes through the library function, the
second through ``arcade discrepancy`` (CSV log and vehicle file); each is flown once.
"""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from rotorpy.controllers.quadrotor_control import SE3Control
from rotorpy.trajectories.lissajous_traj import TwoDLissajous
from rotorpy.vehicles.hummingbird_params import quad_params
from rotorpy.vehicles.multirotor import Multirotor

from arcade import cli
from arcade_io.discrepancy import run_workflow
from arcade_io.flightlog import from_arrays, write_log
from arcade_io.vehicle import load_vehicle
from simulator.log_flights import add_quadrotor_noise

DURATION_S = 60.0
DT = 0.01
SUBSTEPS = 2
WARMUP_S = 2.0
DRAG_EFFECTS = {"rotor_drag", "quadratic_drag"}


def rotorpy_vehicle() -> dict:
    """A vehicle file with RotorPy's Hummingbird parameters and no aerodynamic effect."""
    qp = quad_params
    veh = copy.deepcopy(load_vehicle())
    veh.pop("effects", None)
    inertia = [qp["Ixx"], qp["Iyy"], qp["Izz"]]
    arm = float(np.linalg.norm(qp["rotor_pos"]["r1"]))
    max_thrust = qp["k_eta"] * qp["rotor_speed_max"] ** 2
    yaw_coeff = qp["k_m"] / qp["k_eta"]
    lever = arm / np.sqrt(2.0)
    torque_max = [2 * lever * max_thrust, 2 * lever * max_thrust, 2 * yaw_coeff * max_thrust]
    veh["body"].update(mass_kg=qp["mass"], inertia_kgm2=inertia, arm_length_m=arm)
    veh["rotors"].update(
        max_thrust_n=max_thrust,
        motor_time_constant_s=qp["tau_m"],
        yaw_moment_coeff_m=yaw_coeff,
        rotor_radius_m=qp["rotor_radius"],
    )
    # RotorPy's body-rate loop: torque = J k_w (w_cmd - w), a P loop in normalised torque.
    k_w = qp["k_w"]
    veh["rate_loop"].update(
        time_constant_s=1.0 / k_w,
        p=[inertia[i] * k_w / torque_max[i] for i in range(3)],
        i=[0.0] * 3,
        d=[0.0] * 3,
        ff=[0.0] * 3,
    )
    veh["payload"]["electromagnet_mass_kg"] = 0.0
    return veh


def fly_rotorpy(aero: bool, seed: int):
    """A 100 Hz :class:`~arcade_io.flightlog.FlightLog` of RotorPy flying its figure-eight."""
    qp = quad_params
    path = TwoDLissajous(A=2.5, B=3.0, a=1.0, b=0.5, height=1.5)  # up to 3 m/s
    hover = np.sqrt(qp["mass"] * 9.81 / (4 * qp["k_eta"]))
    start = path.update(-WARMUP_S)
    state = {
        "x": start["x"].copy(),
        "v": start["x_dot"].copy(),
        "q": np.array([0.0, 0.0, 0.0, 1.0]),  # scalar last
        "w": np.zeros(3),
        "wind": np.zeros(3),
        "rotor_speeds": np.full(4, hover),
    }
    vehicle = Multirotor(qp, initial_state=state, control_abstraction="cmd_ctbr", aero=aero)
    control = SE3Control(qp)
    n = round(DURATION_S / DT) + 1
    X, U = np.empty((n, 13)), np.empty((n, 4))
    h = DT / SUBSTEPS
    for k in range(-round(WARMUP_S / DT), n):
        c = control.update(k * DT, state, path.update(k * DT))
        if k >= 0:
            q = state["q"]
            X[k] = np.r_[state["x"], state["v"], q[3], q[:3], state["w"]]
            U[k] = np.r_[c["cmd_thrust"], c["cmd_w"]]
        cmd = np.clip(
            vehicle.get_cmd_motor_speeds(state, c), vehicle.rotor_speed_min, vehicle.rotor_speed_max
        )
        s = Multirotor._pack_state(state)
        for _ in range(SUBSTEPS):  # classical RK4 of RotorPy's state derivative
            k1 = vehicle._s_dot_fn(0.0, s, cmd)
            k2 = vehicle._s_dot_fn(0.0, s + 0.5 * h * k1, cmd)
            k3 = vehicle._s_dot_fn(0.0, s + 0.5 * h * k2, cmd)
            k4 = vehicle._s_dot_fn(0.0, s + h * k3, cmd)
            s = s + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
        state = Multirotor._unpack_state(s)
        state["q"] = state["q"] / np.linalg.norm(state["q"])
    X = add_quadrotor_noise(X, np.random.default_rng(seed), 1.0, DT)
    return from_arrays("quadrotor", np.arange(n) * DT, X, U)


@pytest.fixture(scope="module")
def with_aero():
    """RotorPy's flight with its aerodynamics on and the workflow's result (library)."""
    log = fly_rotorpy(aero=True, seed=1)
    assert np.max(np.linalg.norm(log.X[:, 3:6], axis=1)) > 2.5  # the path is flown
    return log, run_workflow(log, "quadrotor", vehicle=rotorpy_vehicle()).result


def test_rotorpy_drag_is_named_added_and_lowers_the_heldout_gap(with_aero):
    _, result = with_aero
    added = [e for e in result["effects"] if e["added"]]
    drag = [e for e in added if e["name"] in DRAG_EFFECTS]
    assert drag, result["summary"]
    for e in drag:
        ho = e["heldout"]
        assert ho["confirmed"] and ho["after"] <= 0.7 * ho["before"], ho
    assert result["heldout_rmse_after"] <= 0.7 * result["heldout_rmse_before"]
    # RotorPy's horizontal rotor drag: k_d x (sum of hover rotor speeds) / m.
    qp = quad_params
    hover_sum = 4 * np.sqrt(qp["mass"] * 9.81 / (4 * qp["k_eta"]))
    rotor = next((e for e in drag if e["name"] == "rotor_drag"), None)
    if rotor is not None:
        d_true = qp["k_d"] * hover_sum / qp["mass"]
        np.testing.assert_allclose(rotor["params"]["d"][:2], d_true, rtol=0.2)


def _toml(tables: dict) -> str:
    """A vehicle file's text (top-level scalars, then one level of tables)."""

    def value(v):
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list | tuple):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(float(v)) if not isinstance(v, bool) else str(v).lower()

    lines = [f"{k} = {value(v)}" for k, v in tables.items() if not isinstance(v, dict)]
    for name, table in tables.items():
        if isinstance(table, dict):
            lines += ["", f"[{name}]"] + [f"{k} = {value(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


def test_without_rotorpy_aerodynamics_no_drag_is_named(tmp_path, capsys):
    """Through the command line: the CSV log and a vehicle file, as a user runs it."""
    log = fly_rotorpy(aero=False, seed=0)
    csv, vehicle = tmp_path / "rotorpy.csv", tmp_path / "hummingbird.toml"
    write_log(csv, log)
    vehicle.write_text(_toml(rotorpy_vehicle()))
    out = tmp_path / "out"
    argv = ["discrepancy", str(csv), "--vehicle", str(vehicle), "--json", "--out", str(out)]
    assert cli.main(argv) == 0
    result = json.loads(capsys.readouterr().out)
    named = {e["name"] for e in result["effects"] if e["added"]}
    assert not named & DRAG_EFFECTS, result["summary"]
    assert result["heldout_rmse_after"] <= result["heldout_rmse_before"]
    assert (out / "report.md").stat().st_size > 0
