"""The methods of the cartpole evaluation (paper Sec. V-A, Table I) and their one-step predictions.

Offline training of every model (the VLD of Ours and its deterministic variant, MLP, GP,
SysID), their offline one-step predictors, and the online runs over a trajectory: Ours
(Algorithm 1), Ours w/o CP, Ours with the true changepoints, GP, MLP, offline only and the
true-model oracle. Each method predicts ``x_{k+1}`` from ``(x_k, u_k)`` with what it knew
after step ``k-1``; CRMSE is ``arcade_core.metrics.crmse``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from arcade_control import cartpole as cd
from arcade_core import adaptation, encoder, metrics
from arcade_core.baselines import gp, mlp, sysid
from arcade_core.dynamics.cartpole import cartpole_nominal_step, cartpole_true_step
from arcade_core.dynamics.params import CARTPOLE_DT, CARTPOLE_TRUE
from benchmarks.cartpole_settings import EvalSettings


def f_nom(x, u):
    return cartpole_nominal_step(x, u)


def train_vld(
    key, x, u, xn, *, variational: bool, epochs: int, callback=None, **overrides: Any
) -> encoder.VLD:
    """The cartpole VLD (Appendix D preset; ``overrides`` change its config, e.g.
    ``latent_dim`` for :func:`latent_ablation`), residual scale calibrated to sigma^2."""
    delta = xn - cd.nominal_next(x, u)
    cfg = encoder.cartpole_config(epochs=epochs, variational=variational, **overrides)
    model, _ = encoder.train(key, cfg, x, u, delta, callback=callback)
    return encoder.calibrate_residual_scale(model, x, u, delta, adaptation.cartpole_config().sigma2)


@dataclass
class OfflineModels:
    vld: encoder.VLD
    det: encoder.VLD
    mlp: mlp.MLPResidual
    gp: gp.GPModel
    sysid: sysid.SysIDModel
    gp_support: tuple[np.ndarray, np.ndarray, np.ndarray]


def train_all(key, x, u, xn, s: EvalSettings, progress: Callable[[str], None]) -> OfflineModels:
    delta = xn - cd.nominal_next(x, u)
    k = jax.random.split(key, 6)
    progress("VLD encoder")
    vld = train_vld(k[0], x, u, xn, variational=True, epochs=s.epochs)
    progress("deterministic encoder")
    det = train_vld(k[1], x, u, xn, variational=False, epochs=s.epochs)
    progress("MLP")
    net = mlp.init_model(k[2], jnp.asarray(x), jnp.asarray(u), jnp.asarray(delta))
    net = mlp.train(
        net, jnp.asarray(x), jnp.asarray(u), jnp.asarray(delta), key=k[3], epochs=s.epochs
    )
    progress("GP")
    gpm = gp.fit(
        jnp.asarray(x), jnp.asarray(u), jnp.asarray(delta), key=k[4], num_points=s.gp_points
    )
    idx = np.asarray(
        jax.random.choice(k[5], x.shape[0], (min(s.gp_points, x.shape[0]),), replace=False)
    )
    progress("SysID")
    sid = sysid.fit(
        jnp.asarray(x), jnp.asarray(u), jnp.asarray(delta), degree=2, angle_indices=(2,)
    )
    return OfflineModels(vld, det, net, gpm, sid, (x[idx], u[idx], delta[idx]))


# ------------------------------------------------------------------- offline predictions


def offline_predictors(m: OfflineModels) -> dict[str, Callable]:
    """One-step predictors x_{k+1} = f_nom + residual, no online updates."""
    gp_state = gp.condition(m.gp, *(jnp.asarray(a) for a in m.gp_support))
    return {
        "ours": lambda x, u: f_nom(x, u) + m.vld.predict_residual(x, u),
        "deterministic": lambda x, u: f_nom(x, u) + m.det.predict_residual(x, u),
        "mlp": lambda x, u: f_nom(x, u) + m.mlp(jnp.concatenate([x, u])),
        "gp": lambda x, u: f_nom(x, u) + gp.predict(gp_state, x, u)[0],
        "sysid": lambda x, u: f_nom(x, u) + sysid.predict(m.sysid, x, u),
        "nominal": f_nom,
    }


def trajectory_crmse(predict, X, U) -> np.ndarray:
    """CRMSE of one-step predictions for each trajectory of X (n, T+1, 4), U (n, T, 1)."""

    def one(X, U):
        xhat = jax.vmap(predict)(X[:-1], U)
        return metrics.crmse(X[1:], xhat)

    return np.asarray(jax.jit(jax.vmap(one))(jnp.asarray(X), jnp.asarray(U)))


def run_beam(model: encoder.VLD, cfg: adaptation.AdaptationConfig, X, U):
    """Ours (Algorithm 1) over one trajectory: predictions, std, detections."""
    state0 = adaptation.init(model.theta0, cfg)

    def body(state, inp):
        x, u, xn = inp
        z = model.features(x, u)
        nom = f_nom(x, u)
        dn = model.normalise_residual(xn - nom)
        state, pred, info = adaptation.step(state, z, dn, cfg, model.latent_variance(x, u))
        xhat = nom + model.denormalise_residual(pred.mean)
        std = jnp.sqrt(pred.variance) * model.delta_scale
        return state, (xhat, std, info.changepoint, info.cp_prob)

    _, out = jax.lax.scan(body, state0, (X[:-1], U, X[1:]))
    return out


def no_cp_runner(model: encoder.VLD, sigma2) -> Callable[[float], Callable]:
    """Ours w/o CP (one hypothesis, no changepoints) as ``tau2 -> (X, U) -> predictions``."""

    def make(tau2):
        c = adaptation.AdaptationConfig(K=1, pi=0.0, beta=1.0, tau2=tau2, sigma2=sigma2)
        return lambda X, U: run_beam(model, c, X, U)[0]

    return make


def run_known_changepoints(
    model: encoder.VLD, cfg: adaptation.AdaptationConfig, X, U, steps=cd.INTERVENTION_STEPS
):
    """Reference, not a method: Ours with one hypothesis (K = 1) whose changepoints are
    the true intervention steps and no others (the prior tempered with ``cfg.beta`` at
    exactly those steps, Eq. 5). It shows what a detector that never misses and never
    false-alarms would buy. Returns the predictions, ``(T, 4)``."""
    pis = np.zeros(U.shape[0])
    # pi = 1 forces the changepoint branch, pi = 0 forbids it.
    pis[[t for t in steps if t < len(pis)]] = 1.0
    c0 = cfg._replace(K=1)
    state0 = adaptation.init(model.theta0, c0)

    def body(state, inp):
        x, u, xn, pi = inp
        nom = f_nom(x, u)
        dn = model.normalise_residual(xn - nom)
        state, pred, _ = adaptation.step(
            state, model.features(x, u), dn, c0._replace(pi=pi), model.latent_variance(x, u)
        )
        return state, nom + model.denormalise_residual(pred.mean)

    pis = jnp.asarray(pis, jnp.result_type(X))
    return jax.lax.scan(body, state0, (X[:-1], U, X[1:], pis))[1]


def run_offline_only(model: encoder.VLD, X, U):
    return jax.vmap(lambda x, u: f_nom(x, u) + model.predict_residual(x, u))(X[:-1], U)


def run_gp(model: gp.GPModel, X, U):
    def body(state, inp):
        x, u, xn = inp
        nom = f_nom(x, u)
        xhat = nom + gp.predict(state, x, u)[0]
        return gp.update(state, x, u, xn - nom), xhat

    return jax.lax.scan(body, gp.init(model, 50), (X[:-1], U, X[1:]))[1]


def run_mlp(net: mlp.MLPResidual, lr, X, U):
    state0 = mlp.init(net, jnp.zeros(4), jnp.zeros(1), capacity=50, learning_rate=lr)

    def body(state, inp):
        x, u, xn = inp
        nom = f_nom(x, u)
        xhat = nom + mlp.predict_mean(state, x, u)
        return mlp.update(state, x, u, xn - nom), xhat

    return jax.lax.scan(body, state0, (X[:-1], U, X[1:]))[1]


def run_oracle(schedule: cd.Schedule, X, U):
    """Reference, not a method: the true model with the interventions and the mean
    disturbance known. Its error is the irreducible part (the random force), a floor no
    learner can go below."""
    p = CARTPOLE_TRUE

    def one(x, u, f, s):
        params = p._replace(M=p.M * s, m=p.m * s)
        return cartpole_true_step(None, x, u, params, CARTPOLE_DT, force=f, u_dist=p.dist_mean)

    return jax.vmap(one)(X[:-1], U, jnp.asarray(schedule.force), jnp.asarray(schedule.mass_scale))


def crmse_batch(xhat, X) -> np.ndarray:
    return np.asarray(jax.vmap(metrics.crmse)(jnp.asarray(X[:, 1:]), xhat))


def beam_batch(model, cfg, X, U):
    f = jax.jit(jax.vmap(lambda X, U: run_beam(model, cfg, X, U)))
    return f(jnp.asarray(X), jnp.asarray(U))
