"""The paper's cartpole evaluation (Sec. V-A, Fig. 3, Table I, Appendices D-E), one run.

1. Data: 100 trajectories of the true cartpole under the nominal MPC, random initial states.
2. Offline validation: 10 random 80/20 splits; one-step-ahead CRMSE on the 20 test
   trajectories for Ours (VLD), the deterministic (MAP) encoder, MLP, GP and SysID.
3. Online adaptation: disturbed trajectories of 120 steps with interventions at steps 0, 40
   and 80 (see ``cartpole_data``); every method starts from the same offline training
   (split 0) and is updated online after each step; one-step-ahead CRMSE per trajectory.
4. Changepoint detection quality of Ours, ablations over K, beta, pi and the encoder's
   latent dimension l (:func:`latent_ablation`), and the figures.

Prediction protocol: at step k each method predicts x_{k+1} from (x_k, u_k) with what it
knew after step k-1, then sees x_{k+1} and updates. CRMSE is the paper's footnote metric
summed over the trajectory (``arcade_core.metrics.crmse``).

Tuning: every adaptive method's own online hyperparameters are chosen from grids on
separate tuning trajectories (never the evaluation trajectories) by mean CRMSE — for Ours
the tempering beta, the changepoint prior pi and the prior variance tau^2, one after the
other until none changes (:func:`ours_tuning`); for Ours w/o CP the prior variance tau^2
on the same grid (with one hypothesis its predictions depend on tau^2 / sigma^2 only, so
that is its one knob); for the MLP the online learning rate; the GP's hyperparameters are
fitted by marginal likelihood on the offline data (Appendix D). Detection quality is not a
tuning criterion. The paper's own settings (Appendix D: beta = 0.9, tau^2 = 0.1; MLP rate
1e-6) are reported beside the tuned ones, as are an oracle that knows the true model (the
noise floor) and Ours with the true changepoints (:func:`run_known_changepoints`, its beta
and tau^2 tuned the same way): what a detector that never misses and never false-alarms
would buy.

Beside them, one more row for a user who needs the detector itself (to log or act on
changes): ``ours_detection_tuned``, the (beta, pi, tau^2) setting of the grid with the
lowest tuning CRMSE among those that detect at least :data:`DETECTION_MIN_HIT_RATE` of the
tuning trajectories' interventions within :data:`HIT_WINDOW` steps (:func:`detection_tuning`).
It is evaluated on the same trajectories; the ratios stay those of the CRMSE-tuned Ours.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from arcade_core import adaptation, encoder, metrics
from arcade_core.baselines import gp, mlp, sysid
from arcade_core.dynamics.cartpole import cartpole_nominal_step, cartpole_true_step
from arcade_core.dynamics.params import CARTPOLE_DT, CARTPOLE_TRUE
from benchmarks import cartpole_data as cd

STATE_NAMES = ("x", "xdot", "theta", "thetadot")
MLP_LR_GRID = (1e-6, 1e-4, 1e-3, 1e-2, 1e-1, 0.3, 1.0)
# Ours' knobs are tuned one after the other (beta, pi, tau^2), each at the others' current
# values, starting from the preset (which every grid holds), in passes until one changes
# nothing (:func:`ours_tuning`).
OURS_BETA_GRID = (0.3, 0.5, 0.7, 0.9, 0.97)
OURS_PI_GRID = (0.01, 0.02, 0.05, 0.1, 0.2, 0.3)
# Wide on purpose: with K = 1 the predictions depend on tau^2 / sigma^2 only, and the
# tuning picks the largest values (an almost flat prior); a grid ending at 1 cut it short.
NO_CP_TAU2_GRID = (0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 100.0)
# Ours gets the same prior-variance grid as Ours w/o CP: the same tuning effort.
OURS_TAU2_GRID = NO_CP_TAU2_GRID
OURS_KNOBS = ("beta", "pi", "tau2")
MAX_TUNING_PASSES = 4
# The known-changepoint reference restarts only at true changes: it may temper harder.
KNOWN_CP_BETA_GRID = (0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 0.9)
#: Latent dimensions of the ablation over l (Appendix D: l = 2 for the cartpole).
LATENT_DIMS = (2, 4, 8)
PAPER_MLP_LR = 1e-6
HIT_WINDOW = 3  # steps after an intervention within which a detection counts (issue spec)
#: Hit rate the detection-tuned row must reach on the tuning trajectories.
DETECTION_MIN_HIT_RATE = 0.9


@dataclass(frozen=True)
class EvalSettings:
    n_traj: int = 100
    T_data: int = 100
    n_splits: int = 10
    n_test: int = 20
    trials: int = 10
    T_online: int = 120
    epochs: int = 50
    gp_points: int = 400
    # 20: with 5 (or 10) Ours' tau^2 scores from 1 to 100 lay within 1.3 % and the pick
    # changed with 20 and 40, which agree (docs/cartpole.md).
    tuning_trials: int = 20
    ablations: bool = True
    seed: int = 0

    @classmethod
    def quick(cls, trials: int = 4) -> EvalSettings:
        """A fast variant for tests: fewer trajectories, splits and epochs."""
        return cls(
            n_traj=30,
            T_data=80,
            n_splits=2,
            n_test=6,
            trials=trials,
            epochs=50,
            gp_points=150,
            tuning_trials=2,
            ablations=False,
        )


# ----------------------------------------------------------------------------- models


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


# -------------------------------------------------------------------- online methods


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


def _crmse_batch(xhat, X) -> np.ndarray:
    return np.asarray(jax.vmap(metrics.crmse)(jnp.asarray(X[:, 1:]), xhat))


def beam_batch(model, cfg, X, U):
    f = jax.jit(jax.vmap(lambda X, U: run_beam(model, cfg, X, U)))
    return f(jnp.asarray(X), jnp.asarray(U))


def changepoint_quality(flags: np.ndarray, steps=cd.INTERVENTION_STEPS, window=HIT_WINDOW):
    """Hit rate within ``window`` steps after each intervention, false alarms, delay.

    ``flags`` (n, T) are the per-step detections; a detection at step k concerns the
    transition x_k -> x_{k+1}, the step an intervention at k acts on.
    """
    flags = np.asarray(flags, bool)
    n, T = flags.shape
    hits, delays = 0, []
    near = np.zeros(T, bool)
    for t in steps:
        near[t : t + window + 1] = True
        for i in range(n):
            det = np.flatnonzero(flags[i, t : t + window + 1])
            if det.size:
                hits += 1
                delays.append(int(det[0]))
    false = flags[:, ~near].sum()
    return {
        "hit_rate": hits / (n * len(steps)),
        "false_alarms_per_100_steps": 100.0 * float(false) / (n * T),
        "mean_delay_steps": float(np.mean(delays)) if delays else float("nan"),
    }


def hits_per_intervention(flags: np.ndarray, steps=cd.INTERVENTION_STEPS) -> dict[str, float]:
    """Hit rate of each intervention step alone (``{"40": 0.9, ...}``). The one at step 0
    has no earlier regime: the beam starts from the offline prior, which is already what
    a changepoint at step 0 would restart from, tempered."""
    return {str(t): changepoint_quality(flags, steps=(t,))["hit_rate"] for t in steps}


def _choice(scores: dict[float, float]) -> dict[str, Any]:
    """The grid value with the lowest mean tuning CRMSE, and every value's score."""
    return {
        "chosen": min(scores, key=scores.get),
        "tuning_crmse": {str(k): v for k, v in scores.items()},
    }


