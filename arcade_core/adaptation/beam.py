"""One step of Algorithm 1 over the beam: expand, score, prune, update (Eqs. 5-10, Lemma 3).

Every hypothesis branches into ``c_k in {0, 1}``; each candidate is scored with the Eq. 8
marginal likelihood and the Eq. 7 recursion (Lemma 3), whose changepoint term is the Eq. 9
posterior (``AdaptationConfig.score = "algorithm1"``, Algorithm 1 as written) or the prior
``pi`` (``"joint"``, the exact joint log-probability of the path); the top-``K`` survive
(:func:`top_k`) and only they get the Eq. 6 posterior update.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from arcade_core.adaptation.config import AdaptationConfig, nu_of, score_of
from arcade_core.adaptation.posterior import (
    _log_marginal,
    _potter,
    _project,
    _Projections,
    _tempered,
)
from arcade_core.adaptation.predictive import _mixture, map_last_changepoint
from arcade_core.adaptation.state import BeamState, Prediction, UpdateInfo, _noise


def top_k(values: Array, k: int) -> tuple[Array, Array]:
    """The ``k`` largest entries of a 1-D array, descending, ties to the lower index.

    Same result as ``jax.lax.top_k`` (Algorithm 1, "prune beam"), computed by
    pairwise ranking: for the ``2K <= 60`` candidates of a beam this is one fused
    ``O(K^2)`` comparison kernel, several times faster on CPU than the sort behind
    ``lax.top_k``. NaN ranks below every number (``-inf`` included), so the indices are
    always a valid selection.
    """
    n = values.shape[0]
    i = jnp.arange(n)
    nan = jnp.isnan(values)
    # A strict total order (NaN last) keeps the ranks a permutation.
    same_class = nan[None, :] == nan[:, None]
    tie = (values[None, :] == values[:, None]) | (nan[None, :] & nan[:, None])
    before = (nan[:, None] & ~nan[None, :]) | (
        same_class & ((values[None, :] > values[:, None]) | (tie & (i[None, :] < i[:, None])))
    )
    rank = jnp.sum(before, axis=1)  # a permutation of 0..n-1
    hit = rank[None, :] == jnp.arange(k)[:, None]
    idx = jnp.sum(jnp.where(hit, i[None, :], 0), axis=1)
    return values[idx], idx


def _update(
    state: BeamState, z: Array, delta: Array, config: AdaptationConfig, proj: _Projections
) -> tuple[BeamState, UpdateInfo]:
    dtype = state.means.dtype
    K, d, _ = state.means.shape
    score = score_of(config)  # static: one trace per scoring rule
    pi = jnp.asarray(config.pi, dtype)
    beta2 = jnp.square(jnp.asarray(config.beta, dtype))
    sigma2 = _noise(config.sigma2, d, dtype)
    d_cov = state.sqrt_covariances.shape[1]
    if d_cov == 1 and d > 1 and jnp.ndim(config.sigma2) > 0:
        raise ValueError(
            "this state shares one covariance across outputs (initialised with a scalar "
            "sigma2); per-output sigma2 needs a state initialised with a (d,) sigma2"
        )

    r = delta - proj.m  # (K, d) innovation under each parent
    # Changepoint branch: tempered prior (Eq. 5), optionally with the offline prior
    # re-injected; its mean (and so its innovation) differs from the parent's then.
    mean1, w1, a1, b1, q1, g1 = _tempered(state, z, proj, beta2, config)
    r1 = delta - jnp.sum(mean1 * z, axis=-1)
    nu = nu_of(config)  # static: one trace per likelihood form
    ll0 = _log_marginal(proj.q, r, sigma2, 1.0, nu)
    ll1 = _log_marginal(q1, r1, sigma2, g1, nu)
    # Eq. 9 in log-odds form: logit p(c=1|.) = log Lambda + log(pi / (1 - pi)).
    logit = ll1 - ll0 + jnp.log(pi) - jnp.log1p(-pi)
    logp1 = jax.nn.log_sigmoid(logit)
    logp0 = jax.nn.log_sigmoid(-logit)

    if score == "joint":
        # Eq. 7 with its own conditioning (c_{1:k-1}, x_{1:k}, u_{1:k}: not delta_k), so
        # log p(c_k|.) is the prior: the exact joint log-probability of the path.
        logc0, logc1 = jnp.log1p(-pi), jnp.log(pi)
    else:
        # Algorithm 1 as written: log p(c_k|.) is the Eq. 9 posterior.
        logc0, logc1 = logp0, logp1

    # Eq. 7: L_k = L_{k-1} + log p(delta|z,c) + log p(c|.), both branches.
    prev = state.log_scores
    cand = jnp.concatenate([prev + ll0 + logc0, prev + ll1 + logc1])
    top, idx = top_k(cand, K)
    # A non-finite observation (or one no hypothesis can score) would turn every score
    # into NaN for good: it is skipped. Each hypothesis then keeps its slot on the c = 0
    # branch with a zero gain and innovation, which makes Eq. 6 the identity bit for bit
    # (cheaper than selecting between the old and the new beam).
    accepted = jnp.all(jnp.isfinite(z)) & jnp.all(jnp.isfinite(delta)) & jnp.isfinite(top[0])
    idx = jnp.where(accepted, idx, jnp.arange(K))
    parent = idx % K
    branch = idx >= K
    gamma = jnp.where(branch, g1, jnp.ones((), dtype))

    # One gather of everything the survivors need from their parents (and branch).
    parts = (state.means, state.sqrt_covariances, proj.a, proj.b, proj.q, r)
    parts1 = (mean1, w1, a1, b1, q1, r1)
    rows = jnp.concatenate(
        [
            jnp.concatenate([x.reshape(K, -1) for x in parts], axis=1),
            jnp.concatenate([x.reshape(K, -1) for x in parts1], axis=1),
        ]
    )[idx]
    sizes = [math.prod(x.shape[1:]) for x in parts]
    splits = [sum(sizes[: i + 1]) for i in range(len(sizes) - 1)]
    mean_p, w_p, a_p, b_p, q_p, r_p = (
        x.reshape(K, *y.shape[1:]) for x, y in zip(jnp.split(rows, splits, axis=1), parts)
    )
    # On a skip: mu + 0 * (-0 / s) = mu and (W - c 0 0^T) / sqrt(1) = W exactly.
    a_p, b_p, q_p = (jnp.where(accepted, x, 0.0) for x in (a_p, b_p, q_p))
    r_p = jnp.where(accepted, r_p, -0.0)
    new_mean, new_w = _potter(mean_p, w_p, a_p, b_p, q_p, r_p, sigma2, sigma2[:d_cov], gamma)

    shift = top[0]  # top_k is sorted: the best candidate (finite when accepted) leads
    k = jnp.where(accepted, state.step + 1, state.step)
    last = jnp.where(branch, k, state.last_changepoint[parent])
    new_state = BeamState(
        means=new_mean,
        sqrt_covariances=new_w,
        log_scores=jnp.where(accepted, top - shift, prev),
        log_offset=jnp.where(accepted, state.log_offset + shift, state.log_offset),
        num_changepoints=state.num_changepoints[parent] + branch.astype(jnp.int32),
        last_changepoint=last,
        is_changepoint=jnp.where(accepted, branch, state.is_changepoint),
        step=k,
        sigma2=jnp.where(accepted, sigma2, state.sigma2),
        prior_mean=state.prior_mean,
    )

    w_prev = jax.nn.softmax(prev)
    w_new = jax.nn.softmax(new_state.log_scores)
    p1 = jnp.where(accepted, jnp.exp(logp1), 0.0)
    mix = jnp.logaddexp(jnp.log(pi) + ll1, jnp.log1p(-pi) + ll0)
    log_evidence = jax.nn.logsumexp(mix, b=w_prev)
    prev_map_last = map_last_changepoint(state)
    info = UpdateInfo(
        p_change=p1,
        cp_prob=w_prev @ p1,
        cp_mass=jnp.sum(jnp.where(branch, w_new, 0.0)),
        changepoint=accepted & (last[0] > prev_map_last),
        map_last_changepoint=last[0],
        log_evidence=jnp.where(accepted, log_evidence, jnp.nan),
        accepted=accepted,
    )
    return new_state, info


def update(
    state: BeamState, z: ArrayLike, delta: ArrayLike, config: AdaptationConfig
) -> tuple[BeamState, UpdateInfo]:
    """Algorithm 1 after "observe new data": expand every hypothesis into ``c_k in {0,1}``,
    score, prune.

    For each hypothesis: Eq. 8 marginal log-likelihood ``l_c = log p(delta|z,c)`` under
    the tempered prior ``N(mu, Sigma/gamma)`` for ``gamma in {1, beta^2}`` (Eq. 5), the
    Eq. 9 changepoint posterior ``p1``, and the candidate scores (Eq. 7, Lemma 3)
    chosen by the static ``config.score``:

    - ``"algorithm1"`` (default, Algorithm 1 as written):
      ``L + l_c + log(c p1 + (1 - c) (1 - p1))``;
    - ``"joint"``: ``L + l_c + log(c pi + (1 - c) (1 - pi))``,

    then the top-``K`` of the ``2K`` candidates (:func:`top_k`, the same selection as
    ``jax.lax.top_k``) get the Eq. 6 posterior update. The new beam is sorted by score,
    so slot 0 is the MAP hypothesis.

    How the two differ. Eq. 7 conditions ``c_k`` on ``c_{1:k-1}, x_{1:k}, u_{1:k}``, not on
    ``delta_k``, so its exact value is the prior and ``"joint"`` accumulates the joint
    log-probability ``log p(delta_{1:k}, c_{1:k} | x, u)`` (App. "Changepoint Scoring"):
    the beam weights (Eq. 10) are the exact posterior of the paths the beam keeps.
    Algorithm 1 uses the Eq. 9 *posterior*, which already contains ``p(delta_k|c_k)``: per
    step it adds ``log p(c_k|delta_k, .) - log p(c_k) = l_c - log(pi e^{l_1} + (1 - pi)
    e^{l_0})`` to the joint score, so the data term enters twice. Two sibling candidates
    differ by ``2 log Lambda_k + log(pi / (1 - pi))`` with ``"algorithm1"`` and by ``log
    Lambda_k + log(pi / (1 - pi))`` (the log posterior odds) with ``"joint"``, where
    ``Lambda_k = e^{l_1 - l_0}`` is the Eq. 9 likelihood ratio: the changepoint branch
    outranks its sibling when ``Lambda_k > sqrt((1 - pi) / pi)`` (``sqrt(19) = 4.36`` for
    ``pi = 0.05``) with ``"algorithm1"`` but only when ``Lambda_k > (1 - pi) / pi``
    (``19``) with ``"joint"``, i.e. when its posterior probability exceeds 1/2. With
    ``"algorithm1"`` the weights are not a posterior of the paths: each step multiplies a
    path's weight by ``p(c_k|delta_k, .) / p(c_k)``, which sharpens towards whichever
    branch the residual favours (a changepoint after a surprising residual). ``p_change``,
    ``cp_prob`` and ``log_evidence`` in ``info`` are the same Eq. 9 / App. "LRT"
    quantities under both scores (computed from the previous beam's weights).

    An observation with a non-finite ``z`` or ``delta`` (or one that no hypothesis can
    score) is skipped: the state comes back unchanged and ``info.accepted`` is False (see
    :class:`UpdateInfo`), so later updates proceed as if it had never arrived.

    Args:
        state: beam after step ``k - 1``.
        z: ``(l,)`` latent features ``z_k``.
        delta: ``(d,)`` residual ``delta_k = x_{k+1} - f_nom(x_k, u_k)``.
        config: hyperparameters (``K`` is taken from ``state``).
    """
    dtype = state.means.dtype
    z = jnp.asarray(z, dtype)
    delta = jnp.asarray(delta, dtype)
    return _update(state, z, delta, config, _project(state, z))


def step(
    state: BeamState,
    z: ArrayLike,
    delta: ArrayLike,
    config: AdaptationConfig,
    sigma_z2: ArrayLike | None = None,
) -> tuple[BeamState, Prediction, UpdateInfo]:
    """One iteration of Algorithm 1: predict at ``z_k`` (Eq. 10), then update with
    ``delta_k`` and prune (Eqs. 5-9, Lemma 3). The prediction is made *before* ``delta_k``
    is seen, from the same projections the update reuses.
    """
    dtype = state.means.dtype
    z = jnp.asarray(z, dtype)
    delta = jnp.asarray(delta, dtype)
    proj = _project(state, z)
    pred = _mixture(state, proj, sigma_z2)
    new_state, info = _update(state, z, delta, config, proj)
    return new_state, pred, info
