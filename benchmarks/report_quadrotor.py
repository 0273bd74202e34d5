"""The BENCHMARKS.md section of the stored quadrotor evaluation (paper Sec. V-B, Tables II, III, V).

The evaluation has its own command (about 3 hours on 2 cores); the report renders its
stored results, one table per metric with a cell per payload, speed and method.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from arcade_control.knobs import FLAGSHIP
from arcade_io import jsonout
from benchmarks.common import RESULTS
from benchmarks.report_paired import ORDER, paired_lines

QUADROTOR_DIR = RESULTS / "quadrotor"
QUADROTOR_COMMAND = f"arcade eval quadrotor --out {QUADROTOR_DIR.as_posix()}"
#: Column order of the tables: the flagship and L1 first (:data:`benchmarks.report_paired.ORDER`).
METHODS = ORDER


def grid_edges(tuning: dict[str, Any]) -> str:
    """One sentence on the grids' edges of a tuning (:func:`benchmarks.quadrotor_closedloop.tune`):
    the values added past an edge a best value lay on, and the knobs still on an edge; empty
    for a run stored before the grids were extended."""
    if "extended" not in tuning:
        return ""
    added = "; ".join(
        f"{k} {', '.join(f'{v:g}' for v in vs)}" for k, vs in tuning["extended"].items()
    )
    edge = ", ".join(tuning.get("still_on_edge", [])) or "none"
    return (
        f" Grids extended past an edge a best value lay on: {added or 'none'}; still on an "
        f"edge (the knob's range exhausted): {edge}."
    )


def flagship_smoothness(tuning: dict[str, Any]) -> str:
    """One sentence on the flagship's tuning constraint (:mod:`benchmarks.quadrotor_tuning`);
    empty for a run without it."""
    ft = tuning.get("flagship_thrust")
    if not ft:
        return ""
    return (
        f" The flagship's knobs are the lowest tuning RMSE among the settings whose thrust "
        f"increments are at most {ft['max_ratio_to_l1']:g} times L1's on the same flights "
        f"(L1 {ft['l1_thrust_increment_rms_n']:.3f} N, the choice "
        f"{ft['chosen_thrust_increment_rms_n']:.3f} N)."
    )


def cell_table(
    cells: list[dict[str, Any]],
    key: str,
    fmt: str,
    best=min,
    order: tuple[str, ...] = METHODS,
    missing: float = math.nan,
) -> list[str]:
    """One row per (payload, speed), one column per method of ``order`` present; the best
    value in bold. A value the results file holds as ``null`` reads as ``missing``
    (``inf`` for a settling time: a trial never settled)."""
    by_cell: dict[tuple[float, float], dict[str, float]] = {}
    for c in cells:
        by_cell.setdefault((c["payload_g"], c["speed_mps"]), {})[c["method"]] = jsonout.number(
            c[key], missing
        )
    methods = [m for m in order if any(m in v for v in by_cell.values())]
    lines = [
        "| payload (g) | speed (m/s) | " + " | ".join(methods) + " |",
        "|---|---|" + "---|" * len(methods),
    ]
    for (pay, speed), vals in sorted(by_cell.items()):
        top = best(vals.values())
        row = [
            (f"**{vals[m]:{fmt}}**" if vals[m] == top else f"{vals[m]:{fmt}}") if m in vals else "-"
            for m in methods
        ]
        lines.append(f"| {pay:g} | {speed:g} | " + " | ".join(row) + " |")
    return lines


def _settling_per_trial(trials: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per cell and method: median settling time over the trials, and how many trials
    were outside the band at some sample after the release (settling time above zero)."""
    by: dict[tuple[float, float, str], list[float]] = {}
    for t in trials:
        by.setdefault((t["payload_g"], t["speed_mps"], t["method"]), []).append(
            jsonout.number(t["settling_s"], math.inf)  # null: never settled
        )
    return [
        {
            "payload_g": p,
            "speed_mps": v,
            "method": m,
            "median": float(np.median(x)),
            "left_band": int(np.sum(np.asarray(x) > 0)),
        }
        for (p, v, m), x in by.items()
    ]


