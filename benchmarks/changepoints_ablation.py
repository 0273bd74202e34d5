"""What the changepoint beam adds over Bayesian linear regression with exponential forgetting.

Replayed on the flights of ``arcade eval changepoints`` (:func:`benchmarks.changepoints.fly`):
the transitions, features, normalised residuals and per-step noise that the adapter's
learner saw, in the order it saw them. Three learners, each predicting a step's residual
before learning it (Eq. 10, one step ahead):

- ``beam``: the learner the stack flies (ours at the adapter's knobs: ``K = 15``, its
  ``pi``, ``beta`` and offline prior floor);
- ``no_changepoints``: one hypothesis that is never tempered (plain BLR, Appendix D 5);
- ``forgetting``: one hypothesis tempered at every step by ``lambda``
  (:func:`arcade_control.learners.forgetting_config`; the offline prior re-injected as in
  the beam), ``lambda`` chosen on the tuning seeds by the one-step predictive negative
  log-likelihood over :data:`LAMBDAS`, as the beam's own knobs were chosen by how well it
  does its job.

Prediction: RMSE of the normalised residual over all outputs and over the vertical ones,
over the second after each release (how fast a learner re-adapts), and the mean Gaussian
negative log-likelihood per output (the predictive variance with the step's noise).

Detection: forgetting has no changepoint variable, so it is given the classic detector of a
forgetting filter, an innovation test (:func:`innovation_test`): the squared innovations of
the watched outputs over their predicted variances, averaged over the last ``window``
steps, declared at ``threshold`` with a refractory period; its knobs are tuned by F1 on the
tuning seeds over :data:`TEST_GRID`, as the beam's detector is. Both are scored by
:func:`benchmarks.changepoints.score`.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from arcade_control.knobs import DETECTION_OUTPUTS
from arcade_control.learners import forgetting_config, no_cp_config
from arcade_control.nominal import CONTROL_DT as DT
from arcade_control.stack import stack_knobs
from arcade_core import adaptation
from benchmarks.changepoints import declare, score

#: Forgetting factors tried (``lambda``; the memory is about ``1 / (1 - lambda)`` steps).
LAMBDAS = (0.8, 0.9, 0.95, 0.98, 0.99, 0.995, 0.998, 0.999)
#: ``lambda`` of a run without tuning (``--quick``): the best of the stored full run.
STORED_LAMBDA = 0.98
#: The innovation test's grid (the first two need no replay of the learner).
TEST_GRID = {
    "outputs": ("all", "translational", "vertical"),
    "window": (1, 5, 10),
    "threshold": (1.2, 1.5, 2.0, 3.0, 5.0, 8.0, 12.0, 20.0),
    "refractory_steps": (5, 20, 50, 100),
}
#: The innovation test of a run without tuning (``--quick``).
STORED_TEST = {"outputs": "vertical", "window": 5, "threshold": 2.0, "refractory_steps": 50}
#: Length after a release over which re-adaptation is measured [s].
AFTER_RELEASE_S = 1.0


def learner_config(which: str, lam: float | None = None) -> adaptation.AdaptationConfig:
    """The configuration of ``which`` (``beam``, ``no_changepoints`` or ``forgetting``) at
    the adapter's knobs (``sigma2`` is replaced by each step's recorded noise)."""
    knobs = stack_knobs()
    cfg = adaptation.quadrotor_config()._replace(
        beta=knobs["ours_beta"], sigma2=knobs["ours_sigma2"]
    )
    if which == "beam":
        return cfg
    if which == "no_changepoints":
        return no_cp_config(cfg)
    if which == "forgetting":
        return forgetting_config(cfg, STORED_LAMBDA if lam is None else lam)
    raise ValueError(f"unknown learner {which!r}")


@jax.jit
def _scan(state, cfg, z, dn, s2, learned):
    def body(st, inp):
        z_k, dn_k, s2_k, l_k = inp
        new, pred, _ = adaptation.step(st, z_k, dn_k, cfg._replace(sigma2=s2_k))
        ok = l_k & jnp.all(jnp.isfinite(z_k)) & jnp.all(jnp.isfinite(dn_k))
        st = jax.tree.map(lambda a, b: jnp.where(ok, a, b), new, st)
        return st, (dn_k - pred.mean, pred.param + pred.between + s2_k)

    return jax.lax.scan(body, state, (z, dn, s2, learned))[1]


def replay(theta0, cfg: adaptation.AdaptationConfig, inputs) -> tuple[np.ndarray, np.ndarray]:
    """One learner over one flight's ``(z, dn, sigma2, learned)``: the one-step innovation
    and its predictive variance at every step, ``(n, d)`` each (steps not learned are
    predicted but leave the learner as it was)."""
    z, dn, s2, learned = inputs
    dtype = jnp.result_type(float)
    d = np.asarray(theta0).shape[0]
    start = cfg._replace(sigma2=jnp.ones(d, dtype))
    state = adaptation.init(jnp.asarray(theta0, dtype), start)
    traced = adaptation.AdaptationConfig(
        K=int(cfg.K),
        pi=jnp.asarray(cfg.pi, dtype),
        beta=jnp.asarray(cfg.beta, dtype),
        tau2=jnp.asarray(cfg.tau2, dtype),
        sigma2=jnp.ones(d, dtype),
        prior_floor=jnp.asarray(cfg.prior_floor, dtype),
        score=cfg.score,
        nu=cfg.nu,
    )
    err, var = _scan(state, traced, z, dn, s2, learned)
    return np.asarray(err), np.asarray(var)


def prediction_metrics(
    flights: list[dict[str, Any]], inputs: list[tuple], replays: list[tuple]
) -> dict[str, float]:
    """RMSE (all outputs, vertical ones, the second after each release) and mean NLL of
    the one-step predictions over the learned steps of ``flights``."""
    vertical = list(DETECTION_OUTPUTS["vertical"])
    sq, sq_v, nll, sq_after = [], [], [], []
    for f, inp, (err, var) in zip(flights, inputs, replays, strict=True):
        keep = inp[3] & np.all(np.isfinite(err), axis=1)
        sq.append(err[keep] ** 2)
        sq_v.append(err[keep][:, vertical] ** 2)
        nll.append(0.5 * (np.log(2 * np.pi * var[keep]) + err[keep] ** 2 / var[keep]))
        if np.isfinite(f["t_release"]):
            t = np.arange(len(err)) * DT - f["t_release"]
            sq_after.append(err[keep & (t > 0) & (t <= AFTER_RELEASE_S)] ** 2)

    def rms(parts):
        return float(np.sqrt(np.mean(np.concatenate(parts)))) if parts else float("nan")

    return {
        "rmse": rms(sq),
        "rmse_vertical": rms(sq_v),
        "rmse_after_release": rms(sq_after),
        "nll": float(np.mean(np.concatenate(nll))),
    }


def _statistic(err: np.ndarray, var: np.ndarray, outputs: str, window: int) -> np.ndarray:
    """Mean squared normalised innovation of the watched outputs over the last ``window``
    steps (about 1 when the predictive variance is right)."""
    q = np.nan_to_num(
        err[:, list(DETECTION_OUTPUTS[outputs])] ** 2 / var[:, list(DETECTION_OUTPUTS[outputs])],
        nan=0.0,
    )
    s = q.mean(axis=1)
    c = np.concatenate([[0.0], np.cumsum(s)])
    n = np.arange(1, len(s) + 1)
    lo = np.maximum(n - window, 0)
    return (c[n] - c[lo]) / (n - lo)


def innovation_test(
    err: np.ndarray, var: np.ndarray, learned: np.ndarray, knobs: dict[str, Any]
) -> np.ndarray:
    """The forgetting filter's changepoint declarations: the windowed statistic at or above
    ``threshold`` on a learned step, nothing for ``refractory_steps`` after one."""
    stat = _statistic(err, var, knobs["outputs"], int(knobs["window"]))
    stat = np.where(learned, stat, 0.0)
    return declare(stat, float(knobs["threshold"]), int(knobs["refractory_steps"]))


def tune_test(flights, inputs, replays) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The innovation test's knobs with the best F1 on ``flights`` (ties: fewer false
    alarms per flight), and every grid point's score."""
    rows = []
    for values in itertools.product(*TEST_GRID.values()):
        knobs = dict(zip(TEST_GRID, values, strict=True))
        declared = [
            innovation_test(e, v, inp[3], knobs)
            for inp, (e, v) in zip(inputs, replays, strict=True)
        ]
        rows.append({"knobs": knobs, **score(flights, declared)})
    best = max(rows, key=lambda r: (np.nan_to_num(r["f1"]), -r["false_alarms_per_flight"]))
    knobs = dict(best["knobs"])
    knobs["on_grid_edge"] = [
        k
        for k, values in TEST_GRID.items()
        if k != "outputs" and knobs[k] in (values[0], values[-1])
    ]
    return knobs, rows


