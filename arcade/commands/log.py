"""`arcade log convert FLIGHT.ulg --out LOG.csv` — a PX4 flight log as the project's CSV log.

Reads a PX4 ULog with :func:`arcade_io.ulog.read_ulog` (the longest airborne segment,
resampled to a constant rate, NED/FRD changed to ENU/FLU, the thrust command in newtons),
writes it with :func:`arcade_io.flightlog.write_log` and prints what it did; with
``--vehicle-out`` also a vehicle file seeded from the log's parameters
(:mod:`arcade_io.ulog_seed`). :func:`add_ulog_options` and :func:`ulog_summary` serve
`arcade discrepancy FLIGHT.ulg` too, which converts the same way in memory.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from arcade_io import jsonout

HELP = "convert a PX4 flight log (ULog, .ulg) into the CSV flight log the workflows read"

_EPILOG = """\
what the conversion does (docs/discrepancy.md, "PX4 flight logs"):
  segment   the longest airborne stretch (vehicle_land_detected) in which every signal is
            logged without a gap over --max-gap-s; shorter than --min-airborne-s: an error
            (shorter than 30 s: a warning, the discrepancy workflow needs that much)
  resample  one constant rate (--rate): linear for positions, velocities and rates,
            normalised linear for the attitude quaternion, zero-order hold for setpoints
  frames    PX4's NED/FRD -> ENU/FLU (arcade_core.frames)
  thrust    the normalised thrust command, linear in force: m*g*s/s_hover, with the hover
            thrust s_hover from hover_thrust_estimate, else MPC_THR_HOVER (PX4 applies
            THR_MDL_FAC at its motor outputs: reported, not used); a ULog has no mass:
            give --mass or --vehicle
  rates     vehicle_rates_setpoint; without it the measured rates stand in (a warning)
