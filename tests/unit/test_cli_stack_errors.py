"""`arcade up` / `arcade demo`: usage errors before anything starts, weights checks, run
folders independent of the working directory, stack errors that quote the failed process."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from arcade.cli import main
from arcade.training import load_or_train
from deploy.launcher import Stack, StackConfig, StackError, last_output
from deploy.px4_profile import Px4StackConfig

WEIGHTS = Path(__file__).resolve().parents[2] / "deploy" / "weights"
TRACEBACK = """\
\x1b[34m[02:23:48|Info ] \x1b[0mMAVSDK version: v4.1.0 (mavsdk_impl.cpp:58)
2026-11-25 14:23:51,183 ERROR arcade.bridge: bridge failed
Traceback (most recent call last):
  File "/repo/services/runtime.py", line 323, in run
    self.setup(bus)
  File "/repo/services/px4_bridge.py", line 198, in _connect
    raise RuntimeError(
RuntimeError: no autopilot heard on udpin://127.0.0.1:14999 within 3 s: is PX4 powered
"""


@pytest.fixture
def elsewhere(tmp_path, monkeypatch):
    """Run from a directory outside the repository, run folders under it."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("ARCADE_RUNS", str(tmp_path / "runs"))
    return tmp_path


def _forbid_flight(monkeypatch) -> None:
    """Fail the test if `arcade up` or `arcade demo` start flying."""

    def reached(*args, **kwargs):
        raise AssertionError("the flight started despite a usage error")

    monkeypatch.setattr("deploy.launcher.run_flight", reached)
    monkeypatch.setattr("arcade.demo_stack.run_demo", reached)


def _value(args: list[str], option: str) -> str:
    return args[args.index(option) + 1]


# ------------------------------------------------------------------ run folder


def test_relative_paths_reach_the_services_absolute(elsewhere):
    cfg = StackConfig(out=Path("runs/r1"), weights=Path("w.eqx"), checkpoint=Path("c.npz"))
    here = Path(os.getcwd())
    assert cfg.out == here / "runs" / "r1"
    for service in cfg.services():
        assert _value(cfg.args(service), "--out") == str(here / "runs" / "r1")
    for service in ("adapter", "controller"):
        assert _value(cfg.args(service), "--weights") == str(here / "w.eqx")
    assert _value(cfg.args("adapter"), "--checkpoint") == str(here / "c.npz")
    # One link delay for the two services that compensate it, and none for the others.
    delayed = StackConfig(out=Path("r4"), link_delay_s=0.02)
    for service in delayed.services():
        args = delayed.args(service)
        if service in ("adapter", "controller"):
            assert _value(args, "--link-delay") == "0.02"
        else:
            assert "--link-delay" not in args
    assert _value(cfg.args("controller"), "--link-delay") == "0"
    px4 = Px4StackConfig(out=Path("r5"), simulate=True, link_delay_s=0.018)
    assert [_value(px4.args(s), "--link-delay") for s in ("adapter", "controller")] == ["0.018"] * 2
    # The run's own checkpoint lies in the absolute run folder too.
    assert StackConfig(out="r2").checkpoint_path() == here / "r2" / "adapter_checkpoint.npz"
    px4 = Px4StackConfig(out=Path("r3"), simulate=True)
    for service in px4.services():
        assert _value(px4.args(service), "--out") == str(here / "r3")


# ------------------------------------------------------------------ stack errors


def test_dead_vehicle_error_quotes_its_output_and_names_the_logs(tmp_path):
    stack = Stack(Px4StackConfig(out=tmp_path))
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "bridge.out").write_text(TRACEBACK)
    stack.procs["bridge"] = subprocess.Popen([sys.executable, "-c", "raise SystemExit(1)"])
    stack.procs["bridge"].wait()
    with pytest.raises(StackError) as err:
        stack._check_alive()
    text = str(err.value)
    assert text.startswith(f"vehicle process bridge exited with code 1; see {tmp_path / 'logs'}")
    assert "ERROR arcade.bridge: bridge failed" in text
    assert "RuntimeError: no autopilot heard on udpin://127.0.0.1:14999" in text
    assert "File " not in text and "\x1b" not in text  # no frames, no colour codes


def test_a_full_disk_does_not_stop_the_supervision(tmp_path):
    """events.jsonl on a full disk (/dev/full: every write fails with ENOSPC): the
    supervisor still restarts, records its events in memory and shows them, and says once
    that the file is no longer written."""
    shown = []
    stack = Stack(StackConfig(out=tmp_path, max_restarts=0), on_event=shown.append)
    (tmp_path / "events.jsonl").symlink_to("/dev/full")
    (tmp_path / "logs").mkdir()
    proc = subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])
    stack._watch("adapter", proc)  # its crash is an event: no exception escapes
    stack.emit("info", "a later event")
    kinds = [(r["src"], r["kind"], r["text"].split(":")[0]) for r in shown]
    assert kinds == [
        ("launcher", "fault", "adapter exited with code 3; no restart left (0 used)"),
        ("launcher", "fault", "cannot write events.jsonl"),
        ("launcher", "info", "a later event"),
    ], kinds
    assert list(stack.events) == shown and "No space left on device" in stack.events_file_error


