"""Estimator service: mocap + gyro -> 13-state at the control rate.

Subscribes ``mocap`` and ``imu``; publishes ``state``. Only the vehicle's frames (body
``--mocap-body``, default :data:`~services.messages.VEHICLE_BODY`) are fused; frames of
other rigid bodies on the stream (the simulator's payload) are counted per body
(``other_bodies``), nothing else: they are no fault, no frame of the vehicle, no gap. But
when frames of other bodies come and none of the vehicle's for :data:`NO_VEHICLE_S` after
the first frame, the vehicle's body is likely named otherwise: a ``fault`` event
(``mocap_body_missing``, a warning in the log) names the bodies seen and the option, once
(an ``info`` event if the vehicle's frames come after all).
The filter is
:mod:`arcade_core.estimation` (constant-acceleration Kalman filter on position, gyro-
propagated attitude, outlier gating, prediction through dropouts, latency compensation).

Clocking: the vehicle link (simulator or bridge) streams ``imu`` at the control rate; each
``imu`` sample is the control instant. Mocap frames that arrived since the previous one are
fused (in capture order) and the state is predicted to the ``imu`` stamp and published with
that stamp, ``meas_stamp`` = capture time of the newest fused frame, ``mocap_stale`` when
no frame was fused this period and ``predicted_through_dropout`` when the newest fused
frame is older than the filter's ``dropout_s``. Before the first frame no state exists, and
none is published. The filter always runs in float64 (its covariance spans too many
orders of magnitude for float32).

Sensor faults, screened before the filter (each announced by an event when it starts and
when it ends; counts in the statistics):

- frozen frames: a frame whose pose is bit-identical to the previous one is a tracker
  repeating its last pose (real mocap noise never repeats exactly); it is dropped, so the
  filter predicts through as in a dropout (``mocap_stale`` / ``predicted_through_dropout``
  flags, ``fault`` event);
- clock jumps: when every frame of a period was captured in the future of the control
  instant (more than ``--stamp-tolerance``) or more than ``--max-frame-lag`` before it, the
  stamps come from a clock that jumped (a stall of a process instead delays or advances
  only some frames of a period: late ones are fused with their own stamps, early ones
  wait for the next instant); such frames are re-stamped onto the control clock (the newest at the
  usual capture-to-control lag, the others keeping their spacing), so the filter keeps
  fusing them (``fault`` event with the offset);
- outliers: gated out by the filter (:mod:`arcade_core.estimation`); a ``fault`` event at
  most once per second while they occur;
- dropouts: the filter predicts (``degraded`` event); the controller hovers when the
  newest fused frame is older than its ``--max-meas-age``.

Frames wait for the next ``imu`` sample in a bounded buffer (:data:`MAX_PENDING`; the
oldest are dropped and counted, ``pending_dropped``, when ``imu`` stops). An estimate that
is not finite or not a valid :class:`~services.messages.State` (a diverged filter)
re-initialises the filter (``fault`` event, ``filter_resets``); the next frame starts it
again.
"""

from __future__ import annotations

import argparse
import dataclasses
import threading
from typing import Any

import numpy as np

from services import options, runtime, timing
from services.messages import MAX_VARIANCE, Imu, MessageError, Mocap, State

#: Frames kept while waiting for the next ``imu`` sample (~2 s of 120 Hz mocap).
MAX_PENDING = 256
#: Other rigid bodies whose frames are counted (``other_bodies``), by name.
MAX_OTHER_BODIES = 16
#: Frames of other bodies only for this long after the first frame [s of stamps]: the
#: ``mocap_body_missing`` fault (a mocap system streams every body at tens of Hz).
NO_VEHICLE_S = 1.0


def _packed_step(filt, frames, t, gyro, config):
    """``fuse_and_predict`` with everything the service reads in one vector (one transfer
    instead of eight: each costs tens of microseconds on the control path)."""
    import jax.numpy as jnp

    from arcade_core import estimation as est

    filt, out = est.fuse_and_predict(filt, frames, t, gyro, config)
    flags = jnp.stack([filt.initialised, filt.rejected, out.fused, out.dropout, out.age, filt.t])
    return filt, jnp.concatenate([out.x, out.var, flags.astype(out.x.dtype)])


class Unpacked:
    """The host-side view of :func:`_packed_step`'s vector."""

    __slots__ = ("age", "dropout", "fused", "initialised", "rejected", "t", "var", "x")

    def __init__(self, v: np.ndarray):
        self.x, self.var = v[:13].copy(), v[13:26]
        self.initialised, self.dropout = bool(v[26]), bool(v[29])
        self.rejected, self.fused = int(v[27]), int(v[28])
        self.age, self.t = float(v[30]), float(v[31])