def ours_tuning(
    grid: list[dict[str, float]], preset: adaptation.AdaptationConfig
) -> dict[str, Any]:
    """Ours' CRMSE tuning read off :func:`beam_tuning_grid` by coordinate descent: beta at
    the preset pi and tau^2, then pi, then tau^2, each at the others' current choice, in
    passes until a pass changes nothing (at most :data:`MAX_TUNING_PASSES`).

    Returns ``{"ours": .., "ours_pi": .., "ours_tau2": ..}`` (beta, pi, tau^2 of the last
    pass, each as :func:`_choice` gives it: the chosen value and the scores along that
    knob at the others' final values) and ``"ours_passes"``.
    """
    scores = {tuple(g[k] for k in OURS_KNOBS): g["tuning_crmse"] for g in grid}
    table, passes = coordinate_descent(
        scores, OURS_KNOBS, {k: float(getattr(preset, k)) for k in OURS_KNOBS}
    )
    return {
        "ours": table["beta"],
        "ours_pi": table["pi"],
        "ours_tau2": table["tau2"],
        "ours_passes": passes,
    }


def coordinate_descent(
    scores: dict[tuple, float], knobs: tuple[str, ...], start: dict[str, float]
) -> tuple[dict[str, dict[str, Any]], int]:
    """Minimise a score tabulated on a grid (keys: values of ``knobs`` in that order) one
    knob after the other from ``start``, in passes until one changes nothing (at most
    :data:`MAX_TUNING_PASSES`). Returns each knob's :func:`_choice` of the last pass and
    the number of passes."""
    values = {k: sorted({key[i] for key in scores}) for i, k in enumerate(knobs)}
    point = dict(start)
    passes = 0
    while passes < MAX_TUNING_PASSES:
        passes += 1
        changed, table = False, {}
        for knob in knobs:
            table[knob] = _choice(
                {v: scores[tuple({**point, knob: v}[k] for k in knobs)] for v in values[knob]}
            )
            changed |= table[knob]["chosen"] != point[knob]
            point[knob] = table[knob]["chosen"]
        if not changed:
            break
    return table, passes


