"""Uncertainty-modulated direct-shooting MPC (Sec. IV, Appendix D)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from arcade_core.dynamics import (
    QuadrotorParams,
    cartpole_nominal_step,
    hover_input,
    hover_state,
    quadrotor_step,
)
from arcade_core.mpc import (
    ArmijoGaussNewton,
    cartpole_mpc_config,
    make_controller,
    make_rollout,
    modulate_q,
    quadrotor_mpc_config,
    residual_along,
    shift_warm_start,
    staged_residual_step,
)
from arcade_core.trajectories import FigureEight, Hover, quadrotor_reference

QUAD = QuadrotorParams()
DT = 0.05
TRACES = {"quad": 0}


def quad_step(x, u, bias):
    """Nominal model plus an additive learned term (here a constant bias vector)."""
    TRACES["quad"] += 1  # counts traces, not calls: a recompile shows up here
    return quadrotor_step(x, u, QUAD, DT) + bias


def cart_step(x, u, bias):
    return cartpole_nominal_step(x, u) + bias


@pytest.fixture(scope="module")
def quad():
    return make_controller(quad_step, quadrotor_mpc_config())


@pytest.fixture(scope="module")
def cart():
    return make_controller(cart_step, cartpole_mpc_config())


def hover_problem(N):
    xr, ur = quadrotor_reference(0.0, N, DT, Hover((0.0, 0.0, 1.0)), QUAD)
    return xr, ur


def run_closed_loop(ctrl, x, xr, ur, u0, steps, step, bias, sigma):
    cfg = ctrl.config
    u_warm, u_prev = ctrl.initial_guess(u0), u0
    history = []
    for _ in range(steps):
        sol = ctrl.solve(x, xr, ur, u_warm, u_prev, bias, sigma)
        assert np.all(np.asarray(sol.u) >= np.asarray(cfg.u_min) - 1e-12)
        assert np.all(np.asarray(sol.u) <= np.asarray(cfg.u_max) + 1e-12)
        u_prev = sol.u[0]
        x = step(x, u_prev, bias)
        u_warm = shift_warm_start(sol.u)
        history.append((np.asarray(x), sol))
    return x, history


def test_modulate_q_is_identity_at_zero_and_monotone():
    Q = jnp.array([40.0, 10.0, 1.0])
    np.testing.assert_allclose(modulate_q(Q, jnp.zeros(3), 10.0, 1e3), Q, rtol=0)
    sig = jnp.array([0.0, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1, 1.0])
    q = jax.vmap(lambda s: modulate_q(Q, jnp.full(3, s), 10.0, 1e3))(sig)
    assert np.all(np.diff(np.asarray(q), axis=0) > 0)
    # Exactly Sec. IV: Q ⊙ [1 + alpha1 log(1 + alpha2 sigma^2)], componentwise.
    s2 = jnp.array([1e-3, 0.0, 2e-2])
    expected = np.asarray(Q) * (1 + 10.0 * np.log(1 + 1e3 * np.asarray(s2)))
    np.testing.assert_allclose(modulate_q(Q, s2, 10.0, 1e3), expected, rtol=1e-12)


def test_cartpole_balances_from_tilted_start(cart):
    cfg = cart.config
    xr, ur = jnp.zeros((cfg.N + 1, 4)), jnp.zeros((cfg.N, 1))
    x0 = jnp.array([0.0, 0.0, 0.3, 0.0])
    x, history = run_closed_loop(
        cart, x0, xr, ur, jnp.zeros(1), 100, cart_step, jnp.zeros(4), jnp.zeros(4)
    )
    thetas = np.array([h[0][2] for h in history])
    assert np.abs(thetas).max() < 0.6  # never fell over
    assert abs(float(x[2])) < 0.01 and abs(float(x[0])) < 0.1  # upright and centred at 5 s
    assert np.mean([bool(h[1].converged) for h in history]) > 0.9


def test_cartpole_input_bounds_hold_when_saturated(cart):
    cfg = cart.config
    xr, ur = jnp.zeros((cfg.N + 1, 4)), jnp.zeros((cfg.N, 1))
    sol = cart.solve(
        jnp.array([0.0, 0.0, 0.5, 0.5]), xr, ur, jnp.zeros((cfg.N, 1)), jnp.zeros(1),
        jnp.zeros(4), jnp.zeros(4),
    )  # fmt: skip
    u = np.asarray(sol.u)
    assert np.all(np.abs(u) <= 20.0)
    assert np.abs(u).max() > 19.5  # the bound is active, not trivially satisfied
    assert np.all(np.isfinite(np.asarray(sol.x_pred)))


def test_quadrotor_reaches_hover_from_offset(quad):
    cfg = quad.config
    xr, ur = hover_problem(cfg.N)
    x0 = hover_state(jnp.array([1.0, -0.5, 0.4]))
    x, history = run_closed_loop(
        quad, x0, xr, ur, hover_input(QUAD), 80, quad_step, jnp.zeros(13), jnp.zeros(13)
    )
    assert np.linalg.norm(np.asarray(x[:3]) - [0.0, 0.0, 1.0]) < 0.03
    assert np.linalg.norm(np.asarray(x[3:6])) < 0.1
    assert all(bool(h[1].converged) for h in history)
    # Costs decrease as the vehicle approaches the setpoint.
    assert float(history[-1][1].cost) < 0.01 * float(history[0][1].cost)


def test_prediction_is_the_rollout_of_the_returned_inputs(quad):
    cfg = quad.config
    xr, ur = hover_problem(cfg.N)
    bias = 1e-3 * jnp.arange(13.0)
    x0 = hover_state(jnp.array([0.3, 0.0, 0.8]))
    sol = quad.solve(x0, xr, ur, ur, ur[0], bias, jnp.zeros(13))
    x = x0
    np.testing.assert_allclose(sol.x_pred[0], x0)
    for i in range(cfg.N):
        x = quad_step(x, sol.u[i], bias)
        np.testing.assert_allclose(sol.x_pred[i + 1], x, atol=1e-10)


def test_uncertainty_raises_q_and_tightens_tracking(quad):
    cfg = quad.config
    xr, ur = hover_problem(cfg.N)
    x0 = hover_state(jnp.array([1.0, 0.0, 1.0]))
    errors, effort = [], []
    for s in (0.0, 1e-4, 1e-3, 1e-2):
        sigma = jnp.zeros(13).at[:3].set(s)  # uncertain position components only
        sol = quad.solve(x0, xr, ur, ur, ur[0], jnp.zeros(13), sigma)
        errors.append(float(jnp.sum((sol.x_pred[1:, :3] - xr[1:, :3]) ** 2)))
        effort.append(float(jnp.sum((sol.u - ur) ** 2)))
    # Monotone: a larger variance weighs position error more and the plan closes it faster.
    assert np.all(np.diff(errors) < 0), errors
    assert np.all(np.diff(effort) > 0), effort
    assert errors[-1] < 0.8 * errors[0]


def test_warm_start_reduces_iterations(quad):
    cfg = quad.config
    path = FigureEight(speed=2.0)
    xr, ur = quadrotor_reference(1.0, cfg.N, DT, path, QUAD)
    x = xr[0].at[:3].add(0.05)
    zero, cold = jnp.zeros(13), quad.initial_guess(hover_input(QUAD))
    sol = quad.solve(x, xr, ur, cold, ur[0], zero, zero)
    # Next control step: shifted previous solution vs a cold (hover) start.
    x_next = quad_step(x, sol.u[0], zero)
    xr2, ur2 = quadrotor_reference(1.0 + DT, cfg.N, DT, path, QUAD)
    warm_sol = quad.solve(x_next, xr2, ur2, shift_warm_start(sol.u), sol.u[0], zero, zero)
    cold_sol = quad.solve(x_next, xr2, ur2, cold, sol.u[0], zero, zero)
    assert bool(warm_sol.converged) and bool(cold_sol.converged)
    assert int(warm_sol.iterations) < int(cold_sol.iterations)
    np.testing.assert_allclose(warm_sol.u, cold_sol.u, atol=1e-3)  # same optimum
    # Re-solving from the optimum itself needs the minimum number of steps.
    again = quad.solve(x_next, xr2, ur2, warm_sol.u, sol.u[0], zero, zero)
    assert int(again.iterations) <= 2


def test_new_model_does_not_recompile(quad):
    cfg = quad.config
    xr, ur = hover_problem(cfg.N)
    x0 = hover_state(jnp.array([0.2, 0.0, 1.0]))
    quad.solve(x0, xr, ur, ur, ur[0], jnp.zeros(13), jnp.zeros(13))
    before = TRACES["quad"]
    # Same shapes and dtypes (note: jnp.full(n, 0.1) without dtype is weakly typed, which
    # jit treats as a different type).
    f64 = jnp.float64
    a = quad.solve(x0, xr, ur, ur, ur[0], jnp.full(13, 1e-3, f64), jnp.zeros(13))
    b = quad.solve(x0, xr, ur, ur, ur[0], jnp.full(13, -1e-3, f64), jnp.full(13, 1e-3, f64))
    assert TRACES["quad"] == before
    assert not np.allclose(a.u, b.u)  # the new model and variance were used


def test_non_finite_model_falls_back_to_warm_start(quad):
    cfg = quad.config
    xr, ur = hover_problem(cfg.N)
    warm = ur.at[:, 0].set(25.0)  # also outside the thrust bound: must be clipped
    broken = jnp.full(13, jnp.nan, jnp.float64)
    sol = quad.solve(hover_state(), xr, ur, warm, ur[0], broken, jnp.zeros(13))
    assert not bool(sol.converged)
    assert np.all(np.isfinite(np.asarray(sol.u)))
    np.testing.assert_allclose(sol.u[:, 0], 20.0)
    np.testing.assert_allclose(sol.u[:, 1:], ur[:, 1:])


def test_diverging_warm_start_falls_back_to_the_input_reference():
    """A warm start the model rolls out to NaN (a diverged plan carried over by the shift)
    is not handed out again: the finite input reference is the fallback of last resort."""

    def fragile_step(x, u, bias):  # the learned term blows up above 15 N of thrust
        return quadrotor_step(x, u, QUAD, DT) + bias + jnp.where(u[0] > 15.0, jnp.nan, 0.0)

    ctrl = make_controller(fragile_step, quadrotor_mpc_config(max_thrust=16.0))
    xr, ur = hover_problem(ctrl.config.N)
    warm = ur.at[:, 0].set(15.5)
    sol = ctrl.solve(hover_state(), xr, ur, warm, ur[0], jnp.zeros(13), jnp.zeros(13))
    assert not bool(sol.converged)
    np.testing.assert_allclose(sol.u, ur)
    assert np.all(np.isfinite(np.asarray(sol.x_pred))) and np.isfinite(float(sol.cost))


def test_non_finite_warm_start_is_never_handed_out():
    """A NaN warm start with a model that makes every plan non-finite (both fallback costs
    inf): the finite input reference is returned, not the NaN warm start."""
    from arcade_core.mpc import MPCConfig

    one = jnp.ones(1, jnp.float64)
    cfg = MPCConfig(
        Q=jnp.ones(2, jnp.float64), R=one, P=jnp.ones(2, jnp.float64), u_min=-one, u_max=one, N=3
    )

    def toy_step(x, u, bias):  # double integrator plus a learned term
        return x + 0.1 * jnp.stack([x[1], u[0]]) + bias

    ctrl = make_controller(toy_step, cfg)
    x0, xr = jnp.array([1.0, 0.0]), jnp.zeros((4, 2))
    ur = jnp.full((3, 1), 0.25)
    nan_warm = jnp.full((3, 1), jnp.nan)
    sol = ctrl.solve(x0, xr, ur, nan_warm, jnp.zeros(1), jnp.full(2, jnp.nan))
    assert not bool(sol.converged)
    np.testing.assert_array_equal(sol.u, ur)
    # Both plans non-finite but the warm start finite: the warm start is kept.
    warm = jnp.full((3, 1), -0.5)
    sol = ctrl.solve(x0, xr, ur, warm, jnp.zeros(1), jnp.full(2, jnp.nan))
    np.testing.assert_array_equal(sol.u, warm)


def test_thrust_bound_follows_the_vehicle():
    assert float(quadrotor_mpc_config().u_max[0]) == 20.0  # Appendix D table
    assert float(quadrotor_mpc_config(max_thrust=16.0).u_max[0]) == 16.0


def test_soft_state_bound_limits_predicted_excursion(cart):
    free, base = cart, cart.config
    x_max = jnp.array([0.3, jnp.inf, jnp.inf, jnp.inf])  # cart position <= 0.3 m
    bounded = make_controller(cart_step, cartpole_mpc_config(x_max=x_max))
    xr, ur = jnp.zeros((base.N + 1, 4)), jnp.zeros((base.N, 1))
    args = (jnp.array([0.0, 0.0, 0.1, 0.0]), xr, ur, jnp.zeros((base.N, 1)), jnp.zeros(1),
            jnp.zeros(4), jnp.zeros(4))  # fmt: skip
    free_max = float(free.solve(*args).x_pred[:, 0].max())
    bounded_max = float(bounded.solve(*args).x_pred[:, 0].max())
    assert free_max > 0.4  # the unconstrained plan moves the cart well past 0.3 m
    assert bounded_max < 0.32


def test_rollout_jvp_matches_plain_autodiff():
    key = jax.random.PRNGKey(0)
    W = 0.3 * jax.random.normal(key, (13, 17))

    def step(x, u, model):
        learned = 0.01 * jnp.tanh(model["W"] @ jnp.concatenate([x, u]))
        return quadrotor_step(x, u, QUAD, DT) + learned

    def plain(x0, U, model):
        def body(x, u):
            x_next = step(x, u, model)
            return x_next, x_next

        return jnp.concatenate([x0[None], jax.lax.scan(body, x0, U)[1]])

    x0 = hover_state(jnp.array([0.1, 0.2, 1.0])).at[3:6].set(jnp.array([0.5, -0.2, 0.1]))
    U = hover_input(QUAD) + 0.2 * jax.random.normal(jax.random.PRNGKey(1), (6, 4))
    tangents = (
        jax.random.normal(jax.random.PRNGKey(2), x0.shape),
        jax.random.normal(jax.random.PRNGKey(3), U.shape),
        jax.random.normal(jax.random.PRNGKey(4), W.shape),
    )

    def derivatives(roll):
        @jax.jit
        def both(x0, U, W, dx0, dU, dW):
            f = lambda x0, U, W: roll(x0, U, {"W": W})  # noqa: E731
            # Inputs only (as the MPC's Gauss-Newton linearisation), then all arguments.
            out, lin = jax.linearize(lambda U: f(x0, U, W), U)
            return out, lin(dU), jax.jvp(f, (x0, U, W), (dx0, dU, dW))[1]

        return both(x0, U, W, *tangents)

    for got, want in zip(derivatives(make_rollout(step)), derivatives(plain)):
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)


def _learned_quad_step(x, u, model):
    return quadrotor_step(x, u, QUAD, DT) + 0.01 * jnp.tanh(model["W"] @ jnp.concatenate([x, u]))


def _nominal_quad(x, u):
    return quadrotor_step(x, u, QUAD, DT)


def test_a_staged_rollout_gives_each_stage_its_model_and_the_right_jvp():
    """``staged=True``: step i sees model[i]; values and derivatives (including those with
    respect to the per-stage model) match plain autodiff of the same recursion."""
    N = 6
    D = 0.01 * jax.random.normal(jax.random.PRNGKey(5), (N, 13))
    x0 = hover_state(jnp.array([0.1, 0.2, 1.0])).at[3:6].set(jnp.array([0.5, -0.2, 0.1]))
    U = hover_input(QUAD) + 0.2 * jax.random.normal(jax.random.PRNGKey(1), (N, 4))
    step = staged_residual_step(_nominal_quad)

    def plain(x0, U, D):
        def body(x, inp):
            x_next = step(x, *inp)
            return x_next, x_next

        return jnp.concatenate([x0[None], jax.lax.scan(body, x0, (U, D))[1]])

    staged = make_rollout(step, staged=True)
    X = staged(x0, U, D)
    # Stage i's residual lands on x_{i+1} and nowhere else.
    np.testing.assert_allclose(X[1:] - jax.vmap(_nominal_quad)(X[:-1], U), D, atol=1e-12)
    tangents = tuple(
        jax.random.normal(jax.random.PRNGKey(k), a.shape) for k, a in zip((2, 3, 4), (x0, U, D))
    )
    got = jax.jvp(staged, (x0, U, D), tangents)
    want = jax.jvp(plain, (x0, U, D), tangents)
    for g, w in zip(got, want):
        np.testing.assert_allclose(g, w, rtol=1e-10, atol=1e-12)


def test_the_residual_held_along_a_plan_reproduces_the_learned_prediction_of_that_plan():
    """:func:`residual_along`: the staged model predicts the plan it was evaluated on
    exactly as the learned model does, but its input derivatives are those of ``f_nom``."""
    W = 0.3 * jax.random.normal(jax.random.PRNGKey(0), (13, 17))
    model = {"W": W}
    x0 = hover_state(jnp.array([0.0, 0.0, 1.0])).at[3:6].set(jnp.array([1.0, 0.0, 0.0]))
    U = hover_input(QUAD) + 0.3 * jax.random.normal(jax.random.PRNGKey(1), (8, 4))
    D = residual_along(_learned_quad_step, _nominal_quad, model, x0, U)
    learned = make_rollout(_learned_quad_step)
    held = make_rollout(staged_residual_step(_nominal_quad), staged=True)
    np.testing.assert_allclose(held(x0, U, D), learned(x0, U, model), atol=1e-12)
    dU = jax.random.normal(jax.random.PRNGKey(2), U.shape)
    d_held = jax.jvp(lambda U: held(x0, U, D), (U,), (dU,))[1]

    def frozen_slopes(x, u, m):  # the learned value, the nominal model's derivatives
        res = _learned_quad_step(x, u, m) - _nominal_quad(x, u)
        return _nominal_quad(x, u) + jax.lax.stop_gradient(res)

    d_nominal = jax.jvp(lambda U: make_rollout(frozen_slopes)(x0, U, model), (U,), (dU,))[1]
    d_learned = jax.jvp(lambda U: learned(x0, U, model), (U,), (dU,))[1]
    np.testing.assert_allclose(d_held, d_nominal, atol=1e-12)
    assert float(jnp.max(jnp.abs(d_learned - d_held))) > 1e-6


def test_line_search_converges_where_full_gauss_newton_steps_diverge():
    """``ArmijoGaussNewton`` rejects steps that raise the cost beyond rounding noise.

    ``r(z) = arctan(z)``: full Gauss-Newton steps from ``|z| > 1.39`` overshoot further
    each time; the backtracking search halves them until the cost falls.
    """
    import lineax as lx
    import optimistix as optx

    def fn(z, _):
        return jnp.arctan(z)

    z0 = jnp.array([3.0])
    lin = lx.Normal(lx.Cholesky())
    full = optx.least_squares(
        fn, optx.GaussNewton(1e-8, 1e-8, linear_solver=lin), z0, max_steps=20, throw=False
    )
    assert not abs(float(full.value[0])) < 1.0  # diverged (or non-finite)
    damped = optx.least_squares(
        fn, ArmijoGaussNewton(1e-8, 1e-8, lin), z0, max_steps=40, throw=False
    )
    assert damped.result == optx.RESULTS.successful
    assert abs(float(damped.value[0])) < 1e-6


def test_a_smoothness_weight_per_input_weighs_that_inputs_change_only():
    """``smooth_weight`` as one weight per input: the same weight on every input is the
    scalar's problem; a larger one on the thrust alone makes the first thrust step from
    the previous input smaller."""
    x0 = hover_state(jnp.array([0.0, 0.0, 0.6]))  # 0.4 m below the reference: climb
    xr, ur = hover_problem(20)
    u_prev = hover_input(QUAD)
    first = {}
    for name, w in (("scalar", 10.0), ("same", (10.0,) * 4), ("thrust", (1000.0,) + (10.0,) * 3)):
        ctrl = make_controller(quad_step, quadrotor_mpc_config(smooth_weight=w))
        sol = ctrl.solve(
            x0, xr, ur, ctrl.initial_guess(u_prev), u_prev, jnp.zeros(13), jnp.zeros(13)
        )
        first[name] = np.asarray(sol.u[0]) - np.asarray(u_prev)
    np.testing.assert_allclose(first["same"], first["scalar"], rtol=1e-12, atol=1e-12)
    assert first["scalar"][0] > 0.1  # it climbs
    assert 0.0 < first["thrust"][0] < 0.5 * first["scalar"][0]