def _shifted(m: Mocap, offset: float) -> Mocap:
    """``m`` with both stamps moved back by ``offset`` (never below 0, never sent before
    it was captured)."""
    capture = max(m.capture_stamp - offset, 0.0)
    return dataclasses.replace(m, capture_stamp=capture, stamp=max(m.stamp - offset, capture))


class Estimator(runtime.Service):
    """Estimator: mocap (+ gyro) -> state at the control rate."""

    name = "estimator"

    def setup(self, bus) -> None:
        import jax
        import jax.numpy as jnp

        from arcade_core import estimation as est

        self.est = est
        self.jnp = jnp
        self.dtype = jnp.result_type(float)
        a = self.args
        self.config = est.FilterConfig(jerk_psd=a.jerk_psd, position_std=a.mocap_noise)
        self.stats["filter"] = {"jerk_psd": a.jerk_psd, "position_std_m": a.mocap_noise}
        self.log.info(
            "filter: jerk density %g (m/s^3)^2/Hz, mocap noise %g mm",
            a.jerk_psd,
            1e3 * a.mocap_noise,
        )
        self.filter = est.init(self.dtype)
        self._step = jax.jit(_packed_step, static_argnames="config")
        self._pending: list[Mocap] = []
        # Frames captured after the previous control instant, screened already: fused at
        # the next one (this thread only).
        self._requeued: list[Mocap] = []
        self._lock = threading.Lock()
        self._transit: dict[str, Any] = {}  # bus transit times per topic
        self._proc = timing.LatencySamples()  # time spent per control instant [s]
        self._dropout_reported = False
        self._last_pose: tuple[np.ndarray, np.ndarray] | None = None
        self._frozen = False
        self._jump: float | None = None  # clock offset being corrected [s]
        self._lag: float | None = None  # usual lag of the newest frame behind the control instant
        self._rejected_seen = 0
        self._outlier_event_t = -np.inf
        self.stats.update(
            states=0,
            frames=0,
            dropped_frames=0,
            frozen_frames=0,
            restamped_frames=0,
            pending_dropped=0,
            filter_resets=0,
            other_bodies={},
        )
        self.vehicle_body = a.mocap_body
        self._first_frame_at: float | None = None  # stamp of the first frame, of any body
        self._vehicle_seen = False
        self._body_missing_reported = False
        # One ordered stream: the frames of a period arrive before its imu sample.
        self._subs = runtime.subscribe_ordered(
            bus,
            {"mocap": self.on_mocap, "imu": self.on_imu},
            seq_only=("mocap",),
            transit=self._transit,
            sources={"mocap": src} if (src := getattr(self.args, "mocap_source", None)) else None,
        )
        self.pub = bus.publisher("state")

    def warmup(self) -> None:
        frames = self.est.empty_frames(dtype=self.dtype)
        for _ in range(3):
            self._step(self.filter, frames, 0.0, np.zeros(3), self.config)

    def on_mocap(self, m: Mocap) -> None:
        if self._first_frame_at is None:
            self._first_frame_at = m.stamp
        if not m.of_vehicle(self.vehicle_body):  # another rigid body (e.g. the payload)
            self._other_body(m)
            return
        if not self._vehicle_seen and self._body_missing_reported:
            self.event(
                "info",
                f"mocap frames of the vehicle's rigid body {self.vehicle_body!r} arrive",
                stamp=m.stamp,
                fault="mocap_body_missing",
            )
        self._vehicle_seen = True
        with self._lock:
            if len(self._pending) >= MAX_PENDING:  # no imu for a while: keep the newest
                del self._pending[0]
                self.stats["pending_dropped"] += 1
                if self.stats["pending_dropped"] == 1:
                    self.log.warning(
                        "no imu sample for %d mocap frames: dropping the oldest", MAX_PENDING
                    )
            self._pending.append(m)

    def _other_body(self, m: Mocap) -> None:
        """Count a frame of a body that is not the vehicle's; say so once per body, and
        once that only such frames come (see the module docstring)."""
        seen, body = self.stats["other_bodies"], m.body
        if body not in seen and len(seen) < MAX_OTHER_BODIES:
            self.log.info(
                "mocap body %r is not the vehicle's (%r): its frames are not fused",
                body,
                self.vehicle_body,
            )
            seen[body] = 0
        if body in seen:
            seen[body] += 1
        after = m.stamp - self._first_frame_at
        if self._vehicle_seen or self._body_missing_reported or after < NO_VEHICLE_S:
            return
        self._body_missing_reported = True
        self.event(
            "fault",
            f"no mocap frame of the vehicle's rigid body {self.vehicle_body!r} in {after:.1f} s, "
            f"only of {', '.join(map(repr, seen))}: name the vehicle's body with --mocap-body "
            "NAME (arcade up --mocap-body NAME)",
            "warning",
            stamp=m.stamp,
            fault="mocap_body_missing",
            mocap_body=self.vehicle_body,
        )

    def _frames(self, batch: list[Mocap]) -> Any:
        est = self.est
        n = min(len(batch), est.MAX_FRAMES)
        if len(batch) > n:
            self.stats["dropped_frames"] += len(batch) - n
        batch = sorted(batch, key=lambda m: m.capture_stamp)[-n:] if n else []
        stamp = np.zeros(est.MAX_FRAMES)
        pos = np.zeros((est.MAX_FRAMES, 3))
        quat = np.tile([1.0, 0.0, 0.0, 0.0], (est.MAX_FRAMES, 1))
        valid = np.zeros(est.MAX_FRAMES, bool)
        for i, m in enumerate(batch):
            stamp[i], pos[i], quat[i], valid[i] = m.capture_stamp, m.position, m.quaternion, True
        # NumPy arrays straight into the jitted step (its C++ fast path converts them);
        # jnp.asarray here cost more than the whole filter step.
        dt = np.dtype(self.dtype)
        return est.Frames(stamp.astype(dt), pos.astype(dt), quat.astype(dt), valid)

    def _drop_frozen(self, batch: list[Mocap], t: float) -> list[Mocap]:
        """Frames whose pose differs from the previous frame's (see the module docstring)."""
        fresh = []
        for m in sorted(batch, key=lambda m: m.capture_stamp):
            last = self._last_pose
            repeat = (
                last is not None
                and np.array_equal(m.position, last[0])
                and np.array_equal(m.quaternion, last[1])
            )
            self._last_pose = (m.position, m.quaternion)
            if repeat:
                self.stats["frozen_frames"] += 1
            else:
                fresh.append(m)
        if batch:
            frozen = not fresh
            if frozen and not self._frozen:
                self.event(
                    "fault",
                    "mocap frozen: repeated poses dropped, predicting",
                    "warning",
                    stamp=t,
                    fault="mocap_frozen",
                )
            elif fresh and self._frozen:
                self.event("info", "mocap poses change again", stamp=t, fault="mocap_frozen")
            self._frozen = frozen
        return fresh

    def _restamp(self, batch: list[Mocap], t: float) -> list[Mocap]:
        """Frames with capture stamps on the control clock (see the module docstring)."""
        a = self.args
        good = [m for m in batch if -a.stamp_tolerance <= t - m.capture_stamp <= a.max_frame_lag]
        bad = [m for m in batch if m not in good]
        if good:
            lag = t - max(m.capture_stamp for m in good)
            self._lag = lag if self._lag is None else 0.9 * self._lag + 0.1 * lag
        if bad and good:
            # Frames on the control clock beside off-clock ones: no clock jump but a stall
            # (of this process or of the publisher). Late frames keep their true stamps (the
            # filter fuses what is still in order); early ones belong to a later instant.
            early = [m for m in bad if m.capture_stamp > t]
            self._requeued = early
            self.stats["late_frames"] = self.stats.get("late_frames", 0) + len(bad) - len(early)
            return good + [m for m in bad if m.capture_stamp <= t]
        if bad:
            newest = max(m.capture_stamp for m in bad)
            offset = newest - (t - (self._lag if self._lag is not None else 0.0))
            self.stats["restamped_frames"] += len(bad)
            if self._jump is None:
                self.event(
                    "fault",
                    f"mocap clock off by {offset:+.3f} s: re-stamping frames",
                    "warning",
                    stamp=t,
                    fault="mocap_clock_jump",
                    offset_s=float(offset),
                )
            self._jump = offset
            bad = [_shifted(m, offset) for m in bad]
        elif batch and self._jump is not None:
            self.event("info", "mocap clock consistent again", stamp=t, fault="mocap_clock_jump")
            self._jump = None
        return good + bad

    def on_imu(self, imu: Imu) -> None:
        t0 = self.now()
        try:
            self._on_imu(imu)
        finally:
            self._proc.append(self.now() - t0)

    def _on_imu(self, imu: Imu) -> None:
        with self._lock:
            batch, self._pending = self._pending, []
        self.stats["frames"] += len(batch)
        # Frames held back from the previous instant were screened for repeats then.
        held, self._requeued = self._requeued, []
        batch = self._restamp(held + self._drop_frozen(batch, imu.stamp), imu.stamp)
        self.filter, packed = self._step(
            self.filter, self._frames(batch), imu.stamp, imu.gyro, self.config
        )
        out = Unpacked(np.asarray(packed, dtype=float))  # one device-to-host copy
        if not out.initialised:
            return
        rejected = out.rejected
        if rejected > self._rejected_seen and imu.stamp - self._outlier_event_t >= 1.0:
            self.event(
                "fault",
                f"mocap outliers rejected ({rejected} so far)",
                "warning",
                stamp=imu.stamp,
                fault="mocap_outliers",
                rejected=rejected,
            )
            self._outlier_event_t = imu.stamp
        self._rejected_seen = rejected
        x = out.x
        if not np.all(np.isfinite(x)):
            self._reset_filter(imu.stamp, "non-finite estimate")
            return
        dropout = out.dropout
        if dropout and not self._dropout_reported:
            self.event(
                "degraded", "mocap dropout: predicting", "warning", stamp=imu.stamp, age_s=out.age
            )
        elif not dropout and self._dropout_reported:
            self.event("info", "mocap recovered", stamp=imu.stamp)
        self._dropout_reported = dropout
        with np.errstate(divide="ignore", invalid="ignore"):  # a zero quaternion: below
            x[6:10] /= np.linalg.norm(x[6:10])
        try:
            state = State(
                x=x,
                cov_diag=np.clip(out.var, 0.0, MAX_VARIANCE),
                mocap_stale=out.fused == 0,
                predicted_through_dropout=dropout,
                # A frame up to --stamp-tolerance ahead of the instant is fused as on
                # time: its age is zero, not negative.
                meas_stamp=min(out.t, imu.stamp),
                stamp=imu.stamp,
            )
        except MessageError as err:  # finite but out of range: a diverged filter
            self._reset_filter(imu.stamp, f"invalid estimate ({err})")
            return
        self.pub.put(state)
        self.stats["states"] += 1

    def _reset_filter(self, stamp: float, why: str) -> None:
        """Start the filter again from the next frame (nothing is published meanwhile)."""
        self.stats["filter_resets"] += 1
        self.filter = self.est.init(self.dtype)
        self._requeued = []
        self.event(
            "fault",
            f"{why} at {stamp:.3f}: filter re-initialised",
            "error",
            stamp=stamp,
            fault="estimator_reset",
        )

    def teardown(self) -> None:
        # One bus hop, simulator -> estimator: put to callback of the control-instant
        # samples (lockstep too: the hop does not depend on the clock mode).
        hops = list(self._transit.get("imu", ()))
        self.stats["hop_imu"] = timing.percentiles_ms(hops)
        self.stats["hop_samples_ms"] = [1e3 * h for h in hops[-20000:]]
        self.stats["process"] = self._proc.summary()
        self.stats["outliers_rejected"] = int(self.filter.rejected)


