"""Controller service: uncertainty-modulated MPC (Sec. IV) on the latest state and model.

Subscribes ``state`` and ``model``; publishes ``setpoint`` (tagged with the ``seq`` and
``stamp`` of the state it answers), after it the ``reference`` it tracked at that instant
(same stamp), and ``event``.

Per state: one step of the in-process closed loop's controller
(``arcade_control.step.make_controller_step`` with the learning left to the
adapter): the flat reference of the flight plan over the horizon (index = mission time
/ 0.05 s; mission time = state stamp minus the first state's stamp in lockstep, minus the
``t0`` of the ``start`` command in realtime, 0 before it), input reference
corrected for the learned thrust, one warm-started MPC solve (``arcade_core.mpc``,
Appendix D weights, N = 20 over 1 s) on ``f_nom + theta phi`` with the beam-marginal
decoder mean of the newest ``model``, ``Q`` modulated by ``sigma_tot^2`` (Sec. IV). The
method sees a one-hypothesis beam that holds the moment-matched posterior of the
``model`` message, so ``sigma_tot^2`` at ``(x, u_warm[0])`` has the parameter and
between-hypothesis parts of the beam mixture exactly (``z^T Sigma_j z`` of the
moment-matched covariance) and the encoder part from the marginal mean (the mixture's
encoder part also counts the spread of the hypotheses' means: slightly less caution).

``--method arcade`` (the product's flagship, ``arcade_control.methods.arcade_method``; the
adapter started with the same option): the model message holds the flagship's posterior
(features with an intercept) and the step also runs its L1 thrust augmentation
(``arcade_control.stack.controller_method``), whose state the controller carries from
step to step: its predictor integrates the setpoint last sent plus what the model message
predicts, and its filtered estimate is added to the MPC's thrust. After a step that is not
tracking (hover, nominal MPC) its predictor synchronises again with the next state.
``--method l1``: the nominal MPC with L1's augmentation (thrust and body rates, the stack's
L1 knobs), carried and synchronised the same way; the model message only paces the step.

With a learned model and ``--advanced-step`` the step is advanced
(``arcade_control.step.make_advanced_step``; not the default, see
``docs/quadrotor-closed-loop.md``): once the setpoint and the reference are out,
the controller solves the MPC for the next state's instant, one control period (``1 /
--rate``) on, from the state its model predicts, with the model message of the moment;
the next state is answered by that plan corrected to first order for where the state is
and for the model message then newest (one forward-mode derivative and a matrix-vector
product), so sense-to-actuate holds no MPC solve. A state that answers no prepared plan
(the first, after hover or the nominal MPC, a state at another instant than planned) is
answered by a full solve. ``stats``: ``planned_steps`` (states answered from a plan),
``prepare`` (the solve's latency after the setpoint), ``solve`` (state to setpoint, the
control step alone). Without it every state is solved for after it arrives.

With ``--link-delay D`` (the link delays every setpoint by ``D``, less than one period)
the step plans from the state predicted ``D`` ahead with the setpoint in flight (the last
MPC input; after a hover setpoint still the MPC's last one) against the reference ``D``
later, as the adapter started with the same ``D`` learns
(:func:`arcade_core.dynamics.predict_over_delay`).

Lockstep: the solve waits for the model that answers the same state (``--model-timeout``)
while the adapter is alive (its liveliness token); without it, the newest model is used.
Realtime: the newest model is used. Models are ordered by their ``stamp`` (the stamp of the
state they answer), which stays monotonic when a restarted estimator counts ``seq`` from 1.
The mission clock: lockstep, simulated time (it starts at 0 with the mission, so a
restarted controller is on it at once); realtime, the ``t0`` of the ``start`` command
(sent again by the simulator when a controller joins late).

Safety: a setpoint is always finite and within the MPC input bounds. Degraded modes, each
announced by an event when entered:

- stale model (older than ``--stale-model-s``, e.g. the adapter died): the last model is
  still used (mode ``track``) and a ``degraded`` event with ``flag: stale_model`` says so;
- no model (no weights, model late or older than ``--max-model-age``): nominal MPC
  (mode ``nominal_model``);
- stale state (realtime: older than ``--max-state-age`` on arrival; any mode: newest
  fused mocap older than ``--max-meas-age``, 0.2 s: the estimator's constant-acceleration
  prediction extrapolates its acceleration estimate, whose noise (~1-2 m/s^2) makes the
  predicted velocity drift by tenths of m/s within a few tenths of a second, which the MPC
  would chase): level hover (mode ``hover``, :func:`level_hover`) at the hover thrust
  learned while tracking (the mean of the tracking thrusts, over the last 2.5 s once there
  are that many, corrected for tilt; the nominal one before any), tracking resumes with
  the next fresh state;
- a non-finite or failed solve, or a control step that raised (``step_errors``; the first
  traceback is logged in full, later ones as a count at most every ``STEP_ERROR_LOG_S``):
  hover for that step.

Hover has no position feedback, so it is bounded: after ``--max-hover-s`` (1 s) of
uninterrupted hover, whatever its cause, a ``failsafe`` event (``reason: hover_timeout``)
asks the vehicle link to fail safe (the PX4 bridge leaves offboard with its ``--failsafe``
action, the simulator holds position); the controller keeps publishing hover setpoints,
and the next tracking step ends the episode. Shorter hovers (e.g. a mocap dropout below
1.2 s) only emit ``degraded``.

A solve that ends after the next control instant (``1 / rate``) is a deadline miss.
"""

