"""The command-line options the service processes share, and their checks.

Every service takes :func:`common_parser`'s options; the adapter and the controller share
the weights and link-delay options, the simulator and the controller the flight plan
(:func:`add_plan_arguments`, :func:`scenario`).
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from arcade_control.knobs import DEFAULT_STACK_METHOD, STACK_METHODS
from services.bus import DEFAULT_HUB


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """Help that ends every option's text with its default (``none`` for ``None``, ``off``
    for a flag), unless the text already speaks of its default."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if (
            re.search(r"\bdefault\b", text)
            or action.default is argparse.SUPPRESS
            or not action.option_strings
        ):
            return text
        if action.nargs == 0:  # a flag: its default is not giving it
            return f"{text} (default: off)"
        return f"{text} (default: {'none' if action.default is None else '%(default)s'})"


def common_parser(name: str, description: str) -> argparse.ArgumentParser:
    """Options every service takes (``--help`` shows each option's default)."""
    p = argparse.ArgumentParser(
        prog=f"python -m services {name}",
        description=description,
        formatter_class=DefaultsHelpFormatter,
    )
    p.add_argument("--vehicle", default="default", help="vehicle name on the bus (key prefix)")
    p.add_argument(
        "--hub",
        default=None,
        help=f"Zenoh hub endpoint of the peer session (default {DEFAULT_HUB})",
    )
    p.add_argument(
        "--bus-config",
        type=Path,
        default=None,
        metavar="FILE",
        help="Zenoh configuration (JSON5) of this process's session instead of the peer "
        "session on --hub, e.g. a client of a router with user/password or TLS",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="run folder: logs/<service>.log and stats/<service>.json go here",
    )
    p.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING, ...")
    p.add_argument("--x64", action="store_true", help="compute in float64 (default float32)")
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="lockstep clock (simulated time, deterministic); default realtime",
    )
    p.add_argument("--rate", type=float, default=20.0, help="control rate [Hz]")
    p.add_argument(
        "--nice",
        type=int,
        default=0,
        help="scheduling priority change (negative: higher; needs privileges, "
        "ignored with a warning otherwise)",
    )
    p.add_argument(
        "--realtime-priority",
        type=int,
        default=0,
        metavar="P",
        help="after warm-up, run every thread of the process under SCHED_FIFO at "
        "priority P (1-99; 0: the normal policy). Needs CAP_SYS_NICE or an "
        "rtprio limit; without, a warning and the normal policy",
    )
    p.add_argument(
        "--cpu-wakeup-latency-us",
        type=int,
        default=None,
        metavar="US",
        help="after warm-up, ask the kernel (PM QoS, /dev/cpu_dma_latency) to keep "
        "every CPU's wake-up latency <= US microseconds while this process "
        "runs (0: idle CPUs poll instead of sleeping; costs power). Needs "
        "root; without, a warning",
    )
    p.add_argument(
        "--incarnation",
        type=int,
        default=0,
        help="restart count given by the supervisor (0: first start)",
    )
    return p


# ----------------------------------------------------------------------- learned model


def add_weights_argument(p: argparse.ArgumentParser) -> None:
    """The learned model's weights, shared by the adapter and the controller (same file on
    both: the controller rebuilds the features the adapter's posterior is over)."""
    p.add_argument(
        "--weights",
        type=Path,
        default=None,
        help="VLD weights (default deploy/weights/quadrotor_vld.eqx)",
    )


#: ``--method``'s help, the same wherever the option is (services and command line).
METHOD_HELP = (
    "the controller the stack flies: arcade, the product's flagship (the learned model "
    "through the thrust axis plus an L1 thrust augmentation that cancels what the model "
    "misses; docs/quadrotor-closed-loop.md); ours, the paper's method (the adapter's "
    "changepoint-aware posterior in the uncertainty-modulated MPC); l1, the L1 "
    f"augmentation on the nominal MPC (the baseline) (default: {DEFAULT_STACK_METHOD})"
)


def add_method_argument(p: argparse.ArgumentParser) -> None:
    """The controller the stack flies, shared by the adapter and the controller (same
    value on both: the model message's shape follows the method's features)."""
    p.add_argument(
        "--method",
        choices=STACK_METHODS,
        default=DEFAULT_STACK_METHOD,
        help=METHOD_HELP,
    )


