"""GP residual baseline: marginal-likelihood fit, interpolation, FIFO buffer, masking."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from arcade_core.baselines import gp


def _truth(x, u):
    return jnp.stack([jnp.sin(2.0 * x[:, 0]) + 0.3 * u[:, 0], x[:, 1] * jnp.cos(x[:, 0])], axis=1)


@pytest.fixture(scope="module")
def data():
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(0), 3)
    x = jax.random.uniform(k1, (200, 2), minval=-1.0, maxval=1.0)
    u = jax.random.uniform(k2, (200, 1), minval=-1.0, maxval=1.0)
    delta = _truth(x, u) + 0.01 * jax.random.normal(k3, (200, 2))
    return x, u, delta


@pytest.fixture(scope="module")
def model(data):
    x, u, delta = data
    return gp.fit(x, u, delta, num_points=100, num_steps=100, key=jax.random.PRNGKey(1))


@jax.jit
def _push_all(state, x, u, delta):
    def step(s, xs):
        return gp.update(s, *xs), None

    return jax.lax.scan(step, state, (x, u, delta))[0]


_predict = jax.jit(gp.predict)
_predict_many = jax.jit(jax.vmap(gp.predict, in_axes=(None, 0, 0)))
_condition = jax.jit(gp.condition)
_init = jax.jit(gp.init, static_argnames="capacity")


def test_marginal_likelihood_increases(data, model):
    x, u, delta = data
    s = model.standardizer
    z = (jnp.concatenate([x[:100], u[:100]], axis=1) - s.in_mean) / s.in_scale
    y = (delta[:100] - s.out_mean) / s.out_scale
    lml = jax.jit(gp.log_marginal_likelihood)
    before = lml(gp.initial_hyperparams(3, 2), z, y)
    after = lml(model.hyper, z, y)
    assert after.shape == (2,)
    # Improvement is large (per-output LML up by more than 50 nats), not marginal.
    assert np.all(np.asarray(after - before) > 50.0)
    # Output 0 depends on x0 and u, not on x1: ARD gives x1 the longest lengthscale there.
    ls = np.exp(np.asarray(model.hyper.log_lengthscale))
    assert ls[0, 1] > ls[0, 0]


def test_interpolates_known_function(data, model):
    x, u, delta = data
    state = _push_all(_init(model, capacity=50), x[:50], u[:50], delta[:50])
    kx, ku = jax.random.split(jax.random.PRNGKey(5))
    xt = jax.random.uniform(kx, (100, 2), minval=-0.9, maxval=0.9)
    ut = jax.random.uniform(ku, (100, 1), minval=-0.9, maxval=0.9)
    mean, var = _predict_many(state, xt, ut)
    rmse = np.sqrt(np.mean((np.asarray(mean) - np.asarray(_truth(xt, ut))) ** 2, axis=0))
    spread = np.std(np.asarray(_truth(xt, ut)), axis=0)
    assert np.all(rmse < 0.05 * spread)
    assert np.all(np.asarray(var) >= 0.0)
    # Far from the data the latent variance returns to the prior signal variance.
    _, var_far = _predict(state, x[0] + 50.0, u[0])
    prior = (
        np.exp(np.asarray(model.hyper.log_signal_var))
        * np.asarray(model.standardizer.out_scale) ** 2
    )
    np.testing.assert_allclose(np.asarray(var_far), prior, rtol=1e-6)
    assert np.all(np.asarray(var).max(axis=0) < 0.01 * prior)


def test_empty_gp_predicts_prior(model):
    state = _init(model, capacity=50)
    mean, var = _predict(state, jnp.zeros(2), jnp.zeros(1))
    np.testing.assert_allclose(mean, model.standardizer.out_mean, atol=1e-12)
    prior = (
        np.exp(np.asarray(model.hyper.log_signal_var))
        * np.asarray(model.standardizer.out_scale) ** 2
    )
    np.testing.assert_allclose(var, prior, rtol=1e-10)


def test_fifo_keeps_last_50_samples(data, model):
    x, u, delta = data
    state = _push_all(_init(model, capacity=50), x[:70], u[:70], delta[:70])
    assert int(state.buffer.count) == 50
    s = model.standardizer
    expected = (jnp.concatenate([x[20:70], u[20:70]], axis=1) - s.in_mean) / s.in_scale

    def rows(a):
        a = np.asarray(a)
        return a[np.lexsort(a.T[::-1])]

    np.testing.assert_allclose(rows(state.buffer.inputs), rows(expected), atol=1e-12)
    # Same predictions as a GP conditioned on exactly those samples (order does not matter).
    ref = _condition(model, x[20:70][::-1], u[20:70][::-1], delta[20:70][::-1])
    idx = jnp.array([0, 21, 77, 150])
    for a, b in zip(_predict_many(state, x[idx], u[idx]), _predict_many(ref, x[idx], u[idx])):
        np.testing.assert_allclose(a, b, atol=1e-8)


def test_masked_slots_do_not_change_predictions(data, model):
    x, u, delta = data
    state = _push_all(_init(model, capacity=50), x[:20], u[:20], delta[:20])
    # Fill the 30 empty slots with garbage, then push one more real sample.
    buf = state.buffer
    junk = state._replace(
        buffer=buf._replace(
            inputs=buf.inputs.at[20:].set(0.3), targets=buf.targets.at[20:].set(1e3)
        )
    )
    junk = jax.jit(gp.update)(junk, x[20], u[20], delta[20])
    assert int(junk.buffer.count) == 21
    ref = _condition(model, x[:21], u[:21], delta[:21])
    idx = jnp.array([3, 20, 100])
    for a, b in zip(_predict_many(junk, x[idx], u[idx]), _predict_many(ref, x[idx], u[idx])):
        np.testing.assert_allclose(a, b, atol=1e-8)


def test_update_and_predict_jit(model):
    state = _init(model, capacity=50)
    upd = jax.jit(gp.update)
    state = upd(state, jnp.ones(2), jnp.zeros(1), jnp.array([0.5, -0.5]))
    mean, var = _predict(state, jnp.ones(2), jnp.zeros(1))
    assert mean.shape == (2,) and var.shape == (2,)
    assert np.all(np.isfinite(np.asarray(mean)))
    # Conditioning on one exact sample pulls the mean towards it.
    prior_mean = np.asarray(model.standardizer.out_mean)
    assert np.all(np.abs(np.asarray(mean) - [0.5, -0.5]) < np.abs(prior_mean - [0.5, -0.5]))
