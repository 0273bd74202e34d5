"""Command-line options of the simulator service (``python -m services sim``), shared with
the simulated PX4 (``px4sim``), which flies the same simulator."""

from __future__ import annotations

import argparse

from services import options
from services.messages import PAYLOAD_BODY
from simulator.mocap_faults import MocapFault


def add_sim_arguments(p: argparse.ArgumentParser) -> None:
    """The simulator service's own options (the plan options included)."""
    options.add_plan_arguments(p)
    p.add_argument(
        "--step-timeout",
        type=float,
        default=5.0,
        help="lockstep: longest wait for a setpoint before holding the last [s]",
    )
    p.add_argument(
        "--preroll",
        type=float,
        default=1.0,
        help="realtime: hover this long at the start pose before the mission [s]",
    )
    p.add_argument(
        "--substep",
        type=float,
        default=0.005,
        help="realtime: physics chunk between setpoint checks [s]",
    )
    p.add_argument(
        "--wait-for",
        default="estimator,adapter,controller",
        help="comma-separated services that must be alive before take-off",
    )
    p.add_argument(
        "--truth-state",
        action="store_true",
        help="diagnostic: publish the ground-truth state (run without the "
        "estimator; this is what the in-process evaluation controls on)",
    )
    p.add_argument(
        "--ready-timeout", type=float, default=600.0, help="longest wait for those services [s]"
    )
    p.add_argument(
        "--failsafe-after",
        type=float,
        default=0.3,
        help="no fresh setpoint for this long -> position hold (realtime: wall "
        "clock; lockstep: simulated time) [s]",
    )
    p.add_argument(
        "--failsafe-resume",
        type=int,
        default=3,
        help="consecutive answered control instants that end the failsafe",
    )
    p.add_argument(
        "--command-delay",
        type=options.seconds(1.0),
        default=0.0,
        metavar="S",
        help="emulate the link to the autopilot: every setpoint reaches the rate loop "
        "this much later (whole ms; up to 1 s) [s]; the simulated PX4 has its own",
    )
    p.add_argument(
        "--mocap-fault",
        action="append",
        type=_mocap_fault,
        default=None,
        metavar="SPEC",
        help="inject a mocap fault: dropout@T+D, freeze@T+D, "
        "outliers@T+D,p=P,m=M, clockjump@T[+D],offset=S (mission time)",
    )
    options.add_mocap_body_argument(p, vehicle_body)


def vehicle_body(text: str) -> str:
    """argparse ``type=``: the simulated vehicle's rigid-body name, a ``mocap`` name other
    than the simulated payload's."""
    name = options.mocap_body(text)
    if name == PAYLOAD_BODY:
        raise argparse.ArgumentTypeError(f"{name!r} is the simulated payload's rigid body")
    return name


def _mocap_fault(spec: str) -> MocapFault:
    try:
        return MocapFault.parse(spec)
    except ValueError as err:  # argparse prints this message, not a generic one
        raise argparse.ArgumentTypeError(str(err)) from None
