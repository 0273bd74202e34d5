"""Localising a model gap: by state component, by regime, by time segment (design §6,
step 2).

Regimes: residuals binned by quantiles of a regime variable (speed, height, thrust, tilt,
...), RMS per bin and component. Time segments come for free from the changepoint machinery
of Algorithm 1 (:mod:`arcade_core.adaptation`): the whitened residual is modelled as a mean
``theta * 1`` that may jump (one constant feature, ``d`` = channels), and the changepoints
on the MAP path of the beam split the log into segments of homogeneous model error.
:func:`localise_gap` is the workflow's step: all three for the current model.
"""

from __future__ import annotations

import itertools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from arcade_core import adaptation, frames
from arcade_core.discrepancy.prediction import rms


class Segmenter(NamedTuple):
    """Algorithm 1 hyperparameters for segmenting whitened residuals (unit noise)."""

    K: int = 5
    pi: float = 0.005
    beta: float = 0.3
    tau2: float = 1.0
    sigma2: float = 1.0


@jax.jit
def _map_last_changepoints(resid: Array, pi, beta, tau2, sigma2, theta0: Array) -> Array:
    config = adaptation.AdaptationConfig(
        K=theta0.shape[0], pi=pi, beta=beta, tau2=tau2, sigma2=sigma2
    )
    state = adaptation.init(theta0[0], config)
    one = jnp.ones((1,), resid.dtype)

    def body(state, delta):
        state, _, info = adaptation.step(state, one, delta, config)
        return state, info.map_last_changepoint

    return jax.lax.scan(body, state, resid)[1]


def changepoints(resid: Array, seg: Segmenter | None = None, min_gap: int = 1) -> np.ndarray:
    """Changepoint indices (ascending) of whitened residuals ``resid (n, c)`` (Algorithm 1).

    The MAP path's changepoints are recovered by backtracking the per-step latest
    changepoint of the MAP hypothesis; changepoints closer than ``min_gap`` are merged.
    """
    seg = Segmenter() if seg is None else seg
    resid = jnp.asarray(resid)
    theta0 = jnp.zeros((seg.K, resid.shape[1], 1), resid.dtype)
    last = np.asarray(_map_last_changepoints(resid, seg.pi, seg.beta, seg.tau2, seg.sigma2, theta0))
    # map_last_changepoint counts processed observations: a changepoint at step k means
    # observation k-1 (0-based) starts a new segment.
    cps: list[int] = []
    c = int(last[-1])
    while c > 0:
        cps.append(c - 1)
        c = int(last[c - 2]) if c >= 2 else -1
    cps = sorted(set(cps))
    merged: list[int] = []
    for c in cps:
        if c > 0 and (not merged or c - merged[-1] >= min_gap):
            merged.append(c)
    return np.asarray(merged, dtype=int)


class Binned(NamedTuple):
    """Residual RMS per quantile bin of one regime variable."""

    edges: np.ndarray  # (bins + 1,)
    rms: np.ndarray  # (bins, c)
    count: np.ndarray  # (bins,)


def binned_rms(resid: Array, variable: Array, bins: int = 4) -> Binned:
    """RMS of ``resid (n, c)`` in ``bins`` quantile bins of ``variable (n,)``."""
    resid = np.asarray(resid)
    var = np.asarray(variable)
    edges = np.quantile(var, np.linspace(0.0, 1.0, bins + 1))
    idx = np.clip(np.searchsorted(edges, var, side="right") - 1, 0, bins - 1)
    count = np.bincount(idx, minlength=bins)
    ss = np.zeros((bins, resid.shape[1]))
    np.add.at(ss, idx, resid**2)
    rms = np.sqrt(ss / np.maximum(count, 1)[:, None])
    return Binned(edges, rms, count)


def segment_rms(resid: Array, cps: np.ndarray) -> list[tuple[int, int, np.ndarray]]:
    """``(start, stop, rms per component)`` of the segments between changepoints."""
    resid = np.asarray(resid)
    bounds = [0, *[int(c) for c in cps], resid.shape[0]]
    return [
        (a, b, np.sqrt(np.mean(resid[a:b] ** 2, axis=0)))
        for a, b in itertools.pairwise(bounds)
        if b > a
    ]


