"""Changepoint-aware beam Bayesian linear regression for the decoder (Sec. III, Algorithm 1).

The residual model is ``delta_k = theta z_k + eps_k`` with ``eps_k ~ N(0, diag(sigma^2))``
(Eq. 4). Every output row ``theta^j`` has a Gaussian posterior per hypothesis ``h`` of a
beam of ``K`` changepoint histories. Equation numbers follow the paper's source: Eq. 5
tempering, Eq. 6 posterior, Eq. 7 score recursion (Lemma 3), Eq. 8 marginal likelihood,
Eq. 9 changepoint posterior, Eq. 10 beam predictive. One step of Algorithm 1:

1. predict with the beam mixture (Eq. 10, Sec. IV ``sigma_tot``);
2. for every hypothesis and both branches ``c_k in {0, 1}`` (tempering ``gamma in
   {1, beta^2}``, Eq. 5) evaluate the marginal likelihood (Eq. 8), the changepoint
   posterior (Eq. 9) and the candidate score (Eq. 7, Lemma 3; see "Scores" below);
3. keep the top-``K`` of the ``2K`` candidates and apply the posterior update (Eq. 6)
   to the survivors only. The update of a candidate depends on its parent and branch
   alone, so pruning before updating gives the same beam at half the work.

Scores (``AdaptationConfig.score``, static). With ``l_c = log p(delta_k | z_k, c_k = c)``
(Eq. 8) a candidate ``c`` of a hypothesis with score ``L`` scores

- ``"algorithm1"`` (default; Algorithm 1 line by line): ``L + l_c + log p(c | delta_k, .)``
  with the Eq. 9 *posterior*, so the data term enters twice;
- ``"joint"``: ``L + l_c + log p(c)`` with the prior ``p(c = 1) = pi``, i.e. Eq. 7 with
  its own conditioning (``c_{1:k-1}, x_{1:k}, u_{1:k}``, not ``delta_k``): the exact joint
  log-probability ``log p(delta_{1:k}, c_{1:k} | x_{1:k}, u_{1:k})`` of the path, whose
  softmax over the beam is the posterior of the paths it keeps.

With the likelihood ratio ``Lambda_k = exp(l_1 - l_0)`` a changepoint branch outranks its
no-change sibling when ``Lambda_k > sqrt((1 - pi) / pi)`` under ``"algorithm1"`` (4.36 for
``pi = 0.05``) but only when ``Lambda_k > (1 - pi) / pi`` (19) under ``"joint"``.
:mod:`.detection` reads a declaration off the ``"joint"`` posterior: the probability that
the newest changepoint lies within the last ``m`` steps, thresholded with a refractory
period.

Optionally (``AdaptationConfig.prior_floor``) a changepoint re-injects the offline prior
``N(theta_0, tau^2 I)``: the tempered prior is ``p(theta | D)^gamma p_0(theta)^(rho (1 -
gamma))``, so it keeps at least the offline prior precision ``tau^-2 I`` (the assumption
in the proof of Lemma 2, where Eq. 5 alone multiplies the covariance by ``beta^-2`` in
every direction the data do not excite, at every changepoint) and its mean moves towards
``theta_0`` by as much as the posterior is forgotten.

Numerics. Each covariance is carried as a square root ``W`` with ``Sigma = W W^T``
(``BeamState.sqrt_covariances``) and updated with Potter's rank-one square-root form
[Potter 1963], the textbook numerically robust form of the Sherman--Morrison update of
Eq. 6: the covariance stays symmetric positive semi-definite by construction, also in
float32, and the update costs the same ``O(l^2)`` as Sherman--Morrison. The
covariance itself is ``BeamState.covariances``. Eq. 6 shows that ``Sigma^j`` depends on
the prior ``tau^2 I``, the features ``z`` and ``sigma_j^2`` but not on the residuals, so
when all outputs share one noise variance (scalar ``sigma2``, as in both Appendix D
presets) every output has the same covariance: the state then stores one square root per
hypothesis, ``(K, 1, l, l)``, instead of ``d`` identical copies.

Scores are stored shifted by a common constant so that the best one is ``0``
(``log_offset`` keeps the shift): softmax weights (Eq. 10) and top-``K`` pruning are
invariant to the shift, and float32 scores do not lose resolution as the raw cumulative
log-likelihood grows without bound.

Conventions. ``K`` is static and is read from the state's shapes by every function except
:func:`init`; ``score`` is static (auxiliary data of the config's pytree, so changing it
recompiles); all other hyperparameters are traced, so changing them does not recompile.
Step ``k`` counts processed observations (``0`` after :func:`init`). Unused beam slots
(Algorithm 1 line 2 starts with a single hypothesis) carry the prior with a ``-inf``
score: they get zero weight and are displaced by real candidates first.

Layout. :mod:`.config` holds the hyperparameters and the Appendix D presets;
:mod:`.state` the beam (:class:`BeamState`), :func:`init` and what a step returns;
:mod:`.posterior` one hypothesis' regression (Eqs. 4-6 and 8); :mod:`.predictive` the
Eq. 10 mixture and the Sec. IV variance; :mod:`.beam` one step of Algorithm 1 (expand,
score, prune, update); :mod:`.packed` the same step on a few flat arrays for the real-time
loop; :mod:`.detection` the declaration rule. Everything public is importable from
``arcade_core.adaptation``.
"""

from arcade_core.adaptation.beam import step, top_k, update
from arcade_core.adaptation.config import (
    SCORES,
    AdaptationConfig,
    cartpole_config,
    quadrotor_config,
)
from arcade_core.adaptation.detection import (
    Detection,
    DetectionConfig,
    DetectionState,
    Detector,
    changepoint_probability_within,
    dated_changepoint_within,
    declare,
    detection_step,
    init_detection,
    init_detector,
)
from arcade_core.adaptation.packed import (
    PackedBeam,
    make_packed_step,
    pack,
    packed_step,
    unpack,
    unpack_outputs,
)
from arcade_core.adaptation.posterior import posterior_update, state_noise_sigma2
from arcade_core.adaptation.predictive import (
    map_last_changepoint,
    marginal_decoder,
    predict,
    sigma_tot2,
)
from arcade_core.adaptation.state import BeamState, Prediction, UpdateInfo, init

__all__ = [
    "SCORES",
    "AdaptationConfig",
    "BeamState",
    "Detection",
    "DetectionConfig",
    "DetectionState",
    "Detector",
    "PackedBeam",
    "Prediction",
    "UpdateInfo",
    "cartpole_config",
    "changepoint_probability_within",
    "dated_changepoint_within",
    "declare",
    "detection_step",
    "init",
    "init_detection",
    "init_detector",
    "make_packed_step",
    "map_last_changepoint",
    "marginal_decoder",
    "pack",
    "packed_step",
    "posterior_update",
    "predict",
    "quadrotor_config",
    "sigma_tot2",
    "state_noise_sigma2",
    "step",
    "top_k",
    "unpack",
    "unpack_outputs",
    "update",
]
