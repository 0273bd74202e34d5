"""In-process cartpole adaptation demo: the true cartpole under adaptive MPC.

The testbed's true system (Appendix D, ``arcade_control.cartpole.TRUE_PARAMS``) goes
through the online-adaptation interventions of Sec. V-A (2 N impulses and mass reductions
at steps 0, 40, 80). Two controllers fly the same
seeded scenario: the nominal MPC, and ARCADE's MPC on ``f_nom + theta phi`` with the
beam-marginal decoder adapted online (Algorithm 1) and Q modulated by sigma_tot (Sec. IV).
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from arcade_control import cartpole as cd
from arcade_core import adaptation, metrics, mpc
from arcade_core.dynamics.cartpole import cartpole_nominal_step, cartpole_true_step
from arcade_core.dynamics.params import CARTPOLE_DT
from arcade_io import atomicfile, jsonout


def _controller():
    def step_fn(x, u, model):
        vld, theta = model
        return cartpole_nominal_step(x, u) + vld.predict_residual(x, u, theta)

    cfg = mpc.cartpole_mpc_config()
    return mpc.make_controller(step_fn, cfg), cfg


def fly(vld, key, x0, schedule: cd.Schedule, adaptive: bool) -> dict[str, np.ndarray]:
    """Closed loop over the schedule; returns states, inputs, predictions and detections."""
    controller, cfg = _controller()
    acfg = adaptation.cartpole_config()
    T = len(schedule.force)
    x_ref, u_ref = jnp.zeros((cfg.N + 1, 4)), jnp.zeros((cfg.N, 1))
    zero_theta = jnp.zeros_like(vld.theta0)

    def body(carry, inp):
        x, u_warm, u_prev, beam = carry
        k_key, f, s = inp
        theta, _ = adaptation.marginal_decoder(beam)
        if adaptive:
            model = (vld, theta)
            # sigma_tot^2 in normalised residual units, like the quadrotor controller: one
            # alpha1/alpha2 (Appendix D) then means the same for every state component.
            z, s2z = vld.features(x, u_prev), vld.latent_variance(x, u_prev)
            s2 = adaptation.sigma_tot2(beam, z, s2z)
        else:
            model, s2 = (vld, zero_theta), None
        sol = controller.solve(x, x_ref, u_ref, u_warm, u_prev, model, s2)
        u = sol.u[0]
        params = cd.scaled(cd.TRUE_PARAMS, s)
        x_next = cartpole_true_step(k_key, x, u, params, CARTPOLE_DT, force=f)
        nom = cartpole_nominal_step(x, u)
        z = vld.features(x, u)
        dn = vld.normalise_residual(x_next - nom)
        beam, pred, info = adaptation.step(beam, z, dn, acfg, vld.latent_variance(x, u))
        x_hat = nom + vld.denormalise_residual(pred.mean)
        std = jnp.sqrt(pred.variance) * vld.delta_scale
        out = (x_next, u, x_hat, std, info.changepoint, info.cp_prob)
        return (x_next, mpc.shift_warm_start(sol.u), u, beam), out

    init = (x0, jnp.zeros((cfg.N, 1)), jnp.zeros(1), adaptation.init(vld.theta0, acfg))
    keys = jax.random.split(key, T)
    inputs = (keys, jnp.asarray(schedule.force), jnp.asarray(schedule.mass_scale))
    _, (xs, us, xh, sd, cp, cpp) = jax.jit(lambda i, c: jax.lax.scan(body, c, i))(inputs, init)
    X = np.concatenate([np.asarray(x0)[None], np.asarray(xs)])
    return {
        "X": X,
        "U": np.asarray(us),
        "x_hat": np.asarray(xh),
        "std": np.asarray(sd),
        "changepoint": np.asarray(cp),
        "cp_prob": np.asarray(cpp),
    }


def run_demo(vld, out: Path, seed: int = 0) -> dict[str, Any]:
    key = jax.random.PRNGKey(seed)
    x0 = jnp.array([0.3, 0.0, 0.2, 0.0])
    schedule = cd.intervention_schedule(120)
    runs = {
        name: fly(vld, key, x0, schedule, adaptive)
        for name, adaptive in (("nominal_mpc", False), ("arcade_mpc", True))
    }
    summary: dict[str, Any] = {}
    for name, r in runs.items():
        X = r["X"]
        summary[name] = {
            "state_rmse_to_upright": float(metrics.rmse(X[1:], np.zeros_like(X[1:]))),
            "theta_rmse_rad": float(np.sqrt(np.mean(X[1:, 2] ** 2))),
            "cart_rmse_m": float(np.sqrt(np.mean(X[1:, 0] ** 2))),
            "prediction_crmse": float(metrics.crmse(X[1:], r["x_hat"])),
            "detected_changepoints": [int(k) for k in np.flatnonzero(r["changepoint"])],
        }
    summary["interventions"] = list(cd.INTERVENTION_STEPS)
    out.mkdir(parents=True, exist_ok=True)
    atomicfile.write_text(out / "metrics.json", jsonout.dumps(summary, indent=2))
    _write_log(out / "log.csv", runs["arcade_mpc"])
    _plot(out / "rollout.png", runs)
    return summary


def _write_log(path: Path, r: dict[str, np.ndarray]) -> None:
    with atomicfile.atomic_open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", "x", "xdot", "theta", "thetadot", "u", "cp_prob", "changepoint"])
        for k in range(len(r["U"])):
            w.writerow(
                [
                    f"{k * CARTPOLE_DT:.3f}",
                    *(f"{v:.6g}" for v in r["X"][k]),
                    f"{r['U'][k, 0]:.6g}",
                    f"{r['cp_prob'][k]:.4g}",
                    int(r["changepoint"][k]),
                ]
            )


def _plot(path: Path, runs: dict[str, dict[str, np.ndarray]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = ("x [m]", "xdot [m/s]", "theta [rad]", "thetadot [rad/s]")
    fig, axes = plt.subplots(6, 1, figsize=(9, 12), sharex=True)
    t = np.arange(121) * CARTPOLE_DT
    for name, r in runs.items():
        for j in range(4):
            axes[j].plot(t, r["X"][:, j], label=name)
        axes[4].step(t[:-1], r["U"][:, 0], where="post", label=name)
    r = runs["arcade_mpc"]
    j = 1
    lo, hi = r["x_hat"][:, j] - 2 * r["std"][:, j], r["x_hat"][:, j] + 2 * r["std"][:, j]
    axes[j].fill_between(t[1:], lo, hi, color="C1", alpha=0.25, label="ARCADE ±2σ prediction")
    axes[5].plot(t[:-1], r["cp_prob"], "C3")
    axes[5].set_ylabel("p(c_k=1)")
    for j, lab in enumerate((*names, "u [N]")):
        axes[j].set_ylabel(lab)
    for ax in axes:
        for k in cd.INTERVENTION_STEPS:
            ax.axvline(k * CARTPOLE_DT, color="0.5", lw=0.8)
        for k in np.flatnonzero(r["changepoint"]):
            ax.axvline(k * CARTPOLE_DT, color="r", ls="--", lw=0.8)
    axes[0].legend(fontsize=8)
    axes[1].legend(fontsize=8)
    axes[-1].set_xlabel("t [s]")
    axes[0].set_title("Cartpole: nominal vs ARCADE MPC (grey: interventions, red: detections)")
    fig.tight_layout()
    atomicfile.save_figure(fig, path, dpi=110)
    plt.close(fig)
