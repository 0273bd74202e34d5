"""The control methods: how each learns and what it hands the MPC (all pure JAX).

- ``nominal``: MPC on ``f_nom``;
- ``l1``: nominal MPC + L1-adaptive augmentation (:mod:`arcade_core.baselines.l1`);
- ``gp``: GP-MPC, GP mean (FIFO 50, re-conditioned every step) inside the rollout;
- ``mlp``: MLP-MPC, last-layer SGD, unscented-transform variance modulating ``Q``;
- ``ours_no_cp``: VLD + BLR without changepoints (``K = 1``, ``pi = 0``);
- ``ours``: full ARCADE: beam-marginal decoder mean inside the rollout, ``Q`` modulated by
  ``sigma_tot^2`` (Sec. IV);
- variants of ours that are not the paper's method (:data:`~arcade_control.knobs.VARIANTS`),
  among them the product's own controller ``arcade`` (:func:`arcade_method`), and the mass
  oracle, a diagnostic.

The variance that modulates ``Q`` is unit-free: the variance of the residual in the units
each model learns in (the VLD's normalised residual for ours, the standardised output for
the MLP); see :mod:`benchmarks.quadrotor_closedloop`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from arcade_control.guard import Guard, clip_residual
from arcade_control.knobs import (
    BEAM_VARIANTS,
    FLAGSHIP,
    FLAGSHIP_ABLATIONS,
    METHODS,
    ORACLE,
    PAPER_SETTINGS,
    RESTARTING,
    base_name,
)
from arcade_control.nominal import CONTROL_DT as DT
from arcade_control.nominal import f_nom, nominal_params
from arcade_core import adaptation, encoder
from arcade_core import frames as quat
from arcade_core.baselines import gp, l1, mlp
from arcade_core.dynamics.quadrotor import quadrotor_step


class Method(NamedTuple):
    """How one method learns and what it hands the MPC (all pure JAX).

    ``learn(a, x_prev, u_prev, x) -> a`` consumes the transition of the last period;
    ``model(a)`` is the pytree passed to the MPC's ``step_fn``; ``sigma(a, x, u)`` the
    variance that modulates ``Q`` (``None``: no modulation); ``correction(a, x)`` an
    additive input correction (L1); ``info(a)`` two diagnostics (changepoint flag, cp prob).
    """

    name: str
    step_fn: Callable
    learn: Callable
    model: Callable
    sigma: Callable
    correction: Callable
    info: Callable
    learned: bool = False
    #: ``reference(model, x_ref, u_ref) -> u_ref`` replacing :func:`thrust_reference`
    #: (learned methods only; the mass oracle's is exact).
    reference: Callable | None = None
    #: Beam methods: ``features(a, x, u) -> z`` and ``latent_variance(a, x, u)``, what the
    #: regression sees (the adapter service computes them as ``learn`` does).
    features: Callable | None = None
    latent_variance: Callable | None = None
    #: Whether the learner has a changepoint variable (a learner that forgets at every
    #: step reports no changepoint and a zero probability).
    changepoints: bool = True
    #: Whether the MPC holds the learned residual along the warm start instead of
    #: differentiating it inside the rollout (:func:`arcade_control.step.make_controller_step`).
    hold_residual: bool = False


def _zero_info(a):
    return jnp.zeros(2)


def _no_correction(a, x):
    return jnp.zeros(4, x.dtype)


def _nominal_step(x, u, model):
    return f_nom(x, u)


def nominal_method() -> Method:
    return Method(
        "nominal",
        _nominal_step,
        lambda a, xp, up, x: a,
        lambda a: jnp.zeros(()),
        lambda a, x, u: None,
        _no_correction,
        _zero_info,
    )


def l1_method() -> Method:
    def learn(a, xp, up, x):
        return l1.update(a, x, up, DT)

    return Method(
        "l1",
        _nominal_step,
        learn,
        lambda a: jnp.zeros(()),
        lambda a, x, u: None,
        l1.correction,
        _zero_info,
    )


class MassOracle(NamedTuple):
    """What :func:`oracle_mass_method` knows: the mass hanging from the vehicle (payload
    and cable) and the release step."""

    count: Array  # () int32: transitions seen (the control step after the first)
    k_release: Array  # () int32: control step of the release (-1: never)
    payload_kg: Array  # ()


def oracle_mass_method() -> Method:
    """A diagnostic, not a method of the evaluation: the nominal model with the payload
    (and the cable's lumped mass) as a rigid mass, known exactly, removed at the exact
    release step. It bounds what any
    model of ``(x, u)`` alone can give this MPC: it knows everything about the payload
    except its swing (the cable's changing pull), which no state in ``(x, u)`` shows.
    The thrust reference is exact (the thrust scales with the mass)."""
    p = nominal_params()

    def mass(a: MassOracle) -> Array:
        attached = (a.k_release < 0) | (a.count < a.k_release)
        return jnp.where(attached, p.mass + a.payload_kg, p.mass).astype(a.payload_kg.dtype)

    def step_fn(x, u, m):
        return quadrotor_step(x, u, p._replace(mass=m), DT)

    def reference(m, x_ref, u_ref):
        return u_ref.at[:, 0].multiply(m / p.mass)

    return Method(
        "oracle_mass",
        step_fn,
        lambda a, xp, up, x: a._replace(count=a.count + 1),
        mass,
        lambda a, x, u: None,
        _no_correction,
        _zero_info,
        learned=True,
        reference=reference,
    )


def gp_method() -> Method:
    def step_fn(x, u, model):
        state, guard = model
        return f_nom(x, u) + clip_residual(gp.predict(state, x, u)[0], guard)

    def learn(a, xp, up, x):
        state, guard = a
        return gp.update(state, xp, up, x - f_nom(xp, up)), guard

    return Method(
        "gp",
        step_fn,
        learn,
        lambda a: a,
        lambda a, x, u: None,
        _no_correction,
        _zero_info,
        learned=True,
    )


def mlp_method() -> Method:
    def step_fn(x, u, model):
        state, guard = model
        return f_nom(x, u) + clip_residual(mlp.predict_mean(state, x, u), guard)

    def learn(a, xp, up, x):
        state, guard = a
        return mlp.update(state, xp, up, x - f_nom(xp, up)), guard

    def sigma(a, x, u):
        # UT variance in the network's standardised output units (module docstring).
        state, _ = a
        return mlp.predict(state, x, u)[1] / state.model.standardizer.out_scale**2

    return Method(
        "mlp", step_fn, learn, lambda a: a, sigma, _no_correction, _zero_info, learned=True
    )


class Restart(NamedTuple):
    """The flagship's changepoint detector and the learner's state it restarts to
    (:func:`restart_at_change`)."""

    detection: adaptation.DetectionState
    config: adaptation.DetectionConfig
    #: The learner's beam at the offline prior mean, its covariance times ``scale``.
    prior: adaptation.BeamState
    scale: Array
    base_sigma2: Array  # the learner's own noise: its step's noise less this is the estimate's
    noise: Array  # the detector's calibrated noise (Appendix D)
    #: ``()`` int32, the step the latest step's declaration is dated to (``-1``: none).
    dated: Array


class BeamLearner(NamedTuple):
    """Adaptive state of ours: frozen VLD, beam, hyperparameters, last update's info."""

    vld: encoder.VLD
    beam: adaptation.BeamState
    config: adaptation.AdaptationConfig
    guard: Guard
    changepoint: Array
    cp_prob: Array
    #: The flagship's matched-disturbance estimate (:func:`arcade_method`); ``None`` in ours.
    l1: l1.L1State | None = None
    #: The flagship's detector that restarts the learner at a declared change.
    restart: Restart | None = None


def clipped_features(vld: encoder.VLD, guard: Guard, x: Array, u: Array) -> Array:
    """``mu_phi(x, u)`` clipped to the training range (:class:`Guard`)."""
    return jnp.clip(vld.features(x, u), guard.feature_lo, guard.feature_hi)


def matched_residual(x: Array, delta: Array) -> Array:
    """The part of a residual ``delta`` (13,) that the collective thrust can cancel.

    Position and velocity parts projected onto the body z axis of ``x``; the attitude and
    body-rate parts zero. What ``ours_matched`` plans with (:func:`beam_method`).
    """
    zb = quat.to_rotation_matrix(x[6:10])[:, 2]  # body z axis (thrust) in the world frame
    out = jnp.zeros_like(delta)
    out = out.at[0:3].set(jnp.dot(delta[0:3], zb) * zb)
    return out.at[3:6].set(jnp.dot(delta[3:6], zb) * zb)


def restart_at_change(a: BeamLearner, z: Array, dn: Array) -> BeamLearner:
    """The detector's step (:func:`arcade_core.adaptation.detection_step`) on a transition's
    VLD features ``z`` and normalised residual ``dn``, with its calibrated noise plus what
    the state estimate adds to the learner's; a declared change restarts the learner at
    the offline prior's mean with ``scale`` times its covariance, and is the learner's
    changepoint flag, the detector's probability its ``cp_prob``, the step it is dated to
    ``restart.dated``. The restarted beam keeps counting steps (``step``), so that the
    learner's steps and the detector's stay one count. With the whole prior
    covariance (``scale = 1``) at the flagship's small ``sigma^2`` the restarted learner
    refits on every period (a gain near one), which made the planned thrust chatter."""
    r = a.restart
    sigma2 = jnp.broadcast_to(r.noise + (a.config.sigma2 - r.base_sigma2), dn.shape)
    state, d = adaptation.detection_step(r.detection, z, dn, sigma2, True, r.config)
    beam = jax.tree.map(lambda p, b: jnp.where(d.declared, p, b), r.prior, a.beam)
    return a._replace(
        beam=beam._replace(step=a.beam.step),
        restart=r._replace(detection=state, dated=d.dated.astype(r.dated.dtype)),
        changepoint=d.declared.astype(dn.dtype),
        cp_prob=d.probability.astype(dn.dtype),
    )


def beam_method(
    name: str = "ours",
    intercept: bool = False,
    matched: bool = False,
    forgetting: bool = False,
    restart: bool = False,
) -> Method:
    """Ours (Sec. III-IV), or a variant that is not the paper's method (:data:`VARIANTS`).

    ``intercept``: the latent features get a constant ``1`` appended (``l + 1`` columns;
    the offline decoder's column is zero), so the online regression can learn an offset
    that does not depend on the state or the input. ``matched``: the MPC's rollout uses
    only :func:`matched_residual` of the learned residual; learning, the changepoints and
    ``sigma_tot^2`` see every output as in ours. ``forgetting``: the learner is a single
    hypothesis that tempers at every step (:func:`arcade_control.learners.forgetting_config`),
    so its own changepoint flag and probability say nothing and stay zero. ``restart``: its
    detector restarts it at a declared change (:func:`restart_at_change`), and the flag and
    the probability are the detector's.
    """

    def features(vld, guard, x, u):
        z = clipped_features(vld, guard, x, u)
        return jnp.concatenate([z, jnp.ones((1,), z.dtype)]) if intercept else z

    def latent_variance(vld, x, u):
        v = vld.latent_variance(x, u)
        return jnp.concatenate([v, jnp.zeros((1,), v.dtype)]) if intercept else v

    def step_fn(x, u, model):
        vld, theta, guard = model
        delta = clip_residual(vld.denormalise_residual(theta @ features(vld, guard, x, u)), guard)
        return f_nom(x, u) + (matched_residual(x, delta) if matched else delta)

    def learn(a: BeamLearner, xp, up, x):
        z = features(a.vld, a.guard, xp, up)
        dn = a.vld.normalise_residual(x - f_nom(xp, up))
        beam, info = adaptation.update(a.beam, z, dn, a.config)
        if restart:
            z_vld = clipped_features(a.vld, a.guard, xp, up)  # what the detector watches
            return restart_at_change(a._replace(beam=beam), z_vld, dn)
        if forgetting:
            return a._replace(beam=beam)
        return a._replace(
            beam=beam, changepoint=info.changepoint.astype(z.dtype), cp_prob=info.cp_prob
        )

    def model(a: BeamLearner):
        # Moment-matched beam marginal of the decoder (Eq. 9): its mean drives the rollout.
        return a.vld, adaptation.marginal_decoder(a.beam)[0], a.guard

    def sigma(a: BeamLearner, x, u):
        z = features(a.vld, a.guard, x, u)
        return adaptation.sigma_tot2(a.beam, z, latent_variance(a.vld, x, u))

    def info(a: BeamLearner):
        return jnp.stack([a.changepoint, a.cp_prob])

    return Method(
        name,
        step_fn,
        learn,
        model,
        sigma,
        _no_correction,
        info,
        learned=True,
        features=lambda a, x, u: features(a.vld, a.guard, x, u),
        latent_variance=lambda a, x, u: latent_variance(a.vld, x, u),
        changepoints=restart or not forgetting,
    )


def augmentation_step(base: Method, a: BeamLearner, xp, up, x) -> BeamLearner:
    """The flagship's L1 step over the transition ``xp -> x`` under the input ``up`` the
    vehicle was sent: its state predictor adds what the learned model ``base.model(a)``
    (the one the next plan uses, updated on this transition) predicts beyond the nominal
    model, so the augmentation estimates only what that model misses (L1-GP).

    The model is evaluated at the plan's input, ``up`` less the augmentation's own thrust
    correction: the VLD's features depend on the thrust, and through them the model's
    prediction would answer the correction, an algebraic loop that, in the stack's
    condition (estimated state, compensated delay), left a payload-sized z offset at
    0.5 m/s (175 g, seed 0: 24.8 mm RMSE in z against 9.6 mm without the loop)."""
    u_plan = up.at[0].add(-l1.correction(a.l1, xp)[0])
    known = (base.step_fn(xp, u_plan, base.model(a)) - f_nom(xp, u_plan))[3:6] / DT
    return a._replace(l1=l1.update(a.l1, x, up, DT, known_accel=known))


def arcade_method(name: str = FLAGSHIP) -> Method:
    """The product's controller ``arcade``: the ARCADE model in the MPC, the remainder
    cancelled every period (not the paper's method; ``docs/quadrotor-closed-loop.md``).

    - The MPC plans with ``f_nom + theta phi`` through its thrust axis (``ours_matched``'s
      model: BLR on the VLD features plus an intercept), learned by one hypothesis with
      exponential forgetting (Eq. 5's tempering at every step, the offline prior
      re-injected; :func:`arcade_control.learners.flagship_config`): the changepoint
      beam's switching between hypotheses made the planned thrust chatter. The adapter's
      changepoint detector restarts it at the prior when it declares a change
      (:func:`restart_at_change`). The MPC holds the learned residual along its warm start
      (:func:`arcade_core.mpc.residual_along`): the same tracking, and at 2.5 m/s at least
      99 % of the solves converge within their iterations (82-93 % with the residual
      inside the rollout).
    - An L1 augmentation of the collective thrust whose state predictor includes that
      learned model (L1-GP): its piecewise-constant law estimates, and its low-pass filter
      cancels, only the force the learned model misses over the last period; the thrust
      correction acts between the MPC's plans like integral action.

    ``name`` one of :data:`FLAGSHIP_ABLATIONS`: the flagship without its learned model (the
    augmentation on the nominal MPC), without the augmentation, without the restart,
    without forgetting (one hypothesis that never tempers nor restarts), or with the
    changepoint beam instead of forgetting and restart (the learners:
    :func:`arcade_control.learners.flagship_config`).
    """
    if name == "arcade_no_model":
        return l1_method()._replace(name=name)
    forgetting = name in (FLAGSHIP, "arcade_no_l1", "arcade_no_restart")
    restart = name in RESTARTING
    base = beam_method(name, intercept=True, matched=True, forgetting=forgetting, restart=restart)
    base = base._replace(hold_residual=True)
    if name == "arcade_no_l1":
        return base

    def learn(a: BeamLearner, xp, up, x):
        return augmentation_step(base, base.learn(a, xp, up, x), xp, up, x)

    def correction(a: BeamLearner, x):
        return l1.correction(a.l1, x)

    return base._replace(learn=learn, correction=correction)


def make_method(name: str) -> Method:
    name = base_name(name)
    if name == "nominal":
        return nominal_method()
    if name == "l1":
        return l1_method()
    if name == FLAGSHIP or name in FLAGSHIP_ABLATIONS:
        return arcade_method(name)
    if name == "gp":
        return gp_method()
    if name == "mlp":
        return mlp_method()
    if name in BEAM_VARIANTS:
        intercept, matched = BEAM_VARIANTS[name]
        return beam_method(name, intercept=intercept, matched=matched)
    if name in ("ours", "ours_no_cp", PAPER_SETTINGS) or name.startswith("ours_K"):
        return beam_method(name)
    if name == ORACLE:
        return oracle_mass_method()
    known = (*METHODS, PAPER_SETTINGS, FLAGSHIP, *FLAGSHIP_ABLATIONS, *BEAM_VARIANTS)
    raise ValueError(f"unknown method {name!r} (one of {', '.join(known)})")
