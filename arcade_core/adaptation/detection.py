"""Declaring changepoints from the beam: a windowed posterior probability and a refractory rule.

Each hypothesis of the beam (Sec. III-B, Algorithm 1) is a changepoint path ``c_{1:k}``
and records the step of its newest changepoint (``BeamState.last_changepoint``). With
``AdaptationConfig.score = "joint"`` the weights ``w_h = softmax(L_{k,h})`` (Eq. 10) are
the exact posterior of the paths the beam keeps (Eq. 7 accumulating the joint
log-probability), so

    ``P_k(m) = sum_h w_h [k - m < last_h <= k]``

is the posterior probability that the newest changepoint lies within the last ``m``
steps, i.e. that the regime changed at one of the steps ``k - m + 1, ..., k``
(:func:`changepoint_probability_within`). A change that needs a few observations to show
is dated back to its step by the beam (its hypotheses branched there) and keeps
``P_k(m)`` up while it is in the window. :func:`declare` turns such a probability into
declarations: one when it reaches a threshold, then none for a refractory period. A change
dated to step ``s`` keeps ``P_k(m)`` up at most until step ``s + m - 1``, so with
``refractory_steps >= m - 1`` it is declared once (unless the beam re-dates it later).

With ``score = "algorithm1"`` the same functions apply, but the weights are not a
posterior (the data term counts twice, see :func:`arcade_core.adaptation.update`), so
``P_k(m)`` is not the probability of a change: a changepoint branch outranks its sibling
from a likelihood ratio of ``sqrt((1 - pi) / pi)`` on, and in the tests' stationary
sequences the same rule raised false alarms on that beam and none on the ``"joint"`` one.

The detector of :func:`detection_step` may learn blocks of ``b`` transitions instead of
single ones (``DetectionConfig.block``): residuals computed from estimated states carry the
estimate's error as a difference ``e_{k+1} - e_k``, which a block's sum cancels but for its
two ends, while a change adds up over the block.

All functions are pure and jit/vmap friendly; ``m``, ``threshold``, ``refractory_steps``
and ``block`` may be traced.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from arcade_core.adaptation.beam import step
from arcade_core.adaptation.config import AdaptationConfig
from arcade_core.adaptation.state import BeamState, init

#: ``Detector.last_declared`` before the first declaration.
NO_DECLARATION = -1


class Detector(NamedTuple):
    """State of :func:`declare`.

    Attributes:
        last_declared: ``()`` int32, step of the latest declaration
            (:data:`NO_DECLARATION`: none yet).
        count: ``()`` int32, declarations so far.
    """

    last_declared: Array
    count: Array


def init_detector() -> Detector:
    """A :class:`Detector` that has declared nothing."""
    return Detector(
        last_declared=jnp.full((), NO_DECLARATION, jnp.int32), count=jnp.zeros((), jnp.int32)
    )


def _recent(beam: BeamState, m: ArrayLike) -> Array:
    """``(K,)`` bool: the hypothesis' newest changepoint is one of the last ``m`` steps."""
    last = beam.last_changepoint
    return (last >= 0) & (last > beam.step - jnp.asarray(m, jnp.int32))


def changepoint_probability_within(beam: BeamState, m: ArrayLike) -> Array:
    """``()`` posterior probability that the newest changepoint lies within the last ``m``
    steps: ``sum_h w_h [k - m < last_h <= k]`` with the Eq. 10 weights ``w_h =
    softmax(L_{k,h})`` and ``k = beam.step``.

    An exact posterior (over the paths the beam keeps) with ``AdaptationConfig.score =
    "joint"``. ``m = 1`` gives the weight of the hypotheses that took ``c_k = 1`` at the
    latest step (``UpdateInfo.cp_mass``); ``m <= 0`` gives 0.
    """
    w = jax.nn.softmax(beam.log_scores)
    return jnp.sum(jnp.where(_recent(beam, m), w, 0.0))


def dated_changepoint_within(beam: BeamState, m: ArrayLike) -> Array:
    """``()`` int32, the most probable step of the newest changepoint among the last ``m``
    steps (``-1`` when no hypothesis has one there).

    The posterior mass of "the newest changepoint is at step ``s``" is ``sum_h w_h
    [last_h = s]`` (Eq. 10 weights); ties go to the later step.
    """
    w = jax.nn.softmax(beam.log_scores)
    last = beam.last_changepoint
    recent = _recent(beam, m)
    same = last[:, None] == last[None, :]
    mass = jnp.sum(jnp.where(same & recent[None, :], w[None, :], 0.0), axis=1)
    mass = jnp.where(recent, mass, -1.0)
    # The largest mass; among equal ones the later step (-1 when nothing is recent).
    return jnp.max(jnp.where(recent & (mass == jnp.max(mass)), last, -1)).astype(jnp.int32)


