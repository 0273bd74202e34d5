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
   base over the step (a share of the plausible range, :func:`scaled_secants`) that
   explains the residual best, so that a lag of many log steps is seen for what it does;
   later over a small fixed share of the range.
2. **Whiten**: fit all candidates by least squares, estimate the channel covariance of
   what is left (trimming gross outliers such as floor contacts: windows whose whitened
   residual exceeds :data:`OUTLIER_CHI2`), and whiten rows with it, so that velocity and
   body-rate residuals (different units, different noise) are weighed by their noise.
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

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

#: Squared whitened residual norm above which a window counts as a gross outlier (about
#: 6 sigma for 6 channels).
OUTLIER_CHI2 = 60.0
#: Largest share of windows that the outlier trimming may leave out.
MAX_OUTLIER_SHARE = 0.02


class SelectionConfig(NamedTuple):
    """Settings of :func:`identify`.

    ``min_explained``: smallest fraction of the remaining residual sum of squares an effect
    must explain to be admissible; ``min_size``: smallest parameter change (largest over
    the effect's parameters, as a share of its plausible range). ``confidence``: bootstrap
    inclusion probability needed to add an effect. ``block``: windows per bootstrap block.
    ``probe``: step of the secants of the linearisations, as a share of the ranges;
    ``probe_scales``: the steps the first one chooses from (:func:`scaled_secants`).
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


class Linearisation(NamedTuple):
    """Whitened per-block sufficient statistics of ``y ~ A delta`` at one point."""

    G: Array  # (n_blocks, P, P)  sum A^T A
    g: Array  # (n_blocks, P)     sum A^T y
    s: Array  # (n_blocks,)       sum y^T y
    n: Array  # (n_blocks,)       number of rows (windows x channels)
    alive: Array  # (P,) bool     parameters the data can see


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


# --------------------------------------------------------------------------- subsets


def group_masks(groups: Sequence[Sequence[int]], n_params: int) -> np.ndarray:
    """Parameter masks ``(2^G, P)`` of every subset of groups (bit ``j`` = group ``j``)."""
    G = len(groups)
    masks = np.zeros((2**G, n_params), dtype=bool)
    for m in range(2**G):
        for j, idx in enumerate(groups):
            if m >> j & 1:
                masks[m, list(idx)] = True
    return masks


def _cholesky_solve(A: Array, b: Array) -> Array:
    """``A^{-1} b`` for a small symmetric positive definite ``A`` (unrolled Cholesky).

    Written with scalar arithmetic only (no in-place updates, no LAPACK call): these
    solves run batched inside the bootstrap (resamples x subsets), where plain arithmetic
    compiles to one fused loop.
    """
    n = A.shape[0]
    L: list[list[Array]] = [[None] * n for _ in range(n)]  # type: ignore[list-item]
    for j in range(n):
        d = A[j, j] - sum((L[j][k] ** 2 for k in range(j)), start=jnp.zeros((), A.dtype))
        L[j][j] = jnp.sqrt(jnp.maximum(d, 1e-300))
        for i in range(j + 1, n):
            acc = A[i, j] - sum((L[i][k] * L[j][k] for k in range(j)), start=jnp.zeros((), A.dtype))
            L[i][j] = acc / L[j][j]
    y: list[Array] = []
    for j in range(n):
        acc = b[j] - sum((L[j][k] * y[k] for k in range(j)), start=jnp.zeros((), A.dtype))
        y.append(acc / L[j][j])
    x: list[Array] = [None] * n  # type: ignore[list-item]
    for j in reversed(range(n)):
        acc = y[j] - sum((L[k][j] * x[k] for k in range(j + 1, n)), start=jnp.zeros((), A.dtype))
        x[j] = acc / L[j][j]
    return jnp.stack(x)


def _solve_masked(G: Array, g: Array, mask: Array, ridge: float = 1e-10) -> Array:
    """Least squares on the columns in ``mask`` (normalised Gram), zeros elsewhere."""
    d = jnp.sqrt(jnp.where(jnp.diag(G) > 0, jnp.diag(G), 1.0))
    Gn = G / d[:, None] / d[None, :]
    m = mask.astype(G.dtype)
    Gm = Gn * m[:, None] * m[None, :] + jnp.diag(1.0 - m) + ridge * jnp.eye(G.shape[0])
    beta = _cholesky_solve(Gm, (g / d) * m)
    return beta / d


_solve_masked_jit = jax.jit(_solve_masked)


def _rss(G: Array, g: Array, s: Array, delta: Array) -> Array:
    return jnp.maximum(s - 2.0 * delta @ g + delta @ G @ delta, 0.0)


class Bounds(NamedTuple):
    """Allowed steps from the base, ``lo <= delta <= hi`` (P,): the plausible ranges."""

    lo: Array
    hi: Array
    span: Array


def _solve_bounded(G: Array, g: Array, mask: Array, bounds: Bounds) -> Array:
    """Masked least squares within the bounds: one active-set pass, then clipping.

    Parameters whose unconstrained estimate leaves ``[lo, hi]`` are held at the bound and
    the others re-solved (a filter time constant that would go negative stays at 0 and the
    delay of the same effect takes the lag); whatever still leaves the range is clipped.
    A parameter held at its base value explains nothing, so an effect that the data would
    only "explain" with an unphysical value fails the relevance test.
    """
    delta = _solve_masked(G, g, mask)
    viol = mask & ((delta < bounds.lo) | (delta > bounds.hi))
    held = jnp.where(viol, jnp.clip(delta, bounds.lo, bounds.hi), 0.0)
    rest = _solve_masked(G, g - G @ held, mask & ~viol)
    return jnp.clip(jnp.where(viol, held, rest), bounds.lo, bounds.hi) * mask


@jax.jit
def subset_rss(G: Array, g: Array, s: Array, masks: Array, bounds: Bounds) -> tuple[Array, Array]:
    """RSS and coefficients of every subset: ``(M,)`` and ``(M, P)``."""
    deltas = jax.vmap(lambda m: _solve_bounded(G, g, m, bounds))(masks)
    return jax.vmap(lambda d: _rss(G, g, s, d))(deltas), deltas


@jax.jit
def choose_subset(
    rss: Array, k: Array, n: Array, group_bits: Array, min_explained: Array, sized: Array
) -> Array:
    """Index of the admissible subset with the smallest BIC (module docstring, step 3).

    ``k`` (M,) free parameters per subset, ``n`` rows, ``group_bits`` (G,) ``1 << j``,
    ``sized`` (M, G) whether each effect's estimate is of relevant size in that subset.
    """
    M = rss.shape[0]
    idx = jnp.arange(M)
    rss = jnp.maximum(rss, 1e-300)
    bic = n * jnp.log(rss / n) + k * jnp.log(n)
    has = (idx[:, None] & group_bits[None, :]) != 0  # (M, G)
    without = rss[idx[:, None] & ~group_bits[None, :]]  # (M, G)
    gain = (without - rss[:, None]) / jnp.maximum(without, 1e-300)
    ok = jnp.all(~has | ((gain >= min_explained) & sized), axis=1)
    return jnp.argmin(jnp.where(ok, bic, jnp.inf))


def _select(
    lin: Linearisation,
    weights: Array,
    masks: Array,
    group_bits,
    min_explained,
    bounds: Bounds,
    min_size,
    members: Array,
):
    G = jnp.einsum("b,bij->ij", weights, lin.G)
    g = jnp.einsum("b,bi->i", weights, lin.g)
    s = weights @ lin.s
    n = weights @ lin.n
    live = masks & lin.alive[None, :]
    rss, deltas = subset_rss(G, g, s, live, bounds)
    k = jnp.sum(live, axis=1)
    # Size of each effect: its largest parameter step as a share of the plausible range.
    rel = jnp.abs(deltas) / bounds.span  # (M, P)
    size = jnp.max(jnp.where(members[None, :, :], rel[:, None, :], 0.0), axis=2)  # (M, G)
    best = choose_subset(rss, k, n, group_bits, min_explained, size >= min_size)
    return best, rss, deltas


@jax.jit
def _bootstrap(
    lin: Linearisation,
    counts: Array,
    masks: Array,
    group_bits,
    min_explained,
    bounds: Bounds,
    min_size,
    members: Array,
    fixed_mask: Array,
):
    def one(w):
        best, _, _ = _select(lin, w, masks, group_bits, min_explained, bounds, min_size, members)
        G = jnp.einsum("b,bij->ij", w, lin.G)
        g = jnp.einsum("b,bi->i", w, lin.g)
        return best, _solve_masked(G, g, fixed_mask & lin.alive)

    return jax.vmap(one)(counts)


# --------------------------------------------------------------------------- linearise


def fd_jacobian(
    residual_fn: Callable[[Array], Array],
    theta: np.ndarray,
    idx: Sequence[int],
    steps: np.ndarray,
    r0: np.ndarray | None = None,
) -> np.ndarray:
    """Forward-difference sensitivities ``d r / d theta_j`` ``(n, c, len(idx))``."""
    theta = np.asarray(theta, dtype=float)
    r0 = np.asarray(residual_fn(jnp.asarray(theta))) if r0 is None else r0
    cols = []
    for j in idx:
        th = theta.copy()
        th[j] += steps[j]
        cols.append((np.asarray(residual_fn(jnp.asarray(th))) - r0) / steps[j])
    return np.stack(cols, axis=-1)


def scaled_secants(
    residual_fn: Callable[[Array], Array],
    theta: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    r0: np.ndarray,
    scales: Sequence[float],
) -> np.ndarray:
    """Secant sensitivities ``(n, c, P)`` at the scale that explains the residual best.

    Per parameter, secants over steps of ``scales`` times its plausible range, both signs,
    within the range; kept is the one whose column alone explains most of ``r0`` (channels
    weighed by their RMS). A lag far larger than a log step (a 0.1 s delay) changes the
    one-step prediction in a way no tangent at zero extrapolates to; the secant over the
    whole range reproduces it exactly, and for a parameter that acts linearly all secants
    agree.
    """
    theta = np.asarray(theta, dtype=float)
    r0 = np.nan_to_num(np.asarray(r0))
    scale = 1.0 / np.maximum(np.sqrt(np.mean(r0**2, axis=0)), 1e-300)
    y = (r0 * scale).reshape(-1)
    span = high - low
    cols = []
    for j in range(theta.shape[0]):
        best, best_score = None, -1.0
        for k in scales:
            for sign in (1.0, -1.0):
                h = sign * k * span[j]
                if not low[j] <= theta[j] + h <= high[j] or h == 0.0:
                    continue
                th = theta.copy()
                th[j] += h
                col = np.nan_to_num((np.asarray(residual_fn(jnp.asarray(th))) - r0) / h)
                a = (col * scale).reshape(-1)
                score = float((a @ y) ** 2 / max(float(a @ a), 1e-300))
                if score > best_score:
                    best, best_score = col, score
        cols.append(best if best is not None else np.zeros_like(r0))
    return np.stack(cols, axis=-1)


def _whitening(e: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whitening matrix from residuals ``e (n, c)`` and the windows kept.

    Gross outliers (squared whitened norm above :data:`OUTLIER_CHI2`) are trimmed, but never
    more than :data:`MAX_OUTLIER_SHARE` of the windows: a model error that affects many
    windows is a gap to explain, not an outlier.
    """
    base = keep.copy()
    keep = keep.copy()
    for _ in range(3):
        cov = np.cov(e[keep].T) + 1e-12 * np.eye(e.shape[1])
        W = np.linalg.inv(np.linalg.cholesky(cov))
        d2 = np.sum((e @ W.T) ** 2, axis=1)
        limit = max(OUTLIER_CHI2, float(np.quantile(d2[base], 1.0 - MAX_OUTLIER_SHARE)))
        keep = base & (d2 <= limit)
    return W, keep


