"""BENCHMARKS.md sections of the stored quadrotor variant runs (``benchmarks.quadrotor_variants``).

The variants, the oracle, the estimated-state, estimator, delay and link diagnostics: each
section renders its stored JSON file, or names the command that makes it.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

from benchmarks.common import RESULTS
from benchmarks.report_quadrotor import cell_table

VARIANTS_DIR = RESULTS / "quadrotor_variants"
VARIANTS_COMMAND = f"arcade bench variants --out {(VARIANTS_DIR / 'results.json').as_posix()}"


def _not_yet(head: list[str], command: str) -> list[str]:
    """A section whose stored run is missing: the command that makes it."""
    return [*head, f"No results yet: run `{command}`, then `make benchmarks`.", ""]


def variants_section(path: Path) -> list[str]:
    """The stored `arcade bench variants` run (its own command, ~13 min on 2 cores)."""
    head = ["## Quadrotor variants beside ours (`arcade bench variants`)", ""]
    if not path.is_file():
        return _not_yet(head, VARIANTS_COMMAND)
    r = json.loads(path.read_text())
    order = tuple(r["methods"])
    tuned = r.get("tuning", {}).get("chosen", {})
    lines = [
        *head,
        _provenance(path, r, VARIANTS_COMMAND),
        "",
        "`ours_matched` is not the paper's method: ours with an intercept feature, whose MPC "
        "plans only with the thrust-axis part of the learned residual "
        "(`arcade_control.methods.beam_method`; read in "
        "`docs/quadrotor-closed-loop.md`)."
        + (
            " `arcade`, the stack's own controller in the making, is not the paper's method "
            "either: `ours_matched`'s model in the MPC plus an L1 thrust augmentation whose "
            "predictor includes that model (`arcade_control.methods.arcade_method`)."
            if "arcade" in order
            else ""
        )
        + " Scenario, seeds and metrics of `arcade eval "
        f"quadrotor`; mean over {r['trials']} trials per cell; every method tuned in the same "
        "run (" + ", ".join(f"{k} = {v:g}" for k, v in tuned.items()) + "); best in bold.",
        "",
    ]
    for title, key, fmt in (
        ("Tracking RMSE (m)", "rmse_m", ".4f"),
        ("z-RMSE (m)", "rmse_z_m", ".4f"),
        ("Shift magnitude at the release (m)", "shift_m", ".4f"),
        ("Settling time after the release, 0.05 m band (s, mean)", "settling_s", ".2f"),
    ):
        missing = math.inf if key == "settling_s" else math.nan
        lines += [
            f"{title}:",
            "",
            *cell_table(r["cells"], key, fmt, order=order, missing=missing),
            "",
        ]
    return lines


ORACLE_COMMAND = (
    f"python -m benchmarks.quadrotor_variants oracle > {(VARIANTS_DIR / 'oracle.json').as_posix()}"
)


def _row_cells(r: dict[str, Any], order: tuple[str, ...]) -> list[dict[str, Any]]:
    """The cells of a diagnostic run stored by rows (one row per payload and speed, one
    entry per method of ``order``) in :func:`cell_table`'s form."""
    return [
        {"payload_g": row["payload_g"], "speed_mps": row["speed_mps"], "method": m, **row[m]}
        for row in r["rows"]
        for m in order
    ]


def _rmse_tables(cells: list[dict[str, Any]], order: tuple[str, ...]) -> list[str]:
    """The tracking RMSE and z-RMSE tables of a stored diagnostic run, best in bold."""
    lines: list[str] = []
    for title, key in (("Tracking RMSE (m)", "rmse_m"), ("z-RMSE (m)", "rmse_z_m")):
        lines += [f"{title}:", "", *cell_table(cells, key, ".4f", order=order), ""]
    return lines


def _flown_order(r: dict[str, Any]) -> tuple[str, ...]:
    """The rows of a stored diagnostic run, in the order they were flown."""
    return tuple(row["name"] for row in r["rows_flown"])


def _tuning_cell_words(rec: dict[str, Any]) -> str:
    """The tuning cell and seeds a stored run scored its grid on, in words."""
    cell = ", ".join(f"{v:g}" for v in rec["cell"])
    return f"({cell}: payload g, speed m/s; seeds {', '.join(map(str, rec['seeds']))})"


