"""The closed loop's thrust reference holds the reference under a learned model whose
residual depends on the thrust (a payload lowers the thrust effectiveness)."""

import jax.numpy as jnp
import numpy as np

from benchmarks import quadrotor_closedloop as cl
from benchmarks import quadrotor_data as qd


def _z_body(q):
    return np.array([2 * (q[1] * q[3] + q[0] * q[2]), 2 * (q[2] * q[3] - q[0] * q[1]),
                     1 - 2 * (q[1] ** 2 + q[2] ** 2)])


def _payload_model(effectiveness: float, offset: float):
    """A learned model in which thrust acts with ``effectiveness`` times the nominal gain,
    plus a constant ``offset`` on the vertical velocity change (both along body z)."""
    p = qd.nominal_params()

    def step(x, u, model):
        x_nom = cl.f_nom(x, u)
        q = x[6:10]
        z_b = jnp.stack([2 * (q[1] * q[3] + q[0] * q[2]), 2 * (q[2] * q[3] - q[0] * q[1]),
                         1 - 2 * (q[1] ** 2 + q[2] ** 2)])
        dv = ((effectiveness - 1.0) * u[0] * cl.DT / p.mass + offset) * z_b
        return x_nom.at[3:6].add(dv)

    return step


def _reference(n: int = 4):
    tilt = np.array([np.cos(0.1), np.sin(0.1), 0.0, 0.0])  # 0.2 rad roll
    x = np.zeros((n + 1, 13))
    x[:, 2] = 1.0
    x[:, 6:10] = tilt
    u = np.zeros((n, 4))
    u[:, 0] = float(qd.nominal_params().mass * 9.81)
    return jnp.asarray(x), jnp.asarray(u)


def test_reference_thrust_matches_the_nominal_acceleration_under_the_learned_model():
    x_ref, u_ref = _reference()
    step = _payload_model(effectiveness=0.8, offset=-0.03)
    out = np.asarray(cl.thrust_reference(step, None, x_ref, u_ref))
    for k in range(len(u_ref)):
        z_b = _z_body(np.asarray(x_ref[k, 6:10]))
        learned = np.asarray(step(x_ref[k], jnp.asarray(out[k]), None))[3:6] @ z_b
        nominal = np.asarray(cl.f_nom(x_ref[k], u_ref[k]))[3:6] @ z_b
        assert abs(learned - nominal) < 1e-5
    np.testing.assert_array_equal(out[:, 1:], np.asarray(u_ref[:, 1:]))  # rates untouched
    # Exact answer of the linear model: T = (T_nom - m offset / dt) / effectiveness.
    p = qd.nominal_params()
    expected = (float(u_ref[0, 0]) - p.mass * -0.03 / cl.DT) / 0.8
    np.testing.assert_allclose(out[:, 0], expected, rtol=1e-5)


def test_one_nominal_step_would_leave_the_reference_short():
    """The first Newton step alone (unit effectiveness) falls short of the thrust that
    holds altitude when the learned effectiveness is below one: what the iterations fix."""
    x_ref, u_ref = _reference(1)
    step = _payload_model(effectiveness=0.8, offset=-0.03)
    p = qd.nominal_params()
    z_b = _z_body(np.asarray(x_ref[0, 6:10]))
    excess = (np.asarray(step(x_ref[0], u_ref[0], None)) - np.asarray(cl.f_nom(x_ref[0], u_ref[0])))
    one_step = float(u_ref[0, 0]) - p.mass * float(excess[3:6] @ z_b) / cl.DT
    solved = float(cl.thrust_reference(step, None, x_ref, u_ref)[0, 0])
    exact = (float(u_ref[0, 0]) - p.mass * -0.03 / cl.DT) / 0.8
    assert exact - one_step > 0.3  # newtons (0.37): what one step leaves out for this model
    np.testing.assert_allclose(solved, exact, rtol=1e-5)


def test_a_learned_model_without_thrust_effect_gives_a_bounded_reference():
    """Effectiveness zero: every Newton step divides by the floored slope, so the reference
    stays finite and known (the caller clips it to the input bounds)."""
    x_ref, u_ref = _reference(2)
    out = np.asarray(cl.thrust_reference(_payload_model(0.0, 0.0), None, x_ref, u_ref))
    t_nom = float(u_ref[0, 0])
    # First step (unit effectiveness) doubles the thrust; each Newton step then adds the
    # constant excess t_nom dt / m over floor * dt / m.
    steps, floor = cl.THRUST_REFERENCE_NEWTON_STEPS, cl.thrust_reference_min_effectiveness()
    np.testing.assert_allclose(out[:, 0], t_nom * (2.0 + steps / floor), rtol=1e-5)


def test_the_floor_is_the_heaviest_training_payloads_mass_ratio():
    m = float(qd.nominal_params().mass)
    floor = cl.thrust_reference_min_effectiveness()
    np.testing.assert_allclose(floor, m / (m + 0.2))
    assert 0.7 < floor < 0.8


def test_a_transient_effectiveness_below_the_floor_is_stepped_at_the_floor():
    """A one-step model that sees only part of a thrust change (rotor lag) learns a gain
    below any payload's; the reference then moves as if the gain were the floor's, so it
    stays below the exact root of that model instead of overshooting the hover thrust."""
    x_ref, u_ref = _reference(1)
    step = _payload_model(effectiveness=0.4, offset=-0.03)
    p = qd.nominal_params()
    exact = (float(u_ref[0, 0]) - p.mass * -0.03 / cl.DT) / 0.4
    solved = float(cl.thrust_reference(step, None, x_ref, u_ref)[0, 0])
    # The damped iteration: e <- e (1 - 0.4 / floor) after the unit first step.
    floor = cl.thrust_reference_min_effectiveness()
    first = float(u_ref[0, 0]) - p.mass * ((0.4 - 1.0) * float(u_ref[0, 0]) * cl.DT / p.mass
                                           - 0.03) / cl.DT
    error = (first - exact) * (1.0 - 0.4 / floor) ** cl.THRUST_REFERENCE_NEWTON_STEPS
    np.testing.assert_allclose(solved, exact + error, rtol=1e-5)
    assert solved < exact
