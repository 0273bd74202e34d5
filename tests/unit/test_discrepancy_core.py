"""Discrepancy building blocks: the effect library, the models with effects, selection with
bootstrap confidence, localisation. Fast; the end-to-end checks on simulated logs are in
``test_discrepancy_quadrotor.py`` and ``test_discrepancy_cartpole.py``."""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest

from arcade import cli
from arcade_core.discrepancy import cartpole as cp
from arcade_core.discrepancy import quadrotor as qm
from arcade_core.discrepancy.catalog import (
    CARTPOLE_EFFECTS,
    DETECTABLE,
    EFFECTS,
    QUADROTOR_EFFECTS,
    magnitude,
)
from arcade_core.discrepancy.identify import SelectionConfig, identify
from arcade_core.discrepancy.linearise import carried_secants, scaled_secants
from arcade_core.discrepancy.localize import binned_rms, changepoints, segment_rms
from arcade_core.discrepancy.subsets import Bounds, _solve_bounded
from arcade_core.dynamics.cartpole import cartpole_true_step
from arcade_core.dynamics.params import CARTPOLE_DT, CARTPOLE_NOMINAL, CARTPOLE_TRUE
from arcade_io.discrepancy import quad_model_from_vehicle
from arcade_io.vehicle import load_vehicle
from simulator import EFFECTS as SIM_EFFECTS

QUAD_NAMES = {
    "rotor_drag",
    "induced_inflow",
    "battery_sag",
    "quadratic_drag",
    "ground_effect",
    "thrust_scale",
    "motor_lag",
    "rate_lag",
    "com_offset",
    "wind",
}
CART_NAMES = {
    "cart_viscous_friction",
    "pole_viscous_friction",
    "coulomb_friction",
    "force_bias",
    "mass_mismatch",
    "length_mismatch",
}


# ---------------------------------------------------------------- library