def linearise(
    r0: np.ndarray,
    jac: np.ndarray,
    W: np.ndarray,
    keep: np.ndarray,
    blocks: np.ndarray,
    n_blocks: int,
    span: np.ndarray,
) -> tuple[Linearisation, np.ndarray, np.ndarray]:
    """Whitened block statistics of ``y = W r0 ~ A delta`` with ``A = -W jac``.

    Returns the statistics, the whitened targets ``(n, c)`` and regressors ``(n, c, P)``.
    """
    y = np.einsum("ij,nj->ni", W, r0) * keep[:, None]
    A = -np.einsum("ij,njp->nip", W, jac) * keep[:, None, None]
    Gw = np.einsum("ncp,ncq->npq", A, A)
    gw = np.einsum("ncp,nc->np", A, y)
    sw = np.sum(y * y, axis=1)
    nw = keep * float(y.shape[1])
    G = np.zeros((n_blocks, *Gw.shape[1:]))
    np.add.at(G, blocks, Gw)
    g = np.zeros((n_blocks, gw.shape[1]))
    np.add.at(g, blocks, gw)
    s = np.bincount(blocks, sw, minlength=n_blocks)
    n = np.bincount(blocks, nw, minlength=n_blocks)
    # A parameter is identifiable when moving it across its plausible range changes the
    # whitened residual by more than a thousandth of its size.
    col = np.sqrt(np.maximum(np.einsum("bpp->p", G), 0.0)) * span
    alive = col > 1e-3 * np.sqrt(max(s.sum(), 1e-300))
    lin = Linearisation(
        jnp.asarray(G), jnp.asarray(g), jnp.asarray(s), jnp.asarray(n), jnp.asarray(alive)
    )
    return lin, y, A


