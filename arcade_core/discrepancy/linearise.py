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
