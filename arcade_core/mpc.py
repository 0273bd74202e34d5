"""Uncertainty-modulated nonlinear MPC by direct shooting (Sec. IV, Appendix D).

At every control step the optimal control problem of Sec. IV

    min_U  sum_{i<N} ||x_i - x^r_i||^2_{Q_k} + ||u_i - u^r_i||^2_R + ||x_N - x^r_N||^2_P
           + w_s sum_i ||u_i - u_{i-1}||^2 + w_c sum_i ||viol(x_i)||^2

is solved over the inputs only (direct shooting, Appendix D "Quadrotor MPC gains"): the
states come from rolling ``step_fn`` forward from the measured state. ``u_{-1}`` is the
input applied at the previous control step, so the smoothness term also penalises a jump
at the start of the horizon. ``Q_k`` is the state weight modulated by the model's total
predictive variance (Sec. IV, ``modulate_q``).

Design decisions:

- **Solver.** Every term is a weighted square, so the problem is a nonlinear least-squares
  problem and Gauss-Newton type solvers (Optimistix) converge in a few iterations from a
  shifted warm start. The quadrotor uses Gauss-Newton steps with a backtracking (Armijo)
  line search (``"gauss_newton_armijo"``, :class:`ArmijoGaussNewton`): with the nominal
  model it converges in 3-6 iterations along a figure-eight, like the full steps of plain
  Gauss-Newton (``"gauss_newton"``), but with a learned residual inside the rollout a full
  step can raise the cost, and plain Gauss-Newton then wanders until the iteration cap
  and hands out whatever iterate it stopped at (measured in the quadrotor closed loop at
  2.5 m/s: 55 % of ours' solves at 175 g and 23 % at 75 g did not converge within 8).
  Levenberg-Marquardt and Dogleg (also available as ``solver``) spend iterations on
  trust-region adjustments. The iteration count is capped (``max_steps``) so the solve
  time is bounded, and the normal equations are solved by Cholesky (``J`` is tall and has
  full column rank thanks to the input-cost rows), several times cheaper than a QR
  factorisation of ``J``.
- **Jacobian.** The rollout has a custom forward-mode rule: the per-step linearisations
  ``A_i = df/dx``, ``B_i = df/du`` are computed in parallel over the horizon (``nx + nu``
  tangents per step instead of ``N * nu``), then propagated with the tangent-linear
  recursion ``dx_{i+1} = A_i dx_i + B_i du_i``. With a learned residual inside ``step_fn``
  this is several times cheaper than differentiating the whole rollout per input.
- **Input bounds.** Inputs are parameterised as ``u = mid + half * tanh(z)`` with the
  decision variable ``z`` unconstrained. The bounds then hold exactly, the problem stays
  a smooth unconstrained least-squares problem (what Optimistix solves), and the
  predicted states are consistent with the returned inputs. Costs are on ``u`` itself.
- **State bounds** (optional) are soft: ``w_c * relu(x - x_max)^2 + w_c * relu(x_min - x)^2``
  (Appendix D soft-constraint penalty, weight 1000).
- **Quaternion error** is the plain difference of the 4-vectors, as in the paper's cost
  with Q acting on all 13 states; references are generated with ``w >= 0`` near the
  vehicle's attitude so the double cover does not matter in practice.
- **Safety.** A non-finite solution, or one costlier than the warm start, is never
  returned: the controller falls back to the cheaper of the (clipped) warm start and the
  (clipped) input reference ``u_ref`` (the feedforward of the reference: hover when
  hovering), and ``converged`` is False. The input reference is the fallback of last
  resort: a warm start that the model rolls out to non-finite states (a diverged plan,
  carried over by the receding-horizon shift) is then dropped instead of being handed
  out again at every later step, and so is a warm start with non-finite inputs, whatever
  the costs: the returned inputs are finite whenever ``u_ref`` is.
- **Models never recompile**: the learned model is an arbitrary pytree passed at solve
  time, ``step_fn(x, u, model) -> x_next``.
- **Learned residual along the warm start** (optional, :func:`residual_along`,
  ``staged=True``; the controllers keep the residual inside the rollout, as Sec. IV
  writes the model): the learned residual is evaluated once per solve along the warm
  start (the previous plan, shifted and rolled out from the measured state with the
  learned model) and held per stage during the iterations, as the linearisation point of
  a real-time iteration is. The prediction still follows the learned model where the plan
  goes; the optimiser no longer sees the model's derivatives with respect to inputs and
  states, and the Jacobians are those of ``f_nom`` (a cheaper solve). Whether that helps
  depends on the slopes: a decoder adapted on a few seconds of data has untrained slopes
  off the flown path, but also carries true ones (a payload lowers the thrust gain). The
  quadrotor evaluation flies both side by side (``run_residual_ablation``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax import Array
from jax.custom_derivatives import SymbolicZero
from jax.scipy.linalg import cho_solve

from arcade_core.dynamics.params import CARTPOLE_DT, QuadrotorParams

StepFn = Callable[[Array, Array, Any], Array]

#: Values of ``MPCConfig.solver``.
SOLVERS = ("gauss_newton_armijo", "gauss_newton", "dogleg", "levenberg_marquardt")

#: Warm starts are pulled this far inside the bounds before ``arctanh`` (finite z).
_SQUASH_MARGIN = 1e-4


class MPCConfig(eqx.Module):
    """MPC problem and solver settings (Appendix D table). Shapes are fixed by ``N``.

    Weights are diagonals: ``Q``, ``P`` (nx,), ``R`` (nu,). ``smooth_weight`` weighs the
    change of the inputs from one stage to the next: one weight for every input, or a tuple
    of one per input (``nu``). ``x_min``/``x_max`` (nx,) are optional soft state bounds
    (``±inf`` entries are ignored).
    """

    Q: Array
    R: Array
    P: Array
    u_min: Array
    u_max: Array
    N: int = eqx.field(static=True, default=20)
    dt: float = eqx.field(static=True, default=0.05)
    smooth_weight: float | tuple[float, ...] = eqx.field(static=True, default=10.0)
    constraint_weight: float = eqx.field(static=True, default=1000.0)
    x_min: Array | None = None
    x_max: Array | None = None
    alpha1: float = eqx.field(static=True, default=10.0)
    alpha2: float = eqx.field(static=True, default=1e3)
    max_steps: int = eqx.field(static=True, default=8)
    rtol: float = eqx.field(static=True, default=1e-3)
    atol: float = eqx.field(static=True, default=1e-4)
    solver: str = eqx.field(static=True, default="gauss_newton")  # one of SOLVERS

    @property
    def nx(self) -> int:
        return int(self.Q.shape[-1])

    @property
    def nu(self) -> int:
        return int(self.R.shape[-1])


class MPCSolution(NamedTuple):
    """Result of one MPC solve."""

    u: Array  # (N, nu) optimal inputs; apply u[0]
    x_pred: Array  # (N+1, nx) predicted states, x_pred[0] = x0
    cost: Array  # scalar J at the solution
    iterations: Array  # solver steps taken
    converged: Array  # bool: tolerance met, finite, no worse than the warm start


def quadrotor_mpc_config(
    params: QuadrotorParams | None = None,
    N: int = 20,
    dt: float = 0.05,
    rate_limit: tuple[float, float, float] = (3.5, 3.5, 3.0),
    dtype=None,
    max_thrust: float = 20.0,
    **overrides: Any,
) -> MPCConfig:
    """Quadrotor MPC gains of the Appendix D table.

    Q, P, R, thrust bounds [0.1, 20] N, N = 20 over 1 s, alpha1 = 10, alpha2 = 1e3.
    Solver (ours, not in the table): Gauss-Newton with an Armijo line search, at most 8
    iterations (module docstring, "Solver").
    ``max_thrust`` replaces the table's 20 N by what the vehicle can produce (the MPC's
    model must not plan with thrust the rotors do not have; the default vehicle: 16 N).
    Departure from the table: its ±0.5 limits apply to body *torques*; our last three
    inputs are body-rate *setpoints*, bounded by the vehicle's rate limits
    (default vehicle: 3.5, 3.5, 3.0 rad/s), which covers a 2.5 m/s figure-eight.
    ``params`` is accepted for symmetry with the model; the gains do not depend on it.
    """
    del params
    # Cast on the host, then placed: jnp.asarray would compile a conversion per shape in
    # every process that builds the config (the same IEEE rounding either way).
    host = jax.dtypes.canonicalize_dtype(dtype or float)
    arr = lambda v: jax.device_put(np.asarray(v, dtype=host))  # noqa: E731
    cfg = dict(
        Q=arr([40, 40, 60, 10, 10, 10, 1, 10, 10, 10, 10, 10, 10]),
        P=arr([400, 400, 600, 20, 20, 20, 1, 10, 10, 10, 10, 10, 10]),
        R=arr([10, 20, 20, 20]),
        u_min=arr([0.1, -rate_limit[0], -rate_limit[1], -rate_limit[2]]),
        u_max=arr([max_thrust, rate_limit[0], rate_limit[1], rate_limit[2]]),
        N=N,
        dt=dt,
        solver="gauss_newton_armijo",
    )
    cfg.update(overrides)
    return MPCConfig(**cfg)


def cartpole_mpc_config(N: int = 25, dt: float = CARTPOLE_DT, dtype=None, **overrides: Any):
    """Cartpole MPC (Appendix D testbed; the paper gives no gains, these are ours).

    State cost on ``[x, xdot, theta, thetadot]`` emphasises the pole angle, with a heavy
    terminal weight; force bound ±20 N; a 1.25 s horizon (25 steps at 0.05 s, about three
    time constants of the nominal pole). The smoothness weight is lowered to 0.01 because
    the input is a force of several newtons, not a normalised command. The unstable,
    often saturated cartpole problem uses the trust-region Dogleg solver, which stays
    reliable where plain Gauss-Newton can overshoot.
    """
    arr = lambda v: jnp.asarray(v, dtype=dtype or float)  # noqa: E731
    cfg = dict(
        Q=arr([1.0, 0.5, 10.0, 0.5]),
        P=arr([100.0, 50.0, 1000.0, 50.0]),
        R=arr([0.01]),
        u_min=arr([-20.0]),
        u_max=arr([20.0]),
        N=N,
        dt=dt,
        smooth_weight=0.01,
        solver="dogleg",
    )
    cfg.update(overrides)
    return MPCConfig(**cfg)


def residual_count(cfg: MPCConfig) -> int:
    """How many weighted residuals the OCP of ``cfg`` has (``m``, the rows of ``J``)."""
    n_bound = sum(
        int(np.sum(np.isfinite(np.asarray(b)))) for b in (cfg.x_max, cfg.x_min) if b is not None
    )
    return cfg.N * cfg.nx + cfg.nx + 2 * cfg.N * cfg.nu + cfg.N * n_bound


def modulate_q(Q: Array, sigma_tot2: Array, alpha1: float, alpha2: float) -> Array:
    """Uncertainty-modulated state weight (Sec. IV).

    ``Q_k = Q ⊙ [1 + alpha1 log(1 + alpha2 sigma_tot^2)]``; monotone in each component
    of the total predictive variance ``sigma_tot2`` and equal to ``Q`` when it is zero.
    """
    sigma_tot2 = jnp.maximum(sigma_tot2, 0.0)  # a variance; guards against round-off
    return Q * (1.0 + alpha1 * jnp.log1p(alpha2 * sigma_tot2))


def shift_warm_start(u: Array) -> Array:
    """Previous solution shifted by one step, last input repeated (receding horizon)."""
    return jnp.concatenate([u[1:], u[-1:]], axis=0)


def learned_step(nominal_step: Callable[[Array, Array], Array], residual) -> StepFn:
    """``x_next = f_nom(x, u) + residual(x, u, model)`` (Sec. III decomposition, Eq. 1)."""

    def step(x: Array, u: Array, model: Any) -> Array:
        return nominal_step(x, u) + residual(x, u, model)

    return step


def _squash(z: Array, lo: Array, hi: Array) -> Array:
    return 0.5 * (hi + lo) + 0.5 * (hi - lo) * jnp.tanh(z)


def _unsquash(u: Array, lo: Array, hi: Array) -> Array:
    s = (2.0 * u - (hi + lo)) / (hi - lo)
    return jnp.arctanh(jnp.clip(s, -1.0 + _SQUASH_MARGIN, 1.0 - _SQUASH_MARGIN))


def make_rollout(step_fn: StepFn, staged: bool = False) -> Callable[[Array, Array, Any], Array]:
    """``rollout(x0, U, model) -> X`` (N+1, nx) with a structured forward-mode rule.

    The JVP linearises every step in parallel and propagates tangents with the
    tangent-linear recursion; see the module docstring (direct shooting, Appendix D).
    ``staged``: every array leaf of ``model`` has a leading axis of length N and step ``i``
    sees ``model[i]`` (a per-stage model, e.g. :func:`residual_along`).
    """

    def rollout(x0: Array, U: Array, model: Any) -> Array:
        dynamic, static = eqx.partition(model, eqx.is_array)
        return _rollout_arrays(step_fn, static, x0, U, dynamic, staged)

    return rollout


def _rollout_arrays(step_fn, static, x0, U, dynamic, staged=False):
    ax = 0 if staged else None

    def step(x, u, dyn):
        return step_fn(x, u, eqx.combine(dyn, static))

    @jax.custom_jvp
    def roll(x0, U, dyn):
        def body(x, inputs):
            u, d = inputs
            x_next = step(x, u, d if staged else dyn)
            return x_next, x_next

        _, xs = jax.lax.scan(body, x0, (U, dyn if staged else None))
        return jnp.concatenate([x0[None], xs], axis=0)

    def roll_jvp(primals, tangents):
        x0, U, dyn = primals
        dx0, dU, ddyn = tangents
        X = roll(x0, U, dyn)
        # Per-step Jacobians, independent given the primal trajectory: one batched call.
        A, B = jax.vmap(jax.jacfwd(step, argnums=(0, 1)), in_axes=(0, 0, ax))(X[:-1], U, dyn)
        terms = jnp.zeros_like(X[1:])
        if not isinstance(dU, SymbolicZero):
            terms = terms + jnp.einsum("nij,nj->ni", B, dU)
        if not all(isinstance(t, SymbolicZero) for t in jax.tree.leaves(ddyn)):
            ddyn = jax.tree.map(
                lambda t, p: jnp.zeros_like(p) if isinstance(t, SymbolicZero) else t,
                ddyn,
                dyn,
                is_leaf=lambda t: isinstance(t, SymbolicZero),
            )
            terms = terms + jax.vmap(
                lambda x, u, d, dd: jax.jvp(lambda d: step(x, u, d), (d,), (dd,))[1],
                in_axes=(0, 0, ax, ax),
            )(X[:-1], U, dyn, ddyn)
        dx0 = jnp.zeros_like(x0) if isinstance(dx0, SymbolicZero) else dx0

        def body(dx, inputs):
            a, c = inputs
            dx_next = a @ dx + c
            return dx_next, dx_next

        _, dxs = jax.lax.scan(body, dx0, (A, terms))
        return X, jnp.concatenate([dx0[None], dxs], axis=0)

    roll.defjvp(roll_jvp, symbolic_zeros=True)
    return roll(x0, U, dynamic)


def residual_along(
    step_fn: StepFn,
    nominal_step: Callable[[Array, Array], Array],
    model: Any,
    x0: Array,
    U: Array,
) -> Array:
    """The learned residual along the trajectory ``step_fn`` rolls ``U`` out to, ``(N, nx)``.

    ``d_i = x_{i+1} - f_nom(x_i, u_i)`` with ``x_{i+1} = step_fn(x_i, u_i, model)``: rolling
    ``U`` out with :func:`staged_residual_step` and these ``d_i`` reproduces that trajectory
    exactly (module docstring, "Learned residual along the warm start").
    """
    X = make_rollout(step_fn)(x0, U, model)
    return X[1:] - jax.vmap(nominal_step)(X[:-1], U)


def staged_residual_step(nominal_step: Callable[[Array, Array], Array]) -> StepFn:
    """``x_next = f_nom(x, u) + d`` with ``d`` the stage's residual (a ``staged`` model)."""

    def step(x: Array, u: Array, d: Array) -> Array:
        return nominal_step(x, u) + d

    return step


