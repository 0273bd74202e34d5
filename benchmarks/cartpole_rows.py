"""The cartpole evaluation's headline rows: the paper's methods at the paper's settings.

Shared by the evaluation (``benchmarks.cartpole_eval``) and its sensitivity study
(``benchmarks.cartpole_sensitivity``): the offline data of a reading, the headline runs
(one step ahead and over the horizon), their per-trajectory CRMSE and the paper's ratios.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from arcade_control import cartpole as cd
from benchmarks.cartpole_methods import (
    OfflineModels,
    beam_batch,
    crmse_batch,
    horizon_crmse,
    no_cp_runner,
    run_gp,
    run_mlp,
    run_offline_only,
    run_oracle,
)
from benchmarks.cartpole_settings import PAPER_MLP_LR, EvalSettings


def stat(v) -> dict[str, float]:
    v = np.asarray(v, float)
    return {"mean": float(v.mean()), "std": float(v.std())}


#: The paper's Table I methods, at the paper's settings: the headline rows.
PAPER_ROWS = ("ours", "ours_no_cp", "gp", "mlp_last_layer", "offline_only")
#: Ratio denominators of the tuned rows (GP and offline only have no online knob).
TUNED_RATIOS = {
    "ours_no_cp": "ours_no_cp_tuned",
    "gp": "gp",
    "mlp_last_layer": "mlp_last_layer_tuned",
    "offline_only": "offline_only",
}


def pair(out, horizon: int):
    """``(one-step, open-loop or None)`` of a run that returns both when ``horizon > 0``."""
    return (out[0], out[1]) if horizon else (out, None)


def headline_runs(m: OfflineModels, cfg, sched, params, X, U, horizon: int):
    """The paper's methods at the paper's settings (Appendix D ``cfg``, MLP rate 1e-6) and
    the oracle on trajectories ``X, U``: ``{name: (one-step, open-loop or None)}`` and Ours'
    full output (for its detections and figure)."""
    vm = lambda f: pair(jax.jit(jax.vmap(f))(X, U), horizon)  # noqa: E731
    beam = beam_batch(m.vld, cfg, X, U, horizon)
    no_cp = no_cp_runner(m.vld, cfg.sigma2, horizon)
    runs = {
        "ours": (beam[0], beam[4] if horizon else None),
        "ours_no_cp": vm(no_cp(cfg.tau2)),
        "gp": vm(lambda X, U: run_gp(m.gp, X, U, horizon)),
        "mlp_last_layer": vm(lambda X, U: run_mlp(m.mlp, PAPER_MLP_LR, X, U, horizon)),
        "offline_only": vm(lambda X, U: run_offline_only(m.vld, X, U, horizon)),
        "oracle_true_model": vm(lambda X, U: run_oracle(sched, X, U, params, horizon)),
    }
    return runs, beam


def score(runs, X) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Per-trajectory one-step CRMSE and horizon CRMSE (where run) of every row."""
    one = {k: crmse_batch(v[0], X) for k, v in runs.items()}
    hor = {k: horizon_crmse(v[1], X) for k, v in runs.items() if v[1] is not None}
    return one, hor


def ratios(crmse: dict[str, Any], ours: str = "ours", others=None) -> dict[str, float]:
    """The paper's four ratios, ``ours/<row>`` of mean CRMSE (keys as the paper's rows;
    ``others`` maps a key to the row it divides by)."""
    others = others or {k: k for k in PAPER_ROWS[1:]}

    def mean(v):
        return v["mean"] if isinstance(v, dict) else float(np.mean(v))

    return {f"ours/{k}": mean(crmse[ours]) / mean(crmse[row]) for k, row in others.items()}


def offline_data(s: EvalSettings, k_data):
    """The stationary offline dataset of this reading (Sec. V-A, Appendix D)."""
    return cd.simulate(
        k_data,
        cd.sample_initial_states(k_data, s.n_traj),
        cd.stationary_schedule(s.T_data),
        s.true_params(),
    )
