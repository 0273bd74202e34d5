"""`arcade bench adapt|mpc|loop|report` — latency figures (design §7)."""

from __future__ import annotations

import argparse
import importlib
import json
import sys

HELP = (
    "latency benchmarks: adaptation step, MPC solve, bus loop; `report` regenerates BENCHMARKS.md"
)

# name -> module in `benchmarks/` exposing run(**kwargs) -> dict
BENCHES = {
    "adapt": "benchmarks.adapt",
    "mpc": "benchmarks.mpc",
    "loop": "benchmarks.loop",
    "discrepancy": "benchmarks.discrepancy",
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("which", choices=[*BENCHES, "report"], help="benchmark to run")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")
    p.add_argument("--quick", action="store_true", help="fewer repetitions (smoke run)")
    p.add_argument("--out", default="BENCHMARKS.md", help="report: file to write")


def run(args: argparse.Namespace) -> int:
    from arcade import jaxsetup

    jaxsetup.configure()
    if args.which == "report":
        from benchmarks.report import write_report

        path = write_report(args.out, quick=args.quick)
        print(f"wrote {path}")
        return 0
    module = importlib.import_module(BENCHES[args.which])
    result = module.run(quick=args.quick)
    if args.json:
        print(json.dumps(result))
    else:
        print(json.dumps(result, indent=2))
    sys.stdout.flush()
    return 0
