"""The discrepancy workflow on quadrotor logs in which an effect is hidden.

Every log is a 90 s flight of the standard exciting trajectory (``arcade simulate``) with
sensor noise on, simulated once per case; the workflow is told nothing about what was
injected. Parameters are drawn at random (fixed seed) from the library's *plausible* range,
from the effect's documented minimum detectable magnitude up (``catalog.DETECTABLE``: below
it no model can halve the one-step gap, so the requirement cannot hold there; how it was
measured is in the catalogue's docstring). Vector effects draw every component; the ones
that decide detectability (the horizontal axes of the drag terms, which the trajectory
excites most) from the detectable part of the range.
"""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest

from arcade import cli
from arcade_core.discrepancy import quadrotor as qm
from arcade_core.discrepancy.catalog import DETECTABLE, QUADROTOR_EFFECTS, magnitude
from arcade_core.discrepancy.settings import Settings, log_blocks
from arcade_io.discrepancy import quad_model_from_vehicle, run_workflow, write_model_file
from arcade_io.flightlog import from_arrays
from arcade_io.vehicle import load_vehicle
from simulator import QuadrotorSim
from simulator.log_flights import fly_quadrotor

DURATION_S = 90.0
#: Known drag of the vehicle in the wind case (wind only acts through drag).
VEHICLE_DRAG = [0.4, 0.4, 0.1]
#: Motor time constant of the default vehicle file [s].
MOTOR_TAU = 0.025


def _range(name: str, param: str) -> tuple[float, float]:
    spec = QUADROTOR_EFFECTS[name].params[param]
    return spec.low, spec.high


def _detectable(rng, name: str, lo: float, hi: float) -> float:
    """Uniform in ``[max(lo, detectable), hi]``."""
    return float(rng.uniform(max(lo, DETECTABLE[name]), hi))


def _signed(rng, name: str, hi: float) -> float:
    """Magnitude in ``[detectable, hi]`` with a random sign."""
    return float(rng.choice([-1.0, 1.0])) * _detectable(rng, name, 0.0, hi)


def _rotor_drag(r):
    lo, hi = _range("rotor_drag", "d")
    return {"d": [_detectable(r, "rotor_drag", lo, hi) for _ in range(2)] + [r.uniform(lo, hi)]}


def _quadratic_drag(r):
    lo, hi = _range("quadratic_drag", "c")
    c = [_detectable(r, "quadratic_drag", lo, hi) for _ in range(2)] + [r.uniform(lo, hi)]
    return {"c": c}


def _motor_lag(r):
    lo, hi = _range("motor_lag", "time_constant_s")
    faster = MOTOR_TAU - lo > DETECTABLE["motor_lag"] and r.uniform() < 0.5
    step = _detectable(r, "motor_lag", 0.0, (MOTOR_TAU - lo) if faster else (hi - MOTOR_TAU))
    return {"time_constant_s": MOTOR_TAU - step if faster else MOTOR_TAU + step}


def _rate_lag(r):
    (_, d_hi), (_, f_hi) = _range("rate_lag", "delay_s"), _range("rate_lag", "time_constant_s")
    while True:  # uniform over the box, above the detectable total lag
        delay, filt = r.uniform(0.0, d_hi), r.uniform(0.0, f_hi)
        if delay + filt >= DETECTABLE["rate_lag"]:
            return {"delay_s": delay, "time_constant_s": filt}


def _com_offset(r):
    # Any direction in the horizontal plane; the vertical offset makes no thrust torque
    # (the model leaves it at the vehicle file's value), so it stays 0 here.
    _, hi = _range("com_offset", "offset_m")
    a = r.uniform(0.0, 2.0 * np.pi)
    length = _detectable(r, "com_offset", 0.0, hi)
    return {"offset_m": [length * np.cos(a), length * np.sin(a), 0.0]}