def test_library_names_units_ranges_and_simulator_share_one_table(capsys):
    assert set(QUADROTOR_EFFECTS) == QUAD_NAMES and set(CARTPOLE_EFFECTS) == CART_NAMES
    for spec in EFFECTS.values():
        assert spec.description and spec.acts_on
        for p in spec.params.values():
            assert p.unit and p.description and p.low < p.high
    # The simulator validates against exactly these specs.
    assert {k: dict(v) for k, v in SIM_EFFECTS.items()} == {
        k: dict(s.params) for k, s in QUADROTOR_EFFECTS.items()
    }
    assert cli.main(["effects", "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)["effects"]
    assert {e["name"] for e in listed} == QUAD_NAMES | CART_NAMES
    drag = next(e for e in listed if e["name"] == "rotor_drag")
    assert drag["system"] == "quadrotor"
    assert drag["params"]["d"]["unit"] == "1/s" and drag["params"]["d"]["range"] == [0.0, 2.0]
    assert drag["detectable_from"] == DETECTABLE["rotor_drag"]


def test_every_quadrotor_effect_has_a_detectability_limit_inside_its_range():
    vehicle = load_vehicle()
    assert set(DETECTABLE) == set(QUADROTOR_EFFECTS)
    for name, spec in QUADROTOR_EFFECTS.items():
        p = next(iter(spec.params.values()))
        top = {"thrust_scale": p.high - 1.0, "motor_lag": p.high - 0.025}.get(name, p.high)
        if name in ("com_offset", "wind"):
            top = p.high * 2**0.5  # horizontal length of a vector
        assert 0.0 < DETECTABLE[name] < top, name
    assert magnitude("thrust_scale", {"scale": 0.8}) == pytest.approx(0.2)
    assert magnitude("motor_lag", {"time_constant_s": 0.1}, vehicle) == pytest.approx(0.075)
    assert magnitude("com_offset", {"offset_m": [0.003, -0.004, 0.02]}) == pytest.approx(0.005)
    assert magnitude("wind", {"velocity_mps": [3.0, 4.0, 0.0]}) == pytest.approx(5.0)


def test_effect_tables_round_trip_through_theta():
    model = quad_model_from_vehicle(load_vehicle())
    tables = {
        "rotor_drag": {"d": [0.4, 0.3, 0.1]},
        "quadratic_drag": {"c": [0.05, 0.06, 0.07]},
        "ground_effect": {"rotor_radius_m": 0.12},
        "thrust_scale": {"scale": 0.9},
        "motor_lag": {"time_constant_s": 0.04},
        "rate_lag": {"delay_s": 0.02, "time_constant_s": 0.03},
        "com_offset": {"offset_m": [0.01, -0.01, 0.0]},
        "wind": {"velocity_mps": [1.0, -2.0, 0.0]},
        "induced_inflow": {"climb_loss": 0.05, "airspeed_loss": -0.01},
        "battery_sag": {"loss_per_min": 0.03},
    }
    theta = qm.theta_from_effects(model, tables)
    for name, table in tables.items():
        back = qm.effect_params(theta, name)
        for k, v in table.items():
            np.testing.assert_allclose(back[k], v, rtol=1e-12)
    off = qm.theta_off(model)
    assert off[8] == pytest.approx(0.025) and off[7] == 1.0  # the vehicle file's own model


# ---------------------------------------------------------------- models


def _excited_inputs(n, seed=0):
    rng = np.random.default_rng(seed)
    U = np.zeros((n, 4))
    U[:, 0] = 0.57 * 9.81 + 0.5 * np.repeat(rng.normal(size=n // 5 + 1), 5)[:n]
    U[:, 1:4] = 0.5 * np.repeat(rng.normal(size=(n // 5 + 1, 3)), 5, axis=0)[:n]
    return U


def test_rate_lag_delay_is_an_exact_input_shift():
    model = quad_model_from_vehicle(load_vehicle())
    n, dt = 120, 0.01
    U = _excited_inputs(n)
    X = np.tile(np.r_[0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0.1, -0.2, 0.05], (n, 1))
    starts = jnp.arange(10, 100, 7)
    delayed = qm.theta_off(model).at[9].set(2 * dt)
    shifted = U.copy()
    shifted[2:, 1:4] = U[:-2, 1:4]
    shifted[:2, 1:4] = U[0, 1:4]
    a = qm.predict_windows(model, delayed, jnp.asarray(X), jnp.asarray(U), starts, 5, dt)
    b = qm.predict_windows(
        model, qm.theta_off(model), jnp.asarray(X), jnp.asarray(shifted), starts, 5, dt
    )
    np.testing.assert_allclose(a, b, atol=1e-11)
    # A fractional delay switches the input inside a step, exactly: half a step of delay
    # equals one step of delay on a log sampled twice as fast (rates are solved exactly).
    fine_U = np.repeat(U, 2, axis=0)
    fine_U[1:, 1:4] = fine_U[:-1, 1:4]
    fine_X = np.repeat(X, 2, axis=0)
    half = qm.theta_off(model).at[9].set(0.5 * dt)
    c = qm.predict_windows(model, half, jnp.asarray(X), jnp.asarray(U), starts, 5, dt)
    f = qm.predict_windows(
        model, qm.theta_off(model), jnp.asarray(fine_X), jnp.asarray(fine_U), 2 * starts, 10, dt / 2
    )
    np.testing.assert_allclose(np.asarray(c)[:, -1, 10:13], np.asarray(f)[:, -1, 10:13], atol=1e-10)


def test_input_states_depend_on_the_filter_entries_only_and_are_reused_exactly():
    """``FILTER_THETA`` lists every entry the input-driven states depend on; the model's
    predictions, which reuse those states across the other entries, equal the plain
    prediction bit for bit."""
    from arcade_core.discrepancy.prediction import DiscrepancyModel

    model = quad_model_from_vehicle(load_vehicle())
    n, dt = 300, 0.01
    U = jnp.asarray(_excited_inputs(n))
    X = np.tile(np.r_[0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0.1, -0.2, 0.05], (n, 1))
    theta = qm.theta_from_effects(
        model,
        {
            "rate_lag": {"delay_s": 0.02, "time_constant_s": 0.03},
            "motor_lag": {"time_constant_s": 0.03},
            "com_offset": {"offset_m": [0.01, -0.02, 0.0]},
            "rotor_drag": {"d": [0.3, 0.3, 0.1]},
        },
    )
    base = qm.filter_states(model, theta, U, dt)
    for j in range(theta.size):
        moved = qm.filter_states(model, theta.at[j].add(1e-3), U, dt)
        same = all(bool(jnp.all(a == b)) for a, b in zip(base, moved, strict=True))
        assert same == (j not in qm.FILTER_THETA), j
    # Against the prediction jitted as one function, on the same padded arguments.
    dm = DiscrepancyModel("quadrotor", model, {})
    starts = np.arange(5, 250, 3)
    for j in (0, 8, 14, 9, 0):  # kept states reused, new ones computed, in any order
        th = theta.at[j].add(2e-3)
        got = dm.predict(th, X, np.asarray(U), starts, 4, dt)
        args, _ = dm.padded(th, X, np.asarray(U), starts)
        want = np.asarray(dm._predict(*args, steps=4, dt=dt))[: len(starts)]
        np.testing.assert_array_equal(got, want)


def test_hover_is_an_equilibrium_and_rates_follow_setpoints():
    model = quad_model_from_vehicle(load_vehicle())
    theta = qm.theta_off(model)
    n = 400
    U = np.tile([0.57 * 9.81, 0.0, 0.0, 0.0], (n, 1))
    X = np.tile(np.r_[0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0.0], (n, 1))
    pred = np.asarray(
        qm.predict_windows(model, theta, jnp.asarray(X), jnp.asarray(U), jnp.array([0]), 300, 0.01)
    )[0]
    np.testing.assert_allclose(pred[-1], X[0], atol=1e-9)
    # A constant yaw-rate setpoint is tracked without steady-state error (PID integrator).
    U[100:, 3] = 0.4
    pred = np.asarray(
        qm.predict_windows(model, theta, jnp.asarray(X), jnp.asarray(U), jnp.array([0]), 300, 0.01)
    )[0]
    assert pred[-1, 12] == pytest.approx(0.4, abs=2e-3)
    assert abs(pred[99, 12]) < 1e-9  # pred[k] is the state at sample k + 1
    assert 0.05 < pred[102, 12] < 0.3  # ... with the loop's lag (about 50 ms)


def test_a_fast_motor_is_predicted_at_a_slow_log_rate():
    # A 2 ms motor (the plausible range's lower end) in the rate loop's companion form
    # needs about 18 squarings of the matrix exponential over a 20 ms log step; with the
    # default limit of 16 the prediction was NaN, and every 50 Hz log broke the secants.
    model = quad_model_from_vehicle(load_vehicle())
    n = 60
    U = np.tile([0.57 * 9.81, 0.0, 0.0, 0.0], (n, 1))
    U[10:, 3] = 0.4  # a yaw-rate step
    X = np.tile(np.r_[0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0.0], (n, 1))
    final = []
    for tau in (0.002, 0.005):
        theta = qm.theta_off(model).at[8].set(tau)
        pred = qm.predict_windows(
            model, theta, jnp.asarray(X), jnp.asarray(U), jnp.array([0]), 50, 0.02
        )
        assert np.isfinite(np.asarray(pred)).all(), tau
        final.append(float(pred[0, -1, 12]))
    np.testing.assert_allclose(final, 0.4, atol=5e-3)


def test_aerodynamic_and_battery_effects_follow_their_formulas():
    """The thrust and the effect acceleration each effect makes at one instant (level)."""
    model = quad_model_from_vehicle(load_vehicle())
    m, g = float(model.params.mass), float(model.params.gravity)
    level, zero = jnp.array([1.0, 0.0, 0.0, 0.0]), jnp.zeros(3)

    def at(tables, v, thrust, t=0.0):
        th = qm.theta_from_effects(model, tables)
        p = jnp.array([0.0, 0.0, 1.0])
        thrust_, a = qm._accel(model, th, p, jnp.asarray(v), level, zero, zero, thrust, t)
        return float(thrust_), np.asarray(a)

    # Rotor drag at 1.44 x hover thrust: the rotors turn 1.2 x as fast.
    f, a = at({"rotor_drag": {"d": [0.4, 0.0, 0.3]}}, [2.0, 0.0, 1.0], 1.44 * m * g)
    np.testing.assert_allclose(a, [-0.4 * 1.2 * 2.0, 0.0, -0.3 * 1.2 * 1.0], rtol=1e-12)
    assert f == pytest.approx(1.44 * m * g, rel=1e-12)
    # Induced inflow: 2 m/s climb and 3 m/s air speed; flying with the wind: none.
    inflow = {"climb_loss": 0.05, "airspeed_loss": 0.01}
    f, a = at({"induced_inflow": inflow}, [3.0, 0.0, 2.0], m * g)
    assert f == pytest.approx((1.0 - 0.1 - 0.09) * m * g, rel=1e-12)
    np.testing.assert_allclose(a, 0.0, atol=1e-15)
    tables = {"induced_inflow": inflow, "wind": {"velocity_mps": [3.0, 0.0, 2.0]}}
    assert at(tables, [3.0, 0.0, 2.0], m * g)[0] == pytest.approx(m * g, rel=1e-12)
    # Battery sag: a minute into the log, 6 % less thrust.
    f, _ = at({"battery_sag": {"loss_per_min": 0.06}}, [0.0, 0.0, 0.0], m * g, t=60.0)
    assert f == pytest.approx(0.94 * m * g, rel=1e-12)


def test_cartpole_model_with_the_papers_effects_is_the_papers_true_system():
    model = cp.CartpoleModel.from_params(CARTPOLE_NOMINAL)
    theta = cp.theta_from_effects(model, {
        "cart_viscous_friction": {"mu_c": CARTPOLE_TRUE.mu_c},
        "pole_viscous_friction": {"mu_p": CARTPOLE_TRUE.mu_p},
        "force_bias": {"mean_n": CARTPOLE_TRUE.dist_mean},
        "mass_mismatch": {"cart_mass_kg": CARTPOLE_TRUE.M, "pole_mass_kg": CARTPOLE_TRUE.m},
        "length_mismatch": {"pole_length_m": CARTPOLE_TRUE.L},
    })  # fmt: skip
    rng = np.random.default_rng(1)
    for _ in range(5):
        x = jnp.asarray(rng.normal(size=4))
        u, noise = rng.normal(scale=3.0), rng.normal(scale=0.7)
        ours = cp.true_step(model, theta, x, u, CARTPOLE_DT, noise)
        paper = cartpole_true_step(
            None, x, u, CARTPOLE_TRUE, CARTPOLE_DT, u_dist=CARTPOLE_TRUE.dist_mean + noise
        )
        np.testing.assert_allclose(ours, paper, rtol=1e-12, atol=1e-12)
    # Coulomb friction opposes the cart's motion.
    x = jnp.array([0.0, 1.0, 0.0, 0.0])
    off = cp.theta_off(model)
    slowed = cp.step(model, off.at[2].set(1.0), x, 0.0, CARTPOLE_DT)
    assert slowed[1] < cp.step(model, off, x, 0.0, CARTPOLE_DT)[1] - 0.02


# ---------------------------------------------------------------- selection


def _linear_problem(theta_true, n=1500, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, 2, 5))
    y = np.einsum("ncp,p->nc", A, theta_true) + rng.normal(size=(n, 2))

    def residual_fn(theta):
        return y - np.einsum("ncp,p->nc", A, np.asarray(theta))

    return residual_fn


GROUPS = [(0, 1), (2,), (3, 4)]
LOW, HIGH = np.full(5, -5.0), np.full(5, 5.0)


def test_identify_names_the_true_effects_with_confidence_and_intervals():
    truth = np.array([0.8, -0.5, 0.0, 0.0, 0.6])
    cfg = SelectionConfig(n_boot=100, block=50)
    res = identify(_linear_problem(truth), np.zeros(5), GROUPS, LOW, HIGH, cfg)
    assert set(res.selected) == {0, 2} and set(res.confident) == {0, 2}
    assert res.confidence[0] >= 0.9 and res.confidence[2] >= 0.9 and res.confidence[1] < 0.5
    np.testing.assert_allclose(res.theta, truth, atol=0.06)
    lo, hi = np.percentile(res.samples, [5, 95], axis=0)
    assert np.all((lo[[0, 1, 4]] <= truth[[0, 1, 4]]) & (truth[[0, 1, 4]] <= hi[[0, 1, 4]]))
    assert np.all(hi[[0, 1, 4]] - lo[[0, 1, 4]] < 0.2)


def test_identify_refuses_a_model_whose_prediction_is_not_finite():
    # A vehicle file far from the logged vehicle can make the current model's prediction
    # non-finite on every window: one clear error, not an IndexError deep in the whitening.
    fn = _linear_problem(np.zeros(5))

    def broken(theta):
        r = fn(theta)
        r[40:] = np.nan
        return r

    with pytest.raises(ValueError, match="finite on only 40 of 1500 fitting windows"):
        identify(broken, np.zeros(5), GROUPS, LOW, HIGH, SelectionConfig(n_boot=10, block=50))


def test_identify_says_nothing_when_there_is_nothing():
    res = identify(
        _linear_problem(np.zeros(5), seed=3),
        np.zeros(5),
        GROUPS,
        LOW,
        HIGH,
        SelectionConfig(n_boot=100, block=50),
    )
    assert res.confident == () and np.all(res.theta == 0.0)
    assert np.all(res.confidence < 0.9)


def test_a_long_delay_is_found_through_scaled_secants():
    # A transport delay of 8 samples in a signal that decorrelates within 2: the tangent at
    # zero delay (the signal's derivative) explains almost nothing of the gap, the secant
    # over the whole range explains most of it; selection names the delay, the fit finds it.
    rng = np.random.default_rng(2)
    n, t = 1200, np.arange(1200.0)
    sig = np.convolve(rng.normal(size=(n + 40)), np.ones(3) / 3.0, mode="same")[20:-20]
    truth = 8.0

    def shifted(delay):
        return np.interp(t - delay, t, sig)

    y = shifted(truth) + 0.05 * rng.normal(size=n)
    other = rng.normal(size=n)

    def residual_fn(theta):
        th = np.asarray(theta)
        return np.stack([y - shifted(th[0]) - other * th[1], other * 0.0], axis=1)

    low, high = np.array([0.0, -1.0]), np.array([10.0, 1.0])
    base = np.zeros(2)
    jac = scaled_secants(residual_fn, base, low, high, residual_fn(base), (0.05, 0.25, 1.0))
    np.testing.assert_allclose(jac[:, 0, 0], -(shifted(10.0) - sig) / 10.0)
    res = identify(residual_fn, base, [(0,), (1,)], low, high, SelectionConfig(n_boot=50, block=50))
    assert res.confident == (0,), res.confidence
    assert res.theta[0] == pytest.approx(truth, abs=0.1)


def test_an_effect_that_acts_only_through_another_is_found_with_it():
    # Wind acts only through drag: y = -d (v - w). A model without drag cannot see the wind
    # (no sensitivity at the base); its secants are taken where the drag is on, and
    # selecting it fits both. A distractor (a third regressor) stays out; without wind in
    # the data nothing is carried.
    rng = np.random.default_rng(4)
    n = 1500
    v = 2.0 * np.sin(0.01 * np.arange(n)) + 0.3 * rng.normal(size=n)
    other, noise = rng.normal(size=n), 0.05 * rng.normal(size=n)
    low, high = np.array([0.0, -5.0, -1.0]), np.array([2.0, 5.0, 1.0])
    groups = [(0,), (1,), (2,)]

    def residuals(d_true, w_true):
        y = -d_true * (v - w_true) + noise

        def residual_fn(theta):
            th = np.asarray(theta)
            return np.stack([y + th[0] * (v - th[1]) - th[2] * other, 0.0 * v], axis=1)

        return residual_fn

    cfg = SelectionConfig(n_boot=100, block=50)
    res = identify(residuals(0.4, 3.0), np.zeros(3), groups, low, high, cfg)
    assert set(res.confident) == {0, 1}, res.confidence
    np.testing.assert_allclose(res.theta[:2], [0.4, 3.0], rtol=0.05)
    calm = residuals(0.4, 0.0)
    base = np.zeros(3)
    jac = scaled_secants(calm, base, low, high, calm(base), cfg.probe_scales)
    _, carried = carried_secants(calm, base, groups, low, high, calm(base), jac, (1.0,), 0.02)
    assert carried == {}


def test_bounded_solution_holds_unphysical_parameters_at_their_bound():
    # Two nearly collinear columns (a delay and a filter time constant): the free solution
    # makes one negative; bounded, it stays at 0 and the other takes the whole lag.
    rng = np.random.default_rng(0)
    a = rng.normal(size=400)
    A = np.stack([a, a + 0.05 * rng.normal(size=400)], axis=1)
    y = A @ np.array([1.3, -0.3])
    G, g = jnp.asarray(A.T @ A), jnp.asarray(A.T @ y)
    mask = jnp.array([True, True])
    b = Bounds(jnp.zeros(2), jnp.ones(2) * 10, jnp.ones(2) * 10)
    delta = np.asarray(_solve_bounded(G, g, mask, b))
    assert delta[1] == 0.0 and delta[0] == pytest.approx(1.0, abs=0.05)


# ---------------------------------------------------------------- localisation


def test_changepoints_and_regimes_localise_a_gap():
    rng = np.random.default_rng(2)
    resid = rng.normal(size=(600, 2))
    resid[300:450, 1] += 3.0
    cps = changepoints(resid, min_gap=20)
    assert np.any(np.abs(cps - 300) <= 5) and np.any(np.abs(cps - 450) <= 5)
    segs = segment_rms(resid, cps)
    worst = max(segs, key=lambda s: s[2][1])
    assert abs(worst[0] - 300) <= 5 and worst[2][1] > 2.5
    var = np.r_[np.zeros(300), np.ones(150), np.zeros(150)] + 1e-3 * np.arange(600)
    b = binned_rms(resid, var, bins=4)
    assert np.argmax(b.rms[:, 1]) == 3 and b.count.sum() == 600


def test_excitation_says_what_a_log_cannot_tell():
    from arcade_core.discrepancy.workflow import HALVING_RATIO, excitation

    reach = {"rotor_drag": 0.5, "thrust_scale": 20.0, "wind": 0.0}
    assert excitation(reach, named=False) == (["wind"], ["rotor_drag"], False)
    low = {"rotor_drag": 0.5, "thrust_scale": 0.9 * HALVING_RATIO, "wind": 0.0}
    assert excitation(low, named=False) == (["wind"], ["rotor_drag", "thrust_scale"], True)
    assert excitation(low, named=True)[2] is False  # something was named after all
    assert excitation({"wind": 0.0}, named=False) == (["wind"], [], False)
