"""`arcade demo` — the whole service stack in lockstep (``--cartpole``: the cartpole demo)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from arcade_control.knobs import DEFAULT_STACK_METHOD, STACK_METHODS
from deploy import trajectories
from services.options import METHOD_HELP

HELP = (
    "fly the figure-eight payload-drop demo through the full service stack (simulator, "
    "estimator, adapter, controller as processes over Zenoh); writes plot, metrics, logs"
)


#: Defaults of the stack demo's flight options (None on the command line: not given).
PAYLOAD_G, SPEED = 175.0, 2.5


def add_arguments(p: argparse.ArgumentParser) -> None:
    from arcade_io.runs import count, number

    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="run folder (default $ARCADE_RUNS/<time>-demo, or -demo-cartpole, "
        "$ARCADE_RUNS defaulting to runs; relative to the current directory)",
    )
    p.add_argument(
        "--payload-g",
        type=number(0.0),
        default=None,
        help=f"swinging payload [g], below what the vehicle lifts at full thrust "
        f"(default: {PAYLOAD_G:g})",
    )
    p.add_argument(
        "--speed",
        type=number(0.0, low_open=True),
        default=None,
        help="mean speed of the figure-eight, of a built-in --trajectory and of waypoints "
        f"without times [m/s] (default: {SPEED:g})",
    )
    p.add_argument("--trajectory", default=None, metavar="FILE|NAME", help=trajectories.HELP)
    p.add_argument("--seed", type=count(0), default=0, help="trial seed (default: %(default)s)")
    p.add_argument(
        "--weights",
        type=Path,
        default=None,
        help="VLD weights: quadrotor (default deploy/weights/quadrotor_vld.eqx), with "
        "--cartpole cartpole (default deploy/weights/cartpole_vld.eqx, trained first if "
        "missing); a given file must exist and load",
    )
    p.add_argument("--x64", action="store_true", help="compute in float64 (stack demo)")
    p.add_argument(
        "--method",
        choices=STACK_METHODS,
        default=None,
        help=METHOD_HELP,
    )
    p.add_argument(
        "--compare",
        action="store_true",
        help="fly l1, ours and arcade through the stack one after the other on the same "
        "seed and plan; writes their x, y, z errors around the release side by side "
        "(compare.png), a metrics table (compare.json) and each flight's run folder",
    )
    from arcade.commands.service_options import add_ros2_argument

    add_ros2_argument(p)
    from arcade.commands.service_options import add_foxglove_argument

    add_foxglove_argument(p)
    p.add_argument(
        "--cartpole",
        action="store_true",
        help="run the in-process cartpole adaptation demo instead",
    )


def _error(msg: str, code: int = 2) -> int:
    print(f"error: {msg}", file=sys.stderr, flush=True)
    return code


def run_cartpole(args: argparse.Namespace) -> int:
    ignored = [
        name
        for name, given in (
            ("--payload-g", args.payload_g is not None),
            ("--speed", args.speed is not None),
            ("--x64", args.x64),
            ("--method", args.method is not None),
            ("--compare", args.compare),
            ("--ros2", args.ros2),
            ("--trajectory", args.trajectory is not None),
        )
        if given
    ]
    if ignored:
        return _error(f"{', '.join(ignored)}: not with --cartpole (stack demo options)")
    from arcade.commands.up import out_problem

    problem = out_problem(args.out)
    if problem is not None:
        return _error(problem)
    from arcade_io import jaxsetup
    from arcade_io.runs import new_run_dir

    jaxsetup.configure()
    from arcade.training import load_cartpole
    from arcade_io.weights import WeightFileError

    try:  # a given file must load; the shipped one is trained first when it is missing
        vld = load_cartpole(args.weights)
    except (OSError, WeightFileError) as err:
        if args.weights is None:  # the shipped file
            return _error(str(err).splitlines()[0], 1)
        return _error(f"--weights {str(err).splitlines()[0]}")
    from arcade.demo_cartpole import run_demo

    out = args.out or new_run_dir("demo-cartpole")
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


def payload_problem(payload_g: float | None) -> str | None:
    """Why the stack demo's payload is more than the shipped vehicle lifts, or None."""
    from arcade.commands.sim import payload_limit_problem
    from arcade_io.vehicle import load_vehicle

    return payload_limit_problem(load_vehicle(None), PAYLOAD_G if payload_g is None else payload_g)


