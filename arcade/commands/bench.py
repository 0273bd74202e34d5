"""`arcade bench adapt|mpc|loop|discrepancy|soak|fuzz|variants|report` — figures of design §7."""

from __future__ import annotations

import argparse
import importlib
import sys

from arcade_control.knobs import STACK_METHODS
from arcade_io import atomicfile, jsonout
from services.options import METHOD_HELP

HELP = (
    "benchmarks: adaptation step, MPC solve, bus loop, discrepancy workflow, numerics soak, "
    "fuzzing, quadrotor variants beside ours; `report` regenerates BENCHMARKS.md "
    "(on 2 cores: report 7-21 min, variants alone 13 min plus the flagship's tuning)"
)

#: Wall time of the long benchmarks on 2 CPU cores (BENCHMARKS.md, README).
DURATIONS = (
    "time on 2 CPU cores: loop ~2.5 min (a 120 s real-time flight after start-up), soak\n"
    "~3 min, variants 13 min plus the flagship's tuning, report 7-21 min (it re-runs the\n"
    "latency benchmarks, the soak,\n"
    "the cartpole evaluation and the discrepancy workflow, and renders the stored quadrotor\n"
    "results).\n"
    "loop, soak and fuzz show progress on stderr; the result (JSON) goes to stdout.\n"
    "fuzz runs the fuzz tests with pytest: it needs the source tree and the dev extras\n"
    "(pip install -e '.[dev]'). soak and fuzz exit with 1 when a check fails."
)

#: Benchmarks whose ``run`` takes ``progress`` (one line at a time, shown on stderr).
WITH_PROGRESS = ("loop", "soak", "fuzz")

