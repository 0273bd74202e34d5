"""The controller service's control steps, traced once and kept on disk (:mod:`arcade_io.traced`).

:func:`build_steps` makes what :mod:`services.controller` calls per state: the plain step
of the nominal MPC (no model yet, or none fresh enough) and, with a weights file, the
method's step on the ``model`` message (the beam held as the message's moment-matched
posterior, :func:`arcade_control.stack.one_hypothesis_beam`), either plain
(:func:`arcade_control.step.make_controller_step`) or advanced
(:func:`arcade_control.step.make_advanced_step`: ``feedback`` answers a state from the
plan prepared with an earlier model message, ``prepare`` makes the next one). Learning is
the adapter's: the steps leave the beam to the messages, and only the flagship's or L1's
L1 augmentation state comes back from a step (the rest of the learner is the service's
constant ``learner0``). Every step returns its input with a finite-solution flag
(:func:`arcade_control.stack.with_finite_flag`).

Imported by the controller's ``setup``, after the precision is set: it imports JAX.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from arcade_control.methods import make_method
from arcade_control.stack import (
    controller_learner,
    controller_method,
    one_hypothesis_beam,
    stack_knobs,
    with_finite_flag,
)
from arcade_control.step import (
    Carry,
    make_advanced_step,
    make_controller_step,
    method_mpc_config,
    planned_carry,
)
from arcade_core import adaptation
from arcade_io.traced import Traced, load_or_trace


class ControlSteps(NamedTuple):
    """The traced steps and what they start from (``learned``, ``feedback`` and
    ``prepare`` are ``None`` where they are not used)."""

    carry: Any  # the carry before the first step (a PlannedCarry when advanced)
    learner0: Any  # the method's learner (None: no weights file)
    theta0: np.ndarray | None  # the prior's decoder mean (d, l) and covariance (d, l, l)
    cov0: np.ndarray | None
    nominal: Traced  # (Carry, x, u_sent, k, x_ref_all, u_ref_all) -> (Carry, [u, ok])
    learned: Traced | None  # plain: (carry, x, u_sent, k, theta, cov, refs...)
    feedback: Traced | None  # advanced: (carry, x, u_sent, k, post_plan, post, refs...)
    prepare: Traced | None  # advanced: (carry, k, period_s, post, refs...) -> carry


def _without_learner(step):
    """``step`` returning its new carry without the learner, and no diagnostics: what the
    service keeps of a control step, as plain arrays (storable, :mod:`arcade_io.traced`)."""

    def plain(*args):
        new, u, _ = step(*args)
        # What a method keeps across steps in the service: the flagship's or L1's L1 state.
        return new._replace(learner=getattr(new.learner, "l1", None)), u

    return plain


def _with_beam(learner, theta, cov):
    return learner._replace(beam=one_hypothesis_beam(learner.beam, theta, cov))


def build_steps(
    cfg: Any,
    method_name: str,
    weights: Path,
    refs: tuple[Any, Any],
    delay_s: float,
    advanced: bool,
    rate_hz: float,
    u0: Any,
) -> ControlSteps:
    """The steps of method ``method_name`` (a weights file at ``weights``; without one,
    only the nominal step) on the MPC ``cfg``, for the reference ``refs`` = ``(x_ref_all,
    u_ref_all)``, a link delay ``delay_s`` compensated, ``advanced`` (with weights) at a
    control period of ``1 / rate_hz``; ``u0``: the input before the first step (hover).
    Besides code the traced steps close over the link delay and the method only, which
    key them on disk."""
    dtype = u0.dtype
    N = cfg.N
    # The in-process per-step update, with learning left to the adapter.
    no_learn = {"learn": lambda learner, x_prev, u_prev, x: learner}
    step_nominal = make_controller_step(
        make_method("nominal")._replace(**no_learn), cfg, delay_s=delay_s
    )
    learner_nominal = jnp.zeros((), dtype)
    x0 = np.zeros(13, np.dtype(dtype))
    key = f"link_delay={delay_s!r} method={method_name}"
    carry = Carry(
        learner_nominal, jnp.broadcast_to(u0, (N, 4)), u0, jnp.zeros(13, dtype), jnp.zeros((), bool)
    )
    nominal = load_or_trace(
        "controller_nominal",
        _without_learner(with_finite_flag(step_nominal)),
        (carry, x0, u0, 0, *refs),
        key,
    )
    if not weights.is_file():
        return ControlSteps(carry, None, None, None, nominal, None, None, None)
    learner0 = controller_learner(weights, dtype, method_name)
    method = controller_method(method_name)
    method_cfg = method_mpc_config(cfg, method_name, stack_knobs(method_name))
    # The prior's mean and covariance, in one compiled call (not op by op).
    theta0, cov0 = jax.jit(
        lambda beam: (adaptation.marginal_decoder(beam)[0], beam.covariances[0])
    )(learner0.beam)
    theta0 = np.asarray(theta0)
    d, l = theta0.shape  # the flagship's features carry an intercept
    cov0 = np.broadcast_to(np.asarray(cov0), (d, l, l)).copy()
    post0 = (theta0.astype(x0.dtype), cov0.astype(x0.dtype))
    carry = carry._replace(learner=learner0)
    if not advanced:
        step = make_controller_step(method, method_cfg, delay_s=delay_s)

        def learned(carry, x, u_sent, k, theta, cov, x_ref_all, u_ref_all):
            carry = carry._replace(learner=_with_beam(carry[0], theta, cov))
            return step(carry, x, u_sent, k, x_ref_all, u_ref_all)

        traced = load_or_trace(
            "controller_learned",
            _without_learner(with_finite_flag(learned)),
            (carry, x0, u0, 0, *post0, *refs),
            key,
        )
        return ControlSteps(carry, learner0, theta0, cov0, nominal, traced, None, None)
    # The plan made with the model message of its time, corrected for the newest one.
    feedback, prepare = make_advanced_step(method, method_cfg, delay_s=delay_s)

    def learned_feedback(carry, x, u_sent, k, post_plan, post, x_ref_all, u_ref_all):
        learner = carry[0]
        carry = carry._replace(learner=_with_beam(learner, *post_plan))
        now = _with_beam(learner, *post)
        return feedback(carry, x, u_sent, k, x_ref_all, u_ref_all, learner_now=now)

    def learned_prepare(carry, k, period_s, post, x_ref_all, u_ref_all):
        carry = carry._replace(learner=_with_beam(carry[0], *post))
        new = prepare(carry, k, period_s, x_ref_all, u_ref_all)
        return new._replace(learner=getattr(new.learner, "l1", None))

    carry = planned_carry(carry, method_cfg)
    period = np.asarray(1.0 / rate_hz, x0.dtype)
    return ControlSteps(
        carry,
        learner0,
        theta0,
        cov0,
        nominal,
        None,
        load_or_trace(
            "controller_feedback",
            _without_learner(with_finite_flag(learned_feedback)),
            (carry, x0, u0, 0, post0, post0, *refs),
            key,
        ),
        load_or_trace("controller_prepare", learned_prepare, (carry, 0, period, post0, *refs), key),
    )