from __future__ import annotations

import math
import queue
import threading
import time
from pathlib import Path

import numpy as np

from arcade_control.hover import HOVER_THRUST_STEPS, level_hover
from arcade_core import frames
from arcade_io.traced import load_or_trace
from services import options, runtime, timing
from services.controller_options import add_controller_arguments as _extra
from services.messages import MAX_STAMP_S, Model, Reference, Setpoint, State

#: Shortest interval between two log lines about failing control steps [s].
STEP_ERROR_LOG_S = 5.0
#: A state stamped further behind the previous setpoint than this is not late: the
#: previous stamp was wrong, and the setpoint stamps follow the states again [s].
MAX_STAMP_LAG_S = 1.0


class Controller(runtime.Service):
    """Controller: uncertainty-modulated MPC on the latest state and model."""

    name = "controller"
    announce_options = True  # arcade replay runs it again as it ran

    def setup(self, bus) -> None:
        # Imported here, like every JAX module of the services: after runtime.setup_jax
        # has set the precision, and not for `--help`.
        import jax.numpy as jnp

        from arcade_control.nominal import CONTROL_DT, nominal_params
        from arcade_control.scenario import flat_reference, reference_arguments
        from arcade_control.step import Carry, mpc_config
        from services.adapter import DEFAULT_WEIGHTS
        from services.controller_steps import build_steps

        a = self.args
        self.jnp = jnp
        dtype = self.dtype = jnp.result_type(float)
        self.cfg = cfg = mpc_config(dtype)
        self.u_min = np.asarray(cfg.u_min, float)
        self.u_max = np.asarray(cfg.u_max, float)
        p = nominal_params()
        self.u_hover = np.array([float(p.mass) * float(p.gravity), 0.0, 0.0, 0.0])
        scen = options.scenario(a)
        self.ref_dt = CONTROL_DT
        t_end = a.duration if a.duration is not None else scen.t_end
        self.n_ref = math.ceil(t_end / CONTROL_DT - 1e-9) + 1
        # With a link delay the plan starts where the setpoint will act: the reference
        # that much later, from the state predicted over it (``make_controller_step``).
        delay = a.link_delay
        # Traced once and kept on disk, like the steps (arcade_io.traced).
        ref_args = reference_arguments(scen, self.n_ref, cfg.N, delay)
        reference = load_or_trace("reference", flat_reference, ref_args)
        self.x_ref_all, self.u_ref_all = reference(*ref_args)
        weights = Path(a.weights) if a.weights else DEFAULT_WEIGHTS
        self.weights = weights
        self.advanced = bool(a.advanced_step) and weights.is_file()
        u0 = jnp.asarray(self.u_hover, dtype)
        steps = build_steps(
            cfg,
            a.method,
            weights,
            (self.x_ref_all, self.u_ref_all),
            delay,
            self.advanced,
            a.rate,
            u0,
        )
        self.carry, self.learner0 = steps.carry, steps.learner0
        self._theta0, self._cov0 = steps.theta0, steps.cov0
        self._step_nominal, self._step_learned = steps.nominal, steps.learned
        self._feedback, self._prepare = steps.feedback, steps.prepare
        self._plain_carry = Carry
        self._learner_nominal = jnp.zeros((), dtype)
        # The flagship's L1 augmentation state, carried from step to step (None: ours).
        self._l1 = getattr(self.learner0, "l1", None)
        self._u_sent = self.u_hover.copy()  # the last setpoint published
        #: The instant the prepared plan answers and the model message it was made with.
        self._plan_k: int | None = None
        self._plan_post: tuple | None = None
        self.t0: float | None = None
        self._model: Model | None = None
        self._cond = threading.Condition()
        self._queue: queue.Queue[tuple[State, float]] = queue.Queue()
        self._mode = "track"
        self._hover_since: float | None = None  # stamp of the first state of this hover
        self._hover_failsafe = False  # the hover bound was reported in this episode
        self._step_error_logged = -math.inf  # when a failing step was last logged
        self._step_errors_unlogged = 0
        self._stale_model = False
        self._thrust_hover = float(self.u_hover[0])  # learned while tracking
        self._thrust_samples = 0  # tracking steps averaged into it so far
        self._solve_s = timing.LatencySamples(skip=1)  # the first solve: warm-up
        self._prepare_s = timing.LatencySamples(skip=1)  # advanced step: after the setpoint
        self.stats.update(
            setpoints=0,
            deadline_misses=0,
            hover=0,
            nominal_model=0,
            solver_failures=0,
            step_errors=0,
            fallback_errors=0,
            hover_failsafes=0,
            stamp_reanchored=0,
            planned_steps=0,
            plan_errors=0,
        )
        bus.subscribe("model", self.on_model, source="adapter")
        self._state_sub = bus.subscribe("state", self.on_state, source=self.args.state_source)
        self._react_s = timing.LatencySamples(skip=1)  # state received -> setpoint put
        self.pub = bus.publisher("setpoint")
        self.pub_ref = bus.publisher("reference")
        self._x_ref = np.asarray(self.x_ref_all, dtype=float)
        self._u_ref = np.asarray(self.u_ref_all, dtype=float)

    def warmup(self) -> None:
        x = np.r_[0, 0, 1.0, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0]
        carry = self.carry
        for k in range(3):  # the first calls after compiling are still slow
            self._solve(x, k, None)
            if self.learner0 is not None:
                post = (self._theta0, self._cov0)
                self._solve(x, k, post)
                if self.advanced:  # the prepared path too, then no plan again
                    self.carry = self._new_carry
                    self._plan(k + 1, post)
                    self._solve(x, k + 1, post)
                    self._plan_k = None
        self.carry = carry
        self.stats["planned_steps"] = 0

    def ready(self) -> None:
        if self.learner0 is None:
            self.event("degraded", f"no weights file at {self.weights}: nominal MPC", "warning")

    def _solve(self, x: np.ndarray, k: int, posterior: tuple | None) -> np.ndarray:
        """One step of the in-process controller; returns the input to apply and whether
        the whole solution (input and warm start) is finite, as one vector (5,)."""
        # NumPy arrays of the right dtype straight into the jitted steps (their C++ fast
        # path converts them; jnp.asarray costs tenths of a millisecond per array).
        dt = np.dtype(self.dtype)
        x = np.asarray(x, dt)
        carry = self.carry
        if posterior is None:
            carry = self._plain_carry(*carry[:5])._replace(learner=self._learner_nominal)
            new, u = self._step_nominal(carry, x, carry.u_mpc, k, self.x_ref_all, self.u_ref_all)
            self._new_l1 = self._resync(self._l1)
        else:
            learner = self.learner0
            if self._l1 is not None:
                learner = learner._replace(l1=self._l1)
            carry = carry._replace(learner=learner)
            post = tuple(np.asarray(v, dt) for v in posterior)
            u_sent = np.asarray(self._u_sent, dt)
            refs = (self.x_ref_all, self.u_ref_all)
            if self.advanced:
                planned = self._plan_k == k
                self.stats["planned_steps"] += int(planned)
                plan = carry.plan._replace(ready=np.asarray(planned))
                post_plan = self._plan_post if planned else post
                new, u = self._feedback(
                    carry._replace(plan=plan), x, u_sent, k, post_plan, post, *refs
                )
                self._plan_k = None  # used, or for another instant
            else:
                new, u = self._step_learned(carry, x, u_sent, k, *post, *refs)
            self._new_l1 = new.learner
        self._new_carry = new._replace(learner=carry.learner)
        if self.advanced and posterior is None:  # the plain step's carry, no plan
            self._new_carry = self.carry._replace(**self._new_carry._asdict())
            self._plan_k = None
        return np.asarray(u, dtype=float)  # (5,): the input and the finite-solution flag

    def _plan(self, k: int, posterior: tuple) -> None:
        """Advanced step: the plan for instant ``k``, one control period after the state
        just answered, made with ``posterior`` (after the setpoint is out)."""
        dt = np.dtype(self.dtype)
        post = tuple(np.asarray(v, dt) for v in posterior)
        period = np.asarray(1.0 / self.args.rate, dt)
        learner = self.learner0
        if self._l1 is not None:
            learner = learner._replace(l1=self._l1)
        carry = self.carry._replace(learner=learner)
        new = self._prepare(carry, k, period, post, self.x_ref_all, self.u_ref_all)
        self.carry = new._replace(learner=self.carry.learner)
        self._plan_k, self._plan_post = k, post

    @staticmethod
    def _resync(l1_state):
        """The flagship's L1 state after a step it did not run (hover, nominal MPC): its
        predictor synchronises with the next state it sees instead of integrating over a
        gap with inputs it did not see."""
        if l1_state is None:
            return None
        return l1_state._replace(started=np.zeros((), bool))

    # -- inputs
    def on_command(self, cmd) -> None:
        if cmd.name == "start" and cmd.target in ("", self.name):
            t0 = cmd.args.get("t0", cmd.stamp)
            if not (isinstance(t0, int | float) and 0.0 <= t0 <= MAX_STAMP_S):
                self.log.warning("start command with an invalid t0 %r: using its stamp", t0)
                t0 = cmd.stamp
            self.t0 = float(t0)
            self.log.info("mission clock started at %.3f", self.t0)

    def on_model(self, m: Model) -> None:
        with self._cond:
            if self._model is None or m.stamp >= self._model.stamp:
                self._model = m
            self._cond.notify_all()

    def _adapter_alive(self) -> bool:
        return self.bus is None or "adapter" in self.bus.alive

    def on_state(self, s: State) -> None:
        self._queue.put((s, time.perf_counter()))

    # -- loop
    def main(self) -> None:
        while not self.stop.is_set():
            try:
                s, t_in = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            if not self.args.lockstep:  # only the newest state matters in real time
                while True:
                    try:
                        s, t_in = self._queue.get_nowait()
                    except queue.Empty:
                        break
            self.step(s, t_in)

    def step(self, s: State, t_in: float) -> None:
        """One control step on ``s``; a step that raises gives a hover setpoint instead."""
        self._next_plan = None
        try:
            self.handle(s)
            self._react_s.append(time.perf_counter() - t_in)
        except Exception as err:
            self.stats["step_errors"] += 1
            self._log_step_error(err)
            try:
                self._set_mode("hover", f"control step failed: {err!r}", s.stamp)
                self.publish(s, self.hover(s), "hover", 0.0)
            except Exception as err2:  # the loop must go on: the next state may be fine
                self.stats["fallback_errors"] += 1
                self._log_step_error(err2)
        try:  # after the setpoint: what it tracked, for the recorder and the tools
            k = self._instant(s)
            ref = Reference(
                x=self._x_ref[k],
                u=self._u_ref[min(k, len(self._u_ref) - 1)],
                t=k * self.ref_dt,
                stamp=self._last_stamp,
            )
            self.pub_ref.put(ref)
        except Exception as err:
            self.stats["fallback_errors"] += 1
            self._log_step_error(err)
        if self._next_plan is not None:  # advanced step: off the sense-to-actuate path
            try:
                t1 = time.perf_counter()
                self._plan(*self._next_plan)
                self._prepare_s.append(time.perf_counter() - t1)
            except Exception as err:  # the next state is then answered by a full solve
                self._plan_k = None
                self.stats["plan_errors"] += 1
                self._log_step_error(err)

    def _instant(self, s: State, ahead_s: float = 0.0) -> int:
        """Index of ``s``'s instant (or ``ahead_s`` after it) in the reference (mission
        time; the start reference until the mission clock starts in realtime)."""
        t = 0.0 if self.t0 is None else s.stamp + ahead_s - self.t0
        return min(max(round(t / self.ref_dt), 0), self.n_ref - 1)

    def _log_step_error(self, err: Exception) -> None:
        """The first failure with its traceback, then a count at most every
        ``STEP_ERROR_LOG_S`` (a persistent error fails every step, 20-50 per second)."""
        now = self.now()
        if self._step_error_logged == -math.inf:
            self.log.exception("control step failed: hover setpoint")
        elif now - self._step_error_logged >= STEP_ERROR_LOG_S:
            self.log.error(
                "control step failed again: %r (%d more failures since the last report; "
                "step_errors %d, fallback_errors %d)",
                err,
                self._step_errors_unlogged + 1,
                self.stats["step_errors"],
                self.stats["fallback_errors"],
            )
        else:
            self._step_errors_unlogged += 1
            return
        self._step_error_logged = now
        self._step_errors_unlogged = 0

    def _set_mode(self, mode: str, why: str, stamp: float) -> None:
        if mode != self._mode:
            if mode == "track":
                self.event("info", f"tracking resumed ({why})", stamp=stamp)
            else:
                self.event("degraded", f"{mode}: {why}", "warning", stamp=stamp, mode=mode)
            self._mode = mode
            self._hover_since = stamp if mode == "hover" else None
            self._hover_failsafe = False
        elif (
            mode == "hover"
            and not self._hover_failsafe
            and self._hover_since is not None
            and stamp - self._hover_since >= self.args.max_hover_s
        ):
            # Open-loop hover drifts: past the bound the vehicle link must fail safe.
            self._hover_failsafe = True
            self._failsafe_reason = "hover_timeout"  # rides on this instant's setpoint
            self.stats["hover_failsafes"] += 1
            self.event(
                "failsafe",
                f"hovering for {stamp - self._hover_since:.2f} s ({why}): "
                "the vehicle link must fail safe",
                "error",
                stamp=stamp,
                reason="hover_timeout",
                hover_s=float(stamp - self._hover_since),
            )

    def model_for(self, s: State) -> Model | None:
        a = self.args

        def current() -> bool:
            return self._model is not None and self._model.stamp >= s.stamp

        with self._cond:
            if a.lockstep and self.learner0 is not None:
                self._cond.wait_for(
                    lambda: current() or self.stop.is_set() or not self._adapter_alive(),
                    a.model_timeout,
                )
            m = self._model
        if m is None or self.learner0 is None or m.theta.shape != self._theta0.shape:
            return None
        age = s.stamp - m.stamp
        if a.lockstep and age > 0 and self._adapter_alive():
            return None  # the adapter is up but late: no guessing in lockstep
        if age > a.max_model_age:
            return None
        stale = age > a.stale_model_s
        if stale != self._stale_model:
            self._stale_model = stale
            if stale:
                self.event(
                    "degraded",
                    f"model {age:.2f} s old: flying on the last one",
                    "warning",
                    stamp=s.stamp,
                    flag="stale_model",
                    age_s=float(age),
                )
            else:
                self.event("info", "fresh models again", stamp=s.stamp, flag="stale_model")
        return m

    def hover(self, s: State) -> np.ndarray:
        """Level hover at the learned hover thrust (:func:`level_hover`)."""
        return np.clip(level_hover(s.q, self._thrust_hover), self.u_min, self.u_max)

    def handle(self, s: State) -> None:
        a = self.args
        t_recv = self.now()
        if self.t0 is None and a.lockstep:
            self.t0 = 0.0  # simulated time starts at 0 with the mission
        age = t_recv - s.stamp if not a.lockstep else 0.0
        meas_age = s.stamp - s.meas_stamp if s.meas_stamp is not None else 0.0
        if age > a.max_state_age or meas_age > a.max_meas_age:
            self.stats["hover"] += 1
            why = (
                f"state {age * 1e3:.0f} ms old"
                if age > a.max_state_age
                else f"newest mocap {meas_age:.2f} s old"
            )
            self._set_mode("hover", why, s.stamp)
            self.publish(s, self.hover(s), "hover", 0.0)
            return
        m = self.model_for(s)
        k = self._instant(s)
        t0 = time.perf_counter()
        if m is None:
            if self.learner0 is not None:
                self.stats["nominal_model"] += 1
            mode = "nominal_model"
            u = self._solve(s.x, k, None)
        else:
            mode = "track"
            cov = (
                m.theta_cov
                if m.theta_cov is not None
                else np.zeros((*m.theta.shape, m.theta.shape[1]))
            )
            u = self._solve(s.x, k, (m.theta, cov))
        solve_s = time.perf_counter() - t0
        self._solve_s.append(solve_s)
        u, finite = u[:4], u[4] == 1.0
        if not finite or not np.all(np.isfinite(u)):
            self.stats["solver_failures"] += 1
            self._plan_k = None
            self._set_mode("hover", "non-finite MPC solution", s.stamp)
            self.publish(s, self.hover(s), "hover", solve_s)
            return
        self.publish(s, u, mode, solve_s)  # first: the bookkeeping below can wait
        self.carry = self._new_carry
        self._l1 = self._new_l1
        if self.advanced and m is not None:  # the next instant's plan, with this model
            self._next_plan = (self._instant(s, 1.0 / a.rate), (m.theta, cov))
        # Hover thrust for the hover mode: what tracking on measured states needed,
        # level-equivalent (a slow mean: a few seconds).
        if not s.predicted_through_dropout:
            q = s.q
            tilt = frames.world_up_in_body_np(q)[2]
            # The plain mean of the first HOVER_THRUST_STEPS samples, then an exponential
            # mean over as many: the nominal value it starts from (no payload) must not
            # linger for seconds.
            self._thrust_samples += 1
            w = max(1.0 / self._thrust_samples, 1.0 / HOVER_THRUST_STEPS)
            self._thrust_hover += w * (float(u[0]) * max(tilt, 0.5) - self._thrust_hover)
        self._set_mode(mode, "model available" if m is not None else "no current model", s.stamp)
        if not a.lockstep and self.now() - t_recv > 1.0 / a.rate:
            self.stats["deadline_misses"] += 1

    def publish(self, s: State, u: np.ndarray, mode: str, solve_s: float) -> None:
        u = np.asarray(u, dtype=float)
        if not np.all(np.isfinite(u)):
            u = self.u_hover.copy()
            mode = "hover"
        u = np.clip(u, self.u_min, self.u_max)
        # The stamp of the answered state; never older than the previous setpoint's, so
        # that an answer to a late state is not rejected as out of order downstream. A
        # state far behind the previous answer is no late state: the previous stamp was
        # wrong (one state stamped in the future, after which the state stream re-anchored),
        # and holding on to it would stamp every later setpoint with it.
        if s.stamp < self._last_stamp - MAX_STAMP_LAG_S:
            self.stats["stamp_reanchored"] += 1
            self.log.warning(
                "state stamp %.3f is %.3f s behind the previous setpoint's: re-anchoring",
                s.stamp,
                self._last_stamp - s.stamp,
            )
            self._last_stamp = s.stamp
        stamp = max(s.stamp, self._last_stamp)
        self._last_stamp = stamp
        if mode != "track":  # the flagship's augmentation did not run on this one
            self._l1 = self._resync(self._l1)
        self._u_sent = u
        failsafe, self._failsafe_reason = self._failsafe_reason, ""
        self.pub.put(
            Setpoint(
                u=u,
                state_seq=s.seq,
                stamp=stamp,
                mode=mode,
                solve_ms=min(solve_s * 1e3, 1e6),
                failsafe=failsafe,
            )
        )
        self.stats["setpoints"] += 1

    _last_stamp = 0.0
    _next_plan: tuple | None = None  # advanced step: (instant, model) to plan for next
    _failsafe_reason = ""  # a failsafe raised for the state being answered

    def teardown(self) -> None:
        self.stats["solve"] = self._solve_s.summary()
        if self.advanced:
            self.stats["prepare"] = self._prepare_s.summary()
        self.stats["solve_samples_ms"] = self._solve_s.samples_ms()
        # The controller's share of sense-to-actuate: the state's bus hop, and from its
        # arrival to the setpoint's put (queue hand-over, solve, encode).
        self.stats["hop_state"] = timing.percentiles_ms(list(self._state_sub.transit_s))
        self.stats["react"] = self._react_s.summary()


def main(argv: list[str] | None = None) -> int:
    return runtime.main_for(Controller, argv, _extra)


__all__ = ["Controller", "main"]