def test_the_supervisor_keeps_the_newest_events_in_memory_and_all_on_disk(tmp_path, monkeypatch):
    """A long flight's events (a PX4 flight: a vehicle_status twice a second) do not grow
    the launcher's memory: the newest are kept, the older counted, events.jsonl has all."""
    import json

    from deploy import launcher

    monkeypatch.setattr(launcher, "EVENTS_KEPT", 5)
    stack = Stack(StackConfig(out=tmp_path))
    for k in range(8):
        stack.emit("info", f"event {k}")
    assert [r["text"] for r in stack.events] == [f"event {k}" for k in range(3, 8)]
    assert stack.events_dropped == 3
    lines = (tmp_path / "events.jsonl").read_text().splitlines()
    assert [json.loads(line)["text"] for line in lines] == [f"event {k}" for k in range(8)]


def test_service_out_of_restarts_error_quotes_its_output(tmp_path):
    stack = Stack(StackConfig(out=tmp_path, max_restarts=0))
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "adapter.out").write_text(
        "Traceback (most recent call last):\n  File 'x', line 1\n"
        "arcade_io.weights.WeightFileError: /tmp/q.csv: not an ARCADE VLD weight file (bad magic)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])
    stack._watch("adapter", proc)  # returns once the process ended: no restart left
    with pytest.raises(StackError) as err:
        stack._check_alive()
    text = str(err.value)
    assert text.startswith("service adapter exited with code 3 (after 0 restarts); see ")
    assert "WeightFileError: /tmp/q.csv: not an ARCADE VLD weight file" in text


def test_last_output_without_traceback_is_the_last_lines(tmp_path):
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "sim.out").write_text("".join(f"line {i}\n\n" for i in range(10)))
    assert last_output(tmp_path, "sim", lines=3) == ["line 7", "line 8", "line 9"]
    assert last_output(tmp_path, "nothing") == []


