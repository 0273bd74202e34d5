"""Gaussian-process residual model: the GP-MPC baseline (Appendix D, item 2).

After Torrente et al. (2021), "Data-driven MPC for quadrotors": one scalar GP per
residual component with an ARD RBF kernel. Hyperparameters (signal variance, one
lengthscale per input, noise variance) are chosen offline by maximising the log marginal
likelihood; online, the GP is re-conditioned at every step on a FIFO buffer holding the
most recent (x, u, delta) samples (capacity 50 in the paper), hyperparameters fixed.

Residual convention: ``delta_k = x_{k+1} - f_nom(x_k, u_k)`` is predicted from the input
``z = [x, u]``. Inputs and outputs are standardised with offline statistics, so the GP
prior mean is the offline mean residual and the hyperparameters are scale-free.

Fixed shapes throughout: the buffer is a ring of ``capacity`` slots plus a count; empty
slots are masked out of the kernel matrix (identity rows, zero targets, zero
cross-covariances) so they cannot influence a prediction. ``update`` and ``predict`` can
be jitted, scanned and vmapped. The FIFO buffer and the standardiser are shared with
:mod:`arcade_core.baselines.mlp`.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import optax
from jax import Array

#: Added to every GP noise variance (standardised units, so relative to the output
#: variance): keeps Cholesky factors of near-noiseless data well defined. Single precision
#: needs a larger floor than double precision.
NOISE_FLOOR = {"float64": 1e-6, "float32": 1e-3}
#: Diagonal jitter relative to the signal variance (very long lengthscales make the
#: kernel matrix nearly rank one).
JITTER = {"float64": 1e-10, "float32": 1e-6}


# ---------------------------------------------------------------------------------------
# Shared pieces: FIFO buffer and standardiser
# ---------------------------------------------------------------------------------------


class FifoBuffer(NamedTuple):
    """Fixed-capacity FIFO of (input, target) pairs.

    Slots are written round-robin; while filling, the valid slots are ``[0, count)``,
    once full all slots are valid and the oldest one is overwritten next.
    """

    inputs: Array  # (capacity, n_in)
    targets: Array  # (capacity, d)
    head: Array  # () int: next slot to write
    count: Array  # () int: number of valid slots, <= capacity


def fifo_init(capacity: int, n_in: int, d: int, dtype: jnp.dtype | None = None) -> FifoBuffer:
    """An empty buffer of ``capacity`` slots."""
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    return FifoBuffer(
        inputs=jnp.zeros((capacity, n_in), dtype),
        targets=jnp.zeros((capacity, d), dtype),
        head=jnp.zeros((), jnp.int32),
        count=jnp.zeros((), jnp.int32),
    )


def fifo_push(buf: FifoBuffer, inputs: Array, target: Array) -> FifoBuffer:
    """Append one sample, overwriting the oldest one when full."""
    capacity = buf.inputs.shape[0]
    return FifoBuffer(
        inputs=buf.inputs.at[buf.head].set(inputs.astype(buf.inputs.dtype)),
        targets=buf.targets.at[buf.head].set(target.astype(buf.targets.dtype)),
        head=(buf.head + 1) % capacity,
        count=jnp.minimum(buf.count + 1, capacity),
    )


def fifo_mask(buf: FifoBuffer) -> Array:
    """Boolean ``(capacity,)`` mask of the valid slots."""
    return jnp.arange(buf.inputs.shape[0]) < buf.count


class Standardizer(NamedTuple):
    """Affine input/output scaling fitted on offline data."""

    in_mean: Array  # (n_in,)
    in_scale: Array  # (n_in,)
    out_mean: Array  # (d,)
    out_scale: Array  # (d,)


def fit_standardizer(inputs: Array, targets: Array) -> Standardizer:
    """Mean and standard deviation per column; constant columns get scale 1."""

    def scale(a: Array) -> Array:
        s = jnp.std(a, axis=0)
        return jnp.where(s > 1e-12, s, 1.0)

    return Standardizer(
        in_mean=jnp.mean(inputs, axis=0),
        in_scale=scale(inputs),
        out_mean=jnp.mean(targets, axis=0),
        out_scale=scale(targets),
    )


# ---------------------------------------------------------------------------------------
# Kernel and marginal likelihood
# ---------------------------------------------------------------------------------------


class GPHyperparams(NamedTuple):
    """Log-hyperparameters of ``d`` independent ARD RBF GPs (standardised units)."""

    log_signal_var: Array  # (d,)
    log_lengthscale: Array  # (d, n_in)
    log_noise_var: Array  # (d,)


class GPModel(NamedTuple):
    """What offline training produces: hyperparameters and the data scaling."""

    hyper: GPHyperparams
    standardizer: Standardizer


def initial_hyperparams(n_in: int, d: int, noise_var: float = 0.1) -> GPHyperparams:
    """Unit signal variance and lengthscales (data are standardised), given noise."""
    return GPHyperparams(
        log_signal_var=jnp.zeros(d),
        log_lengthscale=jnp.zeros((d, n_in)),
        log_noise_var=jnp.full(d, math.log(noise_var)),
    )


def ard_rbf(a: Array, b: Array, log_signal_var: Array, log_lengthscale: Array) -> Array:
    """ARD squared-exponential kernel matrix ``s2 exp(-|(a_i - b_j) / l|^2 / 2)``.

    Appendix D item 2 (the kernel of Torrente et al.). ``a`` is (n, n_in), ``b`` (m, n_in);
    returns (n, m).
    """
    inv_l = jnp.exp(-log_lengthscale)
    a, b = a * inv_l, b * inv_l
    # Expanded form: O(n m) memory instead of an (n, m, n_in) difference tensor.
    sq = jnp.sum(a**2, axis=1)[:, None] + jnp.sum(b**2, axis=1)[None, :] - 2.0 * a @ b.T
    return jnp.exp(log_signal_var) * jnp.exp(-0.5 * jnp.maximum(sq, 0.0))


def _noise_var(log_noise_var: Array) -> Array:
    return jnp.exp(log_noise_var) + NOISE_FLOOR.get(log_noise_var.dtype.name, 1e-3)


def _masked_gram(z: Array, mask: Array, lsv: Array, lls: Array, lnv: Array) -> Array:
    """Kernel matrix plus noise on valid slots, identity on empty ones."""
    k = ard_rbf(z, z, lsv, lls)
    both = mask[:, None] & mask[None, :]
    jitter = JITTER.get(lsv.dtype.name, 1e-6) * jnp.exp(lsv)
    diag = jnp.where(mask, _noise_var(lnv) + jitter, 1.0)
    return jnp.where(both, k, 0.0) + jnp.diag(diag)


def _lml_one(z: Array, y: Array, mask: Array, lsv: Array, lls: Array, lnv: Array) -> Array:
    gram = _masked_gram(z, mask, lsv, lls, lnv)
    chol = jnp.linalg.cholesky(gram)
    y = jnp.where(mask, y, 0.0)
    alpha = jsl.cho_solve((chol, True), y)
    n = jnp.sum(mask)
    # Empty slots have unit diagonal in the factor: log 1 = 0, no contribution.
    return -0.5 * y @ alpha - jnp.sum(jnp.log(jnp.diagonal(chol))) - 0.5 * n * jnp.log(2.0 * jnp.pi)


def log_marginal_likelihood(
    hyper: GPHyperparams, z: Array, y: Array, mask: Array | None = None
) -> Array:
    """Log marginal likelihood ``log p(y | z)`` of each output GP, shape (d,).

    Appendix D item 2 (maximum-likelihood hyperparameters, as in Torrente et al.):
    ``-y^T K^-1 y / 2 - log|K| / 2 - n log(2 pi) / 2`` with ``K = k(z, z) + s_n^2 I``.
    ``z`` (n, n_in) and ``y`` (n, d) are in standardised units; ``mask`` drops rows.
    """
    if mask is None:
        mask = jnp.ones(z.shape[0], bool)
    return jax.vmap(_lml_one, in_axes=(None, 1, None, 0, 0, 0))(
        z, y, mask, hyper.log_signal_var, hyper.log_lengthscale, hyper.log_noise_var
    )


def _standardise_in(s: Standardizer, z: Array) -> Array:
    return (z - s.in_mean) / s.in_scale


def _standardise_out(s: Standardizer, y: Array) -> Array:
    return (y - s.out_mean) / s.out_scale


# ---------------------------------------------------------------------------------------
# Offline: hyperparameters by maximum marginal likelihood
# ---------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("num_points", "num_steps"))
def _fit(z, delta, key, hyper, learning_rate, *, num_points: int, num_steps: int):
    std = fit_standardizer(z, delta)
    if z.shape[0] > num_points:
        idx = jax.random.choice(key, z.shape[0], (num_points,), replace=False)
        z, delta = z[idx], delta[idx]
    zs, ys = _standardise_in(std, z), _standardise_out(std, delta)
    opt = optax.adam(learning_rate)

    def loss(h: GPHyperparams) -> Array:
        return -jnp.sum(log_marginal_likelihood(h, zs, ys)) / zs.shape[0]

    def step(carry, _):
        h, st = carry
        g = jax.grad(loss)(h)
        upd, st_new = opt.update(g, st, h)
        # A step whose gradient is not finite (failed factorisation) is skipped.
        ok = jnp.all(jnp.array([jnp.all(jnp.isfinite(a)) for a in jax.tree.leaves(g)]))

        def keep(new, old):
            return jax.tree.map(lambda a, b: jnp.where(ok, a, b), new, old)

        return (keep(optax.apply_updates(h, upd), h), keep(st_new, st)), None

    (hyper, _), _ = jax.lax.scan(step, (hyper, opt.init(hyper)), None, length=num_steps)
    return GPModel(hyper=hyper, standardizer=std)


def fit(
    x: Array,
    u: Array,
    delta: Array,
    *,
    key: Array | None = None,
    num_points: int = 300,
    num_steps: int = 200,
    learning_rate: float = 0.05,
    init: GPHyperparams | None = None,
) -> GPModel:
    """Fit standardiser and hyperparameters on an offline residual dataset.

    Appendix D item 2: "kernel hyperparameters selected by maximum likelihood
    optimization on the offline dataset". Exact GP marginal likelihood on a random
    subsample of ``num_points`` rows (the cost is cubic in the rows), maximised with a
    fixed number of Adam steps on the log-hyperparameters. Cost per step is one
    Cholesky factorisation (and its gradient) of a ``num_points`` square matrix per output.

    Args:
        x: (N, nx) states, u: (N, nu) inputs, delta: (N, d) residuals.
        key: PRNG key for the subsample (only used when N > num_points).
        init: starting hyperparameters (default :func:`initial_hyperparams`).
    """
    z = jnp.concatenate([jnp.atleast_2d(x), jnp.atleast_2d(u)], axis=1)
    delta = jnp.atleast_2d(delta)
    key = jax.random.PRNGKey(0) if key is None else key
    hyper = initial_hyperparams(z.shape[1], delta.shape[1]) if init is None else init
    hyper = jax.tree.map(lambda a: jnp.asarray(a, z.dtype), hyper)
    lr = jnp.asarray(learning_rate, z.dtype)
    return _fit(z, delta, key, hyper, lr, num_points=num_points, num_steps=num_steps)


# ---------------------------------------------------------------------------------------
# Online: FIFO buffer, re-conditioning, prediction
# ---------------------------------------------------------------------------------------


class GPState(NamedTuple):
    """Online GP: fixed model, buffer (standardised) and its cached factorisation."""

    model: GPModel
    buffer: FifoBuffer  # standardised inputs and targets
    chol: Array  # (d, capacity, capacity) lower Cholesky factors of the masked Gram
    alpha: Array  # (d, capacity) K^-1 y per output, zero on empty slots


def _condition(model: GPModel, buffer: FifoBuffer) -> GPState:
    """Factorise the buffer's Gram matrices (hyperparameters fixed)."""
    mask = fifo_mask(buffer)
    h = model.hyper

    def one(y, lsv, lls, lnv):
        chol = jnp.linalg.cholesky(_masked_gram(buffer.inputs, mask, lsv, lls, lnv))
        alpha = jsl.cho_solve((chol, True), jnp.where(mask, y, 0.0))
        return chol, alpha

    chol, alpha = jax.vmap(one, in_axes=(1, 0, 0, 0))(
        buffer.targets, h.log_signal_var, h.log_lengthscale, h.log_noise_var
    )
    return GPState(model=model, buffer=buffer, chol=chol, alpha=alpha)


