"""The flagship split across the stack's processes: the adapter learns its model, the
controller runs its L1 augmentation on the model message; together they are the in-process
method's step (float64)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from arcade_control.methods import arcade_method, make_method
from arcade_control.nominal import CONTROL_DT, nominal_params
from arcade_control.stack import (
    STACK_ARCADE_KNOBS,
    STACK_L1_KNOBS,
    adapter_learner,
    controller_learner,
    controller_method,
    detector_prior,
    load_learner,
    make_adapter_update,
    one_hypothesis_beam,
    stack_knobs,
)
from arcade_core import adaptation
from arcade_core.dynamics import quadrotor_step
from services.adapter import DEFAULT_WEIGHTS


def _transition(seed: int = 0):
    """A hover-ish transition with the thrust a 175 g payload needs: a real residual."""
    rng = np.random.default_rng(seed)
    xp = np.r_[0.1, -0.2, 1.0, 0.3, 0.1, -0.05, 1.0, 0.0, 0.0, 0.0, 0.05, -0.02, 0.01]
    xp[6:10] += 0.02 * rng.standard_normal(4)
    xp[6:10] /= np.linalg.norm(xp[6:10])
    up = np.array([7.2, 0.1, -0.05, 0.02])
    x = np.asarray(quadrotor_step(jnp.asarray(xp), jnp.asarray(up), nominal_params(), CONTROL_DT))
    x = x + np.r_[np.zeros(3), 0.0, 0.0, -0.03, np.zeros(7)]  # heavier than nominal
    return xp, up, x


def _close(a, b) -> None:
    for u, v in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(u), np.asarray(v), rtol=1e-12, atol=1e-12)


def test_the_stack_flies_the_flagship_at_its_stack_knobs():
    learner, method = load_learner(DEFAULT_WEIGHTS, np.float64, "arcade")
    assert method.name == "arcade" and learner.l1 is not None
    # One hypothesis that forgets at every step (pi = 1, beta^2 = lambda).
    assert learner.beam.means.shape[0] == 1 and float(learner.config.pi) == 1.0
    assert float(learner.config.beta) ** 2 == pytest.approx(STACK_ARCADE_KNOBS["arcade_lambda"])
    assert float(learner.config.sigma2) == pytest.approx(STACK_ARCADE_KNOBS["arcade_sigma2"])
    l = learner.vld.theta0.shape[1]
    assert learner.beam.prior_mean.shape[1] == l + 1  # the intercept's column
    assert detector_prior(learner).shape == learner.vld.theta0.shape
    # The controller carries the augmentation, not the restart detector (the adapter's).
    ctrl = controller_learner(DEFAULT_WEIGHTS, np.float64, "arcade")
    assert learner.restart is not None and ctrl.restart is None and ctrl.l1 is not None
    # The adapter learns the model only; the controller carries the augmentation.
    adapter, adapter_method = adapter_learner(DEFAULT_WEIGHTS, np.float64, "arcade")
    assert adapter.l1 is None and adapter_method.name == "arcade_no_l1"
    assert stack_knobs() == stack_knobs("ours") != stack_knobs("arcade")
    with pytest.raises(ValueError, match="the stack flies arcade or ours or l1"):
        stack_knobs("gp")


def test_the_stack_flies_l1_with_the_in_process_l1_step():
    """``--method l1``: the adapter learns ours' model (the detector and the model messages
    as with ours), the controller runs the in-process L1 method on its own state at the
    stack's L1 knobs, whatever the model message holds."""
    adapter, adapter_method_ = adapter_learner(DEFAULT_WEIGHTS, np.float64, "l1")
    ours, _ = adapter_learner(DEFAULT_WEIGHTS, np.float64, "ours")
    assert adapter.l1 is None and adapter_method_.name == "ours"
    _close(adapter.beam, ours.beam)
    _close(adapter.config, ours.config)

    learner, _ = load_learner(DEFAULT_WEIGHTS, np.float64, "l1")
    assert float(learner.l1.params.cutoff_thrust) == pytest.approx(STACK_L1_KNOBS["l1_cutoff"])
    xp, up, x = _transition()
    l1_ = make_method("l1")
    a = jax.jit(l1_.learn)(jax.jit(l1_.learn)(learner.l1, xp, up, xp), xp, up, x)
    ctrl = controller_method("l1")
    c = learner
    rng = np.random.default_rng(1)
    for transition in ((xp, up, xp), (xp, up, x)):  # any model message: not used
        theta = rng.standard_normal(learner.beam.means.shape[1:])
        cov = np.broadcast_to(np.eye(theta.shape[1]), (theta.shape[0], *theta.shape[1:2] * 2))
        held = c._replace(beam=one_hypothesis_beam(c.beam, theta, cov))
        c = jax.jit(ctrl.learn)(held, *transition)
    _close(c.l1, a)
    np.testing.assert_allclose(ctrl.correction(c, x), l1_.correction(a, x), atol=1e-12)
    assert abs(float(c.l1.thrust_adj)) > 0.0
    assert ctrl.sigma(c, x, up) is None and not ctrl.learned


