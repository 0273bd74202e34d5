"""The closed-loop evaluation's two conditions and its paired comparison with L1.

Conditions (``arcade eval quadrotor --condition``), every method tuned and flown in the one
it is evaluated in:

- ``ideal``: the controller sees the simulator's true state at the control instant and its
  setpoint reaches the rate loop at once (the paper's setting, Sec. V-B);
- ``stack``: what the service stack flies: the estimator's state (motion-capture noise and
  latency, :class:`benchmarks.quadrotor_flights.MocapEstimate`), and a 20 ms
  controller-to-rate-loop delay (the simulated PX4 link's) that every method compensates
  as ``arcade up --link-delay`` does (:func:`arcade_control.step.make_controller_step`'s
  ``delay_s``).

Paired comparison: the trials of a cell fly the same seeds for every method (sensor noise,
start offset, release jitter), so each method's RMSE is compared with L1's trial by trial:
the mean of the paired differences and its 95 % bootstrap confidence interval (BCa,
:func:`scipy.stats.bootstrap`). A method is better than L1 in a cell when the whole
interval lies below zero.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from arcade_control.knobs import STACK_METHODS, TUNED_DEFAULTS
from arcade_control.stack import STACK_ARCADE_KNOBS, stack_knobs

#: The setpoint delay of the simulated PX4 chain [s] (``actuation_delay`` in
#: ``stats/px4sim.json``: median 15-20 ms per flight), compensated as ``arcade up
#: --link-delay`` does.
LINK_DELAY_S = 0.02
#: Bootstrap resamples of the paired confidence intervals, and their seed (reproducible).
BOOTSTRAP_RESAMPLES = 9999
BOOTSTRAP_SEED = 0


class Condition(NamedTuple):
    """How a flight of one condition is flown (:meth:`Runner.fly`'s arguments), and the
    knobs set by hand for it (not tuned: what the stack flies in that condition)."""

    command_delay_s: float
    estimated: bool
    compensate_delay: bool
    hand_set: tuple[tuple[str, float], ...] = ()


CONDITIONS = {
    "ideal": Condition(command_delay_s=0.0, estimated=False, compensate_delay=False),
    "stack": Condition(
        command_delay_s=LINK_DELAY_S,
        estimated=True,
        compensate_delay=True,
        # The flagship's thrust smoothness as the stack flies it (the tuning scores RMSE).
        hand_set=(("arcade_thrust_smooth", STACK_ARCADE_KNOBS["arcade_thrust_smooth"]),),
    ),
}


def stored_knobs(name: str) -> dict[str, float]:
    """The knobs stored for condition ``name``, what ``arcade eval quadrotor
    --stored-knobs`` flies instead of tuning: the evaluation's (:data:`TUNED_DEFAULTS`,
    tuned on the true state); in the stack's condition, the knobs the service stack flies
    (:func:`arcade_control.stack.stack_knobs` of ours, L1 and the flagship, tuned in that
    condition), over those."""
    condition(name)
    knobs = dict(TUNED_DEFAULTS)
    if name == "stack":
        for method in STACK_METHODS:
            knobs.update(stack_knobs(method))
    return {**knobs, **dict(condition(name).hand_set)}


def condition(name: str) -> Condition:
    """The condition called ``name`` (one of :data:`CONDITIONS`)."""
    if name not in CONDITIONS:
        raise ValueError(f"unknown condition {name!r} (one of {', '.join(CONDITIONS)})")
    return CONDITIONS[name]


def paired_ci(diff: Sequence[float]) -> tuple[float, float]:
    """95 % bootstrap confidence interval of the mean of paired differences ``diff``
    (BCa; a single difference, or all equal: the value itself at both ends)."""
    d = np.asarray(diff, float)
    if d.size < 2 or np.all(d == d[0]):
        return float(d.mean()), float(d.mean())
    from scipy.stats import bootstrap

    res = bootstrap(
        (d,),
        np.mean,
        confidence_level=0.95,
        n_resamples=BOOTSTRAP_RESAMPLES,
        method="BCa",
        random_state=np.random.default_rng(BOOTSTRAP_SEED),
    )
    lo, hi = res.confidence_interval
    return float(lo), float(hi)


def paired_differences(
    per_trial: list[dict[str, Any]], vs: str = "l1", key: str = "rmse_m"
) -> list[dict[str, Any]]:
    """Every method's ``key`` against ``vs``'s, trial by trial, per cell: ``[{payload_g,
    speed_mps, method, vs, n, diff_mean_m, ci95_m: [lo, hi], better}, ...]`` (``better``:
    the interval lies below zero). A trial that crashed (non-finite value) for either
    method makes the difference infinite: the mean and the interval say so."""
    by: dict[tuple[float, float, str], dict[int, float]] = {}
    for t in per_trial:
        by.setdefault((t["payload_g"], t["speed_mps"], t["method"]), {})[t["trial"]] = float(
            t[key] if t[key] is not None else np.inf
        )
    out = []
    for (pay, speed, method), values in by.items():
        ref = by.get((pay, speed, vs))
        if method == vs or ref is None:
            continue
        trials = sorted(set(values) & set(ref))
        if not trials:
            continue
        diff = np.array([values[k] - ref[k] for k in trials])
        if np.all(np.isfinite(diff)):
            mean, (lo, hi) = float(diff.mean()), paired_ci(diff)
        else:
            mean = lo = hi = float("inf")
        out.append(
            {
                "payload_g": pay,
                "speed_mps": speed,
                "method": method,
                "vs": vs,
                "n": len(trials),
                "diff_mean_m": mean,
                "ci95_m": [lo, hi],
                "better": bool(hi < 0.0),
            }
        )
    return out


def format_paired(paired: list[dict[str, Any]]) -> list[str]:
    """The paired differences as text lines (mm), one per cell and method."""
    lines = ["Paired RMSE difference to L1 (mm, mean and 95 % CI; negative: better than L1):"]
    for p in sorted(paired, key=lambda p: (p["method"], p["payload_g"], p["speed_mps"])):
        lo, hi = p["ci95_m"]
        mark = "better" if p["better"] else ("worse" if lo > 0.0 else "tie")
        lines.append(
            f"  {p['method']:12s} {p['payload_g']:5g} g {p['speed_mps']:4g} m/s: "
            f"{1e3 * p['diff_mean_m']:+7.2f} [{1e3 * lo:+7.2f}, {1e3 * hi:+7.2f}] {mark}"
        )
    return lines
