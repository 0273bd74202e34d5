"""`arcade up` — launch the service stack (simulator or vehicle link + all services)."""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "launch the service stack as processes over Zenoh (profile sim or px4)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = (
        "examples:\n"
        "  arcade up --profile sim --lockstep          deterministic flight, as fast as it goes\n"
        "  arcade up --profile sim --rate 50           real time at 50 Hz (Ctrl-C stops)\n"
        "  arcade up --payload-g 125 --speed 1.5 --out runs/my-flight\n"
        "  arcade up --profile px4 --connect serial:///dev/ttyACM0:921600\n"
        "                                              a real PX4 (asks before arming)\n"
        "  arcade up --profile px4 --simulate --arm   the same chain against a simulated PX4\n"
        "The run folder gets logs/<service>.log, stats/, events.jsonl, truth.csv,\n"
        "flight_log.csv and bus.mcap (open it in Foxglove Studio)."
    )
    p.add_argument(
        "--profile",
        choices=("sim", "px4"),
        default="sim",
        help="sim: MuJoCo simulator as the vehicle; px4: a PX4 vehicle link",
    )
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="simulated clock: the simulator waits for every setpoint",
    )
    p.add_argument("--vehicle", default="default", help="vehicle name on the bus")
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        help="flight duration [s] (default: take-off, hover, two figure-eight laps)",
    )
    p.add_argument("--payload-g", type=float, default=175.0, help="swinging payload [g]")
    p.add_argument("--speed", type=float, default=2.5, help="figure-eight mean speed [m/s]")
    p.add_argument("--rate", type=float, default=20.0, help="control rate [Hz]")
    p.add_argument("--seed", type=int, default=0, help="trial seed")
    p.add_argument("--out", type=Path, default=None, help="run folder (default runs/<time>-up)")
    p.add_argument("--hub", default=None, help="Zenoh hub endpoint (default: a free loopback port)")
    p.add_argument("--weights", type=Path, default=None, help="VLD weights file")
    p.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        help="adapter posterior checkpoint (restored if present)",
    )
    p.add_argument("--x64", action="store_true", help="compute in float64")
    p.add_argument(
        "--no-realtime-priority",
        dest="realtime_priority",
        action="store_false",
        help="realtime clock: keep the normal scheduling policy and let idle CPUs "
        "sleep (default: the vehicle link, estimator and controller run under "
        "SCHED_FIFO after warm-up and request a CPU wake-up latency of 0 us, "
        "which needs root or an rtprio limit; without, they warn)",
    )
    from deploy import px4_profile

    px4_profile.add_arguments(p)


def run(args: argparse.Namespace) -> int:
    import signal
    import sys

    from arcade.demo_stack import free_hub
    from arcade.runs import new_run_dir
    from deploy.launcher import StackConfig, StackError, run_flight

    out = args.out or new_run_dir("up")
    cfg = StackConfig(
        out=Path(out),
        profile=args.profile,
        lockstep=args.lockstep,
        vehicle=args.vehicle,
        hub=args.hub or free_hub(),
        rate=args.rate,
        duration=args.duration,
        payload_g=args.payload_g,
        speed=args.speed,
        seed=args.seed,
        x64=args.x64,
        weights=args.weights,
        checkpoint=args.checkpoint,
        realtime_priority=args.realtime_priority,
    )

    def say(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    def on_term(*_: object) -> None:
        raise KeyboardInterrupt  # the launcher's context manager stops every service

    signal.signal(signal.SIGTERM, on_term)

    last = [-1.0]

    def on_time(t: float) -> None:
        if t - last[0] >= 1.0:
            last[0] = t
            print(f"\r  t = {t:7.2f} s", end="", file=sys.stderr, flush=True)

    try:
        hooks = {}
        if args.profile == "px4":
            from deploy import px4_profile

            cfg = px4_profile.config_from_args(args, cfg)
            hooks = px4_profile.flight_hooks(args, cfg, say)
        hooks["on_event"] = _show_faults(say, hooks.get("on_event"))
        result = run_flight(cfg, progress=say, on_time=on_time if args.lockstep else None, **hooks)
    except (StackError, ValueError) as err:
        say(f"\nerror: {err}")
        return 1
    say("")
    restarts = result.get("restarts", {})
    for name, code in result["codes"].items():
        extra = f"  ({restarts[name]} restart(s))" if restarts.get(name) else ""
        say(f"  {name:10s} exit {code}{extra}")
    say(f"run folder: {out}")
    return 0 if all(c == 0 for c in result["codes"].values()) else 1


#: Events worth a line on the console while flying (the rest is in events.jsonl).
SHOWN = ("fault", "restart", "failsafe")


def _show_faults(say, then=None):
    """An ``on_event`` hook that prints crashes, restarts and failsafes as they happen."""

    def on_event(rec: dict) -> None:
        if rec["kind"] in SHOWN or (rec["kind"] == "info" and "failsafe" in rec["text"]):
            say(f"\n  [{rec['src'].split('/')[0]}] {rec['kind']}: {rec['text']}")
        if then is not None:
            then(rec)

    return on_event
