"""`arcade replay`: what it refuses, with one ``error:`` line and exit code 2, before it runs
anything (the replay itself is asserted on a stack flight in
tests/integration/test_stack_lockstep.py)."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from arcade.cli import main


class _Bus:
    def key(self, topic):
        return f"arcade/quad1/{topic}"

    def subscribe(self, topic, callback, check_order=True):
        pass


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A bus.mcap with a state and the adapter's start-up record (it flew arcade)."""
    from services.messages import Event, State
    from services.recorder import Recorder

    out = tmp_path_factory.mktemp("run")
    rec = Recorder(argparse.Namespace(out=out, incarnation=0, vehicle="quad1", geofence="none"))
    rec.setup(_Bus())
    argv = "--vehicle quad1 --rate 20 --lockstep --method arcade --link-delay 0"
    rec.record("event", Event(kind="ready", text=argv, data={"service": "adapter"}, stamp=0.0))
    rec.record(
        "state", State.from_parts(p=[0, 0, 1], v=[0] * 3, q=[1, 0, 0, 0], omega=[0] * 3, stamp=0.05)
    )
    rec.teardown()
    return out / "bus.mcap"


def _refused(capsys, argv):
    code = main(["replay", *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


def test_a_missing_file_and_a_file_that_is_no_mcap_are_refused(tmp_path, capsys):
    assert "no such file" in _refused(capsys, [str(tmp_path / "none.mcap")])
    bad = tmp_path / "bus.mcap"
    bad.write_bytes(b"not an mcap file at all")
    assert "not an MCAP file" in _refused(capsys, [str(bad)])


def test_an_mcap_without_arcade_states_or_the_adapter_record_is_refused(tmp_path, capsys):
    from mcap.writer import Writer

    empty = tmp_path / "bus.mcap"
    with empty.open("wb") as f:
        w = Writer(f)
        w.start()
        w.finish()
    assert "no arcade state" in _refused(capsys, [str(empty)])
    from services.messages import State
    from services.recorder import Recorder

    rec = Recorder(argparse.Namespace(out=tmp_path / "r", incarnation=0))
    rec.setup(_Bus())
    x = np.r_[0, 0, 1.0, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0]
    rec.record("state", State(x=x, stamp=1.0))
    rec.teardown()
    assert "start-up record of the adapter" in _refused(capsys, [str(tmp_path / "r" / "bus.mcap")])


def test_unknown_knobs_wrong_values_and_other_methods_knobs_are_refused(recording, capsys):
    path = str(recording)
    assert "unknown knob 'lamda'" in _refused(capsys, [path, "--set", "lamda=0.9"])
    assert "is not a number" in _refused(capsys, [path, "--set", "arcade_lambda=fast"])
    assert "is not an integer" in _refused(capsys, [path, "--set", "detector_window=2.5"])
    assert "not NAME=VALUE" in _refused(capsys, [path, "--set", "arcade_lambda"])
    # ours' knob on a flight of the flagship would change nothing: said, not ignored.
    why = _refused(capsys, [path, "--set", "ours_beta=0.1"])
    assert "not a knob of the adapter flying arcade" in why and "arcade_lambda" in why
    # The controller's knobs (augmentation, MPC) are not the adapter's either.
    for knob in ("arcade_thrust_smooth=30", "arcade_l1_cutoff=40"):
        why = _refused(capsys, [path, "--set", knob])
        assert "not a knob of the adapter flying arcade" in why
        listed = why.rsplit("(", 1)[1]
        assert "arcade_lambda" in listed and "thrust" not in listed and "l1" not in listed


def test_the_recordings_own_folder_is_refused_as_the_output(recording, capsys):
    why = _refused(capsys, [str(recording), "--out", str(recording.parent)])
    assert "own folder" in why


def test_lockstep_replay_puts_each_state_after_the_setpoint_of_the_one_before():
    """The recorder may receive state k+1 before the setpoint answering state k (they come
    on different links); a lockstep adapter waits for that setpoint, so the replay feeds
    them in that order, leaving the other records where they were."""
    from arcade.commands.replay import lockstep_order
    from services.messages import Command, Setpoint, State

    def state(t):
        return (
            "state",
            State.from_parts(p=[0, 0, 1], v=[0] * 3, q=[1, 0, 0, 0], omega=[0] * 3, stamp=t),
        )

    def setpoint(t):
        return ("setpoint", Setpoint(u=[5.0, 0, 0, 0], state_seq=0, stamp=t))

    start = ("command", Command(name="start", stamp=0.0))
    got = lockstep_order(
        [start, state(0.0), state(0.05), setpoint(0.0), setpoint(0.05), state(0.1)]
    )
    assert [(t, m.stamp) for t, m in got] == [
        ("command", 0.0),
        ("state", 0.0),
        ("setpoint", 0.0),
        ("state", 0.05),
        ("setpoint", 0.05),
        ("state", 0.1),
    ]


def test_a_knob_found_by_replay_goes_to_the_stack_adapter_through_service_arg():
    """``arcade up --service-arg adapter:--knob=NAME=VALUE`` is checked by the adapter's
    parser before anything starts (an appending option, told apart from the launcher's)."""
    from arcade.commands.service_options import options_given, service_parser

    parser = service_parser("adapter")
    assert options_given(parser, ["--knob=arcade_lambda=0.95"]) == {"--knob"}
    assert options_given(parser, ["--max-gap-periods=3"]) == {"--max-gap-periods"}
    with pytest.raises(ValueError, match="unknown knob 'lamda'"):
        options_given(parser, ["--knob=lamda=0.9"])
