"""Numerics soak of the packed adaptation step, and where Lemma 2's envelope holds.

``benchmarks.soak`` (``arcade bench soak``) runs 10^6 steps; here a 2 x 10^4-step version
in float32 and float64 with the same checks: everything finite, every covariance positive
definite, and the variance envelopes that follow from Eq. 6 with tempering. The envelope
of Lemma 2 as the paper states it holds with the learner's prior-precision floor at
changepoints (the quadrotor preset), is checked where its assumptions make it provable
for Eq. 5 as written (one latent feature bounded away from zero), and is shown to fail,
precisely, where the tempered prior of a changepoint is more diffuse than ``tau^2 I``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from arcade_core import adaptation as A
from benchmarks import soak


def _assert_sound(r: dict, dtype: str) -> None:
    tol = 1e4 * np.finfo(dtype).eps
    assert r["steps"] == 20_000
    assert r["nonfinite_steps"] == 0
    assert r["min_eigenvalue"] > 0 and np.isfinite(r["max_condition"])
    # Sigma_h <= tau^2 / (rho + (1 - rho) beta^{2 m_h}) I along every z_k, and
    # Sigma_h <= sigma^2 G_h^{-1} over each hypothesis' segment.
    assert r["prior_envelope_violations"] == 0
    assert r["prior_envelope_max_ratio"] <= 1.0 + tol
    assert 0.0 < r["data_envelope_max_ratio"] <= 1.0 + tol
    # The stream is hostile: jumps happened and the beam saw changepoints.
    assert r["true_jumps"] > 50 and r["detected_changepoints"] > 50
    assert np.isfinite(r["max_sigma_tot2"]) and r["max_sigma_tot2"] > 0
    stated = r["lemma2_stated"]
    assert stated["bound"] == pytest.approx(0.1 * soak.R**2)
    # Whatever exceeds tau^2 R^2 is explained by tempering: ratio <= beta^{-2 m}.
    m = stated["worst"]["changepoints_on_path"]
    assert stated["max_ratio"] <= r["beta"] ** (-2 * m) * (1 + tol)
    assert r["ok"]


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_short_soak_of_the_quadrotor_preset(dtype):
    r = soak.soak(20_000, dtype, chunk=2_000, seed=3)
    _assert_sound(r, dtype)
    if r["prior_floor"] == 1.0:  # the tempered prior is never wider than tau^2 I
        assert r["lemma2_stated"]["violations"] == 0
        assert r["lemma2_stated"]["max_ratio"] <= 1.0


def test_short_soak_with_eq5_tempering_as_written():
    cfg = A.quadrotor_config()
    if hasattr(cfg, "prior_floor"):
        cfg = cfg._replace(prior_floor=0.0)
    r = soak.soak(20_000, "float64", chunk=2_000, seed=3, config=cfg)
    assert r["prior_floor"] == 0.0
    _assert_sound(r, "float64")


def _stated_envelope(q, t, z_min, R, tau2, sigma2):
    """Lemma 2: ``min{tau^2 R^2, R^2 sigma^2 / (alpha t)}`` with ``alpha = z_min^2``."""
    alpha = z_min**2
    data = R**2 * sigma2 / (alpha * np.maximum(t, 1))
    return np.where(t >= 1, np.minimum(tau2 * R**2, data), tau2 * R**2)  # t = 0: the prior


def _run_scalar_beam(z_min: float, steps: int, seed: int, outliers: float = 0.05):
    """A beam over one latent feature ``|z|`` log-uniform in ``[z_min, R]``, with jumps and
    outliers;
    returns per step and hypothesis ``q = z^T Sigma z`` before the update, the segment
    sample count ``t`` and the used mask."""
    cfg = A.cartpole_config()._replace(beta=0.9)
    R = 2.0
    rng = np.random.default_rng(seed)
    mag = np.exp(rng.uniform(np.log(z_min), np.log(R), steps)) * rng.choice([-1.0, 1.0], steps)
    theta = np.repeat(rng.normal(0.0, 3.0, steps // 50 + 1), 50)[:steps]
    outlier = (rng.random(steps) < outliers) * 50.0
    delta = theta * mag + 0.3 * rng.standard_normal(steps) + outlier
    K = cfg.K

    def body(state, x):
        z, dlt = x
        w = state.sqrt_covariances[:, 0]
        q = jnp.sum(jnp.square(jnp.einsum("kji,j->ki", w, z)), axis=-1)
        last = state.last_changepoint
        t = jnp.where(last >= 1, state.step - last + 1, state.step)
        used = jnp.isfinite(state.log_scores)
        state, _ = A.update(state, z, dlt, cfg)
        return state, (q, t, used)

    state = A.init(jnp.zeros((1, 1)), cfg)
    xs = (jnp.asarray(mag)[:, None], jnp.asarray(delta)[:, None])
    final, (q, t, used) = jax.jit(lambda s, x: jax.lax.scan(body, s, x))(state, xs)
    assert int(jnp.sum(final.num_changepoints)) > 0
    return np.asarray(q), np.asarray(t), np.asarray(used), np.abs(mag), cfg, R, K


def test_lemma2_holds_as_stated_where_its_assumptions_hold():
    # l = 1 and |z| >= z_min: every segment prefix has lambda_min >= z_min^2 t (alpha =
    # z_min^2), and with z_min^2 >= sigma^2 (1 - beta^2) / tau^2 the tempered precision
    # beta^2 P + z^2 / sigma^2 never drops below 1 / tau^2, which is what the tau^2 R^2
    # term needs.
    cfg = A.cartpole_config()._replace(beta=0.9)

    def violations(z_min: float) -> int:
        q, t, used, mag, cfg, R, _ = _run_scalar_beam(z_min, 3000, seed=1, outliers=0.3)
        env = _stated_envelope(q, t, z_min, R, cfg.tau2, cfg.sigma2)
        # q is evaluated at the step's own z (|z| <= R): compare the Rayleigh quotients.
        return int(np.sum(used & (q > env * (mag[:, None] / R) ** 2 * (1 + 1e-9) + 1e-15)))

    assert violations(1.01 * np.sqrt(cfg.sigma2 * (1 - 0.9**2) / cfg.tau2)) == 0
    # Features that may be tiny: alpha = z_min^2 still exists, but repeated changepoints
    # temper the precision below 1 / tau^2 and the tau^2 R^2 term fails.
    assert violations(1e-3) > 0


def test_lemma2_first_term_fails_after_tempering_in_unexcited_directions():
    # Eq. 5/6 with a changepoint (gamma = beta^2): Sigma' = (beta^2 Sigma^{-1} + z z^T /
    # sigma^2)^{-1}. Starting from the prior tau^2 I and observing z along e1, the
    # direction e2 is not excited, so z2^T Sigma' z2 = tau^2 R^2 / beta^2 > tau^2 R^2 for
    # z2 = R e2: the first term of Lemma 2's envelope does not hold right after a
    # changepoint (the proof assumes the tempered prior is no more diffuse than tau^2 I).
    tau2, sigma2, beta, R = 0.1, 0.1, 0.9, 2.0
    cfg = A.AdaptationConfig(K=2, pi=0.05, beta=beta, tau2=tau2, sigma2=sigma2)
    state = A.init(jnp.zeros((1, 2)), cfg)
    z1, z2 = jnp.array([1.0, 0.0]), jnp.array([0.0, R])
    for gamma, expect in ((1.0, tau2 * R**2), (beta**2, tau2 * R**2 / beta**2)):
        _, w = A.posterior_update(
            state.means[0], state.sqrt_covariances[0], z1, jnp.array([0.3]), sigma2, gamma
        )
        q = float(jnp.sum(jnp.square(w[0].T @ z2)))
        assert q == pytest.approx(expect, rel=1e-12)
    assert tau2 * R**2 / beta**2 > tau2 * R**2
    # The corrected envelope tau^2 R^2 beta^{-2 m} (m changepoints on the path) holds, and
    # m consecutive changepoints without excitation of e2 reach it exactly.
    mean, w = state.means[0], state.sqrt_covariances[0]
    for m in range(1, 6):
        mean, w = A.posterior_update(mean, w, z1, jnp.array([0.3]), sigma2, beta**2)
        q = float(jnp.sum(jnp.square(w[0].T @ z2)))
        assert q == pytest.approx(tau2 * R**2 * beta ** (-2 * m), rel=1e-12)


def test_soak_leaves_the_float64_setting_as_it_found_it():
    """`arcade bench report` runs the soak before the cartpole evaluation in one process:
    the soak's float64 must not leak into it (it changed the cartpole numbers)."""
    from arcade_io import jaxsetup

    before = bool(jax.config.jax_enable_x64)
    with jaxsetup.x64(False):
        r = soak.run(steps=400, dtypes=("float32", "float64"))
        assert not jax.config.jax_enable_x64
    assert bool(jax.config.jax_enable_x64) == before
    assert r["ok"] and {x["dtype"] for x in r["results"]} == {"float32", "float64"}
