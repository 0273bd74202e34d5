"""Sensor faults: mocap dropouts, frozen frames, outliers and clock jumps.

In-process on the estimator service class (its screening plus the filter of
``arcade_core.estimation``), fed ``Mocap``/``Imu`` messages of a vehicle on a 2 m/s circle
(120 Hz, 7 ms latency, 0.3 mm noise, 20 Hz control): the estimate stays within a stated
bound of the truth through each fault, every fault is flagged (state flags and events),
and the stream recovers. The lockstep flights through the whole stack with the faults
injected by the simulator are in ``tests/integration/test_faults_sensor_flights.py``.
"""

from __future__ import annotations

import numpy as np
import pytest

from services.messages import Imu, Mocap

MOCAP_DT = 1.0 / 120.0
CONTROL_DT = 0.05
LATENCY = 0.007
T0 = 100.0  # clock origin (monotonic-like; a backward jump stays positive)
RADIUS, OMEGA, CENTER = 1.0, 2.0, np.array([0.5, -1.0, 1.2])
JERK = RADIUS * OMEGA**3  # of the circle, m/s^3: the constant-acceleration model's error


def truth(t: float) -> np.ndarray:
    return CENTER + RADIUS * np.array([np.cos(OMEGA * t), np.sin(OMEGA * t), 0.0])


def fly(
    make,
    duration=3.0,
    *,
    drop=lambda t: False,
    freeze=lambda t: False,
    outlier=lambda t: False,
    clock=lambda t: 0.0,
    yaw=lambda t: 0.0,
    yaw_rate=lambda t: 0.0,
    seed=0,
):
    """Feed the estimator; returns ``(t, x, state message)`` per control instant, events.

    ``yaw(t)`` [rad] and its derivative ``yaw_rate(t)``: the vehicle's heading (mocap
    quaternion) and gyro (body z rate); level and not turning by default."""
    est, bus = make()
    rng = np.random.default_rng(seed)
    captures = np.arange(0.0, duration, MOCAP_DT)
    rows, i, last = [], 0, None
    for k in range(int(duration / CONTROL_DT)):
        t = k * CONTROL_DT
        while i < len(captures) and (captures[i] + LATENCY <= t + 1e-12 or i == 0):
            tc = captures[i]
            i += 1
            if drop(tc):
                continue
            p = truth(tc) + 3e-4 * rng.standard_normal(3)
            if outlier(tc):
                d = rng.normal(size=3)
                p = p + 0.5 * d / np.linalg.norm(d)
            if freeze(tc) and last is not None:
                p = last
            last = p
            off = clock(tc)
            est.on_mocap(
                Mocap(
                    position=p,
                    quaternion=[np.cos(yaw(tc) / 2), 0, 0, np.sin(yaw(tc) / 2)],
                    capture_stamp=T0 + tc + off,
                    stamp=T0 + tc + LATENCY + off,
                )
            )
        n = len(bus.states)
        est.on_imu(Imu(gyro=np.array([0.0, 0.0, yaw_rate(t)]), stamp=T0 + t))
        if len(bus.states) > n:
            rows.append((t, bus.states[-1].x, bus.states[-1]))
    return rows, bus.events, est


def prediction_bound(horizon: float) -> float:
    """Position error of a constant-acceleration prediction over ``horizon`` on the circle:
    ``J T^3 / 6`` (J: its jerk) plus ``a_err T^2 / 2`` for an acceleration estimate off by
    ``a_err = 2 m/s^2`` (half the centripetal 4 m/s^2; the filter's white-jerk model
    trades this against lag)."""
    return JERK * horizon**3 / 6 + 2.0 * horizon**2 / 2


def errors(rows, window):
    return np.array(
        [np.linalg.norm(x[:3] - truth(t)) for t, x, _ in rows if window[0] <= t < window[1]]
    )


@pytest.mark.parametrize("gap", [0.05, 0.15, 0.3, 0.5])
def test_dropout_predicts_through_with_bounded_error(estimator_factory, gap):
    t0 = 1.0
    rows, events, _ = fly(estimator_factory, drop=lambda t: t0 <= t < t0 + gap)
    err = errors(rows, (t0, t0 + gap + LATENCY + CONTROL_DT))
    horizon = gap + LATENCY + CONTROL_DT
    assert err.max() <= prediction_bound(horizon), (gap, err.max())
    assert err.max() < 0.7 * 2.0 * horizon  # far better than holding the last fix
    flagged = [t for t, _, s in rows if s.predicted_through_dropout]
    assert flagged and min(flagged) >= t0 and max(flagged) <= t0 + gap + 2 * CONTROL_DT
    assert all(s.mocap_stale for t, _, s in rows if t0 + LATENCY + CONTROL_DT <= t < t0 + gap)
    kinds = [(e.kind, e.text) for e in events]
    assert ("degraded", "mocap dropout: predicting") in kinds
    assert ("info", "mocap recovered") in kinds
    assert errors(rows, (t0 + gap + 0.3, 3.0)).max() < 3e-3  # converged again


