"""Bus and loop latency of the full stack in real time (design §7, ``arcade bench loop``).

Runs the whole stack (simulator, estimator, adapter, controller, recorder as processes on a
private loopback Zenoh hub) on the wall clock at 50 Hz and reports:

- ``hop_p50_ms``/``hop_p99_ms``: one bus hop, simulator -> estimator (the ``imu`` sample
  that marks a control instant, from ``put`` to the subscriber callback, measured by the
  bus from the put time each sample carries; both processes read the same
  ``time.monotonic()``);
- ``sense_to_actuate_p99_ms``: from the sample instant of a control instant (its stamp) to
  the setpoint that answers it arriving back at the simulator (the simulator's publishing
  lag, estimator, controller and three hops); targets: at most 10 ms, and at most the
  MPC's p99 solve time + 3 ms;
- ``rate_hz``: achieved control rate over the mission; ``missed_deadlines``: mission
  instants whose setpoint had not arrived by the next instant (target: 0 over 120 s);
  ``host``: what the machine itself did meanwhile (:class:`arcade_io.hostcpu.SlowdownProbe`
  and the steal counter): the intervals it ran slowly in, and how many of the missed
  deadlines fell in a period it stole from or slowed
  (``missed_deadlines_outside_host_slowdowns`` are the stack's own);
- ``mpc_p99_ms``: the controller's MPC solve time in the same run: with the advanced step
  (``advanced_step``: ``arcade bench loop --advanced-step``) the solve for the next
  instant, after the setpoint is out, off the sense-to-actuate path; ``answer_p99_ms``:
  the controller's state-to-setpoint step (the advanced step's Gauss-Newton step from
  the prepared plan; without it, the solve); ``planned_steps``: the states answered from a plan;
- ``stages_ms``: sense-to-actuate stage by stage (p50, p99): the simulator's sample instant
  to its imu put, the hop to the estimator, the estimator's work, the hop to the
  controller, the controller from the state's arrival to the setpoint's put (solve
  included), the hop back; ``gc_pause_max_ms``: the longest collector pause of any service;
- ``realtime``: per service of that path, the scheduling policy it got and the CPU wake-up
  latency it held (``services.runtime``): the conditions of the numbers above.

``ready_s``: the stack's start-up, from the first process started to every liveliness
token seen. The bus is ``arcade up``'s: a hub of its own with a password made for the run
(``credentials=False``: open peers).

``quick`` flies 20 s instead of 120 s. The flight plan is the demo's (175 g payload,
figure-eight at 2.5 m/s, released before the second lap; beyond two laps the figure-eight
continues).
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from arcade_control.knobs import DEFAULT_STACK_METHOD

RATE_HZ = 50.0


def _wakeup(stats: dict[str, Any]) -> int | None:
    """The CPU wake-up latency a service held (µs), ``None`` if it requested none or was
    refused."""
    req = stats.get("cpu_wakeup_latency", {})
    return req.get("requested_us") if req.get("applied") else None


def _every(period: float, show: Callable[[float], None]) -> Callable[[float], None]:
    """An ``on_time`` hook that shows the flight time once per ``period`` seconds of it."""
    last = [-period]

    def on_time(t: float) -> None:
        if t - last[0] >= period:
            last[0] = t
            show(t)

    return on_time


def _since_first_state(on_time: Callable[[float], None]) -> Callable[[float], None]:
    """``on_time`` fed the time since the first state's stamp (the stack reports stamps on
    the monotonic clock in real time, 0 before the first state)."""
    first: list[float] = []

    def hook(stamp: float) -> None:
        if stamp > 0.0 and not first:
            first.append(stamp)
        if first:
            on_time(stamp - first[0])

    return hook


def run(
    quick: bool = False,
    out: Path | None = None,
    rate: float = RATE_HZ,
    duration: float | None = None,
    progress: Callable[[str], None] | None = None,
    method: str = DEFAULT_STACK_METHOD,
    credentials: bool = True,
    advanced: bool = False,
) -> dict[str, Any]:
    """Fly the stack in real time with ``method`` (one of ``STACK_METHODS``) and measure (see
    the module docstring); ``advanced``: the controller's ``--advanced-step``; ``progress``
    gets the stack's start-up lines and the simulated time every 10 s."""
    from arcade.demo_stack import free_hub
    from arcade_io.hostcpu import SlowdownProbe, overlaps
    from benchmarks.common import machine
    from deploy.launcher import StackConfig, run_flight

    duration = duration if duration is not None else (20.0 if quick else 120.0)
    with tempfile.TemporaryDirectory(prefix="arcade-loop-") as tmp:
        folder = Path(out) if out is not None else Path(tmp)
        cfg = StackConfig(
            out=folder,
            lockstep=False,
            hub=free_hub(),
            rate=rate,
            duration=duration,
            method=method,
            credentials=credentials,
            extra={"controller": ["--advanced-step"]} if advanced else {},
        )
        with SlowdownProbe(folder / "host") as host:
            if progress is None:
                result = run_flight(cfg)
            else:
                step = ", advanced step" if advanced else ""
                progress(f"[loop] {duration:g} s real-time flight at {rate:g} Hz ({method}{step})")
                result = run_flight(
                    cfg,
                    progress=lambda m: progress(f"[loop] {m}"),
                    on_time=_since_first_state(
                        _every(10.0, lambda t: progress(f"[loop] t = {t:.0f} s"))
                    ),
                )
        stats = {
            name: json.loads((folder / "stats" / f"{name}.json").read_text())
            for name in ("sim", "estimator", "controller", "adapter")
        }
    sim, est, ctl = stats["sim"], stats["estimator"], stats["controller"]
    wall = sim["wall_s"] - sim.get("preroll_s", 0.0)
    steps = sim["steps"]
    advanced = "prepare" in ctl  # the advanced step: the MPC solve after the setpoint
    mpc = ctl["prepare"] if advanced else ctl["solve"]
    mpc_p99 = mpc["p99_ms"]
    s2a_p99 = sim["sense_to_actuate"]["p99_ms"]
    # A probe without real-time priority waits behind the stack: it excuses nothing then.
    slow = host.episodes if host.summary["fifo"] else []
    by_host = [bool(stolen or overlaps(slow, a, b)) for a, b, stolen in sim["missed_periods"]]
    return {
        "machine": machine(),
        "hop_p50_ms": est["hop_imu"]["p50_ms"],
        "hop_p99_ms": est["hop_imu"]["p99_ms"],
        "sense_to_actuate_p50_ms": sim["sense_to_actuate"]["p50_ms"],
        "sense_to_actuate_p99_ms": s2a_p99,
        "mpc_p50_ms": mpc["p50_ms"],
        "mpc_p99_ms": mpc_p99,
        "advanced_step": advanced,
        "answer_p50_ms": ctl["solve"]["p50_ms"],
        "answer_p99_ms": ctl["solve"]["p99_ms"],
        "planned_steps": ctl.get("planned_steps", 0),
        "adapt_p99_ms": stats["adapter"]["update"]["p99_ms"],
        # Where sense-to-actuate goes, stage by stage in path order (p50/p99 each).
        "stages_ms": {
            name: [round(st[key]["p50_ms"], 3), round(st[key]["p99_ms"], 3)]
            for name, st, key in (
                ("sim_publish", sim, "publish_lag"),
                ("hop_imu", est, "hop_imu"),
                ("estimator", est, "process"),
                ("hop_state", ctl, "hop_state"),
                ("controller", ctl, "react"),
                ("hop_setpoint", sim, "hop_setpoint"),
            )
        },
        # The conditions the numbers were taken under (a service without the privilege
        # runs under the normal policy and lets idle CPUs sleep: expect longer tails).
        "realtime": {
            name: {
                "policy": stats[name].get("scheduling", {}).get("policy", "normal"),
                "cpu_wakeup_latency_us": _wakeup(stats[name]),
            }
            for name in ("sim", "estimator", "controller")
        },
        "gc_pause_max_ms": max(
            st.get("gc_pauses", {}).get(f"gen{g}", {}).get("max_ms", 0.0)
            for st in stats.values()
            for g in range(3)
        ),
        "rate_hz": (steps - 1) / wall if wall > 0 else 0.0,
        "target_rate_hz": rate,
        "missed_deadlines": sim["missed_deadlines"],
        "missed_deadlines_outside_host_slowdowns": by_host.count(False),
        "host": {
            "slow_intervals": host.summary["episodes"],
            "slow_s": host.summary["slow_s"],
            "steal_s": sim.get("host_steal_s"),
            "stolen_periods": sim["stolen_periods"],
            "missed_deadlines_in_host_slowdowns": by_host.count(True),
            "probe_unit_ms": host.summary["unit_ms"],
            "probe_realtime_priority": host.summary["fifo"],
        },
        "method": method,
        "ready_s": result["ready_s"],
        "control_steps": steps,
        "duration_s": duration,
        "crashed": bool(sim["crashed"]),
        "exit_codes": result["codes"],
        "targets_met": {
            "hop_p99_le_1ms": est["hop_imu"]["p99_ms"] <= 1.0,
            "sense_to_actuate_p99_le_10ms": s2a_p99 <= 10.0,
            "sense_to_actuate_p99_le_mpc_p99_plus_3ms": s2a_p99 <= mpc_p99 + 3.0,
            "zero_missed_deadlines": sim["missed_deadlines"] == 0,
        },
    }
