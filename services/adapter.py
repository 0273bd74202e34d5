"""Adapter service: residuals -> ARCADE update (Algorithm 1) -> decoder posterior.

Subscribes ``state`` and ``setpoint``; publishes ``residual`` and ``model`` for every state,
and an ``event`` (kind ``changepoint``) when the changepoint detector declares one: a second
beam beside the learner, on the same features, residuals and noise, scored as the exact
joint and tuned for detection (:func:`arcade_control.detection.detection_config`,
:func:`arcade_core.adaptation.detection_step`), declares when the posterior probability of a
changepoint within its window reaches the threshold, then waits a refractory period. The
event carries that probability (``cp_prob``), the step the change is dated to
(``changepoint_step``) and the stamp of that transition's newer state
(``changepoint_stamp``). The learner's own flag (its MAP path gained a changepoint: with the
knobs it flies, a forgetting step more than a detection) stays in the ``residual`` message.
A restarted adapter's detector starts again from the prior.

Per state ``k`` (after the first): the transition ``(x_{k-1}, u_{k-1}, x_k)`` with
``u_{k-1}`` the setpoint answering state ``k-1`` (lockstep: waited for; realtime: see below)
gives the residual ``delta = x_k - f_nom(x_{k-1}, u_{k-1})``. At the default 20 Hz this is
exactly the in-process evaluation's learning step (``benchmarks.quadrotor_closedloop``,
method ``ours``: paper quadrotor preset, the VLD of the weights file, features clipped to
their training range; ``--method arcade``: the flagship's model, those features plus an
intercept at its stack knobs ``arcade_control.stack.STACK_ARCADE_KNOBS``, the controller
running its L1 augmentation; its learner runs the changepoint detector inside its step and
restarts at a declared change, and those declarations are the events (the same detector, on
the VLD's features and the calibrated noise); ``--method l1``: ours' model, which L1's
controller does not use); at other rates the same update uses the nominal RK4 step over the
elapsed time (the VLD was trained at the 0.05 s control period, so other rates adapt an
approximate residual). The beam-marginal prediction of ``delta`` before the update (Eq. 10)
is published as ``residual`` (normalised units, the variance split of Sec. IV, the Eq. 9
changepoint probability). The ``model`` message carries the moment-matched beam-marginal
decoder posterior (mean and per-row covariance) and ``sigma_tot^2`` at the newest state, in
normalised units. Transitions that end in a state predicted through a mocap dropout are not
learned from, nor transitions whose input the vehicle did not apply: in realtime the vehicle
follows the controller only from the mission ``start`` command on (before it the simulator's
pre-roll or PX4 holds the vehicle, while the controller already streams setpoints), and not
while the vehicle link does not fly them: from a ``failsafe`` event (the PX4 bridge emits
one on every exit from offboard, operator commands included) until ``failsafe_cleared`` (the
link flies the setpoints again: the bridge emits it whenever offboard is engaged) or a new
``start``. A ``start`` that repeats the mission's ``t0`` (the clock re-sent to a restarted
controller) is no new mission and does not resume learning. An adapter that (re)joins a
running mission is sent its clock too, with ``flying`` (whether the link flies the setpoints
at that moment): it learns at once, or announces that it waits for ``failsafe_cleared``. A
``failsafe`` event of the controller is a request to the vehicle link, whose own event
follows when it acts: it does not pause learning by itself. Steps not learned from for this
reason are counted (``not_applied``). In lockstep every setpoint is applied from the first
state on. The input of a transition is the setpoint answering its first state; in realtime,
when that one is missing (the controller answers only the newest state, or the bus dropped
it), the newest setpoint stamped at or before that state (what the vehicle's zero-order hold
applied) if it is at most about one period older (``input_fallback``), else the transition
is skipped (``input_missing``; ``before_first_setpoint`` for the states before the first
setpoint this adapter received: the controller was not answering yet). In realtime the adapter
never falls behind the vehicle: when an update took longer than a period (a loaded host),
the states that arrived meanwhile are dropped (``behind``) and the newest transition is
learned, so that the model the controller gets answers a recent state. Quaternions: ``q``
and ``-q`` are one attitude but far apart as the vectors the features and the residual use;
each transition is taken with the first state's scalar part non-negative (as in training)
and the second state in the same hemisphere. Link delay (``--link-delay D``, the
controller's value): the link applies each setpoint ``D`` after the state it answers, so the
setpoint answering state ``k-1`` acts until ``D`` after state ``k``. Each state is then
replaced by its prediction ``D`` ahead with the setpoint in flight at its instant
(:func:`arcade_core.dynamics.predict_over_delay`, its variance carried along), and the
transition between two such predictions is learned: each input acts over exactly that
period. A transition whose first state has no prediction (the state before had no input) is
skipped (``skipped``). Estimation noise: the residual of two estimated states contains their
errors; to first order (errors in variables) their variances (``State.cov_diag``, propagated
through the Jacobian of ``f_nom``) add to the observation noise ``sigma_j^2`` of each
output, in normalised units. With exact states (``cov_diag`` absent) the update is the
paper's.

Without a weights file the adapter cannot adapt: it says so in a ``degraded`` event and
publishes an empty (zero) model per state so that the controller runs the nominal MPC.

Scheduling (realtime): the update for a state starts once the controller's setpoint for that
state is out (or half a period later): the controller solves with the newest model it has,
which is never this state's, so the adapter only takes CPU from it otherwise.

Checkpoints: the beam is written atomically to ``--checkpoint`` every ``--checkpoint-every``
steps and at shutdown, and restored at start when it matches the weights (``restart``
event). A checkpoint that cannot be written (a full disk) is a ``fault`` event the first
time and counted (``checkpoint_errors``); adaptation goes on.
"""

