"""Estimator service: mocap + gyro -> 13-state at the control rate.

Subscribes ``mocap`` and ``imu``; publishes ``state``. The filter is
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
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from services import runtime
from services.messages import Imu, Mocap, State


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
        self.config = est.FilterConfig()
        self.filter = est.init(self.dtype)
        self._step = jax.jit(est.fuse_and_predict, static_argnames="config")
        self._pending: list[Mocap] = []
        self._lock = threading.Lock()
        self._hops: list[float] = []
        self._dropout_reported = False
        self.stats.update(states=0, frames=0, dropped_frames=0)
        # One ordered stream: the frames of a period arrive before its imu sample.
        self._subs = runtime.subscribe_ordered(bus, {"mocap": self.on_mocap, "imu": self.on_imu})
        self.pub = bus.publisher("state")

    def warmup(self) -> None:
        frames = self.est.empty_frames(dtype=self.dtype)
        for _ in range(3):
            self._step(self.filter, frames, 0.0, np.zeros(3), self.config)

    def on_mocap(self, m: Mocap) -> None:
        with self._lock:
            self._pending.append(m)

    def _frames(self, batch: list[Mocap]) -> Any:
        est, jnp = self.est, self.jnp
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
        return est.Frames(jnp.asarray(stamp, self.dtype), jnp.asarray(pos, self.dtype),
                          jnp.asarray(quat, self.dtype), jnp.asarray(valid))

    def on_imu(self, imu: Imu) -> None:
        if not self.args.lockstep:
            self._hops.append(self.now() - imu.stamp)
        with self._lock:
            batch, self._pending = self._pending, []
        self.stats["frames"] += len(batch)
        self.filter, out = self._step(self.filter, self._frames(batch), imu.stamp, imu.gyro,
                                      self.config)
        if not bool(self.filter.initialised):
            return
        x = np.array(out.x, dtype=float)
        if not np.all(np.isfinite(x)):
            self.log.error("non-finite estimate at %.3f: filter re-initialised", imu.stamp)
            self.filter = self.est.init(self.dtype)
            return
        dropout = bool(out.dropout)
        if dropout and not self._dropout_reported:
            self.event("degraded", "mocap dropout: predicting", "warning", stamp=imu.stamp,
                       age_s=float(out.age))
        elif not dropout and self._dropout_reported:
            self.event("info", "mocap recovered", stamp=imu.stamp)
        self._dropout_reported = dropout
        x[6:10] /= np.linalg.norm(x[6:10])
        self.pub.put(State(
            x=x, cov_diag=np.maximum(np.asarray(out.var, dtype=float), 0.0),
            mocap_stale=int(out.fused) == 0, predicted_through_dropout=dropout,
            meas_stamp=float(self.filter.t), stamp=imu.stamp,
        ))
        self.stats["states"] += 1

    def teardown(self) -> None:
        self.stats["hop_imu"] = runtime.percentiles_ms(self._hops)
        self.stats["hop_samples_ms"] = [1e3 * h for h in self._hops[-20000:]]
        self.stats["outliers_rejected"] = int(self.filter.rejected)


def main(argv: list[str] | None = None) -> int:
    # Always float64: the covariance spans 1e-7 m^2 (mocap noise) to ~1e2 (acceleration),
    # beyond float32's resolution, and the filter is small enough not to care.
    return runtime.main_for(Estimator, argv, x64=True)
