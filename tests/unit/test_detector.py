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


def config(
    scale=(1.0, 1.0, 1.0),
    tracking=0.0,
    threshold=0.9,
    window=5,
    refractory=5,
    block=1,
    whiten=0.0,
    energy=(0.0, 0.0, 0.0),
    gain=0.0,
    rate=0.2,
):
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
        block=block,
        whiten=whiten,
        energy_outputs=jnp.asarray(energy, jnp.float64),
        energy_gain=gain,
        energy_rate=rate,
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


def test_a_block_is_the_beam_learning_the_sums_of_its_transitions():
    """Brute force: with ``block = 3`` the beam is, after every third transition, the one
    that learns each block's sums with the sums of the noise; the probability is held
    between blocks, and a declaration is dated in transitions."""
    shift = np.zeros((D, L))
    shift[0, 0] = 1.5
    theta0, z, y, s2 = sequence(60, shift, n=90)
    b = 3
    # The refractory period counts transitions: 5 blocks are 15 of them.
    state, det = run(config(block=b, refractory=5 * b), theta0, z, y, s2)
    sums = [a.reshape(-1, b, a.shape[1]).sum(1) for a in (z, y, s2)]
    ref_state, ref = run(config(), theta0, *sums)
    np.testing.assert_allclose(state.beam.means, ref_state.beam.means, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(state.beam.log_scores, ref_state.beam.log_scores, atol=1e-9)
    prob = np.asarray(det.probability)
    np.testing.assert_allclose(prob[b - 1 :: b], np.asarray(ref.probability), atol=1e-12)
    assert np.all(prob[b::b] == prob[b - 1 : -1 : b])  # held until the next block
    (blocks,) = np.nonzero(np.asarray(ref.declared))
    np.testing.assert_array_equal(declared_steps(det), blocks * b + b - 1)
    # Block k (from 0) holds transitions 3k + 1 .. 3k + 3, counted from 1.
    assert np.array_equal(
        np.asarray(det.dated)[declared_steps(det)], (np.asarray(ref.dated)[blocks] - 1) * b + 1
    )
    assert int(state.steps) == 90 and int(state.beam.step) == 30


#: Step of the shift in :func:`estimated_states`.
CHANGE = 250


def estimated_states(seed, n=400, e_std=0.1):
    """Residuals of estimated states, ``delta_k = theta z_k + e_{k+1} - e_k`` (features: an
    intercept and a random one), whose intercept shifts by 1.4 times a residual's noise at
    step :data:`CHANGE`: ``(theta, z, y, s2)`` with ``s2`` a one-step residual's variance."""
    rng = np.random.default_rng(seed)
    theta = np.array([[1.0, 0.5], [-0.3, 0.2], [0.0, 1.0]])
    z = np.stack([np.ones(n), rng.normal(size=n)], 1)
    e = e_std * rng.normal(size=(n + 1, D))
    y = z @ theta.T + e[1:] - e[:-1]
    y[CHANGE:, 0] += 0.2
    return theta, z, y, np.full((n, D), 2 * e_std**2)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_blocks_see_a_shift_through_the_noise_of_a_state_estimate(seed):
    """Residuals of estimated states, ``delta_k = theta z_k + e_{k+1} - e_k``, and a shift of
    the intercept by 1.4 times a residual's noise at step 250: a detector learning blocks
    of 4 (their noise calibrated: a block's sum carries ``e`` of its two ends only, so
    ``noise_scale = 1 / 4`` of four transitions' noise) declares it once, within 3 blocks;
    one learning every transition does not (its probability at the change stays below
    the threshold that the block detector clears)."""
    theta, z, y, s2 = estimated_states(seed)

    def detect(b):
        cfg = config(block=b, threshold=0.7, refractory=40, window=8 // b)
        _, det = run(cfg._replace(noise_scale=jnp.full(D, 1.0 / b)), theta, z, y, s2)
        return declared_steps(det)

    blocks = detect(4)
    assert blocks.size == 1 and CHANGE <= blocks[0] < CHANGE + 12, blocks
    single = detect(1)
    assert not np.any((single >= CHANGE) & (single < CHANGE + 12)), single


def test_whitening_is_the_plain_detector_on_the_filtered_sequence():
    """Brute force: with ``whiten = c`` (and blocks of 2) the detector is the one with
    ``whiten = 0`` fed ``x~_k = x_k + c x~_{k-1}`` of the features and the residuals over
    the transitions learned, with the noise divided by ``1 + c^2``; a transition not
    learned leaves the filter as it was."""
    shift = np.zeros((D, L))
    shift[1, 1] = 1.0
    theta0, z, y, s2 = sequence(50, shift, n=90)
    learn = np.ones(len(z), bool)
    learn[[10, 11, 40]] = False
    c = 0.8
    state, det = run(config(whiten=c, block=2), theta0, z, y, s2, learn)
    zf, yf = np.zeros_like(z), np.zeros_like(y)
    pz, py = np.zeros(L), np.zeros(D)
    for k in range(len(z)):
        if learn[k]:
            pz, py = z[k] + c * pz, y[k] + c * py
        zf[k], yf[k] = pz, py
    ref_state, ref = run(config(block=2), theta0, zf, yf, s2 / (1 + c * c), learn)
    np.testing.assert_allclose(state.beam.means, ref_state.beam.means, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(state.beam.log_scores, ref_state.beam.log_scores, atol=1e-9)
    np.testing.assert_allclose(det.probability, ref.probability, atol=1e-12)
    np.testing.assert_array_equal(det.declared, ref.declared)
    np.testing.assert_array_equal(det.dated, ref.dated)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_whitening_sees_a_shift_through_the_noise_of_a_state_estimate(seed):
    """The residuals of the block test above (``e_{k+1} - e_k`` noise, an intercept shift
    of 1.4 times a residual's noise at step 250): the detector that whitens them with
    ``c = 0.8`` (the moving average's own ``c`` is 1) declares the shift once, within 12
    transitions, each transition its own update; the plain one does not."""
    theta, z, y, s2 = estimated_states(seed)

    def detect(c):
        cfg = config(whiten=c, threshold=0.7, refractory=40, window=8)
        _, det = run(cfg, theta, z, y, s2)
        return declared_steps(det)

    white = detect(0.8)
    assert white.size == 1 and CHANGE <= white[0] < CHANGE + 12, white
    plain = detect(0.0)
    assert not np.any((plain >= CHANGE) & (plain < CHANGE + 12)), plain


def energy_sequence(seed=0, n=200, burst=(60, 100), change=150):
    """Outputs 0 and 1 watched, output 2 left out (an infinite noise scale) and read for
    its energy: a burst of output 2 (ten times its noise) over ``burst`` with a shift of
    output 0 inside it (a transient the vehicle's own motion explains), and a lasting
    shift of output 0 at ``change`` with output 2 quiet."""
    theta0, z, y, s2 = sequence(None, 0.0, n=n, seed=seed)
    rng = np.random.default_rng(seed + 10)
    y = y.copy()
    a, b = burst
    y[a:b, 2] += 1.0 * rng.normal(size=b - a)
    y[a + 10 : b - 10, 0] += 0.4
    y[change:, 0] += 0.4
    return theta0, z, y, s2


def test_energy_is_the_plain_detector_with_the_noise_scaled_by_it():
    """Brute force: with ``energy_gain = kappa`` the detector is the one without, fed the
    learner's noise times ``1 + kappa max(0, h_{k-1} - 1)`` at each step, ``h`` the
    exponential average (rate ``a``) over the transitions learned of ``(delta - theta_0
    z)^2 / sigma^2`` on the outputs named (weights), taken before the whitening."""
    theta0, z, y, s2 = energy_sequence()
    learn = np.ones(len(z), bool)
    learn[[30, 31, 90]] = False
    kappa, a, w = 3.0, 0.3, np.array([0.0, 0.5, 1.0])
    scale = (1.0, 1.0, np.inf)
    cfg = config(scale=scale, whiten=0.5, energy=w, gain=kappa, rate=a)
    state, det = run(cfg, theta0, z, y, s2, learn)
    h, factor = 1.0, np.ones(len(z))
    for k in range(len(z)):
        factor[k] = 1.0 + kappa * max(0.0, h - 1.0)
        if learn[k]:
            q = (y[k] - theta0 @ z[k]) ** 2 / s2[k]
            h = (1 - a) * h + a * float(np.sum(w * q) / np.sum(w))
    ref_state, ref = run(config(scale=scale, whiten=0.5), theta0, z, y, s2 * factor[:, None], learn)
    assert float(state.energy) == pytest.approx(h, rel=1e-12)
    assert factor.max() > 10.0  # the burst did inflate the noise
    np.testing.assert_allclose(state.beam.means, ref_state.beam.means, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(det.probability, ref.probability, atol=1e-12)
    np.testing.assert_array_equal(det.declared, ref.declared)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_energy_discounts_a_shift_inside_a_burst_and_keeps_a_lasting_one(seed):
    """The shift of output 0 inside the burst of output 2 is declared without the energy
    knob and not with it; the lasting shift with output 2 quiet is declared by both."""
    theta0, z, y, s2 = energy_sequence(seed)
    scale = (1.0, 1.0, np.inf)

    def detect(gain):
        cfg = config(scale=scale, energy=(0.0, 0.0, 1.0), gain=gain, threshold=0.9, refractory=20)
        return declared_steps(run(cfg, theta0, z, y, s2)[1])

    plain, discounted = detect(0.0), detect(1.0)
    assert np.any((plain >= 70) & (plain < 90)), plain
    assert not np.any((discounted >= 60) & (discounted < 140)), discounted
    for steps in (plain, discounted):
        assert np.sum((steps >= 150) & (steps < 160)) == 1, steps


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
    labelled = [
        {**f, "label": label} for f, label in zip(flights, ("a", "a", "b", "steady"), strict=True)
    ]
    cells = cp.by_cell(labelled, declared)
    assert cells == {
        "a": {"hits": 2, "flights": 2, "false_alarms": 2},
        "b": {"hits": 0, "flights": 1, "false_alarms": 2},
        "steady": {"hits": 0, "flights": 1, "false_alarms": 3},
    }


def test_the_flagships_events_are_what_it_declared_in_its_own_flights(monkeypatch):
    """``flagship_events`` flies ``arcade`` at the stack's stored knobs on the estimate with
    the link delay compensated, every flight of :func:`plans`, and scores the changepoint
    column of its own diagnostics (no replay)."""
    from types import SimpleNamespace

    from benchmarks import quadrotor_flights
    from benchmarks.quadrotor_protocol import stored_knobs

    dt, n = cp.DT, 300
    calls = []

    class FakeRunner:
        def __init__(self, models):
            self.models = models

        def fly(self, method, scenario, seed, estimated, compensate_delay):
            calls.append((method, seed, estimated, compensate_delay, self.models.closedloop))
            diag = np.zeros((n, 17))
            released = scenario.release_fraction >= 0
            diag[103 if released else 7, quadrotor_flights.DIAG_CHANGEPOINT] = 1.0
            return SimpleNamespace(
                t_release=100 * dt if released else float("nan"),
                t=np.arange(n) * dt,
                diag=diag,
                learning=None,
                crashed=False,
            )

    monkeypatch.setattr(quadrotor_flights, "Runner", FakeRunner)
    models = SimpleNamespace(vld=None, guard=None, closedloop={"ignored": 1})
    r = cp.flagship_events(models, [0, 1], lambda msg: None)
    assert len(calls) == 2 * len(cp.plans())
    assert {c[:1] + c[2:4] for c in calls} == {("arcade", True, True)}
    assert all(c[4] == stored_knobs("stack") for c in calls)
    assert r["method"] == "arcade" and r["flights"] == 18
    assert r["release_hit_rate"] == 1.0 and r["false_alarms_per_flight"] == 0.0
    assert r["false_alarms_per_min_steady"] > 0.0  # one declaration in each steady flight
    assert r["precision"] == pytest.approx(18 / 22)
    assert r["by_cell"]["steady, rigid"] == {"hits": 0, "flights": 2, "false_alarms": 2}
    assert r["by_cell"]["75 g, 2.5 m/s"] == {"hits": 2, "flights": 2, "false_alarms": 0}
