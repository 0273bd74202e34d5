"""L1 augmentation: estimates a constant unknown force / rate disturbance and cancels it.

The plant is a tiny local quadrotor integrator in the project's convention (ENU, FLU,
q = [w, x, y, z], first-order body-rate loop), integrated with sub-steps.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from arcade_core import frames
from arcade_core.baselines import l1

MASS, G, TAU = 0.57, 9.81, 0.05
DT, SUBSTEPS, STEPS = 0.01, 10, 300  # 100 Hz control, 3 s


def _plant_step(x, u, force_world, rate_dist):
    """Nominal quadrotor + unknown world force and rate-loop disturbance, one DT."""
    h = DT / SUBSTEPS

    def sub(x, _):
        p, v, q, w = x[0:3], x[3:6], x[6:10], x[10:13]
        r = frames.to_rotation_matrix(frames.normalize(q))
        acc = u[0] / MASS * r[:, 2] - G * jnp.array([0.0, 0.0, 1.0]) + force_world / MASS
        w_dot = (u[1:4] + rate_dist - w) / TAU
        q = q + h * 0.5 * frames.multiply(q, jnp.r_[0.0, w])
        q = q / jnp.linalg.norm(q)
        return jnp.concatenate([p + h * v, v + h * acc, q, w + h * w_dot]), None

    return jax.lax.scan(sub, x, None, length=SUBSTEPS)[0]


def _run(x0, params, force_world, rate_dist, use_l1=True):
    u_base = jnp.array([MASS * G, 0.0, 0.0, 0.0])
    state = l1.update(l1.init(params), x0, u_base, DT)

    def step(carry, _):
        x, st = carry
        u = u_base + jnp.where(use_l1, l1.correction(st, x), 0.0)
        x = _plant_step(x, u, force_world, rate_dist)
        st = l1.update(st, x, u, DT)
        return (x, st), u

    (x, state), us = jax.lax.scan(step, (x0, state), None, length=STEPS)
    return x, state, us[-1]


def _hover(roll=0.0):
    q = jnp.array([jnp.cos(roll / 2), jnp.sin(roll / 2), 0.0, 0.0])
    return jnp.concatenate([jnp.zeros(6), q, jnp.zeros(3)])


@pytest.mark.parametrize("roll", [0.0, 0.35])
def test_estimates_and_cancels_constant_force(roll):
    params = l1.L1Params(mass=MASS, gravity=G, rate_tau=TAU)
    force = jnp.array([0.2, -0.1, -0.8])  # e.g. a payload hanging slightly off-centre [N]
    x0 = _hover(roll)
    x, state, u = jax.jit(_run, static_argnums=4)(x0, params, force, jnp.zeros(3), True)
    r = frames.to_rotation_matrix(frames.normalize(x[6:10]))
    # The attitude is held (zero rate commands, no rate disturbance).
    np.testing.assert_allclose(r, frames.to_rotation_matrix(frames.normalize(x0[6:10])), atol=1e-9)
    # Estimate: body-axis force within 3 % of the truth (the law settles at e^{a_s dt}).
    tol = 0.03 * float(jnp.linalg.norm(force))
    np.testing.assert_allclose(state.sigma_force, r.T @ force, atol=tol)
    np.testing.assert_allclose(l1.acceleration_estimate(state, x), force / MASS, atol=tol / MASS)
    unmatched = l1.acceleration_estimate(state, x, include_matched=False)
    assert abs(float(unmatched @ r[:, 2])) < 1e-9
    # Correction cancels the matched (thrust-axis) component of the disturbance.
    corr = l1.correction(state, x)
    np.testing.assert_allclose(corr[1:], 0.0)
    matched = float(force @ r[:, 2])
    assert abs(float(corr[0]) + matched) < 0.03 * abs(matched)
    residual_axial = float((force + (u[0] - MASS * G) * r[:, 2]) @ r[:, 2])
    assert abs(residual_axial) < 0.03 * abs(matched)


def test_hover_drift_is_removed():
    params = l1.L1Params(mass=MASS, gravity=G, rate_tau=TAU)
    force = jnp.array([0.0, 0.0, -0.8])
    run = jax.jit(_run, static_argnums=4)
    x_off, _, _ = run(_hover(), params, force, jnp.zeros(3), False)
    x_on, _, _ = run(_hover(), params, force, jnp.zeros(3), True)
    # Open loop the vehicle sinks at F/m (4.2 m/s after 3 s); with L1 only the filter
    # transient (about F / (m w_c) = 0.28 m/s) remains and the velocity stops changing.
    np.testing.assert_allclose(x_off[5], -0.8 / MASS * STEPS * DT, rtol=1e-6)
    assert abs(float(x_on[5])) < 0.1 * abs(float(x_off[5]))


def test_rotational_channel_cancels_rate_disturbance():
    dist = jnp.array([0.3, -0.2, 0.1])  # rate-loop bias [rad/s]
    run = jax.jit(_run, static_argnums=4)
    off = l1.L1Params(mass=MASS, gravity=G, rate_tau=TAU, rotational=False)
    on = off._replace(rotational=True)
    x_off, st_off, _ = run(_hover(), off, jnp.zeros(3), dist, True)
    x_on, _, _ = run(_hover(), on, jnp.zeros(3), dist, True)
    np.testing.assert_allclose(x_off[10:13], dist, rtol=1e-6)  # not corrected
    np.testing.assert_allclose(st_off.sigma_rates, dist, rtol=0.03)  # but estimated
    assert float(jnp.max(jnp.abs(x_on[10:13]))) < 0.05 * float(jnp.max(jnp.abs(dist)))


@pytest.mark.parametrize("known_share", [0.0, 0.75, 1.0])
def test_known_acceleration_leaves_only_what_the_model_misses(known_share):
    # L1-GP: the predictor includes what a learned model predicts; the estimate (and the
    # correction) is the rest of the disturbance, and the thrust still cancels all of it.
    params = l1.L1Params(mass=MASS, gravity=G, rate_tau=TAU)
    force = jnp.array([0.0, 0.0, -0.8])
    known = known_share * force / MASS  # the model's share, as an acceleration
    x0 = _hover()
    u_model = jnp.array([MASS * G - known_share * float(force[2]), 0.0, 0.0, 0.0])

    def step(carry, _):
        x, st = carry
        u = u_model + l1.correction(st, x)
        x = _plant_step(x, u, force, jnp.zeros(3))
        return (x, l1.update(st, x, u, DT, known_accel=known)), None

    st0 = l1.update(l1.init(params), x0, u_model, DT, known_accel=known)
    (x, state), _ = jax.jit(lambda c: jax.lax.scan(step, c, None, length=STEPS))((x0, st0))
    missed = (1.0 - known_share) * float(force[2])
    assert abs(float(state.sigma_force[2]) - missed) < 0.03 * abs(float(force[2]))
    assert abs(float(l1.correction(state, x)[0]) + missed) < 0.03 * abs(float(force[2]))
    thrust = float(u_model[0] + l1.correction(state, x)[0])
    assert abs(thrust - MASS * G + float(force[2])) < 0.03 * abs(float(force[2]))  # all of it
