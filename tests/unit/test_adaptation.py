"""Changepoint-aware beam BLR (Sec. III, Eqs. 5-10, Algorithm 1) against independent references.

The references below are straightforward NumPy/SciPy implementations written from the
paper's formulas (information form, explicit Gaussian densities, exhaustive enumeration of
changepoint paths); they share no code with ``arcade_core.adaptation``.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate, stats

from arcade_core import adaptation as A

# ----------------------------------------------------------------------- references


def ref_log_marginals(mu, cov, z, delta, sigma2, gammas):
    """Eq. 8 with explicit normal densities: ``log p(delta | z, c)`` for each gamma."""
    out = []
    for g in gammas:
        total = 0.0
        for j in range(mu.shape[0]):
            var = z @ cov[j] @ z / g + sigma2[j]
            total += stats.norm.logpdf(delta[j], loc=z @ mu[j], scale=np.sqrt(var))
        out.append(total)
    return out


def ref_cp_posterior(ll0, ll1, pi):
    """Eq. 9 by Bayes' rule on explicit probabilities (log-sum-exp for range only)."""
    a, b = np.log(pi) + ll1, np.log1p(-pi) + ll0
    return float(np.exp(a - np.logaddexp(a, b)))


def brute_force(theta0, tau2, sigma2, pi, beta, Z, D, floor=0.0):
    """All 2^T changepoint paths: tempered recursion in information form + Algorithm 1 scores.

    ``floor`` is ``rho``, the share of the offline prior ``N(theta0, tau^2 I)`` a changepoint
    re-injects: in information form the changepoint prior is ``beta^2 (P, eta) + rho (1 -
    beta^2) (I / tau^2, theta0 / tau^2)`` (``floor = 0``: Eq. 5, the mean kept).
    Returns a list of dicts with the raw score, posterior mean/covariance (d, l[, l]),
    number of changepoints and step of the last changepoint (-1: none) per path.
    """
    d, l = theta0.shape
    T = Z.shape[0]
    out = []
    for path in itertools.product((0, 1), repeat=T):
        prec = np.stack([np.eye(l) / tau2] * d)
        eta = theta0 / tau2
        score, last = 0.0, -1
        for k, c in enumerate(path):
            cov = np.linalg.inv(prec)
            mu = np.einsum("dij,dj->di", cov, eta)
            (ll0,) = ref_log_marginals(mu, cov, Z[k], D[k], sigma2, (1.0,))
            c0 = floor * (1.0 - beta**2) / tau2
            prec1 = beta**2 * prec + c0 * np.eye(l)
            eta1 = beta**2 * np.einsum("dij,dj->di", prec, mu) + c0 * theta0
            mu1 = np.einsum("dij,dj->di", np.linalg.inv(prec1), eta1)
            (ll1,) = ref_log_marginals(mu1, np.linalg.inv(prec1), Z[k], D[k], sigma2, (1.0,))
            p1 = ref_cp_posterior(ll0, ll1, pi)
            score += (ll1 + np.log(p1)) if c else (ll0 + np.log(1.0 - p1))
            if c:  # tempered prior (Eq. 5), with the offline prior re-injected if floor
                prec, eta = prec1, eta1
            prec = prec + np.outer(Z[k], Z[k])[None] / sigma2[:, None, None]
            eta = eta + D[k][:, None] * Z[k][None, :] / sigma2[:, None]
            if c:
                last = k + 1
        cov = np.linalg.inv(prec)
        out.append(
            dict(
                score=score,
                mean=np.einsum("dij,dj->di", cov, eta),
                cov=cov,
                ncp=sum(path),
                last=last,
            )
        )
    return out


def ref_mixture_prediction(means, covs, weights, z, sigma2):
    """Eq. 10 mixture moments per output computed hypothesis by hypothesis."""
    m_h = np.einsum("kdi,i->kd", means, z)
    v_h = np.einsum("i,kdij,j->kd", z, covs, z)
    mean = weights @ m_h
    second = weights @ (v_h + sigma2 + m_h**2)
    return mean, second - mean**2