def declare(
    detector: Detector,
    prob: ArrayLike,
    step: ArrayLike,
    threshold: ArrayLike,
    refractory_steps: ArrayLike,
    dated: ArrayLike | None = None,
) -> tuple[Detector, Array, Array]:
    """Declare a changepoint when ``prob >= threshold``, unless one was declared within the
    last ``refractory_steps`` steps.

    A declaration at step ``s`` suppresses declarations at steps ``s + 1, ..., s +
    refractory_steps`` (``0``: none suppressed); the first step at which one can be
    declared again is ``s + refractory_steps + 1``. A NaN ``prob`` never declares.

    Args:
        detector: state of the previous calls (:func:`init_detector` at first).
        prob: ``()`` probability of a recent change, e.g.
            :func:`changepoint_probability_within`.
        step: ``()`` int, the current step (``BeamState.step``); steps must not decrease.
        threshold: ``()`` declaration threshold on ``prob``.
        refractory_steps: ``()`` int >= 0.
        dated: optional ``()`` int, the step the change is dated to (e.g.
            :func:`dated_changepoint_within`); ``step`` when None.

    Returns:
        ``(detector, declared, dated_step)``: the new state, ``()`` bool, and ``()`` int32
        ``dated`` (or ``step``) when declared, ``-1`` otherwise.
    """
    step = jnp.asarray(step, jnp.int32)
    last = detector.last_declared
    free = (last == NO_DECLARATION) | (step - last > jnp.asarray(refractory_steps, jnp.int32))
    declared = (jnp.asarray(prob) >= threshold) & free
    when = step if dated is None else jnp.asarray(dated, jnp.int32)
    new = Detector(
        last_declared=jnp.where(declared, step, last).astype(jnp.int32),
        count=detector.count + declared.astype(jnp.int32),
    )
    return new, declared, jnp.where(declared, when, -1).astype(jnp.int32)


# --------------------------------------------------------------------------- a detector


class DetectionConfig(NamedTuple):
    """A changepoint detector: a beam of its own, scored as the exact joint, and the
    declaration rule.

    The learner that the controller flies keeps its knobs (chosen by prediction error);
    the detector runs a second beam on the same features and residuals with knobs chosen by
    detection quality (``arcade eval changepoints``), so what is declared is
    not what happens to help the prediction.

    Attributes:
        beam: its :class:`~arcade_core.adaptation.AdaptationConfig`; ``score`` should be
            ``"joint"`` (the weights are then a posterior), ``sigma2`` is ignored (see
            ``noise_scale``).
        noise_scale: ``(d,)`` calibrated per-output factor on the observation noise that
            the learner is given (``sigma_j^2`` of the step): what the residuals of flights
            without a change show beyond it (model error, a payload's swing). ``inf``
            leaves an output out of the detector.
        tracking: rate ``a`` in ``[0, 1)`` of the online noise tracking: the factor is
            multiplied by ``max(1, r_j)`` where ``r_j`` is an exponential average (rate
            ``a``) of the squared innovations of output ``j`` over their predicted variance;
            ``0`` turns it off.
        window: ``m`` of :func:`changepoint_probability_within`, in updates of the
            detector's beam (blocks, see ``block``).
        threshold: declaration threshold on that probability.
        refractory_steps: of :func:`declare`, in transitions learned.
        block: ``b >= 1`` (default 1: every transition): the beam learns the sum of ``b``
            consecutive transitions learned, ``(sum z_k, sum delta_k)``, once every ``b``
            of them, and decides only then. The decoder is linear in the features
            (Eq. 4), so a block obeys the same ``theta``; what it changes is the noise.
            A residual computed from estimated states carries the estimate's error twice,
            ``e_{k+1} - e_k`` (a lag-one autocorrelation near ``-1/2``), so in a block's
            sum that error telescopes to its two ends while a change of ``theta`` adds up
            ``b`` times. The block's noise is the sum of its transitions' noise times
            ``noise_scale``, so a block needs its own scale (``arcade eval
            changepoints`` tunes it with ``b``).
        whiten: ``c`` in ``[0, 1)`` (default 0: off): generalised least squares for that
            noise. A residual whose noise is moving-average, ``eps_k - c eps_{k-1}``, obeys
            ``delta~_k = theta z~_k + eps_k`` with white ``eps`` after the inverse filter
            ``x~_k = x_k + c x~_{k-1}`` applied to the features and the residuals alike
            (``theta`` is constant within a segment, Eq. 4); the per-transition noise
            ``sigma^2`` becomes ``sigma^2 / (1 + c^2)``. A lag-one autocorrelation of
            ``-0.49`` is ``c = 0.82``. The filter runs over the transitions learned,
            before the blocks.
        energy_outputs: ``(d,)`` weights (default 0: off) of the outputs whose
            innovation energy inflates the noise of the watched ones: ``h``, an
            exponential average (rate ``energy_rate``) of ``sum_j w_j (delta_j -
            theta_0 z)_j^2 / sigma_j^2 / sum_j w_j`` (the residual the offline decoder
            leaves, over the learner's noise), multiplies the noise by ``1 + energy_gain
            max(0, h - 1)``. For outputs the detector does not watch (an infinite
            ``noise_scale``): a payload swinging on its cable pulls the vehicle sideways
            as much as it changes the vertical force, so while the horizontal residuals
            are large the vertical ones are discounted, while a release, a step of the
            vertical force, shows in the vertical residuals first. ``h`` is taken before
            each update (the transitions before the current one) and is computed from the
            features and residuals as given, before the whitening.
        energy_gain: ``kappa >= 0`` above (0: off).
        energy_rate: rate of ``h`` in ``(0, 1]``.
    """

    beam: AdaptationConfig
    noise_scale: ArrayLike
    tracking: ArrayLike
    window: ArrayLike
    threshold: ArrayLike
    refractory_steps: ArrayLike
    block: ArrayLike = 1
    whiten: ArrayLike = 0.0
    energy_outputs: ArrayLike = 0.0
    energy_gain: ArrayLike = 0.0
    energy_rate: ArrayLike = 0.2


