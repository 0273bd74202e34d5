"""Simulator service: the MuJoCo quadrotor impersonating the vehicle and the mocap system.

Publishes ``mocap`` (frames with the emulated latency, noise and drops of
:class:`simulator.MocapConfig`; ``capture_stamp`` = capture time, ``stamp`` = arrival
time) and, once per control period, one ``imu`` sample (the latest gyro reading) that marks
the control instant; accepts ``setpoint``; emits ``event`` (payload release, timeouts,
crash). Flies the scenario of the plan options (take-off, hover, two figure-eight laps) and
releases the payload at ``--release`` of the first lap (jittered per seed like the
in-process evaluation) or on a ``release_payload`` command.

Clock modes (design §3):

- ``--lockstep``: simulated time. At each control instant ``t_k`` the simulator publishes
  the frames that have arrived by ``t_k`` and the imu sample stamped ``t_k``, then waits
  until the setpoint answering ``t_k`` (same stamp) arrives, or ``--step-timeout`` elapses
  (the last setpoint is then held and the timeout counted), applies it and advances one
  control period. Deterministic for a given seed.
- realtime (default): wall clock. Physics advances in ``--substep`` chunks paced to
  ``time.monotonic()``; frames are published as they arrive; the latest setpoint is
  zero-order held from the chunk after it arrives. The vehicle first hovers at its start
  pose for ``--preroll`` seconds and until setpoints stream (PX4 engages offboard control
  only on a setpoint stream); then a ``start`` command carries the stamp at which the
  mission clock starts. A flight control instant whose setpoint has not arrived before the
  next instant is a missed deadline (pre-roll instants are ``startup_ticks``). Stamps are
  ``time.monotonic()``-based.

The vehicle starts at rest on its start pose: the first mocap frame (captured at ``t = 0``)
is published before the first control instant, so the estimator starts initialised.
``--truth-state`` (diagnostic) publishes the ground-truth state at each control instant
instead of leaving estimation to the estimator (run without it): the loop then sees what
the in-process evaluation sees. Ground truth goes to ``<out>/truth.csv`` (the flight-log
columns of design §5 plus ``ref_px, ref_py, ref_pz`` and ``released``), statistics to
``<out>/stats/sim.json``.
"""

from __future__ import annotations

import csv
import math
import threading
import time
from pathlib import Path

import numpy as np

from services import runtime
from services.messages import Command, Event, Imu, Mocap, Setpoint, State

MAX_GYRO = 99.0
FLIGHT_COLUMNS = ("t", "px", "py", "pz", "vx", "vy", "vz", "qw", "qx", "qy", "qz",
                  "wx", "wy", "wz", "u0", "u1", "u2", "u3")
#: Position error [m] or height [m] at which a flight counts as crashed and stops.
CRASH_ERROR_M = 2.0
CRASH_HEIGHT_M = 0.02


