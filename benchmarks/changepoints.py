"""Changepoint detection on the quadrotor: does a declared event mean a change?

Flights (:func:`fly`): the in-process quadrotor (:class:`benchmarks.quadrotor_flights.Runner`)
flown as the service stack flies it: ours at the adapter's knobs
(:func:`arcade_control.stack.stack_knobs`) on the state estimate, behind the simulated PX4
link's 20 ms setpoint delay, compensated (``arcade up --link-delay``). Each flight records
what the learner learned from at every step (``Flight.learning``), so the detector
(:func:`arcade_core.adaptation.detection_step`, what the adapter runs beside the learner)
is replayed offline on exactly the transitions, features and noise the adapter sees; the
detector does not act on the vehicle, so the replay is the flight's own detection.

The stack flies the flagship ``arcade`` by default: its learner restarts at its detector's
declarations, so that detector acts on the vehicle and cannot be replayed. Its events are
scored as declared in its own flights (:func:`flagship_events`), closed loop, at the
stored knobs; the replays on ours' flights choose the detector's knobs.

Ground truth: the release of the payload, one per flight in the 9 payload x speed cells of
the evaluation; a declaration within :data:`HIT_S` after it is a hit (at most one per
release), every other declaration a false alarm. Steady flights (:func:`steady_scenario`,
about a minute of figure-eight at 1.5 m/s with the 175 g payload swinging on its cable or
rigidly attached, no release) give the false-alarm rate in steady flight.

Knobs (:func:`tune`): the detector's are chosen on tuning seeds that the evaluation does
not fly, by F1 of the declarations (``2 hits / (declarations + releases)``), over the grid
:data:`GRID`; the learner keeps its own knobs (chosen by tracking error). The row
``learner_flags`` is what the adapter published before the detector: every step on which
the learner's MAP path gained a changepoint.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Sequence
from types import SimpleNamespace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from arcade_control.detection import detection_config
from arcade_control.knobs import (
    DETECTION_DEFAULTS,
    DETECTION_ENERGY_OUTPUTS,
    DETECTION_OUTPUTS,
    FLAGSHIP,
)
from arcade_control.methods import clipped_features
from arcade_control.nominal import CONTROL_DT as DT
from arcade_control.nominal import f_nom
from arcade_control.scenario import Scenario
from arcade_control.stack import stack_knobs
from arcade_core import adaptation
from benchmarks.quadrotor_protocol import LINK_DELAY_S, stored_knobs

#: A declaration at most this long after the release is a hit [s].
HIT_S = 0.25
PAYLOADS_G = (75.0, 125.0, 175.0)
SPEEDS_MPS = (0.5, 1.5, 2.5)
#: Seeds of the tuning flights (the evaluation flies 0, 1, ...): six, since the run before
#: the stored one, tuned on three, overfitted a surface flat near its top (F1 0.86 on its
#: tuning seeds, 0.77 on the evaluation seeds; a row 0.006 lower on the tuning seeds scored
#: 0.84). The stored run's six did not generalise better (0.80 and 0.72; docs/changepoints.md).
TUNING_SEEDS = (100, 101, 102, 103, 104, 105)
#: Length of a steady flight [s].
STEADY_S = 60.0
#: The detector's grid: beam knobs, the treatment of the residual's noise and the noise
#: factor (replayed together, one batch), then the declaration knobs. It watches the
#: vertical outputs: of the stored runs of the earlier grids, watching all 13 outputs scored
#: F1 0.39, the translational ones 0.62 and the vertical ones 0.65 (and the translational
#: ones cost three times as much to replay). The estimate's error enters a residual twice,
#: ``e_{k+1} - e_k`` (docs/changepoints.md): ``whiten`` filters it out (0.8: the moving
#: average of the measured lag-one autocorrelation -0.49); every one of the last two grids'
#: 100 best rows whitened. The grid before the last (three tuning seeds) chose the stack's
#: knobs (``arcade_control.knobs.DETECTION_DEFAULTS``); the last one (six seeds, 5,184
#: settings) chose six of its edges (``pi`` 0.5, ``tracking`` 0.5, ``beta`` 0.05,
#: ``window`` 2, ``whiten`` 0.9, ``noise`` 2), so this one extends them (``pi`` 0.8,
#: ``tracking`` 1, ``beta`` 0.1, ``window`` 1, ``whiten`` 0.95, ``noise`` 4) and keeps
#: the stack's values (``pi`` 0.2, ``tracking`` 0.2, ``beta`` 0.01, ``window`` 3,
#: ``whiten`` 0.8); to keep the run near an hour it drops the values neither choice used
#: (``pi`` 0.05, ``tracking`` 0, ``beta`` 0.005, ``window`` 5) and the stack's ``noise`` 1
#: (39 of the last grid's 100 best rows, against 61 for ``noise`` 2; the stored results
#: keep the stack's knobs as their own row). ``block = 1`` is the bottom of its range.
GRID = {
    "outputs": ("vertical",),
    "pi": (0.2, 0.5, 0.8),
    "tracking": (0.2, 0.5, 1.0),
    "beta": (0.01, 0.05, 0.1),
    "window": (1, 2, 3),
    "block": (1,),
    "whiten": (0.8, 0.9, 0.95),
    "noise": (2.0, 4.0),
    "threshold": (0.95, 0.99, 0.999, 0.9999),
    "refractory_steps": (2, 5, 20, 50),
}
#: Pairs of knobs that the grid does not combine (the other's bottom value only).
EXCLUSIVE = (("block", "whiten"),)
#: Knobs whose first value is the bottom of their range.
RANGE_BOTTOM = {"tracking": 0.0, "window": 1, "block": 1, "whiten": 0.0}


def steady_scenario(rigid: bool) -> Scenario:
    """About :data:`STEADY_S` of flight without a change: the 175 g payload on its cable
    (swinging) or rigidly attached, figure-eight at 1.5 m/s, no release."""
    base = Scenario(175.0, 1.5)
    laps = (STEADY_S - base.t_of_clock(0.0)) / base.lap_s
    return Scenario(
        175.0,
        1.5,
        release_fraction=-1.0,
        laps=laps,
        rigid_payload=rigid,
        command_delay_s=LINK_DELAY_S,
    )


def plans() -> list[tuple[str, Scenario]]:
    """The flights of one seed: a release in each payload x speed cell, then the two steady
    flights (:func:`steady_scenario`, swinging and rigid)."""
    out = [
        (f"{p:g} g, {s:g} m/s", Scenario(p, s, command_delay_s=LINK_DELAY_S))
        for p in PAYLOADS_G
        for s in SPEEDS_MPS
    ]
    return out + [(f"steady, {k}", steady_scenario(k == "rigid")) for k in ("swinging", "rigid")]


def fly(
    runner, seeds: Sequence[int], progress: Callable[[str], None], method: str = "ours"
) -> list[dict[str, Any]]:
    """The flights of :func:`plans` for each seed, flown by ``method`` as the stack flies
    it (the state estimate, the link delay compensated). ``flags``: the steps on which the
    method raised its changepoint flag (ours: its MAP path gained a changepoint; the
    flagship: its detector declared a change, what the stack publishes as an event);
    ``learning``: what the learner learned from (ours)."""
    from benchmarks.quadrotor_flights import DIAG_CHANGEPOINT

    out = []
    for seed in seeds:
        for label, scen in plans():
            t0 = time.perf_counter()
            f = runner.fly(method, scen, seed=seed, estimated=True, compensate_delay=True)
            progress(f"{method}, seed {seed}, {label}: {time.perf_counter() - t0:.0f} s")
            out.append(
                {
                    "label": label,
                    "seed": seed,
                    "t_release": f.t_release,
                    "minutes": len(f.t) * DT / 60.0,
                    "learning": f.learning,
                    "flags": f.diag[:, DIAG_CHANGEPOINT] > 0,
                    "crashed": f.crashed,
                }
            )
    return out


def flagship_events(
    models, seeds: Sequence[int], progress: Callable[[str], None]
) -> dict[str, Any]:
    """What the stack flies by default, scored closed loop: the flagship ``arcade`` at the
    stack's stored knobs (:func:`benchmarks.quadrotor_protocol.stored_knobs`), its detector
    at :data:`arcade_control.knobs.DETECTION_DEFAULTS`, every declaration restarting its
    learner; the events are the ones it declared in flight (no replay)."""
    from benchmarks.quadrotor_flights import Runner

    flagship = SimpleNamespace(vld=models.vld, guard=models.guard, closedloop=stored_knobs("stack"))
    flights = fly(Runner(flagship), seeds, progress, method=FLAGSHIP)
    flags = [f["flags"] for f in flights]
    return score(flights, flags) | {
        "by_cell": by_cell(flights, flags),
        "method": FLAGSHIP,
        "crashed": sum(f["crashed"] for f in flights),
        "knobs": dict(DETECTION_DEFAULTS),
    }


@jax.jit
def _features_and_residuals(vld, guard, xp, up, x):
    z = jax.vmap(lambda a, b: clipped_features(vld, guard, a, b))(xp, up)
    dn = jax.vmap(lambda a, b, c: vld.normalise_residual(c - f_nom(a, b)))(xp, up, x)
    return z, dn


def _inputs(vld, guard, flight) -> tuple[np.ndarray, ...]:
    """``(z, dn, sigma2, learned)`` of every step, as the learner computed them."""
    rec = flight["learning"]
    z, dn = _features_and_residuals(vld, guard, rec["xp"], rec["up"], rec["x"])
    n = len(rec["learned"])
    s2 = np.broadcast_to(np.asarray(rec["sigma2"], float).reshape(n, -1), (n, 13))
    return np.asarray(z), np.asarray(dn), np.array(s2), np.asarray(rec["learned"])


@jax.jit
def _replay(theta0, config, z, dn, s2, learned):
    def body(state, inp):
        state, det = adaptation.detection_step(state, *inp, config)
        return state, (det.probability, det.declared)

    state = adaptation.init_detection(theta0, config._replace(beam=config.beam._replace(K=15)))
    return jax.lax.scan(body, state, (z, dn, s2, learned))[1]


def replay(theta0, config, inputs) -> tuple[np.ndarray, np.ndarray]:
    """The detector over one flight: ``(probability, declared)`` per step (compiled once
    per flight length)."""
    p, d = _replay(theta0, config, *inputs)
    return np.asarray(p), np.asarray(d)


def declare(prob: np.ndarray, threshold: float, refractory: int) -> np.ndarray:
    """:func:`arcade_core.adaptation.declare` over a probability series (one step each)."""
    out = np.zeros(prob.shape, bool)
    last = None
    for k in np.flatnonzero(prob >= threshold):
        if last is None or k - last > refractory:
            out[k], last = True, k
    return out


def _hit_delay(t: np.ndarray, t_release: float) -> float | None:
    """The delay of the first declaration (times ``t``) within :data:`HIT_S` after the
    release, ``None`` when there is none (a miss)."""
    after = t - t_release
    inside = np.flatnonzero((after > 0) & (after <= HIT_S + 1e-9))
    return float(after[inside[0]]) if inside.size else None


def score(flights: list[dict[str, Any]], declared: list[np.ndarray]) -> dict[str, float]:
    """Hit rate, delay, false alarms and precision of the declarations of each flight."""
    hits, delays, false_release, false_steady, minutes_steady, n_decl = 0, [], 0, 0, 0.0, 0
    releases = 0
    for f, d in zip(flights, declared, strict=True):
        t = np.flatnonzero(d) * DT
        n_decl += t.size
        if np.isfinite(f["t_release"]):
            releases += 1
            delay = _hit_delay(t, f["t_release"])
            if delay is not None:
                hits += 1
                delays.append(delay)
            false_release += t.size - (delay is not None)
        else:
            false_steady += t.size
            minutes_steady += f["minutes"]
    nan = float("nan")
    return {
        "flights": releases,
        "release_hit_rate": hits / releases if releases else nan,
        "release_delay_s_median": float(np.median(delays)) if delays else nan,
        "false_alarms_per_flight": false_release / releases if releases else nan,
        "false_alarms_per_min_steady": false_steady / minutes_steady if minutes_steady else nan,
        "precision": hits / n_decl if n_decl else nan,
        "f1": 2.0 * hits / (n_decl + releases) if releases else nan,
        "steady_minutes": minutes_steady,
    }


def by_cell(flights: list[dict[str, Any]], declared: list[np.ndarray]) -> dict[str, Any]:
    """Per flight label (a payload x speed cell, or a steady flight): releases hit, flights
    and false alarms, as :func:`score` counts them."""
    out: dict[str, dict[str, int]] = {}
    for f, d in zip(flights, declared, strict=True):
        row = out.setdefault(f["label"], {"hits": 0, "flights": 0, "false_alarms": 0})
        t = np.flatnonzero(d) * DT
        hit = int(np.isfinite(f["t_release"]) and _hit_delay(t, f["t_release"]) is not None)
        row["hits"] += hit
        row["flights"] += 1
        row["false_alarms"] += int(t.size - hit)
    return out


@jax.jit
def _probabilities(theta0, configs, z, dn, s2, learned):
    """:func:`_replay`'s probabilities for a batch of detectors (every leaf of ``configs``
    with a leading batch axis): one compiled program per flight length for the whole grid."""
    return jax.vmap(lambda c: _replay(theta0, c, z, dn, s2, learned)[0])(configs)


def _watching(config, watched):
    """``config`` restricted to the outputs ``watched`` (its noise scale's finite ones)."""
    return config._replace(
        noise_scale=config.noise_scale[watched], energy_outputs=config.energy_outputs[watched]
    )


def tune(vld, flights, inputs, progress) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The grid point with the best F1 on ``flights`` (their replay ``inputs``; ties: fewer
    false alarms per flight, :func:`_rank`)."""
    rows = []
    beam_keys = ("pi", "tracking", "beta", "window", "block", "whiten", "noise")
    for outputs in GRID["outputs"]:
        combos = [
            v
            for v in itertools.product(*(GRID[k] for k in beam_keys))
            if not any(
                v[beam_keys.index(a)] != RANGE_BOTTOM[a]
                and v[beam_keys.index(b)] != RANGE_BOTTOM[b]
                for a, b in EXCLUSIVE
            )
        ]
        knobs = [
            {**DETECTION_DEFAULTS, "outputs": outputs, **dict(zip(beam_keys, v, strict=True))}
            for v in combos
        ]
        # Replayed on the watched outputs only: the others carry a noise variance of 1e12
        # in the detector (no evidence), so their rows change the probabilities by about
        # 1e-5 and cost most of the time. The evaluation replays the full detector.
        # With the energy knob on, the outputs whose energy it reads go along (no evidence).
        extra = DETECTION_ENERGY_OUTPUTS if any(k["energy"] > 0 for k in knobs) else ()
        watched = jnp.asarray(sorted({*DETECTION_OUTPUTS[outputs], *extra}))
        batch = jax.tree.map(
            lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]),
            *[_watching(detection_config(k, estimated=True), watched) for k in knobs],
        )
        theta0 = vld.theta0[watched]
        probs = [
            np.asarray(_probabilities(theta0, batch, z, dn[:, watched], s2[:, watched], learned))
            for z, dn, s2, learned in inputs
        ]
        for b, k in enumerate(knobs):
            for thr, refr in itertools.product(GRID["threshold"], GRID["refractory_steps"]):
                declared = [declare(p[b], thr, refr) for p in probs]
                rows.append(
                    {"knobs": {**k, "threshold": thr, "refractory_steps": refr}}
                    | score(flights, declared)
                )
        progress(f"tuning: the detectors watching the {outputs} outputs replayed")
    best = max(rows, key=_rank)
    knobs = dict(best["knobs"])
    # Numeric knobs whose best value is the grid's first or last (reported, not hidden).
    knobs["on_grid_edge"] = [
        k
        for k, values in GRID.items()
        if k != "outputs"
        and knobs[k] in (values[0], values[-1])
        and RANGE_BOTTOM.get(k) != knobs[k]
    ]
    return knobs, rows


#: Rows of the tuning grid stored in the results (the best by F1; the grid has thousands).
STORED_ROWS = 100


def _rank(row: dict[str, Any]) -> tuple[float, float]:
    """The order of :func:`tune`: F1, then fewer false alarms per flight."""
    return (float(np.nan_to_num(row["f1"])), -row["false_alarms_per_flight"])


def best_rows(rows: list[dict[str, Any]], n: int = STORED_ROWS) -> list[dict[str, Any]]:
    """The ``n`` best tuning rows, best first (ties keep the grid's order)."""
    return sorted(rows, key=_rank, reverse=True)[:n]


def run_changepoints(
    quick: bool = False,
    trials: int = 10,
    tuning: bool | None = None,
    progress: Callable[[str], None] = lambda msg: None,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The quadrotor part of ``arcade eval changepoints``: tune (unless ``tuning`` is
    False; default: not ``quick``), then score, on ``trials`` seeds (``quick``: one seed,
    no tuning, the stored knobs), the events the flagship declared in its own flights
    (:func:`flagship_events`, what the stack publishes), the detector replayed on ours'
    flights at the chosen and the stored knobs, and ours' learner flags.

    Returns the result and what was flown, for the forgetting ablation
    (:func:`benchmarks.changepoints_ablation.run_ablation`): ``theta0``, ``flights``,
    ``inputs`` and the tuning ``tune_flights`` and ``tune_inputs`` (``None`` untuned)."""
    from benchmarks.quadrotor_flights import Runner
    from benchmarks.quadrotor_variants import models

    t_start = time.perf_counter()
    tuning = (not quick) if tuning is None else tuning
    m = models()
    m.closedloop = stack_knobs()
    runner = Runner(m)
    knobs, grid = dict(DETECTION_DEFAULTS), []
    tune_flights = tune_inputs = None
    if tuning:
        tune_flights = fly(runner, TUNING_SEEDS, progress)
        tune_inputs = [_inputs(m.vld, m.guard, f) for f in tune_flights]
        knobs, grid = tune(m.vld, tune_flights, tune_inputs, progress)
    seeds = range(1 if quick else trials)
    flights = fly(runner, seeds, progress)
    chosen = {k: v for k, v in knobs.items() if k != "on_grid_edge"}
    inputs = [_inputs(m.vld, m.guard, f) for f in flights]
    declared = [
        replay(m.vld.theta0, detection_config(chosen, estimated=True), i)[1] for i in inputs
    ]
    # The same detector scoring its hypotheses as Algorithm 1 writes it (the data term
    # twice): its weights are no posterior, and the same threshold means something else.
    literal = detection_config(chosen, score="algorithm1", estimated=True)
    declared_literal = [replay(m.vld.theta0, literal, i)[1] for i in inputs]
    # What the stack flies (the stored knobs) when the tuning chose others: the adapter
    # keeps its knobs until a tuning that generalises better replaces them.
    stored = dict(DETECTION_DEFAULTS)
    declared_stored = (
        declared
        if stored == chosen
        else [replay(m.vld.theta0, detection_config(stored, estimated=True), i)[1] for i in inputs]
    )
    result = {
        # What the stack flies by default and publishes: the flagship's own events.
        "flagship_events": flagship_events(m, seeds, progress),
        "detector": score(flights, declared),
        "detector_stored_knobs": score(flights, declared_stored)
        | {"by_cell": by_cell(flights, declared_stored)},
        "detector_algorithm1_score": score(flights, declared_literal),
        "learner_flags": score(flights, [f["flags"] for f in flights]),
        "knobs": knobs,
        "stored_knobs": dict(DETECTION_DEFAULTS),
        "tuned": tuning,
        "tuning_grid": best_rows(grid),
        "tuning_settings": len(grid),
        "crashed": sum(f["crashed"] for f in flights),
        "seeds": list(seeds),
        "tuning_seeds": list(TUNING_SEEDS) if tuning else [],
        "wall_s": time.perf_counter() - t_start,
    }
    flown = {
        "theta0": m.vld.theta0,
        "flights": flights,
        "inputs": inputs,
        "tune_flights": tune_flights,
        "tune_inputs": tune_inputs,
    }
    return result, flown


def format_table(result: dict[str, Any]) -> str:
    """Both systems' detection quality as text."""
    q = result["quadrotor"]
    lines = [
        "Quadrotor: release of the payload (hit: a declaration within "
        f"{HIT_S:g} s), {q['detector']['flights']} flights, "
        f"{q['detector']['steady_minutes']:.1f} min of steady flight",
        f"{'':26s} {'hit rate':>9s} {'delay med':>10s} {'FA/flight':>10s} "
        f"{'FA/min steady':>14s} {'precision':>10s}",
    ]
    for name in (
        "flagship_events",
        "detector",
        "detector_stored_knobs",
        "detector_algorithm1_score",
        "learner_flags",
    ):
        if name not in q:
            continue
        r = q[name]
        lines.append(
            f"{name:26s} {r['release_hit_rate']:9.2f} {r['release_delay_s_median']:9.2f}s "
            f"{r['false_alarms_per_flight']:10.2f} {r['false_alarms_per_min_steady']:14.2f} "
            f"{r['precision']:10.2f}"
        )
    lines.append(f"detector knobs: {q['knobs']}" + (" (tuned)" if q["tuned"] else " (stored)"))

    c = result["cartpole"]
    lines.append("Cartpole: interventions (hit: a declaration within 3 steps)")
    lines.append(f"{'':26s} {'hit rate':>9s} {'FA/100 steps':>13s} {'precision':>10s}")
    for name, r in (
        ("tuned", c),
        ("paper settings", c["paper_settings"]),
        ("MAP flags, paper settings", c["map_flags_paper_settings"]),
    ):
        lines.append(
            f"{name:26s} {r['hit_rate']:9.2f} {r['false_alarms_per_100_steps']:13.2f} "
            f"{r['precision']:10.2f}"
        )
    return "\n".join(lines)
