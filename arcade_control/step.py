"""The closed-loop controller step: learn from the last transition, plan, correct.

Per method, the whole per-step update (learning from the last transition, reference
window, MPC solve, warm-start shift) is one jitted function, so a caller (the in-process
evaluation, the controller service) only moves a handful of arrays per step.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from arcade_control.knobs import FLAGSHIP, TUNED_DEFAULTS, knob_owner
from arcade_control.methods import Method
from arcade_control.nominal import CONTROL_DT as DT
from arcade_control.nominal import f_nom, nominal_params
from arcade_core import frames as quat
from arcade_core import mpc
from arcade_core.dynamics.quadrotor import quadrotor_step
from arcade_io.vehicle import load_vehicle


class Carry(NamedTuple):
    """What the per-step update carries from one control period to the next."""

    learner: Any
    u_warm: Array  # (N, 4) shifted previous MPC solution
    u_mpc: Array  # (4,) previous MPC output (smoothness reference)
    x_prev: Array  # (13,) state at the previous control instant
    started: Array  # () bool: x_prev / the applied input are real


def mpc_config(dtype) -> mpc.MPCConfig:
    """Appendix D MPC with the vehicle's actuator limits (thrust 16 N, rate limits)."""
    v = load_vehicle()
    rate = tuple(float(r) for r in v["rate_loop"]["max_rate_rad_s"])
    return mpc.quadrotor_mpc_config(
        dt=DT, rate_limit=rate, dtype=dtype, max_thrust=4.0 * float(v["rotors"]["max_thrust_n"])
    )


def method_mpc_config(
    cfg: mpc.MPCConfig, name: str, knobs: dict[str, Any] | None = None
) -> mpc.MPCConfig:
    """The MPC that method ``name`` plans with: ``cfg``, but for the flagship and its
    ablations the smoothness weight on the collective thrust is its knob
    ``arcade_thrust_smooth`` (``knobs`` over :data:`TUNED_DEFAULTS`); ``cfg`` itself where
    that knob is ``cfg``'s own weight."""
    if knob_owner(name) != FLAGSHIP:
        return cfg
    w = float({**TUNED_DEFAULTS, **(knobs or {})}["arcade_thrust_smooth"])
    shared = cfg.smooth_weight
    if not isinstance(shared, (int, float)):
        raise ValueError(f"the shared MPC has a smoothness weight per input: {shared!r}")
    if w == float(shared):
        return cfg
    return dataclasses.replace(cfg, smooth_weight=(w, *(float(shared),) * (cfg.nu - 1)))


def thrust_reference(step_fn, model, x_ref: Array, u_ref: Array) -> Array:
    """Input reference made consistent with a learned model (design decision, see below).

    The flat reference input comes from the nominal model: hover thrust ``m_nom g``. A
    learned model that knows about the payload needs more thrust to hold the reference,
    and the MPC's input cost ``R (u - u_ref)^2`` would then pull the thrust back towards
    the nominal hover value; over a 1 s horizon, sinking a little is cheaper than paying
    that cost, and the vehicle keeps sinking. So every learned-model method adds to the
    reference thrust what cancels its predicted residual acceleration along the body z
    axis at the reference: ``T_ref += -m_nom (delta_v . z_b) / dt``.
    """
    p = nominal_params()

    def one(x, u):
        dv = (step_fn(x, u, model) - f_nom(x, u))[3:6]
        z_b = quat.to_rotation_matrix(x[6:10])[:, 2]
        return u.at[0].add(-p.mass * jnp.dot(dv, z_b) / DT)

    return jax.vmap(one)(x_ref[:-1], u_ref)


def make_controller_step(
    method: Method, cfg: mpc.MPCConfig, hold_residual: bool = False, delay_s: float = 0.0
):
    """The jitted per-step update of one method (see module docstring).

    ``step(carry, x, u_applied, k, x_ref_all, u_ref_all) -> (carry, u, diag)`` where
    ``u_applied`` is what the vehicle actually executed over the last period and ``k``
    the control-step index into the precomputed references. ``diag`` =
    ``[sigma (13), changepoint, cp_prob, solver iterations, converged]``.

    ``hold_residual`` (learned-model methods; or the method's own ``hold_residual``, the
    flagship's): the learned residual is evaluated along the warm start and held per stage
    during the solve (:func:`arcade_core.mpc.residual_along`, module docstring); ``False``
    (default, Sec. IV): it sits inside the rollout, derivatives included.

    ``delay_s`` (a diagnostic, ``compensate_delay`` of
    :meth:`benchmarks.quadrotor_flights.Runner.fly`): the setpoint
    reaches the vehicle that much later, and the method learns and plans from the state
    predicted over the delay instead of ``x``: one RK4 step of the nominal model with the
    input the MPC planned for the period in flight (L1's baseline input, without the
    correction that cancels what the nominal model lacks). Each input then acts over
    exactly the period between two such states. ``x_ref_all``, ``u_ref_all`` must be the
    reference ``delay_s`` later (:func:`arcade_control.scenario.reference`'s ``offset_s``).
    """
    params = nominal_params()
    staged = method.learned and (hold_residual or method.hold_residual)
    if staged:
        controller = mpc.make_controller(mpc.staged_residual_step(f_nom), cfg, staged=True)
    else:
        controller = mpc.make_controller(method.step_fn, cfg)
    N = cfg.N

    def step(carry: Carry, x, u_applied, k, x_ref_all, u_ref_all):
        if delay_s > 0.0:
            x = quadrotor_step(x, carry.u_mpc, params, delay_s)
        x_ref = jax.lax.dynamic_slice_in_dim(x_ref_all, k, N + 1)
        # The quaternion in the reference's hemisphere: the cost and the model see R^4.
        x = x.at[6:10].set(quat.align(x[6:10], x_ref[0, 6:10]))
        learned = method.learn(carry.learner, carry.x_prev, u_applied, x)
        learner = jax.tree.map(lambda a, b: jnp.where(carry.started, a, b), learned, carry.learner)
        u_ref = jax.lax.dynamic_slice_in_dim(u_ref_all, k, N)
        sigma = method.sigma(learner, x, carry.u_warm[0])
        model = method.model(learner)
        if method.reference is not None:
            u_ref = jnp.clip(method.reference(model, x_ref, u_ref), cfg.u_min, cfg.u_max)
        elif method.learned:
            u_ref = jnp.clip(
                thrust_reference(method.step_fn, model, x_ref, u_ref), cfg.u_min, cfg.u_max
            )
        if staged:
            model = mpc.residual_along(method.step_fn, f_nom, model, x, carry.u_warm)
        sol = controller.solve(x, x_ref, u_ref, carry.u_warm, carry.u_mpc, model, sigma)
        u_b = sol.u[0]
        u = jnp.clip(u_b + method.correction(learner, x), cfg.u_min, cfg.u_max)
        sig = jnp.zeros(13, x.dtype) if sigma is None else sigma
        diag = jnp.concatenate(
            [
                sig,
                method.info(learner).astype(x.dtype),
                jnp.stack([sol.iterations, sol.converged]).astype(x.dtype),
            ]
        )
        new = Carry(learner, mpc.shift_warm_start(sol.u), u_b, x, jnp.ones((), bool))
        return new, u, diag

    return jax.jit(step)
