"""Command-line errors: bad options, files and output paths are reported on one line
(``error: ...`` or argparse's ``argument --x: ...``) with exit status 2, before any work
starts and before a run folder is made. The work itself is replaced by functions that
fail the test if they are reached, so these tests take seconds."""

import json
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from arcade.cli import main

QUAD_HEADER = "t,px,py,pz,vx,vy,vz,qw,qx,qy,qz,wx,wy,wz,u0,u1,u2,u3\n"


def _forbid(monkeypatch, target: str) -> None:
    """Make ``target`` (module.attr) fail the test when called: the work must not start."""

    def reached(*_args, **_kwargs):
        raise AssertionError(f"{target} was reached; the error must come before the work")

    monkeypatch.setattr(target, reached)


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    """A clean current folder whose run folders go to ``runs/`` inside it."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("ARCADE_RUNS", str(tmp_path / "runs"))
    (tmp_path / "bad.toml").write_text("mass = [\n")
    return tmp_path


@pytest.fixture
def quad_log(workdir):
    path = workdir / "q.csv"
    rows = "".join(f"{0.01 * k:.2f},0,0,1,0,0,0,1,0,0,0,0,0,0,5.6,0,0,0\n" for k in range(3000))
    path.write_text(QUAD_HEADER + rows)
    return path


@pytest.fixture
def cartpole_log(workdir):
    path = workdir / "cp.csv"
    path.write_text(
        "t,x,xdot,theta,thetadot,u\n" + "".join(f"{0.05 * k},0,0,0,0,0\n" for k in range(400))
    )
    return path


def _exit_code(argv) -> int:
    """Return code of ``main(argv)``, or the SystemExit code of an argparse error."""
    try:
        return main(argv)
    except SystemExit as exc:
        return exc.code


def _error_line(capsys) -> str:
    """The last stderr line, checked to be the only non-usage line (no traceback)."""
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert lines, "no error message"
    assert "error:" in lines[-1]
    return lines[-1]


# --------------------------------------------------------------------------- arcade sim


@pytest.mark.parametrize(
    "extra, expect",
    [
        (["--vehicle", "missing.toml"], "vehicle file not found: missing.toml"),
        (["--vehicle", "bad.toml"], "bad.toml"),
        (["--payload-g", "-50"], "argument --payload-g: must be a finite number >= 0"),
        (["--payload-g", "5000"], "--payload-g must be below 10"),
        (["--release-at", "3"], "--release-at needs a payload"),
        (["--cable-length", "0.3"], "--cable-length needs a payload"),
        (["--duration", "nan"], "argument --duration: must be a finite number > 0"),
        (["--status-every", "-1"], "argument --status-every"),
        (["--of-loss-s", "0"], "argument --of-loss-s: must be a finite number > 0"),
        (["--vision-timeout", "nan"], "argument --vision-timeout: must be a finite number > 0"),
        (["--airborne", "--start", "0", "0", "0"], "--start Z must be above the floor"),
    ],
)
def test_sim_usage_errors_exit_2_before_the_vehicle_starts(
    workdir, monkeypatch, capsys, extra, expect
):
    _forbid(monkeypatch, "simulator.px4.Px4Sim")
    code = _exit_code(["sim", "--px4", "udpout://127.0.0.1:14540", *extra])
    assert code == 2
    assert expect in _error_line(capsys)


def test_sim_help_states_the_vision_timeout_default(capsys):
    assert _exit_code(["sim", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "no longer gives a valid position [s] (default: 0.5)" in out


def test_sim_bad_url_is_a_usage_error(workdir, monkeypatch, capsys):
    _forbid(monkeypatch, "simulator.px4.Px4Sim")
    assert _exit_code(["sim", "--px4", "udpin://127.0.0.1:99999"]) == 2
    assert "--px4 udpin://127.0.0.1:99999" in _error_line(capsys)


def test_sim_payload_within_the_rotors_lift_is_accepted(workdir):
    from arcade.cli import build_parser
    from arcade.commands.sim import check_arguments
    from arcade_io.vehicle import load_vehicle, max_payload_g

    args = build_parser().parse_args(
        ["sim", "--px4", "udpout://127.0.0.1:14540", "--payload-g", "1000", "--release-at", "5"]
    )
    assert check_arguments(args)["name"] == "arcade-152"
    # The limit: the rotors' full thrust (4 x 4 N) carries 0.572 kg of vehicle and cable.
    assert max_payload_g(load_vehicle()) == pytest.approx(4 * 4.0 / 9.81 * 1000 - 572)


def test_sim_link_that_cannot_be_opened_exits_1_naming_the_url(workdir, capsys):
    # The port is taken: binding the link fails (an OSError, not a usage error).
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        url = f"udpin://127.0.0.1:{taken.getsockname()[1]}"
        code = _exit_code(["sim", "--px4", url, "--duration", "0.2", "--status-every", "0"])
    assert code == 1
    line = _error_line(capsys)
    assert line.startswith(f"error: cannot open the MAVLink link {url}: ")


# --------------------------------------------------------------------------- arcade simulate


@pytest.mark.parametrize(
    "extra, expect",
    [
        (["--noise-scale", "-1"], "argument --noise-scale: must be a finite number >= 0, got -1"),
        (["--duration", "nan"], "argument --duration: must be a finite number > 1, got nan"),
        (["--duration", "0.5"], "argument --duration"),
        (["--seed", "-1"], "argument --seed: must be at least 0"),
        (["--vehicle", "missing.toml"], "vehicle file not found: missing.toml"),
        (["--vehicle", "bad.toml"], "bad.toml: not a valid TOML vehicle file"),
        (["--effects", "bad.toml"], "bad.toml: not a valid TOML effects file"),
        (["--system", "cartpole", "--vehicle", "missing.toml"], "--vehicle applies to"),
    ],
)
def test_simulate_rejects_bad_options_before_flying(workdir, monkeypatch, capsys, extra, expect):
    _forbid(monkeypatch, "simulator.log_flights.fly_quadrotor")
    _forbid(monkeypatch, "simulator.log_flights.fly_cartpole")
    assert _exit_code(["simulate", "--out", "log.csv", *extra]) == 2
    assert expect in _error_line(capsys)
    assert not (workdir / "log.csv").exists()


def test_simulate_unknown_effect_names_the_file(workdir, monkeypatch, capsys):
    _forbid(monkeypatch, "simulator.log_flights.fly_quadrotor")
    (workdir / "effects.toml").write_text("[nosuch]\nx = 1\n")
    assert _exit_code(["simulate", "--effects", "effects.toml", "--out", "log.csv"]) == 2
    line = _error_line(capsys)
    assert "effects.toml: unknown effect 'nosuch'" in line and "rotor_drag" in line


@pytest.mark.parametrize("kind", ["folder", "file-as-parent"])
def test_simulate_checks_out_before_flying(workdir, monkeypatch, capsys, kind):
    _forbid(monkeypatch, "simulator.log_flights.fly_quadrotor")
    (workdir / "x").mkdir()
    (workdir / "f").write_text("")
    out = "x" if kind == "folder" else "f/log.csv"
    assert _exit_code(["simulate", "--out", out]) == 2
    assert f"--out {out}" in _error_line(capsys)


# --------------------------------------------------------------------------- arcade discrepancy


@pytest.mark.parametrize(
    "extra, expect",
    [
        (["--heldout", "0.9"], "argument --heldout: must be between 0.05 and 0.5, got 0.9"),
        (["--confidence", "5"], "argument --confidence: must be between 0.5 and 1, got 5"),
        (["--bootstrap", "0"], "argument --bootstrap: must be at least 10, got 0"),
        (["--step", "0"], "argument --step: must be in (0, 2), got 0"),
        (["--horizon", "inf"], "argument --horizon"),
        (["--vehicle", "missing.toml"], "vehicle file not found: missing.toml"),
        (["--vehicle", "bad.toml"], "bad.toml: not a valid TOML vehicle file"),
        (["--out", "q.csv"], "--out q.csv is an existing file, not a folder"),
    ],
)
def test_discrepancy_checks_everything_before_making_a_run_folder(
    quad_log, monkeypatch, capsys, extra, expect
):
    _forbid(monkeypatch, "arcade.commands.discrepancy.run_workflow")
    _forbid(monkeypatch, "arcade_io.runs.new_run_dir")
    assert _exit_code(["discrepancy", str(quad_log.name), *extra]) == 2
    assert expect in _error_line(capsys)
    assert not (quad_log.parent / "runs").exists()


def test_discrepancy_log_too_short_is_not_enough_excitation(workdir, monkeypatch, capsys):
    # Too short to hold the windows the fit needs: an answer, not a guess and not an error.
    _forbid(monkeypatch, "arcade.commands.discrepancy.run_workflow")
    rows = "".join(f"{0.01 * k:.2f},0,0,1,0,0,0,1,0,0,0,0,0,0,5.6,0,0,0\n" for k in range(300))
    (workdir / "short.csv").write_text(QUAD_HEADER + rows)
    assert _exit_code(["discrepancy", "short.csv", "--out", "d"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("not enough excitation to tell: log too short: 0 fitting windows")
    result = json.loads((workdir / "d" / "result.json").read_text())
    assert result["effects"] == [] and result["heldout_rmse_after"] is None


def test_discrepancy_names_the_system_a_log_belongs_to(quad_log, cartpole_log, monkeypatch, capsys):
    _forbid(monkeypatch, "arcade.commands.discrepancy.run_workflow")
    assert _exit_code(["discrepancy", "cp.csv"]) == 2
    line = _error_line(capsys)
    assert "this looks like a cartpole log: pass --system cartpole" in line
    assert "missing column" not in line
    assert _exit_code(["discrepancy", "q.csv", "--system", "cartpole"]) == 2
    assert "this looks like a quadrotor log: pass --system quadrotor" in _error_line(capsys)
    # A log of neither system still lists what is missing.
    (quad_log.parent / "other.csv").write_text("t,a\n" + "".join(f"{k},0\n" for k in range(30)))
    assert _exit_code(["discrepancy", "other.csv"]) == 2
    assert "missing column(s)" in _error_line(capsys)


def test_discrepancy_log_that_is_a_folder_says_so(workdir, monkeypatch, capsys):
    _forbid(monkeypatch, "arcade.commands.discrepancy.run_workflow")
    (workdir / "flights").mkdir()
    assert _exit_code(["discrepancy", "flights"]) == 2
    assert _error_line(capsys) == "error: flight log flights is a directory, not a CSV file"


def test_discrepancy_text_output_formats_the_parameters(quad_log, monkeypatch, capsys):
    from arcade_core.discrepancy.workflow import Outcome

    drag = {"d": [0.5998447167674859, 0.601546438477104, 0.10928580501224755]}
    result = {
        "summary": "missing effect: rotor_drag",
        "effects": [
            {"name": "rotor_drag", "params": drag, "confidence": 1.0, "added": True},
            {"name": "thrust_scale", "params": {"scale": 1.0123456}, "confidence": 0.6,
             "added": False},
        ],
        "heldout_components": ["vx", "vy"],
        "heldout_rmse_before": 0.2,
        "heldout_rmse_after": 0.1,
        "model_file": "vehicle.toml",
    }  # fmt: skip
    monkeypatch.setattr(
        "arcade.commands.discrepancy.run_workflow", lambda *a, **k: Outcome(result=result)
    )
    assert _exit_code(["discrepancy", quad_log.name, "--out", "d"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert "  rotor_drag: d = [0.5998, 0.6015, 0.1093] 1/s, confidence 1.00" in out
    assert "  thrust_scale: scale = 1.012, confidence 0.60 (not added)" in out


def test_effects_name_the_quantity_and_unit_of_the_detection_limit(capsys):
    from arcade_core.discrepancy.catalog import DETECTABLE

    assert _exit_code(["effects", "--system", "quadrotor"]) == 0
    out = capsys.readouterr().out
    assert "detectable on the standard trajectory from largest |d| = 0.35 1/s" in out
    assert "from rotor radius = 0.15 m" in out
    assert "from |scale - 1| = 0.06\n" in out
    assert out.count("detectable on the standard trajectory from") == len(DETECTABLE)


def test_discrepancy_help_lists_columns_ranges_and_defaults(capsys):
    assert _exit_code(["discrepancy", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "design" not in out
    assert "t, px, py, pz, vx, vy, vz, qw, qx, qy, qz, wx, wy, wz, u0, u1, u2, u3" in out
    assert "t, x, xdot, theta, thetadot, u" in out
    assert "0.05 to 0.5 (default: 0.3)" in out
    assert "0.5 to 1 (default: 0.9)" in out
    assert "the system that flew the log (default: quadrotor)" in out


def test_simulate_help_states_the_duration_default(capsys):
    assert _exit_code(["simulate", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "(default: 60.0;" in out and "90 s flights" in out


# --------------------------------------------------------------------------- eval, bench


def test_eval_checks_out_before_the_evaluation(quad_log, monkeypatch, capsys):
    _forbid(monkeypatch, "benchmarks.cartpole_eval.evaluate")
    assert _exit_code(["eval", "cartpole", "--out", "q.csv"]) == 2
    assert "--out q.csv is an existing file, not a folder" in _error_line(capsys)
    assert not (quad_log.parent / "runs").exists()


def test_eval_condition_belongs_to_the_quadrotor(quad_log, monkeypatch, capsys):
    _forbid(monkeypatch, "benchmarks.cartpole_eval.evaluate")
    _forbid(monkeypatch, "benchmarks.changepoints.run_changepoints")
    for system in ("cartpole", "changepoints"):
        assert _exit_code(["eval", system, "--condition", "stack"]) == 2
        assert "--condition stack applies to the quadrotor evaluation only" in _error_line(capsys)
    assert not (quad_log.parent / "runs").exists()


def test_eval_methods_and_stored_knobs_belong_to_the_quadrotor(quad_log, monkeypatch, capsys):
    _forbid(monkeypatch, "benchmarks.cartpole_eval.evaluate")
    _forbid(monkeypatch, "benchmarks.quadrotor_openloop.prepare_models")
    assert _exit_code(["eval", "cartpole", "--methods", "l1", "--stored-knobs"]) == 2
    assert "--methods, --stored-knobs: for the quadrotor evaluation only" in _error_line(capsys)
    assert _exit_code(["eval", "quadrotor", "--methods", "l1,l2"]) == 2
    assert "argument --methods: l2: methods are nominal, l1," in capsys.readouterr().err
    assert not (quad_log.parent / "runs").exists()


@pytest.mark.parametrize("mode", ["--sweep", "--limits"])
def test_bench_discrepancy_rejects_unknown_effects(monkeypatch, capsys, mode):
    _forbid(monkeypatch, "benchmarks.discrepancy.sweep")
    _forbid(monkeypatch, "benchmarks.discrepancy.detection_limits")
    assert _exit_code(["bench", "discrepancy", mode, "--effect", "nosuch"]) == 2
    line = _error_line(capsys)
    assert "unknown effect(s) nosuch" in line
    for known in ("rotor_drag", "motor_lag", "wind"):
        assert known in line


def test_bench_sweep_options_need_a_sweep(monkeypatch, capsys):
    _forbid(monkeypatch, "benchmarks.discrepancy.run")
    assert _exit_code(["bench", "discrepancy", "--effect", "rotor_drag"]) == 2
    assert "need --sweep or --limits" in _error_line(capsys)


def test_bench_variants_checks_out_first_and_writes_it_whole(tmp_path, monkeypatch, capsys):
    _forbid(monkeypatch, "benchmarks.quadrotor_variants.run")
    assert _exit_code(["bench", "variants", "--out", str(tmp_path)]) == 2
    assert "is an existing folder" in _error_line(capsys)
    assert _exit_code(["bench", "adapt", "--out", str(tmp_path / "a.json")]) == 2
    assert "--out belongs to" in _error_line(capsys)
    out = tmp_path / "deeper" / "results.json"
    monkeypatch.setattr("benchmarks.quadrotor_variants.run", lambda quick: {"cells": [1]})
    assert _exit_code(["bench", "variants", "--quick", "--out", str(out)]) == 0
    assert json.loads(out.read_text()) == {"cells": [1]}
    assert [p.name for p in out.parent.iterdir()] == ["results.json"]  # no temporary left


# --------------------------------------------------------------------------- files


def test_invalid_toml_errors_name_the_file(workdir):
    from arcade_io.vehicle import load_vehicle

    with pytest.raises(ValueError, match=r"bad\.toml: not a valid TOML vehicle file"):
        load_vehicle(workdir / "bad.toml")
    (workdir / "partial.toml").write_text("[body]\nmass_kg = 0.5\n[rotors]\n[rate_loop]\n")
    with pytest.raises(ValueError, match=r"partial\.toml: \[body\] inertia_kgm2 must be"):
        load_vehicle(workdir / "partial.toml")


# --------------------------------------------------------------------------- Makefile


@pytest.mark.skipif(shutil.which("make") is None, reason="needs make")
def test_make_refuses_a_python_older_than_3_11(tmp_path):
    root = Path(__file__).resolve().parents[2]
    for name in ("Makefile", "pyproject.toml"):
        shutil.copy(root / name, tmp_path / name)
    old = tmp_path / "python3.10"
    old.write_text(f"#!/bin/sh\nexec {sys.executable} -c 'import sys; sys.exit(1)' \"$@\"\n")
    old.chmod(0o755)
    proc = subprocess.run(
        ["make", f"PYTHON={old}", "install"], cwd=tmp_path, capture_output=True, text=True
    )
    assert proc.returncode != 0
    assert f"error: {old} is not Python 3.11 or newer" in proc.stderr
    assert not (tmp_path / ".venv").exists()
    # An unknown target is an error, not a silent success.
    bench = subprocess.run(["make", "bench"], cwd=tmp_path, capture_output=True, text=True)
    assert bench.returncode != 0