def _grid_table(column: str, labels: list[str], rmse: dict[str, list[float]]) -> list[str]:
    """Mean tracking RMSE per grid value (rows ``labels``) and method (``rmse``'s keys)."""
    names = list(rmse)
    lines = ["| " + column + " | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for i, label in enumerate(labels):
        lines.append(f"| {label} | " + " | ".join(f"{rmse[n][i]:.4f}" for n in names) + " |")
    return lines


def _provenance(path: Path, r: dict[str, Any], command: str) -> str:
    """Where a stored diagnostic run comes from: file, date, command, machine, time."""
    when = r.get("generated") or time.strftime(
        "%Y-%m-%d %H:%M", time.localtime(path.stat().st_mtime)
    )
    return (
        f"From `{path.as_posix()}`, written {when} by `{command}` on "
        f"{r.get('machine', '?')}, in {r['wall_time_s'] / 60:.0f} min (not re-run by "
        "`make benchmarks`)."
    )


def oracle_section(path: Path) -> list[str]:
    """The stored mass-oracle run (its own command, ~8 min on 2 cores)."""
    head = ["## Quadrotor: what knowing the payload would give (mass oracle)", ""]
    if not path.is_file():
        return _not_yet(head, ORACLE_COMMAND)
    r = json.loads(path.read_text())
    order = tuple(r["methods"])
    cells = _row_cells(r, order)
    lines = [
        *head,
        _provenance(path, r, ORACLE_COMMAND),
        "",
        "`oracle_mass` is a diagnostic, not a method: the nominal model plus what hangs from "
        "the vehicle (payload and cable) as a rigid mass, known exactly and dropped at the "
        "exact release step (`arcade_control.methods.oracle_mass_method`; read in "
        "`docs/quadrotor-closed-loop.md`). Scenario and seeds of `arcade eval quadrotor`, "
        f"the stored knobs; mean over {r['trials']} trials per cell; best in bold.",
        "",
    ]
    return lines + _rmse_tables(cells, order)


ESTIMATED_COMMAND = (
    "python -m benchmarks.quadrotor_variants estimated > "
    f"{(VARIANTS_DIR / 'estimated.json').as_posix()}"
)
#: The rows of the stored run flown on the state estimate, in table order.
ESTIMATED_ROWS = ("l1_estimated", "ours_estimated", "ours_stack_estimated")


def estimated_section(path: Path) -> list[str]:
    """The stored run on the state estimate (its own command, ~5 min on 2 cores)."""
    head = ["## Quadrotor: on the state estimate the service stack flies", ""]
    if not path.is_file():
        return _not_yet(head, ESTIMATED_COMMAND)
    r = json.loads(path.read_text())
    cells = _row_cells(r, ESTIMATED_ROWS)
    lines = [
        *head,
        _provenance(path, r, ESTIMATED_COMMAND),
        "",
        "A diagnostic: the evaluation's trials flown on the estimator's output from the "
        "emulated motion capture and gyro instead of the ground-truth state "
        "(`Runner.fly(..., estimated=True)`; ours adds the estimate's noise to its "
        "observation noise, as the stack's adapter does). `ours_stack`: ours with the "
        "stack's adapter knobs (sigma^2 = 0.1, beta = 0.05). Seeds 0 to "
        f"{r['trials'] - 1} of `arcade eval quadrotor`, the stored knobs otherwise; best in "
        "bold; read in `docs/quadrotor-closed-loop.md`.",
        "",
    ]
    return lines + _rmse_tables(cells, ESTIMATED_ROWS)


ESTIMATOR_COMMAND = (
    "python -m benchmarks.quadrotor_variants estimator > "
    f"{(VARIANTS_DIR / 'estimator.json').as_posix()}"
)


def estimator_section(path: Path) -> list[str]:
    """The stored tuning of the estimator's jerk density (its own command, ~8 min)."""
    head = ["## Quadrotor: the estimator's jerk density, tuned for the closed loop", ""]
    if not path.is_file():
        return _not_yet(head, ESTIMATOR_COMMAND)
    r = json.loads(path.read_text())
    tuning = r["tuning"]
    order = _flown_order(r)
    labels = [f"{v:g}" + (" (picked)" if v == tuning["chosen"] else "") for v in tuning["grid"]]
    lines = [
        *head,
        _provenance(path, r, ESTIMATOR_COMMAND),
        "",
        "The estimator's constant-acceleration model (`FilterConfig.jerk_psd`, the service's "
        "`--jerk-psd`) trades the velocity's noise against its lag. L1 and ours with the "
        "stack's adapter knobs (`ours_stack`) fly on the state estimate on the tuning cell "
        f"{_tuning_cell_words(tuning)}; the "
        "value picked minimises the larger of the two methods' RMSE over its best on the "
        "grid (one estimator serves every controller). Mean tracking RMSE (m) on the "
        "tuning cell:",
        "",
        *_grid_table("jerk density", labels, tuning["rmse_m"]),
        "",
        f"The nine cells with the hand-set {tuning['hand_set']:g} and the value picked "
        f"(`name@value`), seeds 0 to {r['trials'] - 1} of `arcade eval quadrotor`, the "
        "stored knobs otherwise; best in bold; read in `docs/quadrotor-closed-loop.md`.",
        "",
    ]
    return lines + _rmse_tables(_row_cells(r, order), order)


DELAY_COMMAND = (
    f"python -m benchmarks.quadrotor_variants delay > {(VARIANTS_DIR / 'delay.json').as_posix()}"
)


def delay_section(path: Path) -> list[str]:
    """The stored command-delay diagnostic (its own command, ~15 min on 2 cores)."""
    head = ["## Quadrotor: a delay between the controller and the rate loop", ""]
    if not path.is_file():
        return _not_yet(head, DELAY_COMMAND)
    r = json.loads(path.read_text())
    sens, tuning = r["sensitivity"], r["tuning"]
    names = list(sens["rmse_m"])
    order = _flown_order(r)
    delay_ms = 1e3 * tuning["command_delay_s"]
    knobs = "; ".join(
        f"{n}: " + ", ".join(f"{k} = {v:g}" for k, v in sens["knobs"][n].items()) for n in names
    )
    lines = [
        *head,
        _provenance(path, r, DELAY_COMMAND),
        "",
        "The evaluation applies each setpoint at the instant of the state it was computed "
        "from; an offboard link to an autopilot delays it (`Scenario.command_delay_s`, the "
        "simulator's `command_delay_s`). Mean tracking RMSE (m) on the tuning cell "
        f"{_tuning_cell_words(sens)} at the stored knobs ({knobs}):",
        "",
        *_grid_table("delay (ms)", [f"{1e3 * d:g}" for d in sens["delays_s"]], sens["rmse_m"]),
    ]

    def knobs(t: dict[str, Any]) -> str:
        return ", ".join(f"{k} = {v:g}" for k, v in t["chosen"].items())

    compensated = r.get("tuning_compensated")
    also = f"; compensating it: {knobs(compensated)}" if compensated else ""
    lines += [
        "",
        f"Tuned again by the evaluation's protocol with {delay_ms:g} ms: {knobs(tuning)}"
        f"{also}. The nine cells without and with {delay_ms:g} ms (`name@delay`; "
        "`_compensated`: learning and planning from the state predicted over the delay; "
        "`_retuned`: the knobs tuned again, where they differ from the stored ones), seeds "
        f"0 to {r['trials'] - 1} of `arcade eval quadrotor`; best in bold; read in "
        "`docs/quadrotor-closed-loop.md`.",
        "",
    ]
    return lines + _rmse_tables(_row_cells(r, order), order)


LINK_COMMAND = (
    f"python -m benchmarks.quadrotor_variants link > {(VARIANTS_DIR / 'link.json').as_posix()}"
)


def link_section(path: Path) -> list[str]:
    """The stored link-delay diagnostic of the stack (its own command, ~40 min on 2 cores)."""
    head = ["## Quadrotor: the service stack behind a delaying link", ""]
    if not path.is_file():
        return _not_yet(head, LINK_COMMAND)
    r = json.loads(path.read_text())
    sens, tuning = r["sensitivity"], r["tuning"]
    rows = sens["rows"]
    order = _flown_order(r)
    labels = [f"{1e3 * d:g}" for d in sens["delays_s"]]
    knobs = "; ".join(
        f"{n}: " + ", ".join(f"{k} = {v:g}" for k, v in sens["knobs"][n].items())
        for n in sens["knobs"]
    )
    chosen = ", ".join(f"{k} = {v:g}" for k, v in tuning["chosen"].items())
    delay_ms = 1e3 * tuning["command_delay_s"]
    return [
        *head,
        _provenance(path, r, LINK_COMMAND),
        "",
        "What the service stack flies when the link delays every setpoint: ours with the "
        f"stack's adapter knobs and L1 ({knobs}), both on the state estimate, on the tuning "
        f"cell {_tuning_cell_words(sens)}. `_compensated`: planning and learning from the "
        "state predicted over the delay (`arcade up --link-delay`); at 0 ms it is the same "
        "flight. Mean tracking RMSE (m):",
        "",
        *_grid_table("delay (ms)", labels, {n: v["rmse_m"] for n, v in rows.items()}),
        "",
        "z-RMSE (m):",
        "",
        *_grid_table("delay (ms)", labels, {n: v["rmse_z_m"] for n, v in rows.items()}),
        "",
        f"Tuned again by the evaluation's protocol in the stack's condition (the estimate, "
        f"{delay_ms:g} ms, compensated): {chosen}. The nine cells in that condition "
        "(`_retuned`: the knobs tuned so, where they differ from the stack's for ours and "
        f"the stored ones for L1), seeds 0 to {r['trials'] - 1} of `arcade eval "
        "quadrotor`; best in bold; read in `docs/quadrotor-closed-loop.md`.",
        "",
        *_rmse_tables(_row_cells(r, order), order),
    ]