# ------------------------------------------------------------------ usage errors


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["up", "--rate", "0"], "argument --rate: must be a finite number > 0, got 0"),
        (["up", "--speed", "0"], "argument --speed: must be a finite number > 0"),
        (["up", "--rate", "nan"], "argument --rate: must be a finite number > 0"),
        (["up", "--duration", "-1"], "argument --duration: must be a finite number > 0"),
        (["up", "--payload-g", "inf"], "argument --payload-g: must be a finite number >= 0"),
        (["up", "--seed", "-1"], "argument --seed: must be at least 0"),
        (["up", "--link-delay", "-0.01"], "argument --link-delay: must be a finite number >= 0"),
        (["demo", "--speed", "0"], "argument --speed: must be a finite number > 0"),
        (["demo", "--payload-g", "-5"], "argument --payload-g: must be a finite number >= 0"),
        (["demo", "--seed", "x"], "argument --seed: not an integer"),
        (["up", "--mocap-body", "cf 1"], "argument --mocap-body: 'cf 1' is not a mocap rigid-"),
    ],
)
def test_bad_numbers_are_argument_errors(elsewhere, capsys, argv, message):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err
    assert not (elsewhere / "runs").exists()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["up", "--profile", "px4", "--lockstep"], "--lockstep is for --profile sim"),
        (["up", "--connect", "udpin://127.0.0.1:14999"], "--connect: only with --profile px4"),
        (["up", "--arm", "--on-ground"], "--arm, --on-ground: only with --profile px4"),
        (["up", "--bridge-arg=--connect-timeout=3"], "--bridge-arg: only with --profile px4"),
        (["up", "--profile", "px4", "--on-ground"], "--on-ground is for the simulated PX4"),
        (["up", "--profile", "px4", "--takeoff-m", "-1"], "--takeoff-m must be a positive"),
        (["demo", "--cartpole", "--speed", "3", "--x64"], "--speed, --x64: not with --cartpole"),
        (["demo", "--cartpole", "--method", "arcade"], "--method: not with --cartpole"),
        (["demo", "--cartpole", "--compare"], "--compare: not with --cartpole"),
        (["demo", "--compare", "--method", "l1"], "--method: not with --compare"),
        (
            ["up", "--lockstep", "--hub", "not-an-endpoint"],
            "--hub not-an-endpoint: Endpoints must be of the form <protocol>/<address>",
        ),
        (
            ["up", "--lockstep", "--vehicle", "deploy/vehicles/default.toml"],
            "--vehicle is the vehicle's name on the bus, not a vehicle file: invalid vehicle name",
        ),
        (
            ["up", "--vehicle", "my_quad.toml"],
            "--vehicle is the vehicle's name on the bus, not a vehicle file: 'my_quad.toml'",
        ),
        (
            ["up", "--profile", "px4", "--bridge-arg=--geofence=abc"],
            "--bridge-arg: --geofence abc: could not convert",
        ),
        (
            ["up", "--profile", "px4", "--bridge-arg=--geofence=-1,1,-1,1,0"],
            "--bridge-arg: --geofence -1,1,-1,1,0: geofence needs 6 finite numbers",
        ),
        (
            ["up", "--profile", "px4", "--bridge-arg=--max-throttle=high"],
            "--bridge-arg: argument --max-throttle: invalid float value: 'high'",
        ),
        (
            ["up", "--profile", "px4", "--bridge-arg=--geofense=-1,1,-1,1,0,2"],
            "--bridge-arg: unrecognized arguments: --geofense=-1,1,-1,1,0,2",
        ),
        (
            ["up", "--profile", "px4", "--bridge-arg=--vehicle-file=missing.toml"],
            "--bridge-arg: vehicle file not found: missing.toml",
        ),
        (
            ["up", "--lockstep", "--mocap-body", "payload"],
            "--mocap-body payload: the simulated payload's rigid body has that name",
        ),
        (
            ["up", "--profile", "px4", "--simulate", "--mocap-body", "payload"],
            "--mocap-body payload: the simulated payload's rigid body has that name",
        ),
        (
            ["up", "--profile", "px4", "--bridge-arg=--mocap-b=cf1"],
            "--bridge-arg: --mocap-body is arcade up's own option, not the bridge's alone",
        ),
        (
            ["up", "--lockstep", "--service-arg=estimator:--mocap-body=cf1"],
            "--service-arg estimator: --mocap-body set by the launcher",
        ),
        (["up", "--lockstep", "--payload-g", "5000"], "--payload-g must be below 1059 g"),
        (["demo", "--payload-g", "1059"], "--payload-g must be below 1059 g"),
        (
            ["up", "--service-arg=estimator"],
            "--service-arg estimator: not NAME:ARG (e.g. estimator:--mocap-noise=1e-4)",
        ),
        (["up", "--service-arg=planner:--x=1"], "--service-arg planner:--x=1: no service"),
        (
            ["up", "--service-arg=bridge:--max-throttle=0.8"],
            "--service-arg bridge:--max-throttle=0.8: the bridge's options go through --bridge-arg",
        ),
        (
            ["up", "--lockstep", "--service-arg=px4sim:--of-loss-s=2"],
            "--service-arg px4sim: not a process of this stack (recorder, estimator, adapter,",
        ),
        (
            ["up", "--lockstep", "--service-arg=estimator:--jerk-psd=0"],
            "--service-arg estimator:--jerk-psd=0: argument --jerk-psd: must be a finite number",
        ),
        (
            ["up", "--lockstep", "--service-arg=controller:--max-model-agee=1"],
            "--service-arg controller:--max-model-agee=1: unrecognized arguments",
        ),
        # What arcade up sets itself, however abbreviated.
        (
            ["up", "--lockstep", "--service-arg=estimator:--veh=other"],
            "--service-arg estimator: --vehicle set by the launcher",
        ),
        (
            ["up", "--lockstep", "--service-arg=sim:--seed=3"],
            "--service-arg sim: --seed set by the launcher",
        ),
        (
            ["up", "--profile", "px4", "--service-arg=adapter:--checkpoint=x.npz"],
            "--service-arg adapter: --checkpoint set by the launcher",
        ),
        # The controller and the adapter compensate one link delay, never one of them alone.
        (
            ["up", "--lockstep", "--service-arg=controller:--link-delay=0.02"],
            "--service-arg controller: --link-delay set by the launcher",
        ),
        (
            ["up", "--lockstep", "--link-delay", "0.05"],
            "--link-delay 0.05 s: must be shorter than the control period (0.05 s at --rate 20)",
        ),
        (
            ["up", "--rate", "50", "--link-delay", "0.03"],
            "--link-delay 0.03 s: must be shorter than the control period (0.02 s at --rate 50)",
        ),
    ],
)
def test_options_that_do_not_fit_together(elsewhere, capsys, monkeypatch, argv, message):
    _forbid_flight(monkeypatch)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {message}") and err.count("\n") == 1
    assert not (elsewhere / "runs").exists()


