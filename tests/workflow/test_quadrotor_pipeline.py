"""Quadrotor pipeline: expert-flight data, shipped VLD weights, a short closed-loop flight."""

import os
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from fake_runner import SequentialTrials

from arcade.training_quadrotor import QUADROTOR_COMMAND, QUADROTOR_WEIGHTS
from arcade_control.guard import Guard, guard_from_metadata
from arcade_control.knobs import (
    ARCADE_BEAM_BETA,
    BEAM_VARIANTS,
    METHODS,
    ORACLE,
    TUNED_DEFAULTS,
    TUNING_METHOD,
    VARIANTS,
    knob_owner,
    knobs_of,
)
from arcade_control.learners import initial_learner, scale_gp_noise
from arcade_control.methods import make_method, matched_residual
from arcade_control.nominal import CONTROL_DT, LOG_DT, LOG_PER_CONTROL, nominal_params
from arcade_control.scenario import Scenario
from arcade_control.step import mpc_config
from arcade_core import encoder
from arcade_core import frames as quat
from arcade_io.weights import load_model, read_header
from benchmarks import quadrotor_tuning as qt
from benchmarks.quadrotor_flights import (
    Runner,
    flight_threads,
)
from simulator.expert_flights import flight_transitions, make_dataset

MINUTES = 0.06  # 3.6 s per flight: mostly the hover lead, where the payload shows clearly
PAYLOADS = (10.0, 200.0)


@pytest.fixture(scope="module")
def data():
    return make_dataset(seed=3, minutes_per_payload=MINUTES, payloads_g=PAYLOADS, cache=False)


def test_dataset_shapes_finite_and_deterministic(data):
    steps = round(60 * MINUTES / CONTROL_DT)
    n_log = steps * LOG_PER_CONTROL + 1
    assert data["X"].shape == (len(PAYLOADS) * n_log, 13)
    assert data["U"].shape == (len(PAYLOADS) * n_log, 4)
    assert (
        data["x"].shape
        == data["x_next"].shape
        == data["delta"].shape
        == (len(PAYLOADS) * steps, 13)
    )
    assert data["u"].shape == (len(PAYLOADS) * steps, 4)
    for key in ("X", "U", "x", "u", "delta"):
        assert np.isfinite(data[key]).all(), key
    # 100 Hz log, transitions at the 20 Hz control period, aligned with setpoint changes.
    t0 = data["t"][data["flight"] == 0]
    np.testing.assert_allclose(np.diff(t0), LOG_DT, atol=1e-12)
    x0, u0, xn0, _ = flight_transitions(data, 0)
    np.testing.assert_array_equal(x0, data["X"][data["flight"] == 0][:-1:5])
    np.testing.assert_array_equal(xn0, data["X"][data["flight"] == 0][5::5])
    np.testing.assert_array_equal(u0, data["U"][data["flight"] == 0][:-1:5])
    # Inputs are held over a transition: the logged setpoint only changes every 5 samples.
    U0 = data["U"][data["flight"] == 0][:-1].reshape(steps, LOG_PER_CONTROL, 4)
    assert np.all(U0[:, :1] == U0)
    again = make_dataset(seed=3, minutes_per_payload=MINUTES, payloads_g=PAYLOADS[:1], cache=False)
    np.testing.assert_array_equal(again["X"], data["X"][data["flight"] == 0])


def test_dataset_payload_is_applied(data):
    """Hovering with a heavier payload needs more thrust, so the nominal model (which
    knows only the airframe) over-predicts the climb rate by ``g dt (m_true / m_nom - 1)``."""
    p = nominal_params()
    mean_dvz = {}
    for i, pay in enumerate(PAYLOADS):
        sel = data["transition_flight"] == i
        assert np.all(data["transition_payload_g"][sel] == pay)
        mean_dvz[pay] = float(np.mean(data["delta"][sel, 5]))
        m_true = float(p.mass) + pay / 1000.0
        expected = -float(p.gravity) * CONTROL_DT * (m_true / float(p.mass) - 1.0)
        assert mean_dvz[pay] == pytest.approx(expected, rel=0.3, abs=0.01)
    assert mean_dvz[200.0] < mean_dvz[10.0] - 0.1


