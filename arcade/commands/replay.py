"""`arcade replay RUN/bus.mcap` — a recorded flight through the adapter (and controller)
again, offline, with the same or other knobs.

The services themselves run, in this process, on a bus that delivers the recorded messages
in the order the recorder received them (its ``log_time``), as fast as the CPU allows:
the adapter (``services.adapter``) gets the recorded states, setpoints, events and
commands; with ``--service controller`` the controller (``services.controller``) also
plans on every recorded state with the replayed adapter's model (open loop: the states
stay the recorded ones, and the adapter learns from the setpoints the vehicle flew). Each
runs with the command line it announced in the recording (its ``ready`` event), plus the
knobs of ``--set`` (the adapter's ``--knob``); their clock reads the stamp of the newest
record. A lockstep flight is reproduced exactly (its states and setpoints are fed in the
order the lockstep adapter waits for them, :func:`lockstep_order`). A real-time one is fed
in the order the recorder received it, the adapter each state once the setpoint answering
it has come (as it waits for it) and after the commands and events received right after
that setpoint; which model a real-time controller had for a state depends on the timing of
the flight, so its setpoints are close to, not exactly, the recorded ones. What they
publish goes, with the recorded inputs, to ``OUT/bus.mcap`` (the recorder service writes
it: the same channels, Foxglove's included), and a comparison with what the recorded
services published to ``OUT/replay.json``: the prediction error of the residuals, the
changepoint events and, with the controller, the setpoints.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

HELP = "feed a recorded flight (bus.mcap) through the adapter (and controller) again, offline"

_EPILOG = """\
what it writes (default OUT: the recording's folder/replay):
  OUT/bus.mcap     the recorded inputs and what the replayed services published
  OUT/replay.json  recorded against replayed: prediction error of the residuals (RMS of
                   delta - mean), their largest difference, the changepoint events and,
                   with --service controller, the setpoints
knobs (--set, repeatable): the learner's of the method flown (arcade: arcade_lambda,
  arcade_restart_scale, arcade_sigma2; ours and l1: ours_beta, ours_sigma2) and the
  changepoint detector's (detector_threshold, detector_window, detector_pi, detector_beta,
  detector_tracking, detector_refractory_steps, detector_outputs=all|translational|vertical)
