"""The held-out gate of the discrepancy workflow (design §6, step 4): which confident
effects are added, and the held-out one-step RMSE before and after
(:func:`arcade_core.discrepancy.workflow.find_discrepancy` uses both).

The log's held-out blocks (:mod:`arcade_core.discrepancy.settings`) are only evaluated
here, never fitted. Arrays in, verdicts out; no files, no printing.
"""

from __future__ import annotations

from itertools import combinations
from typing import Any

import numpy as np

from arcade_core.discrepancy.catalog import effects_for
from arcade_core.discrepancy.prediction import DiscrepancyModel, rms


def velocity_and_rates(model: DiscrepancyModel) -> list[int]:
    """Indices of the components the held-out gap is judged on when nothing is added."""
    comps = list(model.components)
    names = (
        [comps[i] for i in (3, 4, 5, 9, 10, 11)]
        if model.name == "quadrotor"
        else ["xdot", "thetadot"]
    )
    return [comps.index(c) for c in names]


def heldout_gate(
    model: DiscrepancyModel, X, U, dt, ho, H, ident, err0
) -> tuple[Any, dict[int, dict[str, Any]]]:
    """The held-out gate: ``ident`` with only the confident effects that shrink the
    held-out one-step gap, and every confident effect's verdict (``err0``: the current
    model's one-step errors on the held-out windows ``ho``).

    The confident effects are tried in the order of the share they explain, each on top of
    those already accepted (at its estimate of the joint fit): it is accepted when the
    pooled held-out RMSE over the components it acts on (the library's ``acts_on``)
    decreases *and* the gap over all velocity and rate components does not grow, each
    component weighed by the current model's held-out RMSE (so that units do not decide).
    The ones that fail are tried again on top of what a pass accepted (wind shows once the
    drag it acts through is in), until a pass accepts nothing. Effects that act only
    together (wind acts through a drag the current model lacks: the drag without the wind
    predicts worse, the wind without the drag not at all) are then tried together, the
    smallest groups first (in the order above): the first group of those that failed alone
    that passes the same test on the components any of them acts on, each member needed
    (without it the group's gap on its own components is larger), is accepted, and the
    rest are tried again on top. A verdict gives both RMSEs of its components
    (``before``: without it, ``after``: with it), the overall measure, and ``with``: the
    effects it was accepted together with. The held-out windows ``ho`` are only evaluated
    here, never fitted: the decision uses the same data as the reported before/after
    numbers, which is what makes ``heldout_rmse_after <= heldout_rmse_before`` hold.
    """
    groups = [g for _, g in model.groups]
    comps = list(model.components)
    specs = effects_for(model.name)
    base = np.asarray(model.theta_base, float)
    fitted = np.asarray(ident.theta, float)
    overall = velocity_and_rates(model)

    def errors(theta: np.ndarray) -> np.ndarray:
        return model.errors(X, model.predict(theta, X, U, ho, H, dt), ho, H)[:, -1]

    scale = np.maximum(rms(err0[:, overall]), 1e-300)

    def measure(err: np.ndarray) -> float:
        return float(np.sqrt(np.mean((rms(err[:, overall]) / scale) ** 2)))

    def own(js) -> list[int]:
        names = {c for j in js for c in specs[model.groups[j][0]].acts_on}
        return [i for i, c in enumerate(comps) if c in names]

    def pooled(err: np.ndarray, idx: list[int]) -> float:
        return float(rms(err[:, idx].reshape(-1)))

    def with_effects(theta: np.ndarray, js) -> np.ndarray:
        cand = theta.copy()
        for j in js:
            cand[list(groups[j])] = fitted[list(groups[j])]
        return cand

    def verdict(js, err, err_new, cand) -> dict[str, Any]:
        idx = own(js)
        before, after = pooled(err, idx), pooled(err_new, idx)
        all_before, all_after = measure(err), measure(err_new)
        return {
            "components": [comps[i] for i in idx],
            "before": before,
            "after": after,
            "overall_before": all_before,
            "overall_after": all_after,
            "confirmed": bool(after < before and all_after <= all_before),
            "with": [],
            "theta": cand,
        }

    def needed(group, cand, err_new) -> bool:
        """Whether each member is needed: without it the group predicts its components
        worse."""
        for j in group:
            off = cand.copy()
            off[list(groups[j])] = base[list(groups[j])]
            if pooled(errors(off), own([j])) <= pooled(err_new, own([j])):
                return False
        return True

    theta, err = base.copy(), err0
    accepted, verdicts = [], {}
    order = sorted(ident.confident, key=lambda j: -ident.contribution[j])
    while True:  # until nothing more is accepted: one accepted may let another show
        tried = None
        while tried != accepted:
            tried = list(accepted)
            for j in [j for j in order if j not in accepted]:
                cand = with_effects(theta, [j])
                err_new = errors(cand)
                verdicts[j] = verdict([j], err, err_new, cand)
                if verdicts[j]["confirmed"]:
                    theta, err = cand, err_new
                    accepted.append(j)
        pending = [j for j in order if j not in accepted]
        # The smallest group of the rest that passes together, each member needed.
        combos = (c for size in range(2, len(pending) + 1) for c in combinations(pending, size))
        for group in combos:
            cand = with_effects(theta, group)
            err_new = errors(cand)
            joint = verdict(group, err, err_new, cand)
            if joint["confirmed"] and needed(group, cand, err_new):
                names = [model.groups[j][0] for j in group]
                for j in group:
                    verdicts[j] = {**joint, "with": [n for n in names if n != model.groups[j][0]]}
                theta, err = cand, err_new
                accepted += group
                break
        else:
            break
    drop = [j for j in ident.confident if j not in accepted]
    return without_effects(ident, drop, base, groups), verdicts


def heldout_numbers(model: DiscrepancyModel, X, U, dt, ho, H, ident, err_b) -> dict[str, Any]:
    """One-step held-out errors of the model with ``ident``'s added effects, and the pooled
    RMSE before (``err_b``: the current model) and after over the components the added
    effects act on (library) where their contribution to the held-out prediction is at
    least half of what is left (where the effect is visible in this log); over all
    velocity and rate components when nothing is added."""
    comps = list(model.components)
    specs = effects_for(model.name)
    err_a = model.errors(X, model.predict(ident.theta, X, U, ho, H, dt), ho, H)[:, -1]
    names = [model.groups[j][0] for j in ident.confident]
    if names:
        act = sorted({c for nme in names for c in specs[nme].acts_on}, key=comps.index)
        change, left = rms(err_b - err_a), rms(err_a)
        act = [c for c in act if change[comps.index(c)] >= 0.5 * left[comps.index(c)]] or act
    else:
        act = [comps[i] for i in velocity_and_rates(model)]
    sel = [comps.index(c) for c in act]
    return {
        "err_after": err_a,
        "components": act,
        "rmse_before": float(rms(err_b[:, sel].reshape(-1))),
        "rmse_after": float(rms(err_a[:, sel].reshape(-1))),
    }


def without_effects(ident, drop: list[int], theta_base: np.ndarray, groups) -> Any:
    """``ident`` with the effects ``drop`` taken out of the confident (added) set."""
    theta = np.asarray(ident.theta, float).copy()
    for j in drop:
        theta[list(groups[j])] = theta_base[list(groups[j])]
    confident = tuple(j for j in ident.confident if j not in drop)
    return ident._replace(confident=confident, theta=theta)