def _wind(r):
    # Horizontal wind of any direction (the trajectory flies horizontally: vertical air
    # speed is mostly the wind's own, see the module docstring of simulate).
    _, hi = _range("wind", "velocity_mps")
    a = r.uniform(0.0, 2.0 * np.pi)
    speed = _detectable(r, "wind", 0.0, hi)
    return {"velocity_mps": [speed * np.cos(a), speed * np.sin(a), 0.0]}


def _induced_inflow(r):
    # The horizontal air-speed term alone is above the detectable magnitude (the path
    # flies mostly horizontally); the climb term anywhere in its range.
    _, c_hi = _range("induced_inflow", "climb_loss")
    _, h_hi = _range("induced_inflow", "airspeed_loss")
    k_h = float(r.choice([-1.0, 1.0])) * r.uniform(DETECTABLE["induced_inflow"] / 9.0, h_hi)
    return {"climb_loss": r.uniform(0.0, c_hi), "airspeed_loss": k_h}


#: Per effect: parameters drawn from the detectable part of the plausible range.
DRAW = {
    "rotor_drag": _rotor_drag,
    "quadratic_drag": _quadratic_drag,
    "ground_effect": lambda r: {
        "rotor_radius_m": _detectable(
            r, "ground_effect", *_range("ground_effect", "rotor_radius_m")
        )
    },
    "thrust_scale": lambda r: {"scale": 1.0 + _signed(r, "thrust_scale", 0.5)},
    "motor_lag": _motor_lag,
    "rate_lag": _rate_lag,
    "com_offset": _com_offset,
    "wind": _wind,
    "induced_inflow": _induced_inflow,
    "battery_sag": lambda r: {
        "loss_per_min": _detectable(r, "battery_sag", *_range("battery_sag", "loss_per_min"))
    },
}


#: Seed of each case (effects added to the library later come last, so that the earlier
#: cases keep their flights).
CASE_SEEDS = (
    "com_offset", "ground_effect", "motor_lag", "quadratic_drag", "rate_lag", "rotor_drag",
    "thrust_scale", "wind", "induced_inflow", "battery_sag",
)  # fmt: skip


def _vehicle(name):
    veh = load_vehicle()
    if name == "wind":
        veh["effects"] = {"rotor_drag": {"d": VEHICLE_DRAG}}
    return veh


@functools.cache
def _case(name):
    """(injected parameters, workflow result, log) for one hidden effect, simulated once."""
    seed = CASE_SEEDS.index(name)
    rng = np.random.default_rng(100 + seed)
    params = DRAW[name](rng)
    veh = _vehicle(name)
    log = fly_quadrotor({name: params}, DURATION_S, seed=seed, vehicle=veh)
    return params, run_workflow(log, "quadrotor", vehicle=veh).result, log


@pytest.fixture(scope="module", params=sorted(QUADROTOR_EFFECTS))
def single(request):
    """(effect name, injected parameters, workflow result, log) for one hidden effect."""
    return (request.param, *_case(request.param))


def test_every_library_effect_has_a_test_case():
    assert set(DRAW) == set(QUADROTOR_EFFECTS) == set(DETECTABLE) == set(CASE_SEEDS)


def test_draws_cover_the_detectable_part_of_the_plausible_range():
    rng = np.random.default_rng(0)
    for name, draw in DRAW.items():
        for _ in range(20):
            params = draw(rng)
            assert magnitude(name, params, load_vehicle()) >= DETECTABLE[name]
            for k, v in params.items():
                lo, hi = _range(name, k)
                assert np.all(lo <= np.asarray(v)) and np.all(np.asarray(v) <= hi), (name, k, v)


def test_hidden_effect_is_named_first_with_confidence(single):
    name, _, result, _ = single
    assert result["effects"], result["summary"]
    first = result["effects"][0]
    assert first["name"] == name, result["summary"]
    assert first["added"] and first["confidence"] >= 0.9
    assert not result["no_confident_effect"]


