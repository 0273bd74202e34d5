"""The closed-loop controller step: learn from the last transition, plan, correct.

Per method, the whole per-step update (learning from the last transition, reference
window, MPC solve, warm-start shift) is one jitted function, so a caller (the in-process
evaluation, the controller service) only moves a handful of arrays per step. The
advanced-step controller (:func:`make_advanced_step`) splits it in two: a first-order
answer to the state from a plan prepared one period earlier, and the next plan's solve,
which the controller service runs after the setpoint is out.
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
    method: Method,
    cfg: mpc.MPCConfig,
    hold_residual: bool = False,
    delay_s: float = 0.0,
    advanced: bool = False,
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

    ``advanced``: the advanced-step controller (:func:`make_advanced_step`); ``carry`` is
    then a :class:`PlannedCarry` (:func:`planned_carry`) and the step is its feedback
    followed by its preparation, what the controller service runs around publishing.
    """
    if advanced:
        feedback, prepare = make_advanced_step(method, cfg, hold_residual, delay_s)

        def both(carry, x, u_applied, k, x_ref_all, u_ref_all):
            carry, u, diag = feedback(carry, x, u_applied, k, x_ref_all, u_ref_all)
            return prepare(carry, k + 1, DT, x_ref_all, u_ref_all), u, diag

        return jax.jit(both)
    planner = _Planner(method, cfg, hold_residual, delay_s)

    def step(carry: Carry, x, u_applied, k, x_ref_all, u_ref_all):
        x, learner = planner.observe(carry, x, u_applied, k, x_ref_all)
        sol, sigma = planner.plan(learner, x, k, carry.u_warm, carry.u_mpc, x_ref_all, u_ref_all)
        u_b = sol.u[0]
        u = jnp.clip(u_b + method.correction(learner, x), cfg.u_min, cfg.u_max)
        diag = planner.diag(learner, sigma, sol.iterations, sol.converged, x.dtype)
        new = Carry(learner, mpc.shift_warm_start(sol.u), u_b, x, jnp.ones((), bool))
        return new, u, diag

    return jax.jit(step)


def align_to_reference(x: Array, x_ref_all: Array, k, N: int) -> Array:
    """``x`` with its quaternion in the hemisphere of the reference at instant ``k`` (the
    first of the MPC's window ``x_ref_all[k : k + N + 1]``, clamped as the window is)."""
    x_ref0 = jax.lax.dynamic_slice_in_dim(x_ref_all, k, N + 1)[0]
    return x.at[6:10].set(quat.align(x[6:10], x_ref0[6:10]))


class _Planner:
    """What the plain and the advanced-step controllers share: the state they learn and
    plan from, one MPC solve against the reference at an instant, the diagnostics."""

    def __init__(
        self,
        method: Method,
        cfg: mpc.MPCConfig,
        hold_residual: bool,
        delay_s: float,
        prepare_steps: int | None = None,
    ):
        self.method, self.cfg, self.delay_s = method, cfg, delay_s
        self.params = nominal_params()
        self.staged = method.learned and (hold_residual or method.hold_residual)
        step_fn = mpc.staged_residual_step(f_nom) if self.staged else method.step_fn
        self.controller = mpc.make_controller(step_fn, cfg, staged=self.staged)
        #: The advanced step's plans: at most ``prepare_steps`` solver iterations.
        self.preparer = self.controller
        if prepare_steps is not None and prepare_steps < cfg.max_steps:
            capped = dataclasses.replace(cfg, max_steps=prepare_steps)
            self.preparer = mpc.make_controller(step_fn, capped, staged=self.staged)

    def observe(self, carry, x, u_applied, k, x_ref_all, learner=None):
        """The state the method learns and plans from (predicted over the delay, its
        quaternion in the reference's hemisphere) and the learner (``carry``'s, or the
        one given) after the transition."""
        if self.delay_s > 0.0:
            x = quadrotor_step(x, carry.u_mpc, self.params, self.delay_s)
        # The quaternion in the reference's hemisphere: the cost and the model see R^4.
        x = align_to_reference(x, x_ref_all, k, self.cfg.N)
        before = carry.learner if learner is None else learner
        learned = self.method.learn(before, carry.x_prev, u_applied, x)
        return x, jax.tree.map(lambda a, b: jnp.where(carry.started, a, b), learned, before)

    def inputs(self, learner, x, k, u_warm, x_ref_all, u_ref_all, modulate: bool = True):
        """What the MPC solves with from ``x`` at instant ``k``: the reference window, the
        input reference (corrected for the learned thrust), the model (per stage when the
        residual is held along the warm start) and the variance that modulates ``Q``
        (``None`` without ``modulate``)."""
        method, cfg, N = self.method, self.cfg, self.cfg.N
        x_ref = jax.lax.dynamic_slice_in_dim(x_ref_all, k, N + 1)
        u_ref = jax.lax.dynamic_slice_in_dim(u_ref_all, k, N)
        sigma = method.sigma(learner, x, u_warm[0]) if modulate else None
        model = method.model(learner)
        if method.reference is not None:
            u_ref = jnp.clip(method.reference(model, x_ref, u_ref), cfg.u_min, cfg.u_max)
        elif method.learned:
            u_ref = jnp.clip(
                thrust_reference(method.step_fn, model, x_ref, u_ref), cfg.u_min, cfg.u_max
            )
        if self.staged:
            model = mpc.residual_along(method.step_fn, f_nom, model, x, u_warm)
        return x_ref, u_ref, model, sigma

    def plan(self, learner, x, k, u_warm, u_prev, x_ref_all, u_ref_all, gain: bool = False):
        """The MPC solution from ``x`` against the reference at instant ``k`` and the
        variance that modulated ``Q``; with ``gain`` (the advanced step's plan: at most
        ``prepare_steps`` iterations), also the first input's gain on the residuals at the
        plan (``first_input_gain``; zero where it is not finite), the input reference and
        the model it solved with."""
        x_ref, u_ref, model, sigma = self.inputs(learner, x, k, u_warm, x_ref_all, u_ref_all)
        args = (x, x_ref, u_ref)
        controller = self.preparer if gain else self.controller
        sol = controller.solve(*args, u_warm, u_prev, model, sigma)
        if not gain:
            return sol, sigma
        G = controller.first_input_gain(*args, sol.u, u_prev, model, sigma)
        return sol, sigma, jnp.where(jnp.all(jnp.isfinite(G)), G, 0.0), u_ref, model

    def diag(self, learner, sigma, iterations, converged, dtype):
        sig = jnp.zeros(13, dtype) if sigma is None else sigma
        info = self.method.info(learner).astype(dtype)
        return jnp.concatenate([sig, info, jnp.stack([iterations, converged]).astype(dtype)])


