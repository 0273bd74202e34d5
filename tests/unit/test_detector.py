"""The changepoint detector the adapter runs beside the learner (``detection_step``) and the
scoring of ``arcade eval changepoints`` (``benchmarks.changepoints``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from arcade_core import adaptation
from benchmarks import changepoints as cp

D, L = 3, 2


def config(scale=(1.0, 1.0, 1.0), tracking=0.0, threshold=0.9, window=5, refractory=5):
    beam = adaptation.AdaptationConfig(
        K=8, pi=0.01, beta=0.05, tau2=1.0, sigma2=1.0, prior_floor=1.0, score="joint"
    )
    return adaptation.DetectionConfig(
        beam=beam,
        noise_scale=jnp.asarray(scale, jnp.float64),
        tracking=jnp.asarray(tracking, jnp.float64),
        window=window,
        threshold=threshold,
        refractory_steps=refractory,
    )


def sequence(change_at, shift, n=120, noise=0.1, seed=0):
    """Features and residuals of a linear model whose decoder shifts by ``shift`` (D, L)
    at step ``change_at`` (``None``: never)."""
    rng = np.random.default_rng(seed)
    theta = np.array([[1.0, 0.5], [-0.3, 0.2], [0.0, 1.0]])
    z = rng.normal(size=(n, L))
    y = np.empty((n, D))
    for k in range(n):
        th = theta + (shift if change_at is not None and k >= change_at else 0.0)
        y[k] = th @ z[k] + noise * rng.normal(size=D)
    return theta, z, y, np.full((n, D), noise**2)


def run(cfg, theta0, z, y, s2, learn=None):
    learn = np.ones(len(z), bool) if learn is None else learn
    state = adaptation.init_detection(jnp.asarray(theta0), cfg)

    @jax.jit
    def go(state, cfg):
        def body(st, inp):
            st, det = adaptation.detection_step(st, *inp, cfg)
            return st, det

        return jax.lax.scan(body, state, (z, y, s2, learn))

    return go(state, cfg)


def declared_steps(det) -> np.ndarray:
    return np.flatnonzero(np.asarray(det.declared))


@pytest.fixture(autouse=True)
def _x64():
    with jax.enable_x64(True):
        yield


def test_a_lasting_shift_is_declared_once_and_dated_to_it():
    shift = np.zeros((D, L))
    shift[0, 0] = 1.5
    theta0, z, y, s2 = sequence(60, shift)
    _, det = run(config(), theta0, z, y, s2)
    steps = declared_steps(det)
    assert steps.size == 1 and 60 <= steps[0] <= 63, steps
    # Step k of the scan is the detector beam's step k + 1; the change is dated to it.
    assert int(det.dated[steps[0]]) == 61
    assert float(det.probability[steps[0]]) >= 0.9


def test_no_change_no_declaration():
    theta0, z, y, s2 = sequence(None, 0.0)
    _, det = run(config(), theta0, z, y, s2)
    assert declared_steps(det).size == 0
    assert float(jnp.max(det.probability)) < 0.5


def test_steps_not_learned_change_nothing():
    shift = np.zeros((D, L))
    shift[0, 0] = 1.5
    theta0, z, y, s2 = sequence(60, shift)
    learn = np.arange(len(z)) < 50
    state, det = run(config(), theta0, z, y, s2, learn)
    assert declared_steps(det).size == 0
    assert int(state.beam.step) == 50
    assert np.all(np.asarray(det.probability)[50:] == 0.0)


def test_an_output_left_out_carries_no_evidence():
    shift = np.zeros((D, L))
    shift[2, :] = 1.5  # the change only in the third output
    theta0, z, y, s2 = sequence(60, shift)
    _, watched = run(config(), theta0, z, y, s2)
    _, blind = run(config(scale=(1.0, 1.0, np.inf)), theta0, z, y, s2)
    assert declared_steps(watched).size == 1
    assert declared_steps(blind).size == 0


def test_tracking_follows_a_noisier_output():
    """Residuals three times noisier than the learner's noise on the first output: the
    tracked ratio of that output settles near 9, the others near 1."""
    theta0, z, y, s2 = sequence(None, 0.0, n=800)
    rng = np.random.default_rng(1)
    y = y.copy()
    y[:, 0] += 0.1 * np.sqrt(8.0) * rng.normal(size=len(y))
    state, _ = run(config(tracking=0.01), theta0, z, y, s2)
    ratio = np.asarray(state.noise_ratio)
    assert 6.0 < ratio[0] < 12.0 and np.all(np.abs(ratio[1:] - 1.0) < 0.5), ratio
    _, untracked = run(config(threshold=0.5), theta0, z, y, s2)
    _, tracked = run(config(tracking=0.05, threshold=0.5), theta0, z, y, s2)
    assert declared_steps(tracked).size <= declared_steps(untracked).size


def test_numpy_declaration_matches_the_library():
    rng = np.random.default_rng(3)
    prob = rng.uniform(size=300) ** 3
    for threshold, refractory in ((0.5, 0), (0.3, 4), (0.8, 20)):
        det = adaptation.init_detector()
        lib = []
        for k, p in enumerate(prob):
            det, d, _ = adaptation.declare(det, p, k, threshold, refractory)
            lib.append(bool(d))
        assert np.array_equal(cp.declare(prob, threshold, refractory), np.array(lib))


def test_release_scoring():
    dt = cp.DT
    n = 200
    release = {"t_release": 100 * dt, "minutes": n * dt / 60.0}
    steady = {"t_release": float("nan"), "minutes": 2.0}

    def flags(*steps, length=n):
        f = np.zeros(length, bool)
        f[list(steps)] = True
        return f

    flights = [release, release, release, steady]
    declared = [
        flags(103),  # hit after 0.15 s
        flags(40, 101, 104),  # a false alarm, a hit after 0.05 s, a second one in the window
        flags(100, 106),  # at the release (not after it) and 0.3 s after: two false alarms
        flags(5, 50, 500, length=2400),  # three false alarms in 2 minutes of steady flight
    ]
    s = cp.score(flights, declared)
    assert s["flights"] == 3
    assert s["release_hit_rate"] == pytest.approx(2 / 3)
    assert s["release_delay_s_median"] == pytest.approx(0.1)
    assert s["false_alarms_per_flight"] == pytest.approx(4 / 3)
    assert s["false_alarms_per_min_steady"] == pytest.approx(1.5)
    assert s["precision"] == pytest.approx(2 / 9)
    assert s["f1"] == pytest.approx(4 / 12)