def adapter_knob(text: str) -> tuple[str, Any]:
    """``--knob NAME=VALUE`` (:func:`arcade_control.knobs.parse_knob`) for argparse."""
    from arcade_control.knobs import parse_knob

    try:
        return parse_knob(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def add_mocap_source_argument(p: argparse.ArgumentParser) -> None:
    """``--mocap-source``: the one service whose bus session mocap is taken from."""
    p.add_argument(
        "--mocap-source",
        default=None,
        metavar="SERVICE",
        help="accept mocap only from the bus session of this service (its liveliness "
        "token arcade/<vehicle>/alive/SERVICE/<session>), e.g. sim; the rest is refused "
        "as foreign_publisher (default: from any publisher)",
    )


def add_state_source_argument(p: argparse.ArgumentParser) -> None:
    """``--state-source``: the one service whose bus session the state is taken from."""
    p.add_argument(
        "--state-source",
        default="estimator",
        metavar="SERVICE",
        help="accept the state only from the bus session of this service (its liveliness "
        "token arcade/<vehicle>/alive/SERVICE/<session>); the rest is refused as "
        "foreign_publisher (the simulator with --truth-state: sim)",
    )


def mocap_body(text: str) -> str:
    """argparse ``type=``: a rigid-body name as a ``mocap`` record's ``body`` carries it
    (the schema's check of :class:`~services.messages.Mocap`)."""
    from services.messages import MessageError, Mocap, field_specs

    try:
        return field_specs(Mocap)["body"].coerce("body", text, {})
    except MessageError:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a mocap rigid-body name (1 to 64 letters, digits, '_', '.', '-')"
        ) from None


#: ``--mocap-body``'s help (the services and ``arcade up``).
MOCAP_BODY_HELP = (
    "the name of the vehicle's rigid body in the motion capture (the body of its mocap "
    "records): the estimator and the PX4 bridge take only its frames, the simulators "
    "publish the vehicle's under it, Foxglove hangs the payload's cable from it"
)


def add_mocap_body_argument(
    p: argparse.ArgumentParser, parse: Callable[[str], str] = mocap_body
) -> None:
    """``--mocap-body``: the vehicle's rigid body on the ``mocap`` topic (default
    :data:`~services.messages.VEHICLE_BODY`), checked by ``parse``."""
    from services.messages import VEHICLE_BODY

    p.add_argument(
        "--mocap-body",
        type=parse,
        default=VEHICLE_BODY,
        metavar="NAME",
        help=MOCAP_BODY_HELP,
    )


def add_link_delay_argument(p: argparse.ArgumentParser) -> None:
    """The link's delay, shared by the controller and the adapter (same value on both: the
    controller plans from the state the adapter learns from)."""
    p.add_argument(
        "--link-delay",
        type=seconds(1.0, high_open=True),  # the control period bounds it further
        default=0.0,
        metavar="S",
        help="compensate the delay from a state's sample instant to when its setpoint "
        "acts on the vehicle's rate loop, shorter than one control period: plan and learn "
        "from the state predicted that far ahead with the setpoint in flight [s] "
        "(default: 0, none)",
    )


def link_delay_problem(delay: float, rate: float) -> str | None:
    """Why a link delay does not fit the control rate (it must be shorter than one
    period: one setpoint in flight at a time), or None."""
    if delay < 1.0 / rate:
        return None
    return (
        f"--link-delay {delay:g} s: must be shorter than the control period "
        f"({1.0 / rate:g} s at --rate {rate:g})"
    )