def _quiet(**kwargs) -> None:
    """Optimistix's verbose hook, silenced."""


class _RoundoffArmijo(optx.BacktrackingArmijo):
    """Optimistix's backtracking Armijo search, blind to rounding noise in the cost.

    At the optimum a step changes the cost by less than its rounding error (float32: a few
    parts in 1e7), so the strict Armijo test would reject it and halve it again and again
    until the iteration cap. A step whose cost change is within ``roundoff`` times the
    cost is accepted, and the solver's step-size criterion then ends the solve.
    """

    roundoff: float = 100.0

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        y_diff = jax.tree.map(lambda a, b: a - b, y_eval, y)
        predicted = f_info.compute_grad_dot(y_diff)
        f, f_eval = f_info.as_min(), f_eval_info.as_min()
        noise = self.roundoff * jnp.finfo(jnp.result_type(f)).eps * jnp.abs(f)
        armijo = (f_eval - f <= self.slope * predicted + noise) & (predicted <= 0)
        accept = first_step | armijo
        step_size = jnp.where(accept, self.step_init, self.decrease_factor * state.step_size)
        return step_size, accept, optx.RESULTS.successful, type(state)(step_size=step_size)


class ArmijoGaussNewton(optx.AbstractGaussNewton):
    """Gauss-Newton directions with a backtracking line search (Armijo condition).

    A step is accepted when the least-squares cost falls by at least ``slope`` times the
    decrease the linearisation promises (up to rounding noise, :class:`_RoundoffArmijo`);
    otherwise it is halved. Optimistix's ``GaussNewton`` always takes the full step.
    """

    rtol: float
    atol: float
    norm: Callable
    descent: optx.NewtonDescent
    search: optx.BacktrackingArmijo
    verbose: Callable

    def __init__(
        self,
        rtol: float,
        atol: float,
        linear_solver: lx.AbstractLinearSolver,
        decrease_factor: float = 0.5,
        slope: float = 0.1,
    ):
        self.rtol = rtol
        self.atol = atol
        self.norm = optx.max_norm
        self.descent = optx.NewtonDescent(linear_solver=linear_solver)
        self.search = _RoundoffArmijo(decrease_factor=decrease_factor, slope=slope)
        self.verbose = _quiet


