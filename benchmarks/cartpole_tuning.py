"""Tuning of the cartpole evaluation's online knobs on separate tuning trajectories.

Every adaptive method's own hyperparameters are chosen from grids by mean one-step CRMSE
on tuning trajectories that are never evaluated: Ours' (beta, pi, tau^2) by coordinate
descent over one compiled run of the whole grid, the known-changepoint reference's beta
and tau^2 the same way, one knob for Ours w/o CP and the MLP; and the detection-tuned
setting (lowest tuning CRMSE among those that detect enough interventions).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from arcade_core import adaptation
from benchmarks.cartpole_detection import changepoint_quality
from benchmarks.cartpole_methods import crmse_batch, run_beam, run_known_changepoints
from benchmarks.cartpole_settings import (
    DETECTION_MIN_HIT_RATE,
    KNOWN_CP_BETA_GRID,
    MAX_TUNING_PASSES,
    OURS_BETA_GRID,
    OURS_KNOBS,
    OURS_PI_GRID,
    OURS_TAU2_GRID,
)


def _choice(scores: dict[float, float]) -> dict[str, Any]:
    """The grid value with the lowest mean tuning CRMSE, and every value's score."""
    return {
        "chosen": min(scores, key=scores.get),
        "tuning_crmse": {str(k): v for k, v in scores.items()},
    }


def ours_tuning(
    grid: list[dict[str, float]], preset: adaptation.AdaptationConfig
) -> dict[str, Any]:
    """Ours' CRMSE tuning read off :func:`beam_tuning_grid` by coordinate descent: beta at
    the preset pi and tau^2, then pi, then tau^2, each at the others' current choice, in
    passes until a pass changes nothing (at most :data:`MAX_TUNING_PASSES`).

    Returns ``{"ours": .., "ours_pi": .., "ours_tau2": ..}`` (beta, pi, tau^2 of the last
    pass, each as :func:`_choice` gives it: the chosen value and the scores along that
    knob at the others' final values) and ``"ours_passes"``.
    """
    scores = {tuple(g[k] for k in OURS_KNOBS): g["tuning_crmse"] for g in grid}
    table, passes = coordinate_descent(
        scores, OURS_KNOBS, {k: float(getattr(preset, k)) for k in OURS_KNOBS}
    )
    return {
        "ours": table["beta"],
        "ours_pi": table["pi"],
        "ours_tau2": table["tau2"],
        "ours_passes": passes,
    }


def coordinate_descent(
    scores: dict[tuple, float], knobs: tuple[str, ...], start: dict[str, float]
) -> tuple[dict[str, dict[str, Any]], int]:
    """Minimise a score tabulated on a grid (keys: values of ``knobs`` in that order) one
    knob after the other from ``start``, in passes until one changes nothing (at most
    :data:`MAX_TUNING_PASSES`). Returns each knob's :func:`_choice` of the last pass and
    the number of passes."""
    values = {k: sorted({key[i] for key in scores}) for i, k in enumerate(knobs)}
    point = dict(start)
    passes = 0
    while passes < MAX_TUNING_PASSES:
        passes += 1
        changed, table = False, {}
        for knob in knobs:
            table[knob] = _choice(
                {v: scores[tuple({**point, knob: v}[k] for k in knobs)] for v in values[knob]}
            )
            changed |= table[knob]["chosen"] != point[knob]
            point[knob] = table[knob]["chosen"]
        if not changed:
            break
    return table, passes