def seconds(high: float, high_open: bool = False) -> Callable[[str], float]:
    """argparse ``type=``: a duration in ``[0, high]`` seconds (``high_open``: ``[0, high)``)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = float("nan")
        if not (0.0 <= value < high if high_open else 0.0 <= value <= high):
            end = ")" if high_open else "]"
            raise argparse.ArgumentTypeError(
                f"must be a number of seconds in [0, {high:g}{end}, not {text}"
            )
        return value

    return parse


# ----------------------------------------------------------------------- flight plan


def add_plan_arguments(p: argparse.ArgumentParser) -> None:
    """The flight plan shared by the simulator and the controller (same values on both)."""
    p.add_argument("--payload-g", type=float, default=175.0, help="swinging payload [g]")
    p.add_argument("--speed", type=float, default=2.5, help="figure-eight mean speed [m/s]")
    p.add_argument("--seed", type=int, default=0, help="trial seed (noise, start, release)")
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        help="flight duration [s] (default: take-off, hover, two laps)",
    )
    p.add_argument(
        "--release",
        type=float,
        default=0.95,
        help="release the payload at this fraction of the first lap "
        "(negative: only on a release_payload command)",
    )
    p.add_argument(
        "--hover-s",
        type=float,
        default=1.5,
        help="hover this long at the centre before the figure-eight [s] "
        "(longer than the flight: a take-off and hover plan)",
    )
    p.add_argument(
        "--origin",
        type=_xy,
        default=(0.0, 0.0),
        metavar="X,Y",
        help="horizontal offset of the whole plan [m] (one per vehicle on a bus)",
    )

    p.add_argument(
        "--trajectory",
        default=None,
        metavar="SPEC",
        help="fly this after the hover instead of the figure-eight: a built-in "
        "(circle, lissajous, hover, with :KEY=VALUE,...) or a fitted path file (.npz) "
        "that arcade up writes into the run folder",
    )
    p.add_argument(
        "--trajectory-sha256",
        default=None,
        metavar="HEX",
        help="the SHA-256 the --trajectory file must have",
    )


def _xy(text: str) -> tuple[float, float]:
    x, y = (float(v) for v in text.split(","))
    return x, y


def scenario(args: argparse.Namespace) -> Any:
    """The closed-loop scenario (take-off, hover, figure-eight or ``--trajectory``) of the
    plan options."""
    # Imported here: it loads JAX, which the services without a model (the recorder)
    # then do not import at start-up.
    from arcade_control.scenario import Scenario, planned

    return planned(
        payload_g=args.payload_g,
        speed_mps=args.speed,
        release_fraction=args.release,
        hover_s=getattr(args, "hover_s", None),
        origin=getattr(args, "origin", (0.0, 0.0)),
        trajectory=trajectory(
            getattr(args, "trajectory", None),
            getattr(args, "trajectory_sha256", None),
            Scenario().center,
            float(args.speed),
        ),
    )


def trajectory(value: str | None, sha256: str | None, center: Any, speed: float) -> Any:
    """The :class:`arcade_control.trajectory.Trajectory` of ``--trajectory``: a fitted
    path file (``.npz``, its ``--trajectory-sha256`` checked) or a built-in spec; None
    without one or for the figure-eight. ``ValueError`` (one line) otherwise."""
    if value is None:
        return None
    from arcade_control import trajectory as traj

    if value.endswith(".npz"):
        from arcade_core.trajectories import PiecewisePolynomial
        from arcade_io.trajectory_file import load_fitted

        if not sha256:
            raise ValueError(f"--trajectory {value}: needs --trajectory-sha256")
        name, breaks, coeffs, yaw = load_fitted(value, sha256)
        heading = None if yaw is None else PiecewisePolynomial(*yaw)
        return traj.sampled(name, PiecewisePolynomial(breaks, coeffs), heading)
    return traj.builtin(value, center, speed)


def add_adapter_arguments(p: argparse.ArgumentParser) -> None:
    """The adapter's options beyond :func:`common_parser`'s."""
    add_weights_argument(p)
    add_method_argument(p)
    add_link_delay_argument(p)
    add_state_source_argument(p)
    p.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        help="posterior checkpoint file (restored at start if it matches)",
    )
    p.add_argument(
        "--checkpoint-every",
        type=int,
        default=20,
        help="steps between checkpoints (0: only at shutdown)",
    )
    p.add_argument(
        "--step-timeout",
        type=float,
        default=5.0,
        help="lockstep: longest wait for the setpoint of the previous state [s]",
    )
    p.add_argument(
        "--knob",
        type=adapter_knob,
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a knob of the learner (e.g. arcade_lambda=0.95, of the --method flown) or "
        "of the changepoint detector (detector_threshold=0.9) instead of the stack's "
        "(repeatable; `arcade replay --set` tries them on a recorded flight)",
    )
    p.add_argument(
        "--max-gap-periods",
        type=float,
        default=2.5,
        help="states further apart (in control periods) are not learned from",
    )
