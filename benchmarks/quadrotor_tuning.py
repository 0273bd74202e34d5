"""Tuning of the closed-loop quadrotor evaluation's adaptive methods (``arcade eval
quadrotor``; the protocol in :mod:`benchmarks.quadrotor_closedloop`, "Tuning").

Every adaptive method's knobs are chosen on a cell and seeds the evaluation does not fly,
by coordinate descent over small grids, each grid extended past an edge its best value
lies on (:func:`tune`). The flagship is tuned for tracking subject to its smoothness
requirement: its thrust increments at most :data:`FLAGSHIP_THRUST_RATIO` times L1's on the
same tuning flights (issue of the flagship controller: a target beside the tracking).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from arcade_control.knobs import EVAL_METHODS, FLAGSHIP, TUNED_DEFAULTS, TUNING_METHOD
from arcade_control.scenario import Scenario
from benchmarks.eval_progress import Progress
from benchmarks.quadrotor_flights import Runner

#: Tuning cell and seeds (not one of the evaluation cells or seeds), and the grids: the
#: adaptation-rate knob of each adaptive method (:mod:`benchmarks.quadrotor_closedloop`,
#: "Tuning").
TUNING_CELL = (150.0, 2.0)
#: Four flights: with two, ours' two best noise variances swapped places from one CPU's
#: rounding to another's (docs/quadrotor-closed-loop.md, "Tuning flights").
TUNING_SEEDS = (999, 998, 997, 996)  # score: mean RMSE over these flights
TUNING_GRIDS = {
    "ours_beta": (0.997, 0.9, 0.5, 0.2, 0.05),
    "ours_sigma2": (0.1, 0.01, 0.001, 0.0001),
    "gp_noise_scale": (1.0, 0.1, 0.01, 0.001),
    "mlp_lr": (1e-4, 1e-3, 1e-2, 1e-1, 1.0),
    "l1_cutoff": (2.5, 5.0, 10.0, 20.0, 40.0, 80.0),
    "l1_cutoff_rates": (0.0, 5.0, 10.0, 20.0, 40.0, 80.0),  # 0: rate channel not applied
    "l1_a_s": (-5.0, -2.0, -1.0, -0.5, -0.2, -0.1, -0.05),
    "ours_matched_beta": (0.997, 0.9, 0.5, 0.2, 0.05),
    "ours_matched_sigma2": (0.1, 0.01, 0.001, 0.0001),
    # The flagship: its learner's knobs (forgetting factor; sigma^2 one step past the
    # Appendix D value), then its thrust augmentation's, on L1's grids.
    "arcade_lambda": (0.8, 0.9, 0.95, 0.97, 0.98, 0.99, 0.995, 0.999),
    "arcade_restart_scale": (1.0, 0.1, 0.01, 0.001),
    "arcade_sigma2": (10.0, 1.0, 0.1, 0.01, 0.001, 0.0001, 0.00001),
    "arcade_l1_cutoff": (2.5, 5.0, 10.0, 20.0, 40.0, 80.0, 160.0),
    "arcade_l1_a_s": (-5.0, -2.0, -1.0, -0.5, -0.2, -0.1, -0.05, -0.02),
}
#: Where :func:`tune` starts: the presets (Appendix D ``sigma^2 = 0.1``, the GP's
#: marginal-likelihood noise, L1 on the thrust channel only) and a middle value of the
#: other grids; see :func:`tune` for the order and the passes.
TUNING_START = {
    "ours_beta": 0.05,
    "ours_sigma2": 0.1,
    "gp_noise_scale": 1.0,
    "mlp_lr": 0.1,
    "l1_cutoff": 40.0,
    "l1_cutoff_rates": 0.0,
    "l1_a_s": -2.0,
    "ours_matched_beta": 0.05,
    "ours_matched_sigma2": 0.1,
    "arcade_lambda": 0.98,
    "arcade_restart_scale": 0.01,
    "arcade_sigma2": 0.1,
    "arcade_l1_cutoff": 40.0,
    "arcade_l1_a_s": -2.0,
}
MAX_TUNING_PASSES = 4
#: The flagship's smoothness requirement, a constraint of its tuning: on the tuning
#: flights its thrust increments (RMS of the change from one control period to the next)
#: at most this many times those of L1 at L1's knobs of the moment.
FLAGSHIP_THRUST_RATIO = 1.5
#: Values added, one at a time, below / above a grid whose lowest / highest value scores
#: best (:func:`tune`), in this order, within each knob's range: ``beta`` and ``lambda`` in
#: (0, 1], noise variances and bandwidths positive, the predictor pole ``a_s`` negative,
#: the rate channel's bandwidth not below 0 ("off"). The low-pass filters are exact
#: discretisations (``1 - exp(-cutoff dt)``): past a few hundred rad/s they pass the
#: estimate through in one 20 ms period, so their extensions end there; likewise the
#: poles, whose law settles at ``exp(a_s T_s)`` of a constant disturbance, within 1e-4 of
#: all of it at -0.005.
TUNING_EXTENSIONS = {
    "ours_beta": ((0.02, 0.01, 0.005), (0.999,)),
    "ours_sigma2": ((1e-5, 1e-6, 1e-7), (1.0, 10.0)),
    "gp_noise_scale": ((1e-4, 1e-5), (10.0, 100.0)),
    "mlp_lr": ((1e-5, 1e-6), (3.0, 10.0)),
    "l1_cutoff": ((1.0, 0.5), (160.0, 320.0, 640.0)),
    "l1_cutoff_rates": ((), (160.0, 320.0, 640.0)),
    "l1_a_s": ((-10.0, -20.0), (-0.02, -0.01, -0.005)),
    "ours_matched_beta": ((0.02, 0.01, 0.005), (0.999,)),
    "ours_matched_sigma2": ((1e-5, 1e-6, 1e-7), (1.0, 10.0)),
    "arcade_lambda": ((0.7, 0.6, 0.5, 0.4, 0.3, 0.2), (0.9995, 1.0)),
    "arcade_restart_scale": ((1e-4, 1e-5), (3.0, 10.0, 30.0, 100.0, 300.0, 1000.0)),
    "arcade_sigma2": ((1e-6, 1e-7), (100.0, 1000.0, 10000.0)),
    "arcade_l1_cutoff": ((1.0, 0.5), (320.0, 640.0)),
    "arcade_l1_a_s": ((-10.0, -20.0), (-0.01, -0.005, -0.002)),
}


def beyond_edge(knob: str, grid: Sequence[float], best: float) -> float | None:
    """The next value of :data:`TUNING_EXTENSIONS` past the edge of ``grid`` that ``best``
    lies on (its lowest or highest value); ``None`` when ``best`` is inside the grid or the
    knob's range has no value left on that side."""
    lo, hi = min(grid), max(grid)
    if best not in (lo, hi) or lo == hi:
        return None
    below, above = TUNING_EXTENSIONS[knob]
    past = [v for v in below if v < lo] if best == lo else [v for v in above if v > hi]
    return past[0] if past else None


