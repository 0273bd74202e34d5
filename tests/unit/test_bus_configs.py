"""Usage errors of ``arcade up --bus-configs`` and how ``StackConfig`` passes the per-process
bus configurations to the services (nothing is started). A stack flown through the ACL
router with these configurations is in ``tests/integration/test_stack_router.py``."""

from __future__ import annotations

from pathlib import Path

import pytest

from arcade.cli import main
from deploy.launcher import SERVICES, Stack, StackConfig


@pytest.fixture
def elsewhere(tmp_path, monkeypatch):
    """Run from a directory outside the repository, run folders under it."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("ARCADE_RUNS", str(tmp_path / "runs"))
    return tmp_path


def _configs(folder: Path, names) -> Path:
    folder.mkdir(exist_ok=True)
    for name in names:
        (folder / f"{name}.json5").write_text('{ mode: "client" }')
    return folder


def _up_error(argv: list[str], capsys) -> str:
    assert main(["up", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_up_bus_configs_lists_the_missing_files(elsewhere, capsys):
    folder = _configs(elsewhere / "bus", ["launcher", "recorder", "controller"])
    assert _up_error(["--bus-configs", str(folder)], capsys) == (
        f"error: --bus-configs {folder}: missing estimator.json5, adapter.json5, sim.json5"
    )
    assert not (elsewhere / "runs").exists()


def test_up_bus_configs_refuses_a_bad_file_and_other_options(elsewhere, capsys):
    folder = _configs(elsewhere / "bus", ["launcher", *SERVICES])
    (folder / "adapter.json5").write_text('{ mode: "clint" }')
    line = _up_error(["--bus-configs", str(folder)], capsys)
    assert line.startswith(f"error: --bus-configs: bus config {folder / 'adapter.json5'}: ")
    assert "unknown variant `clint`" in line and ".rs:" not in line
    line = _up_error(["--bus-configs", str(folder), "--hub", "tcp/127.0.0.1:7450"], capsys)
    assert line == (
        "error: --hub and --bus-configs exclude each other: the configurations name the endpoints"
    )
    # The px4 profile: its own processes and the operator's session.
    line = _up_error(["--bus-configs", str(folder), "--profile", "px4", "--simulate"], capsys)
    missing = "bridge.json5, px4sim.json5, operator.json5"
    assert line == f"error: --bus-configs {folder}: missing {missing}"
    assert _up_error(["--bus-configs", str(elsewhere / "nowhere")], capsys) == (
        f"error: --bus-configs {elsewhere / 'nowhere'}: not a directory"
    )
    assert not (elsewhere / "runs").exists()


def test_stack_config_bus_configs(elsewhere):
    files = {name: Path(f"bus/{name}.json5") for name in ("launcher", *SERVICES)}
    cfg = StackConfig(out=Path("r"), bus_configs=files)
    assert cfg.bus_configs["sim"] == elsewhere / "bus" / "sim.json5"  # made absolute
    assert cfg.bus_args("sim") == ["--bus-config", str(elsewhere / "bus" / "sim.json5")]
    assert "--hub" not in cfg.args("sim") and "--bus-config" not in cfg.args("sim")
    # Without bus configurations: peers on the hub, exactly as before.
    peers = StackConfig(out=Path("r"), hub="tcp/127.0.0.1:1234")
    assert peers.bus_args("sim") == []
    assert peers.args("sim")[2:4] == ["--hub", "tcp/127.0.0.1:1234"]
    no_launcher = {k: v for k, v in files.items() if k != "launcher"}
    with pytest.raises(ValueError, match=r"^bus_configs: no configuration for launcher$"):
        Stack(StackConfig(out=Path("r"), bus_configs=no_launcher))
    with pytest.raises(ValueError, match=r"^bus_configs: not a process of this stack: simm$"):
        Stack(StackConfig(out=Path("r"), bus_configs={**files, "simm": Path("x.json5")}))
    with pytest.raises(ValueError, match=r"^bus config .*launcher\.json5: No such file"):
        cfg.bus_config("launcher")


def test_stack_config_credentials_are_made_per_run_for_the_owner_only(elsewhere):
    import json
    import stat

    from arcade.commands.up import stack_config
    from arcade.demo_stack import free_hub

    cfg = StackConfig(out=Path("r"), hub="tcp/127.0.0.1:1234", credentials=True)
    peer = cfg.make_credentials()
    folder = elsewhere / "r" / "bus"
    assert peer == folder / "peer.json5"
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    for f in ("peer.json5", "users.txt"):
        assert stat.S_IMODE((folder / f).stat().st_mode) == 0o600, f
    auth = json.loads(peer.read_text())["transport"]["auth"]["usrpwd"]
    user, password = (folder / "users.txt").read_text().strip().split(":")
    assert (auth["user"], auth["password"]) == (user, password) and len(password) >= 40
    assert auth["dictionary_file"] == str(folder / "users.txt")
    # Every process, whatever its name, opens that file instead of the open hub.
    for name in ("sim", "controller", "bridge", "some-new-service"):
        assert cfg.bus_args(name) == ["--bus-config", str(peer)]
    assert "--hub" not in cfg.args("sim")
    assert cfg.bus_config("operator") is not None  # the launcher's own sessions too
    # A new run, a new password; the files go with the run.
    again = StackConfig(out=Path("r2"), hub=free_hub(), credentials=True)
    again.make_credentials()
    assert (elsewhere / "r2" / "bus" / "users.txt").read_text() != f"{user}:{password}\n"
    cfg.remove_credentials()
    assert not folder.exists()
    assert cfg.bus_args("sim") == [] and cfg.args("sim")[2:4] == ["--hub", "tcp/127.0.0.1:1234"]
    # Router configurations keep their set-up; so do open peers.
    files = {name: Path(f"bus/{name}.json5") for name in ("launcher", *SERVICES)}
    assert (
        StackConfig(out=Path("r3"), bus_configs=files, credentials=True).make_credentials() is None
    )
    assert StackConfig(out=Path("r4")).make_credentials() is None
    assert not (elsewhere / "r3" / "bus").exists() and not (elsewhere / "r4").exists()
    # `arcade up` on a hub of its own makes credentials; given --hub, the hub stays open.
    from arcade.cli import build_parser

    parsed = build_parser().parse_args(["up"])
    assert stack_config(parsed, Path("r5"), {}, {}).credentials
    parsed = build_parser().parse_args(["up", "--hub", "tcp/127.0.0.1:7450"])
    assert not stack_config(parsed, Path("r5"), {}, {}).credentials
