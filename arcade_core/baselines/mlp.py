"""MLP residual model with online last-layer SGD: the MLP-MPC baseline (Appendix D, item 3).

After Saviolo et al. (2023), "Active learning of discrete-time dynamics for
uncertainty-aware model predictive control", adapted (as in the paper) to learn the
residual ``delta = x_{k+1} - f_nom(x_k, u_k)`` instead of the full dynamics:

- offline: an MLP (hidden sizes [8, 16, 8, 8] for the cartpole, [64, 128, 64, 64] for the
  quadrotor) is trained on residuals with Adam (mean squared error, standardised units);
- online: the *last layer only* is updated at every step by one SGD step on the mean
  squared error over the whole FIFO buffer (capacity 50), with a small learning rate
  (the paper uses 1e-6; exposed as ``learning_rate``);
- uncertainty: an unscented transform (Wan & van der Merwe, 2000) propagates a Gaussian
  input distribution ``N([x, u], diag(state_std, control_std)^2)`` through the network;
  the spread of the sigma-point outputs is the reported variance. The input standard
  deviations are the caller's statement of how uncertain the network input is (state
  estimation noise; input noise, usually 0). With zero input covariance the variance is 0.

Network inputs and outputs are standardised with offline statistics (the same
:class:`~arcade_core.baselines.gp.Standardizer` as the GP baseline).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
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

#: Hidden sizes used in the paper (Appendix D item 3).
CARTPOLE_HIDDEN = (8, 16, 8, 8)
QUADROTOR_HIDDEN = (64, 128, 64, 64)


class MLPResidual(eqx.Module):
    """Residual network ``delta = head(body(standardise([x, u])))`` (Appendix D item 3)."""

    hidden: tuple[eqx.nn.Linear, ...]
    head: eqx.nn.Linear
    standardizer: Standardizer
    activation: Callable[[Array], Array] = eqx.field(static=True)

    def features(self, z: Array) -> Array:
        """Last hidden activations for one raw input ``z = [x, u]`` (frozen online)."""
        s = jax.lax.stop_gradient(self.standardizer)
        h = (z - s.in_mean) / s.in_scale
        for layer in self.hidden:
            h = self.activation(layer(h))
        return h

    def standardised(self, z: Array) -> Array:
        """Output in standardised units for one raw input ``z``."""
        return self.head(self.features(z))

    def __call__(self, z: Array) -> Array:
        """Residual in original units for one raw input ``z = [x, u]``."""
        s = jax.lax.stop_gradient(self.standardizer)
        return self.standardised(z) * s.out_scale + s.out_mean


def init_model(
    key: Array,
    x: Array,
    u: Array,
    delta: Array,
    hidden: Sequence[int] = CARTPOLE_HIDDEN,
    activation: Callable[[Array], Array] = jax.nn.elu,
) -> MLPResidual:
    """A randomly initialised network whose scaling is fitted to the offline data."""
    z = jnp.concatenate([x, u], axis=1)
    sizes = [z.shape[1], *hidden]
    keys = jax.random.split(key, len(hidden) + 1)
    dtype = z.dtype
    layers = tuple(
        eqx.nn.Linear(a, b, dtype=dtype, key=k) for a, b, k in zip(sizes[:-1], sizes[1:], keys)
    )
    head = eqx.nn.Linear(sizes[-1], delta.shape[1], dtype=dtype, key=keys[-1])
    return MLPResidual(layers, head, fit_standardizer(z, delta), activation)


def _mse(model: MLPResidual, z: Array, y_std: Array, mask: Array) -> Array:
    """Masked mean squared error in standardised output units."""
    err = jax.vmap(model.standardised)(z) - y_std
    per_row = jnp.mean(err**2, axis=1)
    return jnp.sum(jnp.where(mask, per_row, 0.0)) / jnp.maximum(jnp.sum(mask), 1)


def train(
    model: MLPResidual,
    x: Array,
    u: Array,
    delta: Array,
    *,
    key: Array,
    epochs: int = 50,
    batch_size: int = 128,
    learning_rate: float = 1e-3,
    callback: Callable[[int, float], None] | None = None,
) -> MLPResidual:
    """Offline training on residuals with Adam, minibatches reshuffled every epoch.

    Appendix D item 3 ("trains an MLP on offline data"). One jitted scan per epoch over
    ``N // batch_size`` minibatches (the remainder is dropped, differently every epoch).
    ``callback(epoch, mean_loss)`` is called after each epoch (progress display lives
    outside the core).
    """
    z = jnp.concatenate([x, u], axis=1)
    s = model.standardizer
    y = (delta - s.out_mean) / s.out_scale
    n = z.shape[0]
    bs = min(batch_size, n)
    nb = n // bs
    opt = optax.adam(learning_rate)
    params, static = eqx.partition(model, eqx.is_inexact_array)
    opt_state = opt.init(params)
    ones = jnp.ones(bs, bool)

    @jax.jit
    def epoch_fn(params, opt_state, key):
        perm = jax.random.permutation(key, n)[: nb * bs].reshape(nb, bs)

        def step(carry, idx):
            p, st = carry
            loss, g = jax.value_and_grad(
                lambda p_: _mse(eqx.combine(p_, static), z[idx], y[idx], ones)
            )(p)
            upd, st = opt.update(g, st, p)
            return (eqx.apply_updates(p, upd), st), loss

        (params, opt_state), losses = jax.lax.scan(step, (params, opt_state), perm)
        return params, opt_state, jnp.mean(losses)

    for epoch in range(epochs):
        key, sub = jax.random.split(key)
        params, opt_state, loss = epoch_fn(params, opt_state, sub)
        if callback is not None:
            callback(epoch, float(loss))
    return eqx.combine(params, static)


def unscented_transform(
    fn: Callable[[Array], Array],
    mean: Array,
    sqrt_cov: Array,
    alpha: float = 1.0,
    beta: float = 2.0,
    kappa: float = 0.0,
) -> tuple[Array, Array]:
    """Unscented transform of ``N(mean, S S^T)`` through ``fn`` (Wan & van der Merwe 2000).

    Appendix D item 3 (UT on the MLP outputs). ``2n + 1`` sigma points
    ``mean, mean +- sqrt(n + lam) S[:, i]`` with ``lam = alpha^2 (n + kappa) - n``;
    mean weights ``lam / (n + lam)`` and ``1 / (2 (n + lam))``, the centre covariance
    weight adds ``1 - alpha^2 + beta``. The defaults (alpha=1, beta=2, kappa=0) make all
    weights non-negative, so the variance is non-negative by construction.

    Returns the output mean and the diagonal of the output covariance.
    """
    n = mean.shape[0]
    lam = alpha**2 * (n + kappa) - n
    spread = jnp.sqrt(n + lam) * sqrt_cov.T  # rows are scaled columns of S
    points = jnp.concatenate([mean[None], mean + spread, mean - spread])
    w_rest = jnp.full(2 * n, 1.0 / (2.0 * (n + lam)))
    wm = jnp.concatenate([jnp.array([lam / (n + lam)]), w_rest])
    wc = wm.at[0].add(1.0 - alpha**2 + beta)
    out = jax.vmap(fn)(points)
    out_mean = wm @ out
    out_var = wc @ (out - out_mean) ** 2
    return out_mean, out_var


class MLPState(NamedTuple):
    """Online MLP baseline: network (last layer adapts), raw-unit FIFO buffer, settings."""

    model: MLPResidual
    buffer: FifoBuffer  # raw inputs z = [x, u] and raw residuals
    input_std: Array  # (nx + nu,) std of the input distribution propagated by the UT
    learning_rate: Array  # () SGD step size of the last-layer update


def init(
    model: MLPResidual,
    state_std: Array,
    control_std: Array,
    capacity: int = 50,
    learning_rate: float = 1e-6,
) -> MLPState:
    """Online state with an empty buffer.

    ``state_std`` (nx,) and ``control_std`` (nu,) define the diagonal input covariance
    propagated by the unscented transform (e.g. state-estimation noise, zero for inputs).
    """
    s = model.standardizer
    dtype = s.in_mean.dtype
    input_std = jnp.concatenate([jnp.asarray(state_std, dtype), jnp.asarray(control_std, dtype)])
    n_in, d = s.in_mean.shape[0], s.out_mean.shape[0]
    if input_std.shape != (n_in,):
        raise ValueError(f"state_std + control_std must have {n_in} entries")
    return MLPState(
        model=model,
        buffer=fifo_init(capacity, n_in, d, dtype),
        input_std=input_std,
        learning_rate=jnp.asarray(learning_rate, dtype),
    )


def buffer_loss(state: MLPState) -> Array:
    """Mean squared error (standardised units) of the current network on the buffer."""
    s = state.model.standardizer
    y = (state.buffer.targets - s.out_mean) / s.out_scale
    return _mse(state.model, state.buffer.inputs, y, fifo_mask(state.buffer))


def sgd_last_layer(state: MLPState) -> MLPState:
    """One SGD step on the last layer over the whole buffer (Appendix D item 3)."""
    model = state.model
    s = model.standardizer
    mask = fifo_mask(state.buffer)
    y = (state.buffer.targets - s.out_mean) / s.out_scale
    feats = jax.vmap(model.features)(state.buffer.inputs)  # body frozen: computed once

    def loss(head: eqx.nn.Linear) -> Array:
        err = jax.vmap(head)(feats) - y
        per_row = jnp.mean(err**2, axis=1)
        return jnp.sum(jnp.where(mask, per_row, 0.0)) / jnp.maximum(jnp.sum(mask), 1)

    g = jax.grad(loss)(model.head)
    head = jax.tree.map(lambda p, gp: p - state.learning_rate * gp, model.head, g)
    return state._replace(model=eqx.tree_at(lambda m: m.head, model, head))


def update(state: MLPState, x: Array, u: Array, delta: Array) -> MLPState:
    """Push the newest sample into the FIFO, then one last-layer SGD step on the buffer.

    Appendix D item 3: "the model is updated using the entire FIFO buffer".
    """
    buf = fifo_push(state.buffer, jnp.concatenate([x, u]), delta)
    return sgd_last_layer(state._replace(buffer=buf))


def predict_mean(state: MLPState, x: Array, u: Array) -> Array:
    """Network residual at (x, u), no uncertainty propagation (cheap path for rollouts)."""
    return state.model(jnp.concatenate([x, u]))


def predict(state: MLPState, x: Array, u: Array) -> tuple[Array, Array]:
    """Unscented-transform mean and variance of the residual at (x, u), each (d,).

    Appendix D item 3 (UT of Wan & van der Merwe applied to the MLP outputs); the input
    covariance is ``diag(state.input_std)^2``.
    """
    z = jnp.concatenate([x, u])
    return unscented_transform(state.model, z, jnp.diag(state.input_std))
