"""Choosing among subsets of effects: bounded least squares on every subset, BIC with
relevance tests, and the block bootstrap of that choice (design §6, step 3;
:mod:`arcade_core.discrepancy.identify` puts the steps together).

Every subset of the ``G`` candidate effects is solved at once from the whitened per-block
sufficient statistics (:class:`~arcade_core.discrepancy.linearise.Linearisation`), within
the plausible ranges (:class:`Bounds`); :func:`choose_subset` picks the admissible subset
with the smallest BIC. The selection over subsets and the bootstrap are jitted and
vectorised.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from arcade_core.discrepancy.linearise import Linearisation


def group_masks(groups: Sequence[Sequence[int]], n_params: int) -> np.ndarray:
    """Parameter masks ``(2^G, P)`` of every subset of groups (bit ``j`` = group ``j``)."""
    G = len(groups)
    masks = np.zeros((2**G, n_params), dtype=bool)
    for m in range(2**G):
        for j, idx in enumerate(groups):
            if m >> j & 1:
                masks[m, list(idx)] = True
    return masks


@jax.jit
def _cholesky_solve(A: Array, b: Array) -> Array:
    """``A^{-1} b`` for a small symmetric positive definite ``A`` (unrolled Cholesky).

    Written with scalar arithmetic only (no in-place updates, no LAPACK call): these
    solves run batched inside the bootstrap (resamples x subsets), where plain arithmetic
    compiles to one fused loop. Jitted on its own so that the functions that call it
    trace its thousands of scalar operations once per process, not at every call site
    (XLA inlines it: the same arithmetic and results; a process's first workflow run
    traces for about 6 CPU-seconds less).
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


solve_masked_jit = jax.jit(_solve_masked)


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


def select_subset(
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
def bootstrap_selection(
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
        best, _, _ = select_subset(
            lin, w, masks, group_bits, min_explained, bounds, min_size, members
        )
        G = jnp.einsum("b,bij->ij", w, lin.G)
        g = jnp.einsum("b,bi->i", w, lin.g)
        return best, _solve_masked(G, g, fixed_mask & lin.alive)

    return jax.vmap(one)(counts)
