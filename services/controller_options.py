"""Command-line options of the controller service (``python -m services controller``): what
it flies (plan, weights, method, link delay, state source) and how old a model, a state or
a measurement may be before it flies without it."""

from __future__ import annotations

import argparse

from services import options


def add_controller_arguments(p: argparse.ArgumentParser) -> None:
    """The controller service's own options (the plan options included)."""
    options.add_plan_arguments(p)
    options.add_weights_argument(p)
    options.add_method_argument(p)
    options.add_link_delay_argument(p)
    options.add_state_source_argument(p)
    p.add_argument(
        "--advanced-step",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="with a learned model: plan the MPC for the next control instant as soon as "
        "a setpoint is out (two solver iterations), and answer the next state with that "
        "plan's Gauss-Newton step for where the state and the model are (sense-to-actuate "
        "without a solve, about the CPU of a plain step; docs/quadrotor-closed-loop.md); "
        "without it each state is solved for after it arrives",
    )
    p.add_argument(
        "--model-timeout",
        type=float,
        default=5.0,
        help="lockstep: longest wait for the model of the current state [s]",
    )
    p.add_argument(
        "--max-model-age",
        type=float,
        default=0.5,
        help="older models are not used (nominal MPC instead) [s]",
    )
    p.add_argument(
        "--stale-model-s",
        type=float,
        default=0.15,
        help="older models are still used but flagged (stale_model event) [s]",
    )
    p.add_argument(
        "--max-state-age",
        type=float,
        default=0.1,
        help="realtime: older states on arrival give a hover setpoint [s]",
    )
    p.add_argument(
        "--max-meas-age",
        type=float,
        default=0.2,
        help="states whose newest mocap frame is older give a hover setpoint [s]",
    )
    p.add_argument(
        "--max-hover-s",
        type=float,
        default=1.0,
        help="longest uninterrupted hover (no position feedback) before a failsafe event "
        "asks the vehicle link to fail safe (the PX4 bridge leaves offboard, the "
        "simulator holds position) [s]",
    )