class DetectionState(NamedTuple):
    """State of :func:`detection_step`: the detector's beam, its declarations, the tracked
    noise ratio ``r`` (``(d,)``, 1 at first), and the block being summed.

    Attributes:
        beam, detector, noise_ratio: as above.
        block_z: ``(l,)`` sum of the features of the transitions of the current block.
        block_delta: ``(d,)`` sum of their residuals.
        block_noise: ``(d,)`` sum of their calibrated noise variances.
        filled: ``()`` int32, transitions in the current block.
        steps: ``()`` int32, transitions learned so far (what declarations are dated in).
        probability: ``()`` the probability of the latest block (held between blocks).
        white_z: ``(l,)`` the filtered features of the latest transition learned
            (``DetectionConfig.whiten``; zeros at first).
        white_delta: ``(d,)`` its filtered residuals.
        energy: ``()`` the innovation energy ``h`` of ``DetectionConfig.energy_outputs``
            (1 at first).
    """

    beam: BeamState
    detector: Detector
    noise_ratio: Array
    block_z: Array
    block_delta: Array
    block_noise: Array
    filled: Array
    steps: Array
    probability: Array
    white_z: Array
    white_delta: Array
    energy: Array


class Detection(NamedTuple):
    """What one :func:`detection_step` returns (all ``()``): the probability that a
    changepoint lies within the window, whether one is declared now, and the step it is
    dated to (``-1`` unless declared)."""

    probability: Array
    declared: Array
    dated: Array


def init_detection(theta0: ArrayLike, config: DetectionConfig) -> DetectionState:
    """A detector at the offline prior ``theta0`` (``(d, l)``) that has declared nothing;
    ``config.beam.K`` must be a Python int."""
    theta0 = jnp.asarray(theta0)
    d, l = theta0.shape
    beam = init(theta0, config.beam._replace(sigma2=jnp.ones(d, theta0.dtype)))
    zero = jnp.zeros((), jnp.int32)
    return DetectionState(
        beam,
        init_detector(),
        jnp.ones(d, theta0.dtype),
        block_z=jnp.zeros(l, theta0.dtype),
        block_delta=jnp.zeros(d, theta0.dtype),
        block_noise=jnp.zeros(d, theta0.dtype),
        filled=zero,
        steps=zero,
        probability=jnp.zeros((), theta0.dtype),
        white_z=jnp.zeros(l, theta0.dtype),
        white_delta=jnp.zeros(d, theta0.dtype),
        energy=jnp.ones((), theta0.dtype),
    )


