"""The `arcade` command line: help, argument errors, and the benchmark JSON contracts."""

import json
import subprocess
import sys

import pytest

from arcade.cli import COMMANDS, build_parser, main


def test_help_lists_every_subcommand(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for name in COMMANDS:
        assert name in out


def test_every_subcommand_has_help():
    parser = build_parser()
    for name in COMMANDS:
        with pytest.raises(SystemExit) as exc:
            parser.parse_args([name, "--help"])
        assert exc.value.code == 0


def test_unknown_choice_is_rejected(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["bench", "nonsense"])
    assert exc.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


def test_mpc_options_belong_to_bench_mpc(capsys):
    assert main(["bench", "adapt", "--solver", "gauss_newton"]) == 2
    assert "belong to `arcade bench mpc`" in capsys.readouterr().err
    assert main(["bench", "mpc", "--max-steps", "0"]) == 2
    assert "--max-steps must be at least 1" in capsys.readouterr().err
    assert main(["bench", "mpc", "--solver", "newton"]) == 2
    assert "--solver must be one of gauss_newton_armijo" in capsys.readouterr().err


def test_bench_mpc_takes_the_solver_options():
    """`arcade bench mpc --solver --max-steps --residual` reach the benchmark."""
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "arcade",
            "bench",
            "mpc",
            "--json",
            "--quick",
            "--solver",
            "gauss_newton",
            "--max-steps",
            "5",
            "--residual",
            "held",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        check=True,
    )
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert (result["solver"], result["max_steps"], result["residual"]) == (
        "gauss_newton",
        5,
        "held",
    )
    assert 0 < result["median_ms"] <= result["p99_ms"]
    assert result["mean_iterations"] <= 5


def test_bench_adapt_json_contract():
    """`arcade bench adapt --json` prints the documented object (issue contract)."""
    proc = subprocess.run(
        [sys.executable, "-m", "arcade", "bench", "adapt", "--json", "--quick"],
        capture_output=True,
        text=True,
        timeout=600,
        check=True,
    )
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert set(result) == {"machine", "d", "l", "results"}
    assert (result["d"], result["l"]) == (13, 8)
    for floor in (1.0, 0.0):  # the preset's prior floor and Eq. 5 as written, side by side
        ks = [r["K"] for r in result["results"] if r["prior_floor"] == floor]
        assert ks == [5, 10, 15, 20, 30], (floor, ks)
    for r in result["results"]:
        assert 0 < r["median_us"] <= r["p99_us"]