examples:
  arcade replay runs/demo/bus.mcap                       reproduces the recorded adapter
  arcade replay runs/demo/bus.mcap --set arcade_lambda=0.95 --set detector_threshold=0.9
  arcade replay runs/demo/bus.mcap --service controller  the setpoints too"""

#: What the replay of each service publishes instead of the recording.
REPLACED = {"adapter": ("residual", "model"), "controller": ("setpoint",)}
#: The recorded topics each replayed service is fed (as it subscribes them).
INPUTS = {
    "adapter": ("state", "setpoint", "event", "command"),
    "controller": ("state", "command"),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = _EPILOG
    p.add_argument("mcap", type=Path, metavar="RUN/bus.mcap", help="the recorded flight")
    p.add_argument(
        "--service",
        choices=("adapter", "controller"),
        default="adapter",
        help="adapter: replay the adapter; controller: the adapter and the controller "
        "(default: %(default)s)",
    )
    p.add_argument(
        "--set",
        dest="knobs",
        action="append",
        default=[],
        metavar="KNOB=VALUE",
        help="a knob instead of the recorded adapter's (repeatable; the list is below)",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        metavar="DIR",
        help="folder of the replay's bus.mcap and replay.json (default: the recording's "
        "folder/replay; never the recording's own folder)",
    )


# ------------------------------------------------------------------ the recording


class ReplayError(ValueError):
    """A recording or an option that cannot be replayed (one line)."""


def read_recording(path: Path, progress: bool = True) -> tuple[list[tuple[str, Any]], str]:
    """The bus records of ``path`` in receive order as ``(topic, record)``, and the vehicle."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from tqdm import tqdm

    from services.messages import MessageError, message_type

    if not path.is_file():
        raise ReplayError(f"{path}: no such file")
    records: list[tuple[str, Any]] = []
    vehicle = None
    try:
        with path.open("rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            total = summary.statistics.message_count if summary and summary.statistics else None
            bar = tqdm(
                total=total,
                unit="msg",
                disable=None if progress else True,
                file=sys.stderr,
                desc="reading",
            )
            for _, channel, message in reader.iter_messages(log_time_order=True):
                bar.update()
                parts = channel.topic.split("/")
                if channel.message_encoding != "json" or len(parts) != 3 or parts[0] != "arcade":
                    continue  # Foxglove's channels, anything else
                try:
                    cls = message_type(parts[2])
                    data = json.loads(message.data)
                    records.append((parts[2], cls.from_wire(data)))
                except (KeyError, ValueError, MessageError):
                    continue  # not a record of this version: the services would reject it
                vehicle = parts[1]
            bar.close()
    except OSError as err:
        raise ReplayError(f"{path}: {err.strerror or err}") from None
    except Exception as err:  # McapError and others: the reader's errors vary
        why = type(err).__name__ if isinstance(err, McapError) else str(err) or type(err).__name__
        raise ReplayError(f"{path}: not an MCAP file, or a damaged one ({why})") from None
    if vehicle is None or not any(t == "state" for t, _ in records):
        raise ReplayError(f"{path}: no arcade state messages recorded")
    return records, vehicle


def lockstep_order(records: list[tuple[str, Any]]) -> list[tuple[str, Any]]:
    """``records`` with the states and setpoints in the order a lockstep adapter handles
    them: by stamp, each state before the setpoint answering it (the adapter waits for
    that setpoint before the next state; the recorder, on other links, may receive a
    state before the setpoint of the one before). The other records keep their places."""
    rank = {"state": 0, "setpoint": 1}
    slots = [i for i, (t, _) in enumerate(records) if t in rank]
    flow = sorted((records[i] for i in slots), key=lambda r: (r[1].stamp, rank[r[0]]))
    out = list(records)
    for i, r in zip(slots, flow):
        out[i] = r
    return out


def announced_argv(records: list[tuple[str, Any]], service: str) -> list[str]:
    """The command line ``service`` announced in the recording (its first ``ready`` event)."""
    import shlex

    for topic, m in records:
        if topic == "event" and m.kind == "ready" and m.data.get("service") == service:
            return shlex.split(m.text)
    raise ReplayError(
        f"the recording holds no start-up record of the {service} (its 'ready' event): "
        "it was recorded by a stack that did not announce its options"
    )


def service_args(name: str, argv: list[str], out: Path, knobs: list[str]) -> argparse.Namespace:
    """The options of service ``name`` as it ran, in ``out``, with ``knobs`` added."""
    from arcade.commands.service_options import service_parser

    parser = service_parser(name)
    extra = [f"--knob={k}" for k in knobs] if name == "adapter" else []
    try:
        args = parser.parse_args([*argv, *extra])
    except ValueError as err:
        why = f"--set: {err}" if extra else f"{name}'s recorded options: {err}"
        raise ReplayError(why) from None
    args.out, args.checkpoint, args.incarnation = out, None, 0
    return args


def knob_problem(knobs: list[str], method: str) -> str | None:
    """Why a knob does not parse or is none of the adapter's flying ``method``, or None."""
    from arcade_control.knobs import CONTROLLER_KNOBS, DETECTOR_PREFIX, TUNING_METHOD, parse_knob
    from arcade_control.stack import adapter_method, stack_knobs

    own = [k for k in stack_knobs(method) if TUNING_METHOD[k] == adapter_method(method)]
    own = [k for k in own if k not in CONTROLLER_KNOBS]
    for text in knobs:
        try:
            name, _ = parse_knob(text)
        except ValueError as err:
            return f"--set {text}: {err}"
        if not name.startswith(DETECTOR_PREFIX) and name not in own:
            return f"--set {text}: not a knob of the adapter flying {method} ({', '.join(own)})"
    return None


# ------------------------------------------------------------------------ replay


def replay(
    path: Path, service: str, knobs: list[str], out: Path, progress: bool = True
) -> dict[str, Any]:
    """Replay ``path`` (see the module docstring); returns the comparison (replay.json)."""
    from services import runtime
    from services.bus import Bus, key_expr
    from services.messages import encode
    from services.offline_bus import PEER, PINNED, Session

    records, vehicle = read_recording(path, progress)
    names = ["adapter", *(("controller",) if service == "controller" else ())]
    argv = {name: announced_argv(records, name) for name in names}
    args = {name: service_args(name, argv[name], out, []) for name in names}
    problem = knob_problem(knobs, args["adapter"].method)
    if problem is not None:
        raise ReplayError(problem)
    args["adapter"] = service_args("adapter", argv["adapter"], out, knobs)
    runtime.setup_jax(args["adapter"].x64)
    from services.adapter import Adapter
    from services.controller import Controller
    from services.recorder import Recorder

    out.mkdir(parents=True, exist_ok=True)
    published: dict[str, list[Any]] = defaultdict(list)
    sessions: dict[str, Session] = {}

    def on_put(session: Session, key: str, payload: bytes) -> None:
        topic = key.rsplit("/", 1)[-1]
        published[topic].append(payload)
        sessions["recorder"].deliver(key, payload)
        if session.name == "adapter" and topic == "model" and "controller" in sessions:
            sessions["controller"].deliver(key, payload)

    classes = {"adapter": Adapter, "controller": Controller}
    services = {}
    # The services' clock reads the stamp of the newest record delivered: a recorded state
    # is as fresh as when it was published (its age in real time is the recording's).
    clock = [0.0]
    rec_args = argparse.Namespace(out=out, incarnation=0, vehicle=vehicle, geofence="none")
    for name, svc in [("recorder", Recorder(rec_args))] + [(n, classes[n](args[n])) for n in names]:
        sessions[name] = Session(name, on_put)
        bus = Bus(vehicle, name, None).open(session=sessions[name])
        for pinned in PINNED:  # every record comes from the one offline peer session
            bus.pins.owner_up(pinned, PEER)
        svc.bus, svc.now = bus, lambda: clock[0]
        bus.subscribe("command", svc._on_command)
        svc.setup(bus)
        services[name] = svc
    for svc in services.values():
        svc.ready()
    lockstep = bool(args["adapter"].lockstep)
    if lockstep:
        records = lockstep_order(records)
    # Who gets a state first: lockstep, the adapter (the controller waits for its model);
    # real time, the controller (it solves with the newest model it has).
    order = names if lockstep else names[::-1]
    replaced = {t for n in names for t in REPLACED[n]}
    from tqdm import tqdm

    t0 = time.perf_counter()
    ctrl = services.get("controller")
    # Real time: the adapter updates on a state once the controller's setpoint for it is
    # out, or half a period later (services.adapter): what arrives meanwhile, and the
    # commands and events received right after that setpoint, come first.
    held: tuple[Any, str, bytes] | None = None
    answered = False  # the held state's setpoint has come
    wait_s = 0.5 / args["adapter"].rate
    for topic, m in tqdm(
        records, unit="msg", disable=None if progress else True, file=sys.stderr, desc="replay"
    ):
        payload, key = encode(m), key_expr(vehicle, topic)
        src = m.src.split("/")[0]
        clock[0] = max(clock[0], m.stamp)
        if topic not in replaced and not (topic == "event" and src in names):
            sessions["recorder"].deliver(key, payload)
        if held is not None and (
            (answered and topic not in ("command", "event"))
            or topic == "state"
            or m.stamp > held[0].stamp + wait_s
        ):
            sessions["adapter"].deliver(*held[1:])
            held, answered = None, False
        for name in order:
            if topic not in INPUTS[name]:
                continue
            if name == "adapter" and topic == "state" and not lockstep:
                held = (m, key, payload)  # handled once its setpoint is there
                continue
            sessions[name].deliver(key, payload)
            if name == "adapter" and held is not None and topic == "setpoint":
                answered = answered or m.stamp == held[0].stamp
            if name == "controller":
                while not ctrl._queue.empty():
                    ctrl.step(*ctrl._queue.get_nowait())
    if held is not None:
        sessions["adapter"].deliver(*held[1:])
    elapsed = time.perf_counter() - t0
    for svc in services.values():
        svc.teardown()
        svc.bus.close()
    result = compare(records, published, names)
    result.update(
        recording=str(path),
        service=service,
        knobs=knobs,
        messages=len(records),
        replay_s=round(elapsed, 3),
        rejects={n: s.bus.rejects.counts for n, s in services.items()},
    )
    (out / "replay.json").write_text(json.dumps(result, indent=1) + "\n")
    return result


def _residual_errors(residuals: list[Any]) -> dict[float, Any]:
    import numpy as np

    return {
        r.stamp: (np.asarray(r.delta) - np.asarray(r.mean), np.asarray(r.mean)) for r in residuals
    }


def compare(records, published, names) -> dict[str, Any]:
    """Recorded against replayed: prediction errors, changepoints, setpoints."""
    import numpy as np

    from services.messages import decode

    replayed = {t: [decode(t, p) for p in ps] for t, ps in published.items()}
    recorded: dict[str, list[Any]] = defaultdict(list)
    for topic, m in records:
        if topic != "event" or m.src.split("/")[0] == "adapter":
            recorded[topic].append(m)

    def changepoints(events):
        return [round(e.stamp, 4) for e in events if e.kind == "changepoint"]

    def rms(errors):
        return float(np.sqrt(np.mean([e**2 for e, _ in errors.values()]))) if errors else None

    old, new = (
        _residual_errors(recorded["residual"]),
        _residual_errors(replayed.get("residual", [])),
    )
    both = sorted(set(old) & set(new))
    diff = max((float(np.max(np.abs(old[t][1] - new[t][1]))) for t in both), default=None)
    out: dict[str, Any] = {
        "residuals": {"recorded": len(old), "replayed": len(new), "matched": len(both)},
        "prediction_rms": {"recorded": rms(old), "replayed": rms(new)},
        "max_abs_mean_difference": diff,
        "changepoints": {
            "recorded": changepoints(recorded["event"]),
            "replayed": changepoints(replayed.get("event", [])),
        },
    }
    if "controller" in names:
        old_u = {s.stamp: np.asarray(s.u) for s in recorded["setpoint"]}
        new_u = {s.stamp: np.asarray(s.u) for s in replayed.get("setpoint", [])}
        both_u = sorted(set(old_u) & set(new_u))
        out["setpoints"] = {
            "recorded": len(old_u),
            "replayed": len(new_u),
            "matched": len(both_u),
            "max_abs_difference": max(
                (float(np.max(np.abs(old_u[t] - new_u[t]))) for t in both_u), default=None
            ),
        }
    return out


def run(args: argparse.Namespace) -> int:
    from arcade_io.runs import check_output_dir

    def error(msg: str, code: int = 2) -> int:
        print(f"error: {msg}", file=sys.stderr, flush=True)
        return code

    path = args.mcap
    out = args.out if args.out is not None else path.parent / "replay"
    if out.resolve() == path.parent.resolve():
        return error(f"--out {out}: the recording's own folder (its bus.mcap would be replaced)")
    try:
        check_output_dir(out, "--out")
        result = replay(path, args.service, args.knobs, out)
    except ValueError as err:  # ReplayError, OutputPathError
        return error(str(err))
    except OSError as err:
        return error(f"{err.filename or out}: {err.strerror or err}", 1)
    p, cps = result["prediction_rms"], result["changepoints"]
    fmt = lambda v: "-" if v is None else f"{v:.4g}"  # noqa: E731
    print(f"replayed {result['messages']} messages in {result['replay_s']:.1f} s")
    r = result["residuals"]
    n = (r["recorded"], r["replayed"], r["matched"])
    print("residuals: {} recorded, {} replayed, {} matched".format(*n))
    print(
        f"prediction error (RMS, normalised): recorded {fmt(p['recorded'])}, "
        f"replayed {fmt(p['replayed'])}"
    )
    print(f"largest difference of the predicted mean: {fmt(result['max_abs_mean_difference'])}")
    print(f"changepoints at: recorded {cps['recorded']}, replayed {cps['replayed']}")
    if "setpoints" in result:
        s = result["setpoints"]
        print(
            f"setpoints: {s['recorded']} recorded, {s['replayed']} replayed, largest "
            f"difference {fmt(s['max_abs_difference'])}"
        )
    print(f"written: {out / 'bus.mcap'}, {out / 'replay.json'}")
    return 0
