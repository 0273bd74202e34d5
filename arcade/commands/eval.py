"""`arcade eval cartpole|quadrotor` — the paper's tables, all methods in one run."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HELP = (
    "reproduce the paper's evaluations (cartpole: Table I, Fig. 3, App. E), all methods in one run"
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("system", choices=["cartpole"], help="which evaluation")
    p.add_argument("--json", action="store_true", help="print the results as one JSON object")
    p.add_argument("--trials", type=int, default=None, help="online trajectories (default 10)")
    p.add_argument("--quick", action="store_true", help="small, fast variant (smoke test)")
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="folder for figures and results.json (default runs/<time>-eval-<system>)",
    )
    p.add_argument("--seed", type=int, default=0)


def run(args: argparse.Namespace) -> int:
    from arcade import jaxsetup
    from arcade.runs import new_run_dir

    jaxsetup.configure()
    from benchmarks import cartpole_eval as ce

    s = ce.EvalSettings.quick() if args.quick else ce.EvalSettings()
    overrides = {"seed": args.seed}
    if args.trials is not None:
        if args.trials < 1:
            print("--trials must be at least 1", file=sys.stderr)
            return 2
        overrides["trials"] = args.trials
    s = type(s)(**{**s.__dict__, **overrides})
    out = args.out or new_run_dir(f"eval-{args.system}")
    result = ce.evaluate(s, out, progress=lambda m: print(f"[eval] {m}", file=sys.stderr))
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(result, indent=2))
    if args.json:
        print(json.dumps(result))
    else:
        print(ce.format_table(result))
        print(f"figures and results.json in {out}")
    return 0
