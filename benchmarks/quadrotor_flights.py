"""In-process closed-loop flights of the quadrotor (Sec. V-B): one method, one trial.

:class:`Runner` flies the MuJoCo quadrotor (:class:`simulator.QuadrotorSim`) with the
jitted controller step of a method (:func:`arcade_control.step.make_controller_step`) on
the ground-truth state, or on the state estimate the service stack flies
(:class:`MocapEstimate`); :func:`flight_metrics` scores a flight. The flight plan and its
reference are :mod:`arcade_control.scenario`; what the evaluation does with the flights is
:mod:`benchmarks.quadrotor_closedloop`.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from arcade_control.knobs import FLAGSHIP, HELD, base_name
from arcade_control.learners import initial_learner, per_output_noise
from arcade_control.methods import BeamLearner, MassOracle, make_method
from arcade_control.nominal import CONTROL_DT as DT
from arcade_control.nominal import f_nom, nominal_params
from arcade_control.scenario import Scenario, reference, trial
from arcade_control.step import (
    Carry,
    make_controller_step,
    method_mpc_config,
    mpc_config,
    planned_carry,
)
from arcade_core import adaptation, estimation, metrics
from arcade_core.dynamics.quadrotor import predict_over_delay
from simulator import QuadrotorSim

#: A flight whose position error exceeds this is stopped and counted as a crash [m].
CRASH_ERROR_M = 2.0
#: Flights of one method and cell flown at a time (:meth:`Runner.fly_trials`), at most
#: :func:`flight_threads` allows: one flight uses about 1.1 cores, and the compiled solves of
#: one overlap the other's Python (which holds Python's lock).
FLIGHT_THREADS = 2


def flight_threads(requested: int) -> int:
    """How many flights may fly at a time: ``requested``, but at most one per CPU less one.

    A flight's compiled steps execute on XLA's CPU thread pool (a thread per CPU), and
    their LAPACK kernels (a batched Cholesky factorisation) split their batch over the same
    pool and wait for it. With as many flights as pool threads, each can hold a thread
    and wait for another forever: two flights on two CPUs hung ``arcade eval quadrotor``
    in the GP's tuning (both threads in ``jax::ParallelBatchMap``). With a thread to spare,
    one of them always finishes. On two CPUs the flights therefore fly one at a time."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count() or 1
    return max(1, min(requested, cpus - 1))


class MocapEstimate:
    """The state a flight sees: the estimator core (:mod:`arcade_core.estimation`, the
    :class:`~arcade_core.estimation.FilterConfig` of the :class:`Runner`) on the simulator's
    motion capture and gyro (noise, latency, dropped frames), as the stack's estimator
    service runs it at each control instant. The first call also takes the frame captured
    at ``t = 0``, which the stack's simulator publishes before its first control instant."""

    def __init__(self, sim, dtype, step: Callable):
        self.sim, self.dtype, self._step = sim, dtype, step
        self.filter = estimation.init(dtype)
        self.gyro = np.zeros(3)
        self._first = True

    def __call__(self) -> tuple[np.ndarray, np.ndarray]:
        """``(x, var)`` at the simulator's current time: estimate and marginal variances."""
        sim, first, self._first = self.sim, self._first, False
        until = float("inf") if first else sim.time
        gyro = sim.gyro.read(until)
        if gyro:
            self.gyro = gyro[-1].omega
        frames = sim.mocap.read(until)[-estimation.MAX_FRAMES :]
        m, dt = estimation.MAX_FRAMES, np.dtype(self.dtype)
        stamp, pos = np.zeros(m, dt), np.zeros((m, 3), dt)
        quat_ = np.tile(np.array([1.0, 0.0, 0.0, 0.0], dt), (m, 1))
        valid = np.zeros(m, bool)
        for i, f in enumerate(frames):
            stamp[i], pos[i], quat_[i], valid[i] = f.stamp, f.position, f.quaternion, True
        self.filter, out = self._step(
            self.filter,
            estimation.Frames(stamp, pos, quat_, valid),
            np.asarray(sim.time, dt),
            np.asarray(self.gyro, dt),
        )
        return np.asarray(out.x, float), np.asarray(out.var, float)


# --------------------------------------------------------------------------- flights


