"""Bayesian linear regression of one hypothesis: the Gaussian algebra of Eqs. 4-8.

The observation model's noise (Eq. 4, with the errors-in-variables term of estimated
states), the tempered prior of a changepoint branch (Eq. 5, optionally with the offline
prior re-injected), the posterior update in Potter's square-root form (Eq. 6) and the
marginal likelihood of a residual (Eq. 8). The projections of a state onto a latent input
``z`` are shared by the prediction and the update.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from arcade_core.adaptation.config import AdaptationConfig
from arcade_core.adaptation.state import BeamState, _noise

_LOG_2PI = math.log(2.0 * math.pi)


class _Projections(NamedTuple):
    """Per-hypothesis projections of the state onto a latent input ``z``."""

    a: Array  # (K, d_c, l)  W^T z
    b: Array  # (K, d_c, l)  Sigma z = W W^T z
    q: Array  # (K, d_c)     z^T Sigma z
    m: Array  # (K, d)       z^T mu


def _project(state: BeamState, z: Array) -> _Projections:
    w = state.sqrt_covariances
    # Broadcasting z to a batched mat-vec is several times faster on CPU than the
    # equivalent single contraction against an unbatched z.
    zb = jnp.broadcast_to(z, w.shape[:-1])
    a = jnp.einsum("kdji,kdj->kdi", w, zb)
    b = jnp.einsum("kdij,kdj->kdi", w, a)
    q = jnp.sum(a * a, axis=-1)
    m = jnp.sum(state.means * z, axis=-1)
    return _Projections(a, b, q, m)


def state_noise_sigma2(
    sigma2: Array, jacobian: Array, var_prev: Array, var_next: Array, scale: Array
) -> Array:
    """Observation-noise variances of Eq. 4 when both states of a transition are estimates.

    The residual ``delta = x_{k+1} - f(x_k, u_k)`` of estimated states carries their noise
    (errors in variables, first order): ``var_next + J var_prev J^T`` (diagonal; ``J =
    df/dx`` at ``x_k``), in the units the regression learns in (``delta / scale``), adds to
    ``sigma2``. All ``(d,)`` but ``jacobian`` ``(d, d)``.
    """
    var_res = var_next + jnp.einsum("ij,j,ij->i", jacobian, var_prev, jacobian)
    return sigma2 + var_res / scale**2


def posterior_update(
    mean: Array,
    sqrt_cov: Array,
    z: ArrayLike,
    delta: ArrayLike,
    sigma2: ArrayLike,
    gamma: ArrayLike = 1.0,
) -> tuple[Array, Array]:
    """Eq. 6 for one hypothesis and all outputs, in square-root (Potter) form.

    Tempered prior ``N(mu, Sigma / gamma)`` with ``Sigma = W W^T``; returns the posterior
    ``(mu', W')`` after observing ``delta`` (``(d,)``) at ``z`` (``(l,)``):
    ``Sigma' = (gamma Sigma^{-1} + z z^T / sigma^2)^{-1}`` and
    ``mu' = Sigma' (gamma Sigma^{-1} mu + z delta / sigma^2)``.

    Shapes: ``mean (d, l)``, ``sqrt_cov (d_c, l, l)`` with ``d_c in {1, d}`` (one
    covariance shared by all outputs, or one per output), ``sigma2`` scalar or ``(d,)``
    (must be uniform when ``d_c = 1``), ``gamma ()``.
    """
    dtype = mean.dtype
    if sqrt_cov.shape[0] == 1 and mean.shape[0] > 1 and jnp.ndim(sigma2) > 0:
        raise ValueError("a covariance shared by all outputs needs a scalar sigma2")
    z, delta = jnp.asarray(z, dtype), jnp.asarray(delta, dtype)
    sigma2 = _noise(sigma2, mean.shape[0], dtype)
    gamma = jnp.asarray(gamma, dtype)
    a = jnp.einsum("dji,j->di", sqrt_cov, z)
    b = jnp.einsum("dij,dj->di", sqrt_cov, a)
    q = jnp.sum(a * a, axis=-1)
    r = delta - mean @ z
    return _potter(mean, sqrt_cov, a, b, q, r, sigma2, sigma2[: sqrt_cov.shape[0]], gamma)


def _potter(mean, sqrt_cov, a, b, q, r, sigma2, sigma2_cov, gamma):
    """Eq. 6 from precomputed projections (shapes broadcast over leading axes).

    ``s = z^T Sigma z / gamma + sigma^2``; ``mu' = mu + (Sigma z / gamma) r / s``;
    ``W' = (W - c (Sigma z) (W^T z)^T / gamma) / sqrt(gamma)`` with
    ``c = 1 / (s + sigma sqrt(s))``, which gives ``W' W'^T = Sigma/gamma - (Sigma z)(Sigma
    z)^T / (gamma^2 s)`` exactly (Sherman--Morrison of Eq. 6) and is PSD by construction.
    ``sigma2`` is per output ``(d,)``, ``sigma2_cov`` per stored covariance ``(d_c,)``.
    """
    gamma = jnp.asarray(gamma)[..., None]  # broadcast against the output axis
    s = q / gamma + sigma2  # (.., d)
    new_mean = mean + b * (r / (s * gamma))[..., None]
    s_cov = q / gamma + sigma2_cov  # (.., d_c)
    c = 1.0 / (gamma * (s_cov + jnp.sqrt(sigma2_cov * s_cov)))
    outer = b[..., :, None] * a[..., None, :]
    new_w = (sqrt_cov - c[..., None, None] * outer) * jax.lax.rsqrt(gamma)[..., None, None]
    return new_mean, new_w


def _log_marginal(
    q: Array, r: Array, sigma2: Array, gamma: ArrayLike, nu: float = math.inf
) -> Array:
    """Eq. 8: ``log p(delta | z, c)`` per hypothesis, summed over outputs; ``(K,)``.

    ``q = z^T Sigma z`` is ``(K, d_c)`` and broadcasts against ``r`` ``(K, d)``. A finite
    ``nu`` (``AdaptationConfig.nu``, a static Python float) scores each output with a
    Student-t of ``nu`` degrees of freedom and squared scale ``s`` instead (the Gaussian
    is its ``nu -> inf`` limit, taken exactly at ``inf``).
    """
    s = q / gamma + sigma2
    if math.isinf(nu):
        return -0.5 * jnp.sum(_LOG_2PI + jnp.log(s) + r * r / s, axis=-1)
    const = math.lgamma(0.5 * (nu + 1.0)) - math.lgamma(0.5 * nu) - 0.5 * math.log(nu * math.pi)
    t = const - 0.5 * jnp.log(s) - 0.5 * (nu + 1.0) * jnp.log1p(r * r / (nu * s))
    return jnp.sum(t, axis=-1)


def _tempered(
    state: BeamState, z: Array, proj: _Projections, beta2: Array, config: AdaptationConfig
) -> tuple[Array, Array, Array, Array, Array, Array]:
    """Prior of the changepoint branch of every hypothesis: ``(mu1, W1, a1, b1, q1, g1)``
    such that the tempered prior is ``N(mu1, W1 W1^T / g1)`` and ``a1, b1, q1`` are the
    projections of ``W1`` onto ``z`` (as in :class:`_Projections`).

    Eq. 5 as written (``prior_floor = 0``): ``mu1 = mu``, ``W1 = W``, ``g1 = beta^2``.
    With the offline prior re-injected (``c = rho (1 - beta^2) / tau^2 > 0``,
    :class:`AdaptationConfig`): the tempered precision ``P = beta^2 W^-T W^-1 + c I`` has
    the square root ``W1 = W L^-T`` with ``L L^T = beta^2 I + c W^T W`` (no inverse of
    ``W`` needed), ``g1 = 1``, and ``mu1 = P^-1 (beta^2 Sigma^-1 mu + c theta_0) = mu + c
    W1 W1^T (theta_0 - mu)``.
    """
    dtype = state.means.dtype
    rho = jnp.asarray(config.prior_floor, dtype)
    c = jnp.where(rho > 0, rho * (1.0 - beta2) / jnp.asarray(config.tau2, dtype), 0.0)
    w = state.sqrt_covariances

    def eq5(_):
        return state.means, w, proj.a, proj.b, proj.q, beta2

    def floored(_):
        l = w.shape[-1]
        m = beta2 * jnp.eye(l, dtype=dtype) + c * jnp.einsum("...ji,...jk->...ik", w, w)
        chol = jnp.linalg.cholesky(m)
        # W L^-T = (L^-1 W^T)^T
        w1 = jnp.swapaxes(
            jax.scipy.linalg.solve_triangular(chol, jnp.swapaxes(w, -1, -2), lower=True), -1, -2
        )
        zb = jnp.broadcast_to(z, w1.shape[:-1])
        a1 = jnp.einsum("kdji,kdj->kdi", w1, zb)
        b1 = jnp.einsum("kdij,kdj->kdi", w1, a1)
        # (K, d_c, l, l) against (K, d, l): matmul broadcasts a shared covariance (d_c = 1).
        gap = (state.prior_mean - state.means)[..., None]
        pull = w1 @ (jnp.swapaxes(w1, -1, -2) @ gap)
        mean1 = state.means + c * pull[..., 0]
        return mean1, w1, a1, b1, jnp.sum(a1 * a1, axis=-1), jnp.ones((), dtype)

    return jax.lax.cond(c > 0, floored, eq5, None)
