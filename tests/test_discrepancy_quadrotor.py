"""The discrepancy workflow on quadrotor logs in which an effect is hidden.

Every log is a 90 s flight of the standard exciting trajectory (``arcade simulate``) with
sensor noise on, simulated once per case; the workflow is told nothing about what was
injected. Parameters are drawn at random (fixed seed) from the part of each plausible range
where the effect is observable in that flight at that noise level and the pilot still flies
(:data:`TEST_RANGES`): a rotor radius of 1 cm would not change the thrust measurably at the
trajectory's lowest height, and a rate loop lagging by 0.1 s makes the pilot's attitude
loop oscillate into the rate and mixer limits, where no linear rate model predicts well.
"""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest

from arcade import cli
from arcade.commands.discrepancy import quad_model_from_vehicle, run_workflow
from arcade.commands.simulate import fly_quadrotor
from arcade.flightlog import from_arrays
from arcade.vehicle import load_vehicle
from arcade_core.discrepancy import quadrotor as qm
from arcade_core.discrepancy.catalog import QUADROTOR_EFFECTS
from simulator import QuadrotorSim

DURATION_S = 90.0
#: Known drag of the vehicle in the wind case (wind only acts through drag).
VEHICLE_DRAG = [0.4, 0.4, 0.1]


def _mag(rng, lo, hi):
    return float(rng.choice([-1.0, 1.0]) * rng.uniform(lo, hi))


#: Per effect: parameters drawn inside the plausible range where the flight shows them.
TEST_RANGES = {
    "rotor_drag": lambda r: {"d": [r.uniform(0.5, 1.0), r.uniform(0.5, 1.0),
                                   r.uniform(0.1, 0.4)]},
    "quadratic_drag": lambda r: {"c": [r.uniform(0.15, 0.2), r.uniform(0.15, 0.2),
                                       r.uniform(0.1, 0.2)]},
    "ground_effect": lambda r: {"rotor_radius_m": r.uniform(0.15, 0.2)},
    "thrust_scale": lambda r: {"scale": 1.0 + _mag(r, 0.1, 0.3)},
    "motor_lag": lambda r: {"time_constant_s": r.uniform(0.05, 0.1)},
    "rate_lag": lambda r: {"delay_s": r.uniform(0.01, 0.03),
                           "time_constant_s": r.uniform(0.02, 0.04)},
    "com_offset": lambda r: {"offset_m": [_mag(r, 0.005, 0.015), _mag(r, 0.005, 0.015), 0.0]},
    "wind": lambda r: {"velocity_mps": [_mag(r, 2.0, 5.0), _mag(r, 2.0, 5.0), 0.0]},
}  # fmt: skip


def _vehicle(name):
    veh = load_vehicle()
    if name == "wind":
        veh["effects"] = {"rotor_drag": {"d": VEHICLE_DRAG}}
    return veh


@functools.cache
def _case(name):
    """(injected parameters, workflow result, log) for one hidden effect, simulated once."""
    seed = sorted(QUADROTOR_EFFECTS).index(name)
    rng = np.random.default_rng(100 + seed)
    params = TEST_RANGES[name](rng)
    veh = _vehicle(name)
    log = fly_quadrotor({name: params}, DURATION_S, seed=seed, vehicle=veh)
    return params, run_workflow(log, "quadrotor", vehicle=veh).result, log


@pytest.fixture(scope="module", params=sorted(QUADROTOR_EFFECTS))
def single(request):
    """(effect name, injected parameters, workflow result, log) for one hidden effect."""
    return (request.param, *_case(request.param))


def test_every_library_effect_has_a_test_case():
    assert set(TEST_RANGES) == set(QUADROTOR_EFFECTS)


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
    result = run_workflow(log, "quadrotor", out=tmp_path).result
    assert result["no_confident_effect"] and result["summary"] == "no confident effect"
    assert not any(e["added"] for e in result["effects"])
    assert all(e["confidence"] < 0.9 for e in result["effects"])
    assert result["heldout_rmse_after"] == result["heldout_rmse_before"]
    # The model file is the vehicle file unchanged: nothing added.
    assert "effects" not in load_vehicle(result["model_file"])


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
