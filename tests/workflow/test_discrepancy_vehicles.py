"""The discrepancy workflow on logs like a real PX4 flight log: other vehicles, 50 Hz, no
rate setpoints, 30-50 s.

The vehicles (``tests/data/vehicles/``) are the default vehicle scaled to 0.3, 2.7 and
5 kg (inertia, arm, rotor thrust for a hover at 45-50 % throttle, rate-loop gains for the
same closed loop). Every log is flown at the simulator's 100 Hz with the standard sensor
noise and kept at every second row (50 Hz); its rate setpoints are replaced by the measured
body rates, as the ULog import does for a log without ``vehicle_rates_setpoint``. The
vehicle files the workflow is given know none of the injected effects.

- The 2.7 kg vehicle flies a 50 s vertical figure-eight in a steady 14.7 m/s wind with
  rotor drag 0.4 1/s (the aerodynamic force reaches 0.6 g): the workflow must name and add
  drag and wind and lower the held-out one-step gap by at least 30 %.
- Through the command line, 30 s each: the 0.3 kg vehicle hovering (nothing named: not
  enough excitation to tell drag), and the 5 kg vehicle hovering in the wind of the first
  flight (a persistent 0.6 g force: wind and drag named, the gap lower; a hover cannot tell
  the two apart, only their product).
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest

from arcade import cli
from arcade_io.discrepancy import run_workflow
from arcade_io.flightlog import FlightLog, from_arrays, write_log
from simulator.log_flights import VerticalFigureEight, fly_quadrotor, hover_path

VEHICLES = Path(__file__).resolve().parent.parent / "data" / "vehicles"
#: Rotor drag [1/s] and a wind [m/s] whose drag force is 0.6 g at hover (0.4 x 14.7 m/s).
DRAG = {"d": [0.4, 0.4, 0.1]}
WIND = {"velocity_mps": [14.7 * np.cos(np.pi / 6), 14.7 * np.sin(np.pi / 6), 0.0]}


def like_px4(log: FlightLog) -> FlightLog:
    """Every second row (50 Hz), the measured body rates standing in for the setpoints."""
    X, U = log.X[::2], log.U[::2].copy()
    U[:, 1:4] = X[:, 10:13]
    return from_arrays("quadrotor", log.t[::2], X, U)


def vehicle(name: str) -> Path:
    return VEHICLES / f"quad_{name}.toml"


@pytest.fixture(scope="module")
def windy_figure_eight():
    """The 2.7 kg vehicle's figure-eight in the wind (50 Hz, stand-ins) and the result."""
    veh = vehicle("2p7kg")
    effects = {"rotor_drag": DRAG, "wind": WIND}
    log = fly_quadrotor(
        effects, 50.0, seed=1, vehicle=veh, path=VerticalFigureEight(), excitation=0.0
    )
    return log, run_workflow(like_px4(log), "quadrotor", vehicle=veh).result


def test_wind_and_drag_on_a_heavy_vehicle_in_a_strong_wind(windy_figure_eight):
    log, result = windy_figure_eight
    # The path is flown, banked into the wind (tilt ~ atan(0.6)).
    assert np.max(np.linalg.norm(log.X[:, 3:6], axis=1)) > 2.0
    tilt = np.degrees(np.arccos(1.0 - 2.0 * (log.X[:, 7] ** 2 + log.X[:, 8] ** 2)))
    assert np.median(tilt) > 25.0
    added = {e["name"]: e for e in result["effects"] if e["added"]}
    assert {"rotor_drag", "wind"} <= set(added), result["summary"]
    assert result["heldout_rmse_after"] <= 0.7 * result["heldout_rmse_before"]
    np.testing.assert_allclose(added["rotor_drag"]["params"]["d"][:2], DRAG["d"][:2], rtol=0.2)
    wind = np.asarray(added["wind"]["params"]["velocity_mps"])
    assert np.linalg.norm(wind - WIND["velocity_mps"]) <= 0.2 * np.linalg.norm(WIND["velocity_mps"])


#: Hover-only flights through the command line: (vehicle, injected effects).
HOVERS = {
    "light_hover": ("0p3kg", {}),
    "heavy_hover_in_wind": ("5kg", {"rotor_drag": DRAG, "wind": WIND}),
}


@pytest.fixture(scope="module", params=sorted(HOVERS))
def through_cli(request, tmp_path_factory):
    """(case, exit code, printed result) of ``arcade discrepancy --json`` on a 30 s hover."""
    veh, effects = HOVERS[request.param]
    log = fly_quadrotor(
        effects, 30.0, seed=2, vehicle=vehicle(veh), path=hover_path(), excitation=0.0
    )
    tmp = tmp_path_factory.mktemp(request.param)
    csv = write_log(tmp / "log.csv", like_px4(log))
    argv = ["discrepancy", str(csv), "--vehicle", str(vehicle(veh)), "--json"]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = cli.main([*argv, "--out", str(tmp / "out")])
    return request.param, rc, out.getvalue()


def test_each_log_gives_a_result_through_the_command_line(through_cli):
    case, rc, out = through_cli
    assert rc == 0
    result = json.loads(out)
    added = {e["name"] for e in result["effects"] if e["added"]}
    gain = 1.0 - result["heldout_rmse_after"] / result["heldout_rmse_before"]
    if case == "light_hover":  # a hover cannot show drag: nothing is guessed
        assert result["no_confident_effect"] and not added, result["summary"]
        assert {"rotor_drag", "quadratic_drag"} <= set(result["cannot_tell"])
        assert "not enough excitation to tell rotor_drag" in result["summary"]
    else:  # hovering against a persistent 0.6 g force: wind through drag explains it
        assert {"rotor_drag", "wind"} <= added and gain >= 0.3, result["summary"]
