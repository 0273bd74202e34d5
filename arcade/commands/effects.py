"""`arcade effects` — the library of candidate physical effects (design §6)."""

from __future__ import annotations

import argparse

from arcade import jsonout

HELP = "list the library of physical effects (name, parameters with units and ranges)"

#: What the detectability threshold of each quadrotor effect measures, with its unit
#: (``arcade_core.discrepancy.catalog.magnitude``).
MAGNITUDES = {
    "rotor_drag": ("largest |d|", "1/s"),
    "quadratic_drag": ("largest |c|", "kg/m"),
    "ground_effect": ("rotor radius", "m"),
    "thrust_scale": ("|scale - 1|", ""),
    "motor_lag": ("change of the motor time constant", "s"),
    "rate_lag": ("delay + filter time constant", "s"),
    "com_offset": ("horizontal offset", "m"),
    "wind": ("wind speed", "m/s"),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--system",
        choices=["quadrotor", "cartpole"],
        default=None,
        help="only the effects of one system",
    )
    p.add_argument("--json", action="store_true", help="print the library as JSON")


def run(args: argparse.Namespace) -> int:
    from arcade_core.discrepancy.catalog import describe

    effects = describe(args.system)
    if args.json:
        print(jsonout.dumps({"effects": effects}))
        return 0
    for e in effects:
        print(f"{e['name']} ({e['system']}): {e['description']}")
        if e["detectable_from"] is not None:
            quantity, unit = MAGNITUDES[e["name"]]
            print(
                f"    detectable on the standard trajectory from {quantity} = "
                f"{e['detectable_from']:g}{f' {unit}' if unit else ''}"
            )
        for k, p in e["params"].items():
            lo, hi = p["range"]
            default = "" if p["default"] is None else f", default {p['default']}"
            print(f"    {k} [{p['unit']}] in [{lo:g}, {hi:g}]{default}: {p['description']}")
    return 0
