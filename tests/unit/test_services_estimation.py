"""Estimator filter (arcade_core.estimation): dropouts, outliers, latency compensation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from arcade_core import estimation as est

CFG = est.FilterConfig()
MOCAP_DT = 1.0 / 120.0
CONTROL_DT = 0.05
LATENCY = 0.007


def yaw_quat(yaw: float) -> np.ndarray:
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


class Truth:
    """A vehicle on a climbing circle (2 m/s, 4 m/s^2) with a constant yaw rate."""

    center = np.array([0.5, -1.0, 1.2])
    radius, rate, climb = 1.0, 2.0, 0.3
    yaw_rate = 0.8

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        c, s = np.cos(self.rate * t), np.sin(self.rate * t)
        p = self.center + np.array([self.radius * c, self.radius * s, self.climb * t])
        return p, yaw_quat(self.yaw_rate * t)

    def velocity(self, t: float) -> np.ndarray:
        c, s = np.cos(self.rate * t), np.sin(self.rate * t)
        return np.array([-self.radius * self.rate * s, self.radius * self.rate * c, self.climb])


step = jax.jit(est.fuse_and_predict, static_argnames="config")


def fly(duration, *, noise=3e-4, drop=lambda t: False, outlier=lambda t: False, seed=0):
    """Run the filter on a simulated mocap stream; returns per-control-instant outputs."""
    rng = np.random.default_rng(seed)
    truth = Truth()
    omega = jnp.array([0.0, 0.0, truth.yaw_rate])
    state = est.init()
    captures = np.arange(0.0, duration, MOCAP_DT)
    outs = []
    i = 0
    for k in range(1, int(duration / CONTROL_DT)):
        t = k * CONTROL_DT
        batch = []
        while i < len(captures) and captures[i] + LATENCY <= t + 1e-12:
            tc = captures[i]
            i += 1
            if drop(tc):
                continue
            p, q = truth.pose(tc)
            p = p + noise * rng.standard_normal(3)
            if outlier(tc):
                p = p + np.array([0.0, 0.0, 0.5])
            batch.append((tc, p, q))
        frames = est.empty_frames()
        n = len(batch)
        if n:
            frames = est.Frames(
                frames.stamp.at[:n].set(jnp.array([b[0] for b in batch])),
                frames.position.at[:n].set(jnp.array([b[1] for b in batch])),
                frames.quaternion.at[:n].set(jnp.array([b[2] for b in batch])),
                frames.valid.at[:n].set(True),
            )
        state, out = step(state, frames, t, omega, CFG)
        outs.append((t, np.asarray(out.x), bool(out.dropout), int(out.fused), state))
    return truth, outs


def test_tracks_constant_velocity_with_latency_compensation():
    truth, outs = fly(1.5)
    pos_err, vel_err, att_err, lag_err = [], [], [], []
    for t, x, dropout, fused, state in outs[5:]:
        p, q = truth.pose(t)
        assert not dropout and fused >= 5
        pos_err.append(np.linalg.norm(x[:3] - p))
        vel_err.append(np.linalg.norm(x[3:6] - truth.velocity(t)))
        att_err.append(1 - abs(np.dot(x[6:10], q)))
        # Without compensation the output would be the state at the newest capture.
        lag_err.append(np.linalg.norm(np.asarray(state.p) - p))
    assert np.max(pos_err) < 2e-3, np.max(pos_err)
    assert np.max(vel_err) < 0.1, np.max(vel_err)
    assert np.max(att_err) < 1e-6
    # The newest capture is >= 7 ms old: >= 1.6 cm behind at 2.3 m/s; compensated: < 2 mm.
    assert np.min(lag_err) > 0.015
    assert np.mean(pos_err) < 0.1 * np.mean(lag_err)


def test_dropout_predicts_and_flags_then_recovers():
    gap = (0.5, 0.65)  # a 150 ms occlusion
    truth, outs = fly(1.5, drop=lambda t: gap[0] <= t < gap[1])
    flagged = [t for t, _, dropout, _, _ in outs if dropout]
    assert flagged, "dropout not flagged"
    # Flagged exactly while no frame newer than dropout_s exists (latency included).
    assert min(flagged) > gap[0] + LATENCY and max(flagged) <= gap[1] + LATENCY + CONTROL_DT
    for t, x, dropout, fused, _ in outs:
        p, _ = truth.pose(t)
        if dropout:
            assert fused == 0
            # Constant-acceleration prediction through the gap on a 2 m/s circle (jerk
            # 8 m/s^3: < 1 cm, plus the acceleration estimate's noise): within 3 cm,
            # ten times better than holding the last fix (up to ~0.35 m).
            held = truth.pose(gap[0] - MOCAP_DT)[0]
            assert np.linalg.norm(x[:3] - p) < 0.03
            assert np.linalg.norm(x[:3] - p) < 0.1 * max(np.linalg.norm(held - p), 0.05)
    last_t, last_x, last_dropout, _, _ = outs[-1]
    assert not last_dropout
    assert np.linalg.norm(last_x[:3] - truth.pose(last_t)[0]) < 2e-3


def test_outlier_is_gated_and_persistent_jump_reinitialises():
    bad = {round(t, 6) for t in np.arange(0.5, 0.53, MOCAP_DT)[:3]}
    truth, outs = fly(1.0, outlier=lambda t: round(t, 6) in bad)
    state = outs[-1][4]
    assert int(state.rejected) == 3
    for t, x, *_ in outs:
        assert np.linalg.norm(x[:3] - truth.pose(t)[0]) < 3e-3  # never pulled 0.5 m up

    # A jump that persists is re-acquired after max_rejects frames.
    truth, outs = fly(1.0, outlier=lambda t: t >= 0.5)
    t, x, *_ = outs[-1]
    assert abs(x[2] - (truth.pose(t)[0][2] + 0.5)) < 3e-3
    assert int(outs[-1][4].rejected) == CFG.max_rejects - 1


def test_out_of_order_frame_is_ignored():
    state = est.init()
    q = yaw_quat(0.0)
    omega = jnp.zeros(3)
    state, ok = est.update(state, 1.0, jnp.array([0.0, 0.0, 1.0]), q, omega, CFG)
    assert bool(ok)
    later, ok = est.update(state, 0.9, jnp.array([0.0, 0.0, 1.1]), q, omega, CFG)
    assert not bool(ok)
    np.testing.assert_array_equal(np.asarray(later.p), np.asarray(state.p))


def test_a_repeated_frame_is_not_fused_twice():
    truth = Truth()
    omega = jnp.array([0.0, 0.0, truth.yaw_rate])
    update = jax.jit(est.update, static_argnames="config")
    state = est.init()
    for k in range(20):  # the first frame is stamped 0.0, the uninitialised filter's t
        tc = k * MOCAP_DT
        state, ok = update(state, tc, jnp.asarray(truth.pose(tc)[0]), truth.pose(tc)[1], omega, CFG)
        assert bool(ok)
    again, ok = update(state, tc, jnp.asarray(truth.pose(tc)[0]), truth.pose(tc)[1], omega, CFG)
    assert not bool(ok)
    assert int(again.accepted) == 20 and int(again.rejected) == 1
    np.testing.assert_array_equal(np.asarray(again.cov), np.asarray(state.cov))
    np.testing.assert_array_equal(np.asarray(again.p), np.asarray(state.p))
    # Within one control period's batch too: the repeat is not counted as fused.
    tn = 20 * MOCAP_DT
    frames = est.empty_frames()
    rows = [(tn, *truth.pose(tn)), (tn, *truth.pose(tn))]
    frames = est.Frames(
        frames.stamp.at[:2].set(jnp.array([r[0] for r in rows])),
        frames.position.at[:2].set(jnp.array([r[1] for r in rows])),
        frames.quaternion.at[:2].set(jnp.array([r[2] for r in rows])),
        frames.valid.at[:2].set(True),
    )
    once, out = step(state, frames, tn + LATENCY, omega, CFG)
    assert int(out.fused) == 1 and int(once.accepted) == 21


def test_propagate_attitude_matches_closed_form():
    q0 = yaw_quat(0.3)
    q = est.propagate_attitude(jnp.asarray(q0), jnp.array([0.0, 0.0, 2.0]), 0.1)
    np.testing.assert_allclose(np.asarray(q), yaw_quat(0.5), atol=1e-12)


def test_first_frame_starts_in_the_identity_hemisphere_at_any_clock():
    # Realtime stamps are host-monotonic (hours of uptime): the uninitialised filter's
    # prediction is the identity rotated by the gyro over the whole stamp, i.e. arbitrary.
    # The first frame must not inherit that hemisphere: -q is the same attitude but far
    # away for the model and the MPC cost, which see q as a vector.
    q = yaw_quat(0.05)
    omega = jnp.array([0.007, -0.0015, 0.0144])
    signs = set()
    for stamp in (0.0, 20.0, 2_000.0, 20_071.3, 86_400.0):
        for sign in (1.0, -1.0):
            state, ok = est.update(
                est.init(), stamp, jnp.array([0.0, 0.0, 1.5]), sign * q, omega, CFG
            )
            assert bool(ok)
            signs.add(float(np.sign(state.q[0])))
    assert signs == {1.0}

    # Afterwards the hemisphere is continuous: a frame sent as -q is fused, not flipped.
    state, _ = est.update(est.init(), 100.0, jnp.array([0.0, 0.0, 1.5]), q, omega, CFG)
    state, ok = est.update(state, 100.01, jnp.array([0.0, 0.0, 1.5]), -q, omega, CFG)
    assert bool(ok) and float(state.q[0]) > 0.99
