"""Changepoint detection on the cartpole with a declaration rule on the beam posterior.

The evaluation's MAP-path flags (``benchmarks.cartpole_detection.changepoint_quality``)
mark every step at which the best hypothesis' newest changepoint moves. Here the beam is
run with ``AdaptationConfig.score = "joint"`` (its weights are then the posterior of the
paths it keeps) and a changepoint is *declared* at step ``k`` when the posterior
probability that the newest changepoint lies within the last ``m`` steps
(:func:`arcade_core.adaptation.changepoint_probability_within`) reaches a threshold,
unless one was declared within the last ``refractory`` steps
(:func:`arcade_core.adaptation.declare`).

Data, model and pipeline are those of ``benchmarks.cartpole_eval.evaluate`` for Ours: the
same seed-derived offline data, the VLD of split 0 (trained exactly as ``train_all`` does),
the same disturbed evaluation trajectories and the same separate tuning trajectories,
features ``model.features(x, u)`` and normalised residuals of ``x_{k+1} - f_nom(x_k, u_k)``.

Scoring: :func:`benchmarks.cartpole_detection.declaration_quality`, the metric the cartpole
evaluation uses too: a declaration at step ``k`` concerns the transition ``x_k -> x_{k+1}``;
it is a hit if ``t <= k <= t + HIT_WINDOW`` for an intervention step ``t``; each
intervention counts at most one hit (its first declaration in the window, whose offset is
the delay), every other declaration is a false alarm; precision = hits / declarations;
false alarms also per eligible step (outside every hit window), and a random detector at
the same flag rate beside each score.

Knobs are chosen on the tuning trajectories only, by the F1 score of the declarations,
``2 hits / (declarations + interventions)`` (harmonic mean of the hit rate and the
precision); ties go to the higher hit rate, then fewer false alarms, then the shorter
delay, then to the setting nearest the centre of the tied ones (:func:`_best`).
``paper_settings`` keeps the paper's beam (:func:`arcade_core.adaptation.cartpole_config`,
score ``"joint"``) and tunes ``m``, ``threshold`` and ``refractory`` on
:data:`DECLARATION_GRID`; the headline also tunes ``beta``, ``pi``, ``tau2`` and ``sigma2``
on :data:`BEAM_GRID`, all in one compiled program. A grid edge on which a best setting lies
(chosen or tied with it) is extended by the next value in :data:`EXTENSIONS` and the
tuning redone, until no best setting lies on an edge that has a value left;
``knobs["still_on_edge"]`` lists the knobs whose best value is still on an edge.
``map_flags_paper_settings`` scores the evaluation's MAP-path flags (score
``"algorithm1"``, paper config) the same way.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from arcade_control import cartpole as cd
from arcade_core import adaptation
from benchmarks.cartpole_detection import changepoint_quality, declaration_quality
from benchmarks.cartpole_methods import beam_batch, f_nom, train_vld
from benchmarks.cartpole_settings import HIT_WINDOW, EvalSettings

#: Beam knobs tuned for the headline (the paper's values are in every grid).
BEAM_GRID = {
    "beta": (0.3, 0.5, 0.7, 0.9),
    "pi": (0.005, 0.02, 0.05, 0.2),
    "tau2": (0.1, 1.0, 10.0),
    "sigma2": (0.05, 0.1, 0.2),
}
#: Declaration knobs: window ``m`` of the probability, threshold, refractory steps.
DECLARATION_GRID = {"m": (1, 2, 3, 4), "threshold": (0.3, 0.5, 0.7, 0.9), "refractory": (3, 5)}
#: Largest grid the extensions may make (settings; the declarations of all of them are held
#: in memory at once, one byte per setting, trajectory and step).
MAX_SETTINGS = 400_000
#: Values added, one at a time, below / above a grid whose lowest / highest value is best,
#: in this order (within each knob's range: ``beta`` and ``pi`` in (0, 1), a threshold
#: below 1; ``refractory`` at most 20 steps, half the spacing of the interventions, so that
#: the rule cannot learn their schedule). A stored run that extended each edge once tuned
#: ``beta`` 0.1, ``pi`` 0.4, ``tau2`` 0.01 and ``refractory`` 8, the first values added.
EXTENSIONS = {
    "beta": ((0.1, 0.03, 0.01, 0.003), (0.97,)),
    "pi": ((0.001,), (0.4, 0.6, 0.8)),
    "tau2": ((0.01, 0.001, 0.0001, 0.00001), (100.0, 1000.0)),
    "sigma2": ((0.02, 0.01), (0.5, 1.0)),
    "m": ((), (6, 8, 12)),
    "threshold": ((0.15, 0.05, 0.02), (0.97, 0.99)),
    "refractory": ((1,), (8, 12, 20)),
}


def _probabilities(model, cfg, X, U, ms):
    """``(T, len(ms))``: ``P_k(m)`` after each step of the beam over one trajectory,
    with the features and residuals of ``cartpole_methods.run_beam``."""

    def body(state, inp):
        x, u, xn = inp
        dn = model.normalise_residual(xn - f_nom(x, u))
        state, _ = adaptation.update(state, model.features(x, u), dn, cfg)
        p = jax.vmap(lambda m: adaptation.changepoint_probability_within(state, m))(ms)
        return state, p

    return jax.lax.scan(body, adaptation.init(model.theta0, cfg), (X[:-1], U, X[1:]))[1]


def _declarations(probs, threshold, refractory):
    """``(T,)`` bool declarations of :func:`arcade_core.adaptation.declare` on ``probs``."""

    def body(det, inp):
        det, declared, _ = adaptation.declare(det, inp[0], inp[1], threshold, refractory)
        return det, declared

    steps = jnp.arange(probs.shape[0], dtype=jnp.int32)
    return jax.lax.scan(body, adaptation.init_detector(), (probs, steps))[1]


def grid_flags(model, base, X, U, grid: dict[str, tuple]) -> np.ndarray:
    """Declarations for every setting of ``grid`` (beam knobs as :data:`BEAM_GRID`,
    declaration knobs as :data:`DECLARATION_GRID`, all keys needed, in that order):
    ``(len(beta), len(pi), len(tau2), len(sigma2), len(m), len(threshold),
    len(refractory), n, T)`` bool, one compiled program."""
    beam_keys = tuple(BEAM_GRID)
    points = np.array(list(itertools.product(*(grid[k] for k in beam_keys))), float)
    ms = jnp.asarray(grid["m"], jnp.int32)

    def one(*values):
        cfg = base._replace(**dict(zip(beam_keys, values)))
        return jax.vmap(lambda X, U: _probabilities(model, cfg, X, U, ms))(X, U)

    probs = jax.jit(jax.vmap(one))(*jnp.asarray(points.T))  # (C, n, T, M)
    probs = jnp.moveaxis(probs, -1, 1)  # (C, M, n, T)
    flat = probs.reshape(-1, probs.shape[-1])
    decl = jax.vmap(jax.vmap(_declarations, (0, None, None)), (None, 0, None))
    flags = jax.jit(jax.vmap(decl, (None, None, 0)))(
        flat,
        jnp.asarray(grid["threshold"], probs.dtype),
        jnp.asarray(grid["refractory"], jnp.int32),
    )  # (R, Th, C * M * n, T)
    C, M, n, T = probs.shape
    flags = np.asarray(flags).reshape(len(grid["refractory"]), len(grid["threshold"]), C, M, n, T)
    flags = flags.transpose(2, 3, 1, 0, 4, 5)  # (C, M, Th, R, n, T)
    return flags.reshape(*(len(grid[k]) for k in (*beam_keys, *DECLARATION_GRID)), n, T)


def _best(q: dict[str, np.ndarray]) -> tuple[tuple[int, ...], np.ndarray]:
    """Index of the best setting and those of all settings tied with it: max F1, then
    hit rate, fewest false alarms, shortest delay; among exact ties the one nearest the
    centre of the tied set (grid indices scaled to [0, 1]), so that a plateau of equally
    good settings does not push the choice onto a grid edge."""
    shape = q["f1"].shape
    delay = np.nan_to_num(q["mean_delay_steps"], nan=np.inf)
    keys = np.stack(
        [a.ravel() for a in (-q["f1"], -q["hit_rate"], q["false_alarms_per_100_steps"], delay)],
        1,
    )
    best = keys[np.lexsort(keys.T[::-1])[0]]
    tied = np.flatnonzero((keys == best).all(1))
    idx = np.stack(np.unravel_index(tied, shape), 1)
    pos = idx / np.maximum(np.asarray(shape) - 1, 1)
    chosen = idx[np.argmin(((pos - pos.mean(0)) ** 2).sum(1))]
    return tuple(int(i) for i in chosen), idx


def _edges(grid: dict[str, tuple], tied: np.ndarray) -> list[tuple[str, int]]:
    """``(knob, side)`` (side 0: lowest value, 1: highest) of every grid edge that a best
    setting lies on (``tied``: grid indices of the settings tied for best); with all
    settings equally good (e.g. nothing detected anywhere) that is every edge."""
    out = []
    for j, (knob, values) in enumerate(grid.items()):
        if len(values) > 1:
            sides = (tied[:, j].min() == 0, tied[:, j].max() == len(values) - 1)
            out += [(knob, side) for side in (0, 1) if sides[side]]
    return out


def _summary(q: dict[str, np.ndarray], idx=()) -> dict[str, Any]:
    """Plain floats of :func:`declaration_quality` at ``idx``."""
    out = {k: float(v[idx]) for k, v in q.items() if k != "hit_rate_per_intervention"}
    per = q["hit_rate_per_intervention"][idx]
    out["hit_rate_per_intervention"] = {
        str(t): float(h) for t, h in zip(cd.INTERVENTION_STEPS, per)
    }
    return out


def _scored(flags, push_snr: float | None = None) -> dict[str, Any]:
    """:func:`changepoint_quality` of the declarations ``flags (n, T)``."""
    flags = np.asarray(flags).reshape(-1, np.shape(flags)[-1])
    return changepoint_quality(flags, push_snr=push_snr)


def extension(grid: dict[str, tuple], edges: list[tuple[str, int]]) -> dict[str, list]:
    """Per knob, the values to add for the best settings on ``edges`` (:func:`_edges`):
    past each such edge, the nearest value of :data:`EXTENSIONS` not yet passed."""
    grow: dict[str, list] = {}
    for knob, side in edges:
        beyond = [
            v
            for v in EXTENSIONS[knob][side]
            if (v < min(grid[knob]) if side == 0 else v > max(grid[knob]))
        ]
        if beyond:
            grow.setdefault(knob, []).append(beyond[0])
    return grow


def tune_and_evaluate(
    model, base, tune, evaluation, grid, progress, push_snr: float | None = None
) -> dict[str, Any]:
    """Choose the knobs of ``grid`` on ``tune`` (``(X, U)``) by :func:`_best`, extending
    a grid edge by its next value in :data:`EXTENSIONS` while a best setting lies on it
    (:func:`_edges`), and score them on ``evaluation``."""
    grid, extended = dict(grid), {}
    while True:
        size = math.prod(len(v) for v in grid.values())
        progress(f"tuning on {size} settings x {tune[0].shape[0]} trajectories")
        q = declaration_quality(grid_flags(model, base, *tune, grid))
        idx, tied = _best(q)
        knobs = {k: grid[k][i] for k, i in zip(grid, idx)}
        edges = _edges(grid, tied)
        grow = extension(grid, edges)
        if not grow:
            break
        bigger = math.prod(len(v) + len(grow.get(k, ())) for k, v in grid.items())
        if bigger > MAX_SETTINGS:
            progress(f"best on a grid edge, not extended: {bigger} settings > {MAX_SETTINGS}")
            break
        progress(f"best on a grid edge, extending {grow}")
        grid.update({k: tuple(sorted((*grid[k], *v))) for k, v in grow.items()})
        for k, v in grow.items():
            extended[k] = sorted(extended.get(k, []) + v)
    single = {k: (v,) for k, v in knobs.items()}
    flags = grid_flags(model, base, *evaluation, single).reshape(evaluation[1].shape[:2])
    result = _scored(flags, push_snr)
    result["knobs"] = {
        "K": int(base.K),
        "score": base.score,
        **{k: (int(v) if k in ("m", "refractory") else float(v)) for k, v in knobs.items()},
        "tuning": {**_summary(q, idx), "tied_settings": len(tied)},
        "grid": {k: list(v) for k, v in grid.items()},
        "extended": extended,
        "still_on_edge": sorted({knob for knob, _ in edges}),
    }
    return result


def _setup(s: EvalSettings, progress):
    """The VLD of split 0, evaluation and tuning trajectories, as ``cartpole_eval.evaluate``
    makes them (same keys, same order)."""
    key = jax.random.PRNGKey(s.seed)
    k_data, k_split, k_train, k_online, k_tune = jax.random.split(key, 5)
    progress(f"simulating {s.n_traj} offline trajectories")
    params = s.true_params()
    data = cd.simulate(
        k_data,
        cd.sample_initial_states(k_data, s.n_traj),
        cd.stationary_schedule(s.T_data),
        params,
    )
    rng = np.random.default_rng(int(jax.random.randint(k_split, (), 0, 2**31 - 1)))
    train = rng.permutation(s.n_traj)[s.n_test :]
    x, u, xn = cd.transitions(data, train)
    progress("training the VLD (split 0)")
    vld_key = jax.random.split(jax.random.fold_in(k_train, 0), 6)[0]  # as train_all
    vld = train_vld(vld_key, x, u, xn, variational=True, epochs=s.epochs)
    sched = s.schedule()
    progress(f"simulating {s.trials} evaluation and {s.tuning_trials} tuning trajectories")
    online = cd.simulate(k_online, cd.sample_initial_states(k_online, s.trials), sched, params)
    tuning = cd.simulate(k_tune, cd.sample_initial_states(k_tune, s.tuning_trials), sched, params)
    return vld, online, tuning


def cartpole_detection(quick: bool = False, progress=lambda msg: None) -> dict[str, Any]:
    """Declaration-rule detection quality on the cartpole's evaluation trajectories
    (module docstring): headline (beam and declaration knobs tuned), ``paper_settings``
    (declaration knobs tuned) and ``map_flags_paper_settings`` (today's metric)."""
    t0 = time.perf_counter()
    s = EvalSettings.quick() if quick else EvalSettings()
    vld, online, tuning = _setup(s, progress)
    ev = (jnp.asarray(online.X), jnp.asarray(online.U))
    tu = (jnp.asarray(tuning.X), jnp.asarray(tuning.U))
    paper = adaptation.cartpole_config()
    joint = paper._replace(score="joint")

    progress("paper settings: tuning m, threshold, refractory")
    fixed = {k: (float(getattr(paper, k)),) for k in BEAM_GRID}
    snr = s.push_snr()
    paper_res = tune_and_evaluate(vld, joint, tu, ev, {**fixed, **DECLARATION_GRID}, progress, snr)
    progress("headline: tuning beta, pi, tau2, sigma2, m, threshold, refractory")
    head = tune_and_evaluate(vld, joint, tu, ev, {**BEAM_GRID, **DECLARATION_GRID}, progress, snr)

    progress("MAP flags (score algorithm1, paper config)")
    flags = np.asarray(beam_batch(vld, paper, *ev)[2])
    map_res = {
        **_scored(flags, snr),
        "knobs": {"K": paper.K, "score": paper.score, **{k: getattr(paper, k) for k in BEAM_GRID}},
    }
    return {
        **head,
        "paper_settings": paper_res,
        "map_flags_paper_settings": map_res,
        "trajectories": int(online.X.shape[0]),
        "tuning_trajectories": int(tuning.X.shape[0]),
        "criterion": "F1 = 2 hits / (declarations + interventions) on the tuning trajectories",
        "hit_window_steps": HIT_WINDOW,
        "quick": quick,
        "wall_time_s": time.perf_counter() - t0,
    }


def _plain(x):
    """JSON-safe copy: NaN and infinities become None."""
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="EvalSettings.quick() sizes")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()

    def progress(msg: str) -> None:
        print(f"[{time.perf_counter() - t0:7.1f} s] {msg}", file=sys.stderr, flush=True)

    print(json.dumps(_plain(cartpole_detection(args.quick, progress)), indent=2))


if __name__ == "__main__":
    main()
