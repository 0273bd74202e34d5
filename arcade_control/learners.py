"""Each method's adaptive state at take-off, with the knobs it flies with."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from arcade_control.detection import detection_config
from arcade_control.guard import cast as _cast
from arcade_control.guard import make_guard
from arcade_control.knobs import (
    ARCADE_BEAM_BETA,
    BEAM_VARIANTS,
    FIFO,
    FLAGSHIP,
    FLAGSHIP_ABLATIONS,
    MLP_INPUT_STD,
    ORACLE,
    PAPER_SETTINGS,
    RESTARTING,
    TUNED_DEFAULTS,
    base_name,
    knob_owner,
)
from arcade_control.methods import BeamLearner, MassOracle, Restart
from arcade_control.nominal import nominal_params
from arcade_core import adaptation
from arcade_core.baselines import gp, l1, mlp


def no_cp_config(cfg: adaptation.AdaptationConfig) -> adaptation.AdaptationConfig:
    """Ours without changepoints: a single hypothesis that never tempers (Appendix D 5)."""
    return adaptation.AdaptationConfig(
        K=1, pi=0.0, beta=1.0, tau2=cfg.tau2, sigma2=cfg.sigma2, score=cfg.score
    )


def forgetting_config(cfg: adaptation.AdaptationConfig, lam: float) -> adaptation.AdaptationConfig:
    """Bayesian linear regression with exponential forgetting, as a beam: one hypothesis
    that takes the changepoint branch at every step (``pi = 1``), so every step tempers the
    posterior precision by ``lambda = beta^2`` (Eq. 5) before the Eq. 6 update. With
    ``cfg.prior_floor > 0`` the offline prior is re-injected as in the beam (stabilised
    forgetting: the precision never falls below the offline prior's), so the recursion is
    ``P_k = lambda P_{k-1} + rho (1 - lambda) / tau^2 I + z z^T / sigma^2``. The ablation
    that shows what the changepoint beam adds over forgetting (``arcade eval
    changepoints``). The score is the joint one: with a single path it changes nothing,
    and Algorithm 1's Eq. 9 posterior would be ``inf - inf`` at ``pi = 1``."""
    if not 0.0 < lam <= 1.0:
        raise ValueError(f"a forgetting factor lies in (0, 1], not {lam!r}")
    return cfg._replace(K=1, pi=1.0, beta=float(np.sqrt(lam)), score="joint")


def flagship_config(
    name: str, cfg: adaptation.AdaptationConfig, lam: float
) -> adaptation.AdaptationConfig:
    """The learner of the flagship ``arcade`` and of its ablations (``name``) from the
    quadrotor preset ``cfg`` at the flagship's ``sigma^2``: one hypothesis with exponential
    forgetting ``lam`` (:func:`forgetting_config`, the offline prior re-injected as in the
    beam); ``arcade_no_forgetting``: one hypothesis that never tempers
    (:func:`no_cp_config`); ``arcade_beam``: the changepoint beam of the preset, tempered
    by :data:`arcade_control.knobs.ARCADE_BEAM_BETA` (its design before)."""
    if name == "arcade_no_forgetting":
        return no_cp_config(cfg)  # one hypothesis, never tempered nor restarted
    if name == "arcade_beam":
        return cfg._replace(beta=ARCADE_BEAM_BETA)
    return forgetting_config(cfg, lam)


def scale_gp_noise(model: gp.GPModel, scale: float) -> gp.GPModel:
    """``model`` with its noise variances (marginal likelihood, offline) times ``scale``."""
    h = model.hyper
    return model._replace(hyper=h._replace(log_noise_var=h.log_noise_var + np.log(scale)))


def initial_learner(name: str, models, dtype, estimated: bool = False) -> Any:
    """The method's adaptive state at take-off (arrays in ``dtype``); ``estimated``: it
    learns from a state estimate, not the ground truth (the knobs of the flagship's
    changepoint detector, :func:`arcade_control.detection.detection_config`)."""

    def cast(tree):
        return _cast(tree, dtype)

    name = base_name(name)
    if name == "nominal":
        return jnp.zeros((), dtype)
    if name == ORACLE:  # the flight fills in its payload and release step
        return MassOracle(jnp.zeros((), jnp.int32), -jnp.ones((), jnp.int32), jnp.zeros((), dtype))
    tuned = {**TUNED_DEFAULTS, **getattr(models, "closedloop", {})}
    if name == "l1":
        return _l1_state(tuned["l1_cutoff"], tuned["l1_cutoff_rates"], tuned["l1_a_s"], dtype)
    if name == "arcade_no_model":
        return _l1_state(tuned["arcade_l1_cutoff"], 0.0, tuned["arcade_l1_a_s"], dtype)
    guard = make_guard(models, dtype)
    if name == "gp":
        return cast(gp.init(scale_gp_noise(models.gp, tuned["gp_noise_scale"]), FIFO)), guard
    if name == "mlp":
        std = jnp.asarray(MLP_INPUT_STD, dtype)
        return cast(
            mlp.init(
                cast(models.mlp), std[:13], std[13:], capacity=FIFO, learning_rate=tuned["mlp_lr"]
            )
        ), guard
    knobs = knob_owner(name)
    flagship = name == FLAGSHIP or name in FLAGSHIP_ABLATIONS
    cfg = adaptation.quadrotor_config()._replace(sigma2=tuned[f"{knobs}_sigma2"])
    if flagship:
        cfg = flagship_config(name, cfg, tuned["arcade_lambda"])
    else:
        cfg = cfg._replace(beta=tuned[f"{knobs}_beta"])
    if name == PAPER_SETTINGS:  # Appendix D's values, whatever the tuning chose
        cfg = adaptation.quadrotor_config()
    elif name == "ours_no_cp":
        cfg = no_cp_config(cfg)
    elif name.startswith("ours_K"):
        cfg = cfg._replace(K=int(name[len("ours_K") :]))
    vld = cast(models.vld)
    theta0 = vld.theta0
    if flagship or BEAM_VARIANTS.get(name, (False, False))[0]:  # intercept: zero column
        # On the host (exact): jnp.concatenate would compile three operations per process.
        theta0 = np.asarray(theta0)
        theta0 = jax.device_put(
            np.concatenate([theta0, np.zeros((theta0.shape[0], 1), theta0.dtype)], 1)
        )
    beam = adaptation.init(theta0, cfg)  # Algorithm 1 lines 1-2, one compiled call
    traced_cfg = adaptation.AdaptationConfig(
        K=jnp.asarray(cfg.K),
        pi=jnp.asarray(cfg.pi, dtype),
        beta=jnp.asarray(cfg.beta, dtype),
        tau2=jnp.asarray(cfg.tau2, dtype),
        sigma2=jnp.asarray(cfg.sigma2, dtype),
        prior_floor=jnp.asarray(cfg.prior_floor, dtype),
        score=cfg.score,
        nu=cfg.nu,
    )
    zero = jnp.zeros((), dtype)
    learner = BeamLearner(vld, beam, traced_cfg, guard, zero, zero)
    if flagship and name != "arcade_no_l1":  # thrust channel only
        l1_state = _l1_state(tuned["arcade_l1_cutoff"], 0.0, tuned["arcade_l1_a_s"], dtype)
        learner = learner._replace(l1=l1_state)
    if name in RESTARTING:  # the detector at the VLD's prior, the learner's noise
        det = detection_config(dtype=dtype, estimated=estimated)
        scale = jnp.asarray(tuned["arcade_restart_scale"], dtype)
        learner = learner._replace(
            restart=Restart(
                adaptation.init_detection(vld.theta0, det),
                det,
                restart_prior(beam, scale),
                scale,
                traced_cfg.sigma2,
                jnp.asarray(adaptation.quadrotor_config().sigma2, dtype),
                jnp.asarray(-1, jnp.int32),
            )
        )
    return learner


def restart_prior(beam: adaptation.BeamState, scale: Any) -> adaptation.BeamState:
    """``beam`` (at the prior) with its covariances times ``scale``: where the flagship's
    learner restarts at a detected change (:func:`arcade_control.methods.restart_at_change`)."""
    return beam._replace(sqrt_covariances=beam.sqrt_covariances * jnp.sqrt(scale))


def _l1_state(cutoff: float, cutoff_rates: float, a_s: float, dtype) -> l1.L1State:
    """An L1 augmentation at take-off: the rate channel (matched body-rate disturbance) is
    applied when it has a bandwidth."""
    p = nominal_params()
    return l1.init(
        l1.L1Params(
            mass=p.mass,
            gravity=p.gravity,
            rate_tau=p.rate_tau,
            a_s=a_s,
            cutoff_thrust=cutoff,
            cutoff_rates=cutoff_rates if cutoff_rates > 0 else cutoff,
            rotational=cutoff_rates > 0,
        ),
        dtype,
    )


def per_output_noise(learner: BeamLearner) -> BeamLearner:
    """``learner`` with one noise variance per output and one covariance per output row, at
    the prior (Algorithm 1 line 1): what a state estimate's per-component noise needs
    (:func:`arcade_core.adaptation.state_noise_sigma2`). The same beam while all variances
    are equal."""
    cfg, (d, _) = learner.config, learner.vld.theta0.shape
    dtype = learner.beam.means.dtype
    vec = cfg._replace(sigma2=jnp.broadcast_to(jnp.asarray(cfg.sigma2, dtype), (d,)))
    theta0 = learner.beam.prior_mean
    beam = adaptation.init(theta0, vec._replace(K=int(learner.beam.means.shape[0])))
    if learner.restart is not None:  # it restarts to the same layout
        r = learner.restart
        learner = learner._replace(
            restart=r._replace(prior=restart_prior(beam, r.scale), base_sigma2=vec.sigma2)
        )
    return learner._replace(config=vec, beam=beam)
