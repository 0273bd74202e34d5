"""`arcade simulate` — fly a standard exciting trajectory with effects injected, write a log.

The flights are :mod:`simulator.log_flights`'s: the quadrotor in the MuJoCo simulator
flown by the expert pilot along a random path with ground passes, or the Appendix D
cartpole under an exciting controller, each with sensor noise. The effects come from an
effects file (TOML, one table per effect by canonical name, e.g. ``[rotor_drag]`` /
``d = [0.4, 0.4, 0.05]``; ``arcade effects`` lists them), on top of the vehicle file's own
``[effects]``. Options and files are checked before the flight starts; the log is written
as a CSV (:mod:`arcade_io.flightlog`) and a one-line JSON summary printed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from arcade_core.discrepancy.tables import validate_tables
from arcade_io import jsonout

HELP = "fly a standard exciting trajectory in the simulator with effects injected; write a log"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from arcade_io.runs import count, number

    p.add_argument(
        "--system",
        choices=["quadrotor", "cartpole"],
        default="quadrotor",
        help="which simulator (default: %(default)s)",
    )
    p.add_argument(
        "--effects",
        type=Path,
        default=None,
        help="effects file (TOML, one table per effect; `arcade effects` lists them); "
        "default: none",
    )
    p.add_argument(
        "--vehicle",
        type=Path,
        default=None,
        help="vehicle file (TOML; quadrotor only; default: the shipped arcade-152)",
    )
    p.add_argument(
        "--duration",
        type=number(1.0, low_open=True),
        default=60.0,
        metavar="S",
        help="seconds of logged flight, more than 1 (default: %(default)s; the "
        "detectability limits of the effects library are stated for 90 s flights)",
    )
    p.add_argument(
        "--seed", type=count(0), default=0, help="trajectory and noise seed (default: %(default)s)"
    )
    p.add_argument(
        "--noise-scale",
        type=number(0.0),
        default=1.0,
        help="sensor-noise multiplier, >= 0 (default: %(default)s; 0: ground truth)",
    )
    p.add_argument("--out", type=Path, required=True, help="CSV flight log to write")


def read_effects_file(path: str | Path) -> dict[str, Any]:
    """Effect tables of an effects file (or of a model file's ``[effects]`` table)."""
    from arcade_io.vehicle import read_toml

    tables = read_toml(path, "effects file")
    return dict(tables.get("effects", tables))


def _check_tables(system: str, tables: dict[str, Any], path) -> None:
    """:func:`validate_tables`, its error naming the file the tables come from."""
    try:
        validate_tables(system, dict(tables))
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def run(args: argparse.Namespace) -> int:
    from arcade_io.runs import check_output_file

    # Everything the flight needs is checked before it starts.
    try:
        check_output_file(args.out, "--out")
        if args.system != "quadrotor" and args.vehicle is not None:
            raise ValueError("--vehicle applies to --system quadrotor only")
        tables = read_effects_file(args.effects) if args.effects else {}
        _check_tables(args.system, tables, args.effects)
        vehicle = None
        if args.system == "quadrotor":
            from arcade_io.vehicle import DEFAULT_VEHICLE, load_vehicle

            vehicle = load_vehicle(args.vehicle)
            _check_tables("quadrotor", vehicle.get("effects", {}), args.vehicle or DEFAULT_VEHICLE)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2

    from arcade_io import jaxsetup

    jaxsetup.configure(x64=True)
    # Imported here, not at start-up: MuJoCo and JAX are slow to import.
    from arcade_io.flightlog import write_log
    from simulator.log_flights import fly_cartpole, fly_quadrotor

    try:
        if args.system == "quadrotor":
            log = fly_quadrotor(
                tables, args.duration, args.seed, vehicle=vehicle, noise_scale=args.noise_scale
            )
        else:
            log = fly_cartpole(tables, args.duration, args.seed, noise_scale=args.noise_scale)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except RuntimeError as exc:  # a flight the pilot cannot fly
        print(f"error: {exc}", file=sys.stderr)
        return 1
    path = write_log(args.out, log)
    print(
        jsonout.dumps(
            {
                "log": str(path),
                "system": args.system,
                "rows": len(log),
                "dt": log.dt,
                "effects": sorted(tables),
            }
        )
    )
    return 0
