"""`arcade up` — launch the service stack (simulator or vehicle link + all services)."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from arcade.commands.service_options import (
    add_foxglove_argument,
    add_ros2_argument,
    foxglove_line,
    group_service_args,
    ros2_problem,
    service_args_problem,
)
from arcade_control.knobs import DEFAULT_STACK_METHOD, STACK_METHODS
from deploy import trajectories
from services.messages import PAYLOAD_BODY, VEHICLE_BODY
from services.options import METHOD_HELP, MOCAP_BODY_HELP, mocap_body

HELP = "launch the service stack as processes over Zenoh (profile sim or px4)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from arcade_io.runs import count, number

    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = (
        "examples:\n"
        "  arcade up --profile sim --lockstep          deterministic flight, as fast as it goes\n"
        "  arcade up --profile sim --rate 50           real time at 50 Hz (Ctrl-C stops)\n"
        "  arcade up --payload-g 125 --speed 1.5 --out runs/my-flight\n"
        "  arcade up --profile px4 --connect serial:///dev/ttyACM0:921600\n"
        "                                              a real PX4 (asks before arming)\n"
        "  arcade up --profile px4 --simulate --arm   the same chain against a simulated PX4\n"
        "  arcade up --profile px4 --forward udpout://127.0.0.1:14550\n"
        "                                              QGroundControl watches the vehicle\n"
        "  arcade up --profile px4 --service-arg estimator:--mocap-noise=1e-4\n"
        "                                              your motion capture's noise [m]\n"
        "  arcade up --lockstep --trajectory my_path.csv\n"
        "                                              your own path (docs/trajectories.md)\n"
        "  arcade up --lockstep --bus-configs deploy/my-router\n"
        "                                              every process a client of a router\n"
        "The run folder gets logs/<service>.log, stats/, events.jsonl, truth.csv,\n"
        "flight_log.csv and bus.mcap (open it in Foxglove Studio). Crashes, restarts,\n"
        "failsafes and degraded modes are shown as they happen. Options that do not fit\n"
        "together and a --weights file that does not load are refused (exit code 2)\n"
        "before anything starts. A service's own options (`python -m services NAME\n"
        "--help`) go through --service-arg, e.g. --service-arg estimator:--mocap-noise=1e-4\n"
        "(StackConfig.extra from Python). With --foxglove, Foxglove shows the flight live\n"
        "(open a Foxglove WebSocket connection to ws://127.0.0.1:8765).\n"
        "The clock is real time unless --lockstep is given. Without --out the run folder\n"
        "is made under $ARCADE_RUNS (default runs/)."
    )
    p.add_argument(
        "--profile",
        choices=("sim", "px4"),
        default="sim",
        help="sim: MuJoCo simulator as the vehicle; px4: a PX4 vehicle link (default: %(default)s)",
    )
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="simulated clock: the simulator waits for every setpoint (default: real time)",
    )
    p.add_argument(
        "--vehicle",
        default="default",
        metavar="NAME",
        help="the vehicle's name on the bus (topic prefix arcade/NAME/...), not a vehicle "
        "file (default: %(default)s)",
    )
    p.add_argument(
        "--mocap-body",
        type=mocap_body,
        default=VEHICLE_BODY,
        metavar="NAME",
        help=f"{MOCAP_BODY_HELP}. Give your motion capture's name for the vehicle, e.g. "
        "cf1 (default: %(default)s)",
    )
    p.add_argument(
        "--duration",
        type=number(0.0, low_open=True),
        default=None,
        help="flight duration [s] (default: take-off, hover, two figure-eight laps)",
    )
    p.add_argument(
        "--payload-g",
        type=number(0.0),
        default=175.0,
        help="swinging payload [g], below what the vehicle lifts at full thrust "
        "(default: %(default)s)",
    )
    p.add_argument(
        "--speed",
        type=number(0.0, low_open=True),
        default=2.5,
        help="mean speed of the figure-eight, of a built-in --trajectory and of "
        "waypoints without times [m/s] (default: %(default)s)",
    )
    p.add_argument(
        "--trajectory",
        default=None,
        metavar="FILE|NAME",
        help=trajectories.HELP,
    )
    p.add_argument(
        "--rate",
        type=number(0.0, low_open=True),
        default=20.0,
        help="control rate [Hz] (default: %(default)s)",
    )
    p.add_argument("--seed", type=count(0), default=0, help="trial seed (default: %(default)s)")
    p.add_argument(
        "--link-delay",
        type=number(0.0),
        default=0.0,
        metavar="S",
        help="the delay from a state's sample instant to when its setpoint acts on the "
        "vehicle's rate loop, shorter than one control period: the controller plans and "
        "the adapter learns from the state predicted that far ahead (measure it: "
        "docs/quadrotor-closed-loop.md; default: 0, not compensated). In the sim profile "
        "--service-arg sim:--command-delay=S emulates such a link",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="run folder (default $ARCADE_RUNS/<time>-up, $ARCADE_RUNS defaulting to runs; "
        "relative to the current directory)",
    )
    p.add_argument(
        "--hub",
        default=None,
        help="Zenoh hub endpoint of the peers, open to any process that connects to it "
        "(default: a free loopback port that only this run's processes, given a password "
        "made for the run, can join)",
    )
    p.add_argument(
        "--bus-configs",
        type=Path,
        default=None,
        metavar="DIR",
        help="one Zenoh configuration per process instead of peers on the hub: "
        "DIR/<name>.json5 for launcher, recorder, estimator, adapter, controller and sim; "
        "with --profile px4 bridge (and px4sim with --simulate) instead of sim, and "
        "operator; ros2 with --ros2, foxglove with --foxglove (e.g. clients of a router "
        "with their own user and password); checked before anything starts",
    )
    p.add_argument(
        "--weights",
        type=Path,
        default=None,
        help="quadrotor VLD weights file (default deploy/weights/quadrotor_vld.eqx); "
        "checked before anything starts",
    )
    p.add_argument(
        "--method",
        choices=STACK_METHODS,
        default=DEFAULT_STACK_METHOD,
        help=METHOD_HELP,
    )
    p.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        help="adapter posterior checkpoint, restored if present (default: "
        "<run folder>/adapter_checkpoint.npz, removed at start: the flight starts at the "
        "prior)",
    )
    p.add_argument("--x64", action="store_true", help="compute in float64")
    p.add_argument(
        "--service-arg",
        action="append",
        default=[],
        metavar="NAME:ARG",
        help="an option of one service of the stack, e.g. "
        "--service-arg=estimator:--jerk-psd=50 or controller:--max-model-age=1.0 "
        "(repeatable; `python -m services NAME --help` lists them); parsed as the service "
        "parses it before anything starts; the options the launcher sets (vehicle, bus, "
        "run folder, rate, plan, weights, ...) are refused but --log-level, and the "
        "bridge's go through --bridge-arg",
    )
    p.add_argument(
        "--no-realtime-priority",
        dest="realtime_priority",
        action="store_false",
        help="realtime clock: keep the normal scheduling policy and let idle CPUs "
        "sleep (default: the vehicle link, estimator and controller run under "
        "SCHED_FIFO after warm-up and request a CPU wake-up latency of 0 us, "
        "which needs root or an rtprio limit; without, they warn)",
    )
    add_ros2_argument(p)
    add_foxglove_argument(p)
    from deploy import px4_profile

    px4_profile.add_arguments(p)


#: The px4 profile's options and the value each has when not given.
PX4_OPTIONS = {
    "connect": None,
    "simulate": False,
    "arm": False,
    "takeoff_m": None,
    "on_ground": False,
    "forward": [],
    "bridge_arg": [],
}


def usage_problem(args: argparse.Namespace) -> str | None:
    """Why these options do not fit together or do not parse (one line), or None."""
    if args.bus_configs is not None and args.hub is not None:
        return "--hub and --bus-configs exclude each other: the configurations name the endpoints"
    from services.options import link_delay_problem

    problem = (
        link_delay_problem(args.link_delay, args.rate)
        or hub_problem(args.hub)
        or vehicle_name_problem(args.vehicle)
        or mocap_body_problem(args)
        or ros2_problem(args)
    )
    if problem is not None:
        return problem
    if args.profile != "px4":
        given = [k for k, v in PX4_OPTIONS.items() if getattr(args, k) != v]
        if given:
            names = ", ".join("--" + k.replace("_", "-") for k in given)
            return f"{names}: only with --profile px4"
        return None
    if args.lockstep:
        return "--lockstep is for --profile sim: profile px4 runs on the wall clock"
    if args.on_ground and not args.simulate:
        return "--on-ground is for the simulated PX4: add --simulate"
    if args.takeoff_m is not None and not (math.isfinite(args.takeoff_m) and args.takeoff_m > 0):
        return f"--takeoff-m must be a positive number, got {args.takeoff_m:g}"
    return bridge_args_problem([*(f"--forward={url}" for url in args.forward), *args.bridge_arg])


def hub_problem(hub: str | None) -> str | None:
    """Why ``--hub`` is not a Zenoh endpoint (the peers' configuration is refused), or None."""
    if hub is None:
        return None
    import zenoh

    from services.bus import peer_config, zenoh_reason

    try:
        peer_config(hub)
    except zenoh.ZError as err:
        return f"--hub {hub}: {zenoh_reason(err)}"
    return None


def vehicle_name_problem(name: str) -> str | None:
    """Why ``--vehicle`` is not a bus name, or None. A vehicle file is a common mistake:
    ``arcade sim``, ``simulate`` and ``discrepancy`` take one under the same option."""
    from services.bus import check_name

    why = f"{name!r} looks like a vehicle file" if name.endswith(".toml") else None
    try:
        check_name("vehicle", name)
    except ValueError as err:
        why = str(err)
    if why is None:
        return None
    return (
        f"--vehicle is the vehicle's name on the bus, not a vehicle file: {why}; a vehicle "
        "file goes to the bridge with --profile px4 --bridge-arg=--vehicle-file=FILE"
    )


def mocap_body_problem(args: argparse.Namespace) -> str | None:
    """Why ``--mocap-body`` does not fit: the simulated payload's name where a simulator
    flies (one line), or None."""
    if (args.profile == "sim" or args.simulate) and args.mocap_body == PAYLOAD_BODY:
        return f"--mocap-body {PAYLOAD_BODY}: the simulated payload's rigid body has that name"
    return None


def parse_bridge_args(bridge_args: list[str]) -> argparse.Namespace:
    """``--bridge-arg`` values parsed with the bridge's own options and its geofence check,
    as the bridge will parse them; ``ValueError`` with one line otherwise."""
    from services import options, px4_bridge

    parser = options.common_parser("bridge", "PX4 bridge")
    px4_bridge._extra(parser)

    def refuse(message: str) -> None:  # instead of printing the usage and exiting
        raise ValueError(message)

    parser.error = refuse  # type: ignore[method-assign]
    bridge = parser.parse_args(bridge_args)
    try:
        px4_bridge.Geofence.parse(bridge.geofence)
    except ValueError as err:
        raise ValueError(f"--geofence {bridge.geofence}: {err}") from None
    return bridge


def bridge_args_problem(bridge_args: list[str]) -> str | None:
    """Why the bridge would refuse ``--bridge-arg`` at its start, or it sets what ``arcade
    up`` sets for every service (one line), or None."""
    from arcade.commands.service_options import options_given, service_parser

    try:
        parse_bridge_args(bridge_args)
        given = options_given(service_parser("bridge"), bridge_args)
    except ValueError as err:
        return f"--bridge-arg: {err}"
    if "--mocap-body" in given:  # one name on the estimator and the bridge
        return "--bridge-arg: --mocap-body is arcade up's own option, not the bridge's alone"
    return None


def trajectory_problem(args: argparse.Namespace):
    """``--trajectory`` resolved and checked against the vehicle (the shipped one, or the
    bridge's ``--vehicle-file``) and the geofence (the bridge's ``--geofence``): (the
    trajectory or None, why it is refused or None)."""
    if args.trajectory is None:
        return None, None
    from arcade_io import jaxsetup
    from deploy.trajectories import option_problem

    jaxsetup.configure(x64=args.x64)  # the check computes the flat reference
    bridge = parse_bridge_args(args.bridge_arg) if args.profile == "px4" else None
    return option_problem(
        args.trajectory,
        speed=args.speed,
        payload_g=args.payload_g,
        vehicle_file=bridge.vehicle_file if bridge else None,
        geofence=bridge.geofence if bridge else None,
    )


def payload_problem(args: argparse.Namespace) -> str | None:
    """Why ``--payload-g`` is more than the vehicle lifts (the shipped vehicle, or the
    bridge's ``--vehicle-file``), or None."""
    from arcade.commands.sim import payload_limit_problem
    from arcade_io.vehicle import load_vehicle

    vehicle_file = None
    if args.profile == "px4" and args.bridge_arg:
        vehicle_file = parse_bridge_args(args.bridge_arg).vehicle_file
    try:
        vehicle = load_vehicle(vehicle_file)
    except (OSError, ValueError) as err:
        return f"--bridge-arg: {err}"
    return payload_limit_problem(vehicle, args.payload_g)


def bus_configs(directory: Path, processes: tuple[str, ...]) -> dict[str, Path] | str:
    """``{name: DIR/<name>.json5}`` for the launcher and ``processes``, or why not (one
    line: the missing files, or the first that is not a readable Zenoh configuration)."""
    from services.bus import read_config

    if not directory.is_dir():
        return f"--bus-configs {directory}: not a directory"
    files = {name: directory / f"{name}.json5" for name in ("launcher", *processes)}
    missing = [f.name for f in files.values() if not f.is_file()]
    if missing:
        return f"--bus-configs {directory}: missing {', '.join(missing)}"
    for path in files.values():
        try:
            read_config(path)
        except ValueError as err:
            return f"--bus-configs: {err}"
    return files


def out_problem(out: Path | None) -> str | None:
    """Why the run folder (``--out``, else one under the runs root) cannot be made, or None."""
    from arcade_io.runs import check_output_dir, check_runs_root

    try:
        if out is not None:
            check_output_dir(out, "--out")
        else:
            check_runs_root()
    except ValueError as err:
        return str(err)
    return None


def weights_problem(path: Path | None) -> tuple[str, int] | None:
    """Why the quadrotor weights the services would load are unusable, with the exit code
    (2: the given ``--weights``; 1: the shipped file), or None. Without ``--weights`` and
    without the shipped file the services fly the nominal model and say so (``degraded``)."""
    from services.adapter import DEFAULT_WEIGHTS

    if path is None and not DEFAULT_WEIGHTS.is_file():
        return None
    from arcade_io import jaxsetup

    jaxsetup.configure()
    from arcade_io.weights import weight_file_problem

    problem = weight_file_problem(DEFAULT_WEIGHTS if path is None else path, "quadrotor")
    if problem is None:
        return None
    return (f"--weights {problem}", 2) if path is not None else (problem, 1)


def stack_config(args: argparse.Namespace, out: Path, configs: dict[str, Path], extra):
    """The stack's :class:`deploy.launcher.StackConfig` from ``arcade up``'s options (run
    folder, weights, checkpoint and bus configurations made absolute)."""
    from arcade.demo_stack import free_hub
    from deploy.launcher import StackConfig

    return StackConfig(
        out=out,
        profile=args.profile,
        lockstep=args.lockstep,
        vehicle=args.vehicle,
        mocap_body=args.mocap_body,
        hub=args.hub or free_hub(),  # unused with bus configurations
        rate=args.rate,
        duration=args.duration,
        payload_g=args.payload_g,
        speed=args.speed,
        seed=args.seed,
        x64=args.x64,
        link_delay_s=args.link_delay,
        weights=args.weights,
        method=args.method,
        checkpoint=args.checkpoint,
        realtime_priority=args.realtime_priority,
        bus_configs=configs,
        credentials=args.hub is None,  # a bus of its own: only this run's processes join
        extra=dict(extra),
        ros2=args.ros2,
        foxglove_port=args.foxglove,
    )


def run(args: argparse.Namespace) -> int:

    def say(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    # Everything a user can get wrong is refused before the run folder exists.
    problem = usage_problem(args) or payload_problem(args) or out_problem(args.out)
    if problem is not None:
        say(f"error: {problem}")
        return 2
    trajectory, problem = trajectory_problem(args)
    if problem is not None:
        say(f"error: {problem}")
        return 2
    configs: dict[str, Path] = {}
    if args.bus_configs is not None:
        from deploy.launcher import SERVICES
        from deploy.px4_profile import PX4_SERVICES

        if args.profile == "px4":  # the operator session sends arm, hold, land, disarm
            processes = (*PX4_SERVICES, *(("px4sim",) if args.simulate else ()), "operator")
        else:
            processes = SERVICES
        processes = (*processes, *(("ros2",) if args.ros2 else ()))
        if args.foxglove is not None:
            processes = (*processes, "foxglove")
        found = bus_configs(args.bus_configs, processes)
        if isinstance(found, str):
            say(f"error: {found}")
            return 2
        configs = found
    bad_weights = weights_problem(args.weights)
    if bad_weights is not None:
        say(f"error: {bad_weights[0]}")
        return bad_weights[1]

    grouped = group_service_args(args.service_arg)
    if isinstance(grouped, str):
        say(f"error: {grouped}")
        return 2
    if grouped:
        probe = stack_config(args, args.out or Path("runs", "up"), configs, grouped)
        if args.profile == "px4":
            from deploy import px4_profile

            probe = px4_profile.config_from_args(args, probe)
        problem = service_args_problem(probe)
        if problem is not None:
            say(f"error: {problem}")
            return 2

    import zenoh

    from arcade_io.runs import new_run_dir
    from deploy.launcher import StackError, last_output, run_flight, sigterm_interrupts

    cfg = stack_config(args, args.out or new_run_dir("up"), configs, grouped)
    if args.foxglove is not None:
        say(foxglove_line(args.foxglove))
    if args.trajectory is not None:
        from deploy.trajectories import stage

        cfg.trajectory, cfg.trajectory_sha256 = stage(cfg.out, args.trajectory, trajectory)

    last = [-1.0]

    def on_time(t: float) -> None:
        if t - last[0] >= 1.0:
            last[0] = t
            print(f"\r  t = {t:7.2f} s", end="", file=sys.stderr, flush=True)

    try:
        hooks = {}
        if args.profile == "px4":
            from deploy import px4_profile

            cfg = px4_profile.config_from_args(args, cfg)
            hooks = px4_profile.flight_hooks(args, cfg, say)
        hooks["on_event"] = _show_faults(say, hooks.get("on_event"))
        with sigterm_interrupts():
            result = run_flight(
                cfg, progress=say, on_time=on_time if args.lockstep else None, **hooks
            )
    except (StackError, ValueError) as err:
        say(f"\nerror: {err}")
        return 1
    except zenoh.ZError as err:  # e.g. the hub's port is taken: one line, not a traceback
        from services.bus import zenoh_reason

        say(f"\nerror: bus: {zenoh_reason(err)}")
        return 1
    say("")
    restarts = result.get("restarts", {})
    for name, code in result["codes"].items():
        extra = f"  ({restarts[name]} restart(s))" if restarts.get(name) else ""
        say(f"  {name:10s} exit {code}{extra}")
    failed = [name for name, code in result["codes"].items() if code != 0]
    for name in failed:
        tail = last_output(cfg.out, name)
        if tail:
            say(f"last output of {name}:\n" + "\n".join(f"    {r}" for r in tail))
    if failed:
        say(f"see {cfg.out / 'logs'}")
    say(f"run folder: {cfg.out}")
    return 0 if not failed else 1


#: Events worth a line on the console while flying (the rest is in events.jsonl);
#: ``degraded``: e.g. no weights (nominal model), stale model, mocap dropout.
SHOWN = ("fault", "restart", "failsafe", "degraded")


def _show_faults(say, then=None):
    """An ``on_event`` hook that prints crashes, restarts, failsafes and degraded modes as
    they happen."""

    def on_event(rec: dict) -> None:
        if rec["kind"] in SHOWN or (rec["kind"] == "info" and "failsafe" in rec["text"]):
            say(f"\n  [{rec['src'].split('/')[0]}] {rec['kind']}: {rec['text']}")
        if then is not None:
            then(rec)

    return on_event
