"""`arcade log convert` and `arcade discrepancy FLIGHT.ulg`: the CSV they write or pass on,
and one `error:` line (exit 2, no traceback) for every unusable input. The discrepancy
workflow itself is replaced (on the samples it takes minutes): these tests take seconds."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from arcade.cli import main
from arcade_io.flightlog import read_log
from arcade_io.ulog import read_ulog

DATA = Path(__file__).resolve().parents[1] / "data" / "ulog"
EVENTS = DATA / "sample_px4_events.ulg"
SMALL = DATA / "sample_log_small.ulg"


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("ARCADE_RUNS", str(tmp_path / "runs"))
    return tmp_path


def _code(argv) -> int:
    try:
        return main([str(a) for a in argv])
    except SystemExit as exc:
        return exc.code


def _one_error(capsys) -> str:
    """The only stderr line, an `error:` line (no traceback, nothing else)."""
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


# ----------------------------------------------------------------- arcade log convert


def test_convert_writes_a_csv_the_flight_log_reader_reads_back(workdir, capsys):
    argv = ["log", "convert", EVENTS, "--out", "ev.csv", "--mass", "2", "--min-airborne-s", "5"]
    assert _code(argv) == 0
    out = capsys.readouterr().out
    assert out.startswith("wrote ev.csv: 11.39 s at 100 Hz (1140 rows)")
    assert "rate setpoints: vehicle_rates_setpoint" in out and "warning:" in out
    log = read_log("ev.csv", "quadrotor")
    ref = read_ulog(EVENTS, mass_kg=2.0, min_airborne_s=5.0).log
    np.testing.assert_array_equal(log.t, ref.t)
    np.testing.assert_array_equal(log.X, ref.X)
    np.testing.assert_array_equal(log.U, ref.U)


def test_convert_old_log_at_another_rate_with_a_vehicle_file_and_a_seed(workdir, capsys):
    vehicle = Path(__file__).resolve().parents[2] / "deploy" / "vehicles" / "default.toml"
    argv = ["log", "convert", SMALL, "--out", "sm.csv", "--vehicle", vehicle, "--rate", "200",
            "--min-airborne-s", "1", "--vehicle-out", "seed.toml"]  # fmt: skip
    assert _code(argv) == 0
    out = capsys.readouterr().out
    assert "actuator_controls_0.control[3]" in out and "0.57 kg from vehicle file" in out
    assert "wrote seed.toml" in out and "inertia_kgm2" in out
    log = read_log("sm.csv", "quadrotor")
    assert log.dt == pytest.approx(0.005) and np.all(log.X[:, 2] > 0.0)
    seed = tomllib.loads(Path("seed.toml").read_text())
    assert seed["body"]["mass_kg"] == pytest.approx(0.57)
    assert seed["thrust_curve"]["thr_mdl_fac"] == 0.0


def test_convert_json_is_the_conversions_metadata(workdir, capsys):
    argv = ["log", "convert", EVENTS, "--out", "ev.csv", "--mass", "2", "--min-airborne-s", "5",
            "--json"]  # fmt: skip
    assert _code(argv) == 0
    meta = json.loads(capsys.readouterr().out)
    assert meta["out"] == "ev.csv" and meta["samples"] == 1140
    assert meta["thrust_conversion"]["hover_force_n"] == pytest.approx(19.62)
    assert meta["stand_ins"] == []


@pytest.mark.parametrize(
    "args, expect",
    [
        (["missing.ulg", "--mass", "1"], "error: ULog file not found: missing.ulg"),
        (["notulog.ulg", "--mass", "1"], "notulog.ulg: not a ULog file"),
        ([EVENTS, "--min-airborne-s", "5"], "the vehicle's mass is not in a ULog: give it "
         "with --mass KG or a vehicle file (--vehicle FILE)"),
        ([EVENTS, "--mass", "2", "--min-airborne-s", "12"],
         "less than the 12 s asked for (--min-airborne-s)"),
        ([EVENTS, "--vehicle", "none.toml"], "error: vehicle file not found: none.toml"),
        (["cut.ulg", "--mass", "2", "--min-airborne-s", "5"], "the file is truncated"),
    ],
)  # fmt: skip
def test_convert_errors_are_one_line(workdir, capsys, args, expect):
    (workdir / "notulog.ulg").write_text("t,px,py\n0,0,0\n")
    (workdir / "cut.ulg").write_bytes(EVENTS.read_bytes()[:500_000])
    assert _code(["log", "convert", *args, "--out", "x.csv"]) == 2
    assert expect in _one_error(capsys)
    assert not (workdir / "x.csv").exists()


def test_convert_usage_errors_are_argparse_errors(workdir, capsys):
    assert _code(["log", "convert", EVENTS, "--mass", "2", "--vehicle", "v.toml", "--out",
                  "x.csv"]) == 2  # fmt: skip
    assert "not allowed with argument --mass" in capsys.readouterr().err
    assert _code(["log", "convert", EVENTS, "--mass", "-1", "--out", "x.csv"]) == 2
    assert "argument --mass: must be a finite number > 0" in capsys.readouterr().err
    assert _code(["log", "convert", EVENTS, "--mass", "1"]) == 2  # no --out
    assert "--out" in capsys.readouterr().err


def test_convert_help_explains_the_conversion(capsys):
    assert _code(["log", "convert", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    for text in ("THR_MDL_FAC", "hover_thrust_estimate", "zero-order hold", "--mass KG",
                 "measured rates stand in", "(default: 100)", "(default: 0, any;",
                 "linear in force: m*g*s/s_hover", "reported, not used"):  # fmt: skip
        assert text in out
    assert "through PX4's THR_MDL_FAC curve" not in out  # the curve is PX4's, not applied


# ----------------------------------------------------------- arcade discrepancy .ulg


def test_discrepancy_takes_a_ulog_converted_in_memory(workdir, monkeypatch, capsys):
    from arcade_core.discrepancy.workflow import Outcome

    seen = {}

    def fake(log, system, vehicle, out, settings, progress=None, log_import=None):
        seen.update(log=log, system=system, log_import=log_import)
        return Outcome(result={
            "summary": "no confident effect", "effects": [], "heldout_components": ["vx"],
            "heldout_rmse_before": 0.1, "heldout_rmse_after": 0.1, "model_file": "v.toml",
        })  # fmt: skip

    monkeypatch.setattr("arcade.commands.discrepancy.run_workflow", fake)
    argv = ["discrepancy", EVENTS, "--mass", "2", "--min-airborne-s", "5", "--out", "d"]
    assert _code(argv) == 0
    assert seen["system"] == "quadrotor" and len(seen["log"]) == 1140
    assert seen["log_import"]["thrust_conversion"]["mass_kg"] == 2.0
    err = capsys.readouterr().err
    assert "11.39 s at 100 Hz (1140 rows)" in err and "warning:" in err
    # The model is the shipped 0.57 kg vehicle: a 2 kg thrust scale is called out.
    assert "the model's mass is 0.57 kg: the difference reads as a thrust_scale" in err


@pytest.mark.parametrize(
    "args, expect",
    [
        ([EVENTS, "--min-airborne-s", "5"], "the vehicle's mass is not in a ULog"),
        (["missing.ulg", "--mass", "2"], "error: ULog file not found: missing.ulg"),
        ([EVENTS, "--mass", "2", "--system", "cartpole", "--min-airborne-s", "5"],
         "a PX4 ULog is a quadrotor log, not cartpole"),
        (["notulog.ulg", "--mass", "2"], "not a ULog file"),
        (["flight.csv", "--mass", "2"], "--mass: for a PX4 ULog (.ulg) only"),
    ],
)  # fmt: skip
def test_discrepancy_ulog_errors_come_before_any_work(workdir, monkeypatch, capsys, args, expect):
    def reached(*_a, **_k):
        raise AssertionError("the workflow must not start")

    monkeypatch.setattr("arcade.commands.discrepancy.run_workflow", reached)
    (workdir / "notulog.ulg").write_text("t,px\n")
    (workdir / "flight.csv").write_text("t,px\n")
    assert _code(["discrepancy", *args]) == 2
    assert expect in _one_error(capsys)
    assert not (workdir / "runs").exists()


@pytest.mark.parametrize("ulog", [EVENTS, SMALL], ids=["events", "small"])
def test_both_samples_convert_and_analyse_without_an_error(workdir, monkeypatch, capsys, ulog):
    # Converting takes any airborne stretch (a warning below the workflow's 30 s); the
    # workflow answers "not enough excitation to tell" for 11.4 s and 1.1 s of flight.
    assert _code(["log", "convert", ulog, "--mass", "2", "--out", "x.csv"]) == 0
    assert "the discrepancy workflow needs 30 s to tell effects apart" in capsys.readouterr().out
    assert len(read_log(workdir / "x.csv", "quadrotor")) > 100

    def reached(*_a, **_k):
        raise AssertionError("nothing to fit: the workflow must not start")

    monkeypatch.setattr("arcade.commands.discrepancy.run_workflow", reached)
    assert _code(["discrepancy", ulog, "--mass", "2", "--out", "d", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["summary"].startswith("not enough excitation to tell: the longest usable")
    assert result["not_enough_excitation"] and result["effects"] == []
    assert result["heldout_rmse_before"] is None and result["model_file"] is None
    assert result["log_import"]["thrust_conversion"]["mass_kg"] == 2.0
    assert json.loads((workdir / "d" / "result.json").read_text()) == result
    assert "No effect named or added" in (workdir / "d" / "report.md").read_text()