def run(args: argparse.Namespace) -> int:
    if args.foxglove is not None and (args.compare or args.cartpole):
        return _error("--foxglove: for the stack demo, not with --compare or --cartpole")
    if args.cartpole:
        return run_cartpole(args)
    if args.compare and args.method is not None:
        return _error("--method: not with --compare (it flies l1, ours and arcade)")
    if args.compare and args.trajectory is not None:
        return _error("--trajectory: not with --compare (it flies the figure-eight)")
    from arcade.commands.up import out_problem, weights_problem
    from arcade_io import jaxsetup
    from arcade_io.runs import new_run_dir

    if args.compare and args.ros2:
        return _error("--ros2: not with --compare (one flight at a time is mirrored)")
    problem = payload_problem(args.payload_g) or out_problem(args.out)
    if problem is not None:
        return _error(problem)
    jaxsetup.configure(x64=args.x64)
    bad_weights = weights_problem(args.weights)
    if bad_weights is not None:
        return _error(*bad_weights)
    from arcade.demo_stack import format_summary, run_demo

    payload_g = PAYLOAD_G if args.payload_g is None else args.payload_g
    speed = SPEED if args.speed is None else args.speed
    planned = None
    if args.trajectory is not None:
        from deploy.trajectories import option_problem

        trajectory, problem = option_problem(args.trajectory, speed=speed, payload_g=payload_g)
        if problem is not None:
            return _error(problem)
        planned = (args.trajectory, trajectory)
    out = Path(args.out or new_run_dir("demo")).absolute()
    if planned is None:
        plan = f"{speed:g} m/s figure-eight, released before the second lap"
    else:
        plan = f"trajectory {args.trajectory}, released at 95 % of its first lap"
    print(f"ARCADE stack demo: {payload_g:g} g payload, {plan} (lockstep)", flush=True)
    if args.foxglove is not None:
        from arcade.commands.service_options import foxglove_line

        print(foxglove_line(args.foxglove), flush=True)
    from deploy.launcher import StackError

    if args.compare:
        return _compare(args, out, payload_g, speed)
    try:
        summary = run_demo(
            out,
            payload_g=payload_g,
            speed=speed,
            seed=args.seed,
            x64=args.x64,
            weights=args.weights,
            method=args.method or DEFAULT_STACK_METHOD,
            ros2=args.ros2,
            foxglove_port=args.foxglove,
            trajectory=planned,
        )
    except (StackError, ValueError, OSError) as err:
        return _error(f"{err} (run folder: {out})", 1)
    print()
    print(format_summary(summary))
    print(f"\nrun folder: {out} (flight.png, metrics.json, logs/, flight_log.csv, bus.mcap)")
    codes = summary["exit_codes"]
    return 0 if all(c == 0 for c in codes.values()) and not summary["crashed"] else 1


def _compare(args: argparse.Namespace, out: Path, payload_g: float, speed: float) -> int:
    from arcade.demo_compare import COMPARED, format_compare, run_compare
    from deploy.launcher import StackError

    print(f"flying {', '.join(COMPARED)} one after the other on seed {args.seed}", flush=True)
    try:
        result = run_compare(
            out,
            methods=COMPARED,
            progress=lambda m: print(m, file=sys.stderr, flush=True),
            payload_g=payload_g,
            speed=speed,
            seed=args.seed,
            x64=args.x64,
            weights=args.weights,
        )
    except (StackError, ValueError, OSError) as err:
        return _error(f"{err} (run folder: {out})", 1)
    print()
    print(format_compare(result))
    names = ", ".join(f"{m}/" for m in COMPARED)
    print(f"\nrun folder: {out} (compare.png, compare.json, {names})")
    flights = result["methods"].values()
    clean = all(all(c == 0 for c in s["exit_codes"].values()) for s in flights)
    return 0 if clean and not any(s["crashed"] for s in flights) else 1
