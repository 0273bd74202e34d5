"""`arcade effects` — the library of candidate physical effects (design §6)."""

from __future__ import annotations

import argparse

from arcade_io import jsonout

HELP = "list the library of physical effects (name, parameters with units and ranges)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--system",
        choices=["quadrotor", "cartpole"],
        default=None,
        help="only the effects of one system",
    )
    p.add_argument("--json", action="store_true", help="print the library as JSON")


def run(args: argparse.Namespace) -> int:
    from arcade_core.discrepancy.catalog import MAGNITUDE_QUANTITY, describe

    effects = describe(args.system)
    if args.json:
        print(jsonout.dumps({"effects": effects}))
        return 0
    for e in effects:
        print(f"{e['name']} ({e['system']}): {e['description']}")
        if e["detectable_from"] is not None:
            quantity, unit = MAGNITUDE_QUANTITY[e["name"]]
            print(
                f"    detectable on the standard trajectory from {quantity} = "
                f"{e['detectable_from']:g}{f' {unit}' if unit else ''}"
            )
        for k, p in e["params"].items():
            lo, hi = p["range"]
            default = "" if p["default"] is None else f", default {p['default']}"
            print(f"    {k} [{p['unit']}] in [{lo:g}, {hi:g}]{default}: {p['description']}")
    return 0