@dataclass
class Flight:
    """One closed-loop flight at the control rate."""

    method: str
    scenario: Scenario
    seed: int
    t: np.ndarray  # (n,)
    x: np.ndarray  # (n, 13)
    x_ref: np.ndarray  # (n, 13)
    u: np.ndarray  # (n, 4) applied
    diag: np.ndarray  # (n, 17)
    t_release: float
    crashed: bool
    step_ms: np.ndarray  # (n,) wall time of the jitted update per step
    metrics: dict[str, float] = field(default_factory=dict)
    #: Beam methods: what the learner learned from at each step, ``{"xp", "up", "x"
    #: (n, 13|4|13), "sigma2" (n, 13) or (n,), "learned" (n,) bool}`` (the transition
    #: ``xp -> x`` under ``up`` with its observation noise), for replaying the beam
    #: offline (:mod:`benchmarks.changepoints`); ``None`` for the other methods.
    learning: dict[str, np.ndarray] | None = None

    @property
    def error(self) -> np.ndarray:
        return self.x[:, :3] - self.x_ref[:, :3]


class Runner:
    """Builds (once) and caches the jitted per-step update of each method."""

    def __init__(self, models, dtype=None, filter_config=None, advanced: bool = False):
        """``filter_config``: the estimator's settings for flights on the state estimate
        (:class:`arcade_core.estimation.FilterConfig`; ``None``: its defaults, the
        estimator service's). ``advanced``: what :meth:`fly` flies unless told otherwise
        (the advanced-step controller, as the stack's controller service runs it)."""
        self.advanced = advanced
        self.models = models
        self.dtype = jnp.result_type(float) if dtype is None else dtype
        self.filter_config = filter_config
        self.cfg = mpc_config(self.dtype)
        self._steps: dict[tuple[str, float], Callable] = {}
        self._estimate: Callable | None = None
        self._jacobian: Callable | None = None
        self._predict_var: Callable | None = None

    def _estimation(self) -> tuple[Callable, Callable]:
        """The jitted estimator step and ``df_nom/dx`` (built once)."""
        if self._estimate is None:
            config = self.filter_config
            if config is None:
                config = estimation.FilterConfig()
            self._estimate = jax.jit(
                lambda f, fr, t, w: estimation.fuse_and_predict(f, fr, t, w, config)
            )
            self._jacobian = jax.jit(jax.jacfwd(f_nom))
        assert self._jacobian is not None
        return self._estimate, self._jacobian

    def _predict(self, x, var, u, delay: float):
        """The diagonal variance of the state predicted over ``delay``
        (:func:`arcade_core.dynamics.predict_over_delay`; jitted once)."""
        return self._predictor()(x, var, u, delay)

    def _predictor(self) -> Callable:
        if self._predict_var is None:
            self._predict_var = jax.jit(
                lambda x, var, u, d: predict_over_delay(x, var, u, nominal_params(), d)[1]
            )
        return self._predict_var

    def step_fn(self, name: str, delay_s: float = 0.0, advanced: bool = False) -> Callable:
        """The jitted step of method ``name`` (:func:`make_controller_step`)."""
        key = (name, delay_s, advanced)
        if key not in self._steps:
            cfg = method_mpc_config(self.cfg, name, getattr(self.models, "closedloop", None))
            self._steps[key] = make_controller_step(
                make_method(name),
                cfg,
                hold_residual=name.endswith(HELD),
                delay_s=delay_s,
                advanced=advanced,
            )
        return self._steps[key]

    def fly_trials(
        self,
        name: str,
        scenario: Scenario,
        seeds: Sequence[int],
        estimated: bool = False,
        compensate_delay: bool = False,
        threads: int = FLIGHT_THREADS,
        advanced: bool | None = None,
    ) -> list[Flight]:
        """:meth:`fly` for each of ``seeds``, in their order, up to ``threads`` at a time
        (:func:`flight_threads`: at most one per CPU less one).

        Each flight has its own simulator, estimator and learner and calls the same compiled
        functions (built here first, so that no two threads build one), so the flights are
        those :meth:`fly` flies one by one, bit for bit; only their ``step_ms`` (wall time
        per step) are measured with the other flights running beside them."""
        delay = scenario.command_delay_s if compensate_delay else 0.0
        advanced = self.advanced if advanced is None else advanced
        self.step_fn(name, delay, advanced)
        if estimated:
            self._estimation()
        if delay and estimated:
            self._predictor()

        def one(seed: int) -> Flight:
            return self.fly(name, scenario, seed, estimated, compensate_delay, advanced)

        threads = flight_threads(threads)
        if threads <= 1 or len(seeds) <= 1:
            return [one(s) for s in seeds]
        with ThreadPoolExecutor(max_workers=threads) as pool:
            return list(pool.map(one, seeds))

    def fly(
        self,
        name: str,
        scenario: Scenario,
        seed: int = 0,
        estimated: bool = False,
        compensate_delay: bool = False,
        advanced: bool | None = None,
    ) -> Flight:
        """Fly one trial; returns the log with its metrics.

        ``estimated``: every method sees the state estimate (:class:`MocapEstimate`) instead
        of the ground-truth state, as in the service stack; ours and its variants then add
        the estimate's noise to their observation noise at every step, as the stack's
        adapter does (:func:`arcade_core.adaptation.state_noise_sigma2`).
        ``compensate_delay``: the method knows the scenario's ``command_delay_s`` and
        learns and plans from the state predicted over it, against the reference that much
        later (:func:`make_controller_step`'s ``delay_s``); on the estimate, its variance is
        carried through the prediction (:func:`arcade_core.dynamics.predict_over_delay`)
        before it enters the observation noise. The metrics are of the true trajectory
        against the reference at the control instants either way.
        ``advanced``: the advanced-step controller (:func:`make_controller_step`; ``None``:
        the runner's ``advanced``).
        """
        advanced = self.advanced if advanced is None else advanced
        sim_seed, offset, jitter = trial(seed)
        n = int(np.ceil(scenario.t_end / DT - 1e-9)) + 1
        k_release = round(scenario.t_release / DT) + jitter
        if scenario.release_fraction < 0:
            k_release = -1
        N = self.cfg.N
        x_ref_all, u_ref_all = reference(scenario, n, N)
        delay = scenario.command_delay_s if compensate_delay else 0.0
        x_ref_ctrl, u_ref_ctrl = (
            reference(scenario, n, N, delay) if delay else (x_ref_all, u_ref_all)
        )
        sim = QuadrotorSim(
            payload_mass=scenario.payload_g / 1000.0,
            cable_length=scenario.cable_length_m,
            rigid_payload=scenario.rigid_payload,
            seed=sim_seed,
            command_delay_s=scenario.command_delay_s,
        )
        x = sim.reset(np.asarray(scenario.start) + offset)
        step = self.step_fn(name, delay, advanced)
        dt = self.dtype
        learner = initial_learner(name, self.models, dt, estimated)
        estimate = state_noise = None
        if estimated:
            estimate_step, jacobian = self._estimation()
            estimate = MocapEstimate(sim, dt, estimate_step)
            x_seen, var = estimate()
            if isinstance(learner, BeamLearner):
                learner = per_output_noise(learner)
                base_sigma2 = learner.config.sigma2

                def state_noise(a, x_prev, u, var_prev, var_next):
                    sigma2 = adaptation.state_noise_sigma2(
                        base_sigma2,
                        jacobian(jnp.asarray(x_prev, dt), jnp.asarray(u, dt)),
                        jnp.asarray(var_prev, dt),
                        jnp.asarray(var_next, dt),
                        a.vld.delta_scale,
                    )
                    return a._replace(config=a.config._replace(sigma2=sigma2))
        else:
            x_seen, var = x, np.zeros(13)
        p = nominal_params()
        if isinstance(learner, MassOracle):  # what the rotors carry beyond the nominal
            learner = learner._replace(  # mass: the payload and the cable's lumped mass
                k_release=jnp.asarray(k_release, jnp.int32),
                payload_kg=jnp.asarray(sim.carried_mass() - float(p.mass), dt),
            )
        # Warm start and smoothness reference: the nominal hover input (Appendix D U_0).
        u0 = jnp.asarray([float(p.mass) * float(p.gravity), 0.0, 0.0, 0.0], dt)
        carry = Carry(
            learner, jnp.broadcast_to(u0, (N, 4)), u0, jnp.asarray(x_seen, dt), jnp.zeros((), bool)
        )
        if advanced:
            carry = planned_carry(carry, self.cfg)
        x_prev, var_prev = x_seen, var
        u_applied = np.asarray(u0)
        X, U, D, T_ms = (np.zeros((n, 13)), np.zeros((n, 4)), np.zeros((n, 17)), np.zeros(n))
        x_ref_np = np.asarray(x_ref_all[:n])
        crashed = False
        n_done = n
        beam = isinstance(learner, BeamLearner)
        rec = {
            "xp": np.zeros((n, 13)),
            "up": np.zeros((n, 4)),
            "x": np.zeros((n, 13)),
            "sigma2": [],
            "learned": np.zeros(n, bool),
        }
        for k in range(n):
            if k == k_release:
                sim.release_payload()
            X[k] = x
            t0 = time.perf_counter()
            x_from = x_prev
            if delay and state_noise is not None:  # learned: the states predicted over it
                var = self._predict(
                    jnp.asarray(x_seen, dt), jnp.asarray(var, dt), carry.u_mpc, delay
                )
                x_from = carry.x_prev
            if state_noise is not None and k > 0:  # the transition x_prev -> x_seen
                carry = carry._replace(
                    learner=state_noise(carry.learner, x_from, u_applied, var_prev, var)
                )
            x_prev, var_prev = x_seen, var
            if beam:
                rec["xp"][k], rec["up"][k] = np.asarray(carry.x_prev), u_applied
                rec["sigma2"].append(np.asarray(carry.learner.config.sigma2, float))
                rec["learned"][k] = bool(carry.started)
            carry, u, diag = step(
                carry,
                jnp.asarray(x_seen, dt),
                jnp.asarray(u_applied, dt),
                k,
                x_ref_ctrl,
                u_ref_ctrl,
            )
            u = np.asarray(u)
            if beam:
                rec["x"][k] = np.asarray(carry.x_prev)
            T_ms[k] = 1e3 * (time.perf_counter() - t0)
            D[k] = np.asarray(diag)
            u_applied = sim.set_setpoint(u)
            U[k] = u_applied
            if (
                np.linalg.norm(x[:3] - x_ref_np[k, :3]) > CRASH_ERROR_M
                or x[2] < 0.02
                or not np.all(np.isfinite(x))
            ):
                crashed, n_done = True, k + 1
                break
            x = sim.step(DT)
            x_seen, var = estimate() if estimate is not None else (x, var)
        t = np.arange(n_done) * DT
        flight = Flight(
            name,
            scenario,
            seed,
            t,
            X[:n_done],
            x_ref_np[:n_done],
            U[:n_done],
            D[:n_done],
            k_release * DT if k_release >= 0 else float("nan"),
            crashed,
            T_ms[:n_done],
        )
        if beam:
            flight.learning = {
                k: np.asarray(v)[:n_done] for k, v in rec.items() if k != "sigma2"
            } | {"sigma2": np.stack(rec["sigma2"])}
        flight.metrics = flight_metrics(flight)
        return flight