class _Problem(NamedTuple):
    x0: Array
    x_ref: Array
    u_ref: Array
    u_prev: Array
    model: Any
    q_stage: Array  # (nx,) or (N, nx) modulated stage weights


class Controller(NamedTuple):
    """A compiled MPC: ``solve`` is jitted once per (step_fn, config)."""

    config: MPCConfig
    solve: Callable[..., MPCSolution]
    rollout: Callable[[Array, Array, Any], Array]
    first_input_gain: Callable[..., Array]
    residual_change: Callable[..., tuple[Array, Array]]

    def initial_guess(self, u0: Array) -> Array:
        """Constant input over the horizon (Appendix D: ``U_0`` = hover input)."""
        return jnp.broadcast_to(u0, (self.config.N, u0.shape[-1]))

    @staticmethod
    def shift_warm_start(u: Array) -> Array:
        return shift_warm_start(u)


def make_controller(step_fn: StepFn, config: MPCConfig, staged: bool = False) -> Controller:
    """Build the uncertainty-modulated MPC (Sec. IV) for ``step_fn(x, u, model)``.

    Returns a ``Controller`` whose ``solve(x0, x_ref, u_ref, u_warm, u_prev, model,
    sigma_tot2=None)`` takes ``x_ref`` (N+1, nx), ``u_ref`` (N, nu), the warm start
    ``u_warm`` (N, nu), the previously applied input ``u_prev`` (nu,), the model pytree
    and the total predictive variance ``sigma_tot2`` ((nx,) or (N, nx); ``None`` = no
    modulation), and returns an ``MPCSolution``. ``staged``: ``model`` is per stage
    (:func:`make_rollout`).
    """
    cfg = config
    rollout = make_rollout(step_fn, staged)
    # Only finite state bounds produce penalty rows (decided once, outside tracing).
    hi_idx = lo_idx = np.zeros((0,), dtype=int)
    if cfg.x_max is not None:
        hi_idx = np.flatnonzero(np.isfinite(np.asarray(cfg.x_max)))
    if cfg.x_min is not None:
        lo_idx = np.flatnonzero(np.isfinite(np.asarray(cfg.x_min)))

    def residuals(U: Array, X: Array, prob: _Problem) -> Array:
        """Weighted residuals whose squared sum is the OCP cost J (Sec. IV, Appendix D)."""

        def sq(w):  # square root of a weight, in the working precision
            return jnp.sqrt(jnp.asarray(w, X.dtype))

        stage = sq(prob.q_stage) * (X[:-1] - prob.x_ref[:-1])
        terminal = sq(cfg.P) * (X[-1] - prob.x_ref[-1])
        inputs = sq(cfg.R) * (U - prob.u_ref)
        U_before = jnp.concatenate([prob.u_prev[None], U[:-1]], axis=0)
        smooth = sq(cfg.smooth_weight) * (U - U_before)
        parts = [stage.ravel(), terminal, inputs.ravel(), smooth.ravel()]
        w_c = sq(cfg.constraint_weight)
        if hi_idx.size:
            x_max = jnp.asarray(cfg.x_max, X.dtype)[hi_idx]
            parts.append(w_c * jax.nn.relu(X[1:, hi_idx] - x_max).ravel())
        if lo_idx.size:
            x_min = jnp.asarray(cfg.x_min, X.dtype)[lo_idx]
            parts.append(w_c * jax.nn.relu(x_min - X[1:, lo_idx]).ravel())
        return jnp.concatenate(parts)

    def bounds(dtype) -> tuple[Array, Array]:
        return jnp.asarray(cfg.u_min, dtype), jnp.asarray(cfg.u_max, dtype)

    def fn(z: Array, prob: _Problem) -> Array:
        U = _squash(z, *bounds(z.dtype))
        X = rollout(prob.x0, U, prob.model)
        return residuals(U, X, prob)

    # Normal equations + Cholesky: J is tall and has full column rank (the R rows).
    linear_solver = lx.Normal(lx.Cholesky())
    if cfg.solver == "gauss_newton":
        solver = optx.GaussNewton(rtol=cfg.rtol, atol=cfg.atol, linear_solver=linear_solver)
    elif cfg.solver == "gauss_newton_armijo":
        solver = ArmijoGaussNewton(cfg.rtol, cfg.atol, linear_solver)
    elif cfg.solver == "dogleg":
        solver = optx.Dogleg(rtol=cfg.rtol, atol=cfg.atol, linear_solver=linear_solver)
    elif cfg.solver == "levenberg_marquardt":
        solver = optx.LevenbergMarquardt(rtol=cfg.rtol, atol=cfg.atol, linear_solver=linear_solver)
    else:
        raise ValueError(f"unknown MPC solver {cfg.solver!r} (one of {', '.join(SOLVERS)})")

    def problem(x0, x_ref, u_ref, u_prev, model, sigma_tot2) -> _Problem:
        Q = jnp.asarray(cfg.Q, x0.dtype)
        q_stage = Q if sigma_tot2 is None else modulate_q(Q, sigma_tot2, cfg.alpha1, cfg.alpha2)
        q_stage = jnp.broadcast_to(q_stage, (cfg.N, cfg.nx)).astype(x0.dtype)
        return _Problem(x0, x_ref, u_ref, u_prev, model, q_stage)

    @eqx.filter_jit
    def solve(
        x0: Array,
        x_ref: Array,
        u_ref: Array,
        u_warm: Array,
        u_prev: Array,
        model: Any,
        sigma_tot2: Array | None = None,
    ) -> MPCSolution:
        prob = problem(x0, x_ref, u_ref, u_prev, model, sigma_tot2)
        lo, hi = bounds(u_warm.dtype)
        z0 = _unsquash(u_warm, lo, hi)
        sol = optx.least_squares(fn, solver, z0, args=prob, max_steps=cfg.max_steps, throw=False)
        U = _squash(sol.value, lo, hi)
        X = rollout(x0, U, model)
        cost = jnp.sum(residuals(U, X, prob) ** 2)

        # Safeguards: never hand out a non-finite plan, nor one worse than the warm start
        # (undamped Gauss-Newton can overshoot far from the optimum); the fallback is the
        # cheaper finite one of the warm start and the input reference.
        def plan(U):
            X = rollout(x0, U, model)
            c = jnp.sum(residuals(U, X, prob) ** 2)
            ok = jnp.isfinite(c) & jnp.all(jnp.isfinite(U)) & jnp.all(jnp.isfinite(X))
            return X, jnp.where(ok, c, jnp.inf)

        U_warm = jnp.clip(u_warm, lo, hi)
        U_ref = jnp.clip(u_ref, lo, hi).astype(U_warm.dtype)
        X_warm, cost_warm = plan(U_warm)
        X_ref, cost_ref = plan(U_ref)
        # Costs are finite or inf. Both inf (e.g. a non-finite x0 or model): keep the warm
        # start, unless its inputs are themselves non-finite; then the input reference.
        warm_ok = jnp.all(jnp.isfinite(U_warm)) & (
            ~(cost_warm > cost_ref) | ~jnp.all(jnp.isfinite(U_ref))
        )
        U_safe = jnp.where(warm_ok, U_warm, U_ref)
        X_safe = jnp.where(warm_ok, X_warm, X_ref)
        cost_safe = jnp.where(warm_ok, cost_warm, cost_ref)
        finite = jnp.isfinite(cost) & jnp.all(jnp.isfinite(U)) & jnp.all(jnp.isfinite(X))
        better = finite & ~(cost > cost_safe)
        U = jnp.where(better, U, U_safe)
        X = jnp.where(better, X, X_safe)
        cost = jnp.where(better, cost, cost_safe)
        converged = better & (sol.result == optx.RESULTS.successful)
        return MPCSolution(U, X, cost, sol.stats["num_steps"], converged)

    @eqx.filter_jit
    def first_input_gain(
        x0: Array,
        x_ref: Array,
        u_ref: Array,
        U: Array,
        u_prev: Array,
        model: Any,
        sigma_tot2: Array | None = None,
    ) -> Array:
        """``(nu, m)``: how the optimal first input moves with the residuals at the plan
        ``U`` (the solution of this problem): a change of the problem (initial state, model,
        input reference) that moves the residuals at ``U`` by ``dr`` moves ``u_0*`` by
        ``G dr``, in the Gauss-Newton approximation of the implicit function theorem,
        ``dz* = -(J_z^T J_z)^-1 J_z^T dr`` (the residuals' second derivatives dropped, as
        the solver drops them), through the input squashing (the bounds are the caller's to
        apply to the corrected input). At a plan ``U`` that does not solve the problem,
        ``G r`` (``r``: its residuals) is the first input's Gauss-Newton step from ``U``.
        :func:`residual_change` gives ``r`` and ``dr``; together they are the advanced-step
        controller's correction (:mod:`arcade_control.step`)."""
        prob = problem(x0, x_ref, u_ref, u_prev, model, sigma_tot2)
        lo, hi = bounds(U.dtype)
        z = _unsquash(U, lo, hi)
        J = jax.jacfwd(fn)(z, prob).reshape(-1, z.size)
        chol = jnp.linalg.cholesky(J.T @ J)
        # The first input's rows of (J^T J)^-1 (symmetric: its first columns), then J^T.
        nu = U.shape[-1]
        rows = cho_solve((chol, True), jnp.eye(z.size, nu, dtype=J.dtype)).T @ J.T
        slope = 0.5 * (hi - lo) * (1.0 - jnp.tanh(z[0]) ** 2)  # du_0 / dz_0
        return -slope[:, None] * rows

    @eqx.filter_jit
    def residual_change(
        x0: Array,
        x_ref: Array,
        u_ref: Array,
        U: Array,
        u_prev: Array,
        model: Any,
        sigma_tot2: Array | None,
        x0_new: Array,
        model_new: Any,
        u_ref_new: Array,
    ) -> tuple[Array, Array]:
        """``(r, dr)``, both ``(m,)``: the residuals at the plan ``U`` and their first-order
        change when the initial state, the model and the input reference become ``x0_new``,
        ``model_new`` (the same tree; its floating-point arrays change) and ``u_ref_new``
        (one forward-mode derivative, the state weights held). ``r + dr`` are the new
        problem's residuals at ``U`` to first order: with :func:`first_input_gain`,
        ``G (r + dr)`` is the first input's Gauss-Newton step from ``U`` on the new
        problem (``G r`` vanishes where ``U`` solves the old one)."""
        lo, hi = bounds(U.dtype)
        z = _unsquash(U, lo, hi)
        dyn, static = eqx.partition(model, eqx.is_array)
        dyn_new = eqx.filter(model_new, eqx.is_array)

        def tangent(new, old):
            if jnp.issubdtype(old.dtype, jnp.inexact):
                return (new - old).astype(old.dtype)
            return np.zeros(old.shape, jax.dtypes.float0)

        d_dyn = jax.tree.map(tangent, dyn_new, dyn)

        def res(x, d, ur):
            return fn(z, problem(x, x_ref, ur, u_prev, eqx.combine(d, static), sigma_tot2))

        tangents = (x0_new - x0, d_dyn, u_ref_new - u_ref)
        return jax.jvp(res, (x0, dyn, u_ref), tangents)

    return Controller(
        config=cfg,
        solve=solve,
        rollout=eqx.filter_jit(rollout),
        first_input_gain=first_input_gain,
        residual_change=residual_change,
    )
