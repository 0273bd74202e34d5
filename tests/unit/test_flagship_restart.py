"""The flagship's restart at a detected change (float64): its detector is the adapter's,
a declaration puts the learner back at the offline prior's mean with the scaled prior
covariance, and without one the learner is the forgetting learner alone."""

from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from arcade.training_quadrotor import QUADROTOR_WEIGHTS
from arcade_control.detection import detection_config
from arcade_control.guard import guard_from_metadata
from arcade_control.knobs import DETECTION_DEFAULTS, DETECTION_TRUE_STATE
from arcade_control.learners import initial_learner, per_output_noise
from arcade_control.methods import make_method, restart_at_change
from arcade_control.nominal import CONTROL_DT, f_nom, nominal_params
from arcade_core.dynamics import quadrotor_step
from arcade_io.weights import load_model

SCALE = 0.01


@pytest.fixture(scope="module")
def models():
    vld, _, extra = load_model(QUADROTOR_WEIGHTS)
    knobs = {"arcade_lambda": 0.9, "arcade_restart_scale": SCALE, "arcade_sigma2": 1e-3}
    return SimpleNamespace(vld=vld, guard=guard_from_metadata(extra), closedloop=knobs)


def _transition(dz: float):
    xp = np.r_[0.1, -0.2, 1.0, 0.3, 0.1, -0.05, 1.0, 0.0, 0.0, 0.0, 0.05, -0.02, 0.01]
    up = np.array([7.2, 0.1, -0.05, 0.02])
    x = np.asarray(quadrotor_step(jnp.asarray(xp), jnp.asarray(up), nominal_params(), CONTROL_DT))
    return xp, up, x + np.r_[np.zeros(5), dz, np.zeros(7)]


def _close(a, b, **kw) -> None:
    for u, v in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(u), np.asarray(v), **kw)


def test_the_flagship_carries_the_adapters_detector_and_a_scaled_prior(models):
    a = initial_learner("arcade", models, jnp.float64)
    r = a.restart
    assert r is not None
    assert initial_learner("arcade_no_restart", models, jnp.float64).restart is None
    _close(r.config, detection_config(dtype=jnp.float64, estimated=False))
    # On a state estimate it flies the whitening detector, on the ground truth the plain one.
    on_estimate = initial_learner("arcade", models, jnp.float64, estimated=True).restart
    _close(on_estimate.config, detection_config(dtype=jnp.float64, estimated=True))
    assert float(on_estimate.config.whiten) == DETECTION_DEFAULTS["whiten"] > 0
    assert float(r.config.whiten) == DETECTION_TRUE_STATE["whiten"] == 0
    np.testing.assert_allclose(r.prior.means, a.beam.means)
    np.testing.assert_allclose(r.prior.sqrt_covariances, a.beam.sqrt_covariances * np.sqrt(SCALE))
    # One noise per output: the prior it restarts to has the learner's layout.
    b = per_output_noise(a)
    assert b.restart.prior.sqrt_covariances.shape == b.beam.sqrt_covariances.shape
    np.testing.assert_allclose(b.restart.base_sigma2, b.config.sigma2)


def test_a_declared_change_restarts_the_learner_at_the_scaled_prior(models):
    a = initial_learner("arcade_no_l1", models, jnp.float64)
    method = make_method("arcade_no_l1")
    assert method.changepoints
    xp, up, x = _transition(-0.05)
    learned = jax.jit(method.learn)(a, xp, up, x)
    moved = float(jnp.abs(learned.beam.means - a.beam.means).max())
    assert moved > 1e-6 and float(learned.changepoint) == 0.0  # learned, nothing declared
    # The same step with a detector that declares at once.
    r = a.restart
    eager = r._replace(config=r.config._replace(threshold=jnp.asarray(-1.0)))
    out = jax.jit(method.learn)(a._replace(restart=eager), xp, up, x)
    assert float(out.changepoint) == 1.0
    # At the prior, still counting the steps (the detector's count), dated to this one.
    _close(out.beam._replace(step=r.prior.step), r.prior)
    assert int(out.beam.step) == int(learned.beam.step) == 1
    assert 0 <= int(out.restart.dated) <= int(out.beam.step)
    # restart_at_change on its own: the flag, the probability and the detector's state.
    z = method.features(a, xp, up)[:-1]  # the VLD's features, without the intercept
    dn = a.vld.normalise_residual(x - f_nom(xp, up))
    same = restart_at_change(a._replace(restart=eager), z, dn)
    _close(same.beam._replace(step=r.prior.step), r.prior)
    assert int(same.beam.step) == int(a.beam.step)
    assert float(same.cp_prob) == pytest.approx(float(out.cp_prob), abs=1e-12)
    assert int(same.restart.detection.beam.step) == int(r.detection.beam.step) + 1


def test_without_a_declaration_it_is_the_forgetting_learner(models):
    a = initial_learner("arcade", models, jnp.float64)
    plain = initial_learner("arcade_no_restart", models, jnp.float64)
    for dz in (0.0, -0.01):  # the first step synchronises the augmentation's predictor
        xp, up, x = _transition(dz)
        a = jax.jit(make_method("arcade").learn)(a, xp, up, x)
        plain = jax.jit(make_method("arcade_no_restart").learn)(plain, xp, up, x)
    assert float(a.changepoint) == 0.0
    _close(a.beam, plain.beam, rtol=1e-12, atol=1e-14)
    _close(a.l1, plain.l1, rtol=1e-12, atol=1e-14)
