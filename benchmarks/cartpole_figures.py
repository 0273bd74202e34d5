"""Figures of the cartpole evaluation (paper Fig. 3 and Appendix E Fig. 6)."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from arcade_control import cartpole as cd
from arcade_core import adaptation
from arcade_io import atomicfile

LABELS = ("x [m]", "xdot [m/s]", "theta [rad]", "thetadot [rad/s]")


def online_rollout(path: Path, data: cd.Batch, ours_out, i: int = 0) -> None:
    """Fig. 3 bottom: one-step predictions with the 2-sigma band and detected changepoints."""
    xhat, std, flags, cp_prob = (np.asarray(a[i]) for a in ours_out)
    X = data.X[i]
    k = np.arange(1, X.shape[0])
    fig, axes = plt.subplots(5, 1, figsize=(9, 10), sharex=True)
    for j, ax in enumerate(axes[:4]):
        ax.plot(k, X[1:, j], "k", lw=1.2, label="true")
        ax.plot(k, xhat[:, j], "C0", lw=1.0, label="ours (one-step prediction)")
        ax.fill_between(
            k,
            xhat[:, j] - 2 * std[:, j],
            xhat[:, j] + 2 * std[:, j],
            color="C0",
            alpha=0.25,
            label="±2σ predictive",
        )
        ax.set_ylabel(LABELS[j])
    axes[4].plot(np.arange(len(cp_prob)), cp_prob, "C3")
    axes[4].set_ylabel("p(c_k = 1)")
    axes[4].set_xlabel("step k")
    for ax in axes:
        for t in cd.INTERVENTION_STEPS:
            ax.axvline(t, color="0.5", lw=0.8)
        for t in np.flatnonzero(flags):
            ax.axvline(t, color="r", ls="--", lw=0.8)
    axes[0].legend(loc="upper right", fontsize=7)
    axes[0].set_title("Online rollout: grey = interventions, red dashed = detected changepoints")
    fig.tight_layout()
    atomicfile.save_figure(fig, path, dpi=110)
    plt.close(fig)


def offline_distribution(path: Path, per_split: dict[str, list[np.ndarray]]) -> None:
    """Fig. 3 top: distribution of test-trajectory CRMSE per split for each method."""
    names = list(per_split)
    n_splits = len(per_split[names[0]])
    fig, ax = plt.subplots(figsize=(10, 4.5))
    width = 0.8 / len(names)
    for m, name in enumerate(names):
        pos = np.arange(n_splits) + (m - (len(names) - 1) / 2) * width
        bp = ax.boxplot(
            per_split[name], positions=pos, widths=width * 0.9, patch_artist=True, showfliers=False
        )
        for box in bp["boxes"]:
            box.set_facecolor(f"C{m}")
        ax.plot([], [], color=f"C{m}", lw=6, label=name)
    ax.set_xticks(np.arange(n_splits), [str(s + 1) for s in range(n_splits)])
    ax.set_xlabel("train/test split")
    ax.set_ylabel("CRMSE per test trajectory")
    ax.set_yscale("log")
    ax.legend(ncol=3, fontsize=8)
    ax.set_title("Offline one-step prediction error (stationary dynamics)")
    fig.tight_layout()
    atomicfile.save_figure(fig, path, dpi=110)
    plt.close(fig)


def _ellipse(cov: np.ndarray, n: int = 100) -> np.ndarray:
    w, v = np.linalg.eigh(cov)
    t = np.linspace(0, 2 * np.pi, n)
    return (v @ np.diag(np.sqrt(np.maximum(w, 0))) @ np.stack([np.cos(t), np.sin(t)])).T


def latent_comparison(path: Path, models, data: cd.Batch, output: int = 3) -> None:
    """Appendix E: latent embeddings (coloured by pole angle) and BLR posterior ellipses.

    The ellipses are one-standard-deviation contours of the decoder-row posterior for output
    ``output`` (thetadot) after conditioning on growing subsets of the offline data.
    """
    x, u, xn = cd.transitions(data)
    sub = np.random.default_rng(0).choice(x.shape[0], min(2000, x.shape[0]), replace=False)
    x, u, xn = x[sub], u[sub], xn[sub]
    delta = xn - cd.nominal_next(x, u)
    fig, axes = plt.subplots(2, 2, figsize=(10, 9))
    for row, (name, model) in enumerate((("deterministic", models.det), ("VLD", models.vld))):
        z = np.asarray(jax.vmap(model.features)(jnp.asarray(x), jnp.asarray(u)))
        ax = axes[row, 0]
        sc = ax.scatter(z[:, 0], z[:, 1], c=x[:, 2], s=4, cmap="coolwarm")
        fig.colorbar(sc, ax=ax, label="theta [rad]")
        ax.set_title(f"{name} encoder: latent embedding")
        ax.set_xlabel("z1")
        ax.set_ylabel("z2")
        ax = axes[row, 1]
        dn = np.asarray(jax.vmap(model.normalise_residual)(jnp.asarray(delta)))
        cfg = adaptation.AdaptationConfig(K=1, pi=0.0, beta=1.0, tau2=0.1, sigma2=0.1)
        state = adaptation.init(model.theta0, cfg)
        upd = jax.jit(lambda s, z, d, cfg=cfg: adaptation.update(s, z, d, cfg)[0])
        marks = (0, 5, 20, 100, 500)
        for i in range(max(marks) + 1):
            if i in marks:
                mean = np.asarray(state.means[0, output])
                cov = np.asarray(state.covariances[0, output])
                e = _ellipse(cov) + mean
                ax.plot(e[:, 0], e[:, 1], label=f"n = {i}")
            state = upd(state, jnp.asarray(z[i]), jnp.asarray(dn[i]))
        ax.set_title(f"{name}: posterior 1σ ellipses of θ (output thetadot)")
        ax.set_xlabel("θ_1")
        ax.set_ylabel("θ_2")
        ax.axis("equal")
        ax.legend(fontsize=7)
    fig.tight_layout()
    atomicfile.save_figure(fig, path, dpi=110)
    plt.close(fig)
