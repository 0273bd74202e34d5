"""Quadrotor flight data of the paper's Sec. V-B / Appendix D ("Data Collection").

Training flights carry *rigidly attached* payloads of 10, 100 and 200 g (3 min each),
validation flights 75, 125 and 175 g (1 min each, different random trajectories). The
"expert pilot" is :class:`ExpertPilot`, a cascaded position/attitude controller that
produces what the vehicle's offboard interface takes (collective thrust + body-rate
setpoints) while tracking a smooth random cubic Hermite spline through random waypoints (mean
segment speeds 0.5-3.0 m/s, peak speed capped at 3.5 m/s, peak acceleration at 8 m/s^2 —
the envelope of the closed-loop figure-eight at 2.5 m/s mean speed —
a slowly varying yaw). Like a human pilot it knows the payload only through the hover
throttle it trimmed after take-off.
Low-pass Gaussian excitation (AR(1) with a 0.2 s correlation time; 2.0 N thrust, 0.4 rad/s
rates, clipped at 2 sigma) is added to the setpoints so that the data are informative
about the input channels. Two choices matter for what the residual model learns:

* the excitation is slower than the control period: the motors lag the thrust command by
  25 ms, so white per-step excitation would teach the model that thrust acts only about
  half as strongly as it does once the motors have caught up;
* it is strong: the payload mass is not part of ``(x, u)``, and a heavier payload is flown
  with more thrust, so across the three flights thrust and the (negative) vertical
  residual are confounded. The more the thrust varies *within* each flight, the less the
  offline model mistakes "more thrust" for "heavier payload" (which would make it
  under-estimate the thrust authority inside the MPC).

Rates and residuals. The pilot (like the closed-loop MPC of ``quadrotor_closedloop``)
updates its setpoint every :data:`CONTROL_DT` = 0.05 s (20 Hz) and holds it in between;
the log is recorded at :data:`LOG_DT` = 0.01 s (100 Hz): ground-truth simulator state
(13: p, v, q wxyz, omega; ENU/FLU) and the applied (clamped) setpoint. The residual is
learned *at the MPC step*, which is the control period: transitions are taken from the
100 Hz log every 5 samples, at the instants where a new setpoint starts, so that the input
is constant over the transition, and ``delta = x(t + 0.05) - f_nom(x(t), u(t))`` with the
nominal RK4 model over 0.05 s. The MPC (N = 20, 1 s horizon) then rolls
``f_nom + theta phi`` forward with the very step the residual was learned at; no rescaling
between periods is needed.

Everything is deterministic given the seed. Generating the paper-size sets takes about a
minute of simulation on a laptop core; :func:`make_dataset`/:func:`make_validation` cache
the logs (``$ARCADE_DATA_CACHE``, default ``~/.cache/arcade/data``) keyed by their
arguments and :data:`DATA_VERSION`.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from arcade_core.dynamics import quadrotor_step
from arcade_io import atomicfile
from arcade_io.vehicle import load_vehicle, quadrotor_params

if TYPE_CHECKING:
    from scipy.interpolate import CubicHermiteSpline

#: Control (= MPC step = residual) period [s] and log period [s].
CONTROL_DT = 0.05
LOG_DT = 0.01
LOG_PER_CONTROL = round(CONTROL_DT / LOG_DT)
#: Payloads of the paper's training and validation flights [g].
TRAIN_PAYLOADS_G = (10.0, 100.0, 200.0)
VAL_PAYLOADS_G = (75.0, 125.0, 175.0)
#: Bump when the generator changes so that cached logs are regenerated.
DATA_VERSION = 10

#: Flight envelope of the random trajectories (world ENU, m).
BOX_LOW = np.array([-2.5, -2.5, 1.3])
BOX_HIGH = np.array([2.5, 2.5, 3.3])
START = np.array([0.0, 0.0, 2.0])
MAX_SPEED = 3.5  # m/s
MAX_ACCEL = 8.0  # m/s^2
SEGMENT_SPEED = (0.5, 3.0)  # mean speed between waypoints, m/s
EXCITATION_STD = np.array([2.0, 0.4, 0.4, 0.4])  # thrust N, rates rad/s
EXCITATION_TAU_S = 0.2  # correlation time of the excitation
HOVER_LEAD_S = 3.0  # hover at the start so the pilot's trim settles


# ------------------------------------------------------------------------ trajectories


class RandomPath:
    """Smooth random reference: C1 cubic Hermite spline through random waypoints.

    Segment durations follow random mean speeds in :data:`SEGMENT_SPEED`; the whole
    time axis is then stretched until the peak speed is at most :data:`MAX_SPEED` and the
    peak acceleration at most :data:`MAX_ACCEL`. The path starts with a hover of
    :data:`HOVER_LEAD_S` at :data:`START`. Yaw is a slow random sinusoid (+-0.4 rad).
    """

    def __init__(self, rng: np.random.Generator, duration: float):
        pts, times = [START, START], [0.0, HOVER_LEAD_S]
        while times[-1] < duration + 5.0:
            nxt = rng.uniform(BOX_LOW, BOX_HIGH)
            dist = float(np.linalg.norm(nxt - pts[-1]))
            times.append(times[-1] + max(dist / rng.uniform(*SEGMENT_SPEED), 1.0))
            pts.append(nxt)
        spline = self._fit(np.asarray(times), np.asarray(pts))
        grid = np.arange(HOVER_LEAD_S, times[-1], 0.01)
        vmax = np.max(np.linalg.norm(spline(grid, 1), axis=1))
        amax = np.max(np.linalg.norm(spline(grid, 2), axis=1))
        # Stretching time by s divides speeds by s and accelerations by s^2.
        stretch = max(1.0, vmax / MAX_SPEED, np.sqrt(amax / MAX_ACCEL))
        t = np.asarray(times)
        t = np.where(t > HOVER_LEAD_S, HOVER_LEAD_S + (t - HOVER_LEAD_S) * stretch, t)
        self.spline = self._fit(t, np.asarray(pts))
        self.yaw_amp = rng.uniform(0.1, 0.4)
        self.yaw_freq = rng.uniform(0.02, 0.08)
        self.yaw_phase = rng.uniform(0.0, 2.0 * np.pi)

    @staticmethod
    def _fit(times: np.ndarray, pts: np.ndarray) -> CubicHermiteSpline:
        # Imported here: SciPy's interpolate costs ~0.7 s of import in every process that
        # imports this module (each service of the stack), and only the data needs it.
        from scipy.interpolate import CubicHermiteSpline

        # Catmull-Rom velocities (central differences, rest at both ends): unlike a global
        # C2 spline this cannot overshoot far between unevenly spaced waypoints.
        vel = np.zeros_like(pts)
        vel[1:-1] = (pts[2:] - pts[:-2]) / (times[2:] - times[:-2])[:, None]
        return CubicHermiteSpline(times, pts, vel)

    def __call__(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Position, velocity, acceleration and yaw at time ``t``."""
        s = self.spline
        ramp = min(1.0, t / HOVER_LEAD_S)
        yaw = ramp * self.yaw_amp * np.sin(2 * np.pi * self.yaw_freq * t + self.yaw_phase)
        yaw -= ramp * self.yaw_amp * np.sin(self.yaw_phase)  # start at yaw 0
        return s(t), s(t, 1), s(t, 2), float(yaw)


