"""`arcade train --system cartpole|quadrotor` — offline VLD training (Sec. III-A, Eq. 3)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "offline training of the VLD encoder and decoder prior; writes a weights file"

#: The training configurations' epochs (``arcade_core.encoder``), stated here so that
#: ``--help`` does not import JAX.
EPOCHS = {"cartpole": 50, "quadrotor": 100}


def add_arguments(p: argparse.ArgumentParser) -> None:
    from arcade_io.runs import count

    p.add_argument(
        "--system",
        required=True,
        choices=["cartpole", "quadrotor"],
        help="which system's model to train",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="weights file to write (default: the shipped file under deploy/weights/)",
    )
    p.add_argument(
        "--epochs",
        type=count(1),
        default=None,
        help=f"training epochs, at least 1 (default: Appendix D's, {EPOCHS['cartpole']} for "
        f"the cartpole, {EPOCHS['quadrotor']} for the quadrotor)",
    )
    p.add_argument(
        "--deterministic",
        action="store_true",
        help="train the deterministic (MAP) encoder of Appendix E instead",
    )
    p.add_argument("--seed", type=count(0), default=0, help="training seed (default: 0)")


def run(args: argparse.Namespace) -> int:
    from arcade_io import jaxsetup

    jaxsetup.configure()
    from arcade import training

    if args.system == "quadrotor" and args.deterministic:
        print("error: --deterministic is only available for the cartpole", file=sys.stderr)
        return 2
    if args.out is not None:
        from arcade_io.runs import check_output_file

        try:
            check_output_file(args.out, "--out")
        except ValueError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
    if args.system == "quadrotor":
        from arcade.training_quadrotor import train_quadrotor

        path = train_quadrotor(out=args.out, epochs=args.epochs, seed=args.seed)
    else:
        path = training.train_cartpole(
            out=args.out, epochs=args.epochs, variational=not args.deterministic, seed=args.seed
        )
    print(f"wrote {path}")
    return 0
