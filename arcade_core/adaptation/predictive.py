"""What the beam predicts and reads off: the Eq. 10 mixture and the Sec. IV variance.

The beam-marginal predictive of the residual (Eq. 10) split into its parameter,
between-hypothesis, noise and encoder parts, the total ``sigma_tot^2`` that modulates the
MPC cost (Sec. IV), the moment-matched marginal decoder and the MAP history's latest
changepoint.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from arcade_core.adaptation.posterior import _project, _Projections
from arcade_core.adaptation.state import BeamState, Prediction


def _encoder_term(state: BeamState, weights: Array, sigma_z2: ArrayLike | None) -> Array:
    """Sec. IV encoder term ``(sigma_z^2)^T (sum_h w_h mu_h^j . mu_h^j)`` per output."""
    if sigma_z2 is None:
        return jnp.zeros(state.means.shape[1], state.means.dtype)
    sz = jnp.asarray(sigma_z2, state.means.dtype)
    return jnp.sum(weights[:, None, None] * sz * jnp.square(state.means), axis=(0, 2))


def _mixture(state: BeamState, proj: _Projections, sigma_z2: ArrayLike | None) -> Prediction:
    w = jax.nn.softmax(state.log_scores)[:, None]
    # Weighted sums as multiply-reduce rather than dots: they fuse into fewer kernels.
    mean = jnp.sum(w * proj.m, axis=0)
    param = jnp.broadcast_to(jnp.sum(w * proj.q, axis=0), mean.shape)
    between = jnp.sum(w * jnp.square(proj.m - mean), axis=0)
    w = w[:, 0]
    noise = state.sigma2
    encoder = _encoder_term(state, w, sigma_z2)
    tot = encoder + param + between
    return Prediction(mean, param, between, noise, encoder, tot, tot + noise)


def predict(state: BeamState, z: ArrayLike, sigma_z2: ArrayLike | None = None) -> Prediction:
    """Beam-marginal predictive distribution of the residual at latent input ``z`` (Eq. 10).

    With weights ``w_h = softmax(L_{k,h})`` and ``m_j = sum_h w_h z^T mu_h^j`` the mixture
    variance splits into ``param = sum_h w_h z^T Sigma_h^j z``, ``between = sum_h w_h
    (z^T mu_h^j - m_j)^2`` and ``noise = sigma_j^2``; ``encoder`` is the Sec. IV term
    ``(sigma_z^2)^T sum_h w_h mu_h^j . mu_h^j`` (zero when ``sigma_z2`` is None) and
    ``sigma_tot2`` is Sec. IV's total (see :class:`Prediction`).

    Args:
        state: the beam.
        z: ``(l,)`` latent features ``mu_phi(x, u)``.
        sigma_z2: optional ``(l,)`` encoder variance.
    """
    z = jnp.asarray(z, state.means.dtype)
    return _mixture(state, _project(state, z), sigma_z2)


def sigma_tot2(state: BeamState, z: ArrayLike, sigma_z2: ArrayLike | None = None) -> Array:
    """Sec. IV total predictive variance ``sigma_tot^2`` ``(d,)`` used to modulate ``Q``.

    ``(sigma_z^2)^T (sum_h w_h mu_h^j . mu_h^j) + sum_h w_h z^T Sigma_h^j z + sum_h w_h
    (z^T mu_h^j - m_j)^2``: encoder, parameter and between-hypothesis parts (no noise).
    """
    return predict(state, z, sigma_z2).sigma_tot2


def map_last_changepoint(state: BeamState) -> Array:
    """``()`` int32, the latest changepoint step on the most probable history (highest
    score ``L_{k,h}``, Eq. 7; ``-1``: none)."""
    return state.last_changepoint[jnp.argmax(state.log_scores)]


def marginal_decoder(state: BeamState) -> tuple[Array, Array]:
    """Moment-matched beam-marginal decoder posterior (Eq. 10 mixture over ``theta``).

    Returns ``mean (d, l) = sum_h w_h mu_h`` and ``cov (d, l, l) = sum_h w_h (Sigma_h +
    (mu_h - mean)(mu_h - mean)^T)`` per output row.
    """
    w = jax.nn.softmax(state.log_scores)
    mean = jnp.einsum("k,kdi->di", w, state.means)
    dev = state.means - mean
    sq = state.sqrt_covariances
    within = jnp.einsum("k,kdij,kdlj->dil", w, sq, sq)  # (d_c, l, l)
    cov = within + jnp.einsum("k,kdi,kdj->dij", w, dev, dev)
    return mean, 0.5 * (cov + jnp.swapaxes(cov, -1, -2))