class SimNode(runtime.Service):
    """Simulator: MuJoCo quadrotor + motion capture on the bus."""

    name = "sim"

    def setup(self, bus) -> None:
        from benchmarks.quadrotor_closedloop import DT, reference
        from simulator import QuadrotorSim

        a = self.args
        self.scen = runtime.scenario(a)
        self.trial = runtime.trial(a.seed)
        self.period = 1.0 / a.rate
        t_end = a.duration if a.duration is not None else self.scen.t_end
        self.n_steps = math.ceil(t_end / self.period - 1e-9) + 1
        self.k_release = -1
        if a.release >= 0:
            self.k_release = round(self.scen.t_release / self.period) + self.trial.release_jitter
        # Reference positions at the control instants (crash detection, truth log).
        n_ref = math.ceil(self.n_steps * self.period / DT) + 2
        x_ref, _ = reference(self.scen, n_ref, 0)
        self._ref_t = np.arange(x_ref.shape[0]) * DT
        self._ref_p = np.asarray(x_ref[:, :3], dtype=float)
        self.sim = QuadrotorSim(payload_mass=self.scen.payload_g / 1000.0,
                                cable_length=self.scen.cable_length_m,
                                seed=self.trial.sim_seed)
        self.sim.reset(np.asarray(self.scen.start) + self.trial.start_offset)
        self._cond = threading.Condition()
        self._setpoints: dict[float, Setpoint] = {}
        self._latest: Setpoint | None = None
        self._tick_wall: dict[float, float] = {}
        self._answered: set[float] = set()
        self._s2a: list[tuple[float, float]] = []
        self._flight_stamp = -math.inf  # stamp of the first mission tick
        self._release_cmd = False
        self._gyro = np.zeros(3)
        self.rows: list[list[float]] = []
        self.stats.update(steps=0, timeouts=0, missed_deadlines=0, released_at=None,
                          crashed=False, mode="lockstep" if a.lockstep else "realtime",
                          rate_hz=a.rate)
        self.pub_mocap = bus.publisher("mocap")
        self.pub_imu = bus.publisher("imu")
        bus.subscribe("setpoint", self.on_setpoint)

    # -- inputs
    def on_setpoint(self, sp: Setpoint) -> None:
        now = self.now()
        with self._cond:
            self._setpoints[sp.stamp] = sp
            if self._latest is None or sp.stamp >= self._latest.stamp:
                self._latest = sp
            wall = self._tick_wall.get(sp.stamp)
            if wall is not None and sp.stamp not in self._answered:
                self._answered.add(sp.stamp)
                self._s2a.append((sp.stamp, now - wall))
            self._cond.notify_all()

    def on_command(self, cmd: Command) -> None:
        if cmd.name == "release_payload" and cmd.target in ("", self.name):
            self._release_cmd = True

    # -- helpers
    def _ref(self, t: float) -> np.ndarray:
        return np.array([np.interp(t, self._ref_t, self._ref_p[:, i]) for i in range(3)])

    def _publish_frames(self, frames, to_stamp) -> None:
        for f in frames:
            self.pub_mocap.put(Mocap(position=f.position, quaternion=f.quaternion,
                                     capture_stamp=to_stamp(f.stamp),
                                     stamp=to_stamp(f.arrival)))

    def _tick(self, stamp: float, gyro_samples) -> None:
        if gyro_samples:
            self._gyro = np.clip(gyro_samples[-1].omega, -MAX_GYRO, MAX_GYRO)
        with self._cond:
            self._tick_wall[stamp] = self.now()
        self.pub_imu.put(Imu(gyro=self._gyro, stamp=stamp))
        if self.args.truth_state:
            x = self.sim.state()
            x[6:10] /= np.linalg.norm(x[6:10])
            self.bus.put(State(x=x, meas_stamp=stamp, stamp=stamp))

    def _maybe_release(self, k: int, stamp: float) -> None:
        if (k == self.k_release or self._release_cmd) and self.sim.payload_attached:
            self._release_cmd = False
            if self.sim.release_payload():
                self.stats["released_at"] = self.sim.time
                self.event("info", "payload released", stamp=stamp, sim_time=self.sim.time,
                           step=k)

    def _record(self, u: np.ndarray, t: float | None = None) -> bool:
        """Log ground truth at flight time ``t``; returns False when the flight crashed."""
        x = self.sim.state()
        t = self.sim.time if t is None else t
        ref = self._ref(t)
        self.rows.append([t, *x, *u, *ref, float(not self.sim.payload_attached)])
        crashed = (np.linalg.norm(x[:3] - ref) > CRASH_ERROR_M or x[2] < CRASH_HEIGHT_M
                   or not np.all(np.isfinite(x)))
        if crashed:
            self.stats["crashed"] = True
            self.event("fault", "vehicle crashed or left the flight envelope: stopping",
                       "error", stamp=max(t, 0.0), sim_time=t)
        return not crashed

    def _wait_consumers(self) -> None:
        wanted = [s for s in self.args.wait_for.split(",") if s]
        if wanted:
            self.log.info("waiting for %s", wanted)
            self.bus.wait_alive(wanted, timeout=self.args.ready_timeout)

    # -- loops
    def main(self) -> None:
        self._wait_consumers()
        t0 = time.perf_counter()
        try:
            if self.args.lockstep:
                self._lockstep()
            else:
                self._realtime()
        finally:
            self.stats["wall_s"] = time.perf_counter() - t0
        self.event("info", "flight finished", stamp=max(self._last_stamp, 0.0),
                   steps=self.stats["steps"])

    _last_stamp = 0.0

    def _lockstep(self) -> None:
        sim = self.sim
        u = sim.setpoint
        for k in range(self.n_steps):
            if self.stop.is_set():
                break
            t = k * self.period
            self._last_stamp = t
            self._maybe_release(k, t)
            first = k == 0
            frames = sim.mocap.read(math.inf) if first else sim.read_mocap()
            gyro = sim.gyro.read(math.inf) if first else sim.read_gyro()
            self._publish_frames(frames, float)
            self._tick(t, gyro)
            with self._cond:
                ok = self._cond.wait_for(lambda t=t: t in self._setpoints or self.stop.is_set(),
                                         self.args.step_timeout)
                sp = self._setpoints.pop(t, None)
                self._setpoints = {s: v for s, v in self._setpoints.items() if s > t}
            if sp is not None:
                u = sp.u
            elif not self.stop.is_set():
                self.stats["timeouts"] += 1
                self.event("deadline_miss", f"no setpoint for t={t:.3f} within "
                           f"{self.args.step_timeout} s: holding the last one", "warning",
                           stamp=t, step=k, ok=bool(ok))
            u_applied = sim.set_setpoint(u)
            if not self._record(u_applied):
                break
            sim.step(self.period)
            self.stats["steps"] += 1

    def _realtime(self) -> None:
        sim = self.sim
        sub = self.args.substep
        epoch = self.now()
        self.stats["epoch"] = epoch

        def mono(t_sim: float) -> float:
            return epoch + t_sim

        n, t_next, prev_tick, applied = 0, 0.0, None, None
        k = -1  # flight step; negative during the pre-roll
        t_start = 0.0
        u = sim.setpoint
        while not self.stop.is_set() and k < self.n_steps - 1:
            t_sim = sim.time
            self._publish_frames(sim.mocap.read(math.inf) if n == 0 else sim.read_mocap(), mono)
            if t_sim >= t_next - 1e-9:
                with self._cond:
                    engaged = self._latest is not None
                    missed = prev_tick is not None and prev_tick not in self._answered
                if k >= 0 and missed:
                    self.stats["missed_deadlines"] += 1
                elif missed:
                    self.stats["startup_ticks"] = self.stats.get("startup_ticks", 0) + 1
                stamp = self.now()
                if k < 0 and engaged and t_sim >= self.args.preroll:
                    # Setpoints stream (the loop is engaged, as PX4 requires before
                    # offboard control): start the mission clock at this instant.
                    k, t_start = 0, t_sim
                    self.bus.put(Command(name="start", args={"t0": stamp}, stamp=stamp))
                    self._flight_stamp = stamp
                    self.stats["preroll_s"] = t_sim
                elif k >= 0:
                    k += 1
                if k >= 0:
                    self._maybe_release(k, stamp)
                self._tick(stamp, sim.gyro.read(math.inf) if n == 0 else sim.read_gyro())
                self._last_stamp = stamp
                prev_tick = stamp
                if k >= 0:
                    if not self._record(u, t_sim - t_start):
                        break
                    self.stats["steps"] = k + 1
                n += 1
                t_next += self.period
            with self._cond:
                latest = self._latest
            if latest is not None and latest is not applied:
                u = sim.set_setpoint(latest.u)
                applied = latest
            sim.step(sub)
            delay = mono(sim.time) - self.now()
            if delay > 0:
                self.stop.wait(delay)  # pacing to the wall clock, not synchronisation
            elif delay < -0.5:
                self.stats["overruns"] = self.stats.get("overruns", 0) + 1

    def teardown(self) -> None:
        s2a = [v for stamp, v in self._s2a if stamp >= self._flight_stamp]
        self.stats["sense_to_actuate"] = runtime.percentiles_ms(s2a)
        self.stats["s2a_samples_ms"] = [1e3 * v for v in s2a]
        self.stats["k_release"] = self.k_release
        if self.out is not None:
            path = Path(self.out) / "truth.csv"
            path.parent.mkdir(parents=True, exist_ok=True)
            with path.open("w", newline="") as f:
                w = csv.writer(f)
                w.writerow([*FLIGHT_COLUMNS, "ref_px", "ref_py", "ref_pz", "released"])
                w.writerows(self.rows)


def _extra(p) -> None:
    runtime.add_plan_arguments(p)
    p.add_argument("--step-timeout", type=float, default=5.0,
                   help="lockstep: longest wait for a setpoint before holding the last [s]")
    p.add_argument("--preroll", type=float, default=1.0,
                   help="realtime: hover this long at the start pose before the mission [s]")
    p.add_argument("--substep", type=float, default=0.005,
                   help="realtime: physics chunk between setpoint checks [s]")
    p.add_argument("--wait-for", default="estimator,adapter,controller",
                   help="comma-separated services that must be alive before take-off")
    p.add_argument("--truth-state", action="store_true",
                   help="diagnostic: publish the ground-truth state (run without the "
                        "estimator; this is what the in-process evaluation controls on)")
    p.add_argument("--ready-timeout", type=float, default=600.0,
                   help="longest wait for those services [s]")


def main(argv: list[str] | None = None) -> int:
    return runtime.main_for(SimNode, argv, _extra)


__all__ = ["FLIGHT_COLUMNS", "Event", "SimNode", "main"]