def test_shipped_weights_load_and_predict():
    assert QUADROTOR_WEIGHTS.stat().st_size < 300_000
    model, config, extra = load_model(QUADROTOR_WEIGHTS)
    assert config == encoder.quadrotor_config()
    assert (
        extra["command"] == QUADROTOR_COMMAND == read_header(QUADROTOR_WEIGHTS)["extra"]["command"]
    )
    assert extra["control_dt"] == CONTROL_DT
    rng = np.random.default_rng(0)
    x = np.tile([0.0, 0.0, 2.0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0], (64, 1))
    x[:, :6] += rng.normal(0.0, 0.5, (64, 6))
    u = np.column_stack([rng.uniform(4.0, 10.0, 64), rng.normal(0.0, 0.5, (64, 3))])
    delta = jax.vmap(model.predict_residual)(jnp.asarray(x), jnp.asarray(u))
    assert delta.shape == (64, 13)
    assert bool(jnp.all(jnp.isfinite(delta)))
    # The offline model has learned the payload effect: more hover thrust (a heavier
    # payload in the training flights) goes with a more negative vertical residual.
    hover = jnp.asarray([0.0, 0.0, 2.0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0])
    light = model.predict_residual(hover, jnp.asarray([5.7, 0.0, 0.0, 0.0]))[5]
    heavy = model.predict_residual(hover, jnp.asarray([7.6, 0.0, 0.0, 0.0]))[5]
    assert float(heavy) < float(light) - 0.05


@pytest.mark.parametrize("method", ["ours", "ours_held", "ours_matched"])
def test_short_closed_loop_flight_of_ours(data, method):
    """A few seconds of ARCADE in closed loop with a 75 g swinging payload stay on track,
    with the learned residual inside the MPC rollout and held along the warm start, and
    the matched-channel variant (intercept feature, thrust-axis residual).

    The nominal MPC sags by about 0.35 m under this payload (no integral action); the
    adapted model has to remove most of that for the bounds to hold.
    """
    vld, _, _ = load_model(QUADROTOR_WEIGHTS)
    z = jax.vmap(vld.features)(jnp.asarray(data["x"]), jnp.asarray(data["u"]))
    guard = Guard(
        jnp.max(jnp.abs(jnp.asarray(data["delta"])), axis=0) * 2.0,
        jnp.min(z, axis=0) - 2.0,
        jnp.max(z, axis=0) + 2.0,
    )
    models = SimpleNamespace(vld=vld, closedloop={}, guard=guard)
    scenario = Scenario(
        payload_g=75.0, speed_mps=1.0, takeoff_s=1.0, hover_s=0.5, laps=0.3, release_fraction=0.2
    )
    flight = Runner(models).fly(method, scenario, seed=0)
    assert not flight.crashed
    assert flight.t[-1] > 5.0
    err = np.linalg.norm(flight.error, axis=1)
    assert np.all(np.isfinite(flight.u))
    assert err.max() < 0.15, err.max()
    assert flight.metrics["rmse_m"] < 0.08