def known_changepoints_tuning(
    model, cfg, X, U, X_np, betas=KNOWN_CP_BETA_GRID, tau2s=OURS_TAU2_GRID
) -> dict[str, Any]:
    """The known-changepoint reference's beta and tau^2, tuned like Ours' (coordinate
    descent from the preset on the tuning trajectories; one compiled program for the
    grid). ``chosen`` and ``tuning_crmse`` are beta's, ``tau2`` is :func:`_choice`'s."""
    B, T = (
        a.ravel()
        for a in np.meshgrid(np.asarray(betas, float), np.asarray(tau2s, float), indexing="ij")
    )

    def one(b, t):
        c = cfg._replace(beta=b, tau2=t)
        return jax.vmap(lambda X, U: run_known_changepoints(model, c, X, U))(X, U)

    xhat = jax.jit(jax.vmap(one))(jnp.asarray(B), jnp.asarray(T))
    scores = {}
    for i in range(len(B)):
        scores[(float(B[i]), float(T[i]))] = _tuning_score(xhat[i], X_np)
    table, passes = coordinate_descent(
        scores, ("beta", "tau2"), {"beta": float(cfg.beta), "tau2": float(cfg.tau2)}
    )
    return {**table["beta"], "tau2": table["tau2"], "passes": passes}


def tuned_config(cfg: adaptation.AdaptationConfig, tuned: dict[str, Any]):
    """``cfg`` with Ours' knobs as :func:`ours_tuning` chose them."""
    return cfg._replace(
        beta=tuned["ours"]["chosen"],
        pi=tuned["ours_pi"]["chosen"],
        tau2=tuned["ours_tau2"]["chosen"],
    )


def _tuning_score(xhat, X_np) -> float:
    """Mean CRMSE over the tuning trajectories; infinite if any prediction diverged."""
    c = _crmse_batch(xhat, X_np)
    return float(c.mean()) if np.isfinite(c).all() else float("inf")


def _tune(make_fn, grid, X, U, X_np) -> dict[str, Any]:
    """Pick the grid value with the lowest mean CRMSE on the tuning trajectories."""
    return _choice(
        {value: _tuning_score(jax.jit(jax.vmap(make_fn(value)))(X, U), X_np) for value in grid}
    )