def tune(
    models,
    progress: Callable[[str], None] = lambda msg: None,
    runner: Runner | None = None,
    methods: Sequence[str] = EVAL_METHODS,
    command_delay_s: float = 0.0,
    compensate_delay: bool = False,
    estimated: bool = False,
    hand_set: dict[str, float] | None = None,
    done: Progress | None = None,
) -> dict[str, Any]:
    """Pick the adaptive methods' knobs on the tuning cell (the flights of
    :data:`TUNING_SEEDS` per grid value, lowest mean tracking RMSE wins; crashes are
    infinite) and store the choice on ``models.closedloop``.

    Ours: the temperature ``beta`` (Appendix D: 0.997, also in the grid), then the noise
    variance ``sigma^2`` of the online regression (Appendix D: 0.1, also in the grid);
    GP-MPC: a factor on its noise variances; MLP-MPC: the SGD learning rate; L1: the
    low-pass bandwidth of the thrust channel, then of the rate channel (``0``: the rate
    correction is not applied, L1 on thrust alone), then the predictor pole ``a_s``. The
    flagship (``arcade``): its learner's forgetting factor, restart scale and noise,
    then its L1 augmentation's bandwidth and pole, for the lowest RMSE among the
    settings whose mean thrust increments are at most :data:`FLAGSHIP_THRUST_RATIO`
    times L1's at L1's knobs of the moment, on the same flights (L1 is flown at its
    knobs for that reference if it is not tuned in the run); a knob none of whose values
    meets the bound takes the value nearest to it. ``flagship_thrust`` records the
    reference, the choice's thrust increments and each value's. Knobs are tuned one
    after the other from :data:`TUNING_START` (coordinate descent), in passes over all
    knobs until a pass changes none (at most :data:`MAX_TUNING_PASSES`): a knob tuned
    first is tuned again at the others' choice, so the result does not hinge on the
    order. A knob whose best value is an edge of its grid has the grid extended past
    that edge (:data:`TUNING_EXTENSIONS`, one value at a time) until the best lies
    inside or the knob's range is exhausted; ``grids`` holds the grids as flown,
    ``extended`` the values added and ``still_on_edge`` the knobs whose choice is still
    an edge. ``rmse_m`` holds each knob's scores in the last pass, ``rmse_m_by_pass`` in
    every pass. The nominal MPC has nothing to tune. Only the knobs of ``methods`` are
    tuned; the others keep their :data:`TUNED_DEFAULTS`. ``command_delay_s``: the tuning
    flights' setpoint delay (:class:`Scenario`), compensated by the methods with
    ``compensate_delay``; ``estimated``: the methods fly on the state estimate
    (:meth:`Runner.fly`); ``hand_set``: knobs set by hand for the condition, over
    :data:`TUNED_DEFAULTS` (:class:`~benchmarks.quadrotor_protocol.Condition`);
    ``done``: the scores an interrupted run of the same settings flew, read back instead
    of flown again, and where each new score is kept (:mod:`benchmarks.eval_progress`).
    """
    runner = runner or Runner(models)
    scen = Scenario(*TUNING_CELL, command_delay_s=command_delay_s)
    grids = {k: g for k, g in TUNING_GRIDS.items() if TUNING_METHOD[k] in methods}
    knobs_by_method: dict[str, list[str]] = {}
    for knob in grids:
        knobs_by_method.setdefault(TUNING_METHOD[knob], []).append(knob)
    # (method, its knob values) -> (mean RMSE, mean thrust increments); flights are seeded
    flown: dict[tuple, tuple[float, float]] = {}

    def key_of(method: str, setting: dict[str, float]) -> tuple:
        return (method, *(setting[k] for k in knobs_by_method.get(method, ())))

    def fly(method: str, setting: dict[str, float], what: str) -> tuple[float, float]:
        key = key_of(method, setting)
        part = f"tuning {json.dumps(key)}"
        kept = done.get(part) if done is not None and key not in flown else None
        if kept is not None:
            flown[key] = tuple(kept)
            progress(f"tuning {method}: {what} (flown before: read back)")
        if key not in flown:
            previous, models.closedloop = models.closedloop, setting
            progress(f"tuning {method}: {what}")
            flights = runner.fly_trials(
                method, scen, TUNING_SEEDS, estimated=estimated, compensate_delay=compensate_delay
            )
            metrics = [f.metrics for f in flights]
            models.closedloop = previous
            flown[key] = (
                float(np.mean([m["rmse_m"] for m in metrics])),
                float(np.mean([m["thrust_increment_rms_n"] for m in metrics])),
            )
            if done is not None:
                done.put(part, list(flown[key]))
        return flown[key]

    def l1_thrust() -> float:
        """L1's thrust increments at its knobs of the moment (the flagship's reference)."""
        return fly("l1", models.closedloop, "its thrust increments, the flagship's reference")[1]

    def score(knob: str, value: float) -> tuple[int, float]:
        """``(0, RMSE)`` for a setting that may be chosen; the flagship's settings over its
        smoothness bound score ``(1, their excess over it)`` (chosen only when no setting
        of that knob meets it: the least violation), crashes ``(1, inf)``."""
        method = TUNING_METHOD[knob]
        rmse, thrust = fly(method, {**models.closedloop, knob: value}, f"{knob} = {value:g}")
        if method == FLAGSHIP:
            excess = thrust - FLAGSHIP_THRUST_RATIO * l1_thrust()
            if not (math.isfinite(rmse) and excess <= 0.0):
                return (1, excess if math.isfinite(excess) else math.inf)
        return (0, rmse) if math.isfinite(rmse) else (1, math.inf)

    start = {k: TUNING_START[k] for k in grids}
    models.closedloop = {**TUNED_DEFAULTS, **(hand_set or {}), **start}
    by_pass: list[dict[str, dict[str, float]]] = []
    extended: dict[str, list[float]] = {}
    thrust: dict[str, dict[str, float]] = {}  # the flagship's knobs, last pass
    while len(by_pass) < MAX_TUNING_PASSES:
        changed = False
        table = {}
        for knob in grids:
            scores = {value: score(knob, value) for value in grids[knob]}
            best = min(scores, key=scores.get)
            # A best value on an edge of the grid: the grid grows past it, one value at a
            # time, until the best lies inside or the knob's range is exhausted.
            while scores[best][0] == 0 and (
                (more := beyond_edge(knob, grids[knob], best)) is not None
            ):
                progress(f"tuning {TUNING_METHOD[knob]}: best {knob} on the grid's edge")
                grids[knob] = (*grids[knob], more)
                extended.setdefault(knob, []).append(more)
                scores[more] = score(knob, more)
                best = min(scores, key=scores.get)
            changed |= best != models.closedloop[knob]
            models.closedloop = {**models.closedloop, knob: best}
            method = TUNING_METHOD[knob]
            of = {v: flown[key_of(method, {**models.closedloop, knob: v})] for v in scores}
            table[knob] = {f"{v:g}": rmse for v, (rmse, _) in of.items()}
            if method == FLAGSHIP:
                thrust[knob] = {f"{v:g}": inc for v, (_, inc) in of.items()}
        by_pass.append(table)
        if not changed:
            break
    chosen = {k: models.closedloop[k] for k in grids}
    return {
        "chosen": chosen,
        "grids": {k: list(g) for k, g in grids.items()},
        "extended": extended,
        "still_on_edge": sorted(
            k for k, g in grids.items() if chosen[k] in (min(g), max(g)) and len(g) > 1
        ),
        "rmse_m": by_pass[-1],
        **(
            {
                "flagship_thrust": {
                    "max_ratio_to_l1": FLAGSHIP_THRUST_RATIO,
                    "l1_thrust_increment_rms_n": l1_thrust(),
                    "chosen_thrust_increment_rms_n": flown[key_of(FLAGSHIP, models.closedloop)][1],
                    "thrust_increment_rms_n": thrust,
                }
            }
            if thrust
            else {}
        ),
        "cell": list(TUNING_CELL),
        "seeds": list(TUNING_SEEDS),
        "passes": len(by_pass),
        "rmse_m_by_pass": by_pass,
    }