def test_service_args_reach_their_service_after_the_launcher_s(elsewhere):
    import argparse

    from arcade.commands.up import (
        add_arguments,
        group_service_args,
        service_args_problem,
        stack_config,
    )

    p = argparse.ArgumentParser()
    add_arguments(p)
    argv = ["--lockstep", "--service-arg=estimator:--jerk-psd=50"]
    argv += ["--service-arg=estimator:--mocap-noise", "--service-arg=estimator:1e-4"]
    argv += ["--service-arg=controller:--max-model-age=1.0"]
    argv += ["--service-arg=adapter:--log-level=DEBUG"]  # set by the launcher, yet allowed
    args = p.parse_args(argv)
    grouped = group_service_args(args.service_arg)
    assert grouped == {
        "estimator": ["--jerk-psd=50", "--mocap-noise", "1e-4"],
        "controller": ["--max-model-age=1.0"],
        "adapter": ["--log-level=DEBUG"],
    }
    cfg = stack_config(args, Path("run"), {}, grouped)
    assert service_args_problem(cfg) is None
    est = cfg.args("estimator")
    assert est[-3:] == ["--jerk-psd=50", "--mocap-noise", "1e-4"] and "--vehicle" in est
    assert cfg.args("controller")[-1] == "--max-model-age=1.0"
    adapter = cfg.args("adapter")
    assert not any(a.startswith("--jerk-psd") for a in adapter)
    assert adapter.index("--log-level") < adapter.index("--log-level=DEBUG")  # the last wins


@pytest.mark.parametrize("profile", ["sim", "px4", "px4-simulate"])
def test_the_vehicles_rigid_body_reaches_every_service_that_takes_it(elsewhere, profile):
    """``arcade up --mocap-body cf1``: the estimator and the bridge take cf1's frames, the
    simulators publish the vehicle's under it, the recorder and Foxglove hang the cable
    from it; each service's own parser takes the value."""
    import argparse

    from arcade.commands.service_options import options_given, service_parser
    from arcade.commands.up import add_arguments, stack_config
    from deploy import px4_profile

    p = argparse.ArgumentParser()
    add_arguments(p)
    argv = {"sim": [], "px4": ["--profile", "px4"], "px4-simulate": ["--profile", "px4"]}
    argv["px4-simulate"].append("--simulate")
    args = p.parse_args([*argv[profile], "--mocap-body", "cf1", "--foxglove"])
    cfg = stack_config(args, Path("run"), {}, {})
    if profile != "sim":
        cfg = px4_profile.config_from_args(args, cfg)
    takers = {"estimator", "recorder", "foxglove", "sim", "bridge", "px4sim"}
    assert {"estimator", "recorder", "foxglove"} < set(cfg.services())
    for name in cfg.services():
        given = cfg.args(name)
        parser = service_parser(name)
        if name in takers:
            assert parser.parse_args(given).mocap_body == "cf1", name
        else:
            assert "--mocap-body" not in options_given(parser, given), name
    assert {"sim", "bridge"} & set(cfg.services())


