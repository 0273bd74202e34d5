"""Quadrotor closed loop, the parts around the flight: the controller step on either quaternion
sign, the flight diagnostics, the state estimate and its noise, the setpoint delay and its
compensation."""

import math
from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np
import pytest
from fake_runner import SequentialTrials

from arcade.training_quadrotor import QUADROTOR_WEIGHTS
from arcade_control.guard import guard_from_metadata
from arcade_control.learners import initial_learner, per_output_noise
from arcade_control.methods import make_method
from arcade_control.nominal import CONTROL_DT, nominal_params
from arcade_control.scenario import Scenario, reference
from arcade_control.step import Carry
from arcade_core import adaptation
from arcade_io.weights import load_model
from benchmarks import quadrotor_flights as flights
from benchmarks import quadrotor_tuning as qt
from benchmarks.quadrotor_flights import (
    DIAG_CHANGEPOINT,
    DIAG_CONVERGED,
    Flight,
    MocapEstimate,
    Runner,
    flight_metrics,
)


def _nominal_carry(runner: Runner, x, u, started: bool) -> Carry:
    """The nominal MPC's carry at state ``x``, ``u`` warm-started and in flight."""
    return Carry(
        initial_learner("nominal", runner.models, jnp.float64),
        jnp.broadcast_to(u, (runner.cfg.N, 4)),
        u,
        jnp.asarray(x),
        jnp.asarray(started),
    )


def test_controller_step_does_not_depend_on_the_quaternion_sign():
    """q and -q are one attitude: the MPC step must answer both with the same input.

    (An estimator may start in either hemisphere; unaligned, -q looks like a vehicle
    rotated by 360 degrees to the quaternion cost and the MPC commands a flip.)
    """
    runner = Runner(SimpleNamespace(closedloop={}), jnp.float64)
    step = runner.step_fn("nominal")
    x_ref_all, u_ref_all = reference(Scenario(), 40, runner.cfg.N)
    x = np.asarray(x_ref_all[0]) + np.r_[0.05, -0.03, -0.1, 0.1, 0.0, 0.0, np.zeros(7)]
    u0 = jnp.asarray([5.6, 0.0, 0.0, 0.0])
    carry = _nominal_carry(runner, x, u0, started=False)
    flipped = x.copy()
    flipped[6:10] *= -1.0
    _, u_pos, _ = step(carry, jnp.asarray(x), u0, 0, x_ref_all, u_ref_all)
    _, u_neg, _ = step(carry, jnp.asarray(flipped), u0, 0, x_ref_all, u_ref_all)
    np.testing.assert_allclose(np.asarray(u_neg), np.asarray(u_pos), rtol=1e-9, atol=1e-9)
    assert float(u_pos[0]) > 4.0  # a climb back to the reference, not a cut in thrust


def _logged_flight(method: str, u: np.ndarray, changepoint: np.ndarray) -> Flight:
    """A flight record of 20 control steps at 0.05 s; the figure-eight starts at 0.5 s."""
    n = len(u)
    t = 0.05 * np.arange(n)
    x = np.zeros((n, 13))
    diag = np.zeros((n, 17))
    diag[:, DIAG_CHANGEPOINT] = changepoint
    diag[:, DIAG_CONVERGED] = np.arange(n) % 4 != 0  # one solve in four hit the limit
    scen = Scenario(takeoff_s=0.25, hover_s=0.25, release_fraction=-1.0)
    return Flight(method, scen, 0, t, x, x.copy(), u, diag, float("nan"), False, t)


def test_flight_diagnostics_measure_command_jumps_and_changepoints():
    """Thrust alternating +-0.5 N and roll rate +-0.2 rad/s per period in the figure-eight
    part (the first 10 steps hold still and are outside it); changepoints on 3 of 10 steps."""
    n = 20
    u = np.zeros((n, 4))
    u[:, 0] = 5.0
    u[10:, 0] += 0.5 * (-1.0) ** np.arange(10)
    u[10:, 1] = 0.1 * (-1.0) ** np.arange(10)
    cp = np.zeros(n)
    cp[[2, 12, 15, 19]] = 1.0  # step 2 is before the figure-eight
    m = flight_metrics(_logged_flight("ours", u, cp))
    assert m["thrust_increment_rms_n"] == pytest.approx(1.0)
    assert m["rate_increment_rms_rad_s"] == pytest.approx(np.sqrt(0.2**2 / 3))
    assert m["changepoint_rate"] == pytest.approx(0.3)
    assert m["converged_fraction"] == pytest.approx(0.8)  # steps 12 and 16 of 10..19
    # The flagship (its detector's restarts) and its beam ablation too; methods without a
    # changepoint variable (forgetting without the restart) report none, not zero.
    for method in ("arcade", "arcade_beam"):
        m = flight_metrics(_logged_flight(method, u, cp))
        assert m["changepoint_rate"] == pytest.approx(0.3)
    for method in ("l1", "arcade_no_model", "arcade_no_restart"):
        assert np.isnan(flight_metrics(_logged_flight(method, u, cp))["changepoint_rate"])


