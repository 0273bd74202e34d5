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

from arcade_io import signals
from arcade_io.px4_failsafe import add_failsafe_arguments, failsafe_settings

HELP = "run the simulator alone as a PX4 vehicle on MAVLink (MAVSDK/QGC can fly it)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from arcade_io.runs import count, number

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
        type=number(0.0),
        default=0.0,
        help="swinging payload under the vehicle [g]: 0 (none, the default) up to what "
        "the rotors lift at full thrust (about 1 kg on the default vehicle)",
    )
    p.add_argument(
        "--cable-length",
        type=number(0.0, low_open=True),
        default=None,
        help="payload cable length [m], > 0; with --payload-g (default: the vehicle file's)",
    )
    p.add_argument(
        "--release-at",
        type=number(0.0),
        default=None,
        metavar="S",
        help="release the payload at this simulated time [s], >= 0; with --payload-g",
    )
    p.add_argument(
        "--duration",
        type=number(0.0, low_open=True),
        default=None,
        metavar="S",
        help="stop after this many seconds, > 0 (default: until Ctrl-C)",
    )
    add_failsafe_arguments(p)
    p.add_argument(
        "--takeoff-alt",
        type=number(0.0, low_open=True),
        default=2.5,
        help="take-off height MIS_TAKEOFF_ALT [m], > 0 (default: %(default)s)",
    )
    p.add_argument(
        "--airborne",
        action="store_true",
        help="start hovering at --start, armed, in Hold (default: disarmed on the floor)",
    )
    p.add_argument(
        "--start",
        type=number(),
        nargs=3,
        default=(0.0, 0.0, 1.5),
        metavar=("X", "Y", "Z"),
        help="start position ENU [m] (Z > 0: with --airborne) (default: 0 0 1.5)",
    )
    p.add_argument(
        "--yaw-deg",
        type=number(),
        default=0.0,
        help="start heading, ENU (0 = facing east) [deg] (default: %(default)s)",
    )
    p.add_argument(
        "--seed", type=count(0), default=0, help="sensor-noise seed (default: %(default)s)"
    )
    p.add_argument(
        "--status-every",
        type=number(0.0),
        default=1.0,
        help="status line period [s], >= 0 (default: %(default)s; 0: none)",
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


def payload_limit_problem(vehicle: dict, payload_g: float) -> str | None:
    """Why ``payload_g`` is more than ``vehicle`` lifts at full thrust (one line), or None."""
    from arcade_io.vehicle import max_payload_g

    limit = max_payload_g(vehicle)
    if payload_g >= limit:
        return (
            f"--payload-g must be below {limit:.0f} g for this vehicle (the rotors' full "
            f"thrust carries no more), got {payload_g:g}"
        )
    return None


def check_arguments(args: argparse.Namespace) -> dict:
    """The vehicle file, checked with the options that depend on it; ``ValueError`` /
    ``FileNotFoundError`` with a one-line message otherwise (nothing has started yet)."""
    from arcade_io.vehicle import load_vehicle
    from simulator.px4.link import parse_url

    try:
        parse_url(args.px4)
    except ValueError as err:
        msg = str(err)
        raise ValueError(
            f"--px4: {msg}" if args.px4 in msg else f"--px4 {args.px4}: {msg}"
        ) from None
    vehicle = load_vehicle(args.vehicle)
    problem = payload_limit_problem(vehicle, args.payload_g)
    if problem is not None:
        raise ValueError(problem)
    if args.payload_g == 0.0:
        for flag, value in (
            ("--cable-length", args.cable_length),
            ("--release-at", args.release_at),
        ):
            if value is not None:
                raise ValueError(f"{flag} needs a payload (--payload-g > 0)")
    if args.airborne and args.start[2] <= 0.0:
        raise ValueError(
            f"--start Z must be above the floor (> 0) with --airborne, got {args.start[2]:g}"
        )
    return vehicle


def run(args: argparse.Namespace) -> int:
    try:
        vehicle = check_arguments(args)
    except (ValueError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    from simulator.px4 import Px4Sim

    def on_text(severity: int, text: str) -> None:
        print(f"[px4] {text}", flush=True)

    failsafe = failsafe_settings(args)
    failsafe["params"]["MIS_TAKEOFF_ALT"] = args.takeoff_alt
    try:
        sim = Px4Sim(
            args.px4,
            vehicle=vehicle,
            payload_g=args.payload_g,
            cable_length=args.cable_length,
            start=args.start,
            yaw=math.radians(args.yaw_deg),
            airborne=args.airborne,
            **failsafe,
            seed=args.seed,
            on_text=on_text,
        )
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # the link's socket: address not local, port in use, ...
        print(
            f"error: cannot open the MAVLink link {args.px4}: {err.strerror or err}",
            file=sys.stderr,
        )
        return 1
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
        sig: signal.signal(sig, lambda *_: signals.set_from_handler(sim.stop))
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