# ------------------------------------------------------------------ weights


def test_bridge_args_are_parsed_as_the_bridge_parses_them():
    from arcade.commands.up import parse_bridge_args

    bridge = parse_bridge_args(["--geofence=-3,3,-3,3,0,3", "--max-throttle", "0.8"])
    assert (bridge.geofence, bridge.max_throttle) == ("-3,3,-3,3,0,3", 0.8)
    assert parse_bridge_args([]).geofence == "-5,5,-5,5,-0.5,4"  # the bridge's default


def test_payload_heavier_than_the_bridges_vehicle_file_lifts_is_refused(
    elsewhere, capsys, monkeypatch
):
    """With --profile px4 the payload is checked against the bridge's --vehicle-file."""
    from arcade_io.vehicle import DEFAULT_VEHICLE

    _forbid_flight(monkeypatch)

    light = DEFAULT_VEHICLE.read_text().replace("max_thrust_n = 4.0", "max_thrust_n = 2.0")
    assert light != DEFAULT_VEHICLE.read_text()
    Path("light.toml").write_text(light)
    argv = [
        "up",
        "--profile",
        "px4",
        "--payload-g",
        "300",
        "--bridge-arg=--vehicle-file=light.toml",
    ]
    assert main(argv) == 2
    assert capsys.readouterr().err.startswith("error: --payload-g must be below 243 g")
    assert not (elsewhere / "runs").exists()