def _positive(text: str) -> float:
    """An option that must be a finite number above zero."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0.0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number above zero, not {text}")
    return value


def _extra(p) -> None:
    from arcade_core.estimation import FilterConfig

    p.add_argument(
        "--jerk-psd",
        type=_positive,
        default=FilterConfig().jerk_psd,
        help="white-jerk spectral density of the position filter [(m/s^3)^2/Hz]: lower "
        "is smoother and later (default %(default)s, tuned for the closed loop by "
        "`python -m benchmarks.quadrotor_variants estimator`)",
    )
    p.add_argument(
        "--mocap-noise",
        type=_positive,
        default=FilterConfig().position_std,
        help="standard deviation of the motion capture's position noise [m]",
    )
    p.add_argument(
        "--max-frame-lag",
        type=float,
        default=0.25,
        help="frames captured longer than this before the control instant have a "
        "jumped clock and are re-stamped [s]",
    )
    p.add_argument(
        "--stamp-tolerance",
        type=float,
        default=0.005,
        help="frames captured later than the control instant by more than this "
        "have a jumped clock and are re-stamped [s]",
    )
    options.add_mocap_source_argument(p)
    options.add_mocap_body_argument(p)


def main(argv: list[str] | None = None) -> int:
    # Always float64: the covariance spans 1e-7 m^2 (mocap noise) to ~1e2 (acceleration),
    # beyond float32's resolution, and the filter is small enough not to care.
    return runtime.main_for(Estimator, argv, _extra, x64=True)
