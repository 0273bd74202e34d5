"""Proto-MPC baseline (arcade_core.baselines.proto): prototypes anchor tasks, the
context picks the task online, and an unseen task interpolates between prototypes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from arcade_core.baselines import proto


def _tasks(key, offsets, n=400):
    """Residual = a task-specific offset + a shared function of x, in separate flights."""
    xs, us, ds, task, seg = [], [], [], [], []
    for i, off in enumerate(offsets):
        k1, k2, key = jax.random.split(key, 3)
        x = jax.random.normal(k1, (n, 2))
        u = jax.random.normal(k2, (n, 1))
        d = jnp.stack([off + 0.5 * jnp.sin(x[:, 0]), 0.3 * u[:, 0]], axis=1)
        xs.append(x), us.append(u), ds.append(d)
        task.append(jnp.full(n, i)), seg.append(jnp.full(n, i))
    cat = lambda a: jnp.concatenate(a)  # noqa: E731
    return cat(xs), cat(us), cat(ds), cat(task), cat(seg)


@pytest.fixture(scope="module")
def model():
    """Trained once for the module: tasks with offsets -1 and +1."""
    offsets = (-1.0, 1.0)
    x, u, d, task, seg = _tasks(jax.random.PRNGKey(0), offsets)
    m = proto.init_model(jax.random.PRNGKey(1), x, u, d, tasks=offsets, hidden=32)
    return proto.train(m, x, u, d, task, seg, key=jax.random.PRNGKey(2), steps=1500, batch_size=64)


def _online(model, offset, key, steps=30):
    """Online one-step errors with a context drawn from a task with ``offset``."""
    state = proto.init(model)
    errs, att = [], None
    for k in jax.random.split(key, steps):
        x = jax.random.normal(k, (2,))
        u = jax.random.normal(jax.random.fold_in(k, 1), (1,))
        d = jnp.stack([offset + 0.5 * jnp.sin(x[0]), 0.3 * u[0]])
        errs.append(float(jnp.abs(proto.predict_mean(model, state, x, u) - d)[0]))
        state = proto.update(state, x, u, d)
        att = proto.attention(model, state)
    return np.array(errs), np.asarray(att)


def test_the_context_selects_the_task_and_fits_it(model):
    for i, off in enumerate((-1.0, 1.0)):
        errs, att = _online(model, off, jax.random.PRNGKey(10 + i))
        assert att[i] > 0.9, att
        # With a full context the task's offset is recovered.
        assert np.mean(errs[proto.CONTEXT :]) < 0.15, errs


def test_an_empty_context_attends_uniformly(model):
    att = proto.attention(model, proto.init(model))
    np.testing.assert_allclose(np.asarray(att), 0.5, atol=1e-6)


def test_an_unseen_task_is_between_the_prototypes(model):
    errs, att = _online(model, 0.0, jax.random.PRNGKey(20))
    # Halfway between the two tasks: both prototypes share the weight, and the
    # interpolated prediction is closer than either task's own offset (error 1).
    assert 0.1 < att[0] < 0.9, att
    assert np.mean(errs[proto.CONTEXT :]) < 0.6, errs