def beam_tuning_grid(
    model, cfg, X, U, X_np, betas=OURS_BETA_GRID, pis=OURS_PI_GRID, tau2s=OURS_TAU2_GRID
) -> list[dict[str, float]]:
    """Ours on the tuning trajectories for every ``(beta, pi, tau2)`` triple: mean CRMSE
    and hit rate per triple. All run in one compiled program (the knobs are traced)."""
    B, P, T = (
        a.ravel()
        for a in np.meshgrid(
            np.asarray(betas, float),
            np.asarray(pis, float),
            np.asarray(tau2s, float),
            indexing="ij",
        )
    )

    def one(b, p, t):
        c = cfg._replace(beta=b, pi=p, tau2=t)
        return jax.vmap(lambda X, U: run_beam(model, c, X, U))(X, U)

    xhat, _, flags, _ = jax.jit(jax.vmap(one))(jnp.asarray(B), jnp.asarray(P), jnp.asarray(T))
    grid = []
    for i in range(len(B)):
        grid.append(
            {
                "beta": float(B[i]),
                "pi": float(P[i]),
                "tau2": float(T[i]),
                "tuning_crmse": _tuning_score(xhat[i], X_np),
                "tuning_hit_rate": changepoint_quality(np.asarray(flags[i]))["hit_rate"],
            }
        )
    return grid


def detection_tuning(
    grid: list[dict[str, float]], min_hit_rate=DETECTION_MIN_HIT_RATE
) -> dict[str, Any]:
    """Lowest tuning CRMSE of :func:`beam_tuning_grid` among the settings whose hit rate on
    the tuning trajectories is at least ``min_hit_rate`` (``chosen`` is ``None`` when no
    setting reaches it)."""
    ok = [g for g in grid if g["tuning_hit_rate"] >= min_hit_rate]
    best = min(ok, key=lambda g: g["tuning_crmse"]) if ok else None
    return {
        "min_hit_rate": min_hit_rate,
        "grid": grid,
        "chosen": None if best is None else {k: best[k] for k in OURS_KNOBS},
    }


def _stat(v) -> dict[str, float]:
    v = np.asarray(v, float)
    return {"mean": float(v.mean()), "std": float(v.std())}


# --------------------------------------------------------------------------- pipeline


