"""Closed-loop quadrotor evaluation, in process (Sec. V-B, Table III, Fig. 5, Table V).

Scenario (every trial): the MuJoCo quadrotor (:class:`simulator.QuadrotorSim`) carries a
*swinging* payload on a 0.5 m cable; it climbs from 1.5 m to the centre of the
figure-eight at 2.0 m (2.5 s), hovers (1.5 s), then flies two laps of the figure-eight
(:class:`arcade_core.trajectories.FigureEight`, 4 m x 2 m) at the mean speed of the cell.
The first 2 s of the figure-eight ramp the speed up smoothly (:class:`RampedPath`) so the
reference starts at rest. The payload is released just before the second lap (at 95 % of
the first lap, jittered by up to two control periods per trial). Trials differ in the
simulator's sensor-noise seed, the start position (2 cm std in x and y) and the release
jitter.

Control: one MPC solve per control period ``dt = 0.05 s`` (20 Hz), N = 20 (1 s), Appendix D
weights, on the ground-truth state (``Runner.fly(..., estimated=True)``: on the state
estimate the service stack flies, :class:`MocapEstimate`; a diagnostic,
``python -m benchmarks.quadrotor_variants estimated``); the setpoint is held in between
while the simulator runs its 500 Hz rate loop and 1 kHz physics. Per method, the whole
per-step update (learning from the last transition, reference window, MPC solve,
warm-start shift) is one jitted function, so the Python loop only moves a handful of arrays
per step.

Learned residual in the MPC (every learned-model method alike: GP, MLP, ours): inside the
rollout, as Sec. IV writes the model, derivatives included.
:func:`benchmarks.quadrotor_ablations.run_residual_ablation` flies beside it the variant
that evaluates the residual along the warm start and holds it per stage during the solve
(``<method>_held``; :mod:`arcade_core.mpc`, "Learned residual along the warm start"): the
optimiser then follows the model's prediction but not its derivatives.

Methods:

- ``nominal``: MPC on ``f_nom``;
- ``l1``: nominal MPC + L1-adaptive augmentation (:mod:`arcade_core.baselines.l1`) of the
  thrust, and of the body-rate setpoints if the tuning turns that channel on; bandwidths
  tuned;
- ``gp``: GP-MPC, GP mean (FIFO 50, re-conditioned every step) inside the rollout, no
  variance in the cost;
- ``mlp``: MLP-MPC, last-layer SGD (FIFO 50; learning rate tuned open-loop, see
  :mod:`benchmarks.quadrotor_openloop`), unscented-transform variance modulating ``Q``;
- ``ours_no_cp``: VLD + BLR without changepoints (``K = 1``, ``pi = 0``);
- ``ours``: full ARCADE: beam-marginal decoder mean inside the rollout, ``Q`` modulated
  by ``sigma_tot^2`` (Sec. IV), Appendix D values (``K = 15``, ``pi = 0.05``,
  ``tau^2 = 0.1``; ``beta`` and ``sigma^2`` tuned, see below) and the offline prior re-injected
  at changepoints, which Lemma 2's proof assumes
  (:func:`arcade_core.adaptation.quadrotor_config`);
- ``ours_paper`` (:data:`~arcade_control.knobs.PAPER_SETTINGS`): ours at every Appendix D
  value (``beta = 0.997``, ``sigma^2 = 0.1`` too), never tuned;
- ``ours_matched`` (:data:`VARIANTS`, not the paper's method, not in :data:`EVAL_METHODS`):
  ours with an intercept feature, planning with :func:`matched_residual` only; flown by
  ``arcade bench variants`` (:mod:`benchmarks.quadrotor_variants`);
- ``arcade``: the product's controller (not the paper's method,
  :func:`arcade_control.methods.arcade_method`), in :data:`EVAL_METHODS`.

Units of the variance that modulates ``Q`` (Sec. IV, ``alpha1 = 10``, ``alpha2 = 1e3``):
Sec. IV builds ``sigma_tot^2`` from the posterior of the regression itself (``mu_{k,h}``,
``Sigma_{k,h}``, ``sigma_z^2``), and Appendix D uses the same ``alpha1, alpha2`` for the
cartpole and the quadrotor, so the variance must be unit-free: it is the variance of the
residual in the units each model learns in. For ours that is the normalised residual of
the VLD (``delta / delta_scale``, in which the observation noise is ``sigma_j^2 = 0.1``
and the prior ``tau^2 = 0.1``: the units of every Appendix D value of Algorithm 1), for
the MLP its standardised output (``delta / std(delta)``). In physical units the same
``alpha2`` would leave the position weights unmodulated (factor below 1.001) and raise a
velocity weight about tenfold (residual scales about 1e-3 m and 0.1 m/s per step): the
modulation would then follow the choice of SI units rather than the model's confidence.
The UT input distribution of
the MLP is the state-estimation noise of the motion-capture/gyro emulation
(:data:`MLP_INPUT_STD`).

Two safeguards apply to every learned-model method alike (GP, MLP, ours): the thrust
reference is made consistent with the learned model (:func:`thrust_reference`), and the
learned residual is confined to its training range inside the rollout (:class:`Guard`).

Tuning (:func:`benchmarks.quadrotor_tuning.tune`): each adaptive method gets small grids
over its adaptation knobs on a tuning cell that is not evaluated (150 g, 2.0 m/s, four
flights with their own seeds, mean RMSE), one knob after the other, in passes until a pass
changes nothing (coordinate descent), each grid extended past an edge its best value lies
on: ours the temperature ``beta`` (the Appendix D value 0.997 is in the grid), then the
noise variance ``sigma^2`` of the online regression; the GP a factor on its noise variances;
the MLP its SGD rate; L1 its filter bandwidth, thrust channel then rate channel (or none:
the grid starts at "rate correction off"), then its predictor pole ``a_s`` (the
piecewise-constant law settles at ``exp(a_s T_s)`` of a constant disturbance: at 20 Hz 10 %
short with ``a_s = -2``, and the MPC sags under what is left uncancelled). With ``beta =
0.997`` a changepoint tempers the precision by only 0.6 %, so ours then behaves like ours
without changepoints; the grid is geometric in the share ``beta^2`` of the posterior a
changepoint keeps (99.4 %, 81 %, 25 %, 4 %, 0.25 %): at its small end a changepoint restarts
from the offline prior, which the changepoint prior approaches as ``beta -> 0``
(``prior_floor = 1``). The flagship is tuned for tracking within its smoothness requirement:
its thrust increments at most 1.5 times L1's on the tuning flights
(:data:`benchmarks.quadrotor_tuning.FLAGSHIP_THRUST_RATIO`).

Why a noise knob: ``sigma^2`` (and the GP's noise, fitted by marginal likelihood) is
calibrated on the training flights, where the offline model leaves a one-step
vertical-velocity error of 0.048 m/s (0.035 m/s even after refitting the decoder over 2 s
windows; the expert's sharp thrust changes against the motor lag are the likely source,
not isolated). These flights are flown by the MPC on the ground-truth state: the one-step
error a decoder refitted over 2 s windows leaves is 0.002 m/s at 75 g / 0.5 m/s and
0.04 m/s at 175 g / 2.5 m/s, so the calibrated noise variance is 1.5 to 600 times what the
data show, and a light payload's release (0.07 m/s per step) hardly moves the changepoint
evidence. The stack's adapter, fed by the state estimator, keeps the calibrated
``sigma^2`` (with the ``beta`` tuned at it) and adds the estimator's noise to it at every
step (``arcade_control.stack.stack_knobs``).
All other hyperparameters are the Appendix D values.

Every method shares the MPC's safeguard (:mod:`arcade_core.mpc`): a failed or non-finite
solve hands out the cheaper finite plan of the shifted warm start and the reference
input, so one diverged plan is not carried over from step to step.

Metrics (``arcade_core.metrics``) on the control-rate samples of the figure-eight part
(from its start to the end of the second lap): 3-D position RMSE, z RMSE; the shift
magnitude and the 0.05 m settling time of the z error at the release.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np

from arcade_control.knobs import (
    EVAL_METHODS,
    knobs_of,
)
from arcade_control.nominal import CONTROL_DT as DT
from arcade_control.scenario import Scenario
from arcade_io import atomicfile
from benchmarks.eval_progress import Progress
from benchmarks.quadrotor_flights import FLIGHT_THREADS, Runner, flight_threads
from benchmarks.quadrotor_protocol import condition, format_paired, paired_differences
from benchmarks.quadrotor_tuning import tune

PAYLOADS_G = (75.0, 125.0, 175.0)
SPEEDS_MPS = (0.5, 1.5, 2.5)


# --------------------------------------------------------------------------- tables


KEYS = ("rmse_m", "rmse_z_m", "shift_m", "settling_s")
#: Diagnostics averaged per cell beside :data:`KEYS` (:func:`flight_metrics`).
DIAGNOSTIC_KEYS = (
    "thrust_increment_rms_n",
    "rate_increment_rms_rad_s",
    "changepoint_rate",
    "converged_fraction",
)


def _mean(values: Sequence[float]) -> float:
    return float(np.mean(np.asarray(values, float)))


def _finite_mean(values: Sequence[float], empty: float = float("inf")) -> float:
    """Mean of the finite values (flights that did not crash; for a diagnostic, that have
    it), ``empty`` when there are none."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else empty