def predict_period(method: Method, learner: Any, x: Array, u: Array, period_s) -> Array:
    """The state ``period_s`` after ``x`` under ``u`` as the method's model predicts it:
    the nominal RK4 step over the period plus the learned residual of one model step
    scaled to it, ``f_nom(x, u; h) + (h / dt) (f(x, u) - f_nom(x, u))``, which is the
    method's own step when ``h`` is its step ``dt``; a residual is mostly a velocity
    change of an acceleration the model lacks, linear in ``h`` to first order."""
    params = nominal_params()
    residual = method.step_fn(x, u, method.model(learner)) - f_nom(x, u)
    x_next = quadrotor_step(x, u, params, period_s) + (period_s / DT) * residual
    return x_next.at[6:10].set(quat.normalize(x_next[6:10]))


class Plan(NamedTuple):
    """A plan prepared for the next control instant (:func:`make_advanced_step`); its
    inputs are the carry's ``u_warm``."""

    x0: Array  # (13,) the predicted state it starts from
    warm: Array  # (N, 4) the warm start it was solved from (the held residual's path)
    gain: Array  # (4, m) the first input's gain on the residuals at the plan
    u_ref: Array  # (N, 4) the input reference it was solved against
    held: Array  # (N, 13) the residual held per stage (zeros: inside the rollout instead)
    sigma: Array  # (13,) the variance that modulated Q (zeros: none)
    iterations: Array  # () solver iterations
    converged: Array  # () bool
    ready: Array  # () bool: prepared for the instant the next state answers


class PlannedCarry(NamedTuple):
    """:class:`Carry` with the plan prepared for the next instant."""

    learner: Any
    u_warm: Array  # (N, 4): the prepared plan when ``plan.ready``, else the warm start
    u_mpc: Array
    x_prev: Array
    started: Array
    plan: Plan


def planned_carry(carry: Carry, cfg: mpc.MPCConfig) -> PlannedCarry:
    """``carry`` without a prepared plan: the first advanced step solves in full."""
    dt = carry.u_mpc.dtype
    z = jnp.zeros((), dt)
    plan = Plan(
        jnp.zeros(13, dt),
        jnp.zeros_like(carry.u_warm),
        jnp.zeros((4, mpc.residual_count(cfg)), dt),
        jnp.zeros_like(carry.u_warm),
        jnp.zeros((cfg.N, 13), dt),
        jnp.zeros(13, dt),
        z,
        jnp.zeros((), bool),
        jnp.zeros((), bool),
    )
    return PlannedCarry(*carry, plan)


#: Solver iterations of the advanced step's plan (the real-time iteration's idea: the
#: answer finishes the plan's Gauss-Newton step). In process, stack condition, the
#: flagship at 175 g / 2.5 m/s, 75 g / 0.5 m/s and 125 g / 1.5 m/s, seeds 0 and 1: 2
#: iterations track as the solve to convergence does (RMSE within 0.0001 m in all six
#: flights); 1 iteration is 13-21 % behind (docs/quadrotor-closed-loop.md).
PREPARE_STEPS = 2