def evaluate(
    settings: EvalSettings,
    out_dir: Path | None = None,
    progress: Callable[[str], None] = lambda msg: None,
) -> dict[str, Any]:
    s = settings
    t_start = time.perf_counter()
    key = jax.random.PRNGKey(s.seed)
    k_data, k_split, k_train, k_online, k_tune = jax.random.split(key, 5)

    progress(f"simulating {s.n_traj} trajectories of the true cartpole under nominal MPC")
    data = cd.simulate(
        k_data, cd.sample_initial_states(k_data, s.n_traj), cd.stationary_schedule(s.T_data)
    )

    # ---- offline validation over random splits
    offline: dict[str, list[float]] = {}
    per_split: dict[str, list[np.ndarray]] = {}
    models0 = None
    rng = np.random.default_rng(int(jax.random.randint(k_split, (), 0, 2**31 - 1)))
    for split in range(s.n_splits):
        perm = rng.permutation(s.n_traj)
        test, train = perm[: s.n_test], perm[s.n_test :]
        x, u, xn = cd.transitions(data, train)
        progress(f"split {split + 1}/{s.n_splits}: training")
        models = train_all(
            jax.random.fold_in(k_train, split),
            x,
            u,
            xn,
            s,
            lambda m, sp=split: progress(f"split {sp + 1}/{s.n_splits}: {m}"),
        )
        if split == 0:
            models0, train0 = models, (x, u, xn)
        for name, pred in offline_predictors(models).items():
            c = trajectory_crmse(pred, data.X[test], data.U[test])
            offline.setdefault(name, []).append(float(c.mean()))
            per_split.setdefault(name, []).append(c)

    # ---- online adaptation with interventions (same initial models for every method)
    m = models0
    sched = cd.intervention_schedule(s.T_online)
    progress(f"simulating {s.trials} disturbed trajectories")
    online_data = cd.simulate(k_online, cd.sample_initial_states(k_online, s.trials), sched)
    tune_data = cd.simulate(k_tune, cd.sample_initial_states(k_tune, s.tuning_trials), sched)
    X, U = jnp.asarray(online_data.X), jnp.asarray(online_data.U)

    tx, tu = jnp.asarray(tune_data.X), jnp.asarray(tune_data.U)
    cfg = adaptation.cartpole_config()

    no_cp_fn = no_cp_runner(m.vld, cfg.sigma2)

    def mlp_fn(lr):
        return lambda X, U: run_mlp(m.mlp, lr, X, U)

    def known_fn(beta, tau2):
        return lambda X, U: run_known_changepoints(m.vld, cfg._replace(beta=beta, tau2=tau2), X, U)

    # Each method's online knobs, chosen on separate tuning trajectories (module docstring).
    # Ours: one run of the whole beta x pi x tau^2 grid serves its coordinate descent and
    # the detection-tuned setting.
    progress("online: tuning beta, pi, tau^2 (ours), tau^2 (ours w/o CP), learning rate (MLP)")
    grid = beam_tuning_grid(m.vld, cfg, tx, tu, tune_data.X)
    tuned = ours_tuning(grid, cfg)
    tuned["ours_no_cp"] = _tune(no_cp_fn, NO_CP_TAU2_GRID, tx, tu, tune_data.X)
    tuned["mlp_last_layer"] = _tune(mlp_fn, MLP_LR_GRID, tx, tu, tune_data.X)
    tuned["ours_known_changepoints"] = known_changepoints_tuning(m.vld, cfg, tx, tu, tune_data.X)
    ours_cfg = tuned_config(cfg, tuned)
    detection = detection_tuning(grid)

    progress("online: running all methods")
    vm = lambda f: jax.jit(jax.vmap(f))(X, U)  # noqa: E731
    ours_out = beam_batch(m.vld, ours_cfg, X, U)
    paper_out = beam_batch(m.vld, cfg, X, U)
    runs = {
        "ours": ours_out[0],
        "ours_no_cp": vm(no_cp_fn(tuned["ours_no_cp"]["chosen"])),
        "gp": vm(lambda X, U: run_gp(m.gp, X, U)),
        "mlp_last_layer": vm(mlp_fn(tuned["mlp_last_layer"]["chosen"])),
        "offline_only": vm(lambda X, U: run_offline_only(m.vld, X, U)),
        # Reference rows: the paper's own settings, and the irreducible-noise floor.
        "ours_paper_config": paper_out[0],
        "ours_no_cp_paper_config": vm(no_cp_fn(cfg.tau2)),
        "mlp_last_layer_paper_lr": vm(mlp_fn(PAPER_MLP_LR)),
        "oracle_true_model": vm(lambda X, U: run_oracle(sched, X, U)),
        "ours_known_changepoints": vm(
            known_fn(
                tuned["ours_known_changepoints"]["chosen"],
                tuned["ours_known_changepoints"]["tau2"]["chosen"],
            )
        ),
    }
    det = detection["chosen"]
    if det is not None:
        det_out = beam_batch(m.vld, cfg._replace(**det), X, U)
        runs["ours_detection_tuned"] = det_out[0]
        detection["changepoints"] = changepoint_quality(np.asarray(det_out[2]))
        detection["hit_rate_per_intervention"] = hits_per_intervention(np.asarray(det_out[2]))
    online_crmse = {name: _crmse_batch(xhat, online_data.X) for name, xhat in runs.items()}

    result: dict[str, Any] = {
        "online": {k: _stat(v) for k, v in online_crmse.items()},
        "offline": {k: _stat(v) for k, v in offline.items()},
        "changepoints": changepoint_quality(np.asarray(ours_out[2])),
        "changepoints_paper_config": changepoint_quality(np.asarray(paper_out[2])),
        "hit_rate_per_intervention": hits_per_intervention(np.asarray(ours_out[2])),
        "tuning": tuned,
        "detection_tuning": detection,
        "ours_config": {
            "K": ours_cfg.K,
            "beta": ours_cfg.beta,
            "pi": ours_cfg.pi,
            "tau2": ours_cfg.tau2,
        },
        "mlp_learning_rate": {"chosen": tuned["mlp_last_layer"]["chosen"], "paper": PAPER_MLP_LR},
        "settings": s.__dict__,
    }
    o = result["online"]
    result["ratios"] = {
        f"ours/{k}": o["ours"]["mean"] / o[k]["mean"]
        for k in ("ours_no_cp", "gp", "mlp_last_layer", "offline_only")
    }

    if s.ablations:
        # Around the tuned configuration: at the paper's beta = 0.9 hardly anything is
        # detected, so K and pi would change nothing visible there.
        progress("ablations over K, beta, pi (around the tuned configuration)")
        result["ablations"] = ablations(m.vld, ours_cfg, online_data)
        progress(f"ablation over the latent dimension l = {LATENT_DIMS} (training each)")
        vld_key = jax.random.split(jax.random.fold_in(k_train, 0), 6)[0]  # as train_all
        result["latent_ablation"] = latent_ablation(
            vld_key, train0, m.vld, cfg, s, tune_data, online_data
        )

    if out_dir is not None:
        from benchmarks import cartpole_figures as figs

        progress(f"writing figures to {out_dir}")
        out_dir.mkdir(parents=True, exist_ok=True)
        figs.online_rollout(out_dir / "online_rollout.png", online_data, ours_out, 0)
        figs.online_rollout(out_dir / "online_rollout_paper_config.png", online_data, paper_out, 0)
        figs.offline_distribution(out_dir / "offline_crmse.png", per_split)
        figs.latent_comparison(out_dir / "latent_embeddings.png", m, data)
    result["wall_time_s"] = time.perf_counter() - t_start
    return result


