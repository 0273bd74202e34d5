"""Nominal models (Appendix D), quaternion helpers and flatness-based references."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from arcade_core import frames as quaternion
from arcade_core.dynamics import (
    CARTPOLE_DT,
    CARTPOLE_NOMINAL,
    CARTPOLE_TRUE,
    QuadrotorParams,
    cartpole_nominal_step,
    cartpole_step,
    cartpole_true_step,
    hover_input,
    hover_state,
    predict_over_delay,
    quadrotor_deriv,
    quadrotor_step,
    sample_disturbance,
)
from arcade_core.trajectories import (
    Chain,
    FigureEight,
    Hover,
    Takeoff,
    flat_state,
    quadrotor_reference,
)

QUAD = QuadrotorParams()


def _cartpole_by_hand(x, u, M, m, L, g, mu_c, mu_p, u_dist):
    """Appendix D equations, written out independently with Python floats."""
    _, xd, th, thd = x
    s, c = math.sin(th), math.cos(th)
    den = M + m * s * s
    xdd = (u + u_dist - mu_c * xd + m * s * (L * thd**2 + g * c)) / den
    thdd = (-(u + u_dist) * c - mu_p * thd - m * L * thd**2 * s * c + (M + m) * g * s) / (L * den)
    return np.array([xd, xdd, thd, thdd])


def test_cartpole_true_and_nominal_match_hand_computation():
    x = [0.3, -0.4, 0.25, 0.7]
    u, u_dist, dt = 2.5, -0.8, CARTPOLE_DT
    p = CARTPOLE_TRUE
    expected_true = np.array(x) + dt * _cartpole_by_hand(
        x, u, p.M, p.m, p.L, p.g, p.mu_c, p.mu_p, u_dist
    )
    got_true = cartpole_true_step(None, jnp.array(x), u, u_dist=u_dist)
    np.testing.assert_allclose(got_true, expected_true, rtol=1e-12, atol=1e-14)

    n = CARTPOLE_NOMINAL
    expected_nom = np.array(x) + dt * _cartpole_by_hand(x, u, n.M, n.m, n.L, n.g, 0, 0, 0)
    np.testing.assert_allclose(cartpole_nominal_step(jnp.array(x), u), expected_nom, rtol=1e-12)
    # The two models really differ (parameters, friction, disturbance).
    assert np.abs(expected_true - expected_nom).max() > 1e-2


def test_cartpole_true_step_disturbance_and_impulse():
    key = jax.random.PRNGKey(3)
    x = jnp.array([0.0, 0.2, -0.1, 0.0])
    drawn = cartpole_true_step(key, x, 1.0)
    explicit = cartpole_true_step(None, x, 1.0, u_dist=sample_disturbance(key))
    np.testing.assert_allclose(drawn, explicit, rtol=1e-14)
    # An extra force is the same as a larger input.
    pushed = cartpole_true_step(None, x, 1.0, force=3.0, u_dist=0.0)
    np.testing.assert_allclose(pushed, cartpole_step(x, 4.0, CARTPOLE_TRUE), rtol=1e-14)
    # Disturbance statistics: N(-0.5, 0.5) (variance 0.5).
    d = jax.vmap(sample_disturbance)(jax.random.split(key, 20000))
    assert abs(float(d.mean()) + 0.5) < 0.02
    assert abs(float(d.var()) - 0.5) < 0.03
    with pytest.raises(ValueError):
        cartpole_true_step(None, x, 1.0)


def test_quadrotor_hover_is_equilibrium():
    x = hover_state(jnp.array([0.5, -1.0, 2.0]))
    u = hover_input(QUAD)
    np.testing.assert_allclose(quadrotor_deriv(x, u, QUAD), 0.0, atol=1e-12)
    for _ in range(20):
        x = quadrotor_step(x, u, QUAD, 0.05)
    np.testing.assert_allclose(x, hover_state(jnp.array([0.5, -1.0, 2.0])), atol=1e-12)


def test_quadrotor_free_fall():
    x = hover_state(jnp.array([0.0, 0.0, 10.0]))
    u = jnp.zeros(4)
    dt, n = 0.02, 50
    for _ in range(n):
        x = quadrotor_step(x, u, QUAD, dt)
    t = n * dt
    np.testing.assert_allclose(x[2], 10.0 - 0.5 * QUAD.gravity * t**2, rtol=1e-12)
    np.testing.assert_allclose(x[5], -QUAD.gravity * t, rtol=1e-12)
    np.testing.assert_allclose(x[:2], 0.0, atol=1e-14)


def test_thrust_tilts_with_attitude():
    # Rolled by +30° (right-hand about body x): thrust pushes towards -y in ENU.
    q = quaternion.from_rpy(jnp.array(math.radians(30)), jnp.array(0.0), jnp.array(0.0))
    x = hover_state().at[6:10].set(q)
    acc = quadrotor_deriv(x, jnp.array([10.0, 0.0, 0.0, 0.0]), QUAD)[3:6]
    a = 10.0 / QUAD.mass
    expected = [0.0, -a * 0.5, a * math.cos(math.radians(30)) - 9.81]
    np.testing.assert_allclose(acc, expected, atol=1e-12)


def test_quaternion_stays_unit_over_long_rollout():
    x = hover_state()
    u = jnp.array([QUAD.mass * 9.81, 1.3, -2.1, 0.7])
    step = jax.jit(lambda x: quadrotor_step(x, u, QUAD, 0.05))
    for _ in range(2000):
        x = step(x)
    assert abs(float(jnp.linalg.norm(x[6:10])) - 1.0) < 1e-12
    assert np.all(np.isfinite(np.asarray(x)))


def test_body_rate_step_is_first_order_lag():
    u = jnp.array([QUAD.mass * 9.81, 2.0, -1.0, 0.5])
    x, dt = hover_state(), 0.005
    step = jax.jit(lambda x: quadrotor_step(x, u, QUAD, dt))
    z = -dt / QUAD.rate_tau
    rk4_factor = 1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24  # RK4 amplification for y' = λy
    for k in range(1, 41):
        x = step(x)
        # Exactly the RK4 discretisation of omega' = (omega_cmd - omega)/tau ...
        np.testing.assert_allclose(x[10:13], np.array(u[1:]) * (1 - rk4_factor**k), rtol=1e-12)
        # ... which follows the continuous first-order response closely.
        expected = np.array(u[1:]) * (1.0 - math.exp(-k * dt / QUAD.rate_tau))
        np.testing.assert_allclose(x[10:13], expected, rtol=2e-6)
    # After 4 time constants the rates are within 2 % of the setpoint.
    assert np.all(np.abs(np.asarray(x[10:13]) - np.asarray(u[1:])) < 0.02 * np.abs(u[1:]))


def test_predicting_over_a_link_delay_carries_the_state_and_its_variance():
    q = quaternion.from_rpy(0.1, -0.2, 0.3)
    x = jnp.concatenate(
        [jnp.array([0.3, -0.2, 1.1, 1.5, -0.4, 0.2]), q, jnp.array([0.4, -0.3, 0.2])]
    )
    u = jnp.array([6.2, 0.5, -0.2, 0.1])
    var = jnp.linspace(1e-6, 1.3e-5, 13)
    x_d, var_d = predict_over_delay(x, var, u, QUAD, 0.02)
    # The state: one RK4 step of the nominal model over the delay with the input in flight.
    np.testing.assert_allclose(x_d, quadrotor_step(x, u, QUAD, 0.02), rtol=1e-13, atol=1e-15)
    # Its variance, to first order: against a central-difference Jacobian of that step.
    eps = 1e-6
    cols = [
        (quadrotor_step(x + eps * e, u, QUAD, 0.02) - quadrotor_step(x - eps * e, u, QUAD, 0.02))
        / (2 * eps)
        for e in jnp.eye(13)
    ]
    jac = np.stack([np.asarray(c) for c in cols], axis=1)
    np.testing.assert_allclose(var_d, jac**2 @ np.asarray(var), rtol=1e-6, atol=1e-18)
    # Over the delay the velocity's uncertainty moves into the position's.
    assert np.all(np.asarray(var_d[:3]) > np.asarray(var[:3]))
    # No delay: the same state and, but along the unit quaternion itself, the same variance.
    x_0, var_0 = predict_over_delay(x, var, u, QUAD, 0.0)
    np.testing.assert_allclose(x_0, x, atol=1e-15)
    keep = np.r_[0:6, 10:13]
    np.testing.assert_allclose(np.asarray(var_0)[keep], np.asarray(var)[keep], rtol=1e-12)


def test_quadrotor_jit_and_vmap():
    key = jax.random.PRNGKey(0)
    xs = jnp.tile(hover_state(), (8, 1))
    xs = xs.at[:, :6].add(jax.random.normal(key, (8, 6)))
    qs = quaternion.normalize(jax.random.normal(jax.random.PRNGKey(1), (8, 4)))
    xs = xs.at[:, 6:10].set(qs)
    us = hover_input(QUAD) + 0.3 * jax.random.normal(jax.random.PRNGKey(2), (8, 4))
    batched = jax.jit(jax.vmap(lambda x, u: quadrotor_step(x, u, QUAD, 0.05)))(xs, us)
    single = jax.jit(lambda x, u: quadrotor_step(x, u, QUAD, 0.05))
    looped = jnp.stack([single(x, u) for x, u in zip(xs, us)])
    np.testing.assert_allclose(batched, looped, rtol=1e-12, atol=1e-12)
    cart = jax.vmap(lambda x, u: cartpole_nominal_step(x, u))(xs[:, :4], us[:, 0])
    assert cart.shape == (8, 4)


@jax.jit
def _quaternion_roundtrips(q, v):
    R = quaternion.to_rotation_matrix(q)
    pure = jnp.concatenate([jnp.zeros((q.shape[0], 1)), v], axis=1)
    sandwich = quaternion.multiply(quaternion.multiply(q, pure), quaternion.conjugate(q))
    return R, quaternion.from_rotation_matrix(R), quaternion.rotate(q, v), sandwich[:, 1:]


def test_quaternion_helpers_roundtrip():
    key = jax.random.PRNGKey(7)
    q = quaternion.normalize(jax.random.normal(key, (64, 4)))
    q = jnp.where(q[:, :1] < 0, -q, q)
    # Include near-180° rotations so every Shepperd pivot is exercised.
    q = jnp.concatenate(
        [
            q,
            jnp.array(
                [
                    [0.0, 1.0, 0.0, 0.0],
                    [0.0, 0.0, 1.0, 0.0],
                    [0.0, 0.0, 0.0, 1.0],
                    [1e-3, 0.6, 0.8, 0.0],
                ]
            ),
        ]
    )
    q = quaternion.normalize(q)
    v = jax.random.normal(jax.random.PRNGKey(8), (q.shape[0], 3))
    R, q_back, rotated, sandwich = map(np.asarray, _quaternion_roundtrips(q, v))
    np.testing.assert_allclose(
        R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(q_back, q, atol=1e-9)
    # rotate(q, v) equals the sandwich product q ⊗ [0, v] ⊗ q*.
    np.testing.assert_allclose(rotated, sandwich, atol=1e-12)
    rpy = jnp.array([0.3, -0.4, 2.0])
    q1 = quaternion.from_rpy(*rpy)
    np.testing.assert_allclose(quaternion.to_rpy(q1), rpy, atol=1e-12)
    Rz = quaternion.to_rotation_matrix(quaternion.from_rpy(0.0, 0.0, jnp.pi / 2))
    np.testing.assert_allclose(Rz @ jnp.array([1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-12)


def test_quaternion_error():
    q_ref = quaternion.from_rpy(0.1, 0.2, 0.3)
    np.testing.assert_allclose(quaternion.error(q_ref, q_ref), 0.0, atol=1e-14)
    np.testing.assert_allclose(quaternion.error(-q_ref, q_ref), 0.0, atol=1e-14)
    small = quaternion.from_rpy(0.0, 0.0, 0.01)
    err = quaternion.error(quaternion.multiply(q_ref, small), q_ref)
    np.testing.assert_allclose(err, [0.0, 0.0, 0.01], atol=1e-6)


def test_quaternion_align_picks_the_reference_hemisphere():
    q_ref = quaternion.from_rpy(0.1, -0.2, 0.3)
    q = quaternion.from_rpy(0.15, -0.1, 0.25)
    np.testing.assert_array_equal(quaternion.align(q, q_ref), q)
    np.testing.assert_array_equal(quaternion.align(-q, q_ref), q)
    batch = jnp.stack([q, -q, -q_ref])
    assert np.all(np.asarray(jnp.sum(quaternion.align(batch, q_ref) * q_ref, axis=-1)) > 0)


def test_figure_eight_speed_and_shape():
    path = FigureEight(center=(1.0, 2.0, 1.5), half_length=2.0, half_width=1.0, speed=2.5)
    period = float(path.period())
    ts = jnp.linspace(0.0, period, 4001)
    xs = jax.jit(jax.vmap(lambda t: flat_state(path, t, QUAD)[0]))(ts)
    x_end, xs = xs[-1], xs[:-1]
    speed = jnp.linalg.norm(xs[:, 3:6], axis=1)
    np.testing.assert_allclose(float(speed.mean()), 2.5, rtol=1e-4)
    np.testing.assert_allclose(xs[0, :3], [1.0, 2.0, 1.5], atol=1e-12)  # starts at centre
    np.testing.assert_allclose(xs[:, 2], 1.5, atol=1e-12)  # horizontal
    np.testing.assert_allclose(xs[:, 0].max() - xs[:, 0].min(), 4.0, rtol=1e-4)
    assert float(xs[len(ts) // 4, 0]) > 1.0  # the x > 0 loop first
    np.testing.assert_allclose(x_end, xs[0], atol=1e-9)  # periodic


@pytest.mark.parametrize(
    "path",
    [
        FigureEight(speed=2.5),
        Takeoff(start=(0.0, 0.0, 0.0), end=(0.5, 0.0, 1.0), duration=2.0),
        Chain(Hover((0.0, 0.0, 1.0)), FigureEight(speed=1.0), switch_time=0.5),
    ],
)
def test_flat_reference_satisfies_nominal_dynamics(path):
    """x_ref'(t) = f(x_ref(t), u_ref(t)): thrust, attitude, rates and rate setpoints agree."""
    h = 1e-5

    @jax.jit
    def model_and_finite_difference(t):
        x, u = flat_state(path, t, QUAD)
        fd = (flat_state(path, t + h, QUAD)[0] - flat_state(path, t - h, QUAD)[0]) / (2 * h)
        return quadrotor_deriv(x, u, QUAD), fd, jnp.linalg.norm(x[6:10])

    for t in (0.13, 0.77, 1.41):
        f, fd, qnorm = model_and_finite_difference(t)
        np.testing.assert_allclose(f, fd, atol=1e-6)
        np.testing.assert_allclose(qnorm, 1.0, atol=1e-12)


def test_quadrotor_reference_shapes_and_hover():
    xr, ur = quadrotor_reference(0.0, 20, 0.05, Hover((0.0, 0.0, 1.0)), QUAD)
    assert xr.shape == (21, 13) and ur.shape == (20, 4)
    np.testing.assert_allclose(
        xr, jnp.tile(hover_state(jnp.array([0.0, 0.0, 1.0])), (21, 1)), atol=1e-12
    )
    np.testing.assert_allclose(ur, jnp.tile(hover_input(QUAD), (20, 1)), atol=1e-12)
    xr2, _ = quadrotor_reference(1.0, 20, 0.05, FigureEight(), QUAD)
    x_at, _ = jax.jit(flat_state)(FigureEight(), 1.0 + 0.05 * 7, QUAD)
    np.testing.assert_allclose(xr2[7], x_at, atol=1e-12)
