"""The beam of changepoint hypotheses (Algorithm 1 lines 1-2) and what one step returns.

:class:`BeamState` holds every hypothesis' Gaussian posterior over the decoder rows (Eq. 6)
in square-root form and its cumulative score (Eq. 7); :class:`Prediction` is the Eq. 10
predictive and :class:`UpdateInfo` the diagnostics of one update.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from arcade_core.adaptation.config import AdaptationConfig


class BeamState(NamedTuple):
    """Beam of ``K`` changepoint hypotheses over ``d`` outputs with ``l`` latent features.

    Attributes:
        means: ``(K, d, l)`` posterior means ``mu_{k,h}^j``.
        sqrt_covariances: ``(K, d_c, l, l)`` square roots ``W`` with ``Sigma = W W^T``;
            ``d_c = 1`` (shared by all outputs) when the state was initialised with a
            scalar ``sigma2``, else ``d_c = d``.
        log_scores: ``(K,)`` cumulative scores ``L_{k,h}`` (Eq. 7, Lemma 3) minus ``log_offset``;
            ``-inf`` marks an unused slot.
        log_offset: ``()`` common shift; the raw score is ``log_scores + log_offset``.
        num_changepoints: ``(K,)`` int32, changepoints on the hypothesis' path.
        last_changepoint: ``(K,)`` int32, step of its latest changepoint (``-1``: none).
        is_changepoint: ``(K,)`` bool, whether its latest step took ``c_k = 1``.
        step: ``()`` int32, number of processed observations ``k``.
        sigma2: ``(d,)`` observation-noise variances ``sigma_j^2`` of the latest update
            (set by :func:`init`, refreshed from ``config`` by :func:`update`), so that
            :func:`predict` needs only the state.
        prior_mean: ``(d, l)`` the offline decoder ``theta_0`` (mean of the offline prior),
            which a changepoint re-injects when ``AdaptationConfig.prior_floor > 0``.
    """

    means: Array
    sqrt_covariances: Array
    log_scores: Array
    log_offset: Array
    num_changepoints: Array
    last_changepoint: Array
    is_changepoint: Array
    step: Array
    sigma2: Array
    prior_mean: Array

    @property
    def covariances(self) -> Array:
        """``(K, d, l, l)`` posterior covariances ``Sigma_{k,h}^j = W W^T`` (Eq. 6)."""
        w = self.sqrt_covariances
        cov = jnp.einsum("...ij,...kj->...ik", w, w)
        cov = 0.5 * (cov + jnp.swapaxes(cov, -1, -2))  # exactly symmetric, not just to rounding
        return jnp.broadcast_to(cov, (*self.means.shape, self.means.shape[-1]))

    @property
    def weights(self) -> Array:
        """``(K,)`` beam weights ``w_h = softmax(L_{k,h})`` (Eq. 10)."""
        return jax.nn.softmax(self.log_scores)

    @property
    def raw_log_scores(self) -> Array:
        """``(K,)`` cumulative scores ``L_{k,h}`` exactly as accumulated (Eq. 7 with the
        ``AdaptationConfig.score`` rule: Algorithm 1's, or the joint log-probability)."""
        return self.log_scores + self.log_offset


class Prediction(NamedTuple):
    """Beam-marginal one-step prediction of the residual (Eq. 10, Sec. IV), all ``(d,)``.

    ``variance = param + between + noise + encoder``: the variance of the Eq. 10 mixture,
    plus the first-order encoder term when an encoder variance is given.
    ``sigma_tot2 = encoder + param + between`` is the Sec. IV quantity that modulates the
    MPC cost; as in the paper it excludes the observation noise ``sigma_j^2``, which no
    amount of caution in the controller can reduce.
    """

    mean: Array
    param: Array
    between: Array
    noise: Array
    encoder: Array
    sigma_tot2: Array
    variance: Array


class UpdateInfo(NamedTuple):
    """Diagnostics of one update of Algorithm 1.

    Attributes:
        p_change: ``(K,)`` Eq. 9 changepoint posterior of each previous hypothesis.
        cp_prob: ``()`` beam-weighted changepoint posterior ``sum_h w_h p_h(c_k=1|.)``.
        cp_mass: ``()`` weight of the new beam on hypotheses whose latest step is a
            changepoint.
        changepoint: ``()`` bool detection flag: the latest changepoint on the new MAP path
            is later than the latest changepoint on the previous MAP path, i.e. the most
            probable history has gained a changepoint (possibly dated a few steps back
            when the evidence needed a few observations to accumulate;
            ``map_last_changepoint`` dates it). A MAP history that switches to a path with
            an older changepoint and back raises it again for the same dated step; a
            consumer that reports changepoints keeps the newest step reported (the adapter
            service does).
        map_last_changepoint: ``()`` int32, latest changepoint step on the new MAP path
            (``-1``: none).
        log_evidence: ``()`` one-step log predictive density of ``delta_k`` under the
            beam and the changepoint prior,
            ``log sum_h w_h [pi p(delta|c=1,h) + (1 - pi) p(delta|c=0,h)]`` (App. "LRT").
        accepted: ``()`` bool, False when the observation was skipped: ``z`` or ``delta``
            not finite, or no candidate with a finite score (a residual so large that
            Eq. 8 underflows for every hypothesis). The state is then returned unchanged
            (same step), ``p_change``, ``cp_prob`` and ``cp_mass`` are 0, ``changepoint``
            is False, ``map_last_changepoint`` is that of the unchanged MAP path and
            ``log_evidence`` is NaN.
    """

    p_change: Array
    cp_prob: Array
    cp_mass: Array
    changepoint: Array
    map_last_changepoint: Array
    log_evidence: Array
    accepted: Array


def init(theta0: ArrayLike, config: AdaptationConfig) -> BeamState:
    """Algorithm 1 lines 1-2: ``mu_0^j = theta_0^j``, ``Sigma_0^j = tau^2 I``, one hypothesis.

    The dtype of ``theta0`` (float32 or float64) is the dtype of the state. ``config.K``
    must be a concrete Python int. A scalar ``config.sigma2`` gives a state whose outputs
    share one covariance per hypothesis (exact, see the module notes); a ``(d,)`` one
    gives per-output covariances.
    """
    theta0, tau2, sigma2 = (
        x if hasattr(x, "shape") or isinstance(x, float | int) else jnp.asarray(x)
        for x in (theta0, config.tau2, config.sigma2)
    )  # nested sequences: arrays, as jit takes them
    K = int(config.K)
    d_cov = 1 if jnp.ndim(sigma2) == 0 else jnp.shape(theta0)[0]
    return _init(theta0, tau2, sigma2, K, d_cov)


# Jitted: one compiled program instead of a dozen eager operations (each a compilation or a
# cache read in a fresh process, tens of milliseconds) wherever a service starts a beam.
@functools.partial(jax.jit, static_argnums=(3, 4))
def _init(theta0: ArrayLike, tau2: ArrayLike, sigma2: ArrayLike, K: int, d_cov: int) -> BeamState:
    theta0 = jnp.asarray(theta0)
    if not jnp.issubdtype(theta0.dtype, jnp.floating):
        theta0 = theta0.astype(jnp.result_type(float))
    dtype = theta0.dtype
    d, l = theta0.shape
    tau = jnp.sqrt(jnp.asarray(tau2, dtype))
    eye = jnp.eye(l, dtype=dtype) * tau
    scores = jnp.full((K,), -jnp.inf, dtype).at[0].set(0.0)
    return BeamState(
        means=jnp.broadcast_to(theta0, (K, d, l)),
        sqrt_covariances=jnp.broadcast_to(eye, (K, d_cov, l, l)),
        log_scores=scores,
        log_offset=jnp.zeros((), dtype),
        num_changepoints=jnp.zeros((K,), jnp.int32),
        last_changepoint=jnp.full((K,), -1, jnp.int32),
        is_changepoint=jnp.zeros((K,), bool),
        step=jnp.zeros((), jnp.int32),
        sigma2=_noise(sigma2, d, dtype),
        prior_mean=theta0,
    )


def _noise(sigma2: ArrayLike, d: int, dtype) -> Array:
    return jnp.broadcast_to(jnp.asarray(sigma2, dtype), (d,))
