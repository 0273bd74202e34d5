"""Simulator service: the MuJoCo quadrotor impersonating the vehicle and the mocap system.

Publishes ``mocap`` (frames of the vehicle and of a swinging payload with the emulated
latency, noise and drops of :class:`simulator.MocapConfig`, :mod:`services.sim_mocap`;
``capture_stamp`` = capture time, ``stamp`` = arrival time) and, once per control period,
one ``imu`` sample (the latest gyro reading) that marks the control instant; accepts
``setpoint``; emits ``event`` (payload release, with ``payload="released"`` in its data;
timeouts, crash). Flies the scenario of the plan options (take-off, hover, two
figure-eight laps) and releases the payload at ``--release`` of the first lap (jittered
per seed like the in-process evaluation) or on a ``release_payload`` command: at the first
control instant whose stamp is at or after the command's stamp (a command stamped in the
future releases at that time; lockstep stamps are simulated time).

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
  next instant is a missed deadline (pre-roll instants are ``startup_ticks``); one whose
  period the hypervisor took CPU time from this machine (``steal`` in ``/proc/stat``,
  10 ms resolution) is also counted in ``missed_deadlines_host_steal``, and
  ``stolen_periods`` counts the flight's periods with steal; ``missed_periods`` lists each
  missed period (its start and end on the monotonic clock, and whether steal was seen), to
  be set beside :class:`arcade_io.hostcpu.SlowdownProbe`'s record of when the machine
  itself ran slowly. Stamps are
  ``time.monotonic()``-based; a control instant is stamped with its sample instant (when
  the physics was there), not with the moment the loop got round to publishing it, so
  consecutive instants are exactly one period apart; sense-to-actuate latency counts from
  the sample instant.

Setpoint watchdog (the failsafe of a flight controller that loses its offboard link):
when no fresh setpoint has arrived for ``--failsafe-after`` seconds (realtime: wall clock
since the last setpoint's arrival, checked every physics chunk; lockstep: simulated time
since the control instant of the last setpoint, so a stale setpoint is held for at most
that long), the vehicle holds its position (a PD position loop on its own state, the
role of PX4's position controller, with the hover thrust of the mass it carries) and a
``failsafe`` event says so, with the measured delay. When setpoints answer
``--failsafe-resume`` consecutive control instants again, offboard control resumes
(``failsafe_cleared`` event). A (re)joining controller or adapter is sent the mission's
``start`` command again, so that it picks up the mission clock, with ``flying`` (whether
the vehicle flies the setpoints at that moment: a restarted adapter learns from them only
then).

The controller's failsafe (an ``event`` of kind ``failsafe`` from ``controller/...``: it
hovered open loop, without position feedback, for too long) engages the same position
hold while the mission runs, as a flight controller leaves offboard on it (lockstep: at
the control instant after the one whose setpoint carries the failsafe's reason, so that
the flight stays deterministic: the event itself travels at a lower priority than the
setpoints and may arrive steps later; realtime: on the next physics chunk). That hold
ends only after ``--failsafe-resume`` consecutive control instants answered by setpoints
not in ``hover`` mode (the controller keeps answering while it hovers, and those answers
fly open loop).

Mocap fault injection (``--mocap-fault``, repeatable; times are mission time in seconds):
``dropout@T+D`` (no frames captured in ``[T, T+D)``), ``freeze@T+D`` (the last pose before
``T`` is repeated with fresh stamps, as a tracker that lost the body does),
``outliers@T+D,p=P,m=M`` (each frame jumps by ``M`` m in a random direction with
probability ``P``), ``clockjump@T[+D],offset=S`` (the mocap clock is off by ``S`` s: both
stamps of the frames move). Counts go to the statistics (``mocap_faults``);
:mod:`services.sim_mocap` says which rigid bodies each fault hits.

The vehicle starts at rest on its start pose: the first mocap frame (captured at ``t = 0``)
is published before the first control instant, so the estimator starts initialised.
``--truth-state`` (diagnostic) publishes the ground-truth state at each control instant
instead of leaving estimation to the estimator (run without it): the loop then sees what
the in-process evaluation sees. Ground truth goes to ``<out>/truth.csv`` (the flight-log
columns of design §5 plus ``ref_px, ref_py, ref_pz``, ``released`` and ``failsafe``), one row
per control instant, written while flying (:mod:`services.csvlog`: a killed simulator leaves
all but the last second of it; a file that cannot be written raises a ``fault`` event, the
flight goes on, and ``unwritten_truth_rows`` counts what is lost), statistics to
``<out>/stats/sim.json``.
"""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import numpy as np