def ablations(model, cfg, data) -> dict[str, list[dict[str, float]]]:
    """Online CRMSE and detection quality vs beam size K, temperature beta, prior pi."""
    grids = {
        "K": [cfg._replace(K=k) for k in (1, 2, 5, 10, 20)],
        "beta": [cfg._replace(beta=b) for b in (0.3, 0.5, 0.7, 0.9, 0.97, 0.99)],
        "pi": [cfg._replace(pi=p) for p in (0.01, 0.02, 0.05, 0.1, 0.2)],
    }
    out = {}
    for name, configs in grids.items():
        rows = []
        for c in configs:
            xhat, _, flags, _ = beam_batch(model, c, data.X, data.U)
            crm = _crmse_batch(xhat, data.X)
            q = changepoint_quality(np.asarray(flags))
            rows.append(
                {
                    name: float(getattr(c, name)),
                    "crmse_mean": float(crm.mean()),
                    "crmse_std": float(crm.std()),
                    "hit_rate": q["hit_rate"],
                    "false_alarms_per_100_steps": q["false_alarms_per_100_steps"],
                }
            )
        out[name] = rows
    return out


def latent_ablation(
    key,
    train,
    vld0: encoder.VLD,
    cfg: adaptation.AdaptationConfig,
    s: EvalSettings,
    tune: cd.Batch,
    online: cd.Batch,
    dims=LATENT_DIMS,
) -> list[dict[str, Any]]:
    """Ours, Ours w/o CP and offline-only for each latent dimension ``l`` of the encoder.

    Each ``l`` is trained like the main model (same data, key and epochs; the preset ``l``
    reuses ``vld0``, the model of the main table) and both online methods are tuned
    on the tuning trajectories exactly as in :func:`evaluate`, so a row differs from the
    main table only by ``l``.
    """
    x, u, xn = train
    tx, tu = jnp.asarray(tune.X), jnp.asarray(tune.U)
    X, U = jnp.asarray(online.X), jnp.asarray(online.U)
    rows = []
    for l in dims:
        vld = (
            vld0
            if l == vld0.theta0.shape[-1]
            else train_vld(key, x, u, xn, variational=True, epochs=s.epochs, latent_dim=l)
        )
        tuned = ours_tuning(beam_tuning_grid(vld, cfg, tx, tu, tune.X), cfg)
        no_cp_fn = no_cp_runner(vld, cfg.sigma2)
        tau2 = _tune(no_cp_fn, NO_CP_TAU2_GRID, tx, tu, tune.X)["chosen"]
        c = tuned_config(cfg, tuned)
        xhat, _, flags, _ = beam_batch(vld, c, X, U)
        ours = _crmse_batch(xhat, online.X)
        no_cp = _crmse_batch(jax.jit(jax.vmap(no_cp_fn(tau2)))(X, U), online.X)
        offline = _crmse_batch(
            jax.jit(jax.vmap(lambda X, U, vld=vld: run_offline_only(vld, X, U)))(X, U), online.X
        )
        q = changepoint_quality(np.asarray(flags))
        rows.append(
            {
                "l": l,
                "beta": float(c.beta),
                "pi": float(c.pi),
                "ours_tau2": float(c.tau2),
                "tau2": tau2,
                "ours": _stat(ours),
                "ours_no_cp": _stat(no_cp),
                "offline_only": _stat(offline),
                "ratio_ours_no_cp": float(ours.mean() / no_cp.mean()),
                "hit_rate": q["hit_rate"],
                "false_alarms_per_100_steps": q["false_alarms_per_100_steps"],
            }
        )
    return rows