def test_flights_flown_side_by_side_are_those_flown_one_by_one():
    """``Runner.fly_trials`` flies seeds two at a time on threads where the CPUs allow
    (``flight_threads``; on two CPUs one at a time): every flight is the one ``fly`` gives
    alone, bit for bit (the flagship on the estimate, with the link's delay compensated:
    the most state a flight carries)."""
    from arcade_control.stack import stack_knobs

    vld, _, extra = load_model(QUADROTOR_WEIGHTS)
    models = SimpleNamespace(
        vld=vld, guard=guard_from_metadata(extra), closedloop=stack_knobs("arcade")
    )
    scenario = Scenario(
        payload_g=150.0,
        speed_mps=2.0,
        takeoff_s=1.0,
        hover_s=0.5,
        ramp_s=0.5,
        laps=0.2,
        release_fraction=0.5,
        command_delay_s=0.02,
    )
    runner = Runner(models)
    kw = {"estimated": True, "compensate_delay": True}
    seeds = (999, 998)
    together = runner.fly_trials("arcade", scenario, seeds, threads=2, **kw)
    alone = [runner.fly("arcade", scenario, seed=s, **kw) for s in seeds]
    assert [f.seed for f in together] == list(seeds)
    assert flight_threads(2) == max(1, min(2, len(os.sched_getaffinity(0)) - 1))
    for a, b in zip(alone, together, strict=True):
        assert not a.crashed
        np.testing.assert_array_equal(a.x, b.x)
        np.testing.assert_array_equal(a.u, b.u)
        np.testing.assert_array_equal(a.diag, b.diag)
        np.testing.assert_equal(a.metrics, b.metrics)
    assert len({f.metrics["rmse_m"] for f in alone}) == len(seeds)  # the seeds differ


def test_matched_residual_keeps_what_the_thrust_can_cancel():
    """``ours_matched`` plans with the translational residual along the body z axis only."""
    rng = np.random.default_rng(4)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    x = jnp.asarray(np.r_[rng.normal(size=6), q, rng.normal(size=3)])
    delta = jnp.asarray(rng.normal(size=13))
    m = np.asarray(matched_residual(x, delta))
    R = np.asarray(quat.to_rotation_matrix(jnp.asarray(q)))
    zb = R[:, 2]
    for part in (slice(0, 3), slice(3, 6)):
        np.testing.assert_allclose(m[part], np.dot(np.asarray(delta[part]), zb) * zb, atol=1e-12)
        np.testing.assert_allclose(np.dot(np.asarray(delta[part]) - m[part], zb), 0, atol=1e-12)
    assert np.all(m[6:] == 0)
    level = x.at[6:10].set(jnp.asarray([1.0, 0, 0, 0]))
    np.testing.assert_allclose(matched_residual(level, delta)[3:6], [0, 0, delta[5]])


def test_mass_oracle_carries_the_payload_until_the_release_step():
    """The diagnostic oracle: the nominal model with the payload's mass until the release
    step, without it from then on, and the thrust reference that holds that mass."""
    method = make_method(ORACLE)
    p = nominal_params()
    a = initial_learner(ORACLE, None, jnp.float64)
    a = a._replace(k_release=jnp.asarray(3, jnp.int32), payload_kg=jnp.asarray(0.175))
    masses = []
    for _ in range(5):  # the mass the MPC plans with at control steps 0..4
        masses.append(float(method.model(a)))
        a = method.learn(a, None, None, None)
    np.testing.assert_allclose(masses, [p.mass + 0.175] * 3 + [p.mass] * 2)
    # The reference thrust holds the heavier vehicle: no vertical acceleration at hover.
    x = jnp.asarray(np.r_[0, 0, 1.0, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0])
    u_ref = jnp.asarray([[p.mass * p.gravity, 0.0, 0.0, 0.0]])
    m = jnp.asarray(p.mass + 0.175)
    u = method.reference(m, x[None], u_ref)[0]
    np.testing.assert_allclose(method.step_fn(x, u, m)[3:6], 0.0, atol=1e-12)


def test_beam_variants_start_from_the_offline_decoder():
    """A variant with the intercept starts with one more, zero, decoder column; its knobs
    are its own (``ours_matched``) or ours' (the two changes one at a time)."""
    vld, _, extra = load_model(QUADROTOR_WEIGHTS)
    models = SimpleNamespace(
        vld=vld, guard=guard_from_metadata(extra), closedloop={"ours_matched_beta": 0.5}
    )
    d, l = vld.theta0.shape
    for name, (intercept, _) in BEAM_VARIANTS.items():
        a = initial_learner(name, models, jnp.float64)
        mean = np.asarray(a.beam.means[0])
        assert mean.shape == (d, l + intercept), name
        np.testing.assert_array_equal(mean[:, :l], np.asarray(vld.theta0))
        if intercept:
            assert np.all(mean[:, l] == 0)
        want = 0.5 if name == "ours_matched" else TUNED_DEFAULTS["ours_beta"]
        assert float(a.config.beta) == want, name