def init(model: GPModel, capacity: int = 50) -> GPState:
    """Empty online GP; predicts the offline mean residual and the prior variance."""
    n_in = model.standardizer.in_mean.shape[0]
    d = model.standardizer.out_mean.shape[0]
    dtype = model.standardizer.in_mean.dtype
    return _condition(model, fifo_init(capacity, n_in, d, dtype))


def update(state: GPState, x: Array, u: Array, delta: Array) -> GPState:
    """Push the newest sample into the FIFO and re-condition the GP.

    Appendix D item 2: "a FIFO buffer of capacity 50 is used to store the most recent
    state-control observations, and the GP is refit using these samples".
    """
    s = state.model.standardizer
    z = _standardise_in(s, jnp.concatenate([x, u]))
    buf = fifo_push(state.buffer, z, _standardise_out(s, delta))
    return _condition(state.model, buf)


def condition(model: GPModel, x: Array, u: Array, delta: Array) -> GPState:
    """A GP conditioned on a whole batch (capacity = number of rows).

    For offline-only evaluation: condition once on a (sub)set of training data. Rows are
    taken as chronological: a later :func:`update` overwrites the first row first.
    """
    s = model.standardizer
    z = _standardise_in(s, jnp.concatenate([x, u], axis=1))
    n = z.shape[0]
    buf = FifoBuffer(
        inputs=z,
        targets=_standardise_out(s, delta),
        head=jnp.zeros((), jnp.int32),
        count=jnp.asarray(n, jnp.int32),
    )
    return _condition(model, buf)


def predict(state: GPState, x: Array, u: Array, include_noise: bool = False) -> tuple[Array, Array]:
    """Posterior mean and variance of the residual at one (x, u), each (d,).

    Standard GP regression (Rasmussen & Williams, Alg. 2.1) per output, on the buffer
    (Appendix D item 2). The variance is that of the latent residual function
    (epistemic); ``include_noise`` adds the fitted observation noise. Original units.
    """
    model = state.model
    s, h = model.standardizer, model.hyper
    z = _standardise_in(s, jnp.concatenate([x, u]))
    mask = fifo_mask(state.buffer)

    def one(chol, alpha, lsv, lls, lnv):
        kstar = jnp.where(mask, ard_rbf(z[None], state.buffer.inputs, lsv, lls)[0], 0.0)
        mean = kstar @ alpha
        v = jsl.solve_triangular(chol, kstar, lower=True)
        var = jnp.maximum(jnp.exp(lsv) - v @ v, 0.0)
        return mean, var + jnp.where(include_noise, _noise_var(lnv), 0.0)

    mean, var = jax.vmap(one)(
        state.chol, state.alpha, h.log_signal_var, h.log_lengthscale, h.log_noise_var
    )
    return mean * s.out_scale + s.out_mean, var * s.out_scale**2