def run_closedloop(
    quick: bool = False,
    trials: int = 10,
    methods: Sequence[str] | None = None,
    cells: Sequence[tuple[float, float]] | None = None,
    out=None,
    progress: Callable[[str], None] = lambda msg: None,
    models=None,
    seed: int = 0,
    tuning: bool | None = None,
    condition_name: str = "ideal",
    keep=None,
) -> dict[str, Any]:
    """Table III analogue: every (payload, speed) cell x method, ``trials`` seeded flights.

    ``condition_name``: ``ideal`` or ``stack`` (:mod:`benchmarks.quadrotor_protocol`); the
    tuning and every flight are in that condition. With L1 among the methods, ``paired``
    holds every other method's paired RMSE difference to it per cell.

    ``quick``: one trial of the 175 g / 2.5 m/s cell (a few minutes on a laptop CPU,
    most of it compiling the six controllers). ``cells`` are ``(payload_g, speed_mps)``
    pairs. Returns ``{"cells": [{payload_g, speed_mps, method, rmse_m, rmse_z_m, shift_m,
    settling_s, settled_fraction, crashed, *DIAGNOSTIC_KEYS}, ...] (means over trials;
    the diagnostics over the flights that have them), "trials": [...]
    (per-trial values), "improvement_over_nominal": ..., "settings": ...}``. ``out``: a
    folder for figures and the Fig. 5 time series. ``tuning`` (default: not ``quick``)
    runs :func:`tune` first; otherwise :data:`TUNED_DEFAULTS` (or what ``models`` holds).
    ``keep``: a folder where each finished part (a tuning score, a cell x method's flights)
    is kept as it finishes; run again with the same settings and code, the parts found
    there are read back instead of flown (:mod:`benchmarks.eval_progress`), with the same
    results as one uninterrupted run.
    """
    from benchmarks.quadrotor_openloop import prepare_models

    t_start = time.perf_counter()
    methods = tuple(methods) if methods is not None else EVAL_METHODS
    cond = condition(condition_name)
    if quick:
        trials = 1
        cells = cells if cells is not None else [(175.0, 2.5)]
    if cells is None:
        cells = [(p, s) for p in PAYLOADS_G for s in SPEEDS_MPS]
    if models is None:
        models = prepare_models(quick=quick, seed=seed, progress=progress)
    runner = Runner(models)
    tuning = (not quick) if tuning is None else tuning
    done = Progress(
        keep,
        {
            "condition": condition_name,
            "quick": quick,
            "trials": trials,
            "seed": seed,
            "methods": list(methods),
            "cells": [list(c) for c in cells],
            "knobs": "tuned" if tuning else dict(getattr(models, "closedloop", {})),
        },
    )
    if done.read_back:
        progress(f"continuing the run kept in {done.path}: {done.read_back} finished parts")
    tuning_result = (
        tune(
            models,
            progress,
            runner,
            methods,
            cond.command_delay_s,
            compensate_delay=cond.compensate_delay,
            estimated=cond.estimated,
            hand_set=dict(cond.hand_set),
            done=done,
        )
        if tuning
        else None
    )
    if not tuning:  # the stored or given knobs, with the condition's hand-set ones
        models.closedloop = {**getattr(models, "closedloop", {}), **dict(cond.hand_set)}
    rows, per_trial, fig5 = [], [], {}
    for pay, speed in cells:
        scen = Scenario(
            payload_g=float(pay), speed_mps=float(speed), command_delay_s=cond.command_delay_s
        )
        for name in methods:
            part = f"{pay:g} g, {speed:g} m/s: {name}"
            kept = done.get(part)
            if kept is not None:
                progress(f"{part} (flown before: read back)")
                rows.append(kept["row"])
                per_trial.extend(kept["trials"])
                if out is not None and (pay, speed) == (175.0, 2.5):  # Fig. 5: fly again
                    fig5[name] = runner.fly(
                        name,
                        scen,
                        seed=seed * 1000,
                        estimated=cond.estimated,
                        compensate_delay=cond.compensate_delay,
                    )
                continue
            progress(f"{part} ({trials} trial(s))")
            n_before = len(per_trial)
            vals: dict[str, list[float]] = {k: [] for k in (*KEYS, *DIAGNOSTIC_KEYS, "crashed")}
            step_ms = []
            flights = runner.fly_trials(
                name,
                scen,
                [seed * 1000 + trial for trial in range(trials)],
                estimated=cond.estimated,
                compensate_delay=cond.compensate_delay,
            )
            for trial, f in enumerate(flights):
                step_ms.append(float(np.median(f.step_ms[1:])) if f.step_ms.size > 1 else 0.0)
                for k in vals:
                    vals[k].append(f.metrics[k])
                per_trial.append(
                    {
                        "payload_g": pay,
                        "speed_mps": speed,
                        "method": name,
                        "trial": trial,
                        **f.metrics,
                    }
                )
                if trial == 0 and (pay, speed) == (175.0, 2.5):
                    fig5[name] = f
            settled = [np.isfinite(v) for v in vals["settling_s"]]
            rows.append(
                {
                    "payload_g": pay,
                    "speed_mps": speed,
                    "method": name,
                    **{k: _mean(vals[k]) for k in KEYS},
                    **{k: _finite_mean(vals[k], empty=float("nan")) for k in DIAGNOSTIC_KEYS},
                    "rmse_m_finite_mean": _finite_mean(vals["rmse_m"]),
                    "settled_fraction": float(np.mean(settled)),
                    "crashed": float(np.mean(vals["crashed"])),
                    "step_ms_median": float(np.median(step_ms)),
                }
            )
            done.put(part, {"row": rows[-1], "trials": per_trial[n_before:]})
    result: dict[str, Any] = {
        "cells": rows,
        "trials": per_trial,
        "improvement_over_nominal": improvement(rows),
        "paired": paired_differences(per_trial, vs="l1") if "l1" in methods else [],
        "settings": {
            "condition": condition_name,
            "quick": quick,
            "trials": trials,
            "control_dt": DT,
            "horizon": 20,
            "dtype": str(jnp.dtype(runner.dtype)),
            # Flights flown at a time: ``step_ms_median`` is measured with them side by side.
            "flight_threads": flight_threads(FLIGHT_THREADS),
            "tuned": knobs_of(models.closedloop, methods),
            "methods": list(methods),
            "cells": [list(c) for c in cells],
        },
        "tuning": tuning_result,
    }
    if out is not None:
        from pathlib import Path

        from benchmarks import quadrotor_figures as figs

        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        if fig5:
            figs.tracking_error_figure(out / "quadrotor_tracking_175g_2.5mps.png", fig5)
            series = {
                f"{m}_{k}": getattr(f, k)
                for m, f in fig5.items()
                for k in ("t", "x", "x_ref", "u", "diag")
            }
            with atomicfile.atomic_open(out / "quadrotor_flights_175g_2.5mps.npz", "wb") as f:
                np.savez_compressed(f, **series)
        figs.metric_bars_figure(out / "quadrotor_metrics.png", per_trial)
    # A continued run: with the time its parts read back took when they were flown.
    result["wall_time_s"] = time.perf_counter() - t_start + done.kept_s
    if done.read_back:
        result["continued"] = {"parts_read_back": done.read_back, "their_time_s": done.kept_s}
    return result