def _diagnostics_tables(cells: list[dict[str, Any]]) -> list[str]:
    """Command increments and changepoint rate per cell (absent from older result files)."""
    if not any("thrust_increment_rms_n" in c for c in cells):
        return []
    beam = [c for c in cells if c["method"].startswith("ours") and c["method"] != "ours_no_cp"]
    return [
        "Diagnostics beside the paper's metrics (lower is smoother; not targets). RMS change "
        "of the thrust command from one control period to the next (N):",
        "",
        *cell_table(cells, "thrust_increment_rms_n", ".2f"),
        "",
        "RMS change of the body-rate commands from one control period to the next "
        "(rad/s, three axes):",
        "",
        *cell_table(cells, "rate_increment_rms_rad_s", ".2f"),
        "",
        "Control steps on which ours flagged a changepoint (fraction of the figure-eight):",
        "",
        *cell_table(beam, "changepoint_rate", ".2f", best=lambda v: None),
        "",
    ]


def stored_run(path: Path) -> tuple[dict[str, Any], str]:
    """A stored evaluation's results and when they were written (their ``generated``, else
    the file's time)."""
    r = json.loads(path.read_text())
    when = r.get("generated") or time.strftime(
        "%Y-%m-%d %H:%M", time.localtime(path.stat().st_mtime)
    )
    return r, when


def provenance(path: Path, r: dict[str, Any], when: str, command: str) -> str:
    """The line saying which stored run a section renders: file, time, command, machine."""
    return (
        f"From `{path.as_posix()}`, written {when} by `{command}`"
        + (f" on {r['machine']}" if r.get("machine") else "")
        + (f", in {r['wall_time_s'] / 60:.0f} min" if r.get("wall_time_s") else "")
        + " (not re-run by `make benchmarks`)."
    )


