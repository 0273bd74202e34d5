"""Evaluation metrics of Sec. V: prediction (CRMSE), tracking (RMSE), drop response
(shift magnitude, settling time) and latent-feature Gramian diagnostics (Sec. V-B, Fig. 4),
plus one diagnostic the paper does not report: how much the commands jump from one control
period to the next (:func:`increment_rms`).

All functions are pure JAX on arrays with a leading time axis, jit-friendly (``t_drop``
may be traced; window lengths are static).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

# --------------------------------------------------------------------------- prediction


def _float(a: Array) -> Array:
    a = jnp.asarray(a)
    return a if jnp.issubdtype(a.dtype, jnp.floating) else a.astype(float)


def crmse_curve(x: Array, x_hat: Array) -> Array:
    """Cumulative RMSE curve, Sec. V-A footnote: ``c_T = sum_{k<=T} sqrt(mean_j (x_k^j -
    x_hat_k^j)^2)`` for every ``T``. ``x``, ``x_hat``: ``(T, D)`` (or ``(T,)`` for D = 1)."""
    err = jnp.asarray(x) - jnp.asarray(x_hat)
    err = err[:, None] if err.ndim == 1 else err
    return jnp.cumsum(jnp.sqrt(jnp.mean(err**2, axis=-1)))


def crmse(x: Array, x_hat: Array) -> Array:
    """CRMSE of Sec. V-A (footnote): ``sum_{k=1}^T sqrt(1/D sum_j (x_k^j - x_hat_k^j)^2)``."""
    return crmse_curve(x, x_hat)[-1]


def rmse(x: Array, x_hat: Array) -> Array:
    """Root mean square over all samples and components."""
    return jnp.sqrt(jnp.mean((jnp.asarray(x) - jnp.asarray(x_hat)) ** 2))


def rmse_per_component(x: Array, x_hat: Array) -> Array:
    """RMSE of each component over time: ``(T, D) -> (D,)``."""
    return jnp.sqrt(jnp.mean((jnp.asarray(x) - jnp.asarray(x_hat)) ** 2, axis=0))


def position_rmse(p: Array, p_ref: Array) -> Array:
    """Tracking RMSE of positions (Sec. V-B, "combined RMS"): ``sqrt(mean_t ||p_t -
    p_ref_t||^2)`` for ``(T, 3)`` arrays."""
    return jnp.sqrt(jnp.mean(jnp.sum((jnp.asarray(p) - jnp.asarray(p_ref)) ** 2, axis=-1)))


def z_rmse(p: Array, p_ref: Array) -> Array:
    """Height tracking RMSE (Sec. V-B, "z-axis RMS"): RMS of the third position component."""
    return jnp.sqrt(jnp.mean((jnp.asarray(p)[:, 2] - jnp.asarray(p_ref)[:, 2]) ** 2))


# --------------------------------------------------------------------------- drop response


def shift_magnitude(t: Array, e_z: Array, t_drop: float | Array, window: float = 0.5) -> Array:
    """Shift magnitude ``|e_z(t_drop^+) - e_z(t_drop^-)|`` (Sec. V-B).

    Sampled definition:

    * ``e_z(t_drop^-)`` is the last sample with ``t <= t_drop``: a state sampled at the
      release instant was measured before the release could act on it.
    * ``e_z(t_drop^+)`` is the sample in ``(t_drop, t_drop + window]`` whose error differs
      most from ``e_z(t_drop^-)``. A released mass changes the *acceleration*, so the
      tracking error grows over a few control periods rather than jumping between two
      samples; the one-sample difference would mostly measure the sampling rate. The
      extreme deviation within a short window (default 0.5 s, a fraction of the closed-loop
      settling time) is the step the controller actually suffered.

    Returns NaN when there is no sample on one side of ``t_drop``.
    """
    t, e_z = _float(t), _float(e_z)
    before = t <= t_drop
    after = (t > t_drop) & (t <= t_drop + window)
    i_before = jnp.max(jnp.where(before, jnp.arange(t.shape[0]), -1))
    e_before = e_z[jnp.maximum(i_before, 0)]
    change = jnp.max(jnp.where(after, jnp.abs(e_z - e_before), -jnp.inf))
    valid = (i_before >= 0) & jnp.any(after)
    return jnp.where(valid, change, jnp.nan)


class Settling(NamedTuple):
    """``time``: seconds from ``t_drop`` until the error stays in the band (``inf`` if
    it never does, NaN without samples after ``t_drop``); ``settled``: False when the
    last sample is still outside the band or there is no sample after ``t_drop``."""

    time: Array
    settled: Array


def settling_time(t: Array, e: Array, t_drop: float | Array, band: float = 0.05) -> Settling:
    """Settling time after the drop (Sec. V-B): time from ``t_drop`` until ``|e(t)| <=
    band`` for all later samples.

    Sampled definition: with ``v`` the last sample at ``t >= t_drop`` outside the band, the
    error is considered settled from the next sample, so the time is ``t[v+1] - t_drop``
    (resolution one sample period); 0 if no sample after ``t_drop`` leaves the band. If
    the last sample is outside the band the response never settled within the record:
    ``time = inf`` and ``settled = False`` (a finite number would understate it). A
    non-finite error counts as outside the band (a diverged state is not settled). With
    no sample at or after ``t_drop`` the time is undefined: ``time = NaN`` and ``settled =
    False``, as :func:`shift_magnitude` returns NaN then. ``e`` is a scalar error per
    sample ``(T,)``; pass a norm for vector errors.
    """
    t, e = _float(t), jnp.asarray(e)
    n = t.shape[0]
    after = t >= t_drop
    outside = after & ~(jnp.abs(e) <= band)  # NaN compares False: outside
    last_out = jnp.max(jnp.where(outside, jnp.arange(n), -1))
    observed = jnp.any(after)
    settled = observed & (last_out < n - 1)
    t_settle = t[jnp.clip(last_out + 1, 0, n - 1)] - t_drop
    time = jnp.where(last_out < 0, 0.0, jnp.where(settled, t_settle, jnp.inf))
    time = jnp.where(observed, time, jnp.nan)
    return Settling(time.astype(t.dtype), settled)


def increment_rms(u: Array) -> Array:
    """RMS of the step-to-step change of a command sequence ``u (T, m)``, per channel ``(m,)``.

    Not a paper metric: a smoothness diagnostic of the commands a controller sends (a
    vehicle feels a jumpy thrust or rate setpoint as vibration and motor heat, and two
    controllers with the same tracking error can differ several-fold in it).
    """
    du = jnp.diff(_float(u), axis=0)
    return jnp.sqrt(jnp.mean(du**2, axis=0))


# --------------------------------------------------------------------------- Gramian


class GramianDiagnostics(NamedTuple):
    """Sec. V-B / Fig. 4 diagnostics of the feature Gramian ``G_t = sum_{i<=t} z_i z_i^T``
    at every step ``t`` (arrays of length ``T``):

    * ``lambda_min``, ``lambda_max``: extreme eigenvalues (persistent excitation);
    * ``condition``: ``lambda_max / lambda_min`` (``inf`` while ``G_t`` is singular, i.e.
      ``lambda_min <= 0`` numerically);
    * ``logdet``: ``log det G_t`` (``-inf`` while singular);
    * ``window_lambda_min``: ``(len(windows), T)``, ``lambda_min`` of the sliding-window
      Gramian ``G_t^(W) = sum_{i=t-W+1}^t z_i z_i^T``; NaN for ``t < W - 1`` where the window
      is not yet full (a partial window would read as a spurious excitation dip);
    * ``windows``: the window lengths, in the order of ``window_lambda_min``.
    """

    lambda_min: Array
    lambda_max: Array
    condition: Array
    logdet: Array
    window_lambda_min: Array
    windows: Array


def gramian_diagnostics(z: Array, windows: tuple[int, ...] = (15, 30)) -> GramianDiagnostics:
    """Gramian diagnostics of latent features ``z`` ``(T, l)`` (Sec. V-B, Fig. 4).

    The cumulative Gramian is a cumulative sum of outer products; each sliding window is
    summed directly (``reduce_window``) rather than as a difference of cumulative sums,
    which would cancel catastrophically in float32 on long flights.
    """
    z = jnp.asarray(z)
    outer = z[:, :, None] * z[:, None, :]
    eig = jnp.linalg.eigvalsh(jnp.cumsum(outer, axis=0))
    lam_min, lam_max = eig[:, 0], eig[:, -1]
    positive = lam_min > 0
    condition = jnp.where(positive, lam_max / jnp.where(positive, lam_min, 1.0), jnp.inf)
    logdet = jnp.where(
        positive, jnp.sum(jnp.log(jnp.where(positive[:, None], eig, 1.0)), axis=-1), -jnp.inf
    )
    windows = tuple(int(w) for w in windows)
    rows = [_window_lambda_min(outer, w) for w in windows]
    window_min = jnp.stack(rows) if rows else jnp.zeros((0, z.shape[0]), z.dtype)
    sizes = jnp.asarray(windows, dtype=jnp.int32)
    return GramianDiagnostics(lam_min, lam_max, condition, logdet, window_min, sizes)


def _window_lambda_min(outer: Array, w: int) -> Array:
    n = outer.shape[0]
    if w < 1:
        raise ValueError(f"window length must be positive, got {w}")
    if w > n:
        return jnp.full((n,), jnp.nan, outer.dtype)
    sums = jax.lax.reduce_window(
        outer, jnp.zeros((), outer.dtype), jax.lax.add, (w, 1, 1), (1, 1, 1), "VALID"
    )
    lam = jnp.linalg.eigvalsh(sums)[:, 0]
    return jnp.concatenate([jnp.full((w - 1,), jnp.nan, outer.dtype), lam])