from __future__ import annotations

import hashlib
import queue
import threading
from pathlib import Path
from typing import Any

import numpy as np

from arcade_io.traced import load_or_trace
from services import options, runtime, timing
from services.adapter_inputs import AppliedInputs
from services.checkpoint import load_checkpoint, save_checkpoint
from services.messages import MAX_VARIANCE, Model, Residual, Setpoint, State

#: The shipped quadrotor VLD (``arcade train --system quadrotor`` writes it).
DEFAULT_WEIGHTS = Path(__file__).resolve().parents[1] / "deploy" / "weights" / "quadrotor_vld.eqx"
#: Steps whose stamps are kept to date a changepoint (the MAP history dates one at most a
#: few steps back).
STEP_STAMPS = 256


def _without_network(out: tuple) -> tuple:
    """The adapter update's result with the learner's network left out: it does not change,
    and the rest is plain arrays (storable, :mod:`arcade_io.traced`)."""
    return (out[0]._replace(vld=None), *out[1:])


class Adapter(AppliedInputs, runtime.Service):
    """Adapter: ARCADE online adaptation (Algorithm 1) of the residual model."""

    name = "adapter"
    announce_options = True  # arcade replay runs it again as it ran

    def setup(self, bus) -> None:
        # Imported here, like every JAX module of the services: after runtime.setup_jax
        # has set the precision, and not for `--help`.
        import jax.numpy as jnp

        from arcade_control.detection import detection_config, detector_noise
        from arcade_control.knobs import split_knobs
        from arcade_control.stack import (
            adapter_learner,
            adapter_method,
            detector_prior,
            make_adapter_update,
            same_hemisphere,
        )
        from arcade_core import adaptation
        from arcade_core.dynamics import predict_over_delay
        from arcade_io.vehicle import load_vehicle, quadrotor_params

        self._same_hemisphere = same_hemisphere
        self._Detection = adaptation.Detection

        a = self.args
        self.jnp = jnp
        self.dtype = jnp.result_type(float)
        learner_knobs, detector_knobs = split_knobs(getattr(a, "knob", []))
        weights = Path(a.weights) if a.weights else DEFAULT_WEIGHTS
        self.weights = weights
        self.learner = None
        self.meta: dict[str, Any] = {}
        # The simulator's state is the ground truth (``--truth-state``); any other source
        # is an estimate, whose error the detector's knobs whiten
        # (:data:`arcade_control.knobs.DETECTION_DEFAULTS`).
        self.estimated = estimated = a.state_source != "sim"
        if weights.is_file():
            self.learner, self.method = adapter_learner(
                weights, self.dtype, a.method, learner_knobs, estimated
            )
            self.meta = {"weights_sha256": hashlib.sha256(weights.read_bytes()).hexdigest()}
        params = quadrotor_params(load_vehicle())
        self.model_dt = 0.05

        # At the model's step (the default 20 Hz) the in-process method's own ``learn``
        # runs; at other rates the same update with the nominal step over the elapsed time.
        exact = abs(1.0 / a.rate - self.model_dt) < 1e-9
        base_sigma2 = None if self.learner is None else self.learner.config.sigma2
        detect_sigma2 = None if base_sigma2 is None else detector_noise(base_sigma2)
        adapt, marginal, detect = make_adapter_update(
            getattr(self, "method", None), params, base_sigma2, exact, detect_sigma2
        )

        # Traced for these arguments, loaded from disk when traced before
        # (arcade_io.traced): besides code they close over the rate's step and the link
        # delay only. The update returns the learner without its (unchanged) network.
        x0, u0, var0 = np.zeros(13), np.array([5.6, 0.0, 0.0, 0.0]), np.zeros(13)
        sigma2 = None if base_sigma2 is None else np.asarray(base_sigma2).tolist()
        key = (
            f"link_delay={a.link_delay!r} exact={exact} sigma2={sigma2!r} "
            f"method={adapter_method(a.method)} "
            f"detect_sigma2={adaptation.quadrotor_config().sigma2!r}"
        )
        self._predict = load_or_trace(
            "adapter_predict",
            lambda x, var, u: predict_over_delay(x, var, u, params, a.link_delay),
            (x0, var0, u0),
            key,
        )
        if self.learner is not None:
            if self.learner.restart is not None and detector_knobs:  # the flagship's own
                cfg = detection_config(detector_knobs, dtype=self.dtype, estimated=estimated)
                det0 = adaptation.init_detection(detector_prior(self.learner), cfg)
                restart = self.learner.restart._replace(config=cfg, detection=det0)
                self.learner = self.learner._replace(restart=restart)
            adapt_plain = load_or_trace(
                "adapter_update",
                lambda learner, *rest: _without_network(adapt(learner, *rest)),
                (self.learner, x0, u0, x0, self.model_dt, False, var0, var0),
                key,
            )

            def _adapt(learner, *rest):
                new, *out = adapt_plain(learner, *rest)
                return (new._replace(vld=learner.vld), *out)

            self._adapt = _adapt
            # A learner that restarts at a declared change (the flagship) runs the detector
            # inside its own step: its declarations are the events, with no second detector.
            if self.learner.restart is None:
                self._detect_config = detection_config(
                    detector_knobs, dtype=self.dtype, estimated=estimated
                )
                self._detection0 = adaptation.init_detection(
                    detector_prior(self.learner), self._detect_config
                )
                self._detection = self._detection0
                self._detect = load_or_trace(
                    "adapter_detect",
                    detect,
                    (
                        self._detection,
                        self._detect_config,
                        self.learner,
                        x0,
                        u0,
                        x0,
                        self.model_dt,
                        False,
                        var0,
                        var0,
                    ),
                    key,
                )
            self._marginal = load_or_trace(
                "adapter_marginal", marginal, (self.learner, x0, u0), key
            )
            self._prior = self.learner
            if a.checkpoint is not None:
                restored = load_checkpoint(a.checkpoint, self.learner.beam, self.meta)
                if restored is not None:
                    self.learner = self.learner._replace(beam=restored)
                    self._restored = int(restored.step)
                elif Path(a.checkpoint).is_file():
                    self.log.warning(
                        "checkpoint %s does not match this learner (weights, preset or "
                        "beam layout): starting from the prior",
                        a.checkpoint,
                    )
        self._cond = threading.Condition()
        self._step_stamps: dict[int, float] = {}  # beam step -> stamp of its newer state
        self._setpoints: dict[float, Setpoint] = {}
        self._prev: State | None = None
        # Link delay: (stamp, state, variance) of the newest state predicted over it.
        self._predicted: tuple[float, np.ndarray, np.ndarray] | None = None
        self._lat = timing.LatencySamples()
        self.stats.update(
            steps=0,
            learned=0,
            changepoints=0,
            skipped=0,
            not_applied=0,
            input_fallback=0,
            input_missing=0,
            before_first_setpoint=0,
            nonfinite_resets=0,
            behind=0,
        )
        # Realtime: states wait here for the adapter's own loop (:meth:`main`), which takes
        # the newest; lockstep: each state is handled in its bus callback, in order.
        self._states: queue.Queue[State] = queue.Queue()
        # Whether the vehicle is flying the controller's setpoints (see the module docstring).
        self._applied = bool(a.lockstep)
        self._first_setpoint: float | None = None  # stamp of the first setpoint received
        self._mission_t0: float | None = None  # t0 of the newest mission start
        # Learned from only what the controller answered and the state source measured.
        bus.subscribe("setpoint", self.on_setpoint, source="controller")
        bus.subscribe("state", self.receive_state, source=self.args.state_source)
        bus.subscribe("event", self.on_event, check_order=False)
        self.pub_model = bus.publisher("model")
        self.pub_res = bus.publisher("residual")

    _restored: int | None = None
    _detect = None  # the changepoint detector's step, unless the learner runs its own
    _detection = _detection0 = None

    def warmup(self) -> None:
        if self.learner is None:
            return
        x = np.r_[0, 0, 1.0, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0]
        u = np.array([5.6, 0.0, 0.0, 0.0])
        for _ in range(3):
            self._adapt(self.learner, x, u, x, self.model_dt, False, np.zeros(13), np.zeros(13))
            if self._detect is not None:
                args = (self.learner, x, u, x, self.model_dt, False, np.zeros(13), np.zeros(13))
                self._detect(self._detection, self._detect_config, *args)
            self._marginal(self.learner, x, u)
            if self.args.link_delay > 0.0:
                self._predict(x, np.zeros(13), u)

    def ready(self) -> None:
        if self.learner is None:
            self.event(
                "degraded",
                f"no weights file at {self.weights}: no adaptation, the "
                "controller runs the nominal model",
                "warning",
            )
        elif self._restored is not None:
            self.event(
                "restart",
                f"restored the posterior from {self.args.checkpoint} (step {self._restored})",
                steps=self._restored,
            )

    def _declare(self, xp, up, x, h, learn, var_p, var_x, s: State, step: int, cp) -> None:
        """The detector's step on the transition just learned (``cp``: the learner's
        declaration, when its own detector runs in its step); an event if it declares."""
        if self._detect is None:
            r = self.learner.restart
            det = self._Detection(probability=self.learner.cp_prob, declared=cp, dated=r.dated)
        else:
            args = (self.learner, xp, up, x, h, learn, var_p, var_x)
            self._detection, det = self._detect(self._detection, self._detect_config, *args)
        if bool(det.declared):
            self.stats["changepoints"] += 1
            dated = int(det.dated)
            at = self._step_stamps.get(dated)
            # Dated to the transition that ended in the state stamped ``at``.
            dated_at = {} if at is None else {"changepoint_stamp": at}
            text = "changepoint detected"
            if at is None:
                text += ", dated before the steps kept"
            elif at < s.stamp:
                text += f", dated {s.stamp - at:.2f} s back"
            self.event(
                "changepoint",
                text,
                stamp=s.stamp,
                cp_prob=float(np.clip(det.probability, 0.0, 1.0)),
                step=step,
                state_seq=s.seq,
                changepoint_step=dated,
                **dated_at,
            )

    def receive_state(self, s: State) -> None:
        """The bus's state callback: lockstep, handled at once and in order; realtime,
        queued for :meth:`main`."""
        if self.args.lockstep:
            self.on_state(s)
        else:
            self._states.put(s)

    def main(self) -> None:
        """Realtime: one :meth:`handle_newest` after another until the service stops."""
        if self.args.lockstep:
            return super().main()
        while not self.stop.is_set():
            self.handle_newest(timeout=0.2)

    def handle_newest(self, timeout: float = 0.0) -> bool:
        """One turn of the realtime loop: the newest queued state, with the one before it
        as the start of its transition (False: none came within ``timeout`` seconds).

        An update that takes longer than a period (a loaded host) must not make the adapter
        fall behind the vehicle: a model answers a state it came late for, and one older than
        the controller's ``--max-model-age`` is not flown at all. The states that arrived
        meanwhile are not learned from (counted: ``behind``), except the newest transition."""
        try:
            pending = [
                self._states.get(timeout=timeout) if timeout > 0 else self._states.get_nowait()
            ]
        except queue.Empty:
            return False
        while True:
            try:
                pending.append(self._states.get_nowait())
            except queue.Empty:
                break
        if len(pending) > 1:
            self.stats["behind"] += len(pending) - 1
            self._prev = pending[-2]  # the newest transition is learned
            self._predicted = None  # not predicted over the link delay: skipped
        try:
            self.on_state(pending[-1])
        except Exception as err:  # as a bus callback's failure: counted, logged, go on
            self.bus.rejects.failure(err, topic="state")
        return True

    def on_state(self, s: State) -> None:
        if not self.args.lockstep and self._controller_alive():
            # The controller solves on this state with the newest model it has (this
            # state's comes too late for it either way): let it have the CPU first and
            # update once its setpoint is out (bounded: half a period).
            with self._cond:
                self._cond.wait_for(
                    lambda: s.stamp in self._setpoints or self.stop.is_set(), 0.5 / self.args.rate
                )
        t0 = self.now()
        prev, self._prev = self._prev, s
        if self.learner is None:
            self.pub_model.put(
                Model(
                    theta=np.zeros((13, 1)), sigma_tot2=np.zeros(13), state_seq=s.seq, stamp=s.stamp
                )
            )
            return
        # A gap in the states (a restarted estimator, a stall) is no transition to learn.
        h = s.stamp - prev.stamp if prev is not None else 0.0
        if prev is not None and not 0.0 < h <= self.args.max_gap_periods / self.args.rate:
            self.stats["gaps"] = self.stats.get("gaps", 0) + 1
            prev = None
        sp = self._input_for(prev) if prev is not None else None
        pair = None if sp is None else self._transition(prev, s, sp)
        detect_args = None
        if pair is None:
            if sp is None:
                self._predicted = None  # the setpoint in flight at ``s`` is not known
            theta, cov, sig = self._marginal(
                self.learner, self._same_hemisphere(s.x, s.x)[0], self._u_hover()
            )
            self.stats["skipped"] += prev is not None
        else:
            learn = self._applied and not s.predicted_through_dropout
            self.stats["not_applied"] += not self._applied
            if abs(h - self.model_dt) < 1e-6:
                h = self.model_dt  # bit-identical to the fixed-step nominal model
            xp, var_p, x, var_x = pair
            out = self._adapt(self.learner, xp, sp.u, x, h, learn, var_p, var_x)
            self.learner, dn, pred, cp_prob, cp, theta, cov, sig, _ = out
            self.stats["learned"] += learn
            step = int(self.learner.beam.step)
            if learn:
                self._step_stamps[step] = s.stamp
                self._step_stamps.pop(step - STEP_STAMPS, None)
            pred_np = type(pred)(*(np.asarray(p, dtype=float) for p in pred))
            pred_np = pred_np._replace(
                **{
                    f: np.clip(v, 0.0, MAX_VARIANCE)
                    for f, v in pred_np._asdict().items()
                    if f != "mean"
                }
            )
            if np.all(np.isfinite(np.asarray(dn))) and all(np.all(np.isfinite(p)) for p in pred_np):
                self.pub_res.put(
                    Residual.from_prediction(
                        np.clip(np.asarray(dn, float), -1e6, 1e6),
                        pred_np,
                        cp_prob=float(np.clip(cp_prob, 0.0, 1.0)),
                        changepoint=bool(cp),
                        state_seq=s.seq,
                        stamp=s.stamp,
                    )
                )
            detect_args = (xp, sp.u, x, h, learn, var_p, var_x, s, step, cp)
        theta, cov, sig = (np.asarray(v, dtype=float) for v in (theta, cov, sig))
        # Huge but finite state variances (a long dropout) must not make the message invalid.
        cov = np.clip(cov, -MAX_VARIANCE, MAX_VARIANCE)
        sig = np.clip(sig, 0.0, MAX_VARIANCE)
        if not (
            np.all(np.isfinite(theta)) and np.all(np.isfinite(cov)) and np.all(np.isfinite(sig))
        ):
            self.stats["nonfinite_resets"] += 1
            self.event(
                "fault",
                "non-finite posterior: beam reset to the prior",
                "error",
                stamp=s.stamp,
                state_seq=s.seq,
                resets=self.stats["nonfinite_resets"],
            )
            self.learner, self._detection = self._prior, self._detection0
            self._step_stamps = {}  # the steps count from 0 again
            return
        self.pub_model.put(
            Model.from_marginal(
                theta,
                cov,
                np.maximum(sig, 0.0),
                step=int(self.learner.beam.step),
                changepoints=self.stats["changepoints"],
                state_seq=s.seq,
                stamp=s.stamp,
            )
        )
        if detect_args is not None:
            # The changepoint detector runs once the model is out: its cost never delays
            # the controller's model.
            self._declare(*detect_args)

        self.stats["steps"] += 1
        self._lat.append(self.now() - t0)
        every = self.args.checkpoint_every
        if self.args.checkpoint is not None and every > 0 and self.stats["steps"] % every == 0:
            self._checkpoint()

    def _transition(self, prev: State, s: State, sp: Setpoint) -> tuple | None:
        """The transition ``prev -> s`` under the input ``sp`` as learned: the two states
        (quaternions in one hemisphere) and their variances; with a link delay, their
        predictions over it (None when ``prev`` has none)."""
        zeros = np.zeros(13)
        var_p = prev.cov_diag if prev.cov_diag is not None else zeros
        var_x = s.cov_diag if s.cov_diag is not None else zeros
        xp, x = self._same_hemisphere(prev.x, s.x)
        if self.args.link_delay == 0.0:
            return xp, var_p, x, var_x
        # ``sp`` answered ``prev``: it is the setpoint in flight at ``s``.
        before, x_d, var_d = self._predicted, *self._predict(x, var_x, sp.u)
        x_d, var_d = np.asarray(x_d, float), np.asarray(var_d, float)
        self._predicted = (s.stamp, x_d, var_d)
        if before is None or before[0] != prev.stamp:
            return None
        xp_d, x_d = self._same_hemisphere(before[1], x_d)
        return xp_d, before[2], x_d, var_d

    def _checkpoint(self) -> None:
        """Write the checkpoint; a failure (a full disk) is said once, counted, and tried
        again at the next checkpoint: the adaptation goes on either way."""
        try:
            save_checkpoint(self.args.checkpoint, self.learner.beam, self.meta)
        except OSError as err:
            self.stats["checkpoint_errors"] = self.stats.get("checkpoint_errors", 0) + 1
            if self.stats["checkpoint_errors"] == 1:
                self.event(
                    "fault",
                    f"cannot write the checkpoint {self.args.checkpoint}: "
                    f"{err.strerror or err}; a restarted adapter would start from an "
                    "older posterior or the offline prior",
                    "error",
                    errno=err.errno if err.errno is not None else -1,
                )
            return
        if self.stats.get("checkpoint_errors"):
            self.stats["checkpoint_errors_cleared"] = int(self.learner.beam.step)

    def _u_hover(self) -> np.ndarray:
        return np.array([0.57 * 9.81, 0.0, 0.0, 0.0])

    def teardown(self) -> None:
        self.stats["update"] = self._lat.summary()
        if self.learner is not None and self.args.checkpoint is not None:
            errors = self.stats.get("checkpoint_errors", 0)
            self._checkpoint()
            if self.stats.get("checkpoint_errors", 0) == errors:
                self.stats["checkpoint_step"] = int(self.learner.beam.step)


def _extra(p) -> None:
    options.add_adapter_arguments(p)


def main(argv: list[str] | None = None) -> int:
    return runtime.main_for(Adapter, argv, _extra)
