"""The discrepancy workflow (design §6): where model and log disagree, which effect is
missing, the model with it, and the gap before and after.

On one flight log (states ``X``, inputs ``U`` as a zero-order hold per row, constant
period ``dt``) and the current model (:class:`~arcade_core.discrepancy.prediction.
DiscrepancyModel`: nominal model, motors, rate loop and the effects it already has):

1. **Align**: predictions of the current model from every measured state with the
   measured inputs, over one model step (``step_s``, rounded to whole log samples) and
   over a short horizon; residual per state component.
2. **Localise**: residual RMS per component, per regime (speed, height, thrust, tilt for
   the quadrotor; speeds, pole angle, force for the cartpole) and per time segment (the
   changepoint machinery of Algorithm 1 segments the log;
   :func:`~arcade_core.discrepancy.localize.localise_gap`).
3. **Name**: all library effects of the system are candidates at once; sparse selection
   (BIC among subsets in which every effect explains a relevant share) with a block
   bootstrap for confidence and parameter intervals
   (:mod:`arcade_core.discrepancy.identify`). Only effects with confidence at least
   ``confidence`` are added; otherwise the answer is "no confident effect". A selected
   effect whose signature in this log stays within the noise (it could not halve the
   one-step gap, :func:`effect_visibility`; effects that only compensate each other stand
   out no more than they do together) is reported as "below detectability" and not
   added (quadrotor; the library states each effect's limit on the standard trajectory).
   An effect that this log could not show even at the edge of its plausible range is
   listed as "not enough excitation to tell" (``cannot_tell``, ``reach``); when that holds
   for every effect the answer is "not enough excitation to tell", not a guess.
4. **Gate and add**: a confident effect is added only if the held-out one-step gap
   shrinks with it, on the components it acts on and over all velocity and rate
   components (:func:`~arcade_core.discrepancy.heldout.heldout_gate`; effects that help
   only together, as wind and the drag it acts through, are tried together); otherwise
   it is listed as "not confirmed on held-out data" with both numbers, so the updated
   model is never worse on held-out data than the current one. The effect tables of the
   updated model (``Outcome.model_effects``): the current model's and the added effects,
   within their plausible ranges.
5. **Show**: the log is split in time into blocks; a held-out fraction of them is only
   evaluated, never fitted (:mod:`arcade_core.discrepancy.settings`). Before/after one-step
   RMSE and multi-step CRMSE per component.

A log whose setpoint changed between rows (resampled without regard to the controller's
instants) shows an apparent input lag, which the workflow will name.

``heldout_rmse_before/after`` is the one-step RMSE over the state components the added
effects act on (the library's ``acts_on``) where their contribution to the held-out
prediction is at least half of what is left unexplained (a ground effect acts on the
vertical velocity of a nearly level vehicle, hardly visibly on the horizontal ones); all
velocity and rate components when nothing is added. SI units; ``gap_before/after`` give
every component.

Arrays in, an :class:`Outcome` out; no files, no printing. Run it with float64 enabled
(``jax_enable_x64``): in float32 the numbers differ in the third or fourth digit, and the
secants' scoring overflows.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from arcade_core.discrepancy.catalog import effects_for
from arcade_core.discrepancy.heldout import heldout_gate, heldout_numbers, without_effects
from arcade_core.discrepancy.identify import SelectionConfig, identify
from arcade_core.discrepancy.localize import localise_gap
from arcade_core.discrepancy.prediction import DiscrepancyModel, rms
from arcade_core.discrepancy.settings import (
    Settings,
    block_windows,
    burn_in_samples,
    check_log,
    log_blocks,
    step_samples,
)

#: Gap-to-noise ratio at which adding an effect halves the one-step RMSE (``sqrt(3)``).
HALVING_RATIO = 3.0**0.5


@dataclass
class Outcome:
    """Everything the workflow found.

    ``result``: the findings as JSON-ready data (what ``arcade discrepancy --json``
    prints); ``details``: arrays for plots (held-out windows ``ho``, residuals before and
    after, localisation, ``theta`` before and after, the ``identification``);
    ``model_effects``: the effect tables of the updated model.
    """

    result: dict[str, Any]
    details: dict[str, Any] = field(default_factory=dict)
    model_effects: dict[str, dict[str, Any]] = field(default_factory=dict)


def find_discrepancy(
    model: DiscrepancyModel,
    X: np.ndarray,
    U: np.ndarray,
    dt: float,
    settings: Settings | None = None,
    progress: Callable[[str], None] | None = None,
) -> Outcome:
    """The workflow (module docstring) on states ``X (n, nx)`` and inputs ``U (n, nu)`` at
    period ``dt`` (``settings``: default :class:`Settings`); ``progress`` is told what is
    being done."""
    settings = Settings() if settings is None else settings
    say = progress or (lambda _msg: None)
    system = model.name
    n = X.shape[0]
    check_log(system, n, dt, settings)
    H = step_samples(settings, dt)
    burn = burn_in_samples(settings, system, dt)
    blocks = log_blocks(settings, n, dt)
    n_fit = sum(b - a for a, b, h in blocks if not h)
    fit_starts = block_windows(blocks, False, burn, H, H)
    ch = np.asarray(model.channels)

    def residual_fn(theta):
        pred = model.predict(theta, X, U, fit_starts, H, dt)[:, -1]
        return X[fit_starts + H][:, ch] - pred[:, ch]

    say(f"{n} samples at {1.0 / dt:.4g} Hz; fitting {len(fit_starts)} windows of {H} steps")
    cfg = SelectionConfig(
        min_explained=settings.min_explained,
        min_size=settings.min_size,
        confidence=settings.confidence,
        n_boot=settings.n_boot,
        block=max(1, round(settings.block_s / (H * dt))),
        seed=settings.seed,
    )
    ident = identify(
        residual_fn, model.theta_base, [g for _, g in model.groups], model.low, model.high, cfg,
        carriers=model.carriers,
    )  # fmt: skip
    say(f"selected {[model.groups[j][0] for j in ident.selected]} in {ident.rounds} round(s)")

    # ---- detectability: could each selected effect halve the held-out gap at all? An
    # effect the bootstrap selects but whose signature is within the noise is reported,
    # not added (:func:`effect_visibility`).
    specs = effects_for(system)
    ho = block_windows(blocks, True, burn, H, 1)
    visible, reach = {}, {}
    if system == "quadrotor":
        visible, reach = _visibility(model, X, U, dt, fit_starts, H, ident)
        below = [j for j in ident.confident if visible[j] < HALVING_RATIO]
        if below:
            ident = without_effects(ident, below, model.theta_base, [g for _, g in model.groups])

    # ---- held-out gate: an effect is added only if it shrinks the held-out gap.
    theta_b = model.theta_base
    comps = list(model.components)
    err_b = model.errors(X, model.predict(theta_b, X, U, ho, H, dt), ho, H)[:, -1]
    verdicts: dict[int, dict[str, Any]] = {}
    if ident.confident and len(ho):
        ident, verdicts = heldout_gate(model, X, U, dt, ho, H, ident, err_b)

    # ---- held-out before/after. Each added effect passed the gate on its own
    # components and overall; the pooled number over their union (what the report
    # headlines) is checked too, dropping the effect that explains least until it holds.
    while True:
        held = heldout_numbers(model, X, U, dt, ho, H, ident, err_b)
        if not ident.confident or held["rmse_after"] <= held["rmse_before"]:
            break
        j = min(ident.confident, key=lambda j: ident.contribution[j])
        verdicts[j] = {
            **verdicts.get(j, {}),
            "components": held["components"],
            "before": held["rmse_before"],
            "after": held["rmse_after"],
            "confirmed": False,
            "theta": ident.theta,
        }
        ident = without_effects(ident, [j], model.theta_base, [g for _, g in model.groups])
    theta_a, err_a, act = ident.theta, held["err_after"], held["components"]
    rmse_b, rmse_a = held["rmse_before"], held["rmse_after"]
    gap_before = {c: float(v) for c, v in zip(comps, rms(err_b))}
    gap_after = {c: float(v) for c, v in zip(comps, rms(err_a))}

    # ---- effects, parameters, intervals
    effects_out = []
    listed = sorted(
        set(ident.selected)
        | set(verdicts)
        | {j for j, c in enumerate(ident.confidence) if c >= 0.5},
        key=lambda j: (-(j in ident.confident), -ident.contribution[j], -ident.confidence[j]),
    )
    for j in listed:
        name = model.groups[j][0]
        theta_j = ident.theta if j in ident.confident else ident.theta_selected
        if j in verdicts and not verdicts[j]["confirmed"]:
            theta_j = verdicts[j]["theta"]
        params = model.effect_params(theta_j, name)
        lo = model.effect_params(np.percentile(ident.samples, 5, axis=0), name)
        hi = model.effect_params(np.percentile(ident.samples, 95, axis=0), name)
        interval = {k: _interval(lo[k], hi[k]) for k in params} if j in ident.confident else {}
        vis = visible.get(j)
        effects_out.append({
            "name": name,
            "visibility": None if vis is None else float(vis),
            "below_detectability": vis is not None and vis < HALVING_RATIO,
            "params": params,
            "interval": interval,
            "confidence": float(ident.confidence[j]),
            "explained": float(ident.contribution[j]),
            "added": j in ident.confident,
            "heldout": _public(verdicts.get(j)),
            "acts_on": list(specs[name].acts_on),
        })  # fmt: skip
    confident_names = [model.groups[j][0] for j in ident.confident]

    M = max(2, round(settings.horizon_s / dt))
    stride = max(1, round(0.5 / dt))
    cr_starts = block_windows(blocks, True, burn, M, stride)
    crmse_b: dict[str, float] = {}
    crmse_a: dict[str, float] = {}
    if len(cr_starts):
        eb = model.errors(X, model.predict(theta_b, X, U, cr_starts, M, dt), cr_starts, M)
        ea = model.errors(X, model.predict(theta_a, X, U, cr_starts, M, dt), cr_starts, M)
        # CRMSE (Sec. V-A) of one component is the sum of absolute errors over the horizon.
        crmse_b = {c: float(v) for c, v in zip(comps, np.mean(np.abs(eb).sum(1), axis=0))}
        crmse_a = {c: float(v) for c, v in zip(comps, np.mean(np.abs(ea).sum(1), axis=0))}

    # ---- localisation of the gap (fit part, current model)
    loc = localise_gap(model, X, U, dt, fit_starts, H, theta_b, ident.weights)

    summary = (
        "named: "
        + ", ".join(
            f"{e['name']} (confidence {e['confidence']:.2f})" for e in effects_out if e["added"]
        )
        if confident_names
        else "no confident effect"
    )
    below_names = [e["name"] for e in effects_out if e["below_detectability"]]
    if below_names:
        summary += "; below detectability: " + ", ".join(below_names)
    no_influence, cannot_tell, no_excitation = excitation(reach, bool(confident_names))
    if no_excitation:
        summary = "not enough excitation to tell: no library effect, even at the edge of its "
        summary += "plausible range, would stand out of the noise in this log"
    elif cannot_tell:
        summary += "; not enough excitation to tell " + ", ".join(cannot_tell)
    unconfirmed = [model.groups[j][0] for j, v in verdicts.items() if not v["confirmed"]]
    if unconfirmed:
        summary += "; not confirmed on held-out data: " + ", ".join(
            f"{model.groups[j][0]} ({_gap_text(v)})"
            for j, v in verdicts.items()
            if not v["confirmed"]
        )
    result: dict[str, Any] = {
        "system": system,
        "summary": summary,
        "no_confident_effect": not confident_names,
        "effects": effects_out,
        "gap_before": gap_before,
        "gap_after": gap_after,
        "below_detectability": below_names,
        "not_confirmed_on_heldout": unconfirmed,
        "not_enough_excitation": no_excitation,
        "cannot_tell": cannot_tell,
        "no_influence": no_influence,
        "reach": {k: float(v) for k, v in reach.items()},
        "heldout_rmse_before": rmse_b,
        "heldout_rmse_after": rmse_a,
        "heldout_components": act,
        "crmse_before": crmse_b,
        "crmse_after": crmse_a,
        "step_s": H * dt,
        "horizon_s": M * dt,
        "samples": n,
        "fit_samples": n_fit,
        "outlier_windows": int(ident.outliers.sum()),
        "localisation": loc["summary"],
    }
    details = {
        "ho": ho, "err_before": err_b, "err_after": err_a,
        "components": comps, "localisation": loc, "theta_before": theta_b,
        "theta_after": theta_a, "identification": ident,
    }  # fmt: skip
    return Outcome(result, details, updated_effects(model, ident))


def _public(verdict: dict[str, Any] | None) -> dict[str, Any] | None:
    """A gate verdict for the JSON (without the parameter vector)."""
    if verdict is None:
        return None
    return {k: v for k, v in verdict.items() if k != "theta"}


def _gap_text(verdict: dict[str, Any]) -> str:
    comps = "+".join(verdict["components"])
    return f"{comps} {verdict['before']:.3g} -> {verdict['after']:.3g}"


def updated_effects(model: DiscrepancyModel, ident) -> dict[str, dict[str, Any]]:
    """Effect tables of the updated model: the current model's, and every confident effect
    of ``ident`` at its estimate (clipped into its plausible range)."""
    effects = {k: dict(v) for k, v in model.effect_tables.items()}
    for j in ident.confident:
        name = model.groups[j][0]
        effects[name] = _clip_to_spec(model.name, name, model.effect_params(ident.theta, name))
    return effects


def _clip_to_spec(system: str, name: str, params: dict[str, Any]) -> dict[str, Any]:
    specs = effects_for(system)[name].params
    out = {}
    for k, v in params.items():
        lo, hi = specs[k].low, specs[k].high
        out[k] = [min(max(x, lo), hi) for x in v] if isinstance(v, list) else min(max(v, lo), hi)
    return out


def noise_levels(model: DiscrepancyModel, X, U, dt, starts, H, theta) -> np.ndarray:
    """What is left per identification channel once ``theta`` models the log: the RMS
    one-step residual over the windows ``starts`` (the floor a model can get down to;
    windows whose prediction is not finite are left out)."""
    pred = model.predict(theta, X, U, starts, H, dt)[:, -1]
    ch = np.asarray(model.channels)
    e = X[np.asarray(starts) + H][:, ch] - pred[:, ch]
    return rms(e[np.isfinite(e).all(axis=1)])


def effect_visibility(
    model: DiscrepancyModel, X, U, dt, starts, H, theta, name, sigma, pred0=None
) -> float:
    """How far effect ``name`` at ``theta`` stands out of the noise in this log (quadrotor;
    ``name`` may be a tuple of effects: what they do together, on what any acts on).

    Mirrors the held-out metric: over the windows ``starts``, the RMS change ``g_c`` of the
    one-step prediction that ``theta`` makes against the base model, per component ``c``
    the effect acts on, against that component's noise level ``sigma_c`` (what the fitted
    model leaves, :func:`noise_levels`); pooled over the components where the change is at
    least half the noise (all of them when there is none), the ratio ``sqrt(sum g_c^2 / sum
    sigma_c^2)``. A model that removes the gap takes the pooled RMSE from ``sqrt(sigma^2 +
    g^2)`` to ``sigma`` at best: halving it takes a ratio of at least ``sqrt(3)``
    (:data:`HALVING_RATIO`). Below that the effect is *below detectability* in this log.
    Windows where either prediction is not finite are left out (none left: 0).
    """
    comps = list(model.components)
    # component name -> (state index, identification channel); all are v or omega.
    chan = {comps[i if i < 6 else i - 1]: (i, k) for k, i in enumerate(model.channels)}
    base = np.asarray(model.theta_base, float)
    if pred0 is None:
        pred0 = model.predict(base, X, U, starts, H, dt)[:, -1]
    pred = model.predict(theta, X, U, starts, H, dt)[:, -1]
    finite = np.isfinite(pred).all(axis=1) & np.isfinite(pred0).all(axis=1)
    if not finite.any():
        return 0.0
    pred, pred0 = pred[finite], pred0[finite]
    names = (name,) if isinstance(name, str) else tuple(name)
    on = {c for n in names for c in effects_for(model.name)[n].acts_on}
    acts = [c for c in comps if c in on and c in chan]
    g = np.array([float(rms(pred[:, chan[c][0]] - pred0[:, chan[c][0]])) for c in acts])
    sig = np.array([float(sigma[chan[c][1]]) for c in acts])
    moved = g >= 0.5 * sig
    if moved.any():
        g, sig = g[moved], sig[moved]
    return float(np.sqrt(np.sum(g**2) / max(float(np.sum(sig**2)), 1e-300)))


def excitation(reach: dict[str, float], named: bool) -> tuple[list[str], list[str], bool]:
    """From each effect's reach (:func:`_visibility`): the effects that do not move the
    prediction at all (they act through one the model lacks, as wind acts through drag: no
    log can tell them until that one is in the model), the effects this log cannot tell
    (reach below :data:`HALVING_RATIO`), and whether the log cannot tell any effect that
    could move the prediction and nothing was ``named``: "not enough excitation to tell"."""
    no_influence = [name for name, v in reach.items() if v <= 1e-9]
    cannot_tell = [n for n, v in reach.items() if v < HALVING_RATIO and n not in no_influence]
    influence = len(reach) - len(no_influence)
    return no_influence, cannot_tell, influence > 0 and len(cannot_tell) == influence and not named


def _visibility(
    model: DiscrepancyModel, X, U, dt, starts, H, ident
) -> tuple[dict[int, float], dict[str, float]]:
    """:func:`effect_visibility` of every selected effect at its estimate, against the
    same model without it (the other effects it is fitted with stay in: wind shows only
    through a drag fitted with it), and against what the fit with all selected effects
    leaves (fitting windows), but no larger than that of all selected effects together;
    and every library effect's *reach*: its visibility at the edge of its plausible range
    (each parameter at the bound farther from the current model's value) on top of the
    fitted model's visible effects, what the log could show of it at most. An effect
    whose reach is below :data:`HALVING_RATIO` cannot be told in this log, whatever its
    size: the log does not excite it enough."""
    # Windows the identification left out as gross outliers (floor contacts) stay out.
    starts = np.asarray(starts)[~np.asarray(ident.outliers)]
    sigma = noise_levels(model, X, U, dt, starts, H, ident.theta_selected)
    base = np.asarray(model.theta_base, float)

    def prediction(theta: np.ndarray) -> np.ndarray:
        return model.predict(theta, X, U, starts, H, dt)[:, -1]

    def without(theta: np.ndarray, idx) -> np.ndarray:
        off = np.array(theta, dtype=float)
        off[list(idx)] = base[list(idx)]
        return off

    out = {}
    for j in ident.selected:
        name, idx = model.groups[j]
        th = np.asarray(ident.theta if j in ident.confident else ident.theta_selected, float)
        pred0 = prediction(without(th, idx))
        out[j] = effect_visibility(model, X, U, dt, starts, H, th, name, sigma, pred0)
    # Effects that compensate each other (a thrust scale against an inflow loss) each look
    # large without the other: none stands out if all of them together do not.
    if len(ident.selected) > 1:
        names = tuple(model.groups[j][0] for j in ident.selected)
        together = effect_visibility(
            model, X, U, dt, starts, H, ident.theta_selected, names, sigma, prediction(base)
        )
        out = {j: min(v, together) for j, v in out.items()}
    # The reach on top of the selected effects that stand out of the noise.
    context = np.asarray(ident.theta_selected, float)
    for j, v in out.items():
        if v < HALVING_RATIO:
            context = without(context, model.groups[j][1])
    pred_context = prediction(context)
    reach = {}
    low, high = np.asarray(model.low, float), np.asarray(model.high, float)
    for name, idx in model.groups:
        th = without(context, idx)
        pred0 = pred_context if np.array_equal(th, context) else prediction(th)
        for i in idx:
            th[i] = low[i] if abs(low[i] - base[i]) > abs(high[i] - base[i]) else high[i]
        reach[name] = effect_visibility(model, X, U, dt, starts, H, th, name, sigma, pred0)
    return out, reach


def _interval(lo, hi):
    if isinstance(lo, list):
        return [[min(a, b), max(a, b)] for a, b in zip(lo, hi)]
    return [min(lo, hi), max(lo, hi)]
