"""Heavy-tailed hypothesis scores (``AdaptationConfig.nu``): the Student-t of Eq. 8 against
SciPy, the Gaussian limit, an outlier that is not a change, a shift that is, the packed
step, and ``nu`` static like ``score``."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from arcade_core import adaptation as A
from arcade_core.adaptation.posterior import _log_marginal


def test_student_t_marginal_matches_scipy():
    rng = np.random.default_rng(0)
    K, d = 3, 4
    q, r = rng.uniform(0.1, 2.0, size=(K, d)), rng.normal(size=(K, d))
    sigma2, gamma = rng.uniform(0.05, 0.5, size=d), 0.3
    for nu in (1.0, 3.0, 10.0):
        s = q / gamma + sigma2
        expected = stats.t.logpdf(r, df=nu, scale=np.sqrt(s)).sum(axis=1)
        got = np.asarray(_log_marginal(jnp.asarray(q), jnp.asarray(r), sigma2, gamma, nu))
        np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)
    gauss = stats.norm.logpdf(r, scale=np.sqrt(q / gamma + sigma2)).sum(axis=1)
    np.testing.assert_allclose(np.asarray(_log_marginal(q, r, sigma2, gamma)), gauss, rtol=1e-12)
    np.testing.assert_allclose(
        np.asarray(_log_marginal(q, r, sigma2, gamma, 1e5)), gauss, rtol=0, atol=1e-4
    )


def _config(nu: float) -> A.AdaptationConfig:
    return A.AdaptationConfig(
        K=10, pi=0.02, beta=0.3, tau2=0.1, sigma2=0.01, prior_floor=1.0, score="joint", nu=nu
    )


def _run(cfg, deltas, z):
    """The beam over ``deltas`` (one scan: compiled once, not op by op per step)."""

    def body(state, delta):
        state, info = A.update(state, z, delta[None], cfg)
        return state, info.changepoint

    state, flags = jax.jit(lambda s, d: jax.lax.scan(body, s, d))(
        A.init(np.zeros((1, 2)), cfg), jnp.asarray(deltas)
    )
    return state, np.asarray(flags, bool)


def test_an_outlier_is_a_change_for_the_gaussian_and_not_for_heavy_tails():
    z = np.array([1.0, 0.5])
    rng = np.random.default_rng(1)
    deltas = 0.1 * rng.normal(size=60)
    deltas[30] += 1.5  # one jolt, then the same regime
    _, gauss = _run(_config(math.inf), deltas, z)
    _, heavy = _run(_config(3.0), deltas, z)
    assert gauss[30:33].any()
    assert not heavy.any()


def test_a_lasting_shift_is_a_change_with_heavy_tails_too():
    z = np.array([1.0, 0.5])
    rng = np.random.default_rng(2)
    deltas = 0.1 * rng.normal(size=60)
    deltas[30:] += 1.5  # the regime changes for good
    state, heavy = _run(_config(3.0), deltas, z)
    assert heavy[30:36].any() and not heavy[:30].any()
    assert 30 <= int(A.map_last_changepoint(state)) <= 33


def test_the_config_pytree_and_the_packed_step_carry_nu():
    cfg = _config(4.0)
    leaves, tree = jax.tree.flatten(cfg)
    assert len(leaves) == 6 and jax.tree.unflatten(tree, leaves) == cfg
    rng = np.random.default_rng(3)
    state = A.init(rng.normal(size=(2, 3)), cfg._replace(sigma2=np.array([0.02, 0.05])))
    cfg = cfg._replace(sigma2=np.array([0.02, 0.05]))
    packed = A.pack(state, cfg)
    for _ in range(5):
        z, delta = rng.normal(size=3), rng.normal(size=2)
        state, pred, info = A.step(state, z, delta, cfg)
        packed, out = A.packed_step(packed, jnp.concatenate([z, delta, jnp.zeros(3)]))
        p_pred, p_info = A.unpack_outputs(np.asarray(out), 2, cfg.K)
        np.testing.assert_allclose(p_pred.mean, pred.mean, rtol=1e-12)
        np.testing.assert_allclose(p_info.log_evidence, info.log_evidence, rtol=1e-12)
    _, back = A.unpack(packed)
    assert back.nu == 4.0 and packed.nu == 4.0


def test_nu_is_static_like_score():
    traces = []

    def counted(state, config):
        traces.append(config.nu)
        return A.update(state, jnp.ones(2), jnp.ones(1), config)[0].log_scores

    f = jax.jit(counted)
    cfg = _config(math.inf)
    state = A.init(np.zeros((1, 2)), cfg)
    for pi in (0.02, 0.1):  # a traced hyperparameter: no retrace
        f(state, cfg._replace(pi=pi))
    f(state, cfg._replace(nu=5.0))  # another likelihood: one more trace
    assert traces == [math.inf, 5.0]
    with pytest.raises(ValueError, match="nu must be positive"):
        A.update(state, jnp.ones(2), jnp.ones(1), cfg._replace(nu=0.0))
