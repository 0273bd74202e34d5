"""MLP residual baseline: offline fit, last-layer SGD on the buffer, unscented transform."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from arcade_core.baselines import mlp


def _truth(x, u):
    return jnp.stack([jnp.sin(2.0 * x[:, 0]), 0.5 * x[:, 1] * u[:, 0]], axis=1)


@pytest.fixture(scope="module")
def data():
    k1, k2 = jax.random.split(jax.random.PRNGKey(0))
    x = jax.random.uniform(k1, (1024, 2), minval=-1.5, maxval=1.5)
    u = jax.random.uniform(k2, (1024, 1), minval=-1.0, maxval=1.0)
    return x, u, _truth(x, u)


@pytest.fixture(scope="module")
def trained(data):
    x, u, delta = data
    model = mlp.init_model(jax.random.PRNGKey(1), x, u, delta, hidden=(16, 16))
    losses = []
    model = mlp.train(
        model,
        x,
        u,
        delta,
        key=jax.random.PRNGKey(2),
        epochs=60,
        batch_size=64,
        learning_rate=1e-2,
        callback=lambda epoch, loss: losses.append((epoch, loss)),
    )
    return model, losses


def test_offline_training_fits(data, trained):
    model, losses = trained
    assert [e for e, _ in losses] == list(range(60))
    assert losses[-1][1] < 0.05 * losses[0][1]
    x, u, delta = data
    pred = jax.vmap(model)(jnp.concatenate([x, u], axis=1))
    rel = np.sqrt(np.mean((np.asarray(pred - delta)) ** 2, axis=0)) / np.std(np.asarray(delta), 0)
    assert np.all(rel < 0.1)


def test_paper_architectures_build(data):
    x, u, delta = data
    for hidden in (mlp.CARTPOLE_HIDDEN, mlp.QUADROTOR_HIDDEN):
        # Shapes only (no compilation): eval_shape traces the constructor abstractly.
        model = jax.eval_shape(
            lambda h=hidden: mlp.init_model(jax.random.PRNGKey(0), x, u, delta, h)
        )
        assert [layer.weight.shape[0] for layer in model.hidden] == list(hidden)
        assert model.hidden[0].weight.shape == (hidden[0], 3)
        assert model.head.weight.shape == (2, hidden[-1])


def test_last_layer_sgd_reduces_buffer_loss(data, trained):
    model, _ = trained
    x, u, delta = data
    state = mlp.init(model, state_std=jnp.zeros(2), control_std=jnp.zeros(1), learning_rate=0.05)
    # A shifted regime: the residual moved by a constant the network has not seen.
    shifted = delta + jnp.array([0.4, -0.3])
    z = jnp.concatenate([x[:50], u[:50]], axis=1)
    state = state._replace(
        buffer=state.buffer._replace(inputs=z, targets=shifted[:50], count=jnp.asarray(50))
    )
    before = float(mlp.buffer_loss(state))
    step = jax.jit(mlp.sgd_last_layer)
    after_one = step(state)
    assert float(mlp.buffer_loss(after_one)) < before
    # Only the last layer moved.
    for a, b in zip(state.model.hidden, after_one.model.hidden):
        np.testing.assert_array_equal(a.weight, b.weight)
    assert not np.allclose(state.model.head.bias, after_one.model.head.bias)
    s = state
    for _ in range(100):
        s = step(s)
    assert float(mlp.buffer_loss(s)) < 0.2 * before
    # The paper's step size (1e-6) moves the weights only a little, but still downhill.
    tiny = step(state._replace(learning_rate=jnp.asarray(1e-6)))
    assert 0.0 < before - float(mlp.buffer_loss(tiny)) < 1e-3 * before


def test_update_pushes_then_steps(data, trained):
    model, _ = trained
    x, u, delta = data
    state = mlp.init(model, jnp.zeros(2), jnp.zeros(1), capacity=50, learning_rate=0.05)
    upd = jax.jit(mlp.update)
    shifted = delta + 0.5
    for i in range(60):
        state = upd(state, x[i], u[i], shifted[i])
    assert int(state.buffer.count) == 50
    np.testing.assert_allclose(
        np.sort(np.asarray(state.buffer.targets[:, 0])), np.sort(np.asarray(shifted[10:60, 0]))
    )
    # 60 SGD steps on the shifted data reduce the buffer loss of the offline network.
    offline = float(mlp.buffer_loss(state._replace(model=model)))
    assert float(mlp.buffer_loss(state)) < 0.5 * offline
    np.testing.assert_array_equal(state.model.hidden[0].weight, model.hidden[0].weight)


def test_unscented_transform_variance(trained):
    model, _ = trained
    xq, uq = jnp.array([0.3, -0.7]), jnp.array([0.4])
    predict = jax.jit(mlp.predict)
    zero = mlp.init(model, jnp.zeros(2), jnp.zeros(1))
    mean, var = predict(zero, xq, uq)
    np.testing.assert_allclose(mean, model(jnp.r_[xq, uq]), atol=1e-12)
    assert np.all(np.abs(np.asarray(var)) < 1e-20)
    noisy = mlp.init(model, jnp.array([0.05, 0.05]), jnp.zeros(1))
    _, var = predict(noisy, xq, uq)
    assert np.all(np.asarray(var) > 1e-8)


def test_unscented_transform_is_exact_for_linear_maps():
    a = jnp.array([[1.0, -2.0, 0.5], [0.0, 3.0, 1.0]])
    mean = jnp.array([0.1, 0.2, -0.3])
    sqrt_cov = jnp.array([[0.2, 0.0, 0.0], [0.1, 0.3, 0.0], [0.0, -0.1, 0.4]])
    out_mean, out_var = mlp.unscented_transform(lambda z: a @ z, mean, sqrt_cov)
    cov = sqrt_cov @ sqrt_cov.T
    np.testing.assert_allclose(out_mean, a @ mean, atol=1e-12)
    np.testing.assert_allclose(out_var, jnp.diag(a @ cov @ a.T), rtol=1e-10)
