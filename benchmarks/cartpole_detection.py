"""Changepoint-detection quality on the cartpole: hits, precision, false alarms, delay.

One metric for the cartpole evaluation (``arcade eval cartpole``) and the declaration
rule's study (``arcade eval changepoints``, ``benchmarks.changepoints_cartpole``). A
detection at step ``k`` concerns the transition ``x_k -> x_{k+1}``, the step an
intervention at ``k`` acts on (``arcade_control.cartpole``); it is a hit for intervention
``t`` if ``t <= k <= t + HIT_WINDOW``. Each intervention counts at most one hit (delay: the
offset of its first detection); every other detection is a false alarm; precision = hits /
detections.

False alarms are given per 100 steps of all steps (``false_alarms_per_100_steps``: every
detection that is not a hit) and per 100 *eligible* steps
(``false_alarms_per_100_eligible_steps``: detections outside every hit window over the
steps outside every hit window, where a detection can only be false). Beside each score,
``random_baseline``: the expected scores of a detector that flags every step independently
with the same probability as the scored one (its flag rate), in closed form. And, for the
testbed's one-period push, ``known_dynamics_bound``: the highest hit rate any detector can
have at the scored one's false-alarm rate (:func:`push_detection_bound`).
"""

from __future__ import annotations

import itertools
from statistics import NormalDist
from typing import Any

import numpy as np

from arcade_control import cartpole as cd
from benchmarks.cartpole_settings import HIT_WINDOW


def _windows(T: int, steps, window: int) -> np.ndarray:
    near = np.zeros(T, bool)
    for t in steps:
        near[t : t + window + 1] = True
    return near


def _within(steps, T: int) -> tuple[int, ...]:
    """The intervention steps a ``T``-step trajectory reaches."""
    return tuple(t for t in steps if t < T)


def declaration_quality(flags, steps=cd.INTERVENTION_STEPS, window=HIT_WINDOW):
    """Hits, false alarms, precision and delay of detections ``flags (..., n, T)``.

    Leading axes are independent settings; every entry of the result has their shape
    (``()`` for a 2-D ``flags``). Windows must not overlap; intervention steps at or past
    ``T`` are left out. ``precision`` and
    ``mean_delay_steps`` are NaN without detections resp. hits;
    ``f1 = 2 hits / (detections + interventions)``.
    """
    flags = np.asarray(flags, bool)
    n, T = flags.shape[-2:]
    steps = _within(steps, T)
    starts = sorted(steps)
    if any(b - a <= window for a, b in itertools.pairwise(starts)):
        raise ValueError("hit windows of the interventions overlap")
    near = [flags[..., t : t + window + 1] for t in steps]
    hit = np.stack([w.any(-1) for w in near], -1)  # (..., n, S)
    first = np.stack([w.argmax(-1) for w in near], -1)
    hits = hit.sum((-2, -1))
    declared = flags.sum((-2, -1))
    total = n * len(steps)
    outside = ~_windows(T, steps, window)
    with np.errstate(invalid="ignore", divide="ignore"):
        precision = np.where(declared > 0, hits / declared, np.nan)
        delay = np.where(hits > 0, np.sum(first * hit, (-2, -1)) / hits, np.nan)
    return {
        "hit_rate": hits / total,
        "false_alarms_per_100_steps": 100.0 * (declared - hits) / (n * T),
        "false_alarms_per_100_eligible_steps": 100.0
        * flags[..., outside].sum((-2, -1))
        / (n * max(int(outside.sum()), 1)),
        "precision": precision,
        "mean_delay_steps": delay,
        "f1": 2.0 * hits / (declared + total),
        "hit_rate_per_intervention": hit.mean(-2),
    }


def random_baseline(flag_rate: float, T: int, steps=cd.INTERVENTION_STEPS, window=HIT_WINDOW):
    """Expected scores of a detector flagging each of ``T`` steps independently with
    probability ``flag_rate``: hit rate ``1 - (1 - r)^(window + 1)``, false alarms per 100
    eligible steps ``100 r``, precision expected hits over expected flags."""
    r = float(flag_rate)
    hit = 1.0 - (1.0 - r) ** (window + 1)
    return {
        "flag_rate": r,
        "hit_rate": hit,
        "precision": len(steps) * hit / (r * T) if r > 0 else float("nan"),
        "false_alarms_per_100_eligible_steps": 100.0 * r,
    }