# --------------------------------------------------------------------------- nonlinear fit


def fit_nonlinear(
    residual_fn: Callable[[Array], Array],
    theta0: np.ndarray,
    free: Sequence[int],
    low: np.ndarray,
    high: np.ndarray,
    W: np.ndarray,
    keep: np.ndarray,
    steps: np.ndarray,
    iterations: int = 15,
) -> np.ndarray:
    """Projected Levenberg-Marquardt on the whitened residuals over the ``free`` entries.

    Bounds are the plausible ranges (the step is clipped into them).
    """
    theta = np.clip(np.asarray(theta0, dtype=float), low, high)
    free = list(free)
    if not free:
        return theta

    def cost(r):
        return float(np.sum((np.einsum("ij,nj->ni", W, r) * keep[:, None]) ** 2))

    r = np.asarray(residual_fn(jnp.asarray(theta)))
    c = cost(r)
    lam = 1e-3
    for _ in range(iterations):
        J = fd_jacobian(residual_fn, theta, free, steps, r)
        Jw = np.einsum("ij,njp->nip", W, J)[keep].reshape(-1, len(free))
        rw = np.einsum("ij,nj->ni", W, r)[keep].reshape(-1)
        H = Jw.T @ Jw
        grad = Jw.T @ rw
        improved = False
        for _ in range(8):
            step = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), grad)
            cand = theta.copy()
            cand[free] = np.clip(theta[free] + step, low[free], high[free])
            r_c = np.asarray(residual_fn(jnp.asarray(cand)))
            c_c = cost(r_c)
            if np.isfinite(c_c) and c_c < c:
                improved = True
                rel = (c - c_c) / c
                theta, r, c = cand, r_c, c_c
                lam = max(lam / 5.0, 1e-9)
                break
            lam *= 10.0
        if not improved or rel < 1e-9:
            break
    return theta