def test_the_flagship_plans_with_the_learned_model_and_cancels_only_what_it_misses():
    """``arcade``: ours_matched's model (intercept column at zero) learned with forgetting
    at its own knobs, plus an L1 thrust augmentation whose predictor includes the learned
    model: a model that predicts the disturbance exactly leaves the augmentation nothing to
    cancel."""
    from arcade_control.methods import make_method
    from arcade_control.nominal import f_nom

    vld, _, extra = load_model(QUADROTOR_WEIGHTS)
    models = SimpleNamespace(
        vld=vld,
        guard=guard_from_metadata(extra),
        closedloop={"arcade_lambda": 0.25, "arcade_l1_cutoff": 20.0, "arcade_l1_a_s": -1.0},
    )
    a = initial_learner("arcade", models, jnp.float64)
    d, l = vld.theta0.shape
    assert np.asarray(a.beam.means[0]).shape == (d, l + 1)
    assert int(a.config.K) == 1 and float(a.config.pi) == 1.0 and float(a.config.beta) == 0.5
    assert float(a.l1.params.cutoff_thrust) == 20.0 and float(a.l1.params.a_s) == -1.0
    assert not bool(a.l1.params.rotational)  # thrust channel only
    method = make_method("arcade")
    x0 = jnp.asarray(np.r_[0, 0, 1.0, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0], jnp.float64)
    u = jnp.asarray([2.0, 0.0, 0.0, 0.0], jnp.float64)
    a = a._replace(l1=a.l1._replace(x_prev=x0, v_hat=x0[3:6], started=jnp.ones((), bool)))
    # The next state exactly as the (updated) learned model predicts it.
    learned = method.learn(a, x0, u, method.step_fn(x0, u, method.model(a)))
    x1 = method.step_fn(x0, u, method.model(learned))
    assert float(jnp.abs(x1 - f_nom(x0, u))[3:6].max()) > 1e-4  # the model predicts a force
    a = method.learn(a, x0, u, x1)
    np.testing.assert_allclose(a.l1.sigma_force, 0.0, atol=1e-9)
    np.testing.assert_allclose(method.correction(a, x1), 0.0, atol=1e-9)
    # A state the model does not explain: the augmentation pushes against the remainder.
    a2 = method.learn(a, x1, u, f_nom(x1, u).at[5].add(-0.05))
    assert float(method.correction(a2, x1)[0]) > 0.0
    # The ablations fly with the flagship's knobs, each without one part.
    no_model = initial_learner("arcade_no_model", models, jnp.float64)
    assert float(no_model.params.cutoff_thrust) == 20.0 and float(no_model.params.a_s) == -1.0
    plain = make_method("arcade_no_model")  # the augmentation on the nominal MPC
    assert plain.name == "arcade_no_model" and not plain.learned
    np.testing.assert_array_equal(plain.step_fn(x0, u, None), f_nom(x0, u))
    no_l1 = initial_learner("arcade_no_l1", models, jnp.float64)
    assert no_l1.l1 is None and float(no_l1.config.beta) == 0.5
    np.testing.assert_array_equal(make_method("arcade_no_l1").correction(no_l1, x0), 0.0)
    never = initial_learner("arcade_no_forgetting", models, jnp.float64)
    assert int(never.config.K) == 1 and float(never.config.pi) == 0.0 and never.l1 is not None
    assert float(never.config.beta) == 1.0
    beam = initial_learner("arcade_beam", models, jnp.float64)
    assert beam.beam.means.shape[0] == 15 and float(beam.config.beta) == ARCADE_BEAM_BETA
    assert beam.l1 is not None and make_method("arcade_beam").changepoints
    # Forgetting takes the changepoint branch at every step: without its detector's
    # restart, no flag and no probability; with it, the detector's.
    forgetting = make_method("arcade_no_restart")
    assert not forgetting.changepoints and method.changepoints
    # The flagship's MPC holds the learned residual along its warm start; ours' does not.
    assert method.hold_residual and forgetting.hold_residual
    assert not make_method("ours").hold_residual
    plain = initial_learner("arcade_no_restart", models, jnp.float64)
    assert plain.restart is None
    learned = forgetting.learn(plain, x1, u, f_nom(x1, u).at[5].add(-0.05))
    np.testing.assert_array_equal(forgetting.info(learned), 0.0)


