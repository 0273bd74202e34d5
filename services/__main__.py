"""``python -m services <name> [options]``: run one service process.

Services: ``sim``, ``estimator``, ``adapter``, ``controller``, ``recorder``, ``bridge``
(MAVSDK link to a PX4 vehicle), ``px4sim`` (the simulator as a PX4 vehicle on MAVLink),
``ros2`` (the ROS 2 mirror) and ``foxglove`` (the live flight for Foxglove).
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
    "ros2": "services.ros2_mirror",
    "foxglove": "services.foxglove_live",
}

#: One line per service for ``--help`` (without importing them: JAX, MuJoCo, MAVSDK).
SUMMARIES = {
    "sim": "MuJoCo quadrotor + motion capture on the bus",
    "estimator": "mocap (+ gyro) -> state at the control rate",
    "adapter": "ARCADE online adaptation (Algorithm 1) of the residual model",
    "controller": "uncertainty-modulated MPC on the latest state and model",
    "recorder": "MCAP log of the bus and the CSV flight log",
    "px4sim": "the simulator as a PX4 vehicle on MAVLink + motion capture on the bus",
    "bridge": "setpoints to PX4 offboard, mocap to PX4 vision, PX4 telemetry to the bus",
    "ros2": "state, setpoint, reference and changepoints for ROS 2 (rmw_zenoh keys, CDR)",
    "foxglove": "the live flight over the Foxglove WebSocket protocol (loopback)",
}

USAGE = f"usage: python -m services {{{','.join(SERVICES)}}} [--help]"


def help_text() -> str:
    width = max(map(len, SERVICES))
    lines = [USAGE, "", "Run one service process of the stack.", "", "services:"]
    lines += [f"  {name:<{width}}  {SUMMARIES[name]}" for name in SERVICES]
    lines += ["", "python -m services NAME --help: the options of one service."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] in (["-h"], ["--help"]):
        print(help_text())
        return 0
    if not argv or argv[0] not in SERVICES:
        print(USAGE, file=sys.stderr)
        return 2
    module = importlib.import_module(SERVICES[argv[0]])
    return int(module.main(argv[1:]) or 0)


if __name__ == "__main__":
    sys.exit(main())