def test_hidden_effect_parameters_are_recovered_within_20_percent(single):
    name, params, result, _ = single
    found = next(e for e in result["effects"] if e["name"] == name)
    true = np.concatenate([np.ravel(v) for v in params.values()])
    est = np.concatenate([np.ravel(found["params"][k]) for k in params])
    assert np.linalg.norm(est - true) <= 0.2 * np.linalg.norm(true), (est, true)
    for k, iv in found["interval"].items():  # intervals bracket the estimate
        lo, hi = np.asarray(iv).T
        assert np.all(lo <= np.ravel(found["params"][k]) + 1e-12)
        assert np.all(np.ravel(found["params"][k]) <= hi + 1e-12)


def test_heldout_one_step_gap_shrinks_by_half(single):
    _, _, result, _ = single
    assert result["heldout_rmse_after"] <= 0.5 * result["heldout_rmse_before"], (
        result["heldout_components"], result["heldout_rmse_before"],
        result["heldout_rmse_after"])  # fmt: skip
    for c in result["heldout_components"]:
        assert result["gap_after"][c] < result["gap_before"][c]


def test_a_log_at_another_rate_works_the_same():
    params, _, log = _case("rotor_drag")
    # 20 Hz, the rate at which the pilot changes its setpoint (the inputs stay a
    # zero-order hold per row, as the log format says).
    slow = from_arrays("quadrotor", log.t[::5], log.X[::5], log.U[::5])
    result = run_workflow(slow, "quadrotor").result
    first = result["effects"][0]
    assert first["name"] == "rotor_drag" and first["confidence"] >= 0.9
    assert result["step_s"] == pytest.approx(0.05)
    est, true = np.asarray(first["params"]["d"]), np.asarray(params["d"])
    assert np.linalg.norm(est - true) <= 0.2 * np.linalg.norm(true)


def test_no_hidden_effect_gives_no_confident_effect(tmp_path):
    log = fly_quadrotor({}, DURATION_S, seed=42)
    outcome = run_workflow(log, "quadrotor")
    result = outcome.result
    assert result["no_confident_effect"] and result["summary"].startswith("no confident effect")
    assert not any(e["added"] for e in result["effects"])
    assert all(e["confidence"] < 0.9 for e in result["effects"])
    assert result["heldout_rmse_after"] == result["heldout_rmse_before"]
    # The standard trajectory could show every effect the model can express; wind acts
    # through drag, which this vehicle's model does not have.
    assert result["cannot_tell"] == [] and not result["not_enough_excitation"]
    assert result["no_influence"] == ["wind"]
    assert all(v >= 3**0.5 for k, v in result["reach"].items() if k != "wind")
    # The model file is the vehicle file unchanged: nothing added.
    model_file = write_model_file(tmp_path, "quadrotor", None, outcome.model_effects)
    assert "effects" not in load_vehicle(model_file)


def test_an_effect_below_detectability_is_reported_not_added():
    # Rotor drag of 0.1 1/s: the bootstrap selects it (it is there), but on this trajectory
    # it changes the one-step prediction by less than sqrt(3) noise levels, so no model
    # could halve the gap: it is reported as below detectability, not added as a guess.
    log = fly_quadrotor({"rotor_drag": {"d": [0.1, 0.1, 0.05]}}, DURATION_S, seed=0)
    result = run_workflow(log, "quadrotor").result
    assert result["no_confident_effect"] and not any(e["added"] for e in result["effects"])
    assert result["below_detectability"] == ["rotor_drag"], result["summary"]
    assert result["summary"] == "no confident effect; below detectability: rotor_drag"
    drag = next(e for e in result["effects"] if e["name"] == "rotor_drag")
    assert drag["below_detectability"] and drag["visibility"] < 3**0.5
    assert drag["confidence"] >= 0.9  # selected: it is real, but within the noise
    assert DETECTABLE["rotor_drag"] > 0.1  # consistent with the documented limit
    assert result["heldout_rmse_after"] == result["heldout_rmse_before"]


