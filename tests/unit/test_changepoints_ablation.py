"""The forgetting ablation of ``arcade eval changepoints``: BLR with exponential forgetting
against its information-form recursion, the innovation test, and the ablation end to end on
synthetic flights with a known change."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from arcade_control.learners import forgetting_config
from arcade_control.nominal import CONTROL_DT as DT
from arcade_core import adaptation as A
from benchmarks import changepoints_ablation as cab


def test_forgetting_equals_the_information_form_recursion():
    """K = 1, pi = 1: every step is ``P = lambda P + rho (1 - lambda) / tau^2 I + z z^T /
    sigma^2`` and ``P mu = lambda P mu + rho (1 - lambda) / tau^2 theta_0 + z delta /
    sigma^2`` (float64, written from the formulas, no shared code)."""
    rng = np.random.default_rng(0)
    d, l, lam, tau2, floor = 2, 3, 0.9, 0.1, 1.0
    s2 = np.array([0.05, 0.2])
    theta0 = rng.normal(size=(d, l))
    cfg = forgetting_config(
        A.AdaptationConfig(K=15, pi=0.05, beta=0.5, tau2=tau2, sigma2=s2, prior_floor=floor), lam
    )
    assert (cfg.K, cfg.pi, cfg.score) == (1, 1.0, "joint")
    state = A.init(theta0, cfg)
    prec = [np.eye(l) / tau2 for _ in range(d)]
    info = [theta0[j] / tau2 for j in range(d)]
    c = floor * (1.0 - lam) / tau2
    update = jax.jit(A.update)
    for _ in range(30):
        z, delta = rng.normal(size=l), rng.normal(size=d)
        state, _ = update(state, z, delta, cfg)
        for j in range(d):
            prec[j] = lam * prec[j] + c * np.eye(l) + np.outer(z, z) / s2[j]
            info[j] = lam * info[j] + c * theta0[j] + z * delta[j] / s2[j]
    for j in range(d):
        cov = np.linalg.inv(prec[j])
        np.testing.assert_allclose(np.asarray(state.covariances[0, j]), cov, atol=1e-10)
        np.testing.assert_allclose(np.asarray(state.means[0, j]), cov @ info[j], atol=1e-8)


@pytest.mark.parametrize("lam", [0.0, 1.5])
def test_a_forgetting_factor_outside_0_1_is_refused(lam):
    with pytest.raises(ValueError, match="forgetting factor"):
        forgetting_config(A.quadrotor_config(), lam)


def test_the_innovation_test_declares_a_lasting_shift_once():
    n = 200
    rng = np.random.default_rng(1)
    err = rng.normal(size=(n, 13))
    err[120:, 2] += 4.0  # the vertical velocity's residual shifts
    var, learned = np.ones((n, 13)), np.ones(n, bool)
    knobs = {"outputs": "vertical", "window": 5, "threshold": 5.0, "refractory_steps": 500}
    declared = cab.innovation_test(err, var, learned, knobs)
    assert np.flatnonzero(declared).tolist() == [np.flatnonzero(declared)[0]]
    assert 120 <= np.flatnonzero(declared)[0] <= 125
    # Nothing on steps that were not learned, nothing without the shift.
    assert not cab.innovation_test(err, var, np.zeros(n, bool), knobs).any()
    assert not cab.innovation_test(err[:120], var[:120], learned[:120], knobs).any()


def _flight(rng, theta0, release: int | None, n: int = 300) -> tuple[dict, tuple]:
    """A synthetic flight: features, residuals of ``theta z + noise`` whose decoder shifts
    after the step ``release`` (as in a flight, whose record at step ``k`` is the
    transition into ``x_k``), and the replay inputs ``(z, dn, sigma2, learned)``."""
    d, l = theta0.shape
    z = rng.normal(size=(n, l))
    theta = np.repeat(theta0[None], n, axis=0)
    if release is not None:
        theta[release + 1 :, 2] += 1.5  # the vertical outputs change
        theta[release + 1 :, 5] -= 1.5
    dn = np.einsum("kdl,kl->kd", theta, z) + 0.1 * rng.normal(size=(n, d))
    flight = {
        "t_release": release * DT if release is not None else float("nan"),
        "minutes": n * DT / 60.0,
    }
    return flight, (z, dn, np.full((n, d), 0.01), np.ones(n, bool))


def test_the_ablation_tunes_forgetting_and_scores_both_on_the_same_flights():
    rng = np.random.default_rng(2)
    theta0 = 0.3 * rng.normal(size=(13, 4))
    tune = [_flight(rng, theta0, r) for r in (150, 200, None)]
    ev = [_flight(rng, theta0, r) for r in (120, 180, None)]
    detector = {"release_hit_rate": 1.0}
    out = cab.run_ablation(
        theta0,
        [f for f, _ in ev],
        [i for _, i in ev],
        [f for f, _ in tune],
        [i for _, i in tune],
        detector=detector,
    )
    assert out["tuned"] and out["lambda"] in cab.LAMBDAS
    assert len(out["lambda_tuning"]) == len(cab.LAMBDAS)
    best = min(out["lambda_tuning"], key=lambda r: r["nll"])
    assert out["lambda"] == best["lambda"]
    p = out["prediction"]
    # After the change, a learner that can forget re-adapts; plain BLR is stuck with the
    # evidence of the old decoder.
    assert p["forgetting"]["rmse_after_release"] < p["no_changepoints"]["rmse_after_release"]
    assert p["beam"]["rmse_after_release"] < p["no_changepoints"]["rmse_after_release"]
    assert out["detection"]["beam_detector"] is detector
    test = out["detection"]["forgetting_innovation_test"]
    assert test["flights"] == 2 and test["release_hit_rate"] == 1.0
    assert set(out["innovation_test_knobs"]) >= set(cab.TEST_GRID)
    lines = cab.format_table({**out, "detection": {"forgetting_innovation_test": test}})
    assert any(line.startswith("forgetting ") for line in lines)


def test_without_tuning_flights_the_stored_knobs_are_used():
    rng = np.random.default_rng(3)
    theta0 = 0.3 * rng.normal(size=(13, 4))
    f, i = _flight(rng, theta0, 150)
    out = cab.run_ablation(theta0, [f], [i], None, None, detector={})
    assert not out["tuned"] and out["lambda"] == cab.STORED_LAMBDA
    assert out["innovation_test_knobs"] == cab.STORED_TEST
    assert out["lambda_tuning"] == [] and out["innovation_test_tuning"] == []
