"""Prototype-attention residual model: the Proto-MPC baseline (paper Sec. V-B, Table II).

After Gu et al. (2024), "Proto-MPC: an encoder-prototype-decoder approach for quadrotor
control in challenging winds", written from that description and the paper's account of
it (tasks redefined by the rigidly attached payload mass):

- a *context encoder* maps each recent transition ``[x, u, delta]`` to an embedding; the
  context embedding ``e`` is their mean over the last ``H`` transitions;
- one learned *prototype* ``p_i`` per training task (payload mass); attention
  ``a = softmax(-|e - p_i|^2)`` over the prototypes;
- one *decoder* head per prototype on a shared trunk of ``[x, u]``; the residual is the
  attention-weighted average of the heads, ``delta = sum_i a_i head_i(trunk(x, u))``.

Offline, windows of ``H + 1`` consecutive transitions of one task are drawn: the first
``H`` form the context, the residual of the last is predicted (mean squared error in
standardised units), and a cross-entropy term on the attention logits anchors each
prototype to its task. Online nothing is trained: the context is a FIFO of the last
``H`` observed transitions, and a condition never seen offline (a swinging payload, an
intermediate mass) is explained by interpolating between prototypes. With an empty
context the attention is uniform.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from jax import Array

from arcade_core.baselines.gp import (
    FifoBuffer,
    Standardizer,
    fifo_init,
    fifo_mask,
    fifo_push,
    fit_standardizer,
)

#: Context length (transitions) and embedding size.
CONTEXT = 10
EMBEDDING = 8


class ProtoResidual(eqx.Module):
    """Encoder-prototype-decoder residual network (module docstring)."""

    encoder: eqx.nn.MLP  # [x, u, delta] (standardised) -> embedding
    trunk: eqx.nn.MLP  # [x, u] (standardised) -> shared decoder features
    heads: eqx.nn.Linear  # features -> (M * d) stacked decoder heads
    prototypes: Array  # (M, E)
    standardizer: Standardizer
    tasks: tuple[float, ...] = eqx.field(static=True)

    @property
    def num_outputs(self) -> int:
        return self.standardizer.out_mean.shape[0]

    def _inputs(self, xu: Array) -> Array:
        s = jax.lax.stop_gradient(self.standardizer)
        return (xu - s.in_mean) / s.in_scale

    def embed(self, xu: Array, delta: Array) -> Array:
        """Embedding of one transition ``[x, u] -> delta`` (original units)."""
        s = jax.lax.stop_gradient(self.standardizer)
        d = (delta - s.out_mean) / s.out_scale
        return self.encoder(jnp.concatenate([self._inputs(xu), d]))

    def logits(self, e: Array) -> Array:
        """Attention logits ``-|e - p_i|^2`` over the prototypes."""
        return -jnp.sum((e[None, :] - self.prototypes) ** 2, axis=-1)

    def standardised(self, x: Array, u: Array, attention: Array) -> Array:
        """Attention-weighted decoder output in standardised units."""
        h = self.heads(self.trunk(self._inputs(jnp.concatenate([x, u]))))
        return attention @ h.reshape(self.prototypes.shape[0], self.num_outputs)

    def residual(self, x: Array, u: Array, attention: Array) -> Array:
        """Attention-weighted residual in original units."""
        s = jax.lax.stop_gradient(self.standardizer)
        return self.standardised(x, u, attention) * s.out_scale + s.out_mean


def init_model(
    key: Array,
    x: Array,
    u: Array,
    delta: Array,
    tasks: tuple[float, ...],
    hidden: int = 64,
    embedding: int = EMBEDDING,
) -> ProtoResidual:
    """A randomly initialised model with scaling fitted to the offline data."""
    n_in, d = x.shape[1] + u.shape[1], delta.shape[1]
    k_enc, k_trunk, k_head, k_proto = jax.random.split(key, 4)
    dtype = x.dtype
    enc = eqx.nn.MLP(n_in + d, embedding, hidden, 2, activation=jax.nn.elu, key=k_enc, dtype=dtype)
    trunk = eqx.nn.MLP(
        n_in,
        hidden,
        hidden,
        2,
        activation=jax.nn.elu,
        final_activation=jax.nn.elu,
        key=k_trunk,
        dtype=dtype,
    )
    heads = eqx.nn.Linear(hidden, len(tasks) * d, key=k_head, dtype=dtype)
    protos = jax.random.normal(k_proto, (len(tasks), embedding), dtype)
    std = fit_standardizer(jnp.concatenate([x, u], axis=1), delta)
    return ProtoResidual(enc, trunk, heads, protos, std, tuple(float(t) for t in tasks))


def _window_loss(model: ProtoResidual, x, u, delta, label, task_weight):
    """Loss of one window: ``x, u, delta`` (H + 1, .), the last transition is the target."""
    xu = jnp.concatenate([x[:-1], u[:-1]], axis=1)
    e = jnp.mean(jax.vmap(model.embed)(xu, delta[:-1]), axis=0)
    logits = model.logits(e)
    pred = model.standardised(x[-1], u[-1], jax.nn.softmax(logits))
    s = model.standardizer
    mse = jnp.mean((pred - (delta[-1] - s.out_mean) / s.out_scale) ** 2)
    ce = -jax.nn.log_softmax(logits)[label]
    return mse + task_weight * ce


def train(
    model: ProtoResidual,
    x: Array,
    u: Array,
    delta: Array,
    task: Array,
    segment: Array,
    *,
    key: Array,
    steps: int = 3000,
    batch_size: int = 128,
    context: int = CONTEXT,
    learning_rate: float = 1e-3,
    task_weight: float = 0.1,
    callback: Callable[[int, float], None] | None = None,
) -> ProtoResidual:
    """Offline training with Adam on random windows (module docstring).

    ``task`` (n,) is the prototype index of each transition; ``segment`` (n,) labels
    contiguous flights (a window never spans two). Transitions are in time order within a
    segment. ``callback(step, loss)`` is called every 500 steps.
    """
    n = x.shape[0]
    start = jnp.arange(n - context)
    valid = segment[start] == segment[start + context]
    starts = start[valid]
    offsets = jnp.arange(context + 1)
    opt = optax.adam(learning_rate)
    # The standardizer is fitted, not trained: every use stops its gradient.
    params, static = eqx.partition(model, eqx.is_inexact_array)
    opt_state = opt.init(params)

    def batch_loss(p, idx):
        m = eqx.combine(p, static)
        rows = idx[:, None] + offsets[None, :]
        losses = jax.vmap(_window_loss, in_axes=(None, 0, 0, 0, 0, None))(
            m, x[rows], u[rows], delta[rows], task[rows[:, -1]], task_weight
        )
        return jnp.mean(losses)

    @jax.jit
    def update(p, s, k):
        idx = jax.random.choice(k, starts, (batch_size,))
        loss, g = jax.value_and_grad(batch_loss)(p, idx)
        upd, s = opt.update(g, s, p)
        return optax.apply_updates(p, upd), s, loss

    keys = jax.random.split(key, steps)
    for i in range(steps):
        params, opt_state, loss = update(params, opt_state, keys[i])
        if callback is not None and (i + 1) % 500 == 0:
            callback(i + 1, float(loss))
    return eqx.combine(params, static)


class ProtoState(NamedTuple):
    """Online state: the context FIFO of ``[x, u] -> delta`` (the model stays frozen and
    is passed alongside, so the state is all arrays and scans/jits as a carry)."""

    context: FifoBuffer


def init(model: ProtoResidual, context: int = CONTEXT) -> ProtoState:
    n_in = model.standardizer.in_mean.shape[0]
    return ProtoState(fifo_init(context, n_in, model.num_outputs, model.prototypes.dtype))


def attention(model: ProtoResidual, state: ProtoState) -> Array:
    """Attention over the prototypes from the current context (uniform when empty)."""
    buf = state.context
    emb = jax.vmap(model.embed)(buf.inputs, buf.targets)
    w = fifo_mask(buf).astype(emb.dtype)
    e = jnp.sum(emb * w[:, None], axis=0) / jnp.maximum(jnp.sum(w), 1.0)
    m = model.prototypes.shape[0]
    return jnp.where(
        buf.count > 0, jax.nn.softmax(model.logits(e)), jnp.full(m, 1.0 / m, emb.dtype)
    )


def predict_mean(model: ProtoResidual, state: ProtoState, x: Array, u: Array) -> Array:
    """Residual prediction at ``(x, u)`` in original units."""
    return model.residual(x, u, attention(model, state))


def update(state: ProtoState, x: Array, u: Array, delta: Array) -> ProtoState:
    """Observe one transition: push it into the context (no parameter update)."""
    return ProtoState(fifo_push(state.context, jnp.concatenate([x, u]), delta))