def test_attitude_follows_the_gyro_through_a_long_dropout(estimator_factory):
    # A heading that turns back and forth (yaw rate 1.6 cos 2t rad/s): through 2 s without
    # mocap the attitude must be the gyro's integral, not the last fix turned by the
    # newest rate times the age; and the first frames after the gap must pass the gate.
    t0, gap = 1.0, 2.0
    rows, _, est = fly(
        estimator_factory,
        duration=5.0,
        drop=lambda t: t0 <= t < t0 + gap,
        yaw=lambda t: 0.8 * np.sin(2.0 * t),
        yaw_rate=lambda t: 1.6 * np.cos(2.0 * t),
    )
    yaw_err = np.array(
        [
            abs(np.angle(np.exp(1j * (2 * np.arctan2(x[9], x[6]) - 0.8 * np.sin(2.0 * t)))))
            for t, x, _ in rows
            if t0 <= t < t0 + gap
        ]
    )
    assert yaw_err.max() < 0.05, yaw_err.max()
    assert est.filter.rejected == 0
    assert errors(rows, (t0 + gap + 0.3, 5.0)).max() < 3e-3


def test_frozen_frames_are_dropped_and_flagged(estimator_factory):
    t0, length = 1.0, 0.3
    rows, events, est = fly(estimator_factory, freeze=lambda t: t0 <= t < t0 + length)
    assert est.stats["frozen_frames"] == round(length / MOCAP_DT)
    err = errors(rows, (t0, t0 + length + CONTROL_DT))
    # Predicted through like a dropout; fusing the frozen pose would have lagged the
    # vehicle by up to 0.6 m (2 m/s for 0.3 s).
    assert err.max() <= prediction_bound(length + LATENCY + CONTROL_DT), err.max()
    assert any(s.predicted_through_dropout for t, _, s in rows if t0 < t < t0 + length)
    assert [e.data.get("fault") for e in events if e.kind == "fault"] == ["mocap_frozen"]
    assert errors(rows, (t0 + length + 0.3, 3.0)).max() < 3e-3


def test_outliers_are_rejected_and_flagged_at_most_once_per_second(estimator_factory):
    rng = np.random.default_rng(1)
    bad = set(np.flatnonzero(rng.random(400) < 0.1))  # 10 % of frames jump by 0.5 m
    rows, events, est = fly(
        estimator_factory, outlier=lambda t: round(t / MOCAP_DT) in bad and t > 0.2
    )
    assert int(est.filter.rejected) >= 0.9 * sum(1 for i in bad if 0.2 < i * MOCAP_DT < 3.0)
    assert errors(rows, (0.3, 3.0)).max() < 3e-3  # never pulled towards an outlier
    stamps = [e.stamp for e in events if e.data.get("fault") == "mocap_outliers"]
    assert len(stamps) >= 2 and np.all(np.diff(stamps) >= 1.0 - 1e-9)


@pytest.mark.parametrize("offset", [2.0, -1.5])
def test_clock_jump_is_restamped_and_flagged(estimator_factory, offset):
    t0, length = 1.0, 0.5
    rows, events, est = fly(
        estimator_factory, clock=lambda t: offset if t0 <= t < t0 + length else 0.0
    )
    assert est.stats["restamped_frames"] == pytest.approx(length / MOCAP_DT, abs=1)
    # Frames keep being fused through the jump: no dropout, the error stays at noise level.
    assert not any(s.predicted_through_dropout for _, _, s in rows)
    assert errors(rows, (0.3, 3.0)).max() < 5e-3
    jumps = [e for e in events if e.data.get("fault") == "mocap_clock_jump"]
    assert [e.kind for e in jumps] == ["fault", "info"]
    assert jumps[0].data["offset_s"] == pytest.approx(offset, abs=0.01)


def test_permanent_clock_jump_keeps_the_estimate(estimator_factory):
    rows, events, _ = fly(estimator_factory, clock=lambda t: 5.0 if t >= 1.0 else 0.0)
    assert errors(rows, (0.3, 3.0)).max() < 5e-3
    assert [e.kind for e in events if e.data.get("fault") == "mocap_clock_jump"] == ["fault"]
