"""Figures of the quadrotor evaluation (PNG): Fig. 4 (Gramian), Fig. 5 (tracking errors
around the release, metric bars). Plotting only; the numbers come from
:mod:`benchmarks.quadrotor_openloop` and :mod:`benchmarks.quadrotor_closedloop`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from arcade_io import atomicfile

LABELS = {
    "nominal": "Nominal MPC",
    "l1": "L1-adaptive",
    "gp": "GP-MPC",
    "mlp": "MLP-MPC",
    "ours_no_cp": "Ours (w/o CP)",
    "ours": "Ours",
}
COLORS = {
    "nominal": "tab:gray",
    "l1": "tab:brown",
    "gp": "tab:green",
    "mlp": "tab:orange",
    "ours_no_cp": "tab:cyan",
    "ours": "tab:blue",
}


def _curve(values) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def gramian_figure(path: Path, curves: Mapping[str, Any]) -> Path:
    """Fig. 4: log lambda_min of the feature Gramian (+ windows W), condition, log det."""
    dt = float(curves.get("dt", 1.0))
    lam = _curve(curves["lambda_min"])
    t = np.arange(lam.size) * dt
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
    with np.errstate(divide="ignore", invalid="ignore"):
        a.plot(t, np.log(lam), label=r"$\log\lambda_{\min}(G_t)$", color="k")
        for key, value in curves.items():
            if key.startswith("window_lambda_min_W"):
                w = key.rsplit("W", 1)[1]
                a.plot(
                    t,
                    np.log(_curve(value)),
                    label=rf"$\log\lambda_{{\min}}(G_t^{{({w})}})$",
                    lw=0.8,
                )
    a.set_xlabel("time [s]")
    a.set_title("persistent excitation")
    a.legend(fontsize=8)
    b.plot(t, _curve(curves["condition"]), color="tab:red", label=r"$\kappa(G_t)$")
    b.set_yscale("log")
    b.set_xlabel("time [s]")
    b.set_ylabel("condition number", color="tab:red")
    b2 = b.twinx()
    b2.plot(t, _curve(curves["logdet"]), color="tab:blue", label=r"$\log\det G_t$")
    b2.set_ylabel("log det", color="tab:blue")
    b.set_title("conditioning and information volume")
    fig.tight_layout()
    atomicfile.save_figure(fig, path, dpi=120)
    plt.close(fig)
    return path


def tracking_error_figure(path: Path, flights: Mapping[str, Any], window_s: float = 4.0) -> Path:
    """Fig. 5 (left): x, y, z tracking errors of every method around the release."""
    fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    t_rel = None
    for name, f in flights.items():
        t_rel = f.t_release
        sel = (f.t >= t_rel - window_s) & (f.t <= t_rel + window_s)
        err = f.error
        for i, ax in enumerate(axes):
            ax.plot(
                f.t[sel] - t_rel,
                err[sel, i],
                label=LABELS.get(name, name),
                color=COLORS.get(name),
                lw=1.2 if name == "ours" else 0.9,
            )
    for i, ax in enumerate(axes):
        ax.axvline(0.0, color="k", ls="--", lw=0.8)
        ax.set_ylabel(f"e_{'xyz'[i]} [m]")
        ax.grid(alpha=0.3)
    axes[2].axhspan(-0.05, 0.05, color="k", alpha=0.07)
    axes[-1].set_xlabel("time from release [s]")
    axes[0].legend(fontsize=8, ncol=3)
    if t_rel is not None:
        f0 = next(iter(flights.values()))
        axes[0].set_title(
            f"{f0.scenario.payload_g:g} g, {f0.scenario.speed_mps:g} m/s: "
            "tracking errors around the payload release"
        )
    fig.tight_layout()
    atomicfile.save_figure(fig, path, dpi=120)
    plt.close(fig)
    return path


def metric_bars_figure(path: Path, rows: Sequence[Mapping[str, Any]]) -> Path:
    """Fig. 5 (right): RMSE, z-RMSE, shift and settling per method, averaged over all
    ``rows`` (per-trial or per-cell dicts with a ``method`` key).

    Crashed or never-settled entries are infinite: a bar then shows the mean of the finite
    ones and is hatched; with no finite entry it is replaced by an "inf" mark.
    """
    methods = list(dict.fromkeys(r["method"] for r in rows))
    keys = [
        ("rmse_m", "RMSE [m]"),
        ("rmse_z_m", "z-RMSE [m]"),
        ("shift_m", "shift [m]"),
        ("settling_s", "settling [s]"),
    ]
    fig, axes = plt.subplots(1, 4, figsize=(13, 3.4))
    for ax, (key, label) in zip(axes, keys):
        means, hatched = [], []
        for m in methods:
            v = np.array([r[key] for r in rows if r["method"] == m], float)
            finite = v[np.isfinite(v)]
            means.append(float(finite.mean()) if finite.size else 0.0)
            hatched.append(finite.size < v.size)
        bars = ax.bar(range(len(methods)), means, color=[COLORS.get(m, "k") for m in methods])
        for i, (bar, h) in enumerate(zip(bars, hatched)):
            if h:
                bar.set_hatch("//")
            if h and means[i] == 0.0:
                ax.text(i, 0.0, "inf", ha="center", va="bottom", fontsize=8)
        ax.set_xticks(range(len(methods)))
        ax.set_xticklabels([LABELS.get(m, m) for m in methods], rotation=45, ha="right", fontsize=8)
        ax.set_title(label)
        ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    atomicfile.save_figure(fig, path, dpi=120)
    plt.close(fig)
    return path
