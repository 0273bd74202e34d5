"""The advanced-step controller: a plan solved one period ahead, corrected to first order
when the state and the model arrive (``arcade_core.mpc``'s ``first_input_gain`` and
``residual_change``; ``arcade_control.step.make_advanced_step``). Float64."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from arcade_control.methods import make_method
from arcade_control.nominal import CONTROL_DT, nominal_params
from arcade_control.step import (
    PREPARE_STEPS,
    Carry,
    make_advanced_step,
    make_controller_step,
    mpc_config,
    planned_carry,
    predict_period,
)
from arcade_core import mpc
from arcade_core.dynamics import QuadrotorParams, hover_input, quadrotor_step
from arcade_core.trajectories import FigureEight, quadrotor_reference

QUAD = QuadrotorParams()
F64 = jnp.float64


def wind_step(x, u, wind):
    """Nominal model plus a learned velocity change (a constant acceleration ``wind``)."""
    x_next = quadrotor_step(x, u, QUAD, CONTROL_DT)
    return x_next.at[3:6].add(CONTROL_DT * wind)


@pytest.fixture(scope="module")
def problem():
    cfg = mpc.quadrotor_mpc_config(dtype=F64, max_steps=60, rtol=1e-12, atol=1e-12)
    ctrl = mpc.make_controller(wind_step, cfg)
    path = FigureEight(center=(0.0, 0.0, 1.0), speed=2.0)
    x_ref, u_ref = quadrotor_reference(1.3, cfg.N, CONTROL_DT, path, QUAD)
    offset = jnp.asarray([0.05, -0.03, 0.02, 0.1, 0.05, -0.1, 0, 0, 0, 0, 0.1, -0.1, 0.05])
    u_prev = hover_input(QUAD, F64)
    wind = jnp.asarray([0.3, -0.2, 0.4], F64)
    args = (x_ref[0] + offset, x_ref, u_ref)
    sol = ctrl.solve(*args, jnp.broadcast_to(u_prev, (cfg.N, 4)), u_prev, wind)
    assert bool(sol.converged)
    return ctrl, args, u_prev, wind, sol


def resolve(ctrl, x0, x_ref, u_ref, u_prev, wind, warm):
    return ctrl.solve(x0, x_ref, u_ref, warm, u_prev, wind).u[0]


def test_the_first_input_gain_predicts_how_the_optimum_moves_with_the_state(problem):
    ctrl, (x0, x_ref, u_ref), u_prev, wind, sol = problem
    G = ctrl.first_input_gain(x0, x_ref, u_ref, sol.u, u_prev, wind)
    assert G.shape == (4, mpc.residual_count(ctrl.config))
    rng = np.random.default_rng(0)
    for _ in range(3):
        dx = jnp.asarray(rng.normal(size=13) * 1e-4).at[6:10].set(0.0)
        r, dr = ctrl.residual_change(
            x0, x_ref, u_ref, sol.u, u_prev, wind, None, x0 + dx, wind, u_ref
        )
        exact = resolve(ctrl, x0 + dx, x_ref, u_ref, u_prev, wind, sol.u) - sol.u[0]
        # Gauss-Newton's approximation drops the residuals' curvature: about 1 % here.
        assert np.linalg.norm(G @ dr - exact) <= 0.03 * np.linalg.norm(exact)
        # At the optimum the residuals themselves move nothing (the gradient vanishes).
        assert np.linalg.norm(G @ r) <= 1e-6 * np.linalg.norm(exact)


def test_the_correction_follows_a_change_of_the_model_and_of_the_input_reference(problem):
    ctrl, (x0, x_ref, u_ref), u_prev, wind, sol = problem
    G = ctrl.first_input_gain(x0, x_ref, u_ref, sol.u, u_prev, wind)
    d_wind = jnp.asarray([2e-3, 1e-3, -3e-3], F64)
    d_ref = jnp.zeros_like(u_ref).at[:, 0].add(2e-3)
    changed = (x0, wind + d_wind, u_ref + d_ref)
    _, dr = ctrl.residual_change(x0, x_ref, u_ref, sol.u, u_prev, wind, None, *changed)
    exact = resolve(ctrl, x0, x_ref, u_ref + d_ref, u_prev, wind + d_wind, sol.u) - sol.u[0]
    assert np.abs(exact).max() > 1e-4  # the change moves the optimum
    assert np.linalg.norm(G @ dr - exact) <= 0.03 * np.linalg.norm(exact)
    # Nothing changed: no correction.
    r, same = ctrl.residual_change(x0, x_ref, u_ref, sol.u, u_prev, wind, None, x0, wind, u_ref)
    assert float(jnp.abs(same).max()) == 0.0
    assert np.isclose(float(r @ r), float(sol.cost), rtol=1e-10)  # the plan's residuals


def test_the_correction_at_a_plan_short_of_the_optimum_is_its_gauss_newton_step(problem):
    ctrl, (x0, x_ref, u_ref), u_prev, wind, sol = problem
    # A plan one iteration from a poor start (hover), then the first input's step from it.
    cfg1 = dataclasses.replace(ctrl.config, max_steps=1)
    short = mpc.make_controller(wind_step, cfg1)
    hover = jnp.broadcast_to(u_prev, (cfg1.N, 4))
    plan = short.solve(x0, x_ref, u_ref, hover, u_prev, wind).u
    G = ctrl.first_input_gain(x0, x_ref, u_ref, plan, u_prev, wind)
    r, _ = ctrl.residual_change(x0, x_ref, u_ref, plan, u_prev, wind, None, x0, wind, u_ref)
    before = float(jnp.linalg.norm(plan[0] - sol.u[0]))
    after = float(jnp.linalg.norm(plan[0] + G @ r - sol.u[0]))
    assert before > 1e-2  # one iteration from hover is not the optimum...
    assert after < 0.5 * before  # ...and the step goes most of the way


def _references(n: int):
    """A figure-eight over the horizon of ``n`` control steps: the window of instant ``k``
    is ``x_all[k : k + N + 1]``, ``u_all[k : k + N]``."""
    cfg = mpc_config(F64)
    path = FigureEight(center=(0.0, 0.0, 1.0), speed=1.5)
    x_all, u_all = quadrotor_reference(0.0, cfg.N + n, CONTROL_DT, path, QUAD)
    return cfg, x_all, u_all


def test_an_unprepared_advanced_step_is_the_plain_step_and_a_prepared_one_its_first_order():
    n = 6
    cfg, x_all, u_all = _references(n)
    method = make_method("nominal")
    plain = make_controller_step(method, cfg)
    feedback, prepare = make_advanced_step(method, cfg)
    u0 = hover_input(QUAD, F64)
    x = x_all[0] + jnp.asarray([0.03, -0.02, 0.01, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0], F64)
    carry = Carry(jnp.zeros((), F64), jnp.broadcast_to(u0, (cfg.N, 4)), u0, x, jnp.array(True))
    # No plan yet: the full solve, bit for bit the plain step's.
    new_plain, u_plain, diag_plain = plain(carry, x, u0, 0, x_all, u_all)
    new_adv, u_adv, diag_adv = feedback(planned_carry(carry, cfg), x, u0, 0, x_all, u_all)
    np.testing.assert_array_equal(u_adv, u_plain)
    np.testing.assert_array_equal(diag_adv, diag_plain)
    # Prepared for the next instant from the predicted state, within PREPARE_STEPS
    # iterations: answering exactly that state hands out the plan's first input plus its
    # Gauss-Newton step (as the full solve, to the solver's tolerance); a state off the
    # prediction, its correction too.
    planned = prepare(new_adv, 1, CONTROL_DT, x_all, u_all)
    assert bool(planned.plan.ready)
    # The cap is what stops the plan: solved without it, the same plan takes more.
    _, prepare_full = make_advanced_step(method, cfg, prepare_steps=None)
    full = prepare_full(new_adv, 1, CONTROL_DT, x_all, u_all)
    assert int(full.plan.iterations) > PREPARE_STEPS
    assert int(planned.plan.iterations) == PREPARE_STEPS
    x_pred = predict_period(method, new_adv.learner, new_adv.x_prev, new_adv.u_mpc, CONTROL_DT)
    np.testing.assert_allclose(planned.plan.x0, x_pred, atol=1e-12)
    _, u_on, _ = feedback(planned, x_pred, u_plain, 1, x_all, u_all)
    on_solved = plain(new_plain, x_pred, u_plain, 1, x_all, u_all)[1]
    np.testing.assert_allclose(u_on, on_solved, atol=1e-3)
    off = x_pred + jnp.asarray([0.01, 0.0, -0.01, 0.05, -0.05, 0.02, 0, 0, 0, 0, 0, 0, 0], F64)
    _, u_off, _ = feedback(planned, off, u_plain, 1, x_all, u_all)
    solved = plain(new_plain, off, u_plain, 1, x_all, u_all)[1]
    moved = float(jnp.abs(solved - planned.u_warm[0]).max())
    assert moved > 1e-2  # the state error matters...
    assert float(jnp.abs(u_off - solved).max()) < 0.1 * moved  # ...and is corrected for


def test_the_prediction_over_a_period_is_the_models_step_at_the_models_period():
    method = make_method("nominal")
    x = jnp.asarray([0, 0, 1.0, 0.5, -0.2, 0.1, 1.0, 0, 0, 0, 0.1, 0, 0], F64)
    u = hover_input(nominal_params(), F64).at[0].add(0.3)
    ref = quadrotor_step(x, u, nominal_params(), CONTROL_DT)
    np.testing.assert_allclose(predict_period(method, None, x, u, CONTROL_DT), ref, atol=1e-12)
    short = predict_period(method, None, x, u, 0.02)
    np.testing.assert_allclose(short, quadrotor_step(x, u, nominal_params(), 0.02), atol=1e-12)
    assert jax.tree.leaves(short)[0].dtype == F64