def test_state_noise_adds_the_estimates_variance_through_the_model():
    """Errors in variables, first order: the residual of two estimated states has variance
    ``var_next + J var_prev J^T`` (diagonal), in the regression's units."""
    rng = np.random.default_rng(0)
    J = rng.normal(size=(13, 13))
    var_prev, var_next = rng.uniform(0, 1e-3, 13), rng.uniform(0, 1e-3, 13)
    scale = rng.uniform(0.5, 2.0, 13)
    brute = np.diag(np.diag(var_next) + J @ np.diag(var_prev) @ J.T) / scale**2
    got = adaptation.state_noise_sigma2(
        jnp.full(13, 0.1), jnp.asarray(J), jnp.asarray(var_prev), jnp.asarray(var_next), scale
    )
    np.testing.assert_allclose(np.asarray(got), 0.1 + brute, rtol=1e-12)


def test_per_output_noise_is_the_same_beam_while_the_variances_are_equal():
    vld, _, extra = load_model(QUADROTOR_WEIGHTS)
    models = SimpleNamespace(vld=vld, guard=guard_from_metadata(extra), closedloop={})
    a = initial_learner("ours", models, jnp.float64)
    b = per_output_noise(a)
    assert b.config.sigma2.shape == (13,) and b.beam.sqrt_covariances.shape[1] == 13
    method = make_method("ours")
    rng = np.random.default_rng(1)
    x = np.r_[0, 0, 1.0, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0]
    u = np.array([6.0, 0.0, 0.0, 0.0])
    for _ in range(5):
        x_next = x + np.r_[rng.normal(0, 1e-3, 6), np.zeros(7)]
        a = method.learn(a, jnp.asarray(x), jnp.asarray(u), jnp.asarray(x_next))
        b = method.learn(b, jnp.asarray(x), jnp.asarray(u), jnp.asarray(x_next))
    np.testing.assert_allclose(method.model(b)[1], method.model(a)[1], rtol=1e-9, atol=1e-12)


def test_the_estimated_state_is_what_the_emulated_motion_capture_allows():
    """:class:`MocapEstimate` starts on the frame captured at t = 0 and then tracks the
    hovering vehicle within the emulation's noise (0.3 mm, 0.2 deg; a few ms of latency)."""
    from simulator import QuadrotorSim

    sim = QuadrotorSim(payload_mass=0.0, seed=3)
    sim.reset(np.array([0.0, 0.0, 1.0]))
    runner = Runner(SimpleNamespace(), jnp.float64)
    estimate = MocapEstimate(sim, jnp.float64, runner._estimation()[0])
    errors = []
    for _ in range(40):
        x, var = estimate()
        errors.append(x - sim.state())
        assert np.all(var > 0) and np.all(np.isfinite(x))
        sim.set_setpoint(np.array([sim.hover_thrust(), 0.0, 0.0, 0.0]))
        sim.step(CONTROL_DT)
    e = np.array(errors)
    assert np.abs(e[0, :3]).max() < 2e-3  # initialised from the first frame
    assert np.sqrt(np.mean(e[10:, :3] ** 2)) < 1e-3
    assert np.sqrt(np.mean(e[10:, 3:6] ** 2)) < 0.05


def test_a_runner_flies_the_estimator_settings_it_is_given():
    """``Runner(filter_config=...)`` reaches the estimate: at hover a lower jerk density
    gives a smoother velocity, on the same emulated frames."""
    from arcade_core.estimation import FilterConfig
    from simulator import QuadrotorSim

    def velocity_noise(jerk_psd: float) -> float:
        sim = QuadrotorSim(payload_mass=0.0, seed=3)
        sim.reset(np.array([0.0, 0.0, 1.0]))
        runner = Runner(SimpleNamespace(), jnp.float64, FilterConfig(jerk_psd=jerk_psd))
        estimate = MocapEstimate(sim, jnp.float64, runner._estimation()[0])
        errors = []
        for _ in range(40):
            errors.append(estimate()[0][3:6] - sim.state()[3:6])
            sim.set_setpoint(np.array([sim.hover_thrust(), 0.0, 0.0, 0.0]))
            sim.step(CONTROL_DT)
        return float(np.sqrt(np.mean(np.array(errors[10:]) ** 2)))

    assert velocity_noise(1.0) < 0.5 * velocity_noise(100.0)


