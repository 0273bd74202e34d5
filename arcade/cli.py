"""The ``arcade`` command line.

Each subcommand is a module in ``arcade.commands`` exposing ``HELP`` (one line),
``add_arguments(parser)`` and ``run(args) -> int``. Heavy imports (JAX, MuJoCo, Zenoh)
happen inside ``run`` so that ``arcade --help`` stays instant.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from arcade import __version__

# Order is the order shown by `arcade --help`.
COMMANDS: tuple[str, ...] = (
    "demo",
    "up",
    "replay",
    "train",
    "eval",
    "bench",
    "simulate",
    "sim",
    "effects",
    "log",
    "discrepancy",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="arcade",
        description=(
            "ARCADE: adaptive robot control with online changepoint-aware Bayesian "
            "dynamics learning."
        ),
        epilog=(
            "examples:\n"
            "  arcade demo                       run the demo, write a run folder\n"
            "  arcade bench adapt --json         adaptation-step latency vs beam size\n"
            "  arcade eval cartpole --quick      fast cartpole evaluation\n"
            "run `arcade COMMAND --help` for the options of a command."
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"arcade {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMANDS:
        module = importlib.import_module(f"arcade.commands.{name.replace('-', '_')}")
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except OSError as exc:  # the machine refused (disk full, a folder gone): one line
        print(f"error: {os_error_text(exc)}", file=sys.stderr)
        return 1


def os_error_text(exc: OSError) -> str:
    """``exc`` as a sentence: the system's reason and the file(s) it names."""
    reason = exc.strerror or str(exc)
    files = [f for f in (exc.filename, exc.filename2) if f is not None]
    return f"{reason}: {' -> '.join(map(str, files))}" if files else reason


if __name__ == "__main__":
    sys.exit(main())
