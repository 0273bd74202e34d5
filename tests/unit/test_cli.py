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
    """`arcade bench adapt --json` prints the documented object."""
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


@pytest.mark.parametrize(
    "options, message",
    [
        (["--solver", "dogleg"], "belong to `arcade bench mpc`"),
        (["--residual", "held", "--max-steps", "0"], "belong to `arcade bench mpc`"),
        (["--json"], "--json: `arcade bench report` writes a markdown file"),
        (["--method", "arcade"], "--method and --advanced-step belong to `arcade bench loop`"),
        (["--advanced-step"], "--method and --advanced-step belong to `arcade bench loop`"),
    ],
)
def test_bench_report_refuses_options_of_other_benchmarks(
    tmp_path, monkeypatch, capsys, options, message
):
    def reached(*args, **kwargs):
        raise AssertionError("the report started despite a usage error")

    monkeypatch.setattr("benchmarks.report.write_report", reached)
    assert main(["bench", "report", "--out", str(tmp_path / "B.md"), *options]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and err.count("\n") == 1


@pytest.mark.parametrize("which", ["soak", "fuzz"])
@pytest.mark.parametrize("ok", [True, False])
def test_bench_checks_exit_1_when_they_fail_and_show_progress(monkeypatch, capsys, which, ok):
    def run(quick, progress):
        progress(f"{which} halfway")
        return {"ok": ok}

    monkeypatch.setattr(f"benchmarks.{which}.run", run)
    assert main(["bench", which, "--quick", "--json"]) == (0 if ok else 1)
    captured = capsys.readouterr()
    assert json.loads(captured.out) == {"ok": ok}  # stdout stays the result
    assert captured.err == f"{which} halfway\n"


def test_bench_fuzz_without_the_tests_is_one_line(monkeypatch, capsys):
    def run(quick, progress):
        raise FileNotFoundError("fuzz tests not found (source tree needed): ['tests/x.py']")

    monkeypatch.setattr("benchmarks.fuzz.run", run)
    assert main(["bench", "fuzz"]) == 1
    err = capsys.readouterr().err
    assert err == "error: fuzz tests not found (source tree needed): ['tests/x.py']\n"


def test_bench_help_gives_the_durations(capsys):
    with pytest.raises(SystemExit):
        main(["bench", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    for phrase in (
        "loop ~2.5 min",
        "soak ~3 min",
        "variants 13 min plus the flagship's tuning",
        "report 7-21 min",
    ):
        assert phrase in out
    with pytest.raises(SystemExit):
        main(["--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "variants alone 13 min plus the flagship's tuning" in out and "~3 h on 2 cores" in out


def test_soak_reports_progress_per_tenth_of_its_chunks():
    from arcade_io import jaxsetup

    jaxsetup.configure()
    from benchmarks import soak

    lines: list[str] = []
    result = soak.soak(steps=200, chunk=10, progress=lines.append)
    assert result["steps"] == 200
    assert lines[0].startswith("[soak] float32, prior floor ") and "200 steps" in lines[0]
    assert [ln.split(": ")[1].split(" steps")[0] for ln in lines[1:]] == [
        str(k) for k in range(20, 201, 20)
    ]


def test_loop_shows_the_flight_time_every_period():
    from benchmarks.loop import _every

    shown: list[float] = []
    on_time = _every(10.0, shown.append)
    for t in (0.0, 4.0, 9.9, 10.0, 15.0, 20.5, 29.0, 31.0):
        on_time(t)
    assert shown == [0.0, 10.0, 20.5, 31.0]


def test_loop_counts_the_flight_time_from_the_first_state():
    from benchmarks.loop import _since_first_state

    seen: list[float] = []
    hook = _since_first_state(seen.append)
    for stamp in (0.0, 0.0, 2170.5, 2180.5, 2191.0):  # monotonic stamps once states flow
        hook(stamp)
    assert seen == [0.0, 10.0, 20.5]


@pytest.mark.parametrize("advanced", [False, True])
def test_bench_loop_advanced_step_reaches_the_controller(monkeypatch, capsys, advanced):
    import deploy.launcher

    flown = []

    class Flown(Exception):
        pass

    def run_flight(cfg, **kwargs):
        flown.append(cfg)
        raise Flown  # the options are what matters here, not a flight

    monkeypatch.setattr(deploy.launcher, "run_flight", run_flight)
    with pytest.raises(Flown):
        main(["bench", "loop", "--quick", *(["--advanced-step"] if advanced else [])])
    (cfg,) = flown
    assert ("--advanced-step" in cfg.args("controller")) == advanced
    assert "--advanced-step" not in cfg.args("adapter")
    assert ("advanced step" in capsys.readouterr().err) == advanced
