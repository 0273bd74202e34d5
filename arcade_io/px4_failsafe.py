"""Command-line options of the simulated PX4's estimator and offboard failsafe.

Shared by ``arcade sim --px4`` (the vehicle alone) and the ``px4sim`` service (the vehicle
in the stack), so both accept the same names and turn them into the same
:class:`~simulator.px4.Px4Sim` settings. Kept free of heavy imports (no MuJoCo) so that
``arcade --help`` stays instant.
"""

from __future__ import annotations

import argparse
from typing import Any

from arcade_io.runs import number

#: ``--of-loss-action`` name -> ``COM_OBL_RC_ACT`` value (PX4's codes; the simulated
#: vehicle maps them to its modes, :data:`simulator.px4.vehicle.OFFBOARD_LOSS_ACTIONS`).
LOSS_ACTIONS = {"position": 0, "land": 4, "hold": 5}


def add_failsafe_arguments(p: argparse.ArgumentParser) -> None:
    """``--no-vision-required``, ``--vision-timeout``, ``--of-loss-s``, ``--of-loss-action``."""
    p.add_argument(
        "--no-vision-required",
        action="store_true",
        help="the estimator counts as valid without mocap over MAVLink",
    )
    p.add_argument(
        "--vision-timeout",
        type=number(0.0, low_open=True),
        default=0.5,
        help="mocap older than this no longer gives a valid position [s] (default: %(default)s)",
    )
    p.add_argument(
        "--of-loss-s",
        type=number(0.0, low_open=True),
        default=1.0,
        help="offboard loss timeout COM_OF_LOSS_T [s] (default: %(default)s, PX4's)",
    )
    p.add_argument(
        "--of-loss-action",
        choices=sorted(LOSS_ACTIONS),
        default="hold",
        help="mode after an offboard loss, COM_OBL_RC_ACT (default: %(default)s)",
    )


def failsafe_settings(args: argparse.Namespace) -> dict[str, Any]:
    """The :class:`~simulator.px4.Px4Sim` keyword arguments those options set."""
    return {
        "vision_required": not args.no_vision_required,
        "vision_timeout_s": args.vision_timeout,
        "params": {
            "COM_OF_LOSS_T": args.of_loss_s,
            "COM_OBL_RC_ACT": LOSS_ACTIONS[args.of_loss_action],
        },
    }