def test_a_bus_error_while_flying_is_one_line(elsewhere, capsys, monkeypatch):
    import zenoh

    def fail(*args, **kwargs):
        raise zenoh.ZError(
            "Can not create a new TCP listener bound to tcp/127.0.0.1:7450 at x.rs:5."
        )

    monkeypatch.setattr("deploy.launcher.run_flight", fail)
    assert main(["up", "--lockstep", "--out", "r"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: bus: Can not create a new TCP listener bound to tcp/127.0.0.1:7450"]


def test_up_help_states_defaults_and_units(capsys):
    with pytest.raises(SystemExit):
        main(["up", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "a PX4 vehicle link (default: sim)" in out
    assert "not a vehicle file (default: default)" in out
    assert "(default: <run folder>/adapter_checkpoint.npz, removed at start" in out
    assert "takes off to this height above the ground [m]" in out
    assert "$ARCADE_RUNS" in out
    assert "(default: real time)" in out
    assert "the name of the vehicle's rigid body in the motion capture" in out
    assert "e.g. cf1 (default: vehicle)" in out


def test_train_help_states_the_epochs_of_each_system(capsys):
    from arcade_core import encoder

    with pytest.raises(SystemExit):
        main(["train", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    cartpole, quadrotor = encoder.cartpole_config().epochs, encoder.quadrotor_config().epochs
    assert f"{cartpole} for the cartpole, {quadrotor} for the quadrotor" in out


@pytest.mark.parametrize("command", [["up", "--lockstep"], ["demo"], ["demo", "--cartpole"]])
def test_missing_weights_file_is_an_error(elsewhere, capsys, command):
    assert main([*command, "--weights", "typo.eqx"]) == 2
    assert capsys.readouterr().err == "error: --weights typo.eqx: no such file\n"
    assert not (elsewhere / "runs").exists() and not (elsewhere / "typo.eqx").exists()


@pytest.mark.parametrize("command", [["up"], ["demo"], ["demo", "--cartpole"]])
def test_corrupt_weights_file_is_an_error(elsewhere, capsys, command):
    Path("q.csv").write_text("t,x\n0,1\n")
    assert main([*command, "--weights", "q.csv"]) == 2
    err = capsys.readouterr().err
    assert err == "error: --weights q.csv: not an ARCADE VLD weight file (bad magic)\n"
    assert not (elsewhere / "runs").exists()


@pytest.mark.parametrize(
    ("command", "file", "message"),
    [
        (["up"], "cartpole_vld.eqx", "weights of the cartpole, not of the quadrotor"),
        (["demo"], "cartpole_vld.eqx", "weights of the cartpole, not of the quadrotor"),
        (
            ["demo", "--cartpole"],
            "quadrotor_vld.eqx",
            "weights of the quadrotor, not of the cartpole",
        ),
    ],
)
def test_weights_of_another_system_are_an_error(elsewhere, capsys, command, file, message):
    assert main([*command, "--weights", str(WEIGHTS / file)]) == 2
    assert capsys.readouterr().err == f"error: --weights {WEIGHTS / file}: {message}\n"
    assert not (elsewhere / "runs").exists()


def test_only_the_default_weights_are_trained_on_demand(tmp_path):
    def train(out):
        raise RuntimeError(f"training {out}")

    with pytest.raises(FileNotFoundError, match=r"typo\.eqx: no such file"):
        load_or_train(tmp_path / "typo.eqx", "cmd", train, train_if_missing=False)
    with pytest.raises(RuntimeError, match=r"training .*default\.eqx"):
        load_or_train(tmp_path / "default.eqx", "cmd", train)


def test_the_shipped_weights_pass_the_check():
    from arcade.commands.up import weights_problem

    assert weights_problem(None) is None
    assert weights_problem(WEIGHTS / "quadrotor_vld.eqx") is None


def test_degraded_events_are_shown_on_the_console():
    from arcade.commands.up import _show_faults

    lines: list[str] = []
    hook = _show_faults(lines.append)
    text = "no weights file at /x.eqx: nominal MPC"
    hook({"src": "controller/abc", "kind": "degraded", "text": text})
    hook({"src": "adapter/abc", "kind": "changepoint", "text": "changepoint at 3.1 s"})
    assert lines == [f"\n  [controller] degraded: {text}"]


@pytest.mark.parametrize("command", [["up"], ["demo"], ["demo", "--cartpole"]])
def test_an_out_that_is_a_file_is_refused(elsewhere, capsys, command):
    Path("taken").write_text("")
    assert main([*command, "--out", "taken"]) == 2
    assert capsys.readouterr().err == "error: --out taken is an existing file, not a folder\n"


def test_last_output_keeps_the_exception_when_more_output_follows(tmp_path):
    (tmp_path / "logs").mkdir()
    tail = "".join(f"exit message {i}\n" for i in range(6))
    (tmp_path / "logs" / "bridge.out").write_text(TRACEBACK + tail)
    rows = last_output(tmp_path, "bridge", lines=4)
    assert rows[0].startswith("RuntimeError: no autopilot heard on udpin://127.0.0.1:14999")
    assert rows[1:] == ["exit message 3", "exit message 4", "exit message 5"]


def test_demo_stack_failure_is_one_line(elsewhere, capsys, monkeypatch):
    import arcade.demo_stack

    def fail(*args, **kwargs):
        raise StackError("service adapter exited with code 1 (after 3 restarts)")

    monkeypatch.setattr(arcade.demo_stack, "run_demo", fail)
    assert main(["demo", "--out", "d"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"error: service adapter exited with code 1 (after 3 restarts) (run folder: "
        f"{elsewhere / 'd'})"
    ]


def test_px4_bus_configs_need_the_operator_session(tmp_path):
    files = {n: tmp_path / f"{n}.json5" for n in ("launcher", "bridge", "px4sim", "recorder")}
    files.update({n: tmp_path / f"{n}.json5" for n in ("estimator", "adapter", "controller")})
    cfg = Px4StackConfig(out=tmp_path / "r", simulate=True, bus_configs=files)
    with pytest.raises(ValueError, match=r"^bus_configs: no configuration for operator$"):
        Stack(cfg)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--seed", "-1"], "--seed: must be at least 0, got -1"),
        (["--epochs", "0"], "--epochs: must be at least 1, got 0"),
    ],
)
def test_train_bad_numbers_are_argument_errors(capsys, argv, message):
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--system", "cartpole", *argv])
    assert exit_.value.code == 2
    assert message in capsys.readouterr().err


def test_train_refuses_an_out_that_is_a_folder_before_training(tmp_path, capsys, monkeypatch):
    import arcade.training

    def no_training(**kwargs):
        raise AssertionError("trained despite an unusable --out")

    monkeypatch.setattr(arcade.training, "train_cartpole", no_training)
    assert main(["train", "--system", "cartpole", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: --out {tmp_path} is an existing folder; give a file name"]