def make_advanced_step(
    method: Method,
    cfg: mpc.MPCConfig,
    hold_residual: bool = False,
    delay_s: float = 0.0,
    prepare_steps: int | None = PREPARE_STEPS,
):
    """The advanced-step controller: ``(feedback, prepare)``, both jitted.

    Sense-to-actuate is one MPC solve long when the controller solves after the state
    arrives. The advanced-step scheme (Zavala and Biegler 2009) solves one period ahead
    instead: once a setpoint is out, ``prepare(carry, k_next, period_s, x_ref_all,
    u_ref_all)`` predicts the state at the next control instant, ``period_s`` later, with
    the input just sent (the method's model, :func:`predict_period`), plans the MPC from
    there against the reference at ``k_next`` with at most ``prepare_steps`` solver
    iterations (``None``: the configuration's cap) from the shifted plan, and keeps the
    first input's gain on the problem's residuals at the plan
    (:func:`arcade_core.mpc.make_controller`'s ``first_input_gain``). When the state
    arrives, ``feedback(carry, x, u_applied, k, x_ref_all, u_ref_all, learner_now=None) ->
    (carry, u, diag)`` learns from the transition as the plain step does (from
    ``learner_now``, when given: the controller service's learner holding the newest model
    message, where the carry's holds the one the plan was made with) and answers with the
    plan's first input plus the gain times the problem's residuals at the plan, updated to
    first order for what changed since: the state (measured against predicted) and the
    learned model with the input reference it implies (``residual_change``: one
    forward-mode derivative, then a matrix-vector product, instead of a solve). That is
    the first input's Gauss-Newton step from the plan on the problem of now, as in the
    real-time iteration (Diehl et al. 2005): at a converged plan only the change counts.
    Without a plan prepared for this instant (the first step) it solves in full, as
    :func:`make_controller_step` does. ``diag``'s solver columns are those of the solve
    behind the input (a plan: its iterations, and whether it met the solver's tolerance
    within its cap).
    """
    planner = _Planner(method, cfg, hold_residual, delay_s, prepare_steps)
    controller = planner.controller

    def feedback(carry: PlannedCarry, x, u_applied, k, x_ref_all, u_ref_all, learner_now=None):
        x, learner = planner.observe(carry, x, u_applied, k, x_ref_all, learner_now)
        plan = carry.plan
        refs = (x_ref_all, u_ref_all)

        def prepared(_):
            x_ref, u_ref_new, model_new, _ = planner.inputs(
                learner, x, k, plan.warm, *refs, modulate=False
            )
            model = plan.held if planner.staged else method.model(carry.learner)
            # The weights the plan was solved with (a method without modulation: none).
            modulated = method.sigma(carry.learner, x, plan.warm[0]) is not None
            held = plan.sigma if modulated else None
            r, dr = controller.residual_change(
                plan.x0, x_ref, plan.u_ref, carry.u_warm, carry.u_mpc, model, held,
                x, model_new, u_ref_new,
            )  # fmt: skip
            # One Gauss-Newton step from the plan on the problem of now (to first order).
            u_b = carry.u_warm[0] + plan.gain @ (r + dr)
            return u_b, carry.u_warm, plan.sigma, plan.iterations, plan.converged

        def solved(_):
            sol, sigma = planner.plan(learner, x, k, carry.u_warm, carry.u_mpc, *refs)
            sig = jnp.zeros(13, x.dtype) if sigma is None else sigma
            return sol.u[0], sol.u, sig, sol.iterations.astype(x.dtype), sol.converged

        u_b, U, sigma, iterations, converged = jax.lax.cond(plan.ready, prepared, solved, None)
        u_b = jnp.clip(u_b, cfg.u_min, cfg.u_max)
        u = jnp.clip(u_b + method.correction(learner, x), cfg.u_min, cfg.u_max)
        diag = planner.diag(learner, sigma, iterations, converged, x.dtype)
        new = PlannedCarry(
            learner, U, u_b, x, jnp.ones((), bool), plan._replace(ready=jnp.zeros((), bool))
        )
        return new, u, diag

    def prepare(carry: PlannedCarry, k, period_s, x_ref_all, u_ref_all):
        learner = carry.learner
        x = predict_period(method, learner, carry.x_prev, carry.u_mpc, period_s)
        x = align_to_reference(x, x_ref_all, k, cfg.N)
        warm = mpc.shift_warm_start(carry.u_warm)
        sol, sigma, G, u_ref, model = planner.plan(
            learner, x, k, warm, carry.u_mpc, x_ref_all, u_ref_all, gain=True
        )
        sig = jnp.zeros(13, x.dtype) if sigma is None else sigma
        held = model if planner.staged else jnp.zeros((cfg.N, 13), x.dtype)
        its = sol.iterations.astype(x.dtype)
        G = G.astype(x.dtype)
        plan = Plan(x, warm, G, u_ref, held, sig, its, sol.converged, jnp.ones((), bool))
        return carry._replace(u_warm=sol.u, plan=plan)

    return jax.jit(feedback), jax.jit(prepare)
