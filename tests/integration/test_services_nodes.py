"""Single service processes on a private Zenoh hub: controller degradation, adapter restart."""

from __future__ import annotations

import collections
import json
import os
import queue
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh

from arcade_control.stack import adapter_learner
from services.adapter import DEFAULT_WEIGHTS
from services.bus import Bus, peer_config
from services.checkpoint import load_checkpoint, save_checkpoint
from services.messages import Setpoint, State

REPO = Path(__file__).resolve().parents[2]
TIMEOUT = 120.0  # start-up compiles; an upper bound for a loaded machine, never a sleep


def free_hub() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def start(name: str, hub: str, out: Path, *args: str) -> subprocess.Popen:
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    cmd = [sys.executable, "-m", "services", name, "--hub", hub, "--out", str(out), "--x64", *args]
    if name in ("adapter", "controller"):  # these tests read ours' beam and knobs
        cmd += ["--method", "ours"]
    log = (out / f"{name}.out").open("a")
    return subprocess.Popen(cmd, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)


def stop(p: subprocess.Popen) -> int:
    p.send_signal(signal.SIGINT)
    return p.wait(timeout=60)


def get(q: queue.Queue, what: str, pred=lambda m: True):
    deadline = time.monotonic() + 30.0
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            raise AssertionError(f"no {what}")
        try:
            m = q.get(timeout=left)
        except queue.Empty:
            raise AssertionError(f"no {what}") from None
        if pred(m):
            return m


def hover_state(stamp: float, z: float = 1.5) -> State:
    return State(
        x=np.r_[0.0, 0.0, z, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0], stamp=stamp, meas_stamp=stamp
    )


@pytest.mark.realtime
def test_controller_degrades_on_stale_state_and_rejects_garbage(tmp_path):
    hub = free_hub()
    proc = start("controller", hub, tmp_path, "--max-state-age", "0.2")
    setpoints: queue.Queue = queue.Queue()
    events: queue.Queue = queue.Queue()
    try:
        with Bus("default", "estimator", peer_config(hub)) as est:
            est.subscribe("setpoint", setpoints.put)
            est.subscribe("event", events.put)
            est.wait_alive(["controller"], timeout=TIMEOUT)

            t0 = time.monotonic()
            seq = est.put(hover_state(t0))
            sp = get(setpoints, "setpoint", lambda m: m.state_seq == seq)
            # No model on the bus: nominal MPC, announced by an event.
            assert sp.mode == "nominal_model"
            assert np.all(np.isfinite(sp.u)) and 4.0 < sp.thrust < 8.0
            get(events, "degraded event", lambda e: e.kind == "degraded")

            # A state that is 1 s old on arrival: level hover, and an event says so. Its
            # thrust: the mean of the tracking thrusts so far (level states), i.e. the one
            # tracked thrust, not the nominal hover thrust it starts from.
            tracked = sp.thrust
            # The state is the estimator's (the only source the controller takes): its
            # late stamp must still be newer than its first, so the clock passes t0 + 1 s.
            time.sleep(max(0.0, t0 + 1.05 - time.monotonic()))
            late_seq = est.put(hover_state(time.monotonic() - 1.0))
            sp = get(setpoints, "hover setpoint", lambda m: m.state_seq == late_seq)
            assert sp.mode == "hover"
            np.testing.assert_allclose(sp.rates, 0.0, atol=1e-12)
            assert sp.thrust == pytest.approx(tracked, rel=1e-6)
            ev = get(events, "hover event", lambda e: e.kind == "degraded" and "hover" in e.text)
            assert "old" in ev.text

            # Garbage never becomes a setpoint: a non-finite state is rejected.
            bad = hover_state(time.monotonic()).to_wire()
            bad["x"][2] = float("nan")
            bad["seq"], bad["src"] = 99, "estimator/raw"
            raw = est.session.declare_publisher(est.key("state"))  # the estimator's session
            raw.put(msgpack.packb(bad), source_info=zenoh.SourceInfo(raw.id, 99))
            # Fresh state again: the MPC takes over again (nominal model) and says so.
            seq = est.put(hover_state(time.monotonic()))
            sp = get(setpoints, "setpoint", lambda m: m.state_seq == seq)
            assert sp.mode == "nominal_model"
            get(
                events,
                "mode event",
                lambda e: e.kind == "degraded" and e.data.get("mode") == "nominal_model",
            )
    finally:
        code = stop(proc)
    assert code == 0
    stats = json.loads((tmp_path / "stats" / "controller.json").read_text())
    assert stats["rejects"] == {"non_finite": 1}
    assert stats["setpoints"] == 3 and stats["hover"] == 1


