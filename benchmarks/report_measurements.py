"""BENCHMARKS.md sections of the measurements taken on this machine at each report.

Adaptation step latency, MPC solve time, the realtime service loop, the numerics soak and
the discrepancy workflow: each section renders the result of its benchmark's ``run``.
"""

from __future__ import annotations

from typing import Any

from benchmarks.discrepancy import HIDDEN


def adapt_section(r: dict[str, Any]) -> list[str]:
    lines = [
        "## Adaptation step latency (`arcade bench adapt --json`)",
        "",
        f"One step = predict (Eq. 9) + update of both branches (Eqs. 5-8) + top-K prune, "
        f"d = {r['d']}, l = {r['l']}, float32, CPU. Paper: ~7.6 ms per step on a GPU host.",
        "",
        "Side by side: the quadrotor preset with the offline prior re-injected at changepoints "
        "(`prior_floor = 1`, one l x l Cholesky factorisation per hypothesis and step) and "
        "Eq. 5 as written (`prior_floor = 0`).",
        "",
        "| K | prior floor | median (µs) | p99 (µs) |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {x['K']} | {x.get('prior_floor', 1.0):g} | {x['median_us']:.1f} | {x['p99_us']:.1f} |"
        for x in r["results"]
    ]
    for floor in sorted({x.get("prior_floor", 1.0) for x in r["results"]}, reverse=True):
        by_k = {x["K"]: x["median_us"] for x in r["results"] if x.get("prior_floor", 1.0) == floor}
        if 5 in by_k and 30 in by_k:
            lines += [
                "",
                f"Prior floor {floor:g}: K=30 / K=5 median ratio {by_k[30] / by_k[5]:.2f}",
            ]
    return [*lines, ""]


def mpc_section(runs: list[dict[str, Any]]) -> list[str]:
    lines = [
        "## MPC solve time (`arcade bench mpc --json [--residual rollout|held]`)",
        "",
        "Quadrotor, N = 20 over 1 s, learned residual (VLD encoder [64,128,64], l = 8), "
        "warm-started along a figure-eight, float32, CPU. `rollout`: the residual inside "
        "the rollout, derivatives included (what the controller runs); `held`: evaluated "
        "along the warm start and held per stage (evaluation included in the time).",
        "",
        "| residual | median (ms) | p99 (ms) | mean iterations | tracking RMSE (m) |",
        "|---|---|---|---|---|",
    ]
    lines += [
        f"| {r['residual']} | {r['median_ms']:.2f} | {r['p99_ms']:.2f} | "
        f"{r['mean_iterations']:.2f} | {r['tracking_rmse_m']:.4f} |"
        for r in runs
    ]
    lines.append("")
    for r in runs:
        keys = ", ".join(f"{k} = {v}" for k, v in r.items() if k not in ("machine",))
        lines += [f"All fields ({r['residual']}): {keys}", ""]
    return lines


def _controller_line(r: dict[str, Any]) -> str:
    solve = f"MPC solve p50/p99 {r['mpc_p50_ms']:.2f}/{r['mpc_p99_ms']:.2f} ms"
    if not r.get("advanced_step"):
        return f"Sense-to-actuate stage by stage ({solve}, inside the controller's stage):"
    return (
        f"Sense-to-actuate stage by stage. The controller's advanced step: its {solve} for "
        "the next instant after each setpoint, off this path; the controller's stage answers "
        f"a state from the prepared plan (step p50/p99 {r['answer_p50_ms']:.2f}/"
        f"{r['answer_p99_ms']:.2f} ms; {r['planned_steps']} of {r['control_steps']} states):"
    )