def test_the_estimator_tuning_does_not_sacrifice_one_method_for_another():
    from benchmarks.quadrotor_variants import least_worst_loss

    # b's best value (5) costs a 6x; 20 costs each method at most 3 %.
    scores = {
        "a": {100.0: 0.0191, 20.0: 0.0187, 10.0: 0.0193, 5.0: 0.1212},
        "b": {100.0: 0.0631, 20.0: 0.0530, 10.0: 0.0523, 5.0: 0.0516},
    }
    assert least_worst_loss(scores) == 20.0
    # A tie goes to the larger value (the less lagging filter).
    assert least_worst_loss({"a": {30.0: 1.0, 20.0: 1.0}}) == 30.0
    # One method: its best value.
    assert least_worst_loss({"b": scores["b"]}) == 5.0
    # A crashed setting is never picked; a method that always crashed cannot be tuned.
    assert least_worst_loss({"a": {20.0: 2.0, 10.0: math.inf}}) == 20.0
    with pytest.raises(ValueError, match="a has no finite score"):
        least_worst_loss({"a": {20.0: math.inf}, "b": {20.0: 1.0}})


def test_ours_stack_flies_the_adapter_s_knobs():
    from arcade_control.stack import stack_knobs
    from benchmarks.quadrotor_variants import STACK_KNOBS

    assert stack_knobs() == STACK_KNOBS


class _RecordingRunner(SequentialTrials):
    """Stands in for :class:`Runner`: records what it is asked to fly, scores it by delay."""

    def __init__(self, *args, **kwargs):
        self.flown: list[tuple[str, Scenario, bool]] = []

    def fly(self, method, scenario, seed=0, estimated=False, compensate_delay=False):
        self.flown.append((method, scenario, compensate_delay))
        rmse = 0.01 + scenario.command_delay_s + 0.1 * compensate_delay
        return SimpleNamespace(
            metrics={"rmse_m": rmse, "rmse_z_m": rmse, "thrust_increment_rms_n": 0.1}
        )


def test_the_delay_diagnostic_flies_each_row_with_its_setpoint_delay(monkeypatch):
    from benchmarks import quadrotor_variants as qv

    runners: list[_RecordingRunner] = []

    def runner(*args, **kwargs):
        runners.append(_RecordingRunner())
        return runners[-1]

    monkeypatch.setattr(flights, "Runner", runner)
    monkeypatch.setattr(qv, "models", lambda: SimpleNamespace(closedloop={}))
    flown = [
        qv.Flown("l1@0ms", "l1", {}),
        qv.Flown("l1@20ms", "l1", {}, False, 0.02),
        qv.Flown("l1_compensated@20ms", "l1", {}, False, 0.02, True),
    ]
    rows = qv._cell_means(flown, 1, ("rmse_m",))
    assert len(rows) == 9 and len(runners) == 1  # one runner for the ground-truth rows
    assert rows[0]["l1@0ms"]["rmse_m"] == pytest.approx(0.01)
    assert rows[0]["l1@20ms"]["rmse_m"] == pytest.approx(0.03)
    assert rows[0]["l1_compensated@20ms"]["rmse_m"] == pytest.approx(0.13)
    # The tuning flies its cell with the delay it is given, compensated if it is told so.
    for compensate in (False, True):
        tuning = _RecordingRunner()
        models = SimpleNamespace(closedloop={})
        qt.tune(
            models,
            runner=tuning,
            methods=("l1",),
            command_delay_s=0.02,
            compensate_delay=compensate,
        )
        scenarios = {s for _, s, _ in tuning.flown}
        assert {s.command_delay_s for s in scenarios} == {0.02}
        assert {(s.payload_g, s.speed_mps) for s in scenarios} == {qt.TUNING_CELL}
        assert {c for *_, c in tuning.flown} == {compensate}