def test_adapter_flies_the_calibrated_noise_and_its_beta():
    """The adapter's beam: the calibrated sigma^2 (Appendix D 0.1) with the beta tuned at
    it, not the in-process evaluation's tuned pair (``arcade_control.stack.stack_knobs``)."""
    from arcade_control.stack import STACK_BETA

    learner, _ = adapter_learner(DEFAULT_WEIGHTS, np.float64)
    np.testing.assert_allclose(np.asarray(learner.config.sigma2), 0.1)  # one per output
    assert float(learner.config.beta) == pytest.approx(STACK_BETA)


def test_a_checkpoint_of_another_beam_layout_is_not_restored(tmp_path):
    """A checkpoint whose beam lacks a field of the current one (written by a version
    without the offline prior mean in the state) is refused, not half-loaded."""
    learner, _ = adapter_learner(DEFAULT_WEIGHTS, np.float64)
    beam = learner.beam
    old = collections.namedtuple("OldBeam", [f for f in beam._fields if f != "prior_mean"])
    save_checkpoint(tmp_path / "old.npz", old(*(getattr(beam, f) for f in old._fields)), {})
    assert load_checkpoint(tmp_path / "old.npz", beam, {}) is None
    save_checkpoint(tmp_path / "new.npz", beam, {})
    back = load_checkpoint(tmp_path / "new.npz", beam, {})
    np.testing.assert_array_equal(back.prior_mean, beam.prior_mean)


def test_adapter_checkpoint_round_trip(tmp_path):
    hub = free_hub()
    ckpt = tmp_path / "posterior.npz"
    # Lockstep: the adapter waits for the setpoint answering the previous state.
    args = ("--checkpoint", str(ckpt), "--checkpoint-every", "0", "--lockstep")
    models: queue.Queue = queue.Queue()
    rng = np.random.default_rng(0)
    with (
        Bus("default", "estimator", peer_config(hub)) as bus,
        Bus("default", "controller", peer_config(hub)) as ctl,
    ):
        bus.subscribe("model", models.put)
        # This test plays the controller too: while one is alive, the lockstep adapter
        # waits for the setpoint answering the previous state (sent after its model).
        ctl.declare_alive()

        proc = start("adapter", hub, tmp_path, *args)
        try:
            bus.wait_alive(["adapter"], timeout=TIMEOUT)
            t = time.monotonic()
            last = None
            for k in range(6):
                p = np.r_[0.01 * rng.standard_normal(2), 1.5 + 0.01 * k]
                x = np.r_[p, 0.0, 0.0, 0.2, 1.0, 0, 0, 0, 0, 0, 0]
                seq = bus.put(State(x=x, stamp=t + 0.05 * k, meas_stamp=t + 0.05 * k))
                last = get(models, "model", lambda m, seq=seq: m.state_seq == seq)
                ctl.put(Setpoint(u=[6.0, 0.0, 0.0, 0.0], state_seq=seq, stamp=t + 0.05 * k))
            assert last.step == 5  # five transitions learned
        finally:
            assert stop(proc) == 0
        learner, _ = adapter_learner(DEFAULT_WEIGHTS, np.float64)
        beam = load_checkpoint(ckpt, learner.beam, {})
        assert beam is not None and int(beam.step) == 5

        proc = start("adapter", hub, tmp_path, *args)
        try:
            bus.wait_alive(["adapter"], timeout=TIMEOUT)
            now = time.monotonic()
            seq = bus.put(
                State(
                    x=np.r_[0, 0, 1.5, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0],
                    stamp=now,
                    meas_stamp=now,
                )
            )
            restored = get(models, "model", lambda m: m.state_seq == seq)
        finally:
            assert stop(proc) == 0
    assert restored.step == 5
    assert "restored the posterior" in (tmp_path / "logs" / "adapter.log").read_text()
    np.testing.assert_array_equal(restored.theta, last.theta)
    np.testing.assert_array_equal(restored.theta_cov, last.theta_cov)