def push_detection_bound(fa_per_step: float, push_snr: float, window: int = HIT_WINDOW) -> float:
    """The highest hit rate of any detector of a one-period push of ``push_snr`` standard
    deviations of the disturbance force, at ``fa_per_step`` false alarms per eligible step.

    The detector is given everything: the true dynamics, the disturbance's distribution and
    the push's direction. The states are exact, so the force of every step (the input, the
    disturbance and the push) is read from one transition; the push is then a shift of
    ``push_snr`` in one standard normal draw, and the most powerful test at level ``a``
    (Neyman-Pearson) flags ``e > Phi^-1(1 - a)``: it hits at the push's step with
    ``Phi(push_snr - Phi^-1(1 - a))``, and at one of the ``window`` steps after it by chance
    (rate ``a`` each). A detector that does not know the direction, or the dynamics, hits
    less. Left out: the interventions' mass change, whose own signal at the testbed's
    forces is about a tenth of a standard deviation per step."""
    a = float(fa_per_step)
    if not 0.0 < a < 1.0:
        return 1.0 if a >= 1.0 else 0.0
    n = NormalDist()
    at_push = n.cdf(push_snr - n.inv_cdf(1.0 - a))
    return 1.0 - (1.0 - at_push) * (1.0 - a) ** window


def changepoint_quality(
    flags: np.ndarray,
    steps=cd.INTERVENTION_STEPS,
    window=HIT_WINDOW,
    push_snr: float | None = None,
):
    """:func:`declaration_quality` of ``flags (n, T)`` as plain floats, with the hit rate
    per intervention step, the :func:`random_baseline` at the same flag rate and, given the
    push in standard deviations of the disturbance (``push_snr``, a one-period push), the
    :func:`push_detection_bound` at the same false-alarm rate."""
    flags = np.asarray(flags, bool)
    steps = _within(steps, flags.shape[-1])
    q = declaration_quality(flags, steps, window)
    out = {k: float(v) for k, v in q.items() if k != "hit_rate_per_intervention"}
    out["hit_rate_per_intervention"] = {
        str(t): float(h) for t, h in zip(steps, q["hit_rate_per_intervention"])
    }
    out["random_baseline"] = random_baseline(float(flags.mean()), flags.shape[-1], steps, window)
    if push_snr is not None:
        fa = out["false_alarms_per_100_eligible_steps"] / 100.0
        out["known_dynamics_bound"] = {
            "push_snr": float(push_snr),
            "hit_rate": push_detection_bound(fa, push_snr, window),
        }
    return out


def hits_per_intervention(flags: np.ndarray, steps=cd.INTERVENTION_STEPS) -> dict[str, float]:
    """Hit rate of each intervention step alone (``{"40": 0.9, ...}``). The one at step 0
    has no earlier regime: the beam starts from the offline prior, which is already what
    a changepoint at step 0 would restart from, tempered."""
    return changepoint_quality(flags, steps)["hit_rate_per_intervention"]


def quality_line(label: str, q: dict[str, Any]) -> str:
    """One sentence: hit rate, precision, false alarms and the random detector's scores."""
    rb = q["random_baseline"]

    def pct(v):
        return "n/a" if v is None or not np.isfinite(v) else f"{v:.0%}"

    bound = q.get("known_dynamics_bound")
    return (
        f"{label}: hit rate within {HIT_WINDOW} steps {q['hit_rate']:.0%} (per intervention "
        + ", ".join(f"step {k} {v:.0%}" for k, v in q["hit_rate_per_intervention"].items())
        + f"), precision {pct(q['precision'])}, false alarms "
        f"{q['false_alarms_per_100_eligible_steps']:.2f} per 100 eligible steps; a random "
        f"detector at the same flag rate ({rb['flag_rate']:.3f}/step): hit rate "
        f"{rb['hit_rate']:.0%}, precision {pct(rb['precision'])}"
        + (
            f"; a detector of the push that knows the true dynamics, the disturbance and "
            f"the push's direction hits at most {bound['hit_rate']:.0%} at that false-alarm "
            f"rate (the push: {bound['push_snr']:g} standard deviations of the disturbance "
            "force, one period)."
            if bound
            else "."
        )
    )


def detection_summary(d: dict[str, Any] | None) -> str:
    """One sentence on the detection-tuned row (:func:`detection_tuning`)."""
    if not d:
        return "Detection-tuned Ours: not run."
    goal = f"at least {d['min_hit_rate']:.0%} of the tuning trajectories' interventions"
    if d["chosen"] is None:
        return f"Detection-tuned Ours: no (beta, pi, tau^2) setting of the grid detects {goal}."
    c, q = d["chosen"], d["changepoints"]
    per = q.get("hit_rate_per_intervention", d.get("hit_rate_per_intervention", {}))
    precision = q.get("precision")
    return (
        f"Detection-tuned Ours (lowest tuning CRMSE among the settings that detect {goal}): "
        f"beta = {c['beta']:g}, pi = {c['pi']:g}"
        + (f", tau^2 = {c['tau2']:g}" if "tau2" in c else "")
        + "; on the evaluation trajectories hit rate "
        f"{q['hit_rate']:.0%}"
        + (" (" + ", ".join(f"step {k} {v:.0%}" for k, v in per.items()) + ")" if per else "")
        + (f", precision {precision:.0%}" if precision is not None else "")
        + f", false alarms {q['false_alarms_per_100_steps']:.2f} per 100 steps, mean delay "
        f"{q['mean_delay_steps']:.2f} steps; its CRMSE is the `ours_detection_tuned` row."
    )