# --------------------------------------------------------------------------- identify


def identify(
    residual_fn: Callable[[Array], Array],
    theta_base: np.ndarray,
    groups: Sequence[Sequence[int]],
    low: np.ndarray,
    high: np.ndarray,
    config: SelectionConfig | None = None,
) -> Identification:
    """Select, fit and rate effects for the residuals ``residual_fn`` (module docstring)."""
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

    # Whitening from what is left after all candidates (step 2).
    keep = np.isfinite(r_base).all(axis=1)
    W0, _ = _whitening(np.nan_to_num(r_base), keep)
    lin0, _, _ = linearise(
        np.nan_to_num(r_base), np.nan_to_num(jac), W0, keep, blocks, n_blocks, span
    )
    full = _solve_masked_jit(lin0.G.sum(0), lin0.g.sum(0), lin0.alive)
    e_all = r_base + np.einsum("ncp,p->nc", np.nan_to_num(jac), np.asarray(full))
    W, keep = _whitening(np.nan_to_num(e_all), keep)

    ones = jnp.ones(n_blocks)

    def cost(th: np.ndarray) -> float:
        r_th = np.nan_to_num(np.asarray(residual_fn(jnp.asarray(th))), nan=1e6)
        return float(np.sum((r_th @ W.T)[keep] ** 2))

    def fit(sel: tuple[int, ...], start: np.ndarray) -> np.ndarray:
        free = [i for j in sel for i in groups[j] if alive_any[i]]
        th0 = theta_base.copy()
        th0[free] = start[free]
        # Start from the linear estimate or from the previous fit, whichever is better.
        prev = theta_base.copy()
        prev[free] = theta[free]
        th0 = th0 if cost(np.clip(th0, low, high)) <= cost(prev) else prev
        return fit_nonlinear(
            residual_fn, th0, free, low, high, W, keep, steps, config.lm_iterations
        )

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
        best, _, deltas = _select(lin, ones, masks, bits, rho, bounds, min_size, members)
        new = tuple(j for j in range(len(groups)) if int(best) >> j & 1)
        if set(new) <= set(selected) and rounds > 1:
            break
        new = tuple(sorted(set(new) | set(selected)))
        theta = fit(new, theta_base + np.asarray(deltas[int(best)]))
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
    best_b, _ = _bootstrap(lin, counts, masks, bits, rho, bounds, min_size, members, sel_mask)
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
    _, deltas_b = _bootstrap(lin, counts, masks, bits, rho, bounds, min_size, members, conf_mask)
    # Bootstrap estimates around the nonlinear fit: the linear solution's spread.
    G_all = lin.G.sum(0)
    d_full = np.asarray(_solve_masked_jit(G_all, lin.g.sum(0), conf_mask & lin.alive))
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
