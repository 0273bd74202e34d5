"""`arcade demo` — the whole service stack in lockstep (``--cartpole``: the cartpole demo)."""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = (
    "fly the figure-eight payload-drop demo through the full service stack (simulator, "
    "estimator, adapter, controller as processes over Zenoh); writes plot, metrics, logs"
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=None, help="run folder (default runs/<time>-demo)")
    p.add_argument("--payload-g", type=float, default=175.0, help="swinging payload [g]")
    p.add_argument("--speed", type=float, default=2.5, help="figure-eight mean speed [m/s]")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--weights",
        type=Path,
        default=None,
        help="VLD weights (quadrotor; default the shipped file; cartpole with --cartpole)",
    )
    p.add_argument("--x64", action="store_true", help="compute in float64")
    p.add_argument(
        "--cartpole",
        action="store_true",
        help="run the in-process cartpole adaptation demo instead",
    )


def run_cartpole(args: argparse.Namespace) -> int:
    from arcade import jaxsetup
    from arcade.runs import new_run_dir

    jaxsetup.configure()
    from arcade.demo_cartpole import run_demo
    from arcade.training import load_cartpole

    out = args.out or new_run_dir("demo-cartpole")
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


def run(args: argparse.Namespace) -> int:
    if args.cartpole:
        return run_cartpole(args)
    from arcade import jaxsetup
    from arcade.runs import new_run_dir

    jaxsetup.configure(x64=args.x64)
    from arcade.demo_stack import format_summary, run_demo

    out = args.out or new_run_dir("demo")
    print(
        f"ARCADE stack demo: {args.payload_g:g} g payload, {args.speed:g} m/s figure-eight, "
        "released before the second lap (lockstep)",
        flush=True,
    )
    summary = run_demo(
        out,
        payload_g=args.payload_g,
        speed=args.speed,
        seed=args.seed,
        x64=args.x64,
        weights=args.weights,
    )
    print()
    print(format_summary(summary))
    print(f"\nrun folder: {out} (flight.png, metrics.json, logs/, flight_log.csv, bus.mcap)")
    codes = summary["exit_codes"]
    return 0 if all(c == 0 for c in codes.values()) and not summary["crashed"] else 1