#: Column of ``Flight.diag`` holding the changepoint flag (after the 13 sigma entries), and
#: the column of the MPC solve's convergence flag (:func:`make_controller_step`'s ``diag``).
DIAG_CHANGEPOINT = 13
DIAG_CONVERGED = 16


def flight_metrics(f: Flight) -> dict[str, float]:
    """RMSE, z-RMSE on the figure-eight part; shift and settling at the release.

    Diagnostics beside the paper's metrics, on the figure-eight part too: the RMS of the
    step-to-step change of the thrust command (N) and of the body-rate commands (rad/s,
    over the three axes; :func:`arcade_core.metrics.increment_rms`), the fraction of MPC
    solves that converged within the iteration limit, and for the beam methods the fraction
    of control steps on which a changepoint was flagged (``nan`` for the others).
    """
    inf = float("inf")
    name = base_name(f.method)
    # The methods whose learner has a changepoint variable: ours and its variants, the
    # flagship (its detector's declarations) and its ablations with a beam or a detector.
    beam = name.startswith("ours") or (
        name.startswith(FLAGSHIP) and name not in ("arcade_no_model", "arcade_no_restart")
    )
    if f.crashed:
        return {
            "rmse_m": inf,
            "rmse_z_m": inf,
            "shift_m": inf,
            "settling_s": inf,
            "thrust_increment_rms_n": inf,
            "rate_increment_rms_rad_s": inf,
            "changepoint_rate": float("nan"),
            "converged_fraction": float("nan"),
            "crashed": 1.0,
        }
    sel = f.t >= f.scenario.t_figure - 1e-9
    p, pr = jnp.asarray(f.x[sel, :3]), jnp.asarray(f.x_ref[sel, :3])
    e_z = jnp.asarray(f.error[:, 2])
    t = jnp.asarray(f.t)
    du = np.asarray(metrics.increment_rms(jnp.asarray(f.u[sel])))
    out = {
        "rmse_m": float(metrics.position_rmse(p, pr)),
        "rmse_z_m": float(metrics.z_rmse(p, pr)),
        "shift_m": float("nan"),
        "settling_s": float("nan"),
        "thrust_increment_rms_n": float(du[0]),
        "rate_increment_rms_rad_s": float(np.sqrt(np.mean(du[1:] ** 2))),
        "changepoint_rate": float(np.mean(f.diag[sel, DIAG_CHANGEPOINT])) if beam else float("nan"),
        "converged_fraction": float(np.mean(f.diag[sel, DIAG_CONVERGED])),
        "crashed": 0.0,
    }
    if np.isfinite(f.t_release):
        out["shift_m"] = float(metrics.shift_magnitude(t, e_z, f.t_release))
        out["settling_s"] = float(metrics.settling_time(t, e_z, f.t_release, band=0.05).time)
    return out