# ------------------------------------------------------------------------ the pilot


def _rotmat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


class ExpertPilot:
    """Cascaded position (PID) / attitude (P) controller emitting thrust + body rates.

    Position loop: ``a = a_ref + Kp e_p + Kd e_v + Ki int(e_p)`` with the tilt limited to
    ``max_tilt``; thrust vector ``F = m (a + g e3)``, collective thrust ``F . z_body``,
    where ``m`` is the mass implied by the hover throttle the pilot trimmed after take-off
    (:meth:`trim`), as a pilot knows how heavy the vehicle feels. Attitude
    loop (geometric, Lee et al. 2010): ``omega_cmd = -K_R vee(R_d^T R - R^T R_d) / 2``.
    """

    def __init__(
        self,
        mass: float,
        gravity: float = 9.81,
        kp: float = 6.0,
        kd: float = 4.0,
        ki: float = 2.0,
        k_att: float = 6.0,
        max_tilt: float = np.deg2rad(50.0),
        integral_limit: float = 3.0,
    ):
        self.mass, self.gravity = float(mass), float(gravity)
        self.kp, self.kd, self.ki, self.k_att = kp, kd, ki, k_att
        self.max_tilt, self.integral_limit = max_tilt, integral_limit
        self.integral = np.zeros(3)

    def trim(self, hover_thrust: float) -> None:
        """Learn the hover thrust [N] (after take-off): feedback is scaled by the mass it
        implies, the integrator only removes what is left."""
        self.mass = hover_thrust / self.gravity
        self.integral[:] = 0.0

    def __call__(self, x: np.ndarray, ref, dt: float) -> np.ndarray:
        p_ref, v_ref, a_ref, yaw = ref
        p, v, q = x[0:3], x[3:6], x[6:10]
        e_p = p_ref - p
        self.integral = np.clip(self.integral + e_p * dt, -self.integral_limit, self.integral_limit)
        a = a_ref + self.kp * e_p + self.kd * (v_ref - v) + self.ki * self.integral
        a_z = max(a[2] + self.gravity, 0.3 * self.gravity)
        horiz = a[:2]
        lim = np.tan(self.max_tilt) * a_z
        norm = np.linalg.norm(horiz)
        if norm > lim:
            horiz = horiz * (lim / norm)
        f = self.mass * np.array([horiz[0], horiz[1], a_z])
        r = _rotmat(q)
        thrust = float(f @ r[:, 2])
        z_d = f / np.linalg.norm(f)
        x_c = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        y_d = np.cross(z_d, x_c)
        y_d /= np.linalg.norm(y_d)
        r_d = np.stack([np.cross(y_d, z_d), y_d, z_d], axis=1)
        e = r_d.T @ r - r.T @ r_d
        e_r = 0.5 * np.array([e[2, 1], e[0, 2], e[1, 0]])
        return np.concatenate([[thrust], -self.k_att * e_r])


