"""`arcade sim --px4 URL` — the MuJoCo quadrotor on its own, impersonating a PX4 autopilot.

Any MAVLink client (MAVSDK, QGroundControl, pymavlink scripts) can arm it, take off, land
and fly it in offboard attitude-rate mode on one machine; see :mod:`simulator.px4` for
what it streams and accepts. Runs on the wall clock until ``--duration`` or Ctrl-C and
prints a status line every ``--status-every`` seconds plus every STATUSTEXT it sends.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import time
from pathlib import Path

from arcade.px4_failsafe import add_failsafe_arguments, failsafe_settings

HELP = "run the simulator alone as a PX4 vehicle on MAVLink (MAVSDK/QGC can fly it)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = (
        "examples:\n"
        "  arcade sim --px4 udpout://127.0.0.1:14540\n"
        "      like PX4 SITL: a MAVSDK client connects with udpin://0.0.0.0:14540\n"
        "  arcade sim --px4 udpin://0.0.0.0:14550 --no-vision-required\n"
        "      wait for a client that connects with udpout://HOST:14550; arm without mocap\n"
        "  arcade sim --px4 udpout://127.0.0.1:14540 --payload-g 150 --release-at 20\n"
        "\n"
        "The vehicle behaves like a PX4 that fuses external vision only: it arms once\n"
        "mocap (ODOMETRY or VISION_POSITION_ESTIMATE in NED) streams, or always with\n"
        "--no-vision-required. Offboard needs a SET_ATTITUDE_TARGET stream first; when the\n"
        "stream stops for --of-loss-s the vehicle switches to --of-loss-action."
    )
    p.add_argument(
        "--px4",
        required=True,
        metavar="URL",
        help="MAVLink link: udpout://HOST:PORT (send to a listening client, like "
        "PX4 SITL on 14540) or udpin://HOST:PORT (listen)",
    )
    p.add_argument(
        "--vehicle",
        type=Path,
        default=None,
        help="vehicle file (TOML; default: the shipped arcade-152)",
    )
    p.add_argument(
        "--payload-g",
        type=float,
        default=0.0,
        help="swinging payload under the vehicle [g] (0: none)",
    )
    p.add_argument(
        "--cable-length",
        type=float,
        default=None,
        help="payload cable length [m] (default: the vehicle file's)",
    )
    p.add_argument(
        "--release-at",
        type=float,
        default=None,
        metavar="S",
        help="release the payload at this simulated time [s]",
    )
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        help="stop after this many seconds (default: until Ctrl-C)",
    )
    add_failsafe_arguments(p)
    p.add_argument(
        "--takeoff-alt", type=float, default=2.5, help="take-off height MIS_TAKEOFF_ALT [m]"
    )
    p.add_argument(
        "--airborne",
        action="store_true",
        help="start hovering at --start, armed, in Hold (default: disarmed on the floor)",
    )
    p.add_argument(
        "--start",
        type=float,
        nargs=3,
        default=(0.0, 0.0, 1.5),
        metavar=("X", "Y", "Z"),
        help="start position ENU [m] (Z: with --airborne)",
    )
    p.add_argument(
        "--yaw-deg", type=float, default=0.0, help="start heading, ENU (0 = facing east) [deg]"
    )
    p.add_argument("--seed", type=int, default=0, help="sensor-noise seed")
    p.add_argument(
        "--status-every", type=float, default=1.0, help="status line period [s] (0: none)"
    )


def status_line(v) -> str:
    """One line: time, mode, armed, landed state, position ENU."""
    x = v.state()
    flags = ("ARMED" if v.armed else "disarmed") + (" failsafe" if v.failsafe else "")
    where = "on ground" if v.landed else "in air"
    return (
        f"t={v.time:8.2f}s  mode={v.mode.name:8s} {flags:17s} {where:9s} "
        f"pos ENU=({x[0]:+6.2f}, {x[1]:+6.2f}, {x[2]:+6.2f}) m"
    )


def run(args: argparse.Namespace) -> int:
    from simulator.px4 import Px4Sim
    from simulator.px4.link import parse_url

    try:
        parse_url(args.px4)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2

    def on_text(severity: int, text: str) -> None:
        print(f"[px4] {text}", flush=True)

    failsafe = failsafe_settings(args)
    failsafe["params"]["MIS_TAKEOFF_ALT"] = args.takeoff_alt
    sim = Px4Sim(
        args.px4,
        vehicle=args.vehicle,
        payload_g=args.payload_g,
        cable_length=args.cable_length,
        start=args.start,
        yaw=math.radians(args.yaw_deg),
        airborne=args.airborne,
        **failsafe,
        seed=args.seed,
        on_text=on_text,
    )
    v = sim.vehicle
    print(f"simulated PX4 vehicle on {args.px4} (system 1, component 1); Ctrl-C stops", flush=True)

    state = {"next_status": 0.0, "released": False}

    def on_chunk(s: Px4Sim) -> bool:
        now = time.monotonic()
        if args.release_at is not None and not state["released"] and v.time >= args.release_at:
            state["released"] = True
            if s.release_payload():
                print(f"[sim] payload released at t={v.time:.2f} s", flush=True)
        if args.status_every > 0 and now >= state["next_status"]:
            state["next_status"] = now + args.status_every
            with s.lock:
                line = status_line(v)
            print(line, flush=True)
        return False

    previous = {
        sig: signal.signal(sig, lambda *_: sim.stop.set())
        for sig in (signal.SIGINT, signal.SIGTERM)
    }
    try:
        sim.run(duration=args.duration, on_chunk=on_chunk)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        sim.close()
    with sim.lock:
        print(status_line(v), flush=True)
    rx = ", ".join(f"{k} {n}" for k, n in sorted(sim.mavlink.rx.items())) or "nothing"
    print(
        f"stopped; received {rx}; rejected {dict(sim.mavlink.rejects) or 'none'}; "
        f"wall-clock overruns {sim.overruns}",
        flush=True,
    )
    return 0
