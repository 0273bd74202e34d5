"""Naming the missing effects: sparse group selection with bootstrap confidence (design §6,
step 3).

The model with effects is a function of a parameter vector ``theta`` whose entries are
grouped by effect (``groups``: name -> indices); the *base* ``theta_base`` is the current
model (every effect off or at the vehicle file's value). ``residual_fn(theta)`` returns the
short-horizon prediction residuals ``(n_windows, channels)`` of the log (measured minus
predicted). Identification:

1. **Linearise** at the base: ``r(theta) ~ r_0 - A (theta - theta_base)`` with ``A`` the
   sensitivity of the prediction to every candidate parameter. The columns of ``A`` are
   the candidate regressors, all effects at once. They are secants, not tangents: at the
   base over the step (a share of the plausible range,
   :func:`~arcade_core.discrepancy.linearise.scaled_secants`) that explains the residual
   best, so that a lag of many log steps is seen for what it does; later over a small
   fixed share of the range. An effect that acts only through another the base lacks
   (wind through drag) has no sensitivity at the base; its secants are taken where that
   other effect is on (:func:`~arcade_core.discrepancy.linearise.carried_secants`), and
   when it is selected the two are fitted together (step 4).
2. **Whiten**: fit all candidates by least squares, estimate the channel covariance of
   what is left (trimming gross outliers such as floor contacts: windows whose whitened
   residual exceeds :data:`~arcade_core.discrepancy.linearise.OUTLIER_CHI2`), and
   whiten rows with it, so that velocity and body-rate residuals (different units,
   different noise) are weighed by their noise.
3. **Select** the subset of effects (all ``2^G`` subsets, from per-block sufficient
   statistics) with the smallest BIC ``N log(RSS/N) + k log N`` among the *admissible*
   subsets: each effect in the subset must explain at least ``min_explained`` of the
   residual sum of squares that is left without it, move some parameter by at least
   ``min_size`` of its plausible range, and keep its parameters in their plausible ranges.
   BIC alone would, on long logs, name any effect that explains a sliver of systematic
   model error (a motor time constant 0.5 ms off); the relevance tests ask for a
   physically relevant size, the ranges for a physical explanation (the linearised model
   would otherwise happily "explain" a slightly fast rate loop with a negative delay).
4. **Fit** the selected effects' parameters on the full nonlinear model (projected
   Levenberg-Marquardt within the plausible ranges), linearise again there and repeat
   selection: an effect that only shows once another is in (wind through drag) is found in
   the next round.
5. **Confidence**: a block bootstrap over time (blocks of consecutive windows, resampled
   with replacement) reruns the selection; an effect's confidence is the fraction of
   resamples that select it. Parameter intervals are the 5-95 % percentiles of the
   bootstrap estimates with the selected set. Effects below ``confidence`` are reported
   but not added: "no confident effect" when none reaches it.

Everything here is pure array computation; the selection over subsets and the bootstrap
are jitted and vectorised, the nonlinear fit is a short host loop over the caller's jitted
residual function.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array

from arcade_core.discrepancy.linearise import (
    carried_secants,
    fd_jacobian,
    fit_nonlinear,
    linearise,
    scaled_secants,
    whitening,
)
from arcade_core.discrepancy.settings import MIN_FIT_WINDOWS
from arcade_core.discrepancy.subsets import (
    Bounds,
    bootstrap_selection,
    group_masks,
    select_subset,
    solve_masked_jit,
    subset_rss,
)


class SelectionConfig(NamedTuple):
    """Settings of :func:`identify`.

    ``min_explained``: smallest fraction of the remaining residual sum of squares an effect
    must explain to be admissible; ``min_size``: smallest parameter change (largest over
    the effect's parameters, as a share of its plausible range). ``confidence``: bootstrap
    inclusion probability needed to add an effect. ``block``: windows per bootstrap block.
    ``probe``: step of the secants of the linearisations, as a share of the ranges;
    ``probe_scales``: the steps the first one chooses from
    (:func:`~arcade_core.discrepancy.linearise.scaled_secants`).
    """

    min_explained: float = 0.02
    min_size: float = 0.02
    confidence: float = 0.9
    n_boot: int = 200
    block: int = 40
    seed: int = 0
    max_rounds: int = 3
    lm_iterations: int = 15
    probe: float = 0.05
    probe_scales: tuple[float, ...] = (0.05, 0.25, 1.0)


class Identification(NamedTuple):
    """Result of :func:`identify` (group order of ``groups``).

    ``selected``: groups chosen on the full data; ``confident``: selected with confidence
    at least the threshold, sorted by contribution (largest first); ``theta``: fitted
    model with the confident effects only; ``theta_selected``: with all selected effects;
    ``confidence`` (G,) bootstrap inclusion frequencies; ``contribution`` (G,) share of
    the residual sum of squares each selected effect explains; ``samples`` (B, P)
    bootstrap parameter estimates for the confident set; ``alive`` (P,) identifiable
    parameters; ``weights`` (c, c) whitening matrix; ``outliers`` (n,) windows left out.
    """

    selected: tuple[int, ...]
    confident: tuple[int, ...]
    theta: np.ndarray
    theta_selected: np.ndarray
    confidence: np.ndarray
    contribution: np.ndarray
    samples: np.ndarray
    alive: np.ndarray
    weights: np.ndarray
    outliers: np.ndarray
    rounds: int


def identify(
    residual_fn: Callable[[Array], Array],
    theta_base: np.ndarray,
    groups: Sequence[Sequence[int]],
    low: np.ndarray,
    high: np.ndarray,
    config: SelectionConfig | None = None,
    carriers: dict[int, Sequence[int]] | None = None,
) -> Identification:
    """Select, fit and rate effects for the residuals ``residual_fn`` (module docstring).

    ``carriers``: per group, the groups it may act through (default: any other group)."""
    config = SelectionConfig() if config is None else config
    theta_base = np.asarray(theta_base, dtype=float)
    low, high = np.asarray(low, float), np.asarray(high, float)
    P = theta_base.shape[0]
    span = high - low
    steps = 1e-4 * span
    all_idx = list(range(P))
    masks = jnp.asarray(group_masks(groups, P))
    bits = jnp.asarray([1 << j for j in range(len(groups))])
    rho = jnp.asarray(config.min_explained)
    bounds = Bounds(
        jnp.asarray(low - theta_base), jnp.asarray(high - theta_base), jnp.asarray(span)
    )
    min_size = jnp.asarray(config.min_size)
    members = jnp.asarray(group_masks(groups, P)[[1 << j for j in range(len(groups))]])

    r_base = np.asarray(residual_fn(jnp.asarray(theta_base)))
    n_win = r_base.shape[0]
    blocks = np.arange(n_win) // max(int(config.block), 1)
    n_blocks = int(blocks[-1]) + 1

    # Linearisations are secants over a probe step (a share of the plausible range), not
    # tangents: lags (a transport delay, a motor time constant) act far from linearly; a
    # tangent at zero delay under-predicts what a delay of a few log steps does, and a
    # tangent elsewhere lets the linear model extrapolate one lag into another's role.
    def secants(th: np.ndarray) -> np.ndarray:
        return np.where(th + config.probe * span <= high, 1.0, -1.0) * config.probe * span

    jac = scaled_secants(residual_fn, theta_base, low, high, r_base, config.probe_scales)
    # An effect that acts only through another (wind through a drag the base lacks) gets
    # its secants where that other one is on; selecting it fits both (step 4).
    jac, carried = carried_secants(
        residual_fn, theta_base, groups, low, high, r_base, jac, config.probe_scales,
        config.min_explained, carriers,
    )  # fmt: skip

    # Whitening from what is left after all candidates (step 2).
    keep = np.isfinite(r_base).all(axis=1)
    if keep.sum() < MIN_FIT_WINDOWS:
        raise ValueError(
            f"the current model's one-step prediction is finite on only {int(keep.sum())} of "
            f"{n_win} fitting windows (at least {MIN_FIT_WINDOWS} are needed): check that "
            "the vehicle file describes the logged vehicle (mass, hover thrust, limits)"
        )
    W0, _ = whitening(np.nan_to_num(r_base), keep)
    lin0, _, _ = linearise(
        np.nan_to_num(r_base), np.nan_to_num(jac), W0, keep, blocks, n_blocks, span
    )
    full = solve_masked_jit(lin0.G.sum(0), lin0.g.sum(0), lin0.alive)
    e_all = r_base + np.einsum("ncp,p->nc", np.nan_to_num(jac), np.asarray(full))
    W, keep = whitening(np.nan_to_num(e_all), keep)

    ones = jnp.ones(n_blocks)

    def cost(th: np.ndarray) -> float:
        r_th = np.nan_to_num(np.asarray(residual_fn(jnp.asarray(th))), nan=1e6)
        return float(np.sum((r_th @ W.T)[keep] ** 2))

    def fit(sel: tuple[int, ...], *starts: np.ndarray, previous: bool = True) -> np.ndarray:
        free = [i for j in sel for i in groups[j] if alive_any[i]]
        # Start from a linear estimate or from the previous fit, whichever is best.
        candidates = []
        for start in (*starts, *((theta,) if previous else ())):
            th0 = theta_base.copy()
            th0[free] = start[free]
            candidates.append(np.clip(th0, low, high))
        th0 = min(candidates, key=cost)
        return fit_nonlinear(
            residual_fn, th0, free, low, high, W, keep, steps, config.lm_iterations
        )

    def carried_start(j: int, k: int, ctx, cols, sel: tuple[int, ...]) -> np.ndarray:
        """Start of the fit of ``sel`` in which the carried effect ``j`` acts through ``k``
        (:func:`~arcade_core.discrepancy.linearise.carried_secants`): the linear estimate
        (within the plausible ranges) of ``sel`` without ``j``'s other carriers, at the
        base with ``j``'s secants taken under ``k`` (at ``ctx``: ``cols``), in the reading
        with the smaller cost: ``k`` where the secants were taken, or ``k`` at its own
        linear estimate and ``j`` scaled by how much weaker ``k`` is there (the product of
        the two is what the linear estimate measured, as wind times drag)."""
        gj, gk = list(groups[j]), list(groups[k])
        jac_k = np.array(jac, dtype=float)
        jac_k[..., gj] = cols
        lin_k, _, _ = linearise(
            np.nan_to_num(r_base), np.nan_to_num(jac_k), W, keep, blocks, n_blocks, span
        )
        others = {c for c, _, _ in carried[j]} - {k}
        mask = np.zeros(P, dtype=bool)
        mask[[i for g in sel if g not in others for i in groups[g]]] = True
        _, d = subset_rss(
            lin_k.G.sum(0), lin_k.g.sum(0), lin_k.s.sum(), jnp.asarray(mask[None]), bounds
        )
        d = np.asarray(d[0])
        at_ctx, own = theta_base + d, theta_base + d
        at_ctx[gk] = ctx[gk]
        weaker = np.max(np.abs(ctx[gk] - theta_base[gk])) / max(np.max(np.abs(d[gk])), 1e-12)
        own[gj] = theta_base[gj] + d[gj] * weaker
        return min((at_ctx, own), key=lambda th: cost(np.clip(th, low, high)))

    def drop_gains(th: np.ndarray, sel: tuple[int, ...]) -> dict[int, float]:
        """Share of the residual each effect explains on the nonlinear model."""
        c_full = cost(th)
        gains = {}
        for j in sel:
            off = th.copy()
            off[list(groups[j])] = theta_base[list(groups[j])]
            c_off = cost(off)
            gains[j] = (c_off - c_full) / max(c_off, 1e-300)
        return gains

    def size(th: np.ndarray, j: int) -> float:
        idx = list(groups[j])
        return float(np.max(np.abs(th[idx] - theta_base[idx]) / span[idx]))

    theta = theta_base.copy()
    alive_any = np.asarray(lin0.alive).copy()
    selected: tuple[int, ...] = ()
    r, J = r_base, jac
    rounds = 0
    for rounds in range(1, config.max_rounds + 1):
        # Linearise at the current fit; target as if the fitted effects were switched off.
        y_base = r - np.einsum("ncp,p->nc", J, theta - theta_base)
        lin, _, _ = linearise(y_base, J, W, keep, blocks, n_blocks, span)
        alive_any |= np.asarray(lin.alive)
        best, _, deltas = select_subset(lin, ones, masks, bits, rho, bounds, min_size, members)
        new = tuple(j for j in range(len(groups)) if int(best) >> j & 1)
        if set(new) <= set(selected) and rounds > 1:
            break
        new = tuple(sorted(set(new) | set(selected)))
        start = theta_base + np.asarray(deltas[int(best)])
        carried_now = [j for j in new if j in carried and rounds == 1]
        if carried_now:
            # A carried effect is fitted first with the effects that carry it alone (the
            # relevance test below drops the carriers that do not matter; the rest of the
            # selection is found again in the next round, once the effect is in), once
            # from the linear estimate under each carrier (a bilinear start is rough: its
            # cost does not rank it against the base); the best fit is kept.
            new = tuple(sorted({*carried_now, *(k for j in carried_now for k, *_ in carried[j])}))
            for j in carried_now:
                fits = [
                    fit(new, carried_start(j, k, ctx, cols, new), previous=False)
                    for k, ctx, cols in carried[j]
                ]
                theta = min(fits, key=cost)
        else:
            theta = fit(new, start)
        # Keep only effects that are relevant on the nonlinear model, refit without the rest.
        gains = drop_gains(theta, new)
        kept = tuple(
            j for j in new if gains[j] >= config.min_explained and size(theta, j) >= config.min_size
        )
        if kept != new:
            theta = theta_base.copy() if not kept else fit(kept, theta)
        selected = kept
        r = np.asarray(residual_fn(jnp.asarray(theta)))
        J = fd_jacobian(residual_fn, theta, all_idx, secants(theta), r)
    theta_selected = theta

    # Confidence by block bootstrap at the final linearisation (step 5).
    y_base = r - np.einsum("ncp,p->nc", J, theta - theta_base)
    lin, _, _ = linearise(y_base, J, W, keep, blocks, n_blocks, span)
    rng = np.random.default_rng(config.seed)
    counts = jnp.asarray(
        rng.multinomial(n_blocks, np.full(n_blocks, 1.0 / n_blocks), size=config.n_boot).astype(
            float
        )
    )
    sel_mask = jnp.asarray(group_masks(groups, P)[sum(1 << j for j in selected)])
    best_b, _ = bootstrap_selection(
        lin, counts, masks, bits, rho, bounds, min_size, members, sel_mask
    )
    best_b = np.asarray(best_b)
    confidence = np.array([np.mean((best_b >> j) & 1) for j in range(len(groups))])
    contribution = np.zeros(len(groups))
    for j, gain in drop_gains(theta_selected, selected).items():
        contribution[j] = gain
    confident = tuple(
        sorted(
            (j for j in selected if confidence[j] >= config.confidence),
            key=lambda j: -contribution[j],
        )
    )

    # The model that is added: confident effects only (refit if that is fewer).
    theta_conf = theta_base.copy()
    if confident:
        free = [i for j in confident for i in groups[j] if bool(lin.alive[i])]
        keep_idx = [i for j in confident for i in groups[j]]
        theta_conf[keep_idx] = theta_selected[keep_idx]
        if set(confident) != set(selected):
            theta_conf = fit_nonlinear(
                residual_fn, theta_conf, free, low, high, W, keep, steps, config.lm_iterations
            )
            r = np.asarray(residual_fn(jnp.asarray(theta_conf)))
            J = fd_jacobian(residual_fn, theta_conf, all_idx, secants(theta_conf), r)
            y_base = r - np.einsum("ncp,p->nc", J, theta_conf - theta_base)
            lin, _, _ = linearise(y_base, J, W, keep, blocks, n_blocks, span)
    conf_mask = jnp.asarray(group_masks(groups, P)[sum(1 << j for j in confident)])
    _, deltas_b = bootstrap_selection(
        lin, counts, masks, bits, rho, bounds, min_size, members, conf_mask
    )
    # Bootstrap estimates around the nonlinear fit: the linear solution's spread.
    G_all = lin.G.sum(0)
    d_full = np.asarray(solve_masked_jit(G_all, lin.g.sum(0), conf_mask & lin.alive))
    samples = theta_conf[None, :] + (np.asarray(deltas_b) - d_full[None, :])
    samples = np.clip(samples, low, high)
    return Identification(
        selected=selected,
        confident=confident,
        theta=theta_conf,
        theta_selected=theta_selected,
        confidence=confidence,
        contribution=contribution,
        samples=samples,
        alive=np.asarray(lin.alive),
        weights=W,
        outliers=~keep,
        rounds=rounds,
    )
