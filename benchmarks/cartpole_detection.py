"""Changepoint-detection quality in the cartpole evaluation: hits, false alarms, delay.

A detection at step ``k`` concerns the transition ``x_k -> x_{k+1}``, the step an
intervention at ``k`` acts on (``arcade_control.cartpole``); it counts as a hit within
:data:`~benchmarks.cartpole_settings.HIT_WINDOW` steps after the intervention.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from arcade_control import cartpole as cd
from benchmarks.cartpole_settings import HIT_WINDOW


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
