"""What the host did with this machine's CPUs: time stolen by the hypervisor.

On a virtual machine the host can take a vCPU away (``steal`` in ``/proc/stat``); no
scheduling policy inside the guest protects a deadline from that. A realtime flight records
how much was stolen while it flew, so that a missed deadline can be told from a slow step.
"""

from __future__ import annotations

import argparse
import bisect
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

__all__ = [
    "SlowdownProbe",
    "merge_intervals",
    "overlaps",
    "slow_units",
    "steal_s",
    "usual_duration",
]


def steal_s(path: str = "/proc/stat") -> float | None:
    """CPU time stolen from this machine so far, summed over its CPUs, in seconds (``None``
    where the kernel does not report it)."""
    try:
        with open(path) as f:
            fields = f.readline().split()
    except OSError:
        return None
    if len(fields) < 9 or fields[0] != "cpu":
        return None
    return int(fields[8]) / os.sysconf("SC_CLK_TCK")


# --------------------------------------------------------------------------- slowdowns
#
# Measured on the 2-core virtual machine the tests run on: every second or two, for some
# 10-80 ms, a fixed unit of CPU work takes 3 to 20 times its usual time, then recovers
# gradually, with no steal counted and even under SCHED_FIFO; a thread that only sleeps
# is not delayed. A realtime loop cannot meet a deadline through that, so a flight records
# when it happened, as it records steal.

#: Where one probe process per CPU writes what it saw (``probe-<cpu>.json``).
_PROBE_FILE = "probe-{cpu}.json"


class SlowdownProbe:
    """Run a small fixed unit of work every ``period_s`` on every CPU, at the highest
    real-time priority the process may take (nothing in this machine preempts it), in one
    child process per CPU, and report the intervals in which that unit took more than
    ``factor`` times its usual duration (the 20th percentile over the run): the times at
    which the machine itself ran slowly. Costs about 2 % of each CPU (a 0.07-0.09 ms unit
    every 5 ms).

    Without the privilege for real-time priority (``summary["fifo"]`` false) the probe
    runs under the normal policy and also measures the load of the guest itself: its
    intervals then say nothing about the host.

    Use as a context manager around what it should watch; :attr:`episodes` (monotonic
    ``[start, end]`` seconds, merged over the CPUs) and :attr:`summary` are set on exit.
    """

    def __init__(self, folder: str | os.PathLike, period_s: float = 0.005, factor: float = 3.0):
        self.folder = Path(folder)
        self.period_s = period_s
        self.factor = factor
        self.episodes: list[list[float]] = []
        self.summary: dict[str, Any] = {}
        self._procs: list[subprocess.Popen] = []

    def __enter__(self) -> SlowdownProbe:
        self.folder.mkdir(parents=True, exist_ok=True)
        cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else [0]
        env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
        for cpu in cpus:
            out = self.folder / _PROBE_FILE.format(cpu=cpu)
            args = [sys.executable, "-m", "arcade_io.hostcpu", "--cpu", str(cpu), "--out", str(out)]
            args += ["--period", str(self.period_s), "--factor", str(self.factor)]
            self._procs.append(
                subprocess.Popen(args, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
            )
        for proc in self._procs:  # each says "ready" once warmed up
            if proc.stdout is None or proc.stdout.readline().strip() != b"ready":
                self._stop()
                raise RuntimeError("the host slowdown probe did not start")
        return self

    def _stop(self) -> list[int]:
        codes = []
        for proc in self._procs:
            if proc.stdin is not None:
                proc.stdin.close()  # end of input: the probe writes what it saw and exits
        for proc in self._procs:
            try:
                codes.append(proc.wait(timeout=30))
            except subprocess.TimeoutExpired:
                proc.kill()
                codes.append(proc.wait())
        return codes

    def __exit__(self, exc_type: object, *exc: object) -> None:
        codes = self._stop()
        if exc_type is not None:  # what the block raised goes on, not the probe's report
            return
        if any(codes):
            raise RuntimeError(f"the host slowdown probe failed (exit codes {codes})")
        seen = [json.loads(p.read_text()) for p in sorted(self.folder.glob("probe-*.json"))]
        self.episodes = merge_intervals([e for s in seen for e in s["episodes"]])
        self.summary = {
            "cpus": len(seen),
            "fifo": all(s["fifo"] for s in seen),
            "unit_ms": [s["unit_ms"] for s in seen],
            "episodes": len(self.episodes),
            "slow_s": round(sum(b - a for a, b in self.episodes), 3),
        }


def merge_intervals(intervals: list[list[float]]) -> list[list[float]]:
    """Overlapping ``[start, end]`` intervals joined, in order."""
    merged: list[list[float]] = []
    for a, b in sorted(intervals):
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    return merged


def overlaps(episodes: list[list[float]], start: float, end: float) -> bool:
    """Whether ``[start, end]`` meets any of ``episodes`` (sorted, disjoint)."""
    i = bisect.bisect_left([b for _, b in episodes], start)
    return i < len(episodes) and episodes[i][0] <= end


def usual_duration(durations: list[float]) -> float:
    """The usual duration of a unit: the 20th percentile (0 without units)."""
    return sorted(durations)[len(durations) // 5] if durations else 0.0


def slow_units(
    starts: list[float], durations: list[float], factor: float, min_units: int = 2
) -> list[list[float]]:
    """The intervals of at least ``min_units`` consecutive units that each took more than
    ``factor`` times the 20th percentile of ``durations`` (from the first one's start to
    the last one's end): a sustained slowdown, not one interrupted unit."""
    if not durations:
        return []
    limit = factor * usual_duration(durations)
    runs: list[list[float]] = []
    run: list[int] = []
    for i, d in enumerate([*durations, 0.0]):
        if d > limit:
            run.append(i)
            continue
        if len(run) >= min_units:
            runs.append([starts[run[0]], starts[run[-1]] + durations[run[-1]]])
        run = []
    return runs


def _probe(cpu: int, out: Path, period: float, factor: float) -> int:
    import numpy as np

    fifo = False
    try:
        os.sched_setaffinity(0, {cpu})
        os.sched_setscheduler(
            0, os.SCHED_FIFO, os.sched_param(os.sched_get_priority_max(os.SCHED_FIFO))
        )
        fifo = True
    except (OSError, AttributeError):
        pass
    a = np.random.default_rng(cpu).random((40, 40)) * 0.01

    def unit() -> None:
        x = a
        for _ in range(6):
            x = np.tanh(x @ a)

    for _ in range(200):  # warm-up
        unit()
    done = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
    starts: list[float] = []
    durations: list[float] = []
    print("ready", flush=True)
    t_next = time.monotonic()
    while not done.is_set():
        s = time.monotonic()
        unit()
        durations.append(time.monotonic() - s)
        starts.append(s)
        t_next += period
        delay = t_next - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            t_next = time.monotonic()
    result = {
        "cpu": cpu,
        "fifo": fifo,
        "units": len(durations),
        "unit_ms": round(usual_duration(durations) * 1e3, 4),
        "episodes": slow_units(starts, durations, factor),
    }
    out.write_text(json.dumps(result))
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m arcade_io.hostcpu",
        description="One CPU's host slowdown probe (started by SlowdownProbe); runs until its "
        "standard input ends, then writes the slow intervals to --out.",
    )
    p.add_argument("--cpu", type=int, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--period", type=float, default=0.005)
    p.add_argument("--factor", type=float, default=3.0)
    a = p.parse_args(argv)
    return _probe(a.cpu, a.out, a.period, a.factor)


if __name__ == "__main__":
    sys.exit(main())
