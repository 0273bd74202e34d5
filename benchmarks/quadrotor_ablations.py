"""Ablations of the closed-loop quadrotor evaluation (:mod:`benchmarks.quadrotor_closedloop`),
in process: the Table V analogue (tracking RMSE and adaptation time per step vs beam size
``K``, :func:`run_beam_ablation`) and the learned residual inside the rollout against the
same method with the residual held along the warm start (:func:`run_residual_ablation`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from arcade_control.guard import cast as _cast
from arcade_control.knobs import HELD, TUNED_DEFAULTS, knobs_of
from arcade_control.nominal import f_nom
from arcade_control.scenario import Scenario
from arcade_core import adaptation, encoder
from benchmarks.common import machine
from benchmarks.quadrotor_closedloop import _mean
from benchmarks.quadrotor_flights import Flight, Runner

BEAM_SIZES = (5, 10, 15, 20, 30)


def run_beam_ablation(
    beam_sizes: Sequence[int] = BEAM_SIZES,
    trials: int = 3,
    payload_g: float = 175.0,
    speed_mps: float = 1.5,
    quick: bool = False,
    models=None,
    progress: Callable[[str], None] = lambda msg: None,
    seed: int = 0,
) -> dict[str, Any]:
    """Table V analogue: tracking RMSE and adaptation time per step vs beam size ``K``.

    The adaptation time is that of Algorithm 1 alone (``adaptation.update`` + the
    beam-marginal prediction, jitted, excluding the MPC), timed by replaying the
    transitions of the first trial's flight; median over steps.
    """
    from benchmarks.quadrotor_openloop import prepare_models

    if models is None:
        models = prepare_models(quick=quick, seed=seed, progress=progress)
    if quick:
        trials = 1
    runner = Runner(models)
    tuned = {**TUNED_DEFAULTS, **getattr(models, "closedloop", {})}
    scen = Scenario(payload_g=payload_g, speed_mps=speed_mps)
    rows = []
    for K in beam_sizes:
        name = f"ours_K{int(K)}"
        progress(f"beam ablation: K = {K}")
        flights = [runner.fly(name, scen, seed=seed * 1000 + i) for i in range(trials)]
        rmse = [f.metrics["rmse_m"] for f in flights]
        rows.append(
            {
                "K": int(K),
                "rmse_m": _mean(rmse),
                "adapt_ms_per_step": adaptation_time_ms(
                    models.vld, int(K), tuned["ours_beta"], flights[0], runner.dtype
                ),
            }
        )
    return {
        "rows": rows,
        "payload_g": payload_g,
        "speed_mps": speed_mps,
        "trials": trials,
        "beta": tuned["ours_beta"],
        "machine": machine(),
    }


def run_residual_ablation(
    methods: Sequence[str] = ("gp", "mlp", "ours"),
    trials: int = 3,
    payload_g: float = 175.0,
    speed_mps: float = 2.5,
    models=None,
    progress: Callable[[str], None] = lambda msg: None,
    seed: int = 0,
) -> dict[str, Any]:
    """The learned residual inside the rollout (what every learned-model method flies)
    against the same method with the residual held along the warm start, side by side:
    tracking RMSE, z-RMSE and the median per-step time of the jitted update."""
    from benchmarks.quadrotor_openloop import prepare_models

    if models is None:
        models = prepare_models(seed=seed, progress=progress)
    runner = Runner(models)
    scen = Scenario(payload_g=payload_g, speed_mps=speed_mps)
    rows = []
    for name in methods:
        for variant in (name, name + HELD):
            progress(f"residual ablation: {variant}")
            flights = [runner.fly(variant, scen, seed=seed * 1000 + i) for i in range(trials)]
            rows.append(
                {
                    "method": name,
                    "residual": "held" if variant != name else "rollout",
                    "rmse_m": _mean([f.metrics["rmse_m"] for f in flights]),
                    "rmse_z_m": _mean([f.metrics["rmse_z_m"] for f in flights]),
                    "step_ms_median": float(
                        np.median(np.concatenate([f.step_ms[1:] for f in flights]))
                    ),
                }
            )
    return {
        "rows": rows,
        "payload_g": payload_g,
        "speed_mps": speed_mps,
        "trials": trials,
        "tuned": knobs_of(getattr(models, "closedloop", {}), methods),
        "machine": machine(),
    }


def adaptation_time_ms(vld: encoder.VLD, K: int, beta: float, flight: Flight, dtype) -> float:
    """Median wall time [ms] of one jitted adaptation step (update + predict), replayed."""
    cfg = adaptation.quadrotor_config()._replace(K=K, beta=beta)
    vld = _cast(vld, dtype)
    state = adaptation.init(vld.theta0, cfg)

    @jax.jit
    def one(state, xp, up, x):
        z = vld.features(xp, up)
        dn = vld.normalise_residual(x - f_nom(xp, up))
        state, pred, _ = adaptation.step(state, z, dn, cfg, vld.latent_variance(xp, up))
        return state, pred.mean

    xs = jnp.asarray(flight.x, dtype)
    us = jnp.asarray(flight.u, dtype)
    times = []
    for k in range(xs.shape[0] - 1):
        t0 = time.perf_counter()
        state, mean = one(state, xs[k], us[k], xs[k + 1])
        jax.block_until_ready(mean)
        times.append(time.perf_counter() - t0)
    return float(np.median(times[1:]) * 1e3)