def test_tuning_flies_only_the_methods_asked_for():
    """The variants' knobs are tuned in their own run; the others keep their defaults."""
    models = SimpleNamespace()
    flown = set()

    class FakeRunner(SequentialTrials):
        def fly(self, method, scenario, seed, estimated=False, compensate_delay=False):
            flown.add(method)
            s2 = models.closedloop["ours_matched_sigma2"]
            return SimpleNamespace(
                metrics={"rmse_m": abs(np.log(s2 / 1e-2)), "thrust_increment_rms_n": 0.1}
            )

    out = qt.tune(models, runner=FakeRunner(), methods=VARIANTS)
    # And L1 at its stored knobs: the flagship's smoothness reference.
    assert flown == {*VARIANTS, "l1"} == {"ours_matched", "arcade", "l1"}
    assert set(out["chosen"]) == {
        "ours_matched_beta",
        "ours_matched_sigma2",
        "arcade_lambda",
        "arcade_restart_scale",
        "arcade_sigma2",
        "arcade_l1_cutoff",
        "arcade_l1_a_s",
    }
    assert out["chosen"]["ours_matched_sigma2"] == 1e-2
    assert models.closedloop["ours_beta"] == TUNED_DEFAULTS["ours_beta"]


def test_tuned_knobs_reach_the_learners():
    """The closed-loop knobs (``models.closedloop``) set what each learner starts with."""
    from arcade_core.baselines import gp

    vld, _, _ = load_model(QUADROTOR_WEIGHTS)
    guard = Guard(jnp.ones(13), -jnp.ones(8), jnp.ones(8))
    models = SimpleNamespace(
        vld=vld, guard=guard, closedloop={"ours_beta": 0.2, "ours_sigma2": 0.003}
    )
    for name in ("ours", "ours_no_cp"):
        learner = initial_learner(name, models, jnp.float64)
        assert float(learner.config.sigma2) == pytest.approx(0.003)
    assert float(initial_learner("ours", models, jnp.float64).config.beta) == 0.2
    for rates, applied in ((0.0, False), (10.0, True)):
        models.closedloop = {"l1_cutoff": 40.0, "l1_cutoff_rates": rates}
        params = initial_learner("l1", models, jnp.float64).params
        assert bool(params.rotational) == applied and float(params.cutoff_thrust) == 40.0
    model = gp.GPModel(gp.initial_hyperparams(17, 13, noise_var=0.1), None)
    scaled = scale_gp_noise(model, 0.01)
    np.testing.assert_allclose(np.exp(scaled.hyper.log_noise_var), 1e-3, rtol=1e-6)
    np.testing.assert_array_equal(scaled.hyper.log_lengthscale, model.hyper.log_lengthscale)