def localise_gap(model, X, U, dt, starts, H, theta, W) -> dict[str, Any]:
    """The workflow's step 2: the one-step residual of ``model`` at ``theta`` (a
    :class:`~arcade_core.discrepancy.prediction.DiscrepancyModel`) over the windows
    ``starts`` of ``H`` samples, by component, regime and time segment.

    Residuals of the velocity/rate channels are expressed in units of their noise level
    (``sigma`` from the whitening ``W`` of what is left after fitting every candidate
    effect), so "4 x noise" reads the same for m/s and rad/s and a noisy channel does not
    look like a gap. Regimes: speed, height, thrust, tilt (quadrotor); cart speed, pole
    rate, pole angle, force (cartpole).
    """
    err = model.errors(X, model.predict(theta, X, U, starts, H, dt), starts, H)[:, -1]
    comps = list(model.components)
    dyn = [
        comps.index(c)
        for c in (
            ("vx", "vy", "vz", "wx", "wy", "wz")
            if model.name == "quadrotor"
            else ("xdot", "thetadot")
        )
    ]
    W = np.asarray(W)
    sigma = np.sqrt(np.diag(np.linalg.inv(W.T @ W)))
    norm = err[:, dyn] / sigma
    names = [comps[d] for d in dyn]
    x0 = X[starts]
    if model.name == "quadrotor":
        r22 = frames.to_rotation_matrix_np(x0[:, 6:10])[:, 2, 2]
        tilt = np.degrees(np.arccos(np.clip(r22, -1.0, 1.0)))
        regimes = {
            "speed_mps": np.linalg.norm(x0[:, 3:6], axis=1),
            "height_m": x0[:, 2],
            "thrust_n": U[starts, 0],
            "tilt_deg": tilt,
        }
    else:
        regimes = {
            "cart_speed_mps": np.abs(x0[:, 1]),
            "pole_rate_rad_s": np.abs(x0[:, 3]),
            "pole_cos": np.cos(x0[:, 2]),
            "force_n": np.abs(U[starts, 0]),
        }
    overall = rms(norm)
    by_regime, findings = {}, []
    for name, var in regimes.items():
        b = binned_rms(norm, var, bins=4)
        by_regime[name] = {
            "edges": b.edges.tolist(),
            "rms": {c: b.rms[:, i].tolist() for i, c in enumerate(names)},
        }
        for i, c in enumerate(names):
            k = int(np.argmax(b.rms[:, i]))
            findings.append(
                (
                    float(b.rms[k, i]),
                    float(b.rms[k, i] / max(overall[i], 1e-12)),
                    name,
                    c,
                    b.edges[k],
                    b.edges[k + 1],
                )
            )
    # Regimes where a component's gap concentrates: most noise levels, then most contrast.
    findings.sort(key=lambda f: -f[0] * f[1])
    cps = changepoints(norm @ np.eye(len(names)), min_gap=max(1, round(1.0 / (H * dt))))
    t0 = starts * dt
    segments = [
        {"t_start": float(t0[a]), "t_end": float(t0[b - 1] + H * dt),
         "rms_noise": {c: float(r[i]) for i, c in enumerate(names)}}
        for a, b, r in segment_rms(norm, cps)
    ]  # fmt: skip
    summary = {
        "rmse": {comps[i]: float(v) for i, v in enumerate(rms(err))},
        "rms_noise": {c: float(v) for c, v in zip(names, overall)},
        "noise": {c: float(v) for c, v in zip(names, sigma)},
        "largest": names[int(np.argmax(overall))],
        "regimes": [
            {"regime": f, "bin": [float(lo), float(hi)], "component": c, "rms_noise": r, "ratio": q}
            for r, q, f, c, lo, hi in findings[:3]
        ],
        "segments": segments,
    }
    return {"summary": summary, "by_regime": by_regime, "err": err, "t": t0}
