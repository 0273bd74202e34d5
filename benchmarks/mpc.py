"""MPC solve-time benchmark (design §7): quadrotor, N = 20 (1 s), float32.

Closed loop along a figure-eight on the nominal model plus a learned residual
``delta_scale * (theta @ mu_phi(x, u))`` from the VLD encoder (MLP [64, 128, 64], ELU,
l = 8, Appendix D), in the simulated plant and in the MPC: ``residual="rollout"`` (what
the controller runs, Sec. IV) keeps it inside the rollout, derivatives included;
``residual="held"`` evaluates it along the warm start and holds it per stage during the
solve (:func:`arcade_core.mpc.residual_along`, timed as part of the solve). Each solve is
warm-started with the shifted previous solution and timed to completion
(``block_until_ready``); compilation is excluded.

    python -m benchmarks.mpc [--steps 400] [--speed 2.5] [--residual held|rollout]
"""

from __future__ import annotations

import argparse
import time
from typing import Any, NamedTuple

import numpy as np

from arcade_io import jsonout
from benchmarks.common import machine, percentiles


class LearnedModel(NamedTuple):
    """What the adaptation module hands the controller: frozen encoder + decoder mean."""

    vld: Any
    theta: Any


def _residual_scale(jnp):
    # Plausible one-step residual magnitudes (p, v, q, omega) at 20 Hz, so that the
    # learned term is a perturbation of the nominal model rather than noise.
    return jnp.asarray([1e-3] * 3 + [2e-2] * 3 + [2e-3] * 4 + [5e-2] * 3, dtype=jnp.float32)


def run(
    steps: int = 400,
    speed: float = 2.5,
    warmup: int = 5,
    seed: int = 0,
    solver: str | None = None,
    max_steps: int | None = None,
    quick: bool = False,
    residual: str = "rollout",
) -> dict:
    """Time ``steps`` closed-loop MPC solves; returns the latency summary (ms).

    ``solver``/``max_steps`` override the Appendix D quadrotor configuration's defaults;
    ``quick`` times 60 solves (smoke run).
    """
    if quick:
        steps = min(steps, 60)
    from arcade_io import jaxsetup

    jaxsetup.configure(x64=False)
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from arcade_core.dynamics import QuadrotorParams, hover_input, quadrotor_step
    from arcade_core.encoder import VLD, quadrotor_config
    from arcade_core.mpc import (
        learned_step,
        make_controller,
        quadrotor_mpc_config,
        residual_along,
        staged_residual_step,
    )
    from arcade_core.trajectories import FigureEight, quadrotor_reference

    f32 = jnp.float32
    params = QuadrotorParams(inertia=jnp.asarray(QuadrotorParams().inertia, f32))
    overrides = {}
    if solver is not None:
        overrides["solver"] = solver
    if max_steps is not None:
        overrides["max_steps"] = max_steps
    cfg = quadrotor_mpc_config(dtype=f32, **overrides)
    N, dt = cfg.N, cfg.dt

    key_vld, key_theta = jax.random.split(jax.random.PRNGKey(seed))
    vld = VLD(key_vld, quadrotor_config(), dtype=f32)
    vld = eqx.tree_at(lambda m: m.delta_scale, vld, _residual_scale(jnp))
    theta = vld.theta0 + 0.1 * jax.random.normal(key_theta, vld.theta0.shape, f32)
    model = LearnedModel(vld, theta)

    def nominal(x, u):
        return quadrotor_step(x, u, params, dt)

    def learned_residual(x, u, m: LearnedModel):
        return m.vld.predict_residual(x, u, m.theta)

    if residual not in ("held", "rollout"):
        raise ValueError(f"residual must be 'held' or 'rollout', not {residual!r}")
    step_fn = learned_step(nominal, learned_residual)
    held = residual == "held"
    if held:
        ctrl = make_controller(staged_residual_step(nominal), cfg, staged=True)
        along = jax.jit(lambda x, U, m: residual_along(step_fn, nominal, m, x, U))
    else:
        ctrl = make_controller(step_fn, cfg)
    plant = jax.jit(step_fn)
    path = FigureEight(center=(0.0, 0.0, 1.0), speed=speed)
    reference = jax.jit(lambda t: quadrotor_reference(t, N, dt, path, params))

    x_ref, u_ref = reference(f32(0.0))
    x = x_ref[0]
    u_prev = hover_input(params, f32)
    u_warm = ctrl.initial_guess(u_prev)
    sigma = jnp.zeros((cfg.nx,), f32)

    times, iters, converged, pos_err = [], [], [], []
    for k in range(steps + warmup):
        x_ref, u_ref = reference(f32(k * dt))
        jax.block_until_ready((x_ref, u_ref))
        t0 = time.perf_counter()
        m = along(x, u_warm, model) if held else model
        sol = ctrl.solve(x, x_ref, u_ref, u_warm, u_prev, m, sigma)
        jax.block_until_ready(sol)
        elapsed = time.perf_counter() - t0
        if k >= warmup:
            times.append(elapsed)
            iters.append(int(sol.iterations))
            converged.append(bool(sol.converged))
            pos_err.append(float(jnp.linalg.norm(x[:3] - x_ref[0, :3])))
        u_prev = sol.u[0]
        x = plant(x, u_prev, model)
        u_warm = ctrl.shift_warm_start(sol.u)

    median, p99 = percentiles(times, 1e3)
    return {
        "machine": machine(),
        "horizon": N,
        "dtype": "float32",
        "residual": residual,
        "solver": cfg.solver,
        "max_steps": cfg.max_steps,
        "steps": steps,
        "speed_mps": speed,
        "median_ms": median,
        "p99_ms": p99,
        "mean_iterations": float(np.mean(iters)),
        "converged_fraction": float(np.mean(converged)),
        "tracking_rmse_m": float(np.sqrt(np.mean(np.square(pos_err)))),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--speed", type=float, default=2.5)
    from arcade_core.mpc import SOLVERS

    parser.add_argument(
        "--solver",
        choices=SOLVERS,
        help="MPC solver (default: the quadrotor configuration's, gauss_newton_armijo)",
    )
    parser.add_argument("--max-steps", type=int, default=None)
    parser.add_argument(
        "--residual",
        choices=("rollout", "held"),
        default="rollout",
        help="learned residual inside the rollout (the controller's scheme, "
        "default) or held along the warm start",
    )
    args = parser.parse_args(argv)
    result = run(
        steps=args.steps,
        speed=args.speed,
        solver=args.solver,
        max_steps=args.max_steps,
        residual=args.residual,
    )
    print(jsonout.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