def random_problem(seed, d, l, T, tau2=0.1, sigma2=0.1, switch=None):
    """Latent features ~ N(0, I) (VLD prior), decoders drawn around theta0, Gaussian noise."""
    rng = np.random.default_rng(seed)
    theta0 = 0.3 * rng.normal(size=(d, l))
    th_a = theta0 + np.sqrt(tau2) * rng.normal(size=(d, l))
    th_b = th_a + np.sqrt(tau2) * rng.normal(size=(d, l))
    Z = rng.normal(size=(T, l))
    thetas = np.stack([th_b if (switch is not None and t >= switch) else th_a for t in range(T)])
    D = np.einsum("tdi,ti->td", thetas, Z) + np.sqrt(sigma2) * rng.normal(size=(T, d))
    return theta0, Z, D


def run(state, Z, D, config):
    fn = jax.jit(A.step)
    infos = []
    for z, delta in zip(Z, D):
        state, _, info = fn(state, z, delta, config)
        infos.append(info)
    return state, infos


# ----------------------------------------------------------------------- basics


def test_presets_match_appendix_d():
    q, c = A.quadrotor_config(), A.cartpole_config()
    assert (q.K, q.pi, q.beta, q.tau2, q.sigma2) == (15, 0.05, 0.997, 0.1, 0.1)
    assert (c.K, c.pi, c.beta, c.tau2, c.sigma2) == (5, 0.05, 0.9, 0.1, 0.1)
    # Lemma 2's assumption (offline prior re-injected) on the quadrotor; Eq. 5 as written else.
    assert (q.prior_floor, c.prior_floor) == (1.0, 0.0)


@pytest.mark.parametrize("floor", [0.0, 1.0])
def test_repeated_changepoints_and_the_prior_precision_floor(floor):
    """Lemma 2 assumes a tempered prior is never more diffuse than ``tau^2 I``.

    Forced changepoints (``pi`` ~ 1) with features that only excite the first latent
    direction: Eq. 5 alone inflates the unexcited directions by ``beta^-2`` per step;
    with the floor every covariance stays below the prior, and the excited direction
    still learns (its variance falls well below ``tau^2``).
    """
    d, l, tau2, beta, T = 2, 3, 0.1, 0.7, 30
    cfg = A.AdaptationConfig(
        K=2, pi=1.0 - 1e-9, beta=beta, tau2=tau2, sigma2=0.1, prior_floor=floor
    )
    z = np.array([1.0, 0.0, 0.0])
    D = np.random.default_rng(0).normal(size=(T, d))
    state, _ = run(A.init(np.zeros((d, l)), cfg), [z] * T, D, cfg)
    assert int(state.num_changepoints[0]) == T  # every step was a changepoint
    top = np.linalg.eigvalsh(np.asarray(state.covariances[0]))[:, -1]
    if floor:
        assert np.all(top <= tau2 * (1 + 1e-12))
        assert float(state.covariances[0, 0, 0, 0]) < 0.5 * tau2
    else:
        np.testing.assert_allclose(top, tau2 * beta ** (-2 * T), rtol=1e-9)