def quadrotor_section(path: Path) -> list[str]:
    """Tables of the stored quadrotor evaluation (its own command: ~3 h on 2 cores)."""
    head = [
        "## Quadrotor, the paper's condition (`arcade eval quadrotor --json`; paper Sec. V-B, "
        "Tables II, III, V)",
        "",
        "Every method on the true state, no setpoint delay: the paper's setting, not what the "
        "stack flies (the section above).",
        "",
    ]
    if not path.is_file():
        return [
            *head,
            f"No results yet: run `{QUADROTOR_COMMAND}` (about 3 hours on 2 "
            "cores), then `make benchmarks`.",
            "",
        ]
    r, when = stored_run(path)
    s = r.get("settings", {})
    lines = [
        *head,
        provenance(path, r, when, QUADROTOR_COMMAND),
        "",
        f"Closed loop, figure-eight with a swinging payload released before the second lap; "
        f"mean over {s.get('trials', '?')} seeded trials per cell (the same seeds for every "
        "method); best in bold."
        + (
            " `arcade` is the product's controller (what `arcade up` flies), not the paper's "
            "method; `ours` is the paper's method with `beta` and `sigma^2` tuned, "
            "`ours_paper` the paper's method at Appendix D's values."
            if any(c["method"] == FLAGSHIP for c in r["cells"])
            else ""
        ),
        "",
        *paired_lines(r),
        "Tracking RMSE (m):",
        "",
        *cell_table(r["cells"], "rmse_m", ".3f"),
        "",
        "z-RMSE (m):",
        "",
        *cell_table(r["cells"], "rmse_z_m", ".3f"),
        "",
        "Shift magnitude at the release (m):",
        "",
        *cell_table(r["cells"], "shift_m", ".3f"),
        "",
        "Settling time after the release, 0.05 m band (s; mean over the trials, `inf` when "
        "one of them never settled):",
        "",
        *cell_table(r["cells"], "settling_s", ".2f", missing=math.inf),
        "",
    ]
    if r.get("trials"):
        per = _settling_per_trial(r["trials"])
        lines += [
            "The settling time of a trial counts any excursion out of the band after the "
            "release, however late, so one trial can move the mean. Median over the trials (s):",
            "",
            *cell_table(per, "median", ".2f"),
            "",
            f"Trials (of {s.get('trials', '?')} per cell) in which the z error was outside the "
            "band at some sample after the release:",
            "",
            *cell_table(per, "left_band", "d"),
            "",
        ]
    lines += _diagnostics_tables(r["cells"])
    tuning = r.get("tuning")
    if tuning:
        cell = tuning.get("cell", ["?", "?"])
        n = len(tuning.get("seeds", [tuning.get("seed")]))
        how = (
            f"{n} flight{'s' if n > 1 else ''} per grid value, lowest mean RMSE; one knob "
            "after the other"
            + (f", {tuning['passes']} passes until none changed" if "passes" in tuning else "")
        )
        lines.append(
            f"Knobs tuned on a cell that is not evaluated ({cell[0]:g} g, {cell[1]:g} m/s, "
            f"{how}): "
            + ", ".join(f"{k} = {v:g}" for k, v in tuning["chosen"].items())
            + (
                "; `arcade_thrust_smooth` (the MPC's weight on thrust changes) is set by "
                "hand; `ours_paper` keeps Appendix D's values"
                if any(c["method"] == FLAGSHIP for c in r["cells"])
                else ""
            )
            + "; everything else at the paper's values."
            + grid_edges(tuning)
            + flagship_smoothness(tuning)
        )
        lines.append("")
    for imp in r.get("improvement_over_nominal", []):
        lines.append(
            f"- RMSE improvement over nominal MPC at {imp['payload_g']:g} g, "
            f"{imp['speed_mps']:g} m/s: "
            + ", ".join(
                f"{m} {v:.0f} %" for m, v in imp.items() if m not in ("payload_g", "speed_mps")
            )
        )
    ol = r.get("openloop")
    if ol:
        lines += [
            "",
            "Open loop with online updates (Table II analogue), CRMSE on the validation flights:",
            "",
            "| method | CRMSE |",
            "|---|---|",
        ]
        lines += [f"| {m} | {ol['table'][m]['crmse']:.4f} |" for m in ol["order"]]
        g = ol.get("gramian")
        if g:
            lines += [
                "",
                "Gramian diagnostics (Fig. 4): "
                + ", ".join(
                    f"{k} = {v:.4g}" if isinstance(v, float) else f"{k} = {v}"
                    for k, v in g.items()
                    if not isinstance(v, dict | list)
                ),
            ]
    ab = r.get("beam_ablation")
    if ab:
        lines += [
            "",
            f"Beam ablation (Table V) at {ab['payload_g']:g} g, "
            f"{ab['speed_mps']:g} m/s, beta = {ab['beta']:g}:",
            "",
            "| K | RMSE (m) | adaptation (ms/step) |",
            "|---|---|---|",
        ]
        lines += [
            f"| {row['K']} | {row['rmse_m']:.3f} | {row['adapt_ms_per_step']:.3f} |"
            for row in ab["rows"]
        ]
    ra = r.get("residual_ablation")
    if ra:
        lines += [
            "",
            f"Learned residual in the MPC at {ra['payload_g']:g} g, "
            f"{ra['speed_mps']:g} m/s ({ra['trials']} trials): inside the rollout "
            "(what the methods above fly) or held along the warm start:",
            "",
            "| method | residual | RMSE (m) | z-RMSE (m) | step (ms) |",
            "|---|---|---|---|---|",
        ]
        lines += [
            f"| {row['method']} | {row['residual']} | {row['rmse_m']:.3f} | "
            f"{row['rmse_z_m']:.3f} | {row['step_ms_median']:.2f} |"
            for row in ra["rows"]
        ]
    figs = sorted(path.parent.glob("*.png"))
    if figs:
        lines += ["", "Figures:", ""] + [f"- [{p.stem}]({p.as_posix()})" for p in figs]
    return [*lines, ""]
