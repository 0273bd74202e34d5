"""The options ``arcade up`` and ``arcade demo`` share beyond the plan: the optional
services (``--ros2``, ``--foxglove``) and ``--service-arg``, checked by each service's own
parser before anything starts."""

from __future__ import annotations

import argparse


def add_ros2_argument(p: argparse.ArgumentParser) -> None:
    """``--ros2`` (``arcade up`` and ``arcade demo``)."""
    p.add_argument(
        "--ros2",
        action="store_true",
        help="also run the ROS 2 mirror: state (nav_msgs/Odometry), setpoint, reference and "
        "changepoints as ROS 2 messages on rmw_zenoh's keys, under /arcade/<vehicle>, for "
        "`ros2 topic echo` on a host with RMW_IMPLEMENTATION=rmw_zenoh_cpp; it connects to "
        "the rmw_zenohd router on tcp/localhost:7447 and uses $ROS_DOMAIN_ID (else 0); "
        "other router, domain or namespace: --service-arg ros2:--router=ENDPOINT, "
        "ros2:--domain-id=N, ros2:--namespace=/NS (docs/ros2.md)",
    )


def ros2_problem(args: argparse.Namespace) -> str | None:
    """Why ``--ros2`` would not start: the vehicle's name makes no ROS 2 namespace and no
    ``--service-arg ros2:--namespace`` is given (one line), or None."""
    if not args.ros2:
        return None
    grouped = group_service_args(args.service_arg)
    own = grouped.get("ros2", []) if isinstance(grouped, dict) else []
    try:
        if "--namespace" in options_given(service_parser("ros2"), own):
            return None  # its own namespace, checked by the service's parser
    except ValueError:
        return None  # what the service's parser refuses: service_args_problem says it
    from services.ros2_mirror import default_namespace

    try:
        default_namespace(args.vehicle)
    except ValueError as err:
        return f"--ros2: {err}: give one with --service-arg ros2:--namespace=/NS"
    return None


def foxglove_line(port: int) -> str:
    """Where Foxglove connects to the live flight (``--foxglove PORT``)."""
    where = f"ws://127.0.0.1:{port}" if port else "ws://127.0.0.1 on a free port (its log)"
    return f"Foxglove: open a Foxglove WebSocket connection to {where}"


def add_foxglove_argument(p: argparse.ArgumentParser) -> None:
    """``--foxglove [PORT]`` (``arcade up`` and ``arcade demo``)."""

    def port(text: str) -> int:
        if not text.isdigit() or int(text) > 65535:
            raise argparse.ArgumentTypeError(f"not a TCP port (0-65535): {text!r}")
        return int(text)

    p.add_argument(
        "--foxglove",
        type=port,
        nargs="?",
        const=8765,
        default=None,
        metavar="PORT",
        help="serve the live flight to Foxglove over its WebSocket protocol on "
        "ws://127.0.0.1:PORT (loopback only; PORT default 8765, 0: any free one): the "
        "vehicle's transform, pose and model, the payload with its cable, the reference "
        "path and the geofence, the channels bus.mcap holds too (default: off)",
    )


def group_service_args(values: list[str]) -> dict[str, list[str]] | str:
    """``--service-arg NAME:ARG`` values grouped by service (in order), or why not."""
    from services.__main__ import SERVICES

    grouped: dict[str, list[str]] = {}
    for value in values:
        name, sep, arg = value.partition(":")
        if not sep or not arg:
            return f"--service-arg {value}: not NAME:ARG (e.g. estimator:--mocap-noise=1e-4)"
        if name == "bridge":
            return f"--service-arg {value}: the bridge's options go through --bridge-arg"
        if name not in SERVICES:
            known = ", ".join(s for s in SERVICES if s != "bridge")
            return f"--service-arg {value}: no service {name!r} (services: {known})"
        grouped.setdefault(name, []).append(arg)
    return grouped


def service_parser(name: str) -> argparse.ArgumentParser:
    """The options of service ``name`` as ``python -m services NAME`` parses them, raising
    ``ValueError`` (one line) instead of exiting."""
    import importlib

    from services import options
    from services.__main__ import SERVICES

    parser = options.common_parser(name, name)
    extra = getattr(importlib.import_module(SERVICES[name]), "_extra", None)
    if extra is not None:
        extra(parser)

    def refuse(message: str) -> None:  # instead of printing the usage and exiting
        raise ValueError(message)

    parser.error = refuse  # type: ignore[method-assign]
    return parser


def options_given(parser: argparse.ArgumentParser, argv: list[str]) -> set[str]:
    """The options (long spelling, e.g. ``--max-model-age``) that ``argv`` sets, however
    abbreviated; ``ValueError`` if ``parser`` refuses ``argv``."""
    actions = [a for a in parser._actions if a.option_strings and a.dest != "help"]
    # A mark per option that parsing replaces when the option is given (an appending
    # option copies its list before it appends: an empty list of its own).
    marks = {a.dest: [] if isinstance(a, argparse._AppendAction) else object() for a in actions}
    ns = argparse.Namespace(**marks)
    parser.parse_args(argv, namespace=ns)
    return {a.option_strings[-1] for a in actions if getattr(ns, a.dest) is not marks[a.dest]}


#: Options the launcher sets that ``--service-arg`` may still set for one service (the
#: service's own value comes last and wins).
OVERRIDABLE = frozenset({"--log-level"})
#: Options only the launcher sets, given to it or not (one process alone must not fly
#: another path).
LAUNCHER_ONLY = frozenset({"--trajectory", "--trajectory-sha256"})


def service_args_problem(cfg) -> str | None:
    """Why ``cfg.extra`` (from ``--service-arg``) would not start: a service this stack
    does not run, an option its service refuses, or one the launcher sets itself."""
    import dataclasses

    running = cfg.services()
    own = dataclasses.replace(cfg, extra={})
    for name, argv in cfg.extra.items():
        if name not in running:
            return f"--service-arg {name}: not a process of this stack ({', '.join(running)})"
        parser = service_parser(name)
        try:
            given = options_given(parser, argv)
        except ValueError as err:
            return f"--service-arg {name}:{' '.join(argv)}: {err}"
        launcher = options_given(parser, own.args(name)) | (given & LAUNCHER_ONLY)
        clash = sorted((given & launcher) - OVERRIDABLE)
        if clash:
            return (
                f"--service-arg {name}: {', '.join(clash)} set by the launcher (from "
                "arcade up's own options), not through --service-arg"
            )
    return None
