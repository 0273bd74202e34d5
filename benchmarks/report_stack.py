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

from arcade_control.knobs import FLAGSHIP, FLAGSHIP_ABLATIONS, METHODS, PAPER_SETTINGS
from benchmarks.common import RESULTS
from benchmarks.quadrotor_protocol import paired_differences
from benchmarks.report_quadrotor import cell_table, provenance, stored_run

STACK_DIR = RESULTS / "quadrotor_stack"
STACK_COMMAND = f"arcade eval quadrotor --condition stack --out {STACK_DIR.as_posix()}"
#: The product's controller and the baseline first, then the paper's method (tuned, then at
#: its own settings), the other methods, the flagship's ablations.
ORDER = (
    FLAGSHIP,
    "l1",
    "ours",
    PAPER_SETTINGS,
    *(m for m in METHODS if m not in ("l1", "ours")),
    *FLAGSHIP_ABLATIONS,
)
#: Methods whose paired difference to L1 the first table shows (the rest: the second).
HEADLINE = (FLAGSHIP, "ours", PAPER_SETTINGS, "nominal")


def horizontal(t: dict[str, Any]) -> float:
    """A trial's horizontal RMSE from its 3-D and z RMSE (the position error's squared norm
    is the sum of the horizontal and the vertical one); ``inf`` for a crashed trial."""
    r, z = t["rmse_m"], t["rmse_z_m"]
    if r is None or z is None or not (math.isfinite(r) and math.isfinite(z)):
        return math.inf
    return math.sqrt(max(r * r - z * z, 0.0))


def _with_horizontal(trials: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{**t, "rmse_xy_m": horizontal(t)} for t in trials]


def _cell_means(trials: list[dict[str, Any]], key: str) -> list[dict[str, Any]]:
    by: dict[tuple[float, float, str], list[float]] = {}
    for t in trials:
        by.setdefault((t["payload_g"], t["speed_mps"], t["method"]), []).append(t[key])
    return [
        {"payload_g": p, "speed_mps": v, "method": m, key: sum(x) / len(x)}
        for (p, v, m), x in by.items()
    ]


def paired_table(paired: list[dict[str, Any]], methods: tuple[str, ...]) -> list[str]:
    """Cells x methods: the paired difference to L1 in mm, mean [95 % interval], in bold
    where the interval lies below zero (better than L1)."""
    by = {(p["payload_g"], p["speed_mps"], p["method"]): p for p in paired}
    shown = [m for m in methods if any(k[2] == m for k in by)]
    if not shown:
        return ["(none flown)"]
    lines = [
        "| payload (g) | speed (m/s) | " + " | ".join(shown) + " |",
        "|---|---|" + "---|" * len(shown),
    ]
    for pay, speed in sorted({k[:2] for k in by}):
        row = []
        for m in shown:
            p = by.get((pay, speed, m))
            if p is None:
                row.append("-")
                continue
            lo, hi = p["ci95_m"]
            text = f"{1e3 * p['diff_mean_m']:+.1f} [{1e3 * lo:+.1f}, {1e3 * hi:+.1f}]"
            row.append(f"**{text}**" if p["better"] else text)
        lines.append(f"| {pay:g} | {speed:g} | " + " | ".join(row) + " |")
    return lines


def verdict(paired: list[dict[str, Any]], method: str) -> str:
    """``method`` against L1 over the cells: better / tie / worse by the 95 % interval."""
    rows = [p for p in paired if p["method"] == method]
    better = sum(p["better"] for p in rows)
    worse = sum(p["ci95_m"][0] > 0.0 for p in rows)
    return f"better in {better}, worse in {worse}, no difference in {len(rows) - better - worse}"


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
    trials = _with_horizontal(r.get("trials", []))
    paired = r.get("paired", [])
    paired_xy = paired_differences(trials, vs="l1", key="rmse_xy_m")
    paired_z = paired_differences(trials, vs="l1", key="rmse_z_m")
    n_cells = len({(c["payload_g"], c["speed_mps"]) for c in r["cells"]})
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
        f"Against L1 over the {n_cells} cell{'s' if n_cells != 1 else ''} (95 % bootstrap "
        "interval of the paired RMSE difference): "
        + "; ".join(
            f"`{m}` {verdict(paired, m)}" for m in HEADLINE if any(p["method"] == m for p in paired)
        )
        + ".",
        "",
        "Paired tracking-RMSE difference to L1 (mm, mean [95 % interval]; negative: better "
        "than L1, bold where the interval lies below zero):",
        "",
        *paired_table(paired, HEADLINE),
        "",
        "The same for the horizontal and the vertical RMSE:",
        "",
        *paired_table(
            [{**p, "method": f"{p['method']} xy"} for p in paired_xy]
            + [{**p, "method": f"{p['method']} z"} for p in paired_z],
            tuple(f"{m} {a}" for m in (FLAGSHIP, "ours") for a in ("xy", "z")),
        ),
        "",
        "Tracking RMSE (m; mean over the seeds, best in bold):",
        "",
        *cell_table(r["cells"], "rmse_m", ".3f", order=ORDER),
        "",
        "Horizontal RMSE (m):",
        "",
        *cell_table(_cell_means(trials, "rmse_xy_m"), "rmse_xy_m", ".3f", order=ORDER),
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
    if any(p["method"] in FLAGSHIP_ABLATIONS for p in paired):
        lines += [
            "The flagship's ablations against L1 (paired tracking-RMSE difference, mm):",
            "",
            *paired_table(paired, FLAGSHIP_ABLATIONS),
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
            + "; `arcade_thrust_smooth` is set by hand (not tuned: the tuning scores RMSE "
            "only); `ours_paper` keeps Appendix D's values.",
            "",
        ]
    return lines
