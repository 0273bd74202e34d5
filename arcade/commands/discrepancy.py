"""`arcade discrepancy LOG` — where do model and data disagree, and which effect is missing.

The workflow of design §6 on one flight log (CSV with the columns of :mod:`arcade_io.flightlog`,
any constant rate):

1. **Align**: predictions of the current model (the vehicle or model file: nominal model,
   motors, rate loop and the file's ``[effects]``) from every measured state with the
   measured inputs, over one model step (``--step``, default the 0.05 s control period,
   rounded to whole log samples) and over a short horizon; residual per state component.
2. **Localise**: residual RMS per component, per regime (speed, height, thrust, tilt for
   the quadrotor; speeds, pole angle, force for the cartpole) and per time segment (the
   changepoint machinery of Algorithm 1 segments the log).
3. **Name**: all library effects of the system are candidates at once; sparse selection
   (BIC among subsets in which every effect explains a relevant share) with a block
   bootstrap for confidence and parameter intervals
   (:mod:`arcade_core.discrepancy.identify`). Only effects with confidence at least
   ``--confidence`` are added; otherwise the answer is "no confident effect". A selected
   effect whose signature in this log stays within the noise (it could not halve the
   one-step gap, :func:`effect_visibility`) is reported as "below detectability" and not
   added (quadrotor; the library states each effect's limit on the standard trajectory).
4. **Add**: an updated vehicle/model file with the effects in its ``[effects]`` table,
   loadable by ``arcade_io.vehicle.load_vehicle``, the simulator and the JAX model.
5. **Show**: the log is split in time into blocks of 2 s; a ``--heldout`` fraction of
   them, spread evenly over the flight, is only evaluated, never fitted (so that the
   held-out part sees the same kinds of flight as the fitted part). Before/after one-step
   RMSE and multi-step CRMSE per component, plots and a short report in ``--out``.

Inputs are a zero-order hold per row (:mod:`arcade_io.flightlog`: the setpoint in effect from
``t`` to the next row). A log whose setpoint changed between rows (resampled without regard
to the controller's instants) shows an apparent input lag, which the workflow will name.

``heldout_rmse_before/after`` is the one-step RMSE over the state components the added
effects act on (the library's ``acts_on``) where their contribution to the held-out
prediction is at least half of what is left unexplained (a ground effect acts on the
vertical velocity of a nearly level vehicle, hardly visibly on the horizontal ones); all
velocity and rate components when nothing is added. SI units; ``gap_before/after`` give
every component.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from arcade_io import atomicfile, jsonout

HELP = "find where a flight log and the model disagree, name the missing effect, show the fix"

QUAD_COMPONENTS = (
    "px", "py", "pz", "vx", "vy", "vz", "att_x", "att_y", "att_z", "wx", "wy", "wz",
)  # fmt: skip
CART_COMPONENTS = ("x", "xdot", "theta", "thetadot")
#: Residual channels used for identification (indices into the state).
QUAD_CHANNELS = (3, 4, 5, 10, 11, 12)
CART_CHANNELS = (1, 3)
#: Gap-to-noise ratio at which adding an effect halves the one-step RMSE (``sqrt(3)``).
HALVING_RATIO = 3.0**0.5
_PAD_SAMPLES = 4096
_PAD_WINDOWS = 512


@dataclass(frozen=True)
class Settings:
    """Workflow settings (module docstring); times in seconds."""

    step_s: float = 0.05
    heldout: float = 0.3
    heldout_block_s: float = 2.0
    horizon_s: float = 1.0
    burn_in_s: float = 3.0
    block_s: float = 2.0
    confidence: float = 0.9
    min_explained: float = 0.02
    min_size: float = 0.02
    n_boot: int = 200
    seed: int = 0


#: Valid range of the held-out fraction (``--heldout``).
HELDOUT_RANGE = (0.05, 0.5)
#: Fewest one-step windows the fit needs.
MIN_FIT_WINDOWS = 50


def add_arguments(p: argparse.ArgumentParser) -> None:
    from arcade_io.flightlog import columns
    from arcade_io.runs import count, number

    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = (
        "flight log columns (CSV with a header row, one row per sample at a constant rate,\n"
        "SI units, world ENU, body FLU; extra columns are ignored; see arcade_io.flightlog):\n"
        f"  quadrotor: {', '.join(columns('quadrotor'))}\n"
        "      (u0 collective thrust [N], u1-u3 body-rate setpoints [rad/s], each in effect\n"
        "      from its row's t to the next row's)\n"
        f"  cartpole:  {', '.join(columns('cartpole'))}  (u: force on the cart [N])\n"
        "`arcade simulate --out LOG` writes such a log."
    )
    p.add_argument("log", type=Path, help="flight log (CSV; the columns are listed below)")
    p.add_argument(
        "--system",
        choices=["quadrotor", "cartpole"],
        default="quadrotor",
        help="the system that flew the log (default: %(default)s)",
    )
    p.add_argument(
        "--vehicle", type=Path, default=None,
        help="vehicle file (quadrotor) or cartpole model file; default the shipped one",
    )  # fmt: skip
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder, created if needed (default: runs/<time>-discrepancy-<system>)",
    )
    s = Settings()
    lo, hi = HELDOUT_RANGE
    p.add_argument(
        "--step",
        type=number(0.0, s.heldout_block_s, low_open=True, high_open=True),
        default=s.step_s,
        help=f"model step [s], more than 0 and less than {s.heldout_block_s:g} (the held-out "
        "block), rounded to whole log samples (default: %(default)s)",
    )
    p.add_argument(
        "--heldout",
        type=number(lo, hi),
        default=s.heldout,
        help=f"held-out fraction of the log, {lo:g} to {hi:g} (default: %(default)s)",
    )
    p.add_argument(
        "--horizon",
        type=number(0.0, s.heldout_block_s, low_open=True, high_open=True),
        default=s.horizon_s,
        help=f"CRMSE horizon [s], more than 0 and less than {s.heldout_block_s:g} (the "
        "held-out block) (default: %(default)s)",
    )
    p.add_argument(
        "--confidence",
        type=number(0.5, 1.0),
        default=s.confidence,
        help="bootstrap confidence an effect needs to be added to the model file, 0.5 to 1 "
        "(default: %(default)s)",
    )
    p.add_argument(
        "--bootstrap",
        type=count(10),
        default=s.n_boot,
        help="bootstrap resamples, at least 10 (default: %(default)s)",
    )
    p.add_argument(
        "--seed", type=count(0), default=s.seed, help="bootstrap seed (default: %(default)s)"
    )


# --------------------------------------------------------------------------- models


def quad_model_from_vehicle(vehicle: dict[str, Any]):
    """:class:`~arcade_core.discrepancy.quadrotor.QuadModel` of a vehicle file."""
    import jax.numpy as jnp

    from arcade_core.discrepancy.quadrotor import QuadModel
    from arcade_io.vehicle import quadrotor_params

    rotors, rl = vehicle["rotors"], vehicle["rate_loop"]
    if rotors.get("layout", "x") != "x":
        raise ValueError("only quad-x vehicles are supported")
    b = float(vehicle["body"]["arm_length_m"]) / math.sqrt(2.0)
    h = float(rotors.get("rotor_height_m", 0.015))
    tmax = float(rotors["max_thrust_n"])
    pos = jnp.array([[b, -b, h], [-b, b, h], [b, b, h], [-b, -b, h]])
    # Largest torque per axis (what normalised torque 1 means), as the mixer defines it.
    torque_max = jnp.array(
        [2.0 * b * tmax, 2.0 * b * tmax, 2.0 * float(rotors["yaw_moment_coeff_m"]) * tmax]
    )

    def vec(key: str, default: float):
        return jnp.asarray(rl.get(key, [default] * 3), dtype=float).reshape(3)

    return QuadModel(
        params=quadrotor_params(vehicle),
        motor_tau=float(rotors["motor_time_constant_s"]),
        rotors=pos,
        rate_p=vec("p", 0.0),
        rate_i=vec("i", 0.0),
        rate_d=vec("d", 0.0),
        rate_ff=vec("ff", 0.0),
        torque_max=torque_max,
        d_cutoff_rad_s=2.0 * math.pi * float(rl.get("d_cutoff_hz", 30.0)),
    )


def load_cartpole_file(path: str | Path | None) -> dict[str, Any]:
    """A cartpole model file (TOML ``[cartpole] M, m, L, g`` + ``[effects]``); ``None``:
    the Appendix D nominal model."""
    from arcade_core.dynamics.params import CARTPOLE_NOMINAL as N
    from arcade_io.vehicle import read_toml

    data: dict[str, Any] = {"cartpole": {"M": N.M, "m": N.m, "L": N.L, "g": N.g}}
    if path is not None:
        loaded = read_toml(path, "cartpole model file")
        if not isinstance(loaded.get("cartpole"), dict):
            raise ValueError(f"{path}: missing [cartpole] table (M, m, L)")
        data = {**loaded, "cartpole": {**data["cartpole"], **loaded["cartpole"]}}
        for k in ("M", "m", "L", "g"):
            v = data["cartpole"][k]
            if isinstance(v, bool) or not isinstance(v, int | float) or not 0 < v < math.inf:
                raise ValueError(f"{path}: [cartpole] {k} must be a positive number, got {v!r}")
    return data


class _System:
    """One system's model, parameter layout and jitted predictions."""

    def __init__(self, system: str, vehicle: dict[str, Any]):
        from arcade.commands.simulate import validate_tables

        self.name = system
        self.vehicle = vehicle
        self.effect_tables = validate_tables(system, dict(vehicle.get("effects", {})))
        if system == "quadrotor":
            from arcade_core.discrepancy import quadrotor as mod

            self.model = quad_model_from_vehicle(vehicle)
            self.components = QUAD_COMPONENTS
            self.channels = QUAD_CHANNELS
        else:
            from arcade_core.discrepancy import cartpole as mod

            c = vehicle["cartpole"]
            self.model = mod.CartpoleModel(
                float(c["M"]), float(c["m"]), float(c["L"]), float(c.get("g", 9.81))
            )
            self.components = CART_COMPONENTS
            self.channels = CART_CHANNELS
        self.mod = mod
        self.groups = mod.GROUPS
        self.low = np.asarray(mod.THETA_LOW, float)
        self.high = np.asarray(mod.THETA_HIGH, float)
        self.theta_base = np.asarray(mod.theta_from_effects(self.model, self.effect_tables))
        self._predict = _jitted_predict(system)

    def predict(self, theta, X, U, starts, steps: int, dt: float) -> np.ndarray:
        """Predictions ``(len(starts), steps, nx)`` (padded to shared shapes for jit reuse)."""
        import jax.numpy as jnp

        n, m = X.shape[0], len(starts)
        n_pad = -(-n // _PAD_SAMPLES) * _PAD_SAMPLES
        m_pad = -(-m // _PAD_WINDOWS) * _PAD_WINDOWS
        Xp = np.concatenate([X, np.repeat(X[-1:], n_pad - n, axis=0)])
        Up = np.concatenate([U, np.repeat(U[-1:], n_pad - n, axis=0)])
        sp = np.concatenate([starts, np.full(m_pad - m, starts[0])]).astype(np.int32)
        out = self._predict(
            self.model,
            jnp.asarray(theta),
            jnp.asarray(Xp),
            jnp.asarray(Up),
            jnp.asarray(sp),
            steps=steps,
            dt=dt,
        )
        return np.asarray(out)[:m]

    def errors(self, X, pred, starts, steps) -> np.ndarray:
        """Measured minus predicted per reporting component, ``(m, steps, n_comp)``."""
        idx = np.asarray(starts)[:, None] + np.arange(1, steps + 1)[None, :]
        meas = X[idx]
        if self.name == "cartpole":
            return meas - pred
        att = _attitude_error(meas[..., 6:10], pred[..., 6:10])
        return np.concatenate(
            [meas[..., 0:6] - pred[..., 0:6], att, meas[..., 10:13] - pred[..., 10:13]],
            axis=-1,
        )

    def effect_params(self, theta, name: str):
        return self.mod.effect_params(theta, name)


@functools.cache
def _jitted_predict(system: str):
    """One jitted prediction function per system (compiled once per shape)."""
    import jax

    from arcade_core.discrepancy import cartpole, quadrotor

    fn = quadrotor.predict_windows if system == "quadrotor" else cartpole.predict_windows
    return jax.jit(fn, static_argnames=("steps", "dt"))


def _attitude_error(q_meas: np.ndarray, q_pred: np.ndarray) -> np.ndarray:
    """Rotation vector (body frame) from the predicted to the measured attitude [rad]."""
    w1, v1 = q_pred[..., :1], q_pred[..., 1:]
    w2, v2 = q_meas[..., :1], q_meas[..., 1:]
    # q_pred^* (x) q_meas
    w = w1 * w2 + np.sum(v1 * v2, axis=-1, keepdims=True)
    v = w1 * v2 - w2 * v1 - np.cross(v1, v2)
    return 2.0 * np.sign(np.where(w == 0, 1.0, w)) * v


# --------------------------------------------------------------------------- workflow


@dataclass
class Outcome:
    """Everything the workflow found (``result`` is the JSON printed by the command)."""

    result: dict[str, Any]
    details: dict[str, Any] = field(default_factory=dict)


def _windows(start: int, stop: int, steps: int, stride: int) -> np.ndarray:
    return np.arange(start, max(stop - steps, start), stride, dtype=np.int64)


def split_blocks(n: int, block: int, fraction: float) -> list[tuple[int, int, bool]]:
    """``(start, stop, held_out)`` blocks of ``block`` samples; a ``fraction`` of them,
    spread evenly over the log (the last block of every ``1/fraction``), is held out."""
    out = []
    n_blocks = max(1, -(-n // block))
    for i in range(n_blocks):
        held = math.floor((i + 1) * fraction) > math.floor(i * fraction)
        out.append((i * block, min(n, (i + 1) * block), held))
    return out


def _block_windows(blocks, held: bool, start: int, steps: int, stride: int) -> np.ndarray:
    parts = [_windows(max(a, start), b, steps, stride) for a, b, h in blocks if h == held]
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)


def _rms(a: np.ndarray, axis=0) -> np.ndarray:
    return np.sqrt(np.mean(np.square(a), axis=axis))


def check_settings(log, system: str, settings: Settings) -> None:
    """``ValueError`` if the workflow cannot run on ``log`` with ``settings`` (cheap: no
    model is built)."""
    lo, hi = HELDOUT_RANGE
    if not lo <= settings.heldout <= hi:
        raise ValueError(f"--heldout must be between {lo:g} and {hi:g}, got {settings.heldout:g}")
    if system != log.system:
        raise ValueError(f"log is a {log.system} log, not {system}")
    dt, n = log.dt, len(log)
    H = max(1, round(settings.step_s / dt))
    burn = round(settings.burn_in_s / dt) if system == "quadrotor" else 0
    blocks = split_blocks(n, max(1, round(settings.heldout_block_s / dt)), settings.heldout)
    n_windows = len(_block_windows(blocks, False, burn, H, H))
    if n_windows < MIN_FIT_WINDOWS:
        raise ValueError(
            f"log too short: {n_windows} fitting windows of {H * dt:.3g} s "
            f"(at least {MIN_FIT_WINDOWS} are needed; {n} samples at {1.0 / dt:.4g} Hz, "
            f"--step {settings.step_s:g})"
        )


def run_workflow(
    log,
    system: str,
    vehicle: str | Path | dict[str, Any] | None = None,
    out: str | Path | None = None,
    settings: Settings = Settings(),
    progress=None,
) -> Outcome:
    """The discrepancy workflow on a :class:`~arcade_io.flightlog.FlightLog` (module docstring).

    Writes the model file, plots and report into ``out`` when it is given. Runs in float64
    whatever the caller's JAX setting, as the command line does (the setting is restored
    after it), so that its numbers do not depend on the caller: in float32 they differ in
    the third or fourth digit, and the secants' scoring overflows.
    """
    from arcade_io import jaxsetup

    with jaxsetup.x64():
        return _run_workflow(log, system, vehicle, out, settings, progress)


def _run_workflow(log, system, vehicle, out, settings, progress) -> Outcome:
    from arcade_core.discrepancy.catalog import effects_for
    from arcade_core.discrepancy.identify import SelectionConfig, identify

    say = progress or (lambda _msg: None)
    check_settings(log, system, settings)
    if system == "quadrotor":
        from arcade_io.vehicle import load_vehicle

        veh = vehicle if isinstance(vehicle, dict) else load_vehicle(vehicle)
        vehicle_path = None if isinstance(vehicle, dict) else vehicle
    else:
        veh = vehicle if isinstance(vehicle, dict) else load_cartpole_file(vehicle)
        vehicle_path = None if isinstance(vehicle, dict) else vehicle
    sysm = _System(system, veh)
    X, U, dt = log.X, log.U, log.dt
    n = len(log)
    H = max(1, round(settings.step_s / dt))
    burn = round(settings.burn_in_s / dt) if system == "quadrotor" else 0
    blocks = split_blocks(n, max(1, round(settings.heldout_block_s / dt)), settings.heldout)
    n_fit = sum(b - a for a, b, h in blocks if not h)
    fit_starts = _block_windows(blocks, False, burn, H, H)
    ch = np.asarray(sysm.channels)

    def residual_fn(theta):
        pred = sysm.predict(theta, X, U, fit_starts, H, dt)[:, -1]
        return X[fit_starts + H][:, ch] - pred[:, ch]

    say(f"{n} samples at {1.0 / dt:.4g} Hz; fitting {len(fit_starts)} windows of {H} steps")
    cfg = SelectionConfig(
        min_explained=settings.min_explained,
        min_size=settings.min_size,
        confidence=settings.confidence,
        n_boot=settings.n_boot,
        block=max(1, round(settings.block_s / (H * dt))),
        seed=settings.seed,
    )
    ident = identify(
        residual_fn, sysm.theta_base, [g for _, g in sysm.groups], sysm.low, sysm.high, cfg
    )
    say(f"selected {[sysm.groups[j][0] for j in ident.selected]} in {ident.rounds} round(s)")

    # ---- detectability: could each selected effect halve the held-out gap at all? An
    # effect the bootstrap selects but whose signature is within the noise is reported,
    # not added (:func:`effect_visibility`).
    specs = effects_for(system)
    ho = _block_windows(blocks, True, burn, H, 1)
    visible = {}
    if system == "quadrotor":
        visible = _visibility(sysm, X, U, dt, fit_starts, H, ident)
        below = [j for j in ident.confident if visible[j] < HALVING_RATIO]
        if below:
            ident = _without(ident, below, sysm.theta_base, [g for _, g in sysm.groups])

    # ---- effects, parameters, intervals
    effects_out = []
    listed = sorted(
        set(ident.selected) | {j for j, c in enumerate(ident.confidence) if c >= 0.5},
        key=lambda j: (-(j in ident.confident), -ident.contribution[j], -ident.confidence[j]),
    )
    for j in listed:
        name = sysm.groups[j][0]
        theta_j = ident.theta if j in ident.confident else ident.theta_selected
        params = sysm.effect_params(theta_j, name)
        lo = sysm.effect_params(np.percentile(ident.samples, 5, axis=0), name)
        hi = sysm.effect_params(np.percentile(ident.samples, 95, axis=0), name)
        interval = {k: _interval(lo[k], hi[k]) for k in params} if j in ident.confident else {}
        vis = visible.get(j)
        effects_out.append({
            "name": name,
            "visibility": None if vis is None else float(vis),
            "below_detectability": vis is not None and vis < HALVING_RATIO,
            "params": params,
            "interval": interval,
            "confidence": float(ident.confidence[j]),
            "explained": float(ident.contribution[j]),
            "added": j in ident.confident,
            "acts_on": list(specs[name].acts_on),
        })  # fmt: skip
    confident_names = [sysm.groups[j][0] for j in ident.confident]

    # ---- held-out before/after
    theta_b, theta_a = sysm.theta_base, ident.theta
    err_b = sysm.errors(X, sysm.predict(theta_b, X, U, ho, H, dt), ho, H)[:, -1]
    err_a = sysm.errors(X, sysm.predict(theta_a, X, U, ho, H, dt), ho, H)[:, -1]
    comps = list(sysm.components)
    gap_before = {c: float(v) for c, v in zip(comps, _rms(err_b))}
    gap_after = {c: float(v) for c, v in zip(comps, _rms(err_a))}
    if confident_names:
        # The components the added effects act on (library) and, of those, the ones where
        # their contribution to the held-out prediction stands out of what is left (at
        # least half of it): where the effect is visible in this log.
        act = sorted({c for nme in confident_names for c in specs[nme].acts_on}, key=comps.index)
        change = _rms(err_b - err_a)
        moved = [c for c in act if change[comps.index(c)] >= 0.5 * gap_after[c]]
        act = moved or act
    else:
        act = (
            [comps[i] for i in (3, 4, 5, 9, 10, 11)]
            if system == "quadrotor"
            else ["xdot", "thetadot"]
        )
    sel = [comps.index(c) for c in act]
    rmse_b = float(_rms(err_b[:, sel].reshape(-1)))
    rmse_a = float(_rms(err_a[:, sel].reshape(-1)))
    M = max(2, round(settings.horizon_s / dt))
    stride = max(1, round(0.5 / dt))
    cr_starts = _block_windows(blocks, True, burn, M, stride)
    crmse_b: dict[str, float] = {}
    crmse_a: dict[str, float] = {}
    if len(cr_starts):
        eb = sysm.errors(X, sysm.predict(theta_b, X, U, cr_starts, M, dt), cr_starts, M)
        ea = sysm.errors(X, sysm.predict(theta_a, X, U, cr_starts, M, dt), cr_starts, M)
        # CRMSE (Sec. V-A) of one component is the sum of absolute errors over the horizon.
        crmse_b = {c: float(v) for c, v in zip(comps, np.mean(np.abs(eb).sum(1), axis=0))}
        crmse_a = {c: float(v) for c, v in zip(comps, np.mean(np.abs(ea).sum(1), axis=0))}

    # ---- localisation of the gap (fit part, current model)
    loc = _localise(sysm, X, U, dt, fit_starts, H, theta_b, ident.weights)

    summary = (
        "named: "
        + ", ".join(
            f"{e['name']} (confidence {e['confidence']:.2f})" for e in effects_out if e["added"]
        )
        if confident_names
        else "no confident effect"
    )
    below_names = [e["name"] for e in effects_out if e["below_detectability"]]
    if below_names:
        summary += "; below detectability: " + ", ".join(below_names)
    result: dict[str, Any] = {
        "system": system,
        "summary": summary,
        "no_confident_effect": not confident_names,
        "effects": effects_out,
        "gap_before": gap_before,
        "gap_after": gap_after,
        "below_detectability": below_names,
        "heldout_rmse_before": rmse_b,
        "heldout_rmse_after": rmse_a,
        "heldout_components": act,
        "crmse_before": crmse_b,
        "crmse_after": crmse_a,
        "step_s": H * dt,
        "horizon_s": M * dt,
        "samples": n,
        "fit_samples": n_fit,
        "outlier_windows": int(ident.outliers.sum()),
        "localisation": loc["summary"],
        "model_file": None,
    }
    details = {
        "t": log.t, "ho": ho, "err_before": err_b, "err_after": err_a,
        "components": comps, "localisation": loc, "theta_before": theta_b,
        "theta_after": theta_a, "identification": ident,
    }  # fmt: skip
    if out is not None:
        from arcade.discrepancy_report import write_outputs

        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        model_file = write_model_file(out, system, veh, vehicle_path, sysm, ident)
        result["model_file"] = str(model_file)
        result.update(write_outputs(out, result, details))
        atomicfile.write_text(out / "result.json", jsonout.dumps(result, indent=2))
    return Outcome(result, details)


def noise_levels(sysm, X, U, dt, starts, H, theta) -> np.ndarray:
    """What is left per identification channel once ``theta`` models the log: the RMS
    one-step residual over the windows ``starts`` (the floor a model can get down to)."""
    pred = sysm.predict(theta, X, U, starts, H, dt)[:, -1]
    ch = np.asarray(sysm.channels)
    return _rms(X[np.asarray(starts) + H][:, ch] - pred[:, ch])


def effect_visibility(sysm, X, U, dt, starts, H, theta, name, sigma, pred0=None) -> float:
    """How far effect ``name`` at ``theta`` stands out of the noise in this log (quadrotor).

    Mirrors the held-out metric: over the windows ``starts``, the RMS change ``g_c`` of the
    one-step prediction that ``theta`` makes against the base model, per component ``c``
    the effect acts on, against that component's noise level ``sigma_c`` (what the fitted
    model leaves, :func:`noise_levels`); pooled over the components where the change is at
    least half the noise (all of them when there is none), the ratio ``sqrt(sum g_c^2 / sum
    sigma_c^2)``. A model that removes the gap takes the pooled RMSE from ``sqrt(sigma^2 +
    g^2)`` to ``sigma`` at best: halving it takes a ratio of at least ``sqrt(3)``
    (:data:`HALVING_RATIO`). Below that the effect is *below detectability* in this log.
    """
    from arcade_core.discrepancy.catalog import effects_for

    comps = list(sysm.components)
    # component name -> (state index, identification channel); all are v or omega.
    chan = {comps[i if i < 6 else i - 1]: (i, k) for k, i in enumerate(sysm.channels)}
    base = np.asarray(sysm.theta_base, float)
    if pred0 is None:
        pred0 = sysm.predict(base, X, U, starts, H, dt)[:, -1]
    pred = sysm.predict(theta, X, U, starts, H, dt)[:, -1]
    acts = [c for c in effects_for(sysm.name)[name].acts_on if c in chan]
    g = np.array([float(_rms(pred[:, chan[c][0]] - pred0[:, chan[c][0]])) for c in acts])
    sig = np.array([float(sigma[chan[c][1]]) for c in acts])
    moved = g >= 0.5 * sig
    if moved.any():
        g, sig = g[moved], sig[moved]
    return float(np.sqrt(np.sum(g**2) / max(float(np.sum(sig**2)), 1e-300)))


def _visibility(sysm, X, U, dt, starts, H, ident) -> dict[int, float]:
    """:func:`effect_visibility` of every selected effect at its estimate, alone, against
    what the fit with all selected effects leaves (fitting windows)."""
    # Windows the identification left out as gross outliers (floor contacts) stay out.
    starts = np.asarray(starts)[~np.asarray(ident.outliers)]
    sigma = noise_levels(sysm, X, U, dt, starts, H, ident.theta_selected)
    base = np.asarray(sysm.theta_base, float)
    pred0 = sysm.predict(base, X, U, starts, H, dt)[:, -1]
    out = {}
    for j in ident.selected:
        name, idx = sysm.groups[j]
        th = base.copy()
        src = ident.theta if j in ident.confident else ident.theta_selected
        th[list(idx)] = np.asarray(src)[list(idx)]
        out[j] = effect_visibility(sysm, X, U, dt, starts, H, th, name, sigma, pred0)
    return out


def _without(ident, drop: list[int], theta_base: np.ndarray, groups) -> Any:
    """``ident`` with the effects ``drop`` taken out of the confident (added) set."""
    theta = np.asarray(ident.theta, float).copy()
    for j in drop:
        theta[list(groups[j])] = theta_base[list(groups[j])]
    confident = tuple(j for j in ident.confident if j not in drop)
    return ident._replace(confident=confident, theta=theta)


def _interval(lo, hi):
    if isinstance(lo, list):
        return [[min(a, b), max(a, b)] for a, b in zip(lo, hi)]
    return [min(lo, hi), max(lo, hi)]


def _localise(sysm, X, U, dt, starts, H, theta, W) -> dict[str, Any]:
    """Step 2: the current model's one-step residual by component, regime and time segment.

    Residuals of the velocity/rate channels are expressed in units of their noise level
    (``sigma`` from what is left after fitting every candidate effect), so "4 x noise" reads
    the same for m/s and rad/s and a noisy channel does not look like a gap.
    """
    from arcade_core.discrepancy.localize import binned_rms, changepoints, segment_rms

    err = sysm.errors(X, sysm.predict(theta, X, U, starts, H, dt), starts, H)[:, -1]
    comps = list(sysm.components)
    dyn = [
        comps.index(c)
        for c in (
            ("vx", "vy", "vz", "wx", "wy", "wz")
            if sysm.name == "quadrotor"
            else ("xdot", "thetadot")
        )
    ]
    W = np.asarray(W)
    sigma = np.sqrt(np.diag(np.linalg.inv(W.T @ W)))
    norm = err[:, dyn] / sigma
    names = [comps[d] for d in dyn]
    x0 = X[starts]
    if sysm.name == "quadrotor":
        qx, qy = x0[:, 7], x0[:, 8]
        tilt = np.degrees(np.arccos(np.clip(1 - 2 * (qx * qx + qy * qy), -1.0, 1.0)))
        regimes = {
            "speed_mps": np.linalg.norm(x0[:, 3:6], axis=1),
            "height_m": x0[:, 2],
            "thrust_n": U[starts, 0],
            "tilt_deg": tilt,
        }
    else:
        regimes = {
            "cart_speed_mps": np.abs(x0[:, 1]),
            "pole_rate_rad_s": np.abs(x0[:, 3]),
            "pole_cos": np.cos(x0[:, 2]),
            "force_n": np.abs(U[starts, 0]),
        }
    overall = _rms(norm)
    by_regime, findings = {}, []
    for name, var in regimes.items():
        b = binned_rms(norm, var, bins=4)
        by_regime[name] = {
            "edges": b.edges.tolist(),
            "rms": {c: b.rms[:, i].tolist() for i, c in enumerate(names)},
        }
        for i, c in enumerate(names):
            k = int(np.argmax(b.rms[:, i]))
            findings.append(
                (
                    float(b.rms[k, i]),
                    float(b.rms[k, i] / max(overall[i], 1e-12)),
                    name,
                    c,
                    b.edges[k],
                    b.edges[k + 1],
                )
            )
    # Regimes where a component's gap concentrates: most noise levels, then most contrast.
    findings.sort(key=lambda f: -f[0] * f[1])
    cps = changepoints(norm @ np.eye(len(names)), min_gap=max(1, round(1.0 / (H * dt))))
    t0 = starts * dt
    segments = [
        {"t_start": float(t0[a]), "t_end": float(t0[b - 1] + H * dt),
         "rms_noise": {c: float(r[i]) for i, c in enumerate(names)}}
        for a, b, r in segment_rms(norm, cps)
    ]  # fmt: skip
    summary = {
        "rmse": {comps[i]: float(v) for i, v in enumerate(_rms(err))},
        "rms_noise": {c: float(v) for c, v in zip(names, overall)},
        "noise": {c: float(v) for c, v in zip(names, sigma)},
        "largest": names[int(np.argmax(overall))],
        "regimes": [
            {"regime": f, "bin": [float(lo), float(hi)], "component": c, "rms_noise": r, "ratio": q}
            for r, q, f, c, lo, hi in findings[:3]
        ],
        "segments": segments,
    }
    return {"summary": summary, "by_regime": by_regime, "err": err, "t": t0}


# --------------------------------------------------------------------------- model file


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(float(v))
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} to TOML")


def _effects_toml(effects: dict[str, dict[str, Any]]) -> str:
    lines = []
    for name, params in effects.items():
        lines.append(f"\n[effects.{name}]")
        for k, v in params.items():
            lines.append(f"{k} = {_toml_value(v)}")
    return "\n".join(lines) + "\n"


def _strip_effects(text: str) -> str:
    """Remove ``[effects]`` / ``[effects.*]`` tables from TOML text (other tables kept)."""
    out, skip = [], False
    for line in text.splitlines():
        s = line.strip()
        if s.startswith("[") and not s.startswith("[["):
            skip = s == "[effects]" or s.startswith("[effects.")
        if not skip:
            out.append(line)
    return "\n".join(out).rstrip() + "\n"


def _clip_to_spec(system: str, name: str, params: dict[str, Any]) -> dict[str, Any]:
    from arcade_core.discrepancy.catalog import effects_for

    specs = effects_for(system)[name].params
    out = {}
    for k, v in params.items():
        lo, hi = specs[k].low, specs[k].high
        out[k] = [min(max(x, lo), hi) for x in v] if isinstance(v, list) else min(max(v, lo), hi)
    return out


def write_model_file(
    out: Path, system: str, veh: dict[str, Any], vehicle_path, sysm, ident
) -> Path:
    """The updated vehicle/model file: the original plus the confident effects."""
    effects = {k: dict(v) for k, v in sysm.effect_tables.items()}
    for j in ident.confident:
        name = sysm.groups[j][0]
        effects[name] = _clip_to_spec(system, name, sysm.effect_params(ident.theta, name))
    if system == "quadrotor":
        from arcade_io.vehicle import DEFAULT_VEHICLE

        src = Path(vehicle_path) if vehicle_path is not None else DEFAULT_VEHICLE
        base = _strip_effects(src.read_text()) if src.is_file() else ""
        path = out / "vehicle.toml"
        header = "# Vehicle file updated by `arcade discrepancy`: identified effects below.\n"
    else:
        c = veh["cartpole"]
        base = "[cartpole]\n" + "".join(
            f"{k} = {_toml_value(float(c[k]))}\n" for k in ("M", "m", "L", "g") if k in c
        )
        path = out / "cartpole_model.toml"
        header = "# Cartpole model file updated by `arcade discrepancy`.\n"
    atomicfile.write_text(path, header + base + _effects_toml(effects))
    return path


# --------------------------------------------------------------------------- command


def _log_system(path: Path) -> str | None:
    """The system whose columns the header of the CSV at ``path`` has (``None``: neither)."""
    import csv

    from arcade_io.flightlog import columns

    try:
        with path.open(newline="") as f:
            header = next((r for r in csv.reader(f) if any(c.strip() for c in r)), [])
    except (OSError, UnicodeDecodeError, csv.Error):
        return None
    names = {h.strip() for h in header}
    found = [s for s in ("quadrotor", "cartpole") if set(columns(s)) <= names]
    return found[0] if len(found) == 1 else None


def check_model_file(system: str, path: Path | None) -> None:
    """Read the vehicle/model file and check its effects (``ValueError``,
    ``FileNotFoundError``); cheap: no model is built."""
    from arcade.commands.simulate import validate_tables

    if system == "quadrotor":
        from arcade_io.vehicle import load_vehicle

        veh = load_vehicle(path)
        if veh["rotors"].get("layout", "x") != "x":
            raise ValueError(f"{path}: only quad-x vehicles are supported")
    else:
        veh = load_cartpole_file(path)
    try:
        validate_tables(system, dict(veh.get("effects", {})))
    except ValueError as exc:
        raise ValueError(f"{path or 'default model'}: {exc}") from None


def effect_line(effect: dict[str, Any]) -> str:
    """One identified effect of the result as text: name, parameters with units (as in
    report.md), confidence, and whether it was added to the model file."""
    from arcade.discrepancy_report import format_params
    from arcade_core.discrepancy.catalog import EFFECTS

    units = {k: p.unit for k, p in EFFECTS[effect["name"]].params.items()}
    return (
        f"{effect['name']}: {format_params(effect['params'], units)}, confidence "
        f"{effect['confidence']:.2f}{'' if effect['added'] else ' (not added)'}"
    )


def run(args: argparse.Namespace) -> int:
    from arcade_io.flightlog import LogError, read_log
    from arcade_io.runs import check_output_dir, check_runs_root, new_run_dir

    settings = Settings(
        step_s=args.step, heldout=args.heldout, horizon_s=args.horizon,
        confidence=args.confidence, n_boot=args.bootstrap, seed=args.seed,
    )  # fmt: skip
    # Everything is checked before the run folder is made and the work starts.
    try:
        if args.out is not None:
            check_output_dir(args.out, "--out")
        else:
            check_runs_root()
        check_model_file(args.system, args.vehicle)
        if args.log.is_dir():
            raise ValueError(f"flight log {args.log} is a directory, not a CSV file")
        try:
            log = read_log(args.log, args.system)
        except LogError:
            other = _log_system(args.log)
            if other is not None and other != args.system:
                raise LogError(
                    f"{args.log}: this looks like a {other} log: pass --system {other}"
                ) from None
            raise
        check_settings(log, args.system, settings)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2

    from arcade_io import jaxsetup

    jaxsetup.configure(x64=True)
    out = args.out or new_run_dir(f"discrepancy-{args.system}")

    def progress(msg: str) -> None:
        print(f"[discrepancy] {msg}", file=sys.stderr, flush=True)

    try:
        outcome = run_workflow(log, args.system, args.vehicle, out, settings, progress)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    result = outcome.result
    if args.json:
        print(jsonout.dumps(result))
    else:
        print(result["summary"])
        for e in result["effects"]:
            print(f"  {effect_line(e)}")
        print(
            f"held-out one-step RMSE on {', '.join(result['heldout_components'])}: "
            f"{result['heldout_rmse_before']:.4g} -> {result['heldout_rmse_after']:.4g}"
        )
        print(f"model file: {result['model_file']}; report in {out}")
    return 0