from arcade_control.scenario import trial
from arcade_io import flightlog, hostcpu
from arcade_io.traced import load_or_trace
from arcade_io.vehicle import PAYLOAD_RELEASED
from services import options, runtime, timing
from services.csvlog import StreamedCsv
from services.messages import Command, Event, Imu, Setpoint, State
from services.sim_failsafe import FailsafeHold
from services.sim_mocap import MocapStream
from services.sim_options import add_sim_arguments as _extra

MAX_GYRO = 99.0
FLIGHT_COLUMNS = flightlog.columns("quadrotor")
#: Position error [m] or height [m] at which a flight counts as crashed and stops.
CRASH_ERROR_M = 2.0
CRASH_HEIGHT_M = 0.02


class SimNode(FailsafeHold, runtime.Service):
    """Simulator: MuJoCo quadrotor + motion capture on the bus."""

    name = "sim"

    _on_ground = False  # landed on purpose (the PX4 vehicle's Land): not a crash
    _controller_failsafe: Event | None = None  # received, not yet acted on (realtime)
    _setpoint_failsafe = ""  # lockstep: the reason the last answer carried, acted on next

    def setup(self, bus) -> None:
        from arcade_control.nominal import CONTROL_DT as DT
        from arcade_control.scenario import flat_reference, reference_arguments
        from simulator import QuadrotorSim

        a = self.args
        self.scen = options.scenario(a)
        self.trial = trial(a.seed)
        self.period = 1.0 / a.rate
        t_end = a.duration if a.duration is not None else self.scen.t_end
        self.n_steps = math.ceil(t_end / self.period - 1e-9) + 1
        self.k_release = -1
        if a.release >= 0:
            self.k_release = round(self.scen.t_release / self.period) + self.trial.release_jitter
        # Reference positions at the control instants (crash detection, truth log).
        n_ref = math.ceil(self.n_steps * self.period / DT) + 2
        # Traced once and kept on disk (arcade_io.traced), as the controller does.
        ref_args = reference_arguments(self.scen, n_ref, 0)
        x_ref, _ = load_or_trace("reference", flat_reference, ref_args)(*ref_args)
        self._ref_t = np.arange(x_ref.shape[0]) * DT
        self._ref_p = np.asarray(x_ref[:, :3], dtype=float)
        self.sim = QuadrotorSim(
            payload_mass=self.scen.payload_g / 1000.0,
            cable_length=self.scen.cable_length_m,
            seed=self.trial.sim_seed,
            command_delay_s=a.command_delay,
        )
        self.stats["command_delay_s"] = a.command_delay
        self.sim.reset(np.asarray(self.scen.start) + self.trial.start_offset)
        self._cond = threading.Condition()
        self._setpoints: dict[float, Setpoint] = {}
        self._latest: Setpoint | None = None
        self._tick_wall: dict[float, float] = {}
        self._answered: set[float] = set()
        self._s2a = timing.LatencySamples()  # of the answers to the mission's instants
        self._steal0: float | None = None  # host steal time when the realtime loop began
        self._flight_stamp = -math.inf  # stamp of the first mission tick
        self._release_at = math.inf  # stamp of a release_payload command
        self._gyro = np.zeros(3)
        self.truth: StreamedCsv | None = None
        if self.out is not None:
            Path(self.out).mkdir(parents=True, exist_ok=True)
            self.truth = StreamedCsv(
                Path(self.out) / "truth.csv",
                [*FLIGHT_COLUMNS, "ref_px", "ref_py", "ref_pz", "released", "failsafe"],
                on_error=self._truth_lost,
            )
        # Setpoint watchdog: arrival (wall) of the newest setpoint; failsafe hold state.
        self._sp_wall = -math.inf
        self._t_last_sp = 0.0  # lockstep: control instant of the newest setpoint
        self._hold: np.ndarray | None = None  # hold position while in failsafe
        self._answered_run = 0
        self._mission0 = 0.0 if a.lockstep else math.inf  # sim time of the mission start
        self.mocap_out = MocapStream(
            bus, a.mocap_fault or [], self.trial.sim_seed, vehicle_body=a.mocap_body
        )
        self.stats.update(
            steps=0,
            timeouts=0,
            missed_deadlines=0,
            missed_deadlines_host_steal=0,
            missed_periods=[],
            stolen_periods=0,
            released_at=None,
            crashed=False,
            mode="lockstep" if a.lockstep else "realtime",
            rate_hz=a.rate,
            failsafes=[],
            controller_failsafes=0,
            controller_failsafes_ignored=0,
            mocap_faults=self.mocap_out.fault_counts,
        )
        self.pub_imu = bus.publisher("imu")
        self._sp_sub = bus.subscribe("setpoint", self.on_setpoint, source="controller")
        # Events come from several publishers, each with its own clock: no order check.
        bus.subscribe("event", self.on_event, check_order=False)
        self._publish_lag = timing.LatencySamples()  # sample instant -> imu put (realtime)
        bus.on_alive_change(self._on_alive)

    # -- inputs
    def on_setpoint(self, sp: Setpoint) -> None:
        now = self.now()
        with self._cond:
            self._sp_wall = now
            self._setpoints[sp.stamp] = sp
            if self._latest is None or sp.stamp >= self._latest.stamp:
                self._latest = sp
            wall = self._tick_wall.get(sp.stamp)
            if wall is not None and sp.stamp not in self._answered:
                self._answered.add(sp.stamp)
                if sp.stamp >= self._flight_stamp:
                    self._s2a.append(now - wall)
            self._cond.notify_all()

    def on_event(self, e: Event) -> None:
        # Noted only: the loop acts on it (this runs on the bus's thread, where the physics
        # must not be read nor a blocking event published).
        if e.kind == "failsafe" and e.src.startswith("controller/") and not self.args.lockstep:
            with self._cond:
                self._controller_failsafe = e

    def on_command(self, cmd: Command) -> None:
        if cmd.name == "release_payload" and cmd.target in ("", self.name):
            self.log.info("release_payload command received (stamp %.3f)", cmd.stamp)
            self._release_at = cmd.stamp

    def _on_alive(self, service: str, up: bool) -> None:
        """A controller or adapter that (re)joins after the mission started gets its clock
        again, and whether the vehicle flies the setpoints now (``flying``: not holding)."""
        if service in ("controller", "adapter") and up and math.isfinite(self._flight_stamp):
            args = {"t0": self._flight_stamp, "flying": self._hold is None}
            self.bus.put(Command(name="start", args=args, stamp=self.now()))

    # -- helpers
    def _ref(self, t: float) -> np.ndarray:
        return np.array([np.interp(t, self._ref_t, self._ref_p[:, i]) for i in range(3)])

    def _publish_frames(self, frames, to_stamp) -> None:
        self.mocap_out.publish(frames, to_stamp, lambda t: t - self._mission0)

    def _tick(self, stamp: float, gyro_samples, sampled: float | None = None) -> None:
        """Publish the control instant ``stamp``; sense-to-actuate latency counts from
        ``sampled`` (the wall-clock sample instant; default: now)."""
        if gyro_samples:
            self._gyro = np.clip(gyro_samples[-1].omega, -MAX_GYRO, MAX_GYRO)
        with self._cond:
            self._tick_wall[stamp] = self.now() if sampled is None else sampled
        self.pub_imu.put(Imu(gyro=self._gyro, stamp=stamp))
        if sampled is not None:
            self._publish_lag.append(self.now() - sampled)
        if self.args.truth_state:
            x = self.sim.state()
            x[6:10] /= np.linalg.norm(x[6:10])
            self.bus.put(State(x=x, meas_stamp=stamp, stamp=stamp))

    def _mission_started(self, stamp: float) -> None:
        """The mission clock starts at the control instant ``stamp``: sense-to-actuate counts
        the answers to the mission's instants only (not the pre-roll's)."""
        with self._cond:
            self._flight_stamp = stamp
            self._s2a = timing.LatencySamples()

    def _maybe_release(self, k: int, stamp: float) -> None:
        if (k == self.k_release or stamp >= self._release_at) and self.sim.payload_attached:
            self._release_at = math.inf
            if self.sim.release_payload():
                self.stats["released_at"] = self.sim.time
                self.event(
                    "info",
                    "payload released",
                    stamp=stamp,
                    sim_time=self.sim.time,
                    step=k,
                    payload=PAYLOAD_RELEASED,  # what a Foxglove drawing takes (the cable goes)
                )

    def _record(self, u: np.ndarray, t: float | None = None) -> bool:
        """Log ground truth at flight time ``t``; returns False when the flight crashed."""
        x = self.sim.state()
        t = self.sim.time if t is None else t
        ref = self._ref(t)
        if self.truth is not None:
            flags = [float(not self.sim.payload_attached), float(self._hold is not None)]
            self.truth.write(t, [t, *x, *u, *ref, *flags])
        # In failsafe the vehicle holds its position instead of following the reference.
        goal = ref if self._hold is None else self._hold
        crashed = (
            np.linalg.norm(x[:3] - goal) > CRASH_ERROR_M
            or (x[2] < CRASH_HEIGHT_M and not self._on_ground)
            or not np.all(np.isfinite(x))
        )
        if crashed:
            self._crashed(t)
        return not crashed

    def _crashed(self, t: float) -> None:
        self.stats["crashed"] = True
        self.event(
            "fault",
            "vehicle crashed or left the flight envelope: stopping",
            "error",
            stamp=max(t, 0.0),
            sim_time=t,
        )

    def _stepped_finite(self, t: float) -> bool:
        """After a physics step: a non-finite state is a crash (reported at flight time
        ``t``), caught before the next frame or sample is built from it."""
        if np.all(np.isfinite(self.sim.state())):
            return True
        self._crashed(t)
        return False

    def _prune(self, before: float) -> None:
        """Forget the per-tick bookkeeping of control instants older than ``before``."""
        with self._cond:
            self._setpoints = {s: v for s, v in self._setpoints.items() if s >= before}
            self._tick_wall = {s: v for s, v in self._tick_wall.items() if s >= before}
            self._answered = {s for s in self._answered if s >= before}

    def _wait_consumers(self) -> bool:
        """Wait for the ``--wait-for`` services; False if a stop request came first (a
        signal or a shutdown command is answered within 0.1 s, not after the timeout)."""
        wanted = [s for s in self.args.wait_for.split(",") if s]
        if not wanted:
            return True
        self.log.info("waiting for %s", wanted)
        deadline = time.monotonic() + self.args.ready_timeout
        while not self.stop.is_set():
            left = deadline - time.monotonic()
            try:
                self.bus.wait_alive(wanted, timeout=max(0.0, min(0.1, left)))
                return True
            except TimeoutError:
                if left <= 0.1:
                    missing = sorted(set(wanted) - self.bus.alive)
                    raise TimeoutError(
                        f"not alive after {self.args.ready_timeout:g} s: {missing}"
                    ) from None
        self.log.info("stop requested while waiting for %s: not flying", wanted)
        return False

    # -- loops
    def main(self) -> None:
        if not self._wait_consumers():
            return
        t0 = time.perf_counter()
        try:
            if self.args.lockstep:
                self._lockstep()
            else:
                self._realtime()
        finally:
            self.stats["wall_s"] = time.perf_counter() - t0
        self.event(
            "info", "flight finished", stamp=max(self._last_stamp, 0.0), steps=self.stats["steps"]
        )

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
                ok = self._cond.wait_for(
                    lambda t=t: t in self._setpoints or self.stop.is_set(), self.args.step_timeout
                )
                sp = self._setpoints.pop(t, None)
                self._setpoints = {s: v for s, v in self._setpoints.items() if s > t}
            if sp is not None:
                u = sp.u
                self._t_last_sp = t
                self._answered_run = self._answered_run + 1 if self._resumes(sp) else 0
                if self._hold is not None and self._answered_run >= self.args.failsafe_resume:
                    self._clear_failsafe(t)
            elif not self.stop.is_set():
                self.stats["timeouts"] += 1
                self._answered_run = 0
                since = t - self._t_last_sp
                if self._hold is None and since >= self.args.failsafe_after - 1e-9:
                    self._engage_failsafe(t, since)
                elif self._hold is None:
                    self.event(
                        "deadline_miss",
                        f"no setpoint for t={t:.3f} within "
                        f"{self.args.step_timeout} s: holding the last one",
                        "warning",
                        stamp=t,
                        step=k,
                        ok=bool(ok),
                    )
            # The failsafe an earlier answer carried; this one's is acted on at the next
            # instant, as a flight controller acts on it after the setpoint it came with.
            if self._setpoint_failsafe and not self.stop.is_set():
                self._on_controller_failsafe(
                    self._setpoint_failsafe, t, t - self._t_last_sp, flying=True
                )
            self._setpoint_failsafe = sp.failsafe if sp is not None else ""
            u_applied = self._hold_u() if self._hold is not None else sim.set_setpoint(u)
            if not self._record(u_applied):
                break
            if self._hold is None:
                sim.step(self.period)
            else:  # the hold loop runs at the physics-chunk rate, like the realtime one
                for _ in range(max(1, round(self.period / self.args.substep))):
                    self._hold_u()
                    sim.step(self.period / max(1, round(self.period / self.args.substep)))
            self.stats["steps"] += 1
            if not self._stepped_finite(sim.time):
                break

    def _realtime(self) -> None:
        sim = self.sim
        sub = self.args.substep
        epoch = self.now()
        self.stats["epoch"] = epoch
        self._steal0 = hostcpu.steal_s()

        def mono(t_sim: float) -> float:
            return epoch + t_sim

        n, t_next, prev_tick, applied = 0, 0.0, None, None
        steal_prev = self._steal0  # host steal at the previous control instant
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
                    answer = None if missed else self._setpoints.get(prev_tick)
                # Did the hypervisor take CPU time during the period that just ended?
                steal = hostcpu.steal_s()
                stolen = steal is not None and steal_prev is not None and steal > steal_prev
                steal_prev = steal
                if k >= 0 and stolen:
                    self.stats["stolen_periods"] += 1
                if k >= 0 and missed:
                    self.stats["missed_deadlines"] += 1
                    self.stats["missed_deadlines_host_steal"] += int(stolen)
                    # The missed period on the monotonic clock, for what else watched
                    # the machine then (arcade_io.hostcpu.SlowdownProbe).
                    self.stats["missed_periods"].append([prev_tick, mono(t_sim), stolen])
                elif missed:
                    self.stats["startup_ticks"] = self.stats.get("startup_ticks", 0) + 1
                # The sample instant, not the (later, jittered) moment this loop gets
                # here: states are stamped when the vehicle was there, so consecutive
                # control instants are exactly one period apart, as the physics is.
                stamp = mono(t_sim)
                if k < 0 and engaged and t_sim >= self.args.preroll:
                    # Setpoints stream (the loop is engaged, as PX4 requires before
                    # offboard control): start the mission clock at this instant.
                    k, t_start = 0, t_sim
                    self._mission0 = t_start
                    self.bus.put(Command(name="start", args={"t0": stamp}, stamp=stamp))
                    self._mission_started(stamp)
                    self.stats["preroll_s"] = t_sim
                elif k >= 0:
                    k += 1
                if k >= 0:
                    self._maybe_release(k, stamp)
                if self._hold is not None and prev_tick is not None:
                    self._answered_run = self._answered_run + 1 if self._resumes(answer) else 0
                    if self._answered_run >= self.args.failsafe_resume:
                        self._clear_failsafe(stamp)
                        applied = None  # apply the newest setpoint again
                self._tick(
                    stamp, sim.gyro.read(math.inf) if n == 0 else sim.read_gyro(), sampled=stamp
                )
                self._last_stamp = stamp
                prev_tick = stamp
                # Late answers still count (sense-to-actuate) for a while, then go.
                self._prune(stamp - max(1.0, 10 * self.period))
                if k >= 0:
                    if not self._record(u, t_sim - t_start):
                        break
                    self.stats["steps"] = k + 1
                n += 1
                t_next += self.period
            with self._cond:
                latest, sp_wall = self._latest, self._sp_wall
            now = self.now()
            e = self._take_controller_failsafe()
            if e is not None:
                reason = str(e.data.get("reason", "")) or e.text
                self._on_controller_failsafe(reason, now, now - sp_wall, flying=k >= 0)
            if self._hold is None and k >= 0 and now - sp_wall > self.args.failsafe_after:
                self._engage_failsafe(now, now - sp_wall)
            if self._hold is not None:
                u = self._hold_u()
            elif latest is not None and latest is not applied:
                u = sim.set_setpoint(latest.u)
                applied = latest
            sim.step(sub)
            if not self._stepped_finite(sim.time - t_start if k >= 0 else 0.0):
                break
            delay = mono(sim.time) - self.now()
            if delay > 0:
                self.stop.wait(delay)  # pacing to the wall clock, not synchronisation
            elif delay < -0.5:
                self.stats["overruns"] = self.stats.get("overruns", 0) + 1

    def teardown(self) -> None:
        steal0, steal1 = self._steal0, hostcpu.steal_s()
        if steal0 is not None and steal1 is not None:
            # CPU time the hypervisor took from this machine while the realtime loop ran.
            self.stats["host_steal_s"] = round(steal1 - steal0, 3)
        self.stats["sense_to_actuate"] = self._s2a.summary()
        self.stats["s2a_samples_ms"] = self._s2a.samples_ms()
        # Shares of sense-to-actuate at the vehicle: sample instant -> imu put, and the
        # setpoint's bus hop back.
        self.stats["publish_lag"] = self._publish_lag.summary()
        self.stats["hop_setpoint"] = timing.percentiles_ms(list(self._sp_sub.transit_s))
        self.stats["k_release"] = self.k_release
        if self.truth is not None:
            self.truth.close()
            self.stats["truth_rows"] = self.truth.rows
            self.stats["unwritten_truth_rows"] = self.truth.unwritten

    def _truth_lost(self, err: OSError) -> None:
        """The ground truth cannot be written (a full disk): the flight goes on."""
        self.stats["truth_error"] = str(err)
        self.event(
            "fault",
            f"cannot write {self.truth.path if self.truth else 'truth.csv'}: "
            f"{err.strerror or err}; ground truth not recorded from here on",
            "error",
            file=str(self.truth.path) if self.truth else "truth.csv",
            errno=err.errno if err.errno is not None else -1,
        )


def main(argv: list[str] | None = None) -> int:
    return runtime.main_for(SimNode, argv, _extra)


__all__ = [
    "FLIGHT_COLUMNS",
    "Event",
    "SimNode",
    "main",
]
