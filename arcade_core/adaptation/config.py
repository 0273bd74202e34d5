"""Hyperparameters of Algorithm 1 and the Appendix D presets (Eq. 5 tempering, Eq. 9 prior).

:class:`AdaptationConfig` is a pytree whose leaves are the numeric hyperparameters (``K``
included, as in a plain named tuple) and whose ``score`` is static (part of the tree
structure, like a ``static_argnames`` argument of ``jit``): a config can be passed through
``jit``, ``vmap`` and ``scan`` as it is, and a change of ``score`` retraces.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
from jax.typing import ArrayLike

#: Hypothesis scores of :func:`arcade_core.adaptation.update` (see ``AdaptationConfig.score``).
SCORES = ("algorithm1", "joint")


class AdaptationConfig(NamedTuple):
    """Hyperparameters of Algorithm 1 (Appendix D, "Online Inference" tables).

    ``K`` (beam size) must be a Python int for :func:`init` only (every other function
    reads it from the state's shapes, so under ``jit`` it may be a traced leaf like the
    others); the others may be Python floats or arrays and are traced under ``jit``.
    ``beta`` is the temperature of Eq. 5 (``gamma = beta^2`` on a changepoint).
    ``sigma2`` is a scalar or per-output ``(d,)`` observation-noise variance.

    ``prior_floor`` (``rho`` in ``[0, 1]``, default ``0``: Eq. 5 as written) re-injects
    part of the offline prior ``p_0 = N(theta_0, tau^2 I)`` at a changepoint: the tempered
    prior is the normalised product ``p(theta | D)^gamma p_0(theta)^(rho (1 - gamma))``
    (a power prior, App. "tempered priors", combined geometrically with the offline
    prior), i.e. precision ``P = gamma Sigma^{-1} + c I`` and mean ``P^{-1} (gamma
    Sigma^{-1} mu + c theta_0)`` with ``c = rho (1 - gamma) / tau^2``. With ``rho = 1`` a
    tempered prior is never more diffuse than the offline prior ``tau^2 I`` (every
    posterior then satisfies ``Sigma <= tau^2 I``), which is what the proof of Lemma 2
    assumes; without it, repeated changepoints inflate the covariance geometrically
    (``beta^-2`` per changepoint) in directions the data do not excite. As ``beta -> 0``
    the changepoint prior becomes the offline prior itself (a full reset, as in
    run-length changepoint detection). Needs ``tau2 > 0``.

    ``score`` (static, one of :data:`SCORES`) is how a candidate ``c_k`` of a hypothesis
    is scored (:func:`arcade_core.adaptation.update`); with ``l_c = log p(delta_k | z_k,
    c_k = c)`` (Eq. 8) and ``p_1`` the Eq. 9 posterior:

    - ``"algorithm1"`` (default): Algorithm 1 as written, ``L + l_c + log p(c_k | .)``
      with the Eq. 9 *posterior* ``p(c_k = 1 | .) = p_1``, so the data term counts twice;
    - ``"joint"``: the joint log-probability of the path, ``L + l_c + log p(c_k)`` with
      the prior ``p(c_k = 1) = pi`` (Eq. 7 with its own conditioning ``c_{1:k-1}, x_{1:k},
      u_{1:k}``, which excludes ``delta_k``; App. "Changepoint Scoring"). The beam weights
      are then the exact posterior of the changepoint paths that the beam keeps.

    ``nu`` (default ``inf``: Eq. 8 as written) gives the hypothesis scores heavy tails: the
    Eq. 8 likelihood of each output becomes a Student-t with ``nu`` degrees of freedom
    and squared scale the Gaussian's predictive variance, so that a single outlier (a
    payload's jolt, a glitch of the state estimate) costs a no-change path ``log(1 + r^2 /
    (nu s))`` instead of ``r^2 / (2 s)`` and is not taken for a change of regime, while a
    lasting shift still accumulates evidence step after step. Only the scores (Eqs. 7-9)
    and the evidence change; the posterior update stays the conjugate Eq. 6. ``nu`` is
    static like ``score`` (a Python float; a change retraces), so the default step is the
    Gaussian one and pays nothing for the option.
    """

    K: int
    pi: ArrayLike
    beta: ArrayLike
    tau2: ArrayLike
    sigma2: ArrayLike
    prior_floor: ArrayLike = 0.0
    score: str = "algorithm1"
    nu: ArrayLike = math.inf


_LEAVES = AdaptationConfig._fields[:-2]  # every field but ``score`` and ``nu``
_N = len(_LEAVES)
_KEYS = tuple(jax.tree_util.GetAttrKey(name) for name in _LEAVES)


def _flatten(cfg: AdaptationConfig):
    return cfg[:_N], cfg[_N:]


def _flatten_with_keys(cfg: AdaptationConfig):
    return tuple(zip(_KEYS, cfg[:_N])), cfg[_N:]


def _unflatten(static: tuple[str, float], leaves) -> AdaptationConfig:
    return AdaptationConfig(*leaves, *static)


# ``score`` and ``nu`` are auxiliary data, never leaves: a string cannot be traced, and
# ``nu`` chooses the likelihood's form. The flatten below slices the tuple (the keyed one
# is used only for key paths), which keeps a jitted call about as cheap as with a plain
# named tuple.
jax.tree_util.register_pytree_with_keys(AdaptationConfig, _flatten_with_keys, _unflatten, _flatten)


def score_of(config: AdaptationConfig) -> str:
    """``config.score``, checked against :data:`SCORES` (a static Python string)."""
    score = config.score
    if score not in SCORES:
        raise ValueError(f"AdaptationConfig.score must be one of {SCORES}, not {score!r}")
    return score


def quadrotor_config() -> AdaptationConfig:
    """Quadrotor preset (Appendix D, quadrotor "Online Inference" table), with the offline
    prior re-injected at changepoints (``prior_floor = 1``), which keeps every tempered
    prior at least as precise as the offline prior, as Lemma 2's proof assumes: the
    swinging payload makes changepoints frequent, and repeated tempering would otherwise
    inflate the covariance beyond the prior in weakly excited directions."""
    return AdaptationConfig(K=15, pi=0.05, beta=0.997, tau2=0.1, sigma2=0.1, prior_floor=1.0)


def cartpole_config() -> AdaptationConfig:
    """Cartpole preset (Appendix D, cartpole "Online Inference" table)."""
    return AdaptationConfig(K=5, pi=0.05, beta=0.9, tau2=0.1, sigma2=0.1)


def nu_of(config: AdaptationConfig) -> float:
    """``config.nu`` as the static Python float it must be (``inf``: Gaussian), checked."""
    nu = float(config.nu)
    if not nu > 0.0:
        raise ValueError(f"AdaptationConfig.nu must be positive (inf: Gaussian), not {nu!r}")
    return nu
