"""The methods of the cartpole evaluation (paper Sec. V-A, Table I) and their one-step predictions.

Offline training of every model (the VLD of Ours and its deterministic variant, MLP, GP,
SysID), their offline one-step predictors, and the online runs over a trajectory: Ours
(Algorithm 1), Ours w/o CP, Ours with the true changepoints, GP, MLP, offline only and the
true-model oracle. Each method predicts ``x_{k+1}`` from ``(x_k, u_k)`` with what it knew
after step ``k-1``; CRMSE is ``arcade_core.metrics.crmse``.

With ``horizon = H > 0`` a run also predicts over the MPC horizon: at step ``k``, with what
it knew after step ``k-1``, it rolls its model open loop from ``x_k`` along the recorded
inputs ``u_k .. u_{k+H-1}`` (:func:`horizon_crmse` scores it).
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
from arcade_core.dynamics.params import CARTPOLE_DT
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


def windows(a, H: int):
    """``(T, ...) -> (T, H, ...)``: row ``k`` holds ``a[k], .., a[k+H-1]`` (zeros past the end)."""
    a = jnp.asarray(a)
    pad = jnp.concatenate([a, jnp.zeros((H - 1, *a.shape[1:]), a.dtype)])
    return pad[jnp.arange(a.shape[0])[:, None] + jnp.arange(H)[None, :]]


def _rollout(step, x, inputs):
    """Open-loop predictions ``(H, 4)`` from ``x`` along ``inputs`` (leading axis H)."""

    def body(x, inp):
        xn = step(x, inp)
        return xn, xn

    return jax.lax.scan(body, x, inputs)[1]


def _online(predict, update, state0, X, U, horizon: int):
    """One-step predictions ``(T, 4)`` of ``predict(state, x, u)`` along a trajectory, the
    state updated by ``update(state, x, u, xn)`` after each step; with ``horizon = H > 0``
    also the open-loop predictions ``(T, H, 4)`` (module docstring)."""
    uw = windows(U, horizon) if horizon else jnp.zeros((U.shape[0], 0, U.shape[-1]), U.dtype)

    def body(state, inp):
        x, u, xn, uw = inp
        xhat = predict(state, x, u)
        hor = _rollout(lambda x, u: predict(state, x, u), x, uw) if horizon else None
        return update(state, x, u, xn), (xhat, hor)

    xhat, hor = jax.lax.scan(body, state0, (X[:-1], U, X[1:], uw))[1]
    return (xhat, hor) if horizon else xhat


def horizon_crmse(hor, X) -> np.ndarray:
    """Mean over start steps ``k`` (those with ``k + H <= T``) of the CRMSE of the H-step
    open-loop predictions ``hor (n, T, H, 4)`` against ``X (n, T+1, 4)``, per trajectory."""
    hor, X = np.asarray(hor), np.asarray(X)
    T, H = hor.shape[1:3]
    starts = T - H + 1
    target = np.stack([X[:, 1 + i : 1 + i + starts] for i in range(H)], 2)
    per_step = np.sqrt(np.mean((target - hor[:, :starts]) ** 2, -1)).sum(-1)
    return per_step.mean(-1)


def run_beam(model: encoder.VLD, cfg: adaptation.AdaptationConfig, X, U, horizon: int = 0):
    """Ours (Algorithm 1) over one trajectory: predictions, std, detections, changepoint
    probability (and with ``horizon > 0`` the open-loop predictions, last)."""
    state0 = adaptation.init(model.theta0, cfg)
    uw = windows(U, horizon) if horizon else jnp.zeros((U.shape[0], 0, 1), U.dtype)

    def predict(state, x, u):
        mean = adaptation.predict(state, model.features(x, u)).mean
        return f_nom(x, u) + model.denormalise_residual(mean)

    def body(state, inp):
        x, u, xn, uw = inp
        hor = _rollout(lambda x, u: predict(state, x, u), x, uw) if horizon else None
        z = model.features(x, u)
        nom = f_nom(x, u)
        dn = model.normalise_residual(xn - nom)
        state, pred, info = adaptation.step(state, z, dn, cfg, model.latent_variance(x, u))
        xhat = nom + model.denormalise_residual(pred.mean)
        std = jnp.sqrt(pred.variance) * model.delta_scale
        return state, (xhat, std, info.changepoint, info.cp_prob, hor)

    _, out = jax.lax.scan(body, state0, (X[:-1], U, X[1:], uw))
    return out if horizon else out[:4]


def no_cp_runner(model: encoder.VLD, sigma2, horizon: int = 0) -> Callable[[float], Callable]:
    """Ours w/o CP (one hypothesis, no changepoints) as ``tau2 -> (X, U) -> predictions``
    (with ``horizon > 0``: one-step and open-loop predictions)."""

    def make(tau2):
        c = adaptation.AdaptationConfig(K=1, pi=0.0, beta=1.0, tau2=tau2, sigma2=sigma2)
        if horizon:
            return lambda X, U: run_beam(model, c, X, U, horizon)[::4]
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


def run_offline_only(model: encoder.VLD, X, U, horizon: int = 0):
    return _online(
        lambda _, x, u: f_nom(x, u) + model.predict_residual(x, u),
        lambda state, *_: state,
        jnp.zeros(()),
        X,
        U,
        horizon,
    )


def run_gp(model: gp.GPModel, X, U, horizon: int = 0):
    return _online(
        lambda state, x, u: f_nom(x, u) + gp.predict(state, x, u)[0],
        lambda state, x, u, xn: gp.update(state, x, u, xn - f_nom(x, u)),
        gp.init(model, 50),
        X,
        U,
        horizon,
    )


def run_mlp(net: mlp.MLPResidual, lr, X, U, horizon: int = 0):
    return _online(
        lambda state, x, u: f_nom(x, u) + mlp.predict_mean(state, x, u),
        lambda state, x, u, xn: mlp.update(state, x, u, xn - f_nom(x, u)),
        mlp.init(net, jnp.zeros(4), jnp.zeros(1), capacity=50, learning_rate=lr),
        X,
        U,
        horizon,
    )


def run_oracle(schedule: cd.Schedule, X, U, params=cd.TRUE_PARAMS, horizon: int = 0):
    """Reference, not a method: the true model ``params`` with the interventions and the
    mean disturbance known. Its one-step error is the irreducible part (the random force),
    a floor no learner can go below."""
    force, scale = jnp.asarray(schedule.force), jnp.asarray(schedule.mass_scale)

    def step(x, inp):
        u, f, s = inp
        return cartpole_true_step(
            None, x, u, cd.scaled(params, s), CARTPOLE_DT, force=f, u_dist=params.dist_mean
        )

    onestep = jax.vmap(step)(X[:-1], (U, force, scale))
    if not horizon:
        return onestep
    ws = (windows(U, horizon), windows(force, horizon), windows(scale, horizon))
    return onestep, jax.vmap(lambda x, w: _rollout(step, x, w))(X[:-1], ws)


def crmse_batch(xhat, X) -> np.ndarray:
    return np.asarray(jax.vmap(metrics.crmse)(jnp.asarray(X[:, 1:]), xhat))


def beam_batch(model, cfg, X, U, horizon: int = 0):
    f = jax.jit(jax.vmap(lambda X, U: run_beam(model, cfg, X, U, horizon)))
    return f(jnp.asarray(X), jnp.asarray(U))
