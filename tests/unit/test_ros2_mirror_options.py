"""`--ros2`: the mirror's place in the stack, and the options refused before anything starts."""

from __future__ import annotations

import pytest

from arcade.cli import main
from deploy.launcher import StackConfig
from deploy.px4_profile import Px4StackConfig
from deploy.stack_config import STOP_ORDER
from services import ros2_mirror


def test_the_mirror_starts_before_the_vehicle_and_stops_before_the_recorder(tmp_path):
    cfg = StackConfig(out=tmp_path, ros2=True)
    assert cfg.services() == ("recorder", "estimator", "adapter", "controller", "ros2", "sim")
    sim = cfg.args("sim")
    assert "ros2" in sim[sim.index("--wait-for") + 1].split(",")  # it sees the take-off
    assert STOP_ORDER.index("ros2") == len(STOP_ORDER) - 2
    assert "--nice" in cfg.args("ros2")  # never ahead of the control path
    assert "ros2" not in StackConfig(out=tmp_path).services()
    px4 = Px4StackConfig(out=tmp_path, ros2=True, simulate=True)
    assert px4.services()[-2:] == ("ros2", "bridge")
    assert "ros2" in px4.stop_order


def _refused(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    return capsys.readouterr().err


def test_a_vehicle_name_that_makes_no_ros_namespace_is_refused(capsys, monkeypatch, tmp_path):
    monkeypatch.setattr("deploy.launcher.run_flight", pytest.fail)
    monkeypatch.setattr("arcade.commands.up.weights_problem", lambda path: None)  # not the point
    err = _refused(capsys, ["up", "--ros2", "--lockstep", "--vehicle", "quad-1"])
    assert "error: --ros2: vehicle name 'quad-1' makes no ROS 2 namespace" in err
    assert "--service-arg ros2:--namespace=/NS" in err
    err = _refused(
        capsys,
        ["up", "--ros2", "--lockstep", "--service-arg", "ros2:--namespace=quad", "--out",
         str(tmp_path / "run")],
    )  # fmt: skip
    assert "invalid ROS 2 namespace name 'quad'" in err
    err = _refused(capsys, ["up", "--lockstep", "--service-arg", "ros2:--domain-id=3"])
    assert "--service-arg ros2: not a process of this stack" in err
    err = _refused(capsys, ["up", "--ros2", "--lockstep", "--service-arg", "ros2:--domain-id=300"])
    assert "ROS 2 domain id 300" in err
    assert not (tmp_path / "run").exists()


def test_demo_mirrors_one_flight_at_a_time(capsys, monkeypatch):
    monkeypatch.setattr("arcade.demo_stack.run_demo", pytest.fail)
    assert "error: --ros2: not with --compare" in _refused(capsys, ["demo", "--ros2", "--compare"])
    assert "--ros2" in _refused(capsys, ["demo", "--ros2", "--cartpole"])


def test_the_default_namespace_is_the_vehicles():
    assert ros2_mirror.default_namespace("quad_1") == "/arcade/quad_1"
    with pytest.raises(ValueError, match="makes no ROS 2 namespace"):
        ros2_mirror.default_namespace("quad.1")
