"""``python -m services <name> [options]``: run one service process.

Services: ``sim``, ``estimator``, ``adapter``, ``controller``, ``recorder``, ``bridge``
(MAVSDK link to a PX4 vehicle) and ``px4sim`` (the simulator as a PX4 vehicle on MAVLink).
Each takes ``--help``. The launcher (``arcade up``) starts the ones a profile needs.
"""

from __future__ import annotations

import importlib
import sys

SERVICES = {
    "sim": "services.sim_node",
    "estimator": "services.estimator",
    "adapter": "services.adapter",
    "controller": "services.controller",
    "recorder": "services.recorder",
    "px4sim": "services.px4_sim",
    "bridge": "services.px4_bridge",
}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in SERVICES:
        print(f"usage: python -m services {{{','.join(SERVICES)}}} [--help]", file=sys.stderr)
        return 2
    module = importlib.import_module(SERVICES[argv[0]])
    return int(module.main(argv[1:]) or 0)


if __name__ == "__main__":
    sys.exit(main())
