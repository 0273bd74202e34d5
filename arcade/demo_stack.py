"""`arcade demo`: the whole service stack in lockstep, one figure-eight flight.

The simulator, estimator, adapter, controller and recorder run as separate processes on
a private Zenoh hub (:mod:`deploy.launcher`). The flight: take-off, hover, two laps of the
figure-eight with a swinging payload that is released just before the second lap
(:class:`arcade_control.scenario.Scenario`). Afterwards the ground truth of the
simulator gives the metrics of ``arcade_core.metrics`` (tracking RMSE and z-RMSE over the
figure-eight, shift magnitude and 5 cm settling time of the z error at the release) and the
adapter's changepoint events give the detection delay. The run folder holds the plot,
``metrics.json``, the logs of every service, the flight log and the MCAP recording.
"""

from __future__ import annotations

import json
import socket
import sys
from pathlib import Path
from typing import Any

import numpy as np

from arcade_control.knobs import DEFAULT_STACK_METHOD
from arcade_io import atomicfile, jsonout


def free_hub() -> str:
    """A loopback endpoint on a free port (a private bus for this run)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def read_truth(path: Path) -> dict[str, np.ndarray]:
    """Columns of the simulator's ``truth.csv``."""
    data = np.genfromtxt(path, delimiter=",", names=True)
    return {name: np.atleast_1d(data[name]) for name in data.dtype.names}


def truth_metrics(
    truth: dict[str, np.ndarray], t_figure: float, t_release: float | None
) -> dict[str, float]:
    """RMSE, z-RMSE and the RMS of the thrust command's step-to-step change from
    ``t_figure`` on; shift and settling at ``t_release`` (as the in-process evaluation
    computes them, ``benchmarks.quadrotor_flights.flight_metrics``)."""
    import jax.numpy as jnp

    from arcade_core import metrics

    t = truth["t"]
    p = np.stack([truth["px"], truth["py"], truth["pz"]], axis=1)
    pr = np.stack([truth["ref_px"], truth["ref_py"], truth["ref_pz"]], axis=1)
    sel = t >= t_figure - 1e-9
    u = np.stack([truth[f"u{i}"] for i in range(4)], axis=1)
    out = {
        "rmse_m": float(metrics.position_rmse(jnp.asarray(p[sel]), jnp.asarray(pr[sel]))),
        "rmse_z_m": float(metrics.z_rmse(jnp.asarray(p[sel]), jnp.asarray(pr[sel]))),
        "thrust_increment_rms_n": float(metrics.increment_rms(jnp.asarray(u[sel]))[0]),
    }
    if t_release is not None:
        e_z = jnp.asarray(p[:, 2] - pr[:, 2])
        tt = jnp.asarray(t)
        out["shift_m"] = float(metrics.shift_magnitude(tt, e_z, t_release))
        out["settling_s"] = float(metrics.settling_time(tt, e_z, t_release, band=0.05).time)
    return out


