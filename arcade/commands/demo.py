"""`arcade demo` — the in-process cartpole adaptation demo (writes a run folder)."""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "run the adaptation demo: prints a summary, writes plot, metrics and log to a run folder"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=None, help="run folder (default runs/<time>-demo)")
    p.add_argument("--weights", type=Path, default=None, help="cartpole weights file")
    p.add_argument("--seed", type=int, default=0)


def run(args: argparse.Namespace) -> int:
    from arcade import jaxsetup
    from arcade.runs import new_run_dir

    jaxsetup.configure()
    from arcade.demo_cartpole import run_demo
    from arcade.training import load_cartpole

    out = args.out or new_run_dir("demo")
    vld = load_cartpole(args.weights)
    print("flying the cartpole scenario (nominal MPC, then ARCADE MPC) ...", flush=True)
    summary = run_demo(vld, out, seed=args.seed)
    print(
        f"\n{'controller':14s} {'state RMSE':>10s} {'theta RMSE':>10s} {'pred. CRMSE':>11s}"
        "  detected changepoints"
    )
    for name in ("nominal_mpc", "arcade_mpc"):
        s = summary[name]
        print(
            f"{name:14s} {s['state_rmse_to_upright']:10.3f} {s['theta_rmse_rad']:10.3f} "
            f"{s['prediction_crmse']:11.3f}  {s['detected_changepoints']}"
        )
    print(f"interventions at steps {summary['interventions']}")
    print(f"\nrun folder: {out} (rollout.png, metrics.json, log.csv)")
    return 0