# ------------------------------------------------------------------------ flights


def fly_expert(
    payload_g: float,
    duration_s: float,
    seed: int | np.random.SeedSequence,
    *,
    vehicle: dict[str, Any] | None = None,
    excitation_std: np.ndarray = EXCITATION_STD,
) -> dict[str, np.ndarray]:
    """One expert flight with a rigidly attached payload; the 100 Hz log.

    Returns ``t (n,)``, ``X (n, 13)`` ground-truth states and ``U (n, 4)`` the (clamped)
    setpoint in effect from ``t`` on, with ``n = 5 * steps + 1`` (the last row repeats the
    last setpoint).
    """
    from simulator import QuadrotorSim

    vehicle = vehicle if vehicle is not None else load_vehicle()
    params = quadrotor_params(vehicle)
    ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    path_ss, noise_ss, sim_ss = ss.spawn(3)
    rng_path = np.random.default_rng(path_ss)
    rng_noise = np.random.default_rng(noise_ss)
    sim = QuadrotorSim(
        vehicle,
        payload_mass=payload_g / 1000.0,
        rigid_payload=payload_g > 0.0,
        seed=int(sim_ss.generate_state(1)[0]),
    )
    path = RandomPath(rng_path, duration_s)
    pilot = ExpertPilot(float(params.mass), float(params.gravity))
    x = sim.reset(START)
    # The pilot trims the hover throttle before the log starts (as after a take-off).
    pilot.trim(sim.hover_thrust())
    steps = round(duration_s / CONTROL_DT)
    n = steps * LOG_PER_CONTROL + 1
    t_log = np.arange(n) * LOG_DT
    X = np.empty((n, 13))
    U = np.empty((n, 4))
    X[0] = x
    # AR(1) excitation: low-pass Gaussian noise with correlation time EXCITATION_TAU_S.
    a = np.exp(-CONTROL_DT / EXCITATION_TAU_S)
    noise = np.zeros(4)
    for k in range(steps):
        t = k * CONTROL_DT
        u = pilot(x, path(t), CONTROL_DT)
        w = np.clip(rng_noise.standard_normal(4), -2.0, 2.0)
        noise = a * noise + np.sqrt(1.0 - a * a) * w
        u = sim.set_setpoint(u + noise * excitation_std)
        for j in range(LOG_PER_CONTROL):
            i = k * LOG_PER_CONTROL + j
            U[i] = u
            x = sim.step(LOG_DT)
            X[i + 1] = x
    U[-1] = U[-2]
    if not (np.isfinite(X).all() and np.isfinite(U).all()):
        raise RuntimeError("expert flight produced non-finite states")
    return {"t": t_log, "X": X, "U": U}