def plot(
    path: Path,
    truth: dict[str, np.ndarray],
    t_release: float | None,
    changepoints: list[float],
    flown: str = "figure-eight",
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = truth["t"]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    ax1.plot(truth["ref_px"], truth["ref_py"], "k--", lw=1, label="reference")
    ax1.plot(truth["px"], truth["py"], lw=1.2, label="flown (ground truth)")
    ax1.set_xlabel("x [m]")
    ax1.set_ylabel("y [m]")
    ax1.set_aspect("equal", adjustable="datalim")
    ax1.legend(loc="upper right", fontsize=8)
    ax2.plot(t, truth["pz"] - truth["ref_pz"], lw=1.2, label="z error")
    if t_release is not None:
        ax2.axvline(t_release, color="r", lw=1, label="payload released")
    for i, c in enumerate(changepoints):
        ax2.axvline(c, color="g", lw=0.8, ls=":", label="changepoint event" if i == 0 else None)
    ax2.set_xlabel("t [s]")
    ax2.set_ylabel("z - z_ref [m]")
    ax2.legend(fontsize=8)
    fig.suptitle(f"ARCADE service stack (lockstep): {flown} with payload release")
    fig.tight_layout()
    atomicfile.save_figure(fig, path, dpi=120)
    plt.close(fig)


def run_demo(
    out: Path,
    *,
    payload_g: float = 175.0,
    speed: float = 2.5,
    seed: int = 0,
    rate: float = 20.0,
    x64: bool = False,
    weights: Path | None = None,
    duration: float | None = None,
    lockstep: bool = True,
    progress: bool = True,
    extra: dict[str, list[str]] | None = None,
    truth_state: bool = False,
    hub: str | None = None,
    link_delay_s: float = 0.0,
    method: str = DEFAULT_STACK_METHOD,
    ros2: bool = False,
    foxglove_port: int | None = None,
    trajectory: tuple[str, Any] | None = None,
) -> dict[str, Any]:
    """Fly the demo through the stack; writes the run folder and returns the summary.
    ``link_delay_s``: the link delay the controller and the adapter compensate
    (``arcade up --link-delay``); ``method``: one of ``STACK_METHODS`` (``--method``);
    ``ros2``: run the ROS 2 mirror too (``--ros2``); ``foxglove_port``: serve the flight
    live to Foxglove (``--foxglove``); ``trajectory``: ``--trajectory``'s spec and what
    :func:`deploy.trajectories.prepare` made of it, flown instead of the figure-eight."""
    from tqdm import tqdm

    from arcade_control.scenario import planned
    from deploy.launcher import StackConfig, run_flight, sigterm_interrupts
    from deploy.trajectories import stage

    scen = planned(payload_g, speed, trajectory=trajectory[1] if trajectory else None)
    t_end = duration if duration is not None else scen.t_end
    cfg = StackConfig(
        out=out,
        lockstep=lockstep,
        hub=hub or free_hub(),
        credentials=hub is None,  # a bus of its own: only this run's processes join
        rate=rate,
        duration=duration,
        payload_g=payload_g,
        speed=speed,
        seed=seed,
        x64=x64,
        weights=weights,
        extra=dict(extra or {}),
        truth_state=truth_state,
        link_delay_s=link_delay_s,
        method=method,
        ros2=ros2,
        foxglove_port=foxglove_port,
    )
    out = cfg.out  # absolute: where the services write, whatever the working directory
    if trajectory is not None:
        out.mkdir(parents=True, exist_ok=True)
        cfg.trajectory, cfg.trajectory_sha256 = stage(out, *trajectory)

    bar = tqdm(
        total=round(t_end, 2),
        unit="s sim",
        disable=not progress,
        file=sys.stderr,
        bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} s simulated [{elapsed}]",
    )

    def on_time(t: float) -> None:
        bar.n = round(min(max(t, 0.0), t_end), 2)
        bar.refresh()

    def say(msg: str) -> None:
        if progress:
            tqdm.write(msg, file=sys.stderr)

    try:
        with sigterm_interrupts():
            result = run_flight(cfg, progress=say, on_time=on_time if lockstep else None)
    finally:
        bar.close()
    sim_stats = json.loads((out / "stats" / "sim.json").read_text())
    truth = read_truth(out / "truth.csv")
    t_release = sim_stats.get("released_at")
    cps = sorted(e["stamp"] for e in result["events"] if e["kind"] == "changepoint")
    summary: dict[str, Any] = truth_metrics(truth, scen.t_figure, t_release)
    after = [c - t_release for c in cps if t_release is not None and c >= t_release - 1e-9]
    summary.update(
        t_release_s=t_release,
        changepoints_s=cps,
        detection_delay_s=after[0] if after else None,
        crashed=bool(sim_stats.get("crashed")),
        sim_timeouts=sim_stats.get("timeouts", 0),
        flight_wall_s=result["flight_wall_s"],
        startup_s=result["ready_s"],
        exit_codes=result["codes"],
        adaptation="nominal"
        if any(e["kind"] == "degraded" and "weights" in e["text"] for e in result["events"])
        else method,
        settings={
            "payload_g": payload_g,
            "speed_mps": speed,
            "seed": seed,
            "rate_hz": rate,
            "lockstep": lockstep,
            "x64": x64,
            "method": method,
            "trajectory": trajectory[0] if trajectory else None,
        },
    )
    rejects, failures = {}, {}
    for f in (out / "stats").glob("*.json"):
        stats = json.loads(f.read_text())
        if r := stats.get("rejects", {}):
            rejects[f.stem] = r
        if n := stats.get("callback_failures", {}):
            failures[f.stem] = n
    summary["rejects"] = rejects
    summary["callback_failures"] = failures
    flown = f"trajectory {Path(trajectory[0]).name}" if trajectory else "figure-eight"
    plot(out / "flight.png", truth, t_release, cps, flown)
    atomicfile.write_text(out / "metrics.json", jsonout.dumps(summary, indent=2))
    return summary


#: What the summary's ``adaptation`` names (the method flown, or ``nominal`` when the
#: weights could not be used).
CONTROLLERS = {
    "ours": "ours (ARCADE adaptive MPC, the paper's method)",
    "arcade": "arcade (the flagship: learned model and L1 thrust augmentation)",
    "l1": "l1 (the L1 augmentation on the nominal MPC, the baseline)",
    "nominal": "nominal MPC (the weights could not be used)",
}


def format_summary(s: dict[str, Any]) -> str:
    def f(v: Any, unit: str = "") -> str:
        return "-" if v is None else f"{v:.3f}{unit}"

    lines = [
        f"controller: {CONTROLLERS.get(s['adaptation'], s['adaptation'])}",
        f"{'tracking RMSE':22s} {f(s['rmse_m'], ' m')}",
        f"{'z RMSE':22s} {f(s['rmse_z_m'], ' m')}",
        f"{'shift at release':22s} {f(s.get('shift_m'), ' m')}",
        f"{'settling (5 cm)':22s} {f(s.get('settling_s'), ' s')}",
        f"{'thrust increments RMS':22s} {f(s.get('thrust_increment_rms_n'), ' N')}",
        f"{'changepoint delay':22s} {f(s.get('detection_delay_s'), ' s')}",
        f"{'payload released at':22s} {f(s.get('t_release_s'), ' s')}",
        f"{'flight wall time':22s} {f(s['flight_wall_s'], ' s')} (start-up {s['startup_s']:.1f} s)",
    ]
    if s["crashed"]:
        lines.append("THE VEHICLE CRASHED")
    if s["rejects"]:
        lines.append(f"rejected messages: {s['rejects']}")
    if s.get("callback_failures"):
        lines.append(f"failures handling messages: {s['callback_failures']}")
    return "\n".join(lines)