def test_a_full_reset_restarts_from_the_offline_prior():
    """With the offline prior re-injected (``prior_floor = 1``) and ``beta -> 0`` a
    changepoint's prior is ``N(theta0, tau^2 I)`` itself, mean included: after forced
    changepoints the posterior is the one-observation posterior from the offline prior,
    whatever the earlier segments learned. (Keeping the stale mean instead would leave it
    near the previous segment's decoder.)"""
    d, l, tau2, sigma2 = 2, 3, 0.1, 0.1
    theta0, Z, D = random_problem(3, d, l, T=12, tau2=tau2, sigma2=sigma2, switch=6)
    D = D + 5.0  # earlier segments far from theta0
    cfg = A.AdaptationConfig(K=2, pi=1.0, beta=1e-6, tau2=tau2, sigma2=sigma2, prior_floor=1.0)
    state, _ = run(A.init(theta0, cfg), Z, D, cfg)
    assert int(state.num_changepoints[0]) == len(Z)
    mean, w = A.posterior_update(
        jnp.asarray(theta0), np.sqrt(tau2) * jnp.eye(l)[None], Z[-1], D[-1], sigma2
    )
    np.testing.assert_allclose(state.means[0], mean, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(state.covariances[0, 0], w[0] @ w[0].T, rtol=1e-6, atol=1e-12)


def test_init_has_one_hypothesis_and_prior():
    theta0 = np.arange(6.0).reshape(2, 3)
    s = A.init(theta0, A.AdaptationConfig(K=4, pi=0.1, beta=0.5, tau2=0.2, sigma2=0.3))
    # Scalar sigma2: all outputs share one covariance per hypothesis (Eq. 6 does not
    # depend on the residuals), stored once; per-output sigma2: one per output.
    assert s.means.shape == (4, 2, 3) and s.sqrt_covariances.shape == (4, 1, 3, 3)
    per_output = A.AdaptationConfig(K=4, pi=0.1, beta=0.5, tau2=0.2, sigma2=np.array([0.3, 0.4]))
    assert A.init(theta0, per_output).sqrt_covariances.shape == (4, 2, 3, 3)
    with pytest.raises(ValueError, match="per-output sigma2"):
        A.update(s, np.ones(3), np.ones(2), per_output)
    np.testing.assert_array_equal(s.means[0], theta0)
    np.testing.assert_allclose(s.covariances, np.broadcast_to(0.2 * np.eye(3), (4, 2, 3, 3)))
    np.testing.assert_array_equal(s.weights, [1.0, 0.0, 0.0, 0.0])
    assert np.isneginf(s.log_scores[1:]).all() and s.log_scores[0] == 0.0
    np.testing.assert_array_equal(s.sigma2, [0.3, 0.3])
    assert int(s.step) == 0 and (np.asarray(s.last_changepoint) == -1).all()
    # The prior predictive is exact, with no NaN from the unused slots.
    z = np.array([1.0, -2.0, 0.5])
    p = A.predict(s, z)
    np.testing.assert_allclose(p.mean, theta0 @ z)
    np.testing.assert_allclose(p.param, 0.2 * z @ z)
    np.testing.assert_array_equal(p.between, 0.0)
    np.testing.assert_allclose(p.variance, 0.2 * z @ z + 0.3)


# ------------------------------------------------------------- Lemma 1 / Eq. 6 batch


@pytest.mark.parametrize("sigma2", [0.1, np.array([0.05, 0.2, 0.1])])
def test_recursive_blr_equals_batch_posterior(sigma2):
    """No-changepoint path (pi = 0, K = 1) equals the batch posterior of Lemma 1's proof."""
    d, l, T, tau2 = 3, 4, 40, 0.1
    theta0, Z, D = random_problem(0, d, l, T)
    cfg = A.AdaptationConfig(K=1, pi=0.0, beta=0.5, tau2=tau2, sigma2=sigma2)
    state, infos = run(A.init(theta0, cfg), Z, D, cfg)
    s2 = np.broadcast_to(sigma2, (d,))
    for j in range(d):
        cov = np.linalg.inv(np.eye(l) / tau2 + Z.T @ Z / s2[j])
        mean = cov @ (theta0[j] / tau2 + Z.T @ D[:, j] / s2[j])
        np.testing.assert_allclose(state.covariances[0, j], cov, rtol=0, atol=1e-8)
        np.testing.assert_allclose(state.means[0, j], mean, rtol=0, atol=1e-8)
    assert int(state.num_changepoints[0]) == 0 and int(state.last_changepoint[0]) == -1
    assert all(float(i.p_change[0]) == 0.0 for i in infos)
    # The single-hypothesis Eq. 6 function agrees with the beam.
    m, w = jnp.asarray(theta0), jnp.broadcast_to(np.sqrt(tau2) * jnp.eye(l), (d, l, l))
    for z, delta in zip(Z, D):
        m, w = A.posterior_update(m, w, z, delta, sigma2)
    np.testing.assert_allclose(m, state.means[0], atol=1e-10)
    np.testing.assert_allclose(w @ jnp.swapaxes(w, -1, -2), state.covariances[0], atol=1e-10)


def test_tempered_update_matches_information_form():
    """Eq. 6 with gamma = beta^2: precision gamma Sigma^-1 + z z^T / sigma^2."""
    rng = np.random.default_rng(3)
    d, l = 2, 3
    root = rng.normal(size=(d, l, l))
    cov = root @ np.swapaxes(root, -1, -2) + 0.1 * np.eye(l)
    mean, z, delta = rng.normal(size=(d, l)), rng.normal(size=l), rng.normal(size=d)
    gamma, s2 = 0.3, np.array([0.2, 0.05])
    m, w = A.posterior_update(mean, np.linalg.cholesky(cov), z, delta, s2, gamma)
    for j in range(d):
        prec = gamma * np.linalg.inv(cov[j]) + np.outer(z, z) / s2[j]
        exp_cov = np.linalg.inv(prec)
        exp_mean = exp_cov @ (gamma * np.linalg.inv(cov[j]) @ mean[j] + z * delta[j] / s2[j])
        np.testing.assert_allclose(w[j] @ w[j].T, exp_cov, atol=1e-12)
        np.testing.assert_allclose(m[j], exp_mean, atol=1e-12)


# ------------------------------------------------------------ beam == enumeration


@pytest.mark.parametrize(
    ("T", "K", "pi", "beta", "sigma2", "floor"),
    [
        (8, 256, 0.2, 0.5, np.array([0.05, 0.1, 0.2]), 0.0),
        (5, 40, 0.05, 0.9, 0.1, 0.0),
        (6, 64, 0.3, 0.4, np.array([0.05, 0.1, 0.2]), 1.0),
        (5, 32, 0.2, 0.6, 0.1, 0.5),
    ],
)
def test_beam_equals_exhaustive_enumeration(T, K, pi, beta, sigma2, floor):
    """With K >= 2^T nothing is pruned: the beam is the set of all 2^T changepoint paths
    (also with the offline prior re-injected at changepoints)."""
    d, l, tau2 = 3, 2, 0.1
    theta0, Z, D = random_problem(1, d, l, T, switch=T // 2)
    s2 = np.broadcast_to(np.asarray(sigma2, float), (d,))
    cfg = A.AdaptationConfig(K=K, pi=pi, beta=beta, tau2=tau2, sigma2=sigma2, prior_floor=floor)
    state, _ = run(A.init(theta0, cfg), Z, D, cfg)
    ref = sorted(brute_force(theta0, tau2, s2, pi, beta, Z, D, floor), key=lambda r: -r["score"])

    n = 2**T
    raw = np.asarray(state.raw_log_scores)
    assert np.isfinite(raw[:n]).all() and np.isneginf(raw[n:]).all()
    order = np.argsort(-raw[:n], kind="stable")
    ref_scores = np.array([r["score"] for r in ref])
    np.testing.assert_allclose(raw[order], ref_scores, rtol=0, atol=1e-8)
    w_ref = np.exp(ref_scores - np.logaddexp.reduce(ref_scores))
    w = np.asarray(state.weights)
    np.testing.assert_allclose(w[order], w_ref, atol=1e-10)
    assert np.all(w[n:] == 0.0)
    # Per-hypothesis posteriors and bookkeeping, matched through the score order.
    covs = np.asarray(state.covariances)
    for slot, r in zip(order, ref):
        np.testing.assert_allclose(state.means[slot], r["mean"], atol=1e-8)
        np.testing.assert_allclose(covs[slot], r["cov"], atol=1e-8)
        assert int(state.num_changepoints[slot]) == r["ncp"]
        assert int(state.last_changepoint[slot]) == r["last"]
    # Eq. 10 predictive moments.
    z_star = np.array([0.7, -1.3])
    mean, var = ref_mixture_prediction(
        np.stack([r["mean"] for r in ref]), np.stack([r["cov"] for r in ref]), w_ref, z_star, s2
    )
    p = A.predict(state, z_star)
    np.testing.assert_allclose(p.mean, mean, atol=1e-10)
    np.testing.assert_allclose(p.variance, var, atol=1e-10)


# ------------------------------------------------------------------ Eq. 9 and top-K


def test_changepoint_posterior_matches_numerical_integration():
    """Eq. 9 with ``p(delta|z,c) = int N(delta; z^T theta, s^2) N(theta; mu, Sigma/gamma)``.

    The integral is evaluated by adaptive quadrature over ``u = z^T theta``.
    """
    d, l, pi, beta, s2 = 2, 3, 0.1, 0.6, 0.2
    theta0, Z, D = random_problem(4, d, l, 6, sigma2=s2, switch=3)
    cfg = A.AdaptationConfig(K=3, pi=pi, beta=beta, tau2=0.3, sigma2=s2)
    state, _ = run(A.init(theta0, cfg), Z[:5], D[:5], cfg)
    z, delta = Z[5], D[5]
    _, info = jax.jit(A.update)(state, z, delta, cfg)
    covs = np.asarray(state.covariances)
    for h in range(cfg.K):
        logs = []
        for gamma in (1.0, beta**2):
            total = 0.0
            for j in range(d):
                m = z @ np.asarray(state.means[h, j])
                v = z @ covs[h, j] @ z / gamma
                f = lambda u, j=j, m=m, v=v: (  # noqa: E731
                    stats.norm.pdf(delta[j], u, np.sqrt(s2)) * stats.norm.pdf(u, m, np.sqrt(v))
                )
                sd = np.sqrt(v)
                val, _ = integrate.quad(f, m - 12 * sd, m + 12 * sd, epsabs=0, epsrel=1e-12)
                total += np.log(val)
            logs.append(total)
        p1 = pi * np.exp(logs[1]) / (pi * np.exp(logs[1]) + (1 - pi) * np.exp(logs[0]))
        np.testing.assert_allclose(info.p_change[h], p1, rtol=1e-8)
    w = np.asarray(state.weights)
    np.testing.assert_allclose(info.cp_prob, w @ np.asarray(info.p_change), rtol=1e-12)


def test_pruning_keeps_exactly_the_k_best_candidates():
    """After 2^T > K, every update keeps the K largest of the 2K Algorithm 1 candidates."""
    d, l, K, pi, beta, s2 = 2, 3, 4, 0.2, 0.5, np.array([0.1, 0.3])
    theta0, Z, D = random_problem(5, d, l, 9, switch=4)
    cfg = A.AdaptationConfig(K=K, pi=pi, beta=beta, tau2=0.2, sigma2=s2)
    state = A.init(theta0, cfg)
    upd = jax.jit(A.update)
    for z, delta in zip(Z, D):
        means, covs = np.asarray(state.means), np.asarray(state.covariances)
        raw, ncp = np.asarray(state.raw_log_scores), np.asarray(state.num_changepoints)
        cands = []
        for h in range(K):
            if np.isneginf(raw[h]):
                continue
            ll0, ll1 = ref_log_marginals(means[h], covs[h], z, delta, s2, (1.0, beta**2))
            p1 = ref_cp_posterior(ll0, ll1, pi)
            cands.append((raw[h] + ll0 + np.log1p(-p1), ncp[h]))
            cands.append((raw[h] + ll1 + np.log(p1), ncp[h] + 1))
        cands.sort(key=lambda c: -c[0])
        state, info = upd(state, z, delta, cfg)
        kept = min(K, len(cands))
        new_raw = np.asarray(state.raw_log_scores)
        np.testing.assert_allclose(new_raw[:kept], [c[0] for c in cands[:kept]], atol=1e-9)
        np.testing.assert_array_equal(state.num_changepoints[:kept], [c[1] for c in cands[:kept]])
        assert np.isneginf(new_raw[kept:]).all()
        assert float(np.max(state.log_scores)) == 0.0  # shift bookkeeping
        w = np.asarray(state.weights)
        np.testing.assert_allclose(info.cp_mass, w[np.asarray(state.is_changepoint)].sum())


def test_top_k_matches_lax_top_k_with_ties_and_infinities():
    rng = np.random.default_rng(6)
    ours = jax.jit(A.top_k, static_argnums=1)
    ref = jax.jit(jax.lax.top_k, static_argnums=1)
    for n, k in [(10, 5), (30, 15), (60, 30), (7, 1)]:
        for _ in range(20):
            v = rng.integers(-3, 3, size=n).astype(float)  # many ties
            v[rng.random(n) < 0.3] = -np.inf
            v[0] = 0.0
            vals, idx = ours(jnp.asarray(v), k)
            ref_vals, ref_idx = ref(jnp.asarray(v), k)
            np.testing.assert_array_equal(vals, ref_vals)
            np.testing.assert_array_equal(idx, ref_idx)


def test_top_k_ranks_nan_last_and_returns_valid_indices():
    v = jnp.asarray([0.0, np.nan, -1.0, 2.0, np.nan, 1.0, -np.inf])
    vals, idx = A.top_k(v, 3)
    np.testing.assert_array_equal(idx, [3, 5, 0])
    np.testing.assert_array_equal(vals, [2.0, 1.0, 0.0])
    _, idx = jax.jit(A.top_k, static_argnums=1)(v, 7)
    np.testing.assert_array_equal(idx, [3, 5, 0, 2, 6, 1, 4])  # a permutation, NaN last
    _, idx = A.top_k(jnp.full(4, jnp.nan), 2)
    np.testing.assert_array_equal(idx, [0, 1])


# ------------------------------------------------------------ non-finite observations


def _assert_same_state(a, b):
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_a_non_finite_observation_is_skipped_and_leaves_no_trace(dtype):
    d, l, K, T, bad = 3, 2, 4, 12, 6
    theta0, Z, D = random_problem(21, d, l, T, switch=8)
    theta0, Z, D = (x.astype(dtype) for x in (theta0, Z, D))
    cfg = A.AdaptationConfig(K=K, pi=0.1, beta=0.7, tau2=0.1, sigma2=0.1, prior_floor=1.0)
    fn = jax.jit(A.update)
    clean = A.init(theta0, cfg)
    for t in range(T):
        clean, info = fn(clean, Z[t], D[t], cfg)
        assert bool(info.accepted)
    huge = np.full(d, 1e19 if dtype == np.float32 else 1e300, dtype)  # Eq. 8 overflows
    nan_z, inf_z = Z[bad].copy(), Z[bad].copy()
    nan_z[1], inf_z[0] = np.nan, -np.inf
    nan_d = D[bad].copy()
    nan_d[0] = np.nan
    for z_bad, d_bad in [(Z[bad], nan_d), (nan_z, D[bad]), (inf_z, D[bad]), (Z[bad], huge)]:
        state = A.init(theta0, cfg)
        for t in range(T):
            if t == bad:
                before = state
                state, info = fn(state, z_bad, d_bad, cfg)
                _assert_same_state(state, before)  # bit for bit, step included
                assert not bool(info.accepted) and not bool(info.changepoint)
                assert float(info.cp_prob) == 0.0 and np.isnan(float(info.log_evidence))
                assert int(info.map_last_changepoint) == int(before.last_changepoint[0])
            state, info = fn(state, Z[t], D[t], cfg)
            assert bool(info.accepted)
        # Later updates behave exactly as if the bad observation had never arrived.
        _assert_same_state(state, clean)
        assert np.isfinite(np.asarray(state.log_scores[0]))


def test_a_skipped_observation_under_vmap_and_the_packed_step():
    d, l, K = 2, 2, 3
    theta0, Z, D = random_problem(22, d, l, 3)
    cfg = A.AdaptationConfig(K=K, pi=0.2, beta=0.5, tau2=0.1, sigma2=0.1)
    state = A.init(theta0, cfg)
    state, _, _ = A.step(state, Z[0], D[0], cfg)
    bad = D[1].copy()
    bad[1] = np.nan
    states = jax.tree.map(lambda x: jnp.stack([x, x]), state)
    batched = jax.jit(jax.vmap(A.step, in_axes=(0, 0, 0, None)))
    new, _, info = batched(states, np.stack([Z[1], Z[1]]), np.stack([D[1], bad]), cfg)
    np.testing.assert_array_equal(info.accepted, [True, False])
    good, _, _ = A.step(state, Z[1], D[1], cfg)
    for x, y in zip(jax.tree.map(lambda x: x[0], new), good):
        np.testing.assert_allclose(x, y, atol=1e-14)  # vmap may round differently
    _assert_same_state(jax.tree.map(lambda x: x[1], new), state)
    # The packed fast path reports the skip in its outputs.
    fast = A.make_packed_step()
    packed, out = fast(A.pack(state, cfg), jnp.concatenate([Z[1], bad, jnp.zeros(l)]))
    _, info = A.unpack_outputs(np.asarray(out), d, K)
    assert not bool(info.accepted)
    _assert_same_state(A.unpack(packed)[0], state)


# ----------------------------------------------------------------- Eq. 10 / Sec. IV


def test_prediction_parts_and_marginal_decoder():
    d, l = 3, 2
    theta0, Z, D = random_problem(7, d, l, 6, switch=3)
    cfg = A.AdaptationConfig(K=6, pi=0.3, beta=0.4, tau2=0.1, sigma2=np.array([0.1, 0.2, 0.3]))
    state, _ = run(A.init(theta0, cfg), Z, D, cfg)
    w = np.asarray(state.weights)
    assert (w > 1e-6).sum() >= 3  # a genuine mixture
    mu, cov = np.asarray(state.means), np.asarray(state.covariances)
    z, sz2 = np.array([0.3, -0.8]), np.array([0.05, 0.2])
    p = A.predict(state, z, sz2)
    m_h = mu @ z
    v_h = np.einsum("i,kdij,j->kd", z, cov, z)
    mean = w @ m_h
    np.testing.assert_allclose(p.mean, mean, atol=1e-12)
    np.testing.assert_allclose(p.param, w @ v_h, atol=1e-12)
    np.testing.assert_allclose(p.between, w @ (m_h - mean) ** 2, atol=1e-12)
    np.testing.assert_allclose(p.noise, [0.1, 0.2, 0.3])
    enc = np.einsum("k,kdi,i->d", w, mu**2, sz2)
    np.testing.assert_allclose(p.encoder, enc, atol=1e-12)
    np.testing.assert_allclose(p.sigma_tot2, enc + w @ v_h + w @ (m_h - mean) ** 2, atol=1e-12)
    np.testing.assert_allclose(A.sigma_tot2(state, z, sz2), p.sigma_tot2, atol=1e-14)
    np.testing.assert_allclose(p.variance, p.sigma_tot2 + p.noise, atol=1e-14)
    np.testing.assert_array_equal(A.predict(state, z).encoder, 0.0)
    # Moment-matched marginal decoder reproduces the mixture's predictive mean/variance.
    mean_th, cov_th = A.marginal_decoder(state)
    np.testing.assert_allclose(mean_th, np.einsum("k,kdi->di", w, mu), atol=1e-12)
    np.testing.assert_allclose(np.asarray(mean_th) @ z, p.mean, atol=1e-12)
    np.testing.assert_allclose(np.einsum("i,dij,j->d", z, cov_th, z), p.param + p.between)
    np.testing.assert_allclose(cov_th, np.swapaxes(cov_th, -1, -2))


# --------------------------------------------------------------- packed / jit / vmap


def test_packed_step_equals_step():
    d, l, K = 3, 2, 4
    theta0, Z, D = random_problem(8, d, l, 12, switch=6)
    cfg = A.AdaptationConfig(
        K=K, pi=0.2, beta=0.5, tau2=0.1, sigma2=np.array([0.1, 0.2, 0.3]), prior_floor=1.0
    )
    state = A.init(theta0, cfg)
    back, back_cfg = A.unpack(A.pack(state, cfg))
    for a, b in zip(back, state):
        np.testing.assert_array_equal(a, b)
    assert float(back_cfg.beta) == 0.5 and float(back_cfg.pi) == 0.2
    assert float(back_cfg.prior_floor) == 1.0
    fast = A.make_packed_step()
    packed = A.pack(state, cfg)
    sz2 = np.array([0.01, 0.02])
    ref = jax.jit(A.step)
    for z, delta in zip(Z, D):
        packed, out = fast(packed, jnp.concatenate([z, delta, sz2]))
        state, pred, info = ref(state, z, delta, cfg, sz2)
        got_pred, got_info = A.unpack_outputs(np.asarray(out), d, K)
        for a, b in zip(got_pred, pred):
            np.testing.assert_allclose(a, b, atol=1e-14)
        for name in ("p_change", "cp_prob", "cp_mass", "log_evidence"):
            np.testing.assert_allclose(getattr(got_info, name), getattr(info, name), atol=1e-14)
        assert bool(got_info.changepoint) == bool(info.changepoint)
        assert int(got_info.map_last_changepoint) == int(info.map_last_changepoint)
        assert bool(got_info.accepted) and bool(info.accepted)
    unpacked, _ = A.unpack(packed)
    for a, b in zip(unpacked, state):
        np.testing.assert_allclose(a, b, atol=1e-14)


def test_hyperparameters_are_traced_and_step_vmaps():
    d, l, K = 2, 2, 3
    theta0, Z, D = random_problem(9, d, l, 4)
    traces = []

    def counted(state, z, delta, config):
        traces.append(None)
        return A.step(state, z, delta, config)

    fn = jax.jit(counted)
    for pi, beta, s2 in [(0.1, 0.5, 0.1), (0.2, 0.7, 0.3), (0.05, 0.9, 0.2)]:
        cfg = A.AdaptationConfig(K=K, pi=pi, beta=beta, tau2=0.1, sigma2=s2)
        fn(A.init(theta0, cfg), Z[0], D[0], cfg)
    assert len(traces) == 1
    # vmap over independent beams (e.g. several vehicles) equals separate calls.
    cfg = A.AdaptationConfig(K=K, pi=0.2, beta=0.5, tau2=0.1, sigma2=0.1)
    states = jax.tree.map(lambda x: jnp.stack([x, x]), A.init(theta0, cfg))
    batched = jax.jit(jax.vmap(A.step, in_axes=(0, 0, 0, None)))
    single = jax.jit(A.step)
    s0 = s1 = A.init(theta0, cfg)
    for t in range(3):
        zz, dd = np.stack([Z[t], Z[t + 1]]), np.stack([D[t], -D[t]])
        states, pred, _ = batched(states, zz, dd, cfg)
        s0, p0, _ = single(s0, zz[0], dd[0], cfg)
        s1, p1, _ = single(s1, zz[1], dd[1], cfg)
    np.testing.assert_allclose(states.means[0], s0.means, atol=1e-12)
    np.testing.assert_allclose(states.means[1], s1.means, atol=1e-12)
    np.testing.assert_allclose(pred.mean[0], p0.mean, atol=1e-12)
    np.testing.assert_allclose(pred.mean[1], p1.mean, atol=1e-12)