def test_an_effect_the_heldout_data_contradict_is_not_added():
    # The thrust is 20 % weaker than logged in the fitted blocks, but the log's held-out
    # blocks record the thrust delivered (as if the logging had changed between them):
    # thrust_scale is named on the fit, and adding it would make the held-out prediction
    # worse. It is listed as not confirmed, with both numbers, and not added.
    log = fly_quadrotor({"thrust_scale": {"scale": 0.8}}, DURATION_S, seed=3)
    U = log.U.copy()
    for a, b, held in log_blocks(Settings(), len(log.t), log.dt):
        if held:
            U[a:b, 0] *= 0.8
    result = run_workflow(from_arrays("quadrotor", log.t, log.X, U), "quadrotor").result
    assert result["not_confirmed_on_heldout"] == ["thrust_scale"], result["summary"]
    scale = next(e for e in result["effects"] if e["name"] == "thrust_scale")
    assert scale["confidence"] >= 0.9 and not scale["added"]
    gate = scale["heldout"]
    assert not gate["confirmed"] and gate["after"] > gate["before"]
    assert "vz" in gate["components"]
    assert "not confirmed on held-out data: thrust_scale (" in result["summary"]
    assert result["no_confident_effect"]
    assert result["heldout_rmse_after"] == result["heldout_rmse_before"]


def test_two_hidden_effects_through_the_command_line(tmp_path, capsys):
    effects = tmp_path / "effects.toml"
    effects.write_text(
        "[rotor_drag]\nd = [0.7, 0.6, 0.2]\n\n[rate_lag]\ndelay_s = 0.02\ntime_constant_s = 0.03\n"
    )
    log = tmp_path / "log.csv"
    assert (
        cli.main(
            [
                "simulate",
                "--system",
                "quadrotor",
                "--effects",
                str(effects),
                "--duration",
                str(DURATION_S),
                "--seed",
                "7",
                "--out",
                str(log),
            ]
        )
        == 0
    )
    capsys.readouterr()
    out = tmp_path / "out"
    assert (
        cli.main(["discrepancy", str(log), "--system", "quadrotor", "--json", "--out", str(out)])
        == 0
    )
    result = json.loads(capsys.readouterr().out)
    for key in (
        "effects",
        "gap_before",
        "gap_after",
        "heldout_rmse_before",
        "heldout_rmse_after",
        "model_file",
    ):
        assert key in result
    added = {e["name"]: e for e in result["effects"] if e["added"]}
    assert set(added) == {"rotor_drag", "rate_lag"}
    assert all(e["confidence"] >= 0.9 and e["interval"] for e in added.values())
    assert result["heldout_rmse_after"] < 0.5 * result["heldout_rmse_before"]
    for name in ("report.md", "gap_per_component.png", "heldout_residuals.png"):
        assert (out / name).stat().st_size > 0
    assert "rotor_drag" in (out / "report.md").read_text()

    # The updated vehicle file: the nominal model, the simulator and the JAX model read it.
    veh = load_vehicle(result["model_file"])
    assert set(veh["effects"]) == {"rotor_drag", "rate_lag"}
    np.testing.assert_allclose(
        veh["effects"]["rotor_drag"]["d"], added["rotor_drag"]["params"]["d"]
    )
    sim = QuadrotorSim(vehicle=result["model_file"])
    assert sim.effects.get("rate_lag", "delay_s") == pytest.approx(
        added["rate_lag"]["params"]["delay_s"]
    )
    model = quad_model_from_vehicle(veh)
    theta = qm.theta_from_effects(model, veh["effects"])
    assert float(theta[9]) == pytest.approx(added["rate_lag"]["params"]["delay_s"])
    # Against the updated model the same log has nothing left to explain.
    assert (
        cli.main(
            [
                "discrepancy",
                str(log),
                "--system",
                "quadrotor",
                "--json",
                "--vehicle",
                result["model_file"],
                "--out",
                str(tmp_path / "again"),
            ]
        )
        == 0
    )
    again = json.loads(capsys.readouterr().out)
    assert again["no_confident_effect"], again["summary"]