def known_changepoints_tuning(
    model, cfg, X, U, X_np, betas=KNOWN_CP_BETA_GRID, tau2s=OURS_TAU2_GRID
) -> dict[str, Any]:
    """The known-changepoint reference's beta and tau^2, tuned like Ours' (coordinate
    descent from the preset on the tuning trajectories; one compiled program for the
    grid). ``chosen`` and ``tuning_crmse`` are beta's, ``tau2`` is :func:`_choice`'s."""
    B, T = (
        a.ravel()
        for a in np.meshgrid(np.asarray(betas, float), np.asarray(tau2s, float), indexing="ij")
    )

    def one(b, t):
        c = cfg._replace(beta=b, tau2=t)
        return jax.vmap(lambda X, U: run_known_changepoints(model, c, X, U))(X, U)

    xhat = jax.jit(jax.vmap(one))(jnp.asarray(B), jnp.asarray(T))
    scores = {}
    for i in range(len(B)):
        scores[(float(B[i]), float(T[i]))] = _tuning_score(xhat[i], X_np)
    table, passes = coordinate_descent(
        scores, ("beta", "tau2"), {"beta": float(cfg.beta), "tau2": float(cfg.tau2)}
    )
    return {**table["beta"], "tau2": table["tau2"], "passes": passes}


def tuned_config(cfg: adaptation.AdaptationConfig, tuned: dict[str, Any]):
    """``cfg`` with Ours' knobs as :func:`ours_tuning` chose them."""
    return cfg._replace(
        beta=tuned["ours"]["chosen"],
        pi=tuned["ours_pi"]["chosen"],
        tau2=tuned["ours_tau2"]["chosen"],
    )


def _tuning_score(xhat, X_np) -> float:
    """Mean CRMSE over the tuning trajectories; infinite if any prediction diverged."""
    c = crmse_batch(xhat, X_np)
    return float(c.mean()) if np.isfinite(c).all() else float("inf")


def tune_on_grid(make_fn, grid, X, U, X_np) -> dict[str, Any]:
    """Pick the grid value with the lowest mean CRMSE on the tuning trajectories."""
    return _choice(
        {value: _tuning_score(jax.jit(jax.vmap(make_fn(value)))(X, U), X_np) for value in grid}
    )


def beam_tuning_grid(
    model, cfg, X, U, X_np, betas=OURS_BETA_GRID, pis=OURS_PI_GRID, tau2s=OURS_TAU2_GRID
) -> list[dict[str, float]]:
    """Ours on the tuning trajectories for every ``(beta, pi, tau2)`` triple: mean CRMSE
    and hit rate per triple. All run in one compiled program (the knobs are traced)."""
    B, P, T = (
        a.ravel()
        for a in np.meshgrid(
            np.asarray(betas, float),
            np.asarray(pis, float),
            np.asarray(tau2s, float),
            indexing="ij",
        )
    )

    def one(b, p, t):
        c = cfg._replace(beta=b, pi=p, tau2=t)
        return jax.vmap(lambda X, U: run_beam(model, c, X, U))(X, U)

    xhat, _, flags, _ = jax.jit(jax.vmap(one))(jnp.asarray(B), jnp.asarray(P), jnp.asarray(T))
    grid = []
    for i in range(len(B)):
        grid.append(
            {
                "beta": float(B[i]),
                "pi": float(P[i]),
                "tau2": float(T[i]),
                "tuning_crmse": _tuning_score(xhat[i], X_np),
                "tuning_hit_rate": changepoint_quality(np.asarray(flags[i]))["hit_rate"],
            }
        )
    return grid


def detection_tuning(
    grid: list[dict[str, float]], min_hit_rate=DETECTION_MIN_HIT_RATE
) -> dict[str, Any]:
    """Lowest tuning CRMSE of :func:`beam_tuning_grid` among the settings whose hit rate on
    the tuning trajectories is at least ``min_hit_rate`` (``chosen`` is ``None`` when no
    setting reaches it)."""
    ok = [g for g in grid if g["tuning_hit_rate"] >= min_hit_rate]
    best = min(ok, key=lambda g: g["tuning_crmse"]) if ok else None
    return {
        "min_hit_rate": min_hit_rate,
        "grid": grid,
        "chosen": None if best is None else {k: best[k] for k in OURS_KNOBS},
    }
