"""Sensitivity of the cartpole evaluation to the readings the paper leaves open.

Each reading of :data:`~benchmarks.cartpole_settings.SENSITIVITY` is varied alone around
the evaluation's own (``EvalSettings``): the impulse's length (1, 2, 5 control periods, or
held until the next intervention, alternating: the earlier variant), the noise reading
(``N(-0.5, 0.5)`` as std 0.5 or as variance 0.5) and the horizon of the open-loop CRMSE. A
row is the headline only — the paper's methods at the paper's settings
(``cartpole_eval.headline_runs``), no tuning — on fresh evaluation trajectories of that
reading, with the models of split 0; the noise reading changes the offline data too, so its
rows train their own models (as ``train_all`` does for split 0). The horizons are read off
one rollout of the longest (the first ``h`` steps of an open-loop prediction are the
``h``-step prediction).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from arcade_control import cartpole as cd
from arcade_core import adaptation
from benchmarks.cartpole_detection import changepoint_quality
from benchmarks.cartpole_methods import OfflineModels, horizon_crmse, train_all
from benchmarks.cartpole_rows import headline_runs, offline_data, ratios, score, stat
from benchmarks.cartpole_settings import SENSITIVITY, EvalSettings


def _row(s: EvalSettings, m: OfflineModels, horizons) -> dict[str, Any]:
    key = jax.random.split(jax.random.PRNGKey(s.seed), 5)[3]  # the evaluation's k_online
    params, sched = s.true_params(), s.schedule()
    data = cd.simulate(key, cd.sample_initial_states(key, s.trials), sched, params)
    H = max(horizons)
    runs, beam = headline_runs(
        m, adaptation.cartpole_config(), sched, params, jnp.asarray(data.X), data.U, H
    )
    one, _ = score(runs, data.X)
    row: dict[str, Any] = {
        "online": {k: stat(v) for k, v in one.items()},
        "ratios": ratios(one),
        "changepoints": changepoint_quality(np.asarray(beam[2]), push_snr=s.push_snr()),
    }
    for h in horizons:
        hor = {k: horizon_crmse(np.asarray(v[1])[:, :, :h], data.X) for k, v in runs.items()}
        row[f"online_horizon_{h}"] = {k: stat(v) for k, v in hor.items()}
        row[f"ratios_horizon_{h}"] = ratios(hor)
    return row


def sensitivity(
    s: EvalSettings, m: OfflineModels, progress: Callable[[str], None] = lambda msg: None
) -> dict[str, Any]:
    """``{reading: {value: row}}`` (module docstring); ``m`` are the evaluation's split-0
    models for its own noise reading."""
    horizons = SENSITIVITY["horizon"]
    out: dict[str, Any] = {"horizons": list(horizons), "pulse_steps": {}, "noise": {}}
    for pulse in SENSITIVITY["pulse_steps"]:
        length = "held" if pulse is None else f"of {pulse} control periods"
        progress(f"sensitivity: impulse {length}")
        row = _row(dataclasses.replace(s, pulse_steps=pulse), m, horizons)
        out["pulse_steps"][str(pulse or "held")] = row
    for noise in SENSITIVITY["noise"]:
        progress(f"sensitivity: noise reading {noise}")
        v = dataclasses.replace(s, noise=noise)
        models = m if noise == s.noise else _split0_models(v, progress)
        out["noise"][noise] = _row(v, models, horizons)
    return out


def _split0_models(s: EvalSettings, progress) -> OfflineModels:
    """The models of split 0 on this reading's offline data (as ``evaluate`` trains them)."""
    key = jax.random.PRNGKey(s.seed)
    k_data, k_split, k_train, _, _ = jax.random.split(key, 5)
    data = offline_data(s, k_data)
    rng = np.random.default_rng(int(jax.random.randint(k_split, (), 0, 2**31 - 1)))
    train = rng.permutation(s.n_traj)[s.n_test :]
    x, u, xn = cd.transitions(data, train)
    return train_all(jax.random.fold_in(k_train, 0), x, u, xn, s, progress)
