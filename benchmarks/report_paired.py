"""Paired differences to L1 as BENCHMARKS.md shows them, for both closed-loop conditions.

Both quadrotor evaluations (`arcade eval quadrotor`, in the paper's condition and in the
stack's) fly every method on the same seeds; with L1 among them, each results file holds
every other method's paired RMSE difference to L1 per cell with a 95 % bootstrap interval
(``paired``). This module renders them: a verdict per method, the tracking difference, the
horizontal and vertical ones, the flagship's ablations.
"""

from __future__ import annotations

import math
from typing import Any

from arcade_control.knobs import FLAGSHIP, FLAGSHIP_ABLATIONS, METHODS, PAPER_SETTINGS
from benchmarks.quadrotor_protocol import paired_differences

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
#: Methods whose paired difference to L1 the first table shows.
HEADLINE = (FLAGSHIP, "ours", PAPER_SETTINGS, "nominal")


def horizontal(t: dict[str, Any]) -> float:
    """A trial's horizontal RMSE from its 3-D and z RMSE (the position error's squared norm
    is the sum of the horizontal and the vertical one); ``inf`` for a crashed trial."""
    r, z = t["rmse_m"], t["rmse_z_m"]
    if r is None or z is None or not (math.isfinite(r) and math.isfinite(z)):
        return math.inf
    return math.sqrt(max(r * r - z * z, 0.0))


def with_horizontal(trials: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The trials with their horizontal RMSE (``rmse_xy_m``)."""
    return [{**t, "rmse_xy_m": horizontal(t)} for t in trials]


def cell_means(trials: list[dict[str, Any]], key: str) -> list[dict[str, Any]]:
    """Per (payload, speed, method): the mean of ``key`` over the trials."""
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


def paired_lines(r: dict[str, Any]) -> list[str]:
    """The verdicts and tables of a results file's paired differences to L1 (none without
    them): tracking, then horizontal and vertical, then the flagship's ablations."""
    paired = r.get("paired") or []
    if not paired:
        return []
    trials = with_horizontal(r.get("trials", []))
    paired_xy = paired_differences(trials, vs="l1", key="rmse_xy_m")
    paired_z = paired_differences(trials, vs="l1", key="rmse_z_m")
    n_cells = len({(c["payload_g"], c["speed_mps"]) for c in r["cells"]})
    lines = [
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
    ]
    if any(p["method"] in FLAGSHIP_ABLATIONS for p in paired):
        lines += [
            "The flagship's ablations against L1 (paired tracking-RMSE difference, mm):",
            "",
            *paired_table(paired, FLAGSHIP_ABLATIONS),
            "",
        ]
    return lines