def loop_section(r: dict[str, Any]) -> list[str]:
    return [
        "## Service loop (`arcade bench loop --json`, realtime, full stack over Zenoh)",
        "",
        "Targets: one-hop p99 <= 1 ms; sense-to-actuate p99 <= 10 ms and <= MPC p99 + 3 ms; "
        "50 Hz for 120 s with zero missed deadlines.",
        "",
        "| hop p50 (ms) | hop p99 (ms) | sense-to-actuate p99 (ms) | rate (Hz) | missed "
        "deadlines | duration (s) |",
        "|---|---|---|---|---|---|",
        f"| {r['hop_p50_ms']:.2f} | {r['hop_p99_ms']:.2f} | {r['sense_to_actuate_p99_ms']:.2f} "
        f"| {r['rate_hz']:.2f} | {r['missed_deadlines']} | {r['duration_s']:.0f} |",
        "",
        "Conditions: "
        + ", ".join(
            f"{name} {c['policy']}"
            + (
                f" + CPU wake-up latency {c['cpu_wakeup_latency_us']} µs"
                if c["cpu_wakeup_latency_us"] is not None
                else " (idle CPUs may sleep)"
            )
            for name, c in r["realtime"].items()
        )
        + ".",
        "",
        _controller_line(r),
        "",
        "| stage | p50 (ms) | p99 (ms) |",
        "|---|---|---|",
        *(f"| {name} | {v[0]:.2f} | {v[1]:.2f} |" for name, v in r["stages_ms"].items()),
        "",
        f"All fields: {', '.join(f'{k} = {v}' for k, v in r.items() if k != 'machine')}",
        "",
    ]


def soak_section(r: dict[str, Any]) -> list[str]:
    lines = [
        "## Numerics soak (`arcade bench soak --json`)",
        "",
        f"{r['steps']:,} steps of the packed adaptation step (d = 13, l = 8, K = 15, quadrotor "
        "preset) on a stream with frequent and bursty decoder jumps, Student-t (1.5 dof) "
        "noise and 1 % outliers; see `benchmarks/soak.py` for the checks. Lemma 2 as stated "
        "(`tau^2 R^2`) must hold with the full prior floor; with Eq. 5 as written (floor 0) "
        "its violations are counted (unexcited directions grow by `1/beta^2` per "
        "changepoint).",
        "",
        "| prior floor | dtype | µs/step | non-finite | min eig | tempered envelope viol. | "
        "data envelope max | Lemma 2 stated: max ratio | steps violating | ok |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for x in r["results"]:
        s = x["lemma2_stated"]
        lines.append(
            f"| {x.get('prior_floor', 0.0):g} | {x['dtype']} | {x['us_per_step']:.1f} | "
            f"{x['nonfinite_steps']} | "
            f"{x['min_eigenvalue']:.2e} | {x['prior_envelope_violations']} | "
            f"{x['data_envelope_max_ratio']:.3f} | {s['max_ratio']:.3f} | "
            f"{s['steps_with_violation']} | {x['ok']} |"
        )
    return [*lines, ""]


def discrepancy_section(r: dict[str, Any]) -> list[str]:
    hidden = "; ".join(
        name + " " + ", ".join(f"{k} = {v}" for k, v in params.items())
        for name, params in HIDDEN.items()
    )
    before, after = r["heldout_rmse_before"], r["heldout_rmse_after"]
    lines = [
        "## Discrepancy workflow (`arcade bench discrepancy --json`)",
        "",
        f"A simulated flight of the standard exciting trajectory ({r['minutes_of_data']:g} min "
        f"of 100 Hz data, {r['samples']:,} samples) with effects the nominal model lacks "
        f"({hidden}); the workflow (alignment, localisation, selection with 200 bootstrap "
        "resamples, fit, held-out evaluation) has to name them, fit their parameters and "
        f"shrink the held-out gap. Target: at most {r['target_s']:g} s, JAX compilation (or "
        "loading it from the cache) included.",
        "",
        "| workflow cold (s) | warm (s) | within target | named | held-out one-step RMSE "
        "before | after | gap shrink |",
        "|---|---|---|---|---|---|---|",
        f"| {r['cold_s']:.1f} | {r['warm_s']:.1f} | {r['within_target']} | "
        f"{', '.join(r['named']) or 'none'} | {before:.4f} | {after:.4f} | "
        f"{100 * (1 - after / before):.0f} % |",
        "",
        "| effect | confidence | parameter error (relative) |",
        "|---|---|---|",
    ]
    for name in HIDDEN:
        err = r["parameter_rel_error"].get(name)
        conf = r["confidence"].get(name)
        lines.append(
            f"| {name} | {'—' if conf is None else f'{conf:.2f}'} | "
            f"{'not found' if err is None else f'{100 * err:.1f} %'} |"
        )
    lines += [
        "",
        f"Held-out RMSE over the components {', '.join(r['heldout_components'])} "
        "of the held-out part of the flight (one-step prediction error, SI units: m/s and "
        "rad/s).",
        "",
    ]
    return lines