# name -> module in `benchmarks/` exposing run(**kwargs) -> dict
BENCHES = {
    "adapt": "benchmarks.adapt",
    "mpc": "benchmarks.mpc",
    "loop": "benchmarks.loop",
    "discrepancy": "benchmarks.discrepancy",
    "soak": "benchmarks.soak",
    "fuzz": "benchmarks.fuzz",
    "variants": "benchmarks.quadrotor_variants",
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    from arcade_io.runs import count

    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = DURATIONS
    p.add_argument("which", choices=[*BENCHES, "report"], help="benchmark to run")
    p.add_argument(
        "--json",
        action="store_true",
        help="print the result as one JSON object on one line (default: indented JSON; "
        "discrepancy --sweep: a markdown table); not for report",
    )
    p.add_argument("--quick", action="store_true", help="fewer repetitions (smoke run)")
    p.add_argument(
        "--out",
        default=None,
        help="report: file to write (default: BENCHMARKS.md); variants: also write the "
        "results to this JSON file, once the run has finished",
    )
    g = p.add_argument_group("discrepancy")
    g.add_argument(
        "--sweep",
        action="store_true",
        help="sweep every quadrotor effect over its plausible range (a markdown "
        "table, or JSON with --json) instead of timing the workflow",
    )
    g.add_argument(
        "--limits",
        action="store_true",
        help="measure the minimum detectable magnitude of every quadrotor effect",
    )
    g.add_argument(
        "--effect",
        action="append",
        default=None,
        metavar="NAME",
        help="only this quadrotor effect (repeatable; `arcade effects` lists them)",
    )
    g.add_argument(
        "--seed", type=count(0), default=None, help="flight seed of --sweep / --limits (default: 0)"
    )
    lp = p.add_argument_group("loop")
    lp.add_argument(
        "--method",
        choices=STACK_METHODS,
        default=None,
        help=METHOD_HELP,
    )
    lp.add_argument(
        "--advanced-step",
        action="store_true",
        help="the controller solves one period ahead and answers each state from that plan "
        "(the controller service's --advanced-step; docs/quadrotor-closed-loop.md); default: "
        "it solves after each state",
    )
    m = p.add_argument_group("mpc")
    m.add_argument(
        "--residual",
        choices=("rollout", "held"),
        default=None,
        help="learned residual inside the rollout (the controllers' scheme, "
        "default) or held along the warm start",
    )
    m.add_argument(
        "--solver",
        default=None,
        help="MPC solver: gauss_newton_armijo (the quadrotor configuration's, "
        "default), gauss_newton, dogleg or levenberg_marquardt",
    )
    m.add_argument(
        "--max-steps",
        type=int,
        default=None,
        help="solver iteration cap (default: the configuration's, 8)",
    )


def run(args: argparse.Namespace) -> int:
    from arcade_io import jaxsetup

    if args.out is not None and args.which not in ("report", "variants"):
        print("error: --out belongs to `arcade bench report` and `variants`", file=sys.stderr)
        return 2
    if args.out is not None and args.which == "variants":
        from arcade_io.runs import check_output_file

        try:
            check_output_file(args.out, "--out")
        except ValueError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    sweep_options = args.sweep or args.limits or args.effect or args.seed is not None
    if sweep_options and args.which != "discrepancy":
        print(
            "error: --sweep, --limits, --effect and --seed belong to `arcade bench discrepancy`",
            file=sys.stderr,
        )
        return 2
    if args.which == "discrepancy" and sweep_options:
        return _discrepancy_sweep(args)
    mpc_options = {
        k: v
        for k, v in (
            ("residual", args.residual),
            ("solver", args.solver),
            ("max_steps", args.max_steps),
        )
        if v is not None
    }
    if mpc_options and args.which != "mpc":
        print(
            "error: --residual, --solver and --max-steps belong to `arcade bench mpc`",
            file=sys.stderr,
        )
        return 2
    if (args.method is not None or args.advanced_step) and args.which != "loop":
        print("error: --method and --advanced-step belong to `arcade bench loop`", file=sys.stderr)
        return 2
    if args.which == "report":
        if args.json:
            print("error: --json: `arcade bench report` writes a markdown file", file=sys.stderr)
            return 2
        from arcade_io.runs import check_output_file

        out = args.out or "BENCHMARKS.md"
        try:
            check_output_file(out, "--out")
        except ValueError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        jaxsetup.configure()
        from benchmarks.report import write_report

        path = write_report(out, quick=args.quick)
        print(f"wrote {path}")
        return 0
    jaxsetup.configure()
    if args.max_steps is not None and args.max_steps < 1:
        print("error: --max-steps must be at least 1", file=sys.stderr)
        return 2
    if args.solver is not None:
        from arcade_core.mpc import SOLVERS

        if args.solver not in SOLVERS:
            print(f"error: --solver must be one of {', '.join(SOLVERS)}", file=sys.stderr)
            return 2
    module = importlib.import_module(BENCHES[args.which])
    extra: dict = {"method": args.method} if args.method is not None else {}
    if args.advanced_step:
        extra["advanced"] = True
    if args.which in WITH_PROGRESS:  # long runs: a line now and then, stdout stays the result
        extra["progress"] = lambda m: print(m, file=sys.stderr, flush=True)
    try:
        result = module.run(quick=args.quick, **mpc_options, **extra)
    except FileNotFoundError as exc:
        if args.which != "fuzz":
            raise
        print(f"error: {exc}", file=sys.stderr)  # the fuzz tests are not installed
        return 1
    if args.out is not None:  # written whole, so a failed run leaves an older file intact
        from pathlib import Path

        out = atomicfile.write_text(Path(args.out), jsonout.dumps(result, indent=1))
        print(f"wrote {out}", file=sys.stderr)
    if args.json:
        print(jsonout.dumps(result))
    else:
        print(jsonout.dumps(result, indent=2))
    sys.stdout.flush()
    return 0 if result.get("ok", True) else 1  # soak and fuzz: checks failed


def _discrepancy_sweep(args: argparse.Namespace) -> int:
    from arcade_io import jaxsetup
    from benchmarks import discrepancy

    if not (args.sweep or args.limits):
        print("error: --effect and --seed need --sweep or --limits", file=sys.stderr)
        return 2
    if args.sweep and args.limits:
        print("error: --sweep and --limits are separate runs: give one of them", file=sys.stderr)
        return 2
    error = discrepancy.check_effects(args.effect, "limits" if args.limits else "sweep")
    if error:
        print(f"error: --effect: {error}", file=sys.stderr)
        return 2
    jaxsetup.configure()
    seed = 0 if args.seed is None else args.seed
    if args.limits:
        print(
            jsonout.dumps(
                discrepancy.detection_limits(seed=seed, effects=args.effect),
                indent=None if args.json else 2,
            )
        )
        return 0

    def progress(row: dict) -> None:  # one line per flight on stderr: long job
        print(jsonout.dumps(row), file=sys.stderr, flush=True)

    result = discrepancy.sweep(args.effect, seed=seed, progress=progress)
    print(jsonout.dumps(result) if args.json else discrepancy.sweep_table(result["cases"]))
    return 0