examples:
  arcade log convert flight.ulg --out flight.csv --mass 1.45
  arcade log convert flight.ulg --out flight.csv --vehicle my_quad.toml --rate 200
  arcade log convert flight.ulg --out flight.csv --mass 1.45 --vehicle-out seed.toml"""


def add_ulog_options(p: argparse.ArgumentParser, *, vehicle: bool, defaults: bool) -> None:
    """The ULog import's options (``vehicle``: with ``--vehicle``, exclusive with ``--mass``;
    ``defaults``: give the defaults, else ``None`` so that a caller can tell them given)."""
    from arcade_io.resample import DEFAULT_MAX_GAP_S, DEFAULT_MIN_AIRBORNE_S, DEFAULT_RATE_HZ
    from arcade_io.runs import number

    g = p.add_argument_group("PX4 ULog import (.ulg)")
    mass = g.add_mutually_exclusive_group() if vehicle else g
    mass.add_argument(
        "--mass",
        type=number(0.0, low_open=True),
        default=None,
        metavar="KG",
        help="the vehicle's take-off mass [kg] (a ULog has none): the hover thrust is m*g"
        + ("" if vehicle else "; default: the mass of the --vehicle file, if one is given"),
    )
    if vehicle:
        mass.add_argument(
            "--vehicle",
            type=Path,
            default=None,
            metavar="FILE",
            help="vehicle file whose mass to use: [body] mass_kg plus its electromagnet, as "
            "the model counts it",
        )
    # Converting takes any airborne stretch; the workflow needs DEFAULT_MIN_AIRBORNE_S.
    rate, min_s, gap = (DEFAULT_RATE_HZ, 0.0, DEFAULT_MAX_GAP_S) if defaults else (None,) * 3
    g.add_argument(
        "--rate",
        type=number(0.0, 1000.0, low_open=True),
        default=rate,
        metavar="HZ",
        help=f"output sample rate, more than 0 and at most 1000 (default: {DEFAULT_RATE_HZ:g})",
    )
    g.add_argument(
        "--min-airborne-s",
        type=number(0.0),
        default=min_s,
        metavar="S",
        help="shortest airborne segment accepted [s] (default: "
        + ("0, any" if defaults else f"{DEFAULT_MIN_AIRBORNE_S:g}")
        + f"; the discrepancy workflow needs {DEFAULT_MIN_AIRBORNE_S:g} s to tell effects "
        "apart: below it, it answers 'not enough excitation to tell')",
    )
    g.add_argument(
        "--max-gap-s",
        type=number(0.0, low_open=True),
        default=gap,
        metavar="S",
        help="a signal silent for longer splits the segment; the longest piece is kept "
        f"(default: {DEFAULT_MAX_GAP_S:g})",
    )
    g.add_argument(
        "--allow-damaged",
        action="store_true",
        help="read a truncated or corrupted log as far as it goes (a warning, not an error)",
    )


def ulog_options_given(args: argparse.Namespace) -> list[str]:
    """The ULog options given on the command line (with ``defaults=False``)."""
    names = {
        "mass": "--mass",
        "rate": "--rate",
        "min_airborne_s": "--min-airborne-s",
        "max_gap_s": "--max-gap-s",
        "allow_damaged": "--allow-damaged",
    }
    return [flag for k, flag in names.items() if getattr(args, k, None) not in (None, False)]


def read_ulog_args(args: argparse.Namespace, path: Path, min_airborne_s: float | None = None):
    """:func:`arcade_io.ulog.read_ulog` of ``path`` with the options in ``args``
    (``min_airborne_s``: instead of the option's)."""
    from arcade_io import resample, ulog

    def opt(name: str, default: float) -> float:
        v = getattr(args, name, None)
        return default if v is None else v

    return ulog.read_ulog(
        path,
        mass_kg=args.mass,
        vehicle=getattr(args, "vehicle", None),
        rate_hz=opt("rate", resample.DEFAULT_RATE_HZ),
        min_airborne_s=(
            opt("min_airborne_s", resample.DEFAULT_MIN_AIRBORNE_S)
            if min_airborne_s is None
            else min_airborne_s
        ),
        max_gap_s=opt("max_gap_s", resample.DEFAULT_MAX_GAP_S),
        allow_damaged=args.allow_damaged,
    )


def is_ulog(path: Path) -> bool:
    """A ``.ulg`` name, or a file that starts as a ULog does (without loading the reader)."""
    if path.suffix.lower() == ".ulg":
        return True
    try:
        with path.open("rb") as f:
            return f.read(4) == b"ULog"
    except OSError:
        return False


def ulog_summary(meta: dict[str, Any]) -> list[str]:
    """What a ULog conversion did, a few lines of text (its metadata)."""
    a, b = meta["segment_s"]
    n_air = len(meta["airborne_segments_s"])
    th = meta["thrust_conversion"]
    lines = [
        f"{meta['duration_s']:.2f} s at {meta['rate_hz']:g} Hz ({meta['samples']} rows): "
        f"{a:.2f}-{b:.2f} s into the log ({n_air} airborne segment{'s' if n_air > 1 else ''})",
        f"thrust: {th['thrust_source']}, hover {th['hover_thrust']:.3f} from "
        f"{th['hover_thrust_source']} = {th['hover_force_n']:.4g} N ({th['mass_kg']:g} kg from "
        f"{th['mass_source']}), THR_MDL_FAC {th['thr_mdl_fac']:g}",
        f"rate setpoints: {meta['signals'].get('rate_setpoints', 'none logged')}",
    ]
    lines += [f"stand-in: {s}" for s in meta["stand_ins"]]
    lines += [f"warning: {w}" for w in meta["warnings"]]
    return lines


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION")
    sub.required = True
    c = sub.add_parser(
        "convert",
        help="a PX4 ULog (.ulg) as the project's CSV flight log",
        description="convert a PX4 ULog (.ulg) into the project's CSV flight log (world ENU,\n"
        "body FLU, SI, one constant rate; the columns `arcade discrepancy --help` lists)",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    c.add_argument("ulog", type=Path, metavar="FLIGHT.ulg", help="the PX4 flight log")
    c.add_argument("--out", type=Path, required=True, metavar="LOG.csv", help="CSV to write")
    add_ulog_options(c, vehicle=True, defaults=True)
    c.add_argument(
        "--vehicle-out",
        type=Path,
        default=None,
        metavar="VEHICLE.toml",
        help="also write a vehicle file seeded from the log's parameters, listing on top "
        "what a ULog does not hold (inertia, motor time constant, ...)",
    )
    c.add_argument("--json", action="store_true", help="print the conversion's metadata as JSON")


def run(args: argparse.Namespace) -> int:
    return _convert(args)  # the only action


def _convert(args: argparse.Namespace) -> int:
    from arcade_io import atomicfile
    from arcade_io.flightlog import write_log
    from arcade_io.runs import check_output_file

    try:
        check_output_file(args.out, "--out")
        if args.vehicle_out is not None:
            check_output_file(args.vehicle_out, "--vehicle-out")
        imp = read_ulog_args(args, args.ulog)
        seed = None
        if args.vehicle_out is not None:
            from arcade_io.ulog_seed import seed_toml, vehicle_seed

            th = imp.meta["thrust_conversion"]
            seed = vehicle_seed(
                args.ulog,
                th["mass_kg"],
                gravity=th["gravity_mps2"],
                hover=(th["hover_thrust"], th["hover_thrust_source"]),
            )
        write_log(args.out, imp.log)
        if seed is not None:
            atomicfile.write_text(args.vehicle_out, seed_toml(seed, str(args.ulog)))
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        out = {**imp.meta, "out": str(args.out)}
        if seed is not None:
            out["vehicle_out"] = str(args.vehicle_out)
            out["vehicle_missing"] = seed["missing"]
        print(jsonout.dumps(out))
        return 0
    print(f"wrote {args.out}: " + "\n".join(ulog_summary(imp.meta)))
    if seed is not None:
        print(f"wrote {args.vehicle_out}: a vehicle file to complete; not in the log:")
        print("".join(f"  {m}\n" for m in seed["missing"]), end="")
    return 0
