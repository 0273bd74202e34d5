"""The BENCHMARKS.md section of the stored closed-loop evaluation in the stack's condition.

`arcade eval quadrotor --condition stack` flies every method as the service stack flies it:
on the estimator's state (the motion capture's noise and latency), behind the simulated
PX4 link's 20 ms setpoint delay, compensated; every method tuned in that condition. This is
the condition users fly, so its section leads the closed-loop tables. The report renders
the stored run (its own command: 3-4 hours on 2 cores with the tuning); paired differences to L1
with 95 % bootstrap intervals for the tracking, horizontal and vertical RMSE.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from benchmarks.common import RESULTS
from benchmarks.report_paired import ORDER, cell_means, paired_lines, with_horizontal
from benchmarks.report_quadrotor import (
    cell_table,
    flagship_smoothness,
    grid_edges,
    provenance,
    stored_run,
)

STACK_DIR = RESULTS / "quadrotor_stack"
STACK_COMMAND = f"arcade eval quadrotor --condition stack --out {STACK_DIR.as_posix()}"


def _command(settings: dict[str, Any]) -> str:
    """The command that wrote a run with ``settings``."""
    cmd = STACK_COMMAND
    if settings.get("knobs") == "stored":
        cmd += " --stored-knobs"
    methods = settings.get("methods")
    if methods and set(methods) != set(ORDER):
        cmd += f" --methods {','.join(methods)}"
    return cmd


def stack_section(path: Path) -> list[str]:
    """Tables of the stored stack-condition evaluation (its own command)."""
    head = [
        "## Quadrotor closed loop as the stack flies it (`arcade eval quadrotor --condition "
        "stack`)",
        "",
    ]
    if not path.is_file():
        return [
            *head,
            f"No results yet: run `{STACK_COMMAND}` (3-4 hours on 2 cores; with "
            "`--stored-knobs`, no tuning, about 50 minutes for five methods), then "
            "`make benchmarks`.",
            "",
        ]
    r, when = stored_run(path)
    s = r.get("settings", {})
    trials = with_horizontal(r.get("trials", []))
    lines = [
        *head,
        provenance(path, r, when, _command(s)),
        "",
        "Every method flies on the estimator's state (motion-capture noise and latency) "
        "behind the simulated PX4 link's 20 ms setpoint delay, compensated, as the service "
        "stack flies"
        + (
            "; with the knobs stored for this condition (below)"
            if s.get("knobs") == "stored"
            else "; each tuned in this condition on a cell that is not evaluated (same grids "
            "and budget for every method)"
        )
        + f". {s.get('trials', '?')} paired seeds per cell "
        f"(the same seeds for every method; {', '.join(s.get('methods', []))} flown); "
        "figure-eight with a swinging payload released "
        "before the second lap. `arcade` is the product's controller (what `arcade up` "
        "flies), not the paper's method; `ours` is the paper's method with `beta` and "
        "`sigma^2` chosen for this condition, `ours_paper` the paper's method at Appendix "
        "D's values.",
        "",
        *paired_lines(r),
        "Tracking RMSE (m; mean over the seeds, best in bold):",
        "",
        *cell_table(r["cells"], "rmse_m", ".3f", order=ORDER),
        "",
        "Horizontal RMSE (m):",
        "",
        *cell_table(cell_means(trials, "rmse_xy_m"), "rmse_xy_m", ".3f", order=ORDER),
        "",
        "z-RMSE (m):",
        "",
        *cell_table(r["cells"], "rmse_z_m", ".3f", order=ORDER),
        "",
        "RMS change of the thrust command from one control period to the next (N; "
        "smoothness, lower is smoother):",
        "",
        *cell_table(r["cells"], "thrust_increment_rms_n", ".2f", order=ORDER),
        "",
        "MPC solves that converged within the iteration limit (fraction):",
        "",
        *cell_table(r["cells"], "converged_fraction", ".2f", best=max, order=ORDER),
        "",
        "Shift magnitude at the release (m):",
        "",
        *cell_table(r["cells"], "shift_m", ".3f", order=ORDER),
        "",
        "Settling time after the release, 0.05 m band (s; `inf` when a seed never settled):",
        "",
        *cell_table(r["cells"], "settling_s", ".2f", missing=math.inf, order=ORDER),
        "",
    ]
    tuning = r.get("tuning")
    if s.get("knobs") == "stored":
        tuned = s.get("tuned", {})
        lines += [
            "Not tuned in this run (`--stored-knobs`): every method flew the knobs stored "
            "for this condition, the service stack's own where it has them "
            "(`arcade_control.stack`: chosen in this condition before, by the protocol's "
            "tuning for L1 and ours, partly by hand for the flagship: "
            "docs/quadrotor-closed-loop.md), the evaluation's otherwise: "
            + ", ".join(f"{k} = {v:g}" for k, v in tuned.items())
            + ". A full run (`arcade eval quadrotor --condition stack`) tunes every method "
            "again.",
            "",
        ]
    elif tuning:
        cell = tuning.get("cell", ["?", "?"])
        lines += [
            f"Knobs tuned in this condition on {cell[0]:g} g, {cell[1]:g} m/s (not "
            f"evaluated), {len(tuning.get('seeds', []))} flights per grid value: "
            + ", ".join(f"{k} = {v:g}" for k, v in tuning["chosen"].items())
            + "; `arcade_thrust_smooth` (the MPC's weight on thrust changes) is set by "
            "hand; `ours_paper` keeps Appendix D's values."
            + grid_edges(tuning)
            + flagship_smoothness(tuning),
            "",
        ]
    return lines