def detection_step(
    state: DetectionState,
    z: ArrayLike,
    delta: ArrayLike,
    sigma2: ArrayLike,
    learn: ArrayLike,
    config: DetectionConfig,
) -> tuple[DetectionState, Detection]:
    """One observation ``(z_k, delta_k)`` with the learner's noise ``sigma2`` (``(d,)``):
    filtered (``config.whiten``) and added to the current block; when the block holds
    ``config.block`` transitions the detector's beam learns their sum (Algorithm 1 with
    ``config.beam``; the Eq. 8 noise ``sum_k sigma_{j,k}^2 noise_scale_j max(1, r_j) /
    (1 + c^2)``), then :func:`declare` on :func:`changepoint_probability_within`. A
    declaration is dated to the first transition of the block the change is dated to,
    counted in transitions learned (with ``block = 1``, the beam's own step). ``learn =
    False`` (or a non-finite input) leaves the state as it was and declares nothing."""
    beam = state.beam
    dtype = beam.means.dtype
    z = jnp.asarray(z, dtype)
    delta = jnp.asarray(delta, dtype)
    learn = jnp.asarray(learn, bool) & jnp.all(jnp.isfinite(delta)) & jnp.all(jnp.isfinite(z))
    size = jnp.asarray(config.block, jnp.int32)
    # Innovation energy of the outputs named (before the whitening), taken before this update.
    weights = jnp.broadcast_to(jnp.asarray(config.energy_outputs, dtype), delta.shape)
    lean = (delta - beam.prior_mean @ z) ** 2 / jnp.asarray(sigma2, dtype)
    total = jnp.sum(weights)
    q_energy = jnp.sum(jnp.where(weights > 0, weights * lean, 0.0)) / jnp.maximum(total, 1e-30)
    rate = jnp.asarray(config.energy_rate, dtype)
    energy = jnp.where(
        learn & (total > 0), (1.0 - rate) * state.energy + rate * q_energy, state.energy
    )
    inflate = 1.0 + jnp.asarray(config.energy_gain, dtype) * jnp.maximum(state.energy - 1.0, 0.0)
    c = jnp.asarray(config.whiten, dtype)
    white_z = jnp.where(learn, z + c * state.white_z, state.white_z)
    white_delta = jnp.where(learn, delta + c * state.white_delta, state.white_delta)
    z, delta = white_z, white_delta
    base_k = (
        jnp.asarray(sigma2, dtype)
        * jnp.asarray(config.noise_scale, dtype)
        * inflate
        / (1.0 + c * c)
    )
    block_z = state.block_z + jnp.where(learn, z, 0.0)
    block_delta = state.block_delta + jnp.where(learn, delta, 0.0)
    block_noise = state.block_noise + jnp.where(learn, base_k, 0.0)
    filled = state.filled + learn.astype(jnp.int32)
    steps = state.steps + learn.astype(jnp.int32)
    full = learn & (filled >= size)

    base = block_noise
    noise = base * jnp.maximum(1.0, state.noise_ratio)
    # Outputs left out (an infinite scale) carry no evidence: a huge finite variance.
    noise = jnp.where(jnp.isfinite(noise), noise, jnp.asarray(1e12, dtype))
    # One projection of the beam serves the prediction and the update (Algorithm 1 step).
    new, pred, _ = step(beam, block_z, block_delta, config.beam._replace(sigma2=noise))
    new = jax.tree.map(lambda a, b: jnp.where(full, a, b), new, beam)
    # Innovation over its predicted variance at the calibrated (untracked) noise.
    q = (block_delta - pred.mean) ** 2 / (
        pred.param + pred.between + jnp.where(jnp.isfinite(base), base, 1.0)
    )
    a = jnp.asarray(config.tracking, dtype)
    ratio = jnp.where(full, (1.0 - a) * state.noise_ratio + a * q, state.noise_ratio)
    prob = jnp.where(
        full,
        changepoint_probability_within(new, config.window),
        jnp.where(learn, state.probability, 0.0),
    )
    # The beam's step b is the block of transitions (b - 1) * block + 1, ..., b * block.
    dated_block = dated_changepoint_within(new, config.window)
    dated = jnp.where(dated_block > 0, (dated_block - 1) * size + 1, dated_block)
    detector, declared, when = declare(
        state.detector,
        jnp.where(full, prob, jnp.nan),
        steps,
        config.threshold,
        config.refractory_steps,
        dated.astype(jnp.int32),
    )

    def emptied(x):
        return jnp.where(full, jnp.zeros_like(x), x)

    new_state = DetectionState(
        new,
        detector,
        ratio,
        block_z=emptied(block_z),
        block_delta=emptied(block_delta),
        block_noise=emptied(block_noise),
        filled=jnp.where(full, 0, filled).astype(jnp.int32),
        steps=steps,
        probability=prob,
        white_z=white_z,
        white_delta=white_delta,
        energy=energy,
    )
    return new_state, Detection(prob, declared & full, when)
