"""Process-level helpers of the services: realtime scheduling, CPU wake-up latency,
garbage-collector pauses, and what a service imports at start-up."""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import struct
import subprocess
import sys
import threading

import pytest

from services import timing


def _policies() -> dict[int, int]:
    return {tid: policy for tid, (policy, _) in _scheduling().items()}


def _scheduling() -> dict[int, tuple[int, int]]:
    """Policy and priority of every thread of this process."""
    out = {}
    for t in os.listdir("/proc/self/task"):
        with contextlib.suppress(ProcessLookupError):  # a thread that ended meanwhile
            out[int(t)] = (os.sched_getscheduler(int(t)), os.sched_getparam(int(t)).sched_priority)
    return out


def test_realtime_scheduling_covers_every_thread_or_says_it_did_not(caplog):
    """Every thread (those started before the call too) runs under SCHED_FIFO, or the call
    reports and logs what was refused: never a silent fallback."""
    release = threading.Event()
    worker = threading.Thread(target=release.wait, daemon=True)
    worker.start()
    before = _scheduling()
    try:
        with caplog.at_level(logging.INFO, logger=timing.log.name):
            result = timing.realtime_scheduling(1)
        after = _policies()
        assert result["priority"] == 1
        if result["refused"] == 0:
            assert result["policy"] == "fifo" and result["threads"] == len(after)
            assert all(p == os.SCHED_FIFO for p in after.values()), after
            assert worker.native_id in after and after[worker.native_id] == os.SCHED_FIFO
        else:  # unprivileged: the normal policy stays and a warning says so
            assert result["policy"] in ("normal", "partial")
            assert any(
                r.levelno == logging.WARNING and "SCHED_FIFO" in r.getMessage()
                for r in caplog.records
            )
    finally:
        for tid, (policy, priority) in before.items():
            with contextlib.suppress(OSError):  # ended meanwhile: checked below
                os.sched_setscheduler(tid, policy, os.sched_param(priority))
        release.set()
        worker.join()
    after = _scheduling()
    assert all(after[t] == before[t] for t in before if t in after), (before, after)


def test_gc_pauses_are_measured_per_generation():
    pauses = timing.GcPauses()
    try:
        gc.collect(2)
        gc.collect(0)
        summary = pauses.summary()
    finally:
        pauses.close()
    assert summary["gen2"]["n"] >= 1 and summary["gen0"]["n"] >= 1
    assert summary["gen2"]["max_ms"] > 0.0
    assert summary["gen2"]["total_ms"] >= summary["gen2"]["max_ms"]
    assert pauses._callback not in gc.callbacks


def test_cpu_wakeup_latency_request_is_held_until_closed_or_refused_aloud(tmp_path, caplog):
    """The PM QoS request writes the latency as the kernel's binary int32 and stays in
    force while the returned descriptor is open; a device that cannot be opened gives a
    warning and ``applied: False``, never a silent fallback."""
    device = tmp_path / "cpu_dma_latency"
    device.write_bytes(b"")
    fd, result = timing.cpu_wakeup_latency(0, device=str(device))
    try:
        assert fd is not None and result == {"requested_us": 0, "applied": True}
        assert os.fstat(fd).st_ino == device.stat().st_ino  # the request lives with this fd
    finally:
        os.close(fd)
    assert device.read_bytes() == struct.pack("i", 0)
    with caplog.at_level(logging.WARNING, logger=timing.log.name):
        fd, result = timing.cpu_wakeup_latency(5, device=str(tmp_path / "missing"))
    assert fd is None and result["applied"] is False and result["requested_us"] == 5
    assert any("wake-up latency" in r.getMessage() for r in caplog.records)


def test_latency_samples_are_exact_below_the_cap():
    values = [0.001 * (i % 37) for i in range(1000)]
    lat = timing.LatencySamples(cap=1000)
    for v in values:
        lat.append(v)
    assert lat.summary() == {**timing.percentiles_ms(values), "kept": 1000}
    assert lat.samples_ms() == [1e3 * v for v in values]  # in arrival order


def test_latency_samples_stay_bounded_and_unbiased_over_a_long_run():
    """A drifting latency (0 .. 1 s over the run): the kept samples are a uniform subset of
    the whole run, not its first or last ``cap``, so the median is the run's (0.5 s);
    count and maximum are exact, whenever the maximum came."""
    n, cap = 200_000, 5_000
    lat = timing.LatencySamples(cap=cap, seed=3)
    for i in range(n):
        lat.append(i / n)
    lat.append(7.0)  # one outlier after the cap: exact max, at most one kept sample
    s = lat.summary()
    assert s["n"] == n + 1 and s["kept"] == cap and len(lat.samples_ms()) == cap
    assert s["max_ms"] == 7000.0
    # Binomial standard deviation of a sample median of 5000: 7 ms.
    assert abs(s["p50_ms"] - 500.0) < 25.0
    assert abs(s["p99_ms"] - 990.0) < 10.0


def test_latency_samples_skip_the_warm_up():
    lat = timing.LatencySamples(skip=1)
    for v in (5.0, 0.002, 0.004):
        lat.append(v)
    assert lat.summary() == {"n": 2, "p50_ms": 3.0, "p99_ms": 3.98, "max_ms": 4.0, "kept": 2}
    assert timing.LatencySamples().summary() == {
        "n": 0, "p50_ms": 0.0, "p99_ms": 0.0, "max_ms": 0.0, "kept": 0
    }  # fmt: skip


def test_the_services_start_without_importing_scipy():
    """The simulator, the adapter and the controller import the closed-loop control library
    at start-up; SciPy's interpolation (~0.7 s of import per process on a slow CPU) is for
    the offline data only, so no service may pull it in."""
    modules = (
        "services.sim_node",
        "services.estimator",
        "services.adapter",
        "services.controller",
        "services.recorder",
        "arcade_control.scenario",
        "arcade_control.stack",
        "arcade_control.step",
    )
    code = (
        f"import sys; import {', '.join(modules)}; "
        "print(sorted(m for m in sys.modules if m.startswith('scipy')))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip() == "[]", out.stdout


@pytest.mark.parametrize(
    ("module", "service"),
    [
        ("services.recorder", "Recorder"),
        ("services.px4_bridge", "Px4Bridge"),
        ("services.ros2_mirror", "Ros2Mirror"),
    ],
)
def test_services_that_compute_no_model_run_without_jax(module, service):
    """The recorder, the PX4 bridge and the ROS 2 mirror compute nothing with a model (the
    frames they change are NumPy's): their processes neither import JAX nor set it up
    (``main_for`` skips that for them), which saves about a second of CPU at every start."""
    import importlib

    assert getattr(importlib.import_module(module), service).uses_jax is False
    code = f"import sys; import {module}; print('jax' in sys.modules)"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip() == "False", out.stdout