def run_ablation(
    theta0,
    flights: list[dict[str, Any]],
    inputs: list[tuple],
    tune_flights: list[dict[str, Any]] | None,
    tune_inputs: list[tuple] | None,
    detector: dict[str, Any],
    progress: Callable[[str], None] = lambda msg: None,
) -> dict[str, Any]:
    """The ablation's result: ``lambda`` and the innovation test tuned on ``tune_flights``
    (stored values without them), then prediction and detection on ``flights`` beside the
    beam's (``detector``: the beam detector's score on the same flights)."""
    lam, lam_rows, test, test_rows = STORED_LAMBDA, [], dict(STORED_TEST), []
    if tune_flights:
        for value in LAMBDAS:
            cfg = learner_config("forgetting", value)
            reps = [replay(theta0, cfg, i) for i in tune_inputs]
            lam_rows.append(
                {"lambda": value, **prediction_metrics(tune_flights, tune_inputs, reps)}
            )
            progress(f"forgetting ablation: lambda {value} nll {lam_rows[-1]['nll']:.3f}")
        lam = min(lam_rows, key=lambda r: r["nll"])["lambda"]
        reps = [replay(theta0, learner_config("forgetting", lam), i) for i in tune_inputs]
        test, test_rows = tune_test(tune_flights, tune_inputs, reps)
    prediction, forgetting_reps = {}, None
    for which in ("beam", "no_changepoints", "forgetting"):
        cfg = learner_config(which, lam)
        reps = [replay(theta0, cfg, i) for i in inputs]
        prediction[which] = prediction_metrics(flights, inputs, reps)
        if which == "forgetting":
            forgetting_reps = reps
        progress(f"forgetting ablation: {which} replayed")
    chosen = {k: v for k, v in test.items() if k != "on_grid_edge"}
    declared = [
        innovation_test(e, v, inp[3], chosen)
        for inp, (e, v) in zip(inputs, forgetting_reps, strict=True)
    ]
    return {
        "prediction": prediction,
        "detection": {
            "beam_detector": detector,
            "forgetting_innovation_test": score(flights, declared),
        },
        "lambda": lam,
        "lambda_on_grid_edge": bool(tune_flights) and lam in (LAMBDAS[0], LAMBDAS[-1]),
        "lambda_tuning": lam_rows,
        "innovation_test_knobs": test,
        "innovation_test_tuning": test_rows,
        "tuned": bool(tune_flights),
    }


def format_table(ablation: dict[str, Any]) -> list[str]:
    """The ablation as text lines (prediction, then detection)."""
    p, d = ablation["prediction"], ablation["detection"]
    lines = [
        f"Forgetting ablation (lambda {ablation['lambda']:g}): one-step prediction of the "
        "normalised residual",
        f"{'':26s} {'RMSE':>8s} {'vertical':>9s} {'1 s after':>10s} {'NLL':>8s}",
    ]
    for name, r in p.items():
        lines.append(
            f"{name:26s} {r['rmse']:8.4f} {r['rmse_vertical']:9.4f} "
            f"{r['rmse_after_release']:10.4f} {r['nll']:8.3f}"
        )
    for name, r in d.items():
        lines.append(
            f"{name:26s} hit rate {r['release_hit_rate']:.2f}, "
            f"FA/flight {r['false_alarms_per_flight']:.2f}, "
            f"FA/min steady {r['false_alarms_per_min_steady']:.2f}, "
            f"precision {r['precision']:.2f}"
        )
    return lines
