"""Changepoint-aware beam Bayesian linear regression for the decoder (Sec. III, Algorithm 1).

The residual model is ``delta_k = theta z_k + eps_k`` with ``eps_k ~ N(0, diag(sigma^2))``
(Eq. 4). Every output row ``theta^j`` has a Gaussian posterior per hypothesis ``h`` of a
beam of ``K`` changepoint histories. Equation numbers follow the paper's source: Eq. 5
tempering, Eq. 6 posterior, Eq. 7 score recursion (Lemma 3), Eq. 8 marginal likelihood,
Eq. 9 changepoint posterior, Eq. 10 beam predictive. One step of Algorithm 1:

1. predict with the beam mixture (Eq. 10, Sec. IV ``sigma_tot``);
2. for every hypothesis and both branches ``c_k in {0, 1}`` (tempering ``gamma in
   {1, beta^2}``, Eq. 5) evaluate the marginal likelihood (Eq. 8), the changepoint
   posterior (Eq. 9) and the candidate score (Eq. 7, Lemma 3);
3. keep the top-``K`` of the ``2K`` candidates and apply the posterior update (Eq. 6)
   to the survivors only. The update of a candidate depends on its parent and branch
   alone, so pruning before updating gives the same beam at half the work.

Optionally (``AdaptationConfig.prior_floor``) a changepoint re-injects the offline prior
``N(theta_0, tau^2 I)``: the tempered prior is ``p(theta | D)^gamma p_0(theta)^(rho (1 -
gamma))``, so it keeps at least the offline prior precision ``tau^-2 I`` (the assumption
in the proof of Lemma 2, where Eq. 5 alone multiplies the covariance by ``beta^-2`` in
every direction the data do not excite, at every changepoint) and its mean moves towards
``theta_0`` by as much as the posterior is forgotten.

Numerics. Each covariance is carried as a square root ``W`` with ``Sigma = W W^T``
(``BeamState.sqrt_covariances``) and updated with Potter's rank-one square-root form
[Potter 1963], the textbook numerically robust form of the Sherman--Morrison update of
Eq. 6: the covariance stays symmetric positive semi-definite by construction, also in
float32, and the update costs the same ``O(l^2)`` as Sherman--Morrison. The
covariance itself is ``BeamState.covariances``. Eq. 6 shows that ``Sigma^j`` depends on
the prior ``tau^2 I``, the features ``z`` and ``sigma_j^2`` but not on the residuals, so
when all outputs share one noise variance (scalar ``sigma2``, as in both Appendix D
presets) every output has the same covariance: the state then stores one square root per
hypothesis, ``(K, 1, l, l)``, instead of ``d`` identical copies.

Scores are stored shifted by a common constant so that the best one is ``0``
(``log_offset`` keeps the shift): softmax weights (Eq. 10) and top-``K`` pruning are
invariant to the shift, and float32 scores do not lose resolution as the raw cumulative
log-likelihood grows without bound.

Conventions. ``K`` is static and is read from the state's shapes by every function except
:func:`init`; all other hyperparameters are traced, so changing them does not recompile.
Step ``k`` counts processed observations (``0`` after :func:`init`). Unused beam slots
(Algorithm 1 line 2 starts with a single hypothesis) carry the prior with a ``-inf``
score: they get zero weight and are displaced by real candidates first.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

_LOG_2PI = math.log(2.0 * math.pi)


class AdaptationConfig(NamedTuple):
    """Hyperparameters of Algorithm 1 (Appendix D, "Online Inference" tables).

    ``K`` (beam size) is a static Python int used only by :func:`init`; the others may be
    Python floats or arrays and are traced under ``jit``. ``beta`` is the temperature of
    Eq. 5 (``gamma = beta^2`` on a changepoint). ``sigma2`` is a scalar or per-output
    ``(d,)`` observation-noise variance.

    ``prior_floor`` (``rho`` in ``[0, 1]``, default ``0``: Eq. 5 as written) re-injects
    part of the offline prior ``p_0 = N(theta_0, tau^2 I)`` at a changepoint: the tempered
    prior is the normalised product ``p(theta | D)^gamma p_0(theta)^(rho (1 - gamma))``
    (a power prior, App. "tempered priors", combined geometrically with the offline
    prior), i.e. precision ``P = gamma Sigma^{-1} + c I`` and mean ``P^{-1} (gamma
    Sigma^{-1} mu + c theta_0)`` with ``c = rho (1 - gamma) / tau^2``. With ``rho = 1`` a
    tempered prior is never more diffuse than the offline prior ``tau^2 I`` (every
    posterior then satisfies ``Sigma <= tau^2 I``), which is what the proof of Lemma 2
    assumes; without it, repeated changepoints inflate the covariance geometrically
    (``beta^-2`` per changepoint) in directions the data do not excite. As ``beta -> 0``
    the changepoint prior becomes the offline prior itself (a full reset, as in
    run-length changepoint detection). Needs ``tau2 > 0``.
    """

    K: int
    pi: ArrayLike
    beta: ArrayLike
    tau2: ArrayLike
    sigma2: ArrayLike
    prior_floor: ArrayLike = 0.0


def quadrotor_config() -> AdaptationConfig:
    """Quadrotor preset (Appendix D, quadrotor "Online Inference" table), with the offline
    prior re-injected at changepoints (``prior_floor = 1``), which keeps every tempered
    prior at least as precise as the offline prior, as Lemma 2's proof assumes: the
    swinging payload makes changepoints frequent, and repeated tempering would otherwise
    inflate the covariance beyond the prior in weakly excited directions."""
    return AdaptationConfig(K=15, pi=0.05, beta=0.997, tau2=0.1, sigma2=0.1, prior_floor=1.0)


def cartpole_config() -> AdaptationConfig:
    """Cartpole preset (Appendix D, cartpole "Online Inference" table)."""
    return AdaptationConfig(K=5, pi=0.05, beta=0.9, tau2=0.1, sigma2=0.1)


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
        """``(K,)`` cumulative scores ``L_{k,h}`` exactly as Algorithm 1 accumulates them."""
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


# ----------------------------------------------------------------------------- init


def init(theta0: ArrayLike, config: AdaptationConfig) -> BeamState:
    """Algorithm 1 lines 1-2: ``mu_0^j = theta_0^j``, ``Sigma_0^j = tau^2 I``, one hypothesis.

    The dtype of ``theta0`` (float32 or float64) is the dtype of the state. ``config.K``
    must be a concrete Python int. A scalar ``config.sigma2`` gives a state whose outputs
    share one covariance per hypothesis (exact, see the module notes); a ``(d,)`` one
    gives per-output covariances.
    """
    theta0 = jnp.asarray(theta0)
    if not jnp.issubdtype(theta0.dtype, jnp.floating):
        theta0 = theta0.astype(jnp.result_type(float))
    dtype = theta0.dtype
    d, l = theta0.shape
    K = int(config.K)
    d_cov = 1 if jnp.ndim(config.sigma2) == 0 else d
    tau = jnp.sqrt(jnp.asarray(config.tau2, dtype))
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
        sigma2=_noise(config.sigma2, d, dtype),
        prior_mean=theta0,
    )


# ------------------------------------------------------------------------- predict


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


def _noise(sigma2: ArrayLike, d: int, dtype) -> Array:
    return jnp.broadcast_to(jnp.asarray(sigma2, dtype), (d,))


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


# -------------------------------------------------------------------------- update


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


def _log_marginal(q: Array, r: Array, sigma2: Array, gamma: ArrayLike) -> Array:
    """Eq. 8: ``log p(delta | z, c)`` per hypothesis, summed over outputs; ``(K,)``.

    ``q = z^T Sigma z`` is ``(K, d_c)`` and broadcasts against ``r`` ``(K, d)``.
    """
    s = q / gamma + sigma2
    return -0.5 * jnp.sum(_LOG_2PI + jnp.log(s) + r * r / s, axis=-1)


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


def _update(
    state: BeamState, z: Array, delta: Array, config: AdaptationConfig, proj: _Projections
) -> tuple[BeamState, UpdateInfo]:
    dtype = state.means.dtype
    K, d, _ = state.means.shape
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
    ll0 = _log_marginal(proj.q, r, sigma2, 1.0)
    ll1 = _log_marginal(q1, r1, sigma2, g1)
    # Eq. 9 in log-odds form: logit p(c=1|.) = log Lambda + log(pi / (1 - pi)).
    logit = ll1 - ll0 + jnp.log(pi) - jnp.log1p(-pi)
    logp1 = jax.nn.log_sigmoid(logit)
    logp0 = jax.nn.log_sigmoid(-logit)

    # Eq. 7 / Algorithm 1: L_k = L_{k-1} + log p(delta|z,c) + log p(c|.), both branches.
    prev = state.log_scores
    cand = jnp.concatenate([prev + ll0 + logp0, prev + ll1 + logp1])
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

    For each hypothesis: Eq. 8 marginal log-likelihood under the tempered prior
    ``N(mu, Sigma/gamma)`` for ``gamma in {1, beta^2}`` (Eq. 5), the Eq. 9 changepoint
    posterior ``p1``, and the candidate scores ``L + log p(delta|z,c) + log(c p1 + (1-c)
    (1-p1))`` (Eq. 7, Lemma 3); the top-``K`` of the ``2K`` candidates (:func:`top_k`, the
    same selection as ``jax.lax.top_k``) get the Eq. 6 posterior update. The new beam is
    sorted by score, so slot 0 is the MAP hypothesis.

    Algorithm 1 is followed as written: ``log p(c_k|.)`` is the Eq. 9 *posterior*, which
    already contains ``p(delta_k|c_k)``, so the data term enters a candidate's score twice
    and two sibling candidates differ by ``2 log Lambda_k + log(pi / (1 - pi))`` (with
    ``Lambda_k`` the Eq. 9 likelihood ratio) rather than by the log posterior odds.

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


# ------------------------------------------------------------------ packed fast path


class PackedBeam(NamedTuple):
    """A :class:`BeamState` plus ``pi, beta, tau2, prior_floor`` in five arrays, for the
    real-time loop.

    At this problem size a jitted call costs about as much per argument and result leaf
    as the arithmetic of a whole step, so the loop passes the two large arrays and the
    constant prior mean as they are and everything small in one float and one int buffer:
    ``floats = [log_scores (K), log_offset, sigma2 (d), pi, beta, tau2, prior_floor]``
    (state dtype),
    ``ints = [num_changepoints (K), last_changepoint (K), is_changepoint (K), step]``.
    (Flattening the arrays into the float buffer too would save leaves but makes XLA fuse
    the update into one slow concatenation kernel: with the ``(d, l)`` prior mean in it a
    step took three times as long.) See :func:`make_packed_step`.
    """

    means: Array
    sqrt_covariances: Array
    floats: Array
    ints: Array
    prior_mean: Array


def pack(state: BeamState, config: AdaptationConfig) -> PackedBeam:
    """``state`` and the traced hyperparameters of ``config`` as a :class:`PackedBeam`.

    ``state`` stays valid after the packed beam has been donated to a step.
    """
    dtype = state.means.dtype
    hyper = jnp.stack(
        [jnp.asarray(v, dtype) for v in (config.pi, config.beta, config.tau2, config.prior_floor)]
    )
    floats = jnp.concatenate([state.log_scores, state.log_offset[None], state.sigma2, hyper])
    ints = jnp.concatenate(
        [
            state.num_changepoints,
            state.last_changepoint,
            state.is_changepoint.astype(jnp.int32),
            state.step[None],
        ]
    )
    # Copies, so that donating the packed beam never invalidates ``state``.
    return PackedBeam(
        jnp.copy(state.means),
        jnp.copy(state.sqrt_covariances),
        floats,
        ints,
        jnp.copy(state.prior_mean),
    )


def unpack(packed: PackedBeam) -> tuple[BeamState, AdaptationConfig]:
    """Inverse of :func:`pack` (sizes are read from the array shapes)."""
    K, d, _ = packed.means.shape
    f, n = packed.floats, packed.ints
    sigma2 = f[K + 1 : K + 1 + d]
    pi, beta, tau2, floor = f[K + 1 + d], f[K + 2 + d], f[K + 3 + d], f[K + 4 + d]
    state = BeamState(
        means=packed.means,
        sqrt_covariances=packed.sqrt_covariances,
        log_scores=f[:K],
        log_offset=f[K],
        num_changepoints=n[:K],
        last_changepoint=n[K : 2 * K],
        is_changepoint=n[2 * K : 3 * K] != 0,
        step=n[3 * K],
        sigma2=sigma2,
        prior_mean=packed.prior_mean,
    )
    shared = packed.sqrt_covariances.shape[1] == 1
    noise = sigma2[0] if shared else sigma2  # keeps the shared-covariance contract
    return state, AdaptationConfig(
        K=K, pi=pi, beta=beta, tau2=tau2, sigma2=noise, prior_floor=floor
    )


def packed_step(packed: PackedBeam, inputs: Array) -> tuple[PackedBeam, Array]:
    """:func:`step` on a :class:`PackedBeam` (Algorithm 1, one iteration).

    Args:
        packed: the beam and hyperparameters.
        inputs: ``[z (l), delta (d), sigma_z2 (l)]`` in the state dtype (zeros for
            ``sigma_z2`` when the encoder variance is not used).

    Returns:
        the new packed beam and ``outputs`` (see :func:`unpack_outputs`).
    """
    state, config = unpack(packed)
    _, d, l = state.means.shape
    z, delta, sigma_z2 = inputs[:l], inputs[l : l + d], inputs[l + d :]
    new_state, pred, info = step(state, z, delta, config, sigma_z2)
    dtype = state.means.dtype
    outputs = jnp.concatenate(
        [
            *pred,
            info.p_change,
            jnp.stack([info.cp_prob, info.cp_mass, info.log_evidence]),
            jnp.stack([info.changepoint, info.map_last_changepoint, info.accepted]).astype(dtype),
        ]
    )
    return pack(new_state, config), outputs


def unpack_outputs(outputs, d: int, K: int) -> tuple[Prediction, UpdateInfo]:
    """Split the ``outputs`` of :func:`packed_step` (NumPy or JAX array) by slicing only.

    ``map_last_changepoint`` comes back in the state dtype (exact below ``2**24`` steps
    in float32; the int32 value is ``ints[K]`` of the returned :class:`PackedBeam`).
    """
    pred = Prediction(*(outputs[i * d : (i + 1) * d] for i in range(7)))
    o = 7 * d
    info = UpdateInfo(
        p_change=outputs[o : o + K],
        cp_prob=outputs[o + K],
        cp_mass=outputs[o + K + 1],
        log_evidence=outputs[o + K + 2],
        changepoint=outputs[o + K + 3] != 0,
        map_last_changepoint=outputs[o + K + 4],
        accepted=outputs[o + K + 5] != 0,
    )
    return pred, info


def make_packed_step():
    """Jitted :func:`packed_step` that donates the packed beam (updated in place).

    Returns ``fn(packed, inputs) -> (packed, outputs)``; the packed beam passed in must not
    be used after the call. Compiles once per beam size, dimensions and dtype.
    """
    return jax.jit(packed_step, donate_argnums=0)
