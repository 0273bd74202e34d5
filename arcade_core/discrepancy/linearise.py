"""Linearising the prediction residuals in the effect parameters, and the nonlinear fit
(design §6, step 3; :mod:`arcade_core.discrepancy.identify` puts them together).

The residual ``r(theta)`` of the short-horizon predictions is linearised as ``r_0 - A
(theta - theta_base)`` with secant sensitivities (:func:`scaled_secants`,
:func:`fd_jacobian`), whitened by the channel covariance of what is left (gross outliers
trimmed, :func:`whitening`), and reduced to per-block sufficient statistics
(:func:`linearise`) that the subset selection and the bootstrap resample. The selected
effects are then fitted on the full nonlinear model (:func:`fit_nonlinear`, projected
Levenberg-Marquardt within the plausible ranges).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array

#: Squared whitened residual norm above which a window counts as a gross outlier (about
#: 6 sigma for 6 channels).
OUTLIER_CHI2 = 60.0
#: Largest share of windows that the outlier trimming may leave out.
MAX_OUTLIER_SHARE = 0.02
#: Carriers of an effect (:func:`carried_secants`) kept: those under which it adds at least
#: this share of what it adds under the best one.
CARRIER_SHARE = 0.5


class Linearisation(NamedTuple):
    """Whitened per-block sufficient statistics of ``y ~ A delta`` at one point."""

    G: Array  # (n_blocks, P, P)  sum A^T A
    g: Array  # (n_blocks, P)     sum A^T y
    s: Array  # (n_blocks,)       sum y^T y
    n: Array  # (n_blocks,)       number of rows (windows x channels)
    alive: Array  # (P,) bool     parameters the data can see


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
    idx: Sequence[int] | None = None,
    target: np.ndarray | None = None,
) -> np.ndarray:
    """Secant sensitivities ``(n, c, P)`` at the scale that explains the residual best.

    Per parameter, secants over steps of ``scales`` times its plausible range, both signs,
    within the range; kept is the one whose column alone explains most of ``target``
    (default ``r0``, the residual at ``theta``; channels weighed by their RMS). A lag far
    larger than a log step (a 0.1 s delay) changes the one-step prediction in a way no
    tangent at zero extrapolates to; the secant over the whole range reproduces it
    exactly, and for a parameter that acts linearly all secants agree. A step whose
    prediction is not finite where ``r0`` is gives no secant. ``idx``: only these
    parameters (``(n, c, len(idx))``).
    """
    theta = np.asarray(theta, dtype=float)
    finite = np.isfinite(np.asarray(r0))
    r0 = np.nan_to_num(np.asarray(r0))
    target = r0 if target is None else np.nan_to_num(np.asarray(target))
    scale = 1.0 / np.maximum(np.sqrt(np.mean(target**2, axis=0)), 1e-300)
    y = (target * scale).reshape(-1)
    span = high - low
    cols = []
    for j in range(theta.shape[0]) if idx is None else idx:
        best, best_score = None, -1.0
        for k in scales:
            for sign in (1.0, -1.0):
                h = sign * k * span[j]
                if not low[j] <= theta[j] + h <= high[j] or h == 0.0:
                    continue
                th = theta.copy()
                th[j] += h
                r_h = np.asarray(residual_fn(jnp.asarray(th)))
                if not np.isfinite(r_h[finite]).all():  # no secant into a broken prediction
                    continue
                col = np.nan_to_num((r_h - r0) / h)
                a = (col * scale).reshape(-1)
                score = float((a @ y) ** 2 / max(float(a @ a), 1e-300))
                if score > best_score:
                    best, best_score = col, score
        cols.append(best if best is not None else np.zeros_like(r0))
    return np.stack(cols, axis=-1)


def carried_secants(
    residual_fn: Callable[[Array], Array],
    theta: np.ndarray,
    groups: Sequence[Sequence[int]],
    low: np.ndarray,
    high: np.ndarray,
    r0: np.ndarray,
    jac: np.ndarray,
    scales: Sequence[float],
    min_gain: float,
    candidates: dict[int, Sequence[int]] | None = None,
) -> tuple[np.ndarray, dict[int, list[tuple[int, np.ndarray, np.ndarray]]]]:
    """Secants of the effects that do not move the residual at ``theta`` because they act
    through another one (wind through drag), taken where that one is on.

    For each group whose columns of ``jac`` are all zero, each other group (or each of its
    ``candidates``, the groups the model says it acts through) is switched on at the bound
    of its plausible range farther from ``theta``; it is a *carrier* if the first group
    then moves the residual. The group's :func:`scaled_secants` (over the two largest of
    ``scales``: this is a search, not a fit) are taken under each carrier. What
    they add is the share of ``r0`` that all columns of ``jac`` leave and they explain
    (least squares, channels weighed by their RMS): under a carrier through which the
    group only repeats what another effect does (wind through the thrust's inflow loss
    acts as a thrust scale) it adds nothing. Carriers under which the group adds at least
    ``min_gain`` and :data:`CARRIER_SHARE` of what it adds under the best one are kept,
    best first; the group's columns become those under the best. Returns ``jac`` with
    those columns, and per such group its carriers, each with the parameter vector at
    which the secants were taken (the linear model assumes the first carrier at that
    value) and the secants there. Groups no carrier adds to stay at zero.
    """
    jac = np.array(jac, dtype=float)
    theta = np.asarray(theta, dtype=float)
    r0 = np.nan_to_num(np.asarray(r0))
    weight = 1.0 / np.maximum(np.sqrt(np.mean(r0**2, axis=0)), 1e-300)
    y = (r0 * weight).reshape(-1)
    span = high - low
    coarse = sorted(scales)[-2:]
    dead = [j for j, idx in enumerate(groups) if not np.any(jac[..., list(idx)])]
    live = [i for i in range(theta.shape[0]) if np.any(jac[..., i])]
    A0 = (np.nan_to_num(jac[..., live]) * weight[None, :, None]).reshape(-1, len(live))
    # What the columns of jac leave: projections onto the orthogonal complement of their span.
    U, sv, _ = np.linalg.svd(A0, full_matrices=False)
    U = U[:, sv > 1e-10 * max(float(sv[0]), 1e-300)] if sv.size else U

    def rest(a: np.ndarray) -> np.ndarray:
        return a - U @ (U.T @ a)

    e0 = rest(y)
    rss0 = float(e0 @ e0)
    carried: dict[int, list[tuple[int, np.ndarray, np.ndarray]]] = {}
    for j in dead:
        idx = list(groups[j])
        found = []
        for k, idx_k in enumerate(groups):
            if k in dead or (candidates is not None and k not in candidates.get(j, ())):
                continue
            ctx = theta.copy()
            for i in idx_k:
                ctx[i] = low[i] if abs(low[i] - theta[i]) > abs(high[i] - theta[i]) else high[i]
            r_ctx = np.nan_to_num(np.asarray(residual_fn(jnp.asarray(ctx))))
            if candidates is None:  # one probe of the whole group first: a carrier at all?
                probe = ctx.copy()
                for i in idx:
                    h = max(scales) * span[i]
                    probe[i] = ctx[i] + h if ctx[i] + h <= high[i] else ctx[i] - h
                moved = np.nan_to_num(np.asarray(residual_fn(jnp.asarray(probe)))) - r_ctx
                if not np.any(moved):
                    continue
            cols = scaled_secants(residual_fn, ctx, low, high, r_ctx, coarse, idx, target=r0)
            C = rest((cols * weight[None, :, None]).reshape(-1, len(idx)))
            coef, *_ = np.linalg.lstsq(C, e0, rcond=None)
            gain = float(e0 @ (C @ coef)) / max(rss0, 1e-300)
            if gain >= min_gain:
                found.append((gain, k, ctx, cols))
        if found:
            found.sort(key=lambda f: -f[0])
            jac[..., idx] = found[0][3]
            lead = found[0][0]
            carried[j] = [(k, c, cols) for g, k, c, cols in found if g >= CARRIER_SHARE * lead]
    return jac, carried


def whitening(e: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
