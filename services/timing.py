"""What a service measures and asks of the host for its timing: latency percentiles in
bounded memory, the garbage collector's pauses, ``SCHED_FIFO`` for the sense-to-actuate
path and a CPU wake-up latency request (PM QoS). :class:`services.runtime.Service` applies
them; the services report them in ``<out>/stats/<name>.json``."""

from __future__ import annotations

import gc
import logging
import math
import os
import random
import struct
import time
from array import array
from collections.abc import Sequence
from typing import Any

import numpy as np

log = logging.getLogger("arcade.service")


def percentiles_ms(samples_s: Sequence[float]) -> dict[str, float]:
    """p50/p99/max of latencies given in seconds, in ms (empty -> NaN-free zeros)."""
    if not len(samples_s):
        return {"n": 0, "p50_ms": 0.0, "p99_ms": 0.0, "max_ms": 0.0}
    a = np.asarray(samples_s) * 1e3
    return {
        "n": int(a.size),
        "p50_ms": float(np.median(a)),
        "p99_ms": float(np.percentile(a, 99)),
        "max_ms": float(a.max()),
    }


class LatencySamples:
    """Per-message latencies of a service that may run for hours, in bounded memory.

    Every sample is kept up to ``cap``; after that a uniform random subset of ``cap`` of
    all samples so far (reservoir sampling, algorithm R), so the percentiles stay unbiased.
    The count and the maximum are exact. A stack left running between flights (the PX4
    profile) sees 100-240 mocap frames a second: unbounded lists grew by megabytes an hour.
    """

    def __init__(self, cap: int = 100_000, seed: int = 0, skip: int = 0) -> None:
        self.cap = cap
        self._skip = skip  # the first samples (a first call that still warms up) left out
        self.n = 0
        self.max = -math.inf
        self._kept = array("d")
        self._rng = random.Random(seed)

    def append(self, value_s: float) -> None:
        if self._skip:
            self._skip -= 1
            return
        self.n += 1
        self.max = max(self.max, value_s)
        if len(self._kept) < self.cap:
            self._kept.append(value_s)
        else:
            j = self._rng.randrange(self.n)
            if j < self.cap:
                self._kept[j] = value_s

    def __len__(self) -> int:
        return self.n

    def summary(self) -> dict[str, float]:
        """:func:`percentiles_ms` of the kept samples, with the exact count and maximum, and
        ``kept``: how many samples the percentiles are of."""
        out = percentiles_ms(self._kept)
        if self.n:
            out.update(n=self.n, max_ms=1e3 * self.max)
        out["kept"] = len(self._kept)
        return out

    def samples_ms(self) -> list[float]:
        """The kept samples in ms (in arrival order until ``cap`` samples came)."""
        return [1e3 * v for v in self._kept]


class GcPauses:
    """Durations of the garbage collector's pauses, per generation, from construction to
    :meth:`close` (a pause stalls the whole process, hence its control path)."""

    def __init__(self) -> None:
        self._t0 = 0.0
        self.pauses: dict[int, list[float]] = {0: [], 1: [], 2: []}
        gc.callbacks.append(self._callback)

    def _callback(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self._t0 = time.perf_counter()
        else:
            self.pauses[info["generation"]].append(time.perf_counter() - self._t0)

    def close(self) -> None:
        if self._callback in gc.callbacks:
            gc.callbacks.remove(self._callback)

    def summary(self) -> dict[str, Any]:
        return {
            f"gen{g}": {"n": len(v), "max_ms": 1e3 * max(v, default=0.0), "total_ms": 1e3 * sum(v)}
            for g, v in self.pauses.items()
        }


def realtime_scheduling(priority: int, log: logging.Logger = log) -> dict[str, Any]:
    """Put every thread of this process (main, Zenoh's, XLA's) under ``SCHED_FIFO`` at
    ``priority``; threads started later inherit it. Returns what was applied.

    Why: on a host shared with the adapter's updates, the recorder and the rest of the
    machine, a sense-to-actuate path under the fair scheduler waits behind them for CPU; under
    SCHED_FIFO it preempts them. Only the sleeping/blocking services of that path get it
    (none of them spins), and the kernel's RT throttling keeps 5 % for everything else.
    Applied after warm-up, so that XLA's compilation does not starve the other services.
    """
    param = os.sched_param(priority)
    tids = (
        [int(t) for t in os.listdir("/proc/self/task")] if os.path.isdir("/proc/self/task") else [0]
    )
    done, errors = 0, []
    for tid in tids:
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, param)
            done += 1
        except ProcessLookupError:
            continue  # a thread that ended meanwhile
        except (OSError, AttributeError) as err:
            errors.append(str(err))
    if errors:
        log.warning(
            "SCHED_FIFO %d refused for %d of %d threads (%s): normal scheduling, "
            "expect more latency jitter",
            priority,
            len(errors),
            len(tids),
            errors[0],
        )
    else:
        log.info("SCHED_FIFO priority %d on %d threads", priority, done)
    return {
        "policy": "fifo" if not errors else "partial" if done else "normal",
        "priority": priority,
        "threads": done,
        "refused": len(errors),
    }


def cpu_wakeup_latency(
    us: int, log: logging.Logger = log, device: str = "/dev/cpu_dma_latency"
) -> tuple[int | None, dict[str, Any]]:
    """Request a CPU wake-up latency of at most ``us`` microseconds (Linux PM QoS); returns
    the descriptor that holds the request (close it to withdraw) and what was applied.

    Why: between two control periods the CPUs fall idle, and waking an idle CPU (on a
    virtual machine a halted vCPU) adds a few hundred microseconds, at random, to every
    bus hop and cold step of the sense-to-actuate path. With ``0`` idle CPUs poll instead
    (the usual setting of a realtime host); the kernel keeps the request as long as the
    descriptor is open, the strictest request of all processes applies.
    """
    try:
        fd = os.open(device, os.O_WRONLY)
    except OSError as err:
        log.warning(
            "CPU wake-up latency request refused (%s): idle CPUs may sleep deeply, "
            "expect more latency jitter",
            err,
        )
        return None, {"requested_us": us, "applied": False, "error": str(err)}
    try:
        os.write(fd, struct.pack("i", us))
    except OSError as err:
        os.close(fd)
        log.warning("CPU wake-up latency request of %d us refused (%s)", us, err)
        return None, {"requested_us": us, "applied": False, "error": str(err)}
    log.info("CPU wake-up latency <= %d us requested (PM QoS)", us)
    return fd, {"requested_us": us, "applied": True}