def test_tuning_passes_until_no_knob_changes():
    """Coordinate descent: a knob tuned first is tuned again at the others' choice, so an
    interaction between two knobs of one method (here: the best beta depends on sigma^2)
    does not leave the first pass's choice in place; seeded flights are not re-flown."""
    models = SimpleNamespace()
    flights = []

    class FakeRunner(SequentialTrials):
        def fly(self, method, scenario, seed, estimated=False, compensate_delay=False):
            k = dict(models.closedloop)
            flights.append(
                (method, seed, *(v for n, v in sorted(k.items()) if TUNING_METHOD[n] == method))
            )
            if method == "ours":  # best beta 0.05 at sigma^2 0.1, 0.2 at sigma^2 <= 0.01
                want = 0.05 if k["ours_sigma2"] > 0.05 else 0.2
                rmse = abs(np.log(k["ours_beta"] / want)) + abs(np.log(k["ours_sigma2"] / 1e-3))
            else:
                rmse = 1.0
            return SimpleNamespace(metrics={"rmse_m": float(rmse), "thrust_increment_rms_n": 0.1})

    out = qt.tune(models, runner=FakeRunner())
    assert out["chosen"]["ours_beta"] == 0.2 and out["chosen"]["ours_sigma2"] == 1e-3
    assert out["passes"] == 3  # pass 2 moves beta, pass 3 confirms
    first = out["rmse_m_by_pass"][0]["ours_beta"]  # at the starting sigma^2 = 0.1
    assert len(out["rmse_m_by_pass"]) == 3 and min(first, key=first.get) == "0.05"
    assert out["rmse_m_by_pass"][-1] == out["rmse_m"]
    assert len(flights) == len(set(flights))  # no setting of a method flown twice
    assert {f[1] for f in flights} == set(qt.TUNING_SEEDS)


def test_tuning_extends_a_grid_past_an_edge_its_best_lies_on():
    """A best value on a grid's edge is not a choice: the grid grows past it, one value of
    ``TUNING_EXTENSIONS`` at a time, until the best lies inside; a knob whose range runs
    out first is reported as still on its edge."""
    models = SimpleNamespace()

    # best beta 0.01 (below the grid's 0.05), best sigma^2 far below 1e-7
    class FakeRunner(SequentialTrials):
        def fly(self, method, scenario, seed, estimated=False, compensate_delay=False):
            k = models.closedloop
            rmse = abs(np.log(k["ours_beta"] / 0.01)) + abs(np.log(k["ours_sigma2"] / 1e-12))
            return SimpleNamespace(metrics={"rmse_m": float(rmse), "thrust_increment_rms_n": 0.1})

    out = qt.tune(models, runner=FakeRunner(), methods=("ours",))
    assert out["chosen"] == {"ours_beta": 0.01, "ours_sigma2": 1e-7}
    assert out["extended"] == {"ours_beta": [0.02, 0.01, 0.005], "ours_sigma2": [1e-5, 1e-6, 1e-7]}
    assert out["still_on_edge"] == ["ours_sigma2"]
    assert out["grids"]["ours_beta"] == [*qt.TUNING_GRIDS["ours_beta"], 0.02, 0.01, 0.005]
    assert set(out["rmse_m"]["ours_beta"]) == {f"{v:g}" for v in out["grids"]["ours_beta"]}
    # Inside a grid nothing is added; past the knob's range neither.
    assert qt.beyond_edge("l1_a_s", qt.TUNING_GRIDS["l1_a_s"], -1.0) is None
    assert qt.beyond_edge("l1_a_s", (-5.0, -0.05), -0.05) == -0.02
    assert qt.beyond_edge("l1_cutoff_rates", (0.0, 80.0), 0.0) is None
    assert qt.beyond_edge("arcade_lambda", (0.9, 0.9995, 1.0), 1.0) is None
    for knob, (below, above) in qt.TUNING_EXTENSIONS.items():  # ordered away from the grid
        grid = qt.TUNING_GRIDS[knob]
        assert list(below) == sorted(below, reverse=True) and max(below, default=-1e9) < min(grid)
        assert list(above) == sorted(above) and min(above, default=1e9) > max(grid)


