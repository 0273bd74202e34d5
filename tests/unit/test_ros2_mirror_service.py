"""The ROS 2 mirror service: what it makes of each record, its place in the stack
(`--ros2`), and the options refused before anything starts."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import ros2_idl as idl

from arcade.cli import main
from arcade_io import ros2_messages as rm
from deploy.launcher import StackConfig
from deploy.px4_profile import Px4StackConfig
from deploy.stack_config import STOP_ORDER
from services import ros2_mirror
from services.messages import Event, Setpoint, State

X = np.r_[1.0, 2.0, 3.0, 0.5, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.1, 0.2, 0.3]


def _wire(topic: str, record) -> dict:
    """ROS 2 topic -> the pycdr2 reading of its CDR bytes, for one bus record."""
    out = {}
    for ros_topic, msg in ros2_mirror.ros_messages(topic, record, "quad1"):
        ros_type = ros2_mirror.OUTPUTS[ros_topic]
        cls = {rm.ODOMETRY: idl.Odometry, rm.VECTOR3_STAMPED: idl.Vector3Stamped,
               rm.DIAGNOSTICS: idl.DiagnosticArray}[ros_type]  # fmt: skip
        out[ros_topic] = cls.deserialize(rm.cdr(msg, ros_type))
    return out


def test_each_record_becomes_its_ros_messages():
    odom = _wire("state", State(x=X, stamp=1.5, cov_diag=np.full(13, 1e-4)))["odom"]
    assert odom.child_frame_id == "base_link" and odom.pose.covariance[0] == 1e-4
    sp = _wire("setpoint", Setpoint(u=[6.5, 0.1, -0.2, 0.3], state_seq=1, stamp=1.5))
    assert sp["setpoint/thrust"].vector.z == 6.5 and sp["setpoint/body_rates"].vector.y == -0.2
    event = Event(kind="changepoint", text="changepoint detected", stamp=1.5, src="adapter/ab",
                  data={"changepoint_step": 30})  # fmt: skip
    (status,) = _wire("event", event)["changepoint"].status
    assert status.hardware_id == "quad1"
    assert {kv.key: kv.value for kv in status.values} == {
        "changepoint_step": "30",
        "src": "adapter/ab",
    }
    assert _wire("event", Event(kind="fault", text="x", stamp=1.5)) == {}  # not mirrored


def test_the_reference_is_the_planned_state_as_odometry():
    """The stack's reference (``x``: the planned state), as a record with that field."""
    ref = _wire("reference", SimpleNamespace(stamp=2.0, x=X))["reference"]
    assert ref.child_frame_id == "reference" and not any(ref.pose.covariance)
    p = ref.pose.pose.position
    assert (p.x, p.y, p.z) == (1.0, 2.0, 3.0)
    assert ros2_mirror.SOURCES["reference"] == "reference" and set(ros2_mirror.SOURCES) == set(
        ros2_mirror.OUTPUTS
    )


def test_a_record_ros_cannot_hold_is_refused():
    with pytest.raises(ValueError, match="not a ROS 2 time"):
        ros2_mirror.ros_messages("state", State(x=X, stamp=3.0e9), "quad1")


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
    # its own namespace, however abbreviated, is the one checked
    own = ["--service-arg", "ros2:--names=/q1", "--service-arg", "ros2:--domain-id=300"]
    err = _refused(capsys, ["up", "--ros2", "--lockstep", "--vehicle", "quad-1", *own])
    assert "ROS 2 domain id 300" in err and "quad-1" not in err
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


def test_demo_ros2_runs_the_mirror_in_its_stack(capsys, monkeypatch, tmp_path):
    from deploy.launcher import StackError

    flown = []

    def run_flight(cfg, **kwargs):
        flown.append(cfg)
        raise StackError("not flown in a unit test")

    monkeypatch.setattr("deploy.launcher.run_flight", run_flight)
    monkeypatch.setattr("arcade.commands.up.weights_problem", lambda path: None)
    assert main(["demo", "--ros2", "--out", str(tmp_path / "demo")]) == 1
    assert "not flown in a unit test" in capsys.readouterr().err
    (cfg,) = flown
    assert cfg.ros2 and "ros2" in cfg.services()
