"""The training and validation flights of the paper's Sec. V-B / Appendix D ("Data Collection").

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

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from arcade_control.expert import START, ExpertPilot, RandomPath
from arcade_control.nominal import CONTROL_DT, LOG_DT, LOG_PER_CONTROL, nominal_next
from arcade_io import atomicfile
from arcade_io.vehicle import load_vehicle, quadrotor_params
from simulator.quadrotor import QuadrotorSim

#: Payloads of the paper's training and validation flights [g].
TRAIN_PAYLOADS_G = (10.0, 100.0, 200.0)
VAL_PAYLOADS_G = (75.0, 125.0, 175.0)
#: Bump when the generator changes so that cached logs are regenerated.
DATA_VERSION = 10
EXCITATION_STD = np.array([2.0, 0.4, 0.4, 0.4])  # thrust N, rates rad/s
EXCITATION_TAU_S = 0.2  # correlation time of the excitation


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