def format_table(result: dict[str, Any]) -> str:
    """Human-readable summary of :func:`evaluate`."""
    lines = ["Online adaptation (CRMSE, mean ± std over trajectories):"]
    for k, v in result["online"].items():
        lines.append(f"  {k:26s} {v['mean']:8.3f} ± {v['std']:.3f}")
    lines.append("Offline validation (CRMSE, mean ± std over splits):")
    for k, v in result["offline"].items():
        lines.append(f"  {k:26s} {v['mean']:8.3f} ± {v['std']:.3f}")
    cp = result["changepoints"]
    lines.append(
        f"Changepoints: hit rate {cp['hit_rate']:.0%}, false alarms "
        f"{cp['false_alarms_per_100_steps']:.2f}/100 steps, mean delay "
        f"{cp['mean_delay_steps']:.2f} steps"
    )
    lines.append(detection_summary(result.get("detection_tuning")))
    for row in result.get("latent_ablation", []):
        lines.append(
            f"Latent dimension l = {row['l']}: ours {row['ours']['mean']:.3f} (hit rate "
            f"{row['hit_rate']:.0%}), ours_no_cp {row['ours_no_cp']['mean']:.3f}, "
            f"offline_only {row['offline_only']['mean']:.3f}, "
            f"ours/ours_no_cp {row['ratio_ours_no_cp']:.2f}"
        )
    lines.append("Ratios: " + ", ".join(f"{k} = {v:.2f}" for k, v in result["ratios"].items()))
    return "\n".join(lines)


def detection_summary(d: dict[str, Any] | None) -> str:
    """One sentence on the detection-tuned row (:func:`detection_tuning`)."""
    if not d:
        return "Detection-tuned Ours: not run."
    goal = f"at least {d['min_hit_rate']:.0%} of the tuning trajectories' interventions"
    if d["chosen"] is None:
        return f"Detection-tuned Ours: no (beta, pi, tau^2) setting of the grid detects {goal}."
    c, q = d["chosen"], d["changepoints"]
    per = d.get("hit_rate_per_intervention", {})
    return (
        f"Detection-tuned Ours (lowest tuning CRMSE among the settings that detect {goal}): "
        f"beta = {c['beta']:g}, pi = {c['pi']:g}"
        + (f", tau^2 = {c['tau2']:g}" if "tau2" in c else "")
        + "; on the evaluation trajectories hit rate "
        f"{q['hit_rate']:.0%}"
        + (" (" + ", ".join(f"step {k} {v:.0%}" for k, v in per.items()) + ")" if per else "")
        + f", false alarms {q['false_alarms_per_100_steps']:.2f} per 100 steps, mean delay "
        f"{q['mean_delay_steps']:.2f} steps; its CRMSE is the `ours_detection_tuned` row."
    )
