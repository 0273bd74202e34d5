"""``arcade bench variants``: ours beside variants that are not the paper's method.

Flies L1, ours and every :data:`arcade_control.knobs.VARIANTS` method on the
nine cells of the closed-loop evaluation (same scenario, seeds and metrics as
``arcade eval quadrotor``), each tuned on the tuning cell in the same run
(:func:`benchmarks.quadrotor_closedloop.tune`). Only the shipped VLD weights are needed,
no baseline is trained. ``ours_matched``
(:func:`arcade_control.methods.beam_method`) asks what the swinging payload's
unmatched pull costs ours: the regression gets an intercept feature and the MPC plans
with the part of the learned residual that the collective thrust can cancel, the
structural assumption of the L1 augmentation. ``docs/quadrotor-closed-loop.md`` reads the
results.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Sequence
from types import SimpleNamespace
from typing import Any, NamedTuple

from arcade_io import jsonout
from benchmarks import quadrotor_tuning as qt
from benchmarks.common import machine
from benchmarks.quadrotor_protocol import LINK_DELAY_S

METHODS = ("l1", "ours")


def _progress(msg: str) -> None:
    print(f"[variants] {msg}", file=sys.stderr, flush=True)


def models() -> SimpleNamespace:
    """The shipped VLD and its guard: all that L1, ours and the variants need."""
    from arcade.training_quadrotor import QUADROTOR_WEIGHTS, load_quadrotor
    from arcade_control.guard import guard_from_metadata
    from arcade_io.weights import load_model

    vld = load_quadrotor()
    guard = guard_from_metadata(load_model(QUADROTOR_WEIGHTS)[2])
    return SimpleNamespace(vld=vld, guard=guard, closedloop={})


def run(quick: bool = False, trials: int | None = None) -> dict[str, Any]:
    """``quick``: one trial of two cells with the stored knobs (no tuning flights)."""
    from arcade_control.knobs import VARIANTS
    from benchmarks import quadrotor_closedloop as qc

    methods = (*METHODS, *VARIANTS)
    cells = [(175.0, 0.5), (75.0, 2.5)] if quick else None
    t0 = time.perf_counter()
    r = qc.run_closedloop(
        trials=1 if quick else (trials or 10),
        methods=methods,
        cells=cells,
        models=models(),
        tuning=not quick,
        progress=_progress,
    )
    best: dict[tuple[float, float], dict[str, Any]] = {}
    for c in r["cells"]:
        key = (c["payload_g"], c["speed_mps"])
        if key not in best or c["rmse_m"] < best[key]["rmse_m"]:
            best[key] = c
    return {
        "generated": time.strftime("%Y-%m-%d %H:%M"),
        "machine": machine(),
        "methods": list(methods),
        "cells": r["cells"],
        "lowest_rmse": [
            {"payload_g": p, "speed_mps": s, "method": c["method"]} for (p, s), c in best.items()
        ],
        "tuned": r["settings"]["tuned"],
        "tuning": r["tuning"],
        "trials": r["settings"]["trials"],
        "wall_time_s": time.perf_counter() - t0,
    }


#: The ablation of ``ours_matched``'s two changes: method and knobs (``models.closedloop``).
#: ``ours_matched`` here with ``beta = 0.05``, ``sigma^2 = 1e-3``, knobs picked by looking at
#: evaluation cells (``docs/quadrotor-closed-loop.md`` says so): the split, not a result.
ABLATION = (
    ("l1", {}),
    ("ours", {}),
    ("ours_intercept", {"ours_sigma2": 1e-3}),
    ("ours_thrust_axis", {}),
    ("ours_matched", {"ours_matched_beta": 0.05, "ours_matched_sigma2": 1e-3}),
)


def ablation(seeds: tuple[int, ...] = (0, 1, 2)) -> dict[str, Any]:
    """Mean RMSE per cell of :data:`ABLATION`, flown in process on ``seeds`` (no tuning:
    the stored knobs of :data:`arcade_control.knobs.TUNED_DEFAULTS` plus each
    row's overrides). ``python -m benchmarks.quadrotor_variants`` prints it (~7 min)."""
    from arcade_control.scenario import Scenario
    from benchmarks import quadrotor_closedloop as qc
    from benchmarks.quadrotor_flights import Runner

    m = models()
    runner = Runner(m)
    t0 = time.perf_counter()
    rows = []
    for pay in qc.PAYLOADS_G:
        for speed in qc.SPEEDS_MPS:
            scen = Scenario(payload_g=pay, speed_mps=speed)
            row: dict[str, Any] = {"payload_g": pay, "speed_mps": speed}
            for name, knobs in ABLATION:
                m.closedloop = dict(knobs)
                row[name] = sum(runner.fly(name, scen, seed=sd).metrics["rmse_m"] for sd in seeds)
                row[name] /= len(seeds)
            rmse = " ".join(f"{n} {row[n]:.4f}" for n, _ in ABLATION)
            _progress(f"{pay:g} g, {speed:g} m/s: RMSE {rmse}")
            rows.append(row)
    return {
        "machine": machine(),
        "seeds": list(seeds),
        "methods": [{"method": n, "knobs": k} for n, k in ABLATION],
        "rows": rows,
        "wall_time_s": time.perf_counter() - t0,
    }


def oracle(trials: int = 10) -> dict[str, Any]:
    """L1, ours and the mass oracle (:func:`arcade_control.methods.oracle_mass_method`:
    the payload's mass and the release step known exactly) side by side, in process, on
    the nine cells with the evaluation's seeds ``0 .. trials-1`` and the stored knobs:
    mean RMSE, z-RMSE and settling time per cell (~10 min on a 2-core CPU)."""
    from arcade_control.knobs import ORACLE

    names = ("l1", "ours", ORACLE)
    t0 = time.perf_counter()
    rows = _cell_means(
        [(n, n, {}, False) for n in names], trials, ("rmse_m", "rmse_z_m", "settling_s")
    )
    return {
        **_run_header(trials),
        "methods": list(names),
        "rows": rows,
        "wall_time_s": time.perf_counter() - t0,
    }


def _run_header(trials: int) -> dict[str, Any]:
    """When, where and with how many trials a stored diagnostic run was flown."""
    return {"generated": time.strftime("%Y-%m-%d %H:%M"), "machine": machine(), "trials": trials}


def _tuning_flights() -> dict[str, Any]:
    """The tuning cell and its seeds, as a stored run records the flights it scored there."""

    return {"cell": list(qt.TUNING_CELL), "seeds": list(qt.TUNING_SEEDS)}


#: Per-cell means of the runs on the state estimate.
ESTIMATE_KEYS = ("rmse_m", "rmse_z_m", "settling_s", "changepoint_rate")


class Flown(NamedTuple):
    """One row of :func:`_cell_means`: its name, the method and its knobs
    (``models.closedloop`` overrides of the stored ones), the state it flies on (``False``:
    the ground-truth state; ``True``: the state estimate with the estimator's defaults; a
    :class:`arcade_core.estimation.FilterConfig`: the estimate with those settings), the
    setpoints' transport delay (:class:`arcade_control.scenario.Scenario`) and
    whether the method compensates it (``Runner.fly``'s ``compensate_delay``)."""

    name: str
    method: str
    knobs: dict[str, Any]
    state: Any = False
    command_delay_s: float = 0.0
    compensate_delay: bool = False


def _cell_means(
    flown: Sequence[Sequence[Any]], trials: int, keys: tuple[str, ...]
) -> list[dict[str, Any]]:
    """One row per cell of the evaluation: for each :class:`Flown` row of ``flown`` (or a
    tuple of its fields), the mean of ``keys`` over the evaluation's seeds
    ``0 .. trials-1`` (:meth:`benchmarks.quadrotor_flights.Runner.fly`)."""
    from arcade_control.scenario import Scenario
    from benchmarks import quadrotor_closedloop as qc
    from benchmarks.quadrotor_flights import Runner

    m = models()
    runners: dict[Any, Runner] = {}
    rows = []
    flown = [Flown(*f) for f in flown]
    for pay in qc.PAYLOADS_G:
        for speed in qc.SPEEDS_MPS:
            row: dict[str, Any] = {"payload_g": pay, "speed_mps": speed}
            for f in flown:
                scen = Scenario(pay, speed, command_delay_s=f.command_delay_s)
                m.closedloop = dict(f.knobs)
                config = None if isinstance(f.state, bool) else f.state
                if config not in runners:
                    runners[config] = Runner(m, filter_config=config)
                flights = [
                    runners[config]
                    .fly(
                        f.method,
                        scen,
                        seed=sd,
                        estimated=f.state is not False,
                        compensate_delay=f.compensate_delay,
                    )
                    .metrics
                    for sd in range(trials)
                ]
                row[f.name] = {k: sum(fl[k] for fl in flights) / trials for k in keys}
            rmse = " ".join(f"{f.name} {row[f.name]['rmse_m']:.4f}" for f in flown)
            _progress(f"{pay:g} g, {speed:g} m/s: RMSE {rmse}")
            rows.append(row)
    return rows


#: The service stack's adapter knobs (:func:`arcade_control.stack.stack_knobs`: the calibrated
#: ``sigma^2 = 0.1``, ``beta = 0.05``): ``ours_stack`` flies ours with them.
STACK_KNOBS = {"ours_sigma2": 0.1, "ours_beta": 0.05}

#: Flown by :func:`estimated_state`: (row name, method, knobs, on the estimated state).
ESTIMATED_STATE = (
    ("l1", "l1", {}, False),
    ("l1_estimated", "l1", {}, True),
    ("ours", "ours", {}, False),
    ("ours_estimated", "ours", {}, True),
    ("ours_stack_estimated", "ours", STACK_KNOBS, True),
)


def estimated_state(trials: int = 3) -> dict[str, Any]:
    """L1 and ours on the ground-truth state (what ``arcade eval quadrotor`` flies) and on
    the state estimate from the emulated motion capture and gyro (what the service stack
    flies: :class:`benchmarks.quadrotor_flights.MocapEstimate`), in process, on the nine
    cells with the evaluation's seeds ``0 .. trials-1`` and the stored knobs, plus ours with
    the stack's knobs (:data:`ESTIMATED_STATE`): mean RMSE, z-RMSE, settling time and the
    changepoint rate per cell (~5 min on a 2-core CPU)."""
    t0 = time.perf_counter()
    rows = _cell_means(ESTIMATED_STATE, trials, ESTIMATE_KEYS)
    return {
        **_run_header(trials),
        "rows_flown": [
            {"name": n, "method": meth, "knobs": k, "estimated": e}
            for n, meth, k, e in ESTIMATED_STATE
        ],
        "rows": rows,
        "wall_time_s": time.perf_counter() - t0,
    }


#: Jerk densities of the estimator's constant-acceleration model tried on the tuning cell
#: [(m/s^3)^2 / Hz] (:func:`estimator_tuning`).
JERK_PSD_GRID = (100.0, 50.0, 30.0, 20.0, 10.0, 5.0, 3.0)
#: The hand-set jerk density the tuning replaced: the nine cells fly it beside the value
#: picked.
HAND_SET_JERK_PSD = 100.0
#: The adaptive methods the estimator is tuned for: (row name, method, knobs).
ESTIMATOR_METHODS = (("l1", "l1", {}), ("ours_stack", "ours", STACK_KNOBS))


def least_worst_loss(scores: dict[str, dict[float, float]]) -> float:
    """The grid value whose worst relative loss over the methods is smallest.

    ``scores[method][value]``: a score to minimise (the mean tracking RMSE). A method's
    loss at a value is its score there over its best score on the grid; the choice
    minimises the largest loss over the methods, so no method is sacrificed for another
    (one estimator serves every controller). Ties go to the larger value (less lag). A
    crashed setting scores ``inf``; a method that crashed at every value is an error."""
    values = sorted(next(iter(scores.values())), reverse=True)
    best = {m: min(s.values()) for m, s in scores.items()}
    for m, b in best.items():
        if not math.isfinite(b):
            raise ValueError(f"{m} has no finite score on the grid: nothing to tune")
    worst = {v: max(s[v] / best[m] for m, s in scores.items()) for v in values}
    return min(values, key=lambda v: worst[v])  # min keeps the first: the larger value


def estimator_tuning(trials: int = 3) -> dict[str, Any]:
    """The estimator's jerk density, tuned for the closed loop like every other knob.

    On the tuning cell (:data:`benchmarks.quadrotor_tuning.TUNING_CELL`, its four
    seeds), L1 and ours with the stack's knobs fly on the state estimate with each value of
    :data:`JERK_PSD_GRID`; :func:`least_worst_loss` picks the value. Then both fly the nine
    cells (the evaluation's seeds ``0 .. trials-1``, the stored knobs otherwise) with
    :data:`HAND_SET_JERK_PSD` and with the value picked, side by side: mean RMSE, z-RMSE,
    settling time and changepoint rate per cell (~6 min on a 2-core CPU)."""
    from arcade_control.scenario import Scenario
    from arcade_core import estimation
    from benchmarks.quadrotor_flights import Runner

    t0 = time.perf_counter()
    m = models()
    scen = Scenario(payload_g=qt.TUNING_CELL[0], speed_mps=qt.TUNING_CELL[1])
    scores: dict[str, dict[float, float]] = {name: {} for name, *_ in ESTIMATOR_METHODS}
    for psd in JERK_PSD_GRID:
        runner = Runner(m, filter_config=estimation.FilterConfig(jerk_psd=psd))
        for name, method, knobs in ESTIMATOR_METHODS:
            m.closedloop = dict(knobs)
            rmse = [
                runner.fly(method, scen, seed=sd, estimated=True).metrics["rmse_m"]
                for sd in qt.TUNING_SEEDS
            ]
            scores[name][psd] = sum(rmse) / len(rmse)
        _progress(
            f"tuning cell, jerk density {psd:g}: RMSE "
            + " ".join(f"{n} {scores[n][psd]:.4f}" for n in scores)
        )
    chosen = least_worst_loss(scores)
    default = estimation.FilterConfig().jerk_psd
    _progress(f"picked jerk density {chosen:g} (the estimator's default: {default:g})")
    flown = [
        (f"{name}@{psd:g}", method, knobs, estimation.FilterConfig(jerk_psd=psd))
        for name, method, knobs in ESTIMATOR_METHODS
        for psd in dict.fromkeys((HAND_SET_JERK_PSD, chosen))
    ]
    rows = _cell_means(flown, trials, ESTIMATE_KEYS)
    return {
        **_run_header(trials),
        "tuning": {
            **_tuning_flights(),
            "grid": list(JERK_PSD_GRID),
            "rmse_m": {n: [s[v] for v in JERK_PSD_GRID] for n, s in scores.items()},
            "chosen": chosen,
            "hand_set": HAND_SET_JERK_PSD,
            "default": default,
        },
        "rows_flown": [
            {"name": n, "method": meth, "knobs": k, "jerk_psd": c.jerk_psd}
            for n, meth, k, c in flown
        ],
        "rows": rows,
        "wall_time_s": time.perf_counter() - t0,
    }


#: Setpoint transport delays flown on the tuning cell [s] (:func:`command_delay`).
DELAY_GRID_S = (0.0, 0.01, 0.02, 0.03)
#: The delay the knobs are re-tuned at and the nine cells are flown with [s]: what the
#: simulated PX4 chain adds (99th percentile 25 ms).
PX4_LIKE_DELAY_S = LINK_DELAY_S
#: The methods of :func:`command_delay`: (row name, method, knobs) at the stored knobs.
DELAY_METHODS = (("l1", "l1", {}), ("ours", "ours", {}), ("ours_stack", "ours", STACK_KNOBS))


def _moved_knobs(
    chosen: dict[str, float], method: str, before: dict[str, float]
) -> dict[str, float] | None:
    """``method``'s knobs in a tuning's ``chosen`` if any differs from ``before``, else
    None (no re-tuned row to fly)."""
    from arcade_control.knobs import TUNING_METHOD

    knobs = {k: v for k, v in chosen.items() if TUNING_METHOD[k] == method}
    return knobs if any(knobs[k] != before[k] for k in knobs) else None


def command_delay(trials: int = 3) -> dict[str, Any]:
    """What a transport delay between the controller and the rate loop costs each method.

    The evaluation applies each setpoint at the instant of the state it was computed from;
    a real offboard link cannot (:class:`arcade_control.scenario.Scenario`'s
    ``command_delay_s``). On the tuning cell (its four seeds) L1, ours and ours with the
    stack's knobs fly with each delay of :data:`DELAY_GRID_S`, at the stored knobs. Then L1
    and ours are tuned again by the evaluation's protocol with :data:`PX4_LIKE_DELAY_S`,
    without and with compensating it (``_compensated``: learning and planning from the
    state predicted over the delay, ``Runner.fly``'s ``compensate_delay``), and the nine
    cells (the evaluation's seeds ``0 .. trials-1``) are flown without and with that
    delay: L1 and ours at the stored knobs, compensated at the stored knobs, and at the
    knobs re-tuned either way where they differ from the stored ones (``_retuned``).
    Mean RMSE, z-RMSE, settling time and changepoint rate per cell (~15 min on a 2-core
    CPU)."""
    from arcade_control.knobs import knobs_of
    from arcade_control.scenario import Scenario
    from benchmarks.quadrotor_flights import Runner

    t0 = time.perf_counter()
    m = models()
    runner = Runner(m)
    sensitivity: dict[str, list[float]] = {name: [] for name, *_ in DELAY_METHODS}
    for delay in DELAY_GRID_S:
        scen = Scenario(*qt.TUNING_CELL, command_delay_s=delay)
        for name, method, knobs in DELAY_METHODS:
            m.closedloop = dict(knobs)
            rmse = [runner.fly(method, scen, seed=sd).metrics["rmse_m"] for sd in qt.TUNING_SEEDS]
            sensitivity[name].append(sum(rmse) / len(rmse))
        _progress(
            f"tuning cell, delay {1e3 * delay:g} ms: RMSE "
            + " ".join(f"{n} {v[-1]:.4f}" for n, v in sensitivity.items())
        )
    tuned = {}
    for compensate in (False, True):
        m.closedloop = {}
        tuned[compensate] = qt.tune(
            m, _progress, runner, METHODS, PX4_LIKE_DELAY_S, compensate_delay=compensate
        )
    stored = knobs_of({}, METHODS)
    at = f"@{1e3 * PX4_LIKE_DELAY_S:g}ms"
    flown: list[Flown] = []
    for delay in (0.0, PX4_LIKE_DELAY_S):
        flown += [Flown(f"{meth}@{1e3 * delay:g}ms", meth, {}, False, delay) for meth in METHODS]
    for compensate, kind in ((False, ""), (True, "_compensated")):
        for meth in METHODS:
            if compensate:
                flown.append(Flown(f"{meth}{kind}{at}", meth, {}, False, PX4_LIKE_DELAY_S, True))
            retuned = _moved_knobs(tuned[compensate]["chosen"], meth, stored)
            if retuned is not None:
                name = f"{meth}{kind}_retuned{at}"
                flown.append(Flown(name, meth, retuned, False, PX4_LIKE_DELAY_S, compensate))
    rows = _cell_means(flown, trials, ESTIMATE_KEYS)
    return {
        **_run_header(trials),
        "sensitivity": {
            **_tuning_flights(),
            "delays_s": list(DELAY_GRID_S),
            "knobs": {n: knobs_of(k, (meth,)) for n, meth, k in DELAY_METHODS},
            "rmse_m": sensitivity,
        },
        "tuning": {"command_delay_s": PX4_LIKE_DELAY_S, "stored": stored, **tuned[False]},
        "tuning_compensated": tuned[True],
        "rows_flown": [f._asdict() for f in flown],
        "rows": rows,
        "wall_time_s": time.perf_counter() - t0,
    }


#: Setpoint delays of :func:`link_delay` [s]: none, the simulated PX4 link's, and beyond.
LINK_DELAYS_S = (0.0, 0.02, 0.03, 0.04)
#: Flown by :func:`link_delay`, on the state estimate: (name, method, knobs).
LINK_METHODS = (("ours_stack", "ours", STACK_KNOBS), ("l1", "l1", {}))


def link_delay(trials: int = 3) -> dict[str, Any]:
    """What the service stack flies behind a link that delays its setpoints, and what
    compensating the delay gives (``arcade up --link-delay``).

    Everything on the state estimate, as in the stack. First ours with the stack's adapter
    knobs and L1 at its stored knobs on the tuning cell (its four seeds) with each delay of
    :data:`LINK_DELAYS_S`, without and with compensation (``Runner.fly``'s
    ``compensate_delay``: the stack's controller and adapter given ``--link-delay``; at
    0 ms the two are one flight). Then L1 and ours tuned again by the evaluation's protocol
    in the stack's condition (the estimate, :data:`PX4_LIKE_DELAY_S`, compensated), and the
    nine cells (the evaluation's seeds ``0 .. trials-1``) in that condition: ours at the
    stack's knobs, L1 at its stored knobs, and each at its re-tuned knobs where they differ.
    Mean RMSE, z-RMSE, settling time and changepoint rate (~40 min on a 2-core CPU)."""
    from arcade_control.knobs import knobs_of
    from arcade_control.scenario import Scenario
    from benchmarks.quadrotor_flights import Runner

    t0 = time.perf_counter()
    m = models()
    runner = Runner(m)
    keys = ("rmse_m", "rmse_z_m", "changepoint_rate")
    sensitivity: dict[str, dict[str, list[float]]] = {}
    for name, method, knobs in LINK_METHODS:
        m.closedloop = dict(knobs)
        for delay in LINK_DELAYS_S:
            for compensate in (False, True):
                key = f"{name}_compensated" if compensate else name
                row = sensitivity.setdefault(key, {k: [] for k in keys})
                if compensate and delay == 0.0:  # nothing to compensate: the same flight
                    for k in keys:
                        row[k].append(sensitivity[name][k][-1])
                    continue
                scen = Scenario(*qt.TUNING_CELL, command_delay_s=delay)
                flights = [
                    runner.fly(
                        method, scen, seed=sd, estimated=True, compensate_delay=compensate
                    ).metrics
                    for sd in qt.TUNING_SEEDS
                ]
                for k in keys:
                    row[k].append(sum(f[k] for f in flights) / len(flights))
                _progress(f"{key}, delay {1e3 * delay:g} ms: RMSE {row['rmse_m'][-1]:.4f}")
    m.closedloop = {}
    tuning = qt.tune(
        m,
        _progress,
        runner,
        METHODS,
        PX4_LIKE_DELAY_S,
        compensate_delay=True,
        estimated=True,
    )
    at = f"_compensated@{1e3 * PX4_LIKE_DELAY_S:g}ms"
    flown = [
        Flown(f"ours_stack{at}", "ours", STACK_KNOBS, True, PX4_LIKE_DELAY_S, True),
        Flown(f"l1{at}", "l1", {}, True, PX4_LIKE_DELAY_S, True),
    ]
    starting = {"ours": STACK_KNOBS, "l1": knobs_of({}, ("l1",))}
    for meth in METHODS:
        retuned = _moved_knobs(tuning["chosen"], meth, starting[meth])
        if retuned is not None:
            flown.append(Flown(f"{meth}_retuned{at}", meth, retuned, True, PX4_LIKE_DELAY_S, True))
    rows = _cell_means(flown, trials, ESTIMATE_KEYS)
    return {
        **_run_header(trials),
        "sensitivity": {
            **_tuning_flights(),
            "delays_s": list(LINK_DELAYS_S),
            "knobs": {n: knobs_of(k, (meth,)) for n, meth, k in LINK_METHODS},
            "rows": sensitivity,
        },
        "tuning": {"command_delay_s": PX4_LIKE_DELAY_S, **tuning},
        "rows_flown": [f._asdict() for f in flown],
        "rows": rows,
        "wall_time_s": time.perf_counter() - t0,
    }


if __name__ == "__main__":
    import argparse

    from arcade_io import jaxsetup

    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.quadrotor_variants",
        description="In-process diagnostics of the closed loop, JSON on stdout: the "
        "ablation of ours_matched's two changes (seeds 0-2, ~7 min), the mass oracle "
        "beside L1 and ours (10 seeds, ~10 min), L1 and ours on the estimated state "
        "beside the ground-truth state (seeds 0-2, ~5 min), the estimator's jerk density "
        "tuned for the closed loop (seeds 0-2, ~6 min), what a setpoint delay costs "
        "L1 and ours, with their knobs tuned again at 20 ms and with the delay "
        "compensated (seeds 0-2, ~15 min), or what it costs the stack's knobs on the "
        "state estimate with and without compensation, with L1 and ours tuned again "
        "in that condition (seeds 0-2, ~40 min).",
    )
    runs = {
        "ablation": ablation,
        "oracle": oracle,
        "estimated": estimated_state,
        "estimator": estimator_tuning,
        "delay": command_delay,
        "link": link_delay,
    }
    parser.add_argument("run", nargs="?", choices=tuple(runs), default="ablation")
    args = parser.parse_args()
    jaxsetup.configure()
    print(jsonout.dumps(runs[args.run](), indent=1))