def test_adapter_then_controller_is_the_in_process_flagship_step():
    """The adapter's exact update (no estimation noise) then the controller's L1 step on
    the model it publishes (held in a one-hypothesis beam) give the in-process step's
    augmentation; ours' controller learns nothing."""
    xp, up, x = _transition()
    learner, _ = load_learner(DEFAULT_WEIGHTS, np.float64, "arcade")
    # Two in-process steps, so that the L1 predictor has been synchronised.
    step = jax.jit(arcade_method().learn)
    a1 = step(learner, xp, up, xp)
    a2 = step(a1, xp, up, x)

    adapter, adapter_method = adapter_learner(DEFAULT_WEIGHTS, np.float64, "arcade")
    params = nominal_params()
    adapt, _, _ = make_adapter_update(adapter_method, params, adapter.config.sigma2, exact=True)
    zero = np.zeros(13)
    b1 = adapt(adapter, xp, up, xp, CONTROL_DT, True, zero, zero)[0]
    out = adapt(b1, xp, up, x, CONTROL_DT, True, zero, zero)
    theta, cov = out[5], out[6]
    # The adapter's posterior is the in-process beam's marginal.
    theta_in, cov_in = adaptation.marginal_decoder(a2.beam)
    np.testing.assert_allclose(theta, theta_in, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(cov, cov_in, rtol=1e-10, atol=1e-12)

    # The controller: learner0 with the model messages' posteriors, its own L1 state.
    ctrl = controller_method("arcade")
    theta1, cov1 = adaptation.marginal_decoder(b1.beam)
    c = learner
    for th, cv, transition in ((theta1, cov1, (xp, up, xp)), (theta, cov, (xp, up, x))):
        held = c._replace(beam=one_hypothesis_beam(c.beam, th, cv))
        c = jax.jit(ctrl.learn)(held, *transition)
    _close(c.l1, a2.l1)
    assert float(ctrl.correction(c, x)[0]) == pytest.approx(
        float(arcade_method().correction(a2, x)[0]), abs=1e-12
    )
    assert abs(float(c.l1.thrust_adj)) > 0.0  # it did correct something

    ours = controller_method("ours")
    base, _ = load_learner(DEFAULT_WEIGHTS, np.float64, "ours")
    assert ours.learn(base, xp, up, x) is base
    assert make_method("ours").name == ours.name


@pytest.mark.parametrize(
    ("adaptation", "text"),
    [("ours", "controller: ours (ARCADE"), ("arcade", "controller: arcade (the flagship"),
     ("l1", "controller: l1 (the L1"), ("nominal", "controller: nominal MPC")],
)  # fmt: skip
def test_the_demo_summary_names_the_controller_flown(adaptation, text):
    from arcade.demo_stack import format_summary

    s = {"adaptation": adaptation, "rmse_m": 0.04, "rmse_z_m": 0.02, "flight_wall_s": 30.0,
         "startup_s": 4.0, "crashed": False, "rejects": {}}  # fmt: skip
    assert format_summary(s).splitlines()[0].startswith(text)


def test_the_flagship_plans_with_its_thrust_smoothness_the_others_with_the_shared_one():
    from arcade_control.knobs import TUNED_DEFAULTS
    from arcade_control.stack import STACK_ARCADE_KNOBS, stack_knobs
    from arcade_control.step import method_mpc_config, mpc_config

    cfg = mpc_config(jnp.float64)
    assert cfg.smooth_weight == 10.0
    for name in ("l1", "ours", "nominal", "ours_matched"):
        assert method_mpc_config(cfg, name, {"arcade_thrust_smooth": 50.0}) is cfg
    w = TUNED_DEFAULTS["arcade_thrust_smooth"]
    for name in ("arcade", "arcade_no_model", "arcade_no_l1"):
        assert method_mpc_config(cfg, name).smooth_weight == (w, 10.0, 10.0, 10.0)
    assert method_mpc_config(cfg, "arcade", {"arcade_thrust_smooth": 35.0}).smooth_weight == (
        35.0, 10.0, 10.0, 10.0)  # fmt: skip
    # The stack flies the shared weight: its controller's MPC is the shared one.
    assert STACK_ARCADE_KNOBS["arcade_thrust_smooth"] == 10.0
    assert method_mpc_config(cfg, "arcade", stack_knobs("arcade")) is cfg