def transitions(X: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(x_k, u_k, x_{k+1})`` at the control period from one 100 Hz log (module docstring)."""
    idx = np.arange(0, X.shape[0] - LOG_PER_CONTROL, LOG_PER_CONTROL)
    return X[idx], U[idx], X[idx + LOG_PER_CONTROL]


@functools.cache
def nominal_params():
    """Nominal-model parameters of the shipped default vehicle (read once).

    Evaluated eagerly even when first called while a function is being traced, so the
    cached value never holds tracers.
    """
    with jax.ensure_compile_time_eval():
        return quadrotor_params(load_vehicle())


def f_nom(x, u):
    """Nominal RK4 step ``f_nom(x, u)`` over :data:`CONTROL_DT` (Appendix D), one sample."""
    return quadrotor_step(x, u, nominal_params(), CONTROL_DT)


def nominal_next(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """:func:`f_nom` for every row of ``x`` (n, 13) and ``u`` (n, 4)."""
    return np.asarray(jax.jit(jax.vmap(f_nom))(jnp.asarray(x), jnp.asarray(u)), dtype=float)


def _flights(
    kind: str,
    seed: int,
    minutes_per_payload: float,
    payloads_g: tuple[float, ...],
    cache: bool,
    progress,
) -> list[dict[str, np.ndarray]]:
    key = json.dumps(
        {
            "kind": kind,
            "seed": seed,
            "min": minutes_per_payload,
            "payloads": [float(p) for p in payloads_g],
            "version": DATA_VERSION,
        },
        sort_keys=True,
    )
    path = _cache_dir() / f"quadrotor_{hashlib.sha256(key.encode()).hexdigest()[:16]}.npz"
    if cache and path.is_file():
        with np.load(path) as f:
            return [
                {"t": f[f"t{i}"], "X": f[f"X{i}"], "U": f[f"U{i}"]} for i in range(len(payloads_g))
            ]
    # Training and validation seeds come from different branches: disjoint trajectories.
    branch = {"train": 0, "val": 1}[kind]
    seqs = np.random.SeedSequence([seed, branch]).spawn(len(payloads_g))
    flights = []
    for i, (pay, ss) in enumerate(zip(payloads_g, seqs)):
        if progress is not None:
            progress(
                f"{kind} flight {i + 1}/{len(payloads_g)}: {pay:g} g, {minutes_per_payload:g} min"
            )
        flights.append(fly_expert(pay, 60.0 * minutes_per_payload, ss))
    if cache:
        arrays = {f"{k}{i}": f[k] for i, f in enumerate(flights) for k in ("t", "X", "U")}
        with atomicfile.atomic_open(path, "wb") as f:
            np.savez_compressed(f, **arrays)
    return flights


def _cache_dir() -> Path:
    env = os.environ.get("ARCADE_DATA_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "arcade" / "data"


def _assemble(flights, payloads_g) -> dict[str, np.ndarray]:
    logs = {"t": [], "X": [], "U": [], "payload_g": [], "flight": []}
    tr = {"x": [], "u": [], "x_next": [], "transition_payload_g": [], "transition_flight": []}
    for i, (f, pay) in enumerate(zip(flights, payloads_g)):
        n = f["X"].shape[0]
        logs["t"].append(f["t"])
        logs["X"].append(f["X"])
        logs["U"].append(f["U"])
        logs["payload_g"].append(np.full(n, float(pay)))
        logs["flight"].append(np.full(n, i))
        x, u, xn = transitions(f["X"], f["U"])
        tr["x"].append(x)
        tr["u"].append(u)
        tr["x_next"].append(xn)
        tr["transition_payload_g"].append(np.full(x.shape[0], float(pay)))
        tr["transition_flight"].append(np.full(x.shape[0], i))
    out = {k: np.concatenate(v) for k, v in {**logs, **tr}.items()}
    out["delta"] = out["x_next"] - nominal_next(out["x"], out["u"])
    out["control_dt"] = np.asarray(CONTROL_DT)
    out["log_dt"] = np.asarray(LOG_DT)
    return out


def make_dataset(
    seed: int = 0,
    minutes_per_payload: float = 3.0,
    payloads_g: tuple[float, ...] = TRAIN_PAYLOADS_G,
    *,
    cache: bool = True,
    progress=None,
) -> dict[str, np.ndarray]:
    """Training flights (Appendix D): one flight per payload, rigidly attached.

    Returns a dict of arrays. The 100 Hz logs: ``t``, ``X (n, 13)``, ``U (n, 4)``,
    ``payload_g (n,)``, ``flight (n,)`` (flight index; ``t`` restarts per flight). The
    transitions at the control period: ``x``, ``u``, ``x_next``, ``delta`` (residual of
    the nominal model, physical units), ``transition_payload_g``, ``transition_flight``.
    Also ``control_dt`` and ``log_dt`` (0-d). ``progress(msg)`` is told about each flight.
    """
    flights = _flights("train", seed, minutes_per_payload, tuple(payloads_g), cache, progress)
    return _assemble(flights, payloads_g)


def make_validation(
    seed: int = 0,
    minutes_per_payload: float = 1.0,
    payloads_g: tuple[float, ...] = VAL_PAYLOADS_G,
    *,
    cache: bool = True,
    progress=None,
) -> dict[str, np.ndarray]:
    """Validation flights (Sec. V-B): 75, 125, 175 g, 1 min each, disjoint trajectories.

    Same layout as :func:`make_dataset`.
    """
    flights = _flights("val", seed, minutes_per_payload, tuple(payloads_g), cache, progress)
    return _assemble(flights, payloads_g)


def flight_transitions(data: dict[str, np.ndarray], flight: int):
    """``(x, u, x_next, delta)`` of one flight of a dataset, in time order."""
    sel = data["transition_flight"] == flight
    return data["x"][sel], data["u"][sel], data["x_next"][sel], data["delta"][sel]
