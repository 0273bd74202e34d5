"""Runtime and reach of the discrepancy workflow (design §7).

**Runtime** (:func:`run`): a flight of the standard exciting trajectory (``arcade
simulate``) with two hidden effects (rotor drag and a slower motor), 10 minutes of 100 Hz
data, is simulated first (not timed); then the whole workflow (alignment, localisation,
selection with 200 bootstrap resamples, fit, held-out evaluation; no plots) is timed twice
in one process: ``cold_s`` includes JAX compilation (or loading it from the persistent
cache), ``warm_s`` is a second run. Target: at most 60 s. Also reported: what was named,
the parameter errors and the held-out gap shrink.

**Sweep** (:func:`sweep`): every quadrotor effect of the library, one at a time, at a
handful of parameter values across its *whole* plausible range (extremes and signs
included), each in its own simulated flight with sensor noise on; per case whether the
workflow names it first, its confidence, the parameter error and the held-out one-step
RMSE shrink, next to the effect's magnitude and the catalogue's minimum detectable
magnitude (:data:`arcade_core.discrepancy.catalog.DETECTABLE`). This is how those minima
were measured.

Run: ``python -m benchmarks.discrepancy [--quick] [--sweep [--effect NAME ...]] [--json]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from arcade_core.discrepancy import quadrotor as qm
from arcade_core.discrepancy.catalog import DETECTABLE, QUADROTOR_EFFECTS, magnitude
from arcade_core.discrepancy.settings import Settings, fit_windows
from arcade_core.discrepancy.workflow import effect_visibility, noise_levels
from arcade_io import jaxsetup, jsonout
from arcade_io.discrepancy import discrepancy_model, run_workflow
from arcade_io.vehicle import load_vehicle
from benchmarks.common import machine
from simulator.log_flights import fly_quadrotor

HIDDEN = {
    "rotor_drag": {"d": [0.6, 0.5, 0.15]},
    "motor_lag": {"time_constant_s": 0.06},
}
TARGET_S = 60.0
#: Flight length of a sweep case [s] (the length the tests fly).
SWEEP_DURATION_S = 90.0
#: Drag of the vehicle in the wind cases (wind acts only through drag).
WIND_VEHICLE_DRAG = [0.4, 0.4, 0.1]

# fmt: off
#: Parameter values per effect: small to the ends of the plausible range, both signs.
SWEEP_CASES: dict[str, list[dict]] = {
    "rotor_drag": [
        {"d": [0.02, 0.02, 0.01]}, {"d": [0.1, 0.1, 0.05]}, {"d": [0.3, 0.3, 0.1]},
        {"d": [1.0, 1.0, 0.5]}, {"d": [2.0, 2.0, 2.0]}, {"d": [2.0, 0.2, 1.0]},
    ],
    "quadratic_drag": [
        {"c": [0.005, 0.005, 0.005]}, {"c": [0.02, 0.02, 0.02]}, {"c": [0.05, 0.05, 0.02]},
        {"c": [0.1, 0.1, 0.1]}, {"c": [0.2, 0.2, 0.2]}, {"c": [0.2, 0.05, 0.1]},
    ],
    "ground_effect": [
        {"rotor_radius_m": 0.01}, {"rotor_radius_m": 0.03}, {"rotor_radius_m": 0.06},
        {"rotor_radius_m": 0.1}, {"rotor_radius_m": 0.2},
    ],
    "thrust_scale": [
        {"scale": 0.5}, {"scale": 0.8}, {"scale": 0.97}, {"scale": 0.99}, {"scale": 1.01},
        {"scale": 1.03}, {"scale": 1.2}, {"scale": 1.5},
    ],
    "motor_lag": [
        {"time_constant_s": 0.002}, {"time_constant_s": 0.015}, {"time_constant_s": 0.035},
        {"time_constant_s": 0.05}, {"time_constant_s": 0.1}, {"time_constant_s": 0.2},
    ],
    "rate_lag": [
        {"delay_s": 0.005, "time_constant_s": 0.0}, {"delay_s": 0.02, "time_constant_s": 0.0},
        {"delay_s": 0.05, "time_constant_s": 0.0}, {"delay_s": 0.1, "time_constant_s": 0.0},
        {"delay_s": 0.0, "time_constant_s": 0.01}, {"delay_s": 0.0, "time_constant_s": 0.1},
        {"delay_s": 0.0, "time_constant_s": 0.3}, {"delay_s": 0.1, "time_constant_s": 0.3},
    ],
    "com_offset": [
        {"offset_m": [0.001, 0.0, 0.0]}, {"offset_m": [0.003, -0.003, 0.0]},
        {"offset_m": [-0.01, 0.005, 0.0]}, {"offset_m": [0.015, -0.015, 0.0]},
        {"offset_m": [-0.015, 0.015, 0.015]},
    ],
    "wind": [
        {"velocity_mps": [0.3, 0.0, 0.0]}, {"velocity_mps": [1.0, -1.0, 0.0]},
        {"velocity_mps": [-3.0, 2.0, 0.0]}, {"velocity_mps": [7.0, -5.0, 1.0]},
        {"velocity_mps": [-15.0, 0.0, 0.0]}, {"velocity_mps": [10.0, 10.0, -2.0]},
    ],
    "induced_inflow": [
        {"climb_loss": 0.02, "airspeed_loss": 0.0}, {"climb_loss": 0.1, "airspeed_loss": 0.0},
        {"climb_loss": 0.0, "airspeed_loss": 0.005}, {"climb_loss": 0.0, "airspeed_loss": -0.01},
        {"climb_loss": 0.2, "airspeed_loss": 0.02}, {"climb_loss": 0.05, "airspeed_loss": -0.02},
    ],
    "battery_sag": [
        {"loss_per_min": 0.005}, {"loss_per_min": 0.02}, {"loss_per_min": 0.05},
        {"loss_per_min": 0.1},
    ],
}
# fmt: on


def _rel_error(true: dict, found: dict) -> float:
    t = np.concatenate([np.ravel(v) for v in true.values()])
    e = np.concatenate([np.ravel(found[k]) for k in true])
    return float(np.linalg.norm(e - t) / max(np.linalg.norm(t), 1e-12))


def sweep_case(name: str, params: dict, seed: int = 0, duration: float = SWEEP_DURATION_S):
    """One sweep case: fly with only ``name`` injected, run the workflow told nothing."""
    veh = load_vehicle()
    if name == "wind":
        veh["effects"] = {"rotor_drag": {"d": WIND_VEHICLE_DRAG}}
    t0 = time.perf_counter()
    try:
        log = fly_quadrotor({name: params}, duration, seed=seed, vehicle=veh)
    except RuntimeError as exc:  # a flight the pilot cannot fly
        return {"effect": name, "params": params, "error": str(exc)}
    t1 = time.perf_counter()
    res = run_workflow(log, "quadrotor", vehicle=veh).result
    t2 = time.perf_counter()
    first = res["effects"][0] if res["effects"] else None
    found = next((e for e in res["effects"] if e["name"] == name), None)
    before, after = res["heldout_rmse_before"], res["heldout_rmse_after"]
    return {
        "effect": name,
        "params": params,
        "magnitude": magnitude(name, params, veh),
        "detectable": DETECTABLE[name],
        "summary": res["summary"],
        "first": first["name"] if first else None,
        "named_first": bool(first and first["name"] == name and first["added"]),
        "confidence": found["confidence"] if found else 0.0,
        "visibility": found["visibility"] if found else None,
        "estimate": found["params"] if found else None,
        "param_rel_error": _rel_error(params, found["params"]) if found else None,
        "rmse_shrink": 1.0 - after / before if before > 0 else 0.0,
        "others_added": [e["name"] for e in res["effects"] if e["added"] and e["name"] != name],
        "below_detectability": res.get("below_detectability", []),
        "simulation_s": t1 - t0,
        "workflow_s": t2 - t1,
    }


#: Gap-to-noise ratio of the stated limits: ``sqrt(3)`` halves the gap with a perfect
#: model; 2 (15 % more) leaves room for estimation error and flight-to-flight spread.
LIMIT_RATIO = 2.0
#: Per effect: parameters of magnitude ``m`` (catalogue's :func:`magnitude`) in the
#: directions the detectability limits are stated for; several directions: the limit is
#: the largest.
LIMIT_DIRECTIONS = {
    # Drag: horizontal axes only (the vertical one is excited least; any vertical drag
    # only adds to what the horizontal axes show).
    "rotor_drag": [lambda m: {"d": [m, m, 0.0]}],
    "quadratic_drag": [lambda m: {"c": [m, m, 0.0]}],
    "ground_effect": [lambda m: {"rotor_radius_m": m}],
    "thrust_scale": [lambda m: {"scale": 1.0 + m}, lambda m: {"scale": 1.0 - m}],
    "motor_lag": [
        lambda m: {"time_constant_s": 0.025 + m},
        lambda m: {"time_constant_s": max(0.025 - m, 0.002)},
    ],
    "rate_lag": [
        lambda m: {"delay_s": m, "time_constant_s": 0.0},
        lambda m: {"delay_s": 0.0, "time_constant_s": m},
    ],
    "com_offset": [lambda m: {"offset_m": [m / 2**0.5, -m / 2**0.5, 0.0]}],
    "wind": [lambda m: {"velocity_mps": [m / 2**0.5, -m / 2**0.5, 0.0]}],
    # Induced inflow: magnitude |k_c| + 9 |k_h| (1 m/s climb, 3 m/s air speed).
    "induced_inflow": [
        lambda m: {"climb_loss": m, "airspeed_loss": 0.0},
        lambda m: {"climb_loss": 0.0, "airspeed_loss": m / 9.0},
        lambda m: {"climb_loss": 0.0, "airspeed_loss": -m / 9.0},
    ],
    "battery_sag": [lambda m: {"loss_per_min": m}],
}


def _limit(ctx: dict, name: str, direction, hi: float) -> float:
    """Smallest magnitude in ``direction`` at which ``name`` halves the gap (bisection)."""
    sysm = ctx["sysm"]

    def visibility(m: float) -> float:
        tables = {**sysm.effect_tables, name: direction(m)}
        th = np.asarray(qm.theta_from_effects(sysm.model, tables))
        return effect_visibility(
            sysm, ctx["X"], ctx["U"], ctx["dt"], ctx["starts"], ctx["H"], th, name,
            ctx["sigma"], ctx["pred0"],
        )  # fmt: skip

    if visibility(hi) < LIMIT_RATIO:
        return float("inf")
    lo = 1e-4 * hi
    for _ in range(14):  # bisection in log space
        mid = (lo * hi) ** 0.5
        lo, hi = (mid, hi) if visibility(mid) < LIMIT_RATIO else (lo, mid)
    return hi


def detection_limits(
    seed: int = 0, duration: float = SWEEP_DURATION_S, effects: list[str] | None = None
) -> dict:
    """Minimum detectable magnitude of every quadrotor effect on the standard trajectory.

    A flight with no effect (for wind: with the wind cases' vehicle drag) at the standard
    sensor noise; the workflow's noise levels on it; per effect the smallest magnitude at
    which :func:`arcade_core.discrepancy.workflow.effect_visibility` reaches
    :data:`LIMIT_RATIO` (``sqrt(3)`` is where adding the effect would halve the held-out
    one-step RMSE with a perfect model).
    """
    jaxsetup.configure(x64=True)
    settings = Settings()
    out = {}
    for wind in (False, True):
        if effects and not any((n == "wind") == wind for n in effects):
            continue  # no effect asked for is measured on this flight
        veh = load_vehicle()
        if wind:
            veh["effects"] = {"rotor_drag": {"d": WIND_VEHICLE_DRAG}}
        log = fly_quadrotor({}, duration, seed=seed, vehicle=veh)
        outcome = run_workflow(log, "quadrotor", vehicle=veh)
        sysm = discrepancy_model("quadrotor", veh)
        X, U, dt = log.X, log.U, log.dt
        H = round(settings.step_s / dt)
        starts = fit_windows(settings, "quadrotor", len(log), dt)
        ctx = {
            "sysm": sysm, "X": X, "U": U, "dt": dt, "H": H, "starts": starts,
            "sigma": noise_levels(
                sysm, X, U, dt, starts, H, outcome.details["identification"].theta_selected
            ),
            "pred0": sysm.predict(sysm.theta_base, X, U, starts, H, dt)[:, -1],
        }  # fmt: skip
        for name, spec in QUADROTOR_EFFECTS.items():
            if (name == "wind") != wind or (effects and name not in effects):
                continue
            hi = max(max(abs(p.low), abs(p.high)) for p in spec.params.values())
            hi = {"thrust_scale": 0.5, "motor_lag": 0.2 - 0.025, "induced_inflow": 0.18}.get(
                name, hi
            )
            out[name] = max(_limit(ctx, name, d, hi) for d in LIMIT_DIRECTIONS[name])
    return {"machine": machine(), "duration_s": duration, "seed": seed, "limits": out}


def sweep(effects: list[str] | None = None, seed: int = 0, progress=None) -> dict:
    """Every case of :data:`SWEEP_CASES` (or of ``effects``); module docstring."""
    jaxsetup.configure(x64=True)
    rows = []
    for name, cases in SWEEP_CASES.items():
        if effects and name not in effects:
            continue
        for params in cases:
            rows.append(sweep_case(name, params, seed=seed))
            if progress:
                progress(rows[-1])
    return {"machine": machine(), "duration_s": SWEEP_DURATION_S, "seed": seed, "cases": rows}


def sweep_table(rows: list[dict]) -> str:
    """Markdown table of sweep rows."""
    out = [
        "| effect | parameters | magnitude | detectable from | named first | confidence "
        "| param error | RMSE shrink |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "error" in r:
            out.append(f"| {r['effect']} | {_fmt(r['params'])} | | | flight failed | | | |")
            continue
        err = "" if r["param_rel_error"] is None else f"{100 * r['param_rel_error']:.1f} %"
        if r["named_first"]:
            named = "yes"
        elif r["effect"] in r["below_detectability"]:
            named = "below detectability"
        else:
            named = f"no ({r['first'] or 'nothing'})"
        out.append(
            f"| {r['effect']} | {_fmt(r['params'])} | {r['magnitude']:.3g} "
            f"| {r['detectable']:.3g} | {named} | {r['confidence']:.2f} | {err} "
            f"| {100 * r['rmse_shrink']:.0f} % |"
        )
    return "\n".join(out)


def _fmt(params: dict) -> str:
    def v(x):
        return "[" + ", ".join(f"{a:g}" for a in x) + "]" if isinstance(x, list) else f"{x:g}"

    return ", ".join(f"{k}={v(x)}" for k, x in params.items())


def run(quick: bool = False) -> dict:
    """Time the workflow on 10 min (``quick``: 2 min) of simulated 100 Hz data."""
    jaxsetup.configure(x64=True)
    minutes = 2.0 if quick else 10.0
    t0 = time.perf_counter()
    log = fly_quadrotor(HIDDEN, 60.0 * minutes, seed=0)
    sim_s = time.perf_counter() - t0
    times = []
    result = None
    for _ in range(2):
        t0 = time.perf_counter()
        result = run_workflow(log, "quadrotor").result
        times.append(time.perf_counter() - t0)
    assert result is not None
    errors = {}
    for e in result["effects"]:
        if e["name"] in HIDDEN:
            errors[e["name"]] = _rel_error(HIDDEN[e["name"]], e["params"])
    return {
        "machine": machine(),
        "minutes_of_data": minutes,
        "samples": len(log),
        "simulation_s": sim_s,
        "cold_s": times[0],
        "warm_s": times[1],
        "target_s": TARGET_S,
        "within_target": times[0] <= TARGET_S,
        "named": [e["name"] for e in result["effects"] if e["added"]],
        "confidence": {e["name"]: e["confidence"] for e in result["effects"]},
        "parameter_rel_error": errors,
        "heldout_rmse_before": result["heldout_rmse_before"],
        "heldout_rmse_after": result["heldout_rmse_after"],
        "heldout_components": result["heldout_components"],
    }


def check_effects(effects: list[str] | None, which: str = "sweep") -> str | None:
    """Why ``effects`` (``--effect`` names) cannot be run by :func:`sweep` (``which``
    ``"sweep"``) or :func:`detection_limits` (``"limits"``); ``None`` when they can."""
    known = SWEEP_CASES if which == "sweep" else LIMIT_DIRECTIONS
    unknown = [e for e in effects or [] if e not in known]
    if unknown:
        return (
            f"unknown effect(s) {', '.join(unknown)}; known quadrotor effects: {', '.join(known)}"
        )
    return None


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="2 minutes of data instead of 10")
    p.add_argument("--sweep", action="store_true", help="sweep every effect over its range")
    p.add_argument("--effect", action="append", default=None, help="sweep only this effect")
    p.add_argument("--seed", type=int, default=0, help="sweep and limits: flight seed")
    p.add_argument("--json", action="store_true", help="sweep: JSON instead of a table")
    p.add_argument(
        "--limits", action="store_true", help="minimum detectable magnitude of every effect"
    )
    args = p.parse_args()
    if args.sweep and args.limits:
        p.error("--sweep and --limits are separate runs: give one of them")
    if args.effect and not (args.sweep or args.limits):
        p.error("--effect needs --sweep or --limits")
    if args.seed < 0:
        p.error(f"argument --seed: must be at least 0, got {args.seed}")
    error = check_effects(args.effect, "limits" if args.limits else "sweep")
    if error:
        p.error(f"argument --effect: {error}")
    if args.limits:
        print(jsonout.dumps(detection_limits(seed=args.seed, effects=args.effect), indent=2))
        return
    if not args.sweep:
        print(jsonout.dumps(run(quick=args.quick), indent=2))
        return

    def progress(row):
        import sys

        print(jsonout.dumps(row), file=sys.stderr, flush=True)

    result = sweep(args.effect, seed=args.seed, progress=progress)
    print(jsonout.dumps(result, indent=2) if args.json else sweep_table(result["cases"]))


if __name__ == "__main__":
    main()
