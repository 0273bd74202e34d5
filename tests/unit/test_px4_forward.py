"""``--forward`` of the PX4 bridge and ``arcade up --profile px4`` (the forwarding itself is
flown in ``tests/integration/test_px4_bridge.py``)."""

from __future__ import annotations

import argparse

import pytest

from arcade.cli import build_parser
from arcade.commands.up import parse_bridge_args, usage_problem
from deploy import px4_profile
from deploy.stack_config import StackConfig
from services.px4_bridge_options import mavlink_url


def test_forward_takes_mavsdk_urls_only():
    assert mavlink_url("udpout://127.0.0.1:14550") == "udpout://127.0.0.1:14550"
    for bad in ("127.0.0.1:14550", "http://x:1", "udpout://"):
        with pytest.raises(argparse.ArgumentTypeError, match="not a MAVSDK URL"):
            mavlink_url(bad)
    assert parse_bridge_args(["--forward=udpout://a:1", "--forward=tcpout://b:2"]).forward == [
        "udpout://a:1",
        "tcpout://b:2",
    ]
    with pytest.raises(ValueError, match="not a MAVSDK URL: '14550'"):
        parse_bridge_args(["--forward", "14550"])


def test_arcade_up_forward_goes_to_the_bridge_of_the_px4_profile(tmp_path, capsys):
    url = "udpout://127.0.0.1:14550"
    args = build_parser().parse_args(["up", "--forward", url])
    assert usage_problem(args) == "--forward: only with --profile px4"
    args = build_parser().parse_args(["up", "--profile", "px4", "--simulate", "--forward", url])
    assert usage_problem(args) is None
    cfg = px4_profile.config_from_args(args, StackConfig(out=tmp_path))
    assert f"--forward={url}" in cfg.args("bridge")
    with pytest.raises(SystemExit) as exit_:  # argparse: the usage and one error line
        build_parser().parse_args(["up", "--profile", "px4", "--forward", "14550"])
    assert exit_.value.code == 2
    assert "argument --forward: not a MAVSDK URL: '14550'" in capsys.readouterr().err