def improvement(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per cell: RMSE reduction of every method relative to the nominal MPC [%]."""
    out = []
    by_cell: dict[tuple[float, float], dict[str, float]] = {}
    for r in rows:
        by_cell.setdefault((r["payload_g"], r["speed_mps"]), {})[r["method"]] = r["rmse_m"]
    for (pay, speed), vals in by_cell.items():
        if "nominal" not in vals:
            continue
        base = vals["nominal"]
        out.append(
            {
                "payload_g": pay,
                "speed_mps": speed,
                **{m: 100.0 * (base - v) / base for m, v in vals.items() if m != "nominal"},
            }
        )
    return out


def format_table(result: dict[str, Any]) -> str:
    """Human-readable Table III analogue."""
    lines = [
        "Closed-loop tracking (mean over trials): RMSE / z-RMSE [m], shift [m], "
        "settling [s]; RMS command increments per control period (dT, drate); "
        "fraction of steps with a changepoint flagged (beam methods)"
    ]
    for r in result["cells"]:
        lines.append(
            f"  {r['payload_g']:5.0f} g {r['speed_mps']:.1f} m/s  {r['method']:11s} "
            f"{r['rmse_m']:.3f} / {r['rmse_z_m']:.3f}  shift {r['shift_m']:.3f}  "
            f"settle {r['settling_s']:.2f} ({100 * r['settled_fraction']:.0f} % settled)"
            f"  dT {r['thrust_increment_rms_n']:.2f} N  drate "
            f"{r['rate_increment_rms_rad_s']:.2f} rad/s"
            + (
                f"  changepoints {r['changepoint_rate']:.2f}"
                if np.isfinite(r["changepoint_rate"])
                else ""
            )
            + (
                f"  CRASHED in {100 * r['crashed']:.0f} % of trials (mean RMSE of the others "
                f"{r['rmse_m_finite_mean']:.3f})"
                if r["crashed"] > 0
                else ""
            )
        )
    if result.get("paired"):
        lines += format_paired(result["paired"])
    for imp in result["improvement_over_nominal"]:
        lines.append(
            f"  improvement over nominal at {imp['payload_g']:g} g, "
            f"{imp['speed_mps']:g} m/s: "
            + ", ".join(
                f"{m} {v:.0f} %" for m, v in imp.items() if m not in ("payload_g", "speed_mps")
            )
        )
    return "\n".join(lines)