def test_the_link_diagnostic_flies_the_stack_on_the_estimate_with_and_without_compensation(
    monkeypatch,
):
    from benchmarks import quadrotor_variants as qv

    flown = []

    class Recorder(SequentialTrials):
        def __init__(self, models, **kwargs):
            self.models = models

        def fly(self, method, scenario, seed=0, estimated=False, compensate_delay=False):
            knobs = dict(self.models.closedloop)
            flown.append((method, knobs, scenario, seed, estimated, compensate_delay))
            rmse = 0.01 + scenario.command_delay_s * (0.5 if compensate_delay else 2.0)
            if method == "l1":  # the tuning moves L1's pole off its stored value ...
                rmse += 0.01 * abs(knobs.get("l1_a_s", -0.1) + 1.0)
            else:  # ... and keeps ours at the stack's knobs
                rmse += 0.001 * sum(knobs[k] != v for k, v in qv.STACK_KNOBS.items())
            metrics = {"rmse_m": rmse, "rmse_z_m": rmse / 2, "changepoint_rate": 0.1}
            metrics["thrust_increment_rms_n"] = 0.1
            return SimpleNamespace(metrics={**metrics, "settling_s": 0.0})

    monkeypatch.setattr(flights, "Runner", Recorder)
    monkeypatch.setattr(qv, "models", lambda: SimpleNamespace(closedloop={}))
    r = qv.link_delay(trials=1)
    assert all(est for *_, est, _ in flown)  # what the stack flies: the estimate
    # The grid on the tuning cell: each delay without compensation, each non-zero one with
    # it (0 ms is one flight), ours at the stack's knobs.
    n = len(qv.LINK_DELAYS_S)
    grid = flown[: 2 * (2 * n - 1) * len(qt.TUNING_SEEDS)]
    assert {(s.payload_g, s.speed_mps) for _, _, s, *_ in grid} == {qt.TUNING_CELL}
    assert all(f[1] == qv.STACK_KNOBS for f in grid if f[0] == "ours")
    sens = r["sensitivity"]
    assert sens["delays_s"] == list(qv.LINK_DELAYS_S)
    comp, plain = sens["rows"]["ours_stack_compensated"], sens["rows"]["ours_stack"]
    assert comp["rmse_m"][0] == plain["rmse_m"][0] == pytest.approx(0.01)
    i = qv.LINK_DELAYS_S.index(0.02)
    assert plain["rmse_m"][i] == pytest.approx(0.05) and comp["rmse_m"][i] == pytest.approx(0.02)
    # The tuning and the cells fly the stack's condition: 20 ms, compensated.
    rest = flown[len(grid) :]
    assert {(s.command_delay_s, c) for _, _, s, _, _, c in rest} == {(0.02, True)}
    assert r["tuning"]["chosen"]["l1_a_s"] == -1.0
    names = [f["name"] for f in r["rows_flown"]]
    # Ours keeps the stack's knobs: no re-tuned row of its own.
    assert names == [
        "ours_stack_compensated@20ms",
        "l1_compensated@20ms",
        "l1_retuned_compensated@20ms",
    ]
    assert len(r["rows"]) == 9 and all(n in r["rows"][0] for n in names)


def test_a_runner_flies_the_scenarios_setpoint_delay(monkeypatch):
    class Built(Exception):
        pass

    def build(**kwargs):
        raise Built(kwargs["command_delay_s"])

    monkeypatch.setattr(flights, "QuadrotorSim", build)
    scen = Scenario(takeoff_s=0.25, hover_s=0.25, release_fraction=-1.0, command_delay_s=0.02)
    runner = Runner(SimpleNamespace(closedloop={}), jnp.float64)
    with pytest.raises(Built) as built:
        runner.fly("nominal", scen)
    assert built.value.args == (0.02,)


def test_a_compensated_delay_plans_from_the_state_predicted_over_it():
    """With ``delay_s`` the step answers ``x`` as the plain step answers the state one RK4
    step of the nominal model later under the input in flight (the MPC's own last input),
    and the reference for it is the same path that much later."""
    from arcade_core.dynamics.quadrotor import quadrotor_step

    runner = Runner(SimpleNamespace(closedloop={}), jnp.float64)
    scen = Scenario(command_delay_s=0.02)
    # One control period of offset is the next control instant's reference.
    x_ref_all, u_ref_all = reference(scen, 40, runner.cfg.N)
    x_late, u_late = reference(scen, 40, runner.cfg.N, CONTROL_DT)
    np.testing.assert_allclose(x_late[:-1], x_ref_all[1:], atol=1e-12)
    np.testing.assert_allclose(u_late[:-1], u_ref_all[1:], atol=1e-9)
    x_ref_d, u_ref_d = reference(scen, 40, runner.cfg.N, 0.02)
    x = np.asarray(x_ref_all[5]) + np.r_[0.05, -0.03, -0.1, 0.3, 0.0, 0.2, np.zeros(7)]
    u_in_flight = jnp.asarray([6.5, 0.2, -0.1, 0.0])
    carry = _nominal_carry(runner, x, u_in_flight, started=True)
    x_pred = quadrotor_step(jnp.asarray(x), u_in_flight, nominal_params(), 0.02)
    _, u_comp, _ = runner.step_fn("nominal", 0.02)(
        carry, jnp.asarray(x), u_in_flight, 5, x_ref_d, u_ref_d
    )
    _, u_plain, _ = runner.step_fn("nominal")(carry, x_pred, u_in_flight, 5, x_ref_d, u_ref_d)
    _, u_naive, _ = runner.step_fn("nominal")(
        carry, jnp.asarray(x), u_in_flight, 5, x_ref_d, u_ref_d
    )
    np.testing.assert_allclose(np.asarray(u_comp), np.asarray(u_plain), rtol=1e-9, atol=1e-9)
    assert np.max(np.abs(np.asarray(u_comp) - np.asarray(u_naive))) > 1e-3