def test_a_run_records_only_the_knobs_of_the_methods_it_flies():
    """A results file's setting names what its flights used, not another method's knobs;
    the beam methods other than the matched variant fly with ours' knobs."""
    paper = knobs_of({"ours_beta": 0.2}, METHODS)
    owners = {"ours_matched", "arcade"}  # not among the paper's methods
    assert set(paper) == {k for k, m in TUNING_METHOD.items() if m not in owners}
    flagship = {k for k, m in TUNING_METHOD.items() if m == "arcade"}
    assert set(knobs_of({}, ("arcade_no_model", "arcade_no_restart", "arcade_beam"))) == flagship
    assert paper["ours_beta"] == 0.2 and paper["l1_a_s"] == TUNED_DEFAULTS["l1_a_s"]
    assert set(knobs_of({}, ("ours_K5", "ours_no_cp_held"))) == {"ours_beta", "ours_sigma2"}
    assert set(knobs_of({}, ("nominal",))) == set()
    assert {knob_owner(m) for m in BEAM_VARIANTS} == {"ours", "ours_matched"}
    assert knob_owner("ours_matched_held") == "ours_matched"


def test_mpc_input_bounds_are_what_the_simulated_vehicle_executes():
    """The MPC must not plan with thrust or body rates the vehicle clamps away."""
    from simulator import QuadrotorSim

    sim = QuadrotorSim(payload_mass=0.0)
    cfg = mpc_config(jnp.float64)
    np.testing.assert_allclose(cfg.u_max, [4.0 * sim.max_thrust, *sim.max_rate])
    np.testing.assert_allclose(cfg.u_min[1:], -sim.max_rate)
    too_much = np.asarray(cfg.u_max) + np.array([1.0, 0.5, 0.5, 0.5])
    np.testing.assert_allclose(sim.set_setpoint(too_much), cfg.u_max)


def test_the_flagship_is_tuned_for_tracking_within_its_smoothness_bound():
    """The flagship's tuning takes the lowest RMSE among the settings whose thrust
    increments are at most ``FLAGSHIP_THRUST_RATIO`` times L1's on the same flights; the
    others (L1 here) are tuned for RMSE alone."""
    models = SimpleNamespace()

    # lower lambda: better tracking, rougher thrust; L1 at 0.2 N
    class FakeRunner(SequentialTrials):
        def fly(self, method, scenario, seed, estimated=False, compensate_delay=False):
            k = models.closedloop
            if method == "l1":
                return SimpleNamespace(
                    metrics={
                        "rmse_m": abs(np.log(k["l1_cutoff"] / 40.0)),
                        "thrust_increment_rms_n": 0.2,
                    }
                )
            lam = k["arcade_lambda"]
            return SimpleNamespace(
                metrics={"rmse_m": lam, "thrust_increment_rms_n": 0.2 * (1.0 + 4.0 * (1.0 - lam))}
            )

    out = qt.tune(models, runner=FakeRunner(), methods=("l1", "arcade"))
    # 0.2 (1 + 4 (1 - lambda)) <= 1.5 x 0.2 holds for lambda >= 0.875: the lowest such is 0.9
    # of the grid (0.8, 0.9, ...), where RMSE alone would take 0.5 (past the grid's 0.8).
    assert out["chosen"]["arcade_lambda"] == 0.9 and out["chosen"]["l1_cutoff"] == 40.0
    ft = out["flagship_thrust"]
    assert (
        ft["max_ratio_to_l1"] == qt.FLAGSHIP_THRUST_RATIO and ft["l1_thrust_increment_rms_n"] == 0.2
    )
    assert ft["chosen_thrust_increment_rms_n"] == pytest.approx(0.28)
    assert ft["thrust_increment_rms_n"]["arcade_lambda"]["0.8"] == pytest.approx(0.36)
    assert out["rmse_m"]["arcade_lambda"]["0.8"] == 0.8  # the tables keep the RMSE
    assert "arcade_lambda" not in out["extended"]  # 0.8 is on the edge but over the bound
