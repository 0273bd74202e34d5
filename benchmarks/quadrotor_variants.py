"""``arcade bench variants``: ours beside variants that are not the paper's method.

Flies L1, ours and every :data:`benchmarks.quadrotor_closedloop.VARIANTS` method on the
nine cells of the closed-loop evaluation (same scenario, seeds and metrics as
``arcade eval quadrotor``), each tuned on the tuning cell in the same run
(:func:`benchmarks.quadrotor_closedloop.tune`). Only the shipped VLD weights are needed,
no baseline is trained. ``ours_matched``
(:func:`benchmarks.quadrotor_closedloop.beam_method`) asks what the swinging payload's
unmatched pull costs ours: the regression gets an intercept feature and the MPC plans
with the part of the learned residual that the collective thrust can cancel, the
structural assumption of the L1 augmentation. ``docs/quadrotor-closed-loop.md`` reads the
results.
"""

from __future__ import annotations

import sys
import time
from types import SimpleNamespace
from typing import Any

import numpy as np

from benchmarks.common import machine

METHODS = ("l1", "ours")


def _progress(msg: str) -> None:
    print(f"[variants] {msg}", file=sys.stderr, flush=True)


def models() -> SimpleNamespace:
    """The shipped VLD and its guard: all that L1, ours and the variants need."""
    from arcade.training_quadrotor import QUADROTOR_WEIGHTS, load_quadrotor
    from arcade.weights import load_model
    from benchmarks import quadrotor_closedloop as qc

    vld = load_quadrotor()
    guard = qc.guard_from_metadata(load_model(QUADROTOR_WEIGHTS)[2])
    return SimpleNamespace(vld=vld, guard=guard, closedloop={})


def run(quick: bool = False, trials: int | None = None) -> dict[str, Any]:
    """``quick``: one trial of two cells with the stored knobs (no tuning flights)."""
    from benchmarks import quadrotor_closedloop as qc

    methods = (*METHODS, *qc.VARIANTS)
    cells = [(175.0, 0.5), (75.0, 2.5)] if quick else None
    t0 = time.perf_counter()
    r = qc.run_closedloop(
        trials=1 if quick else (trials or 10),
        methods=methods,
        cells=cells,
        models=models(),
        tuning=not quick,
        progress=_progress,
    )
    best: dict[tuple[float, float], str] = {}
    for c in r["cells"]:
        key = (c["payload_g"], c["speed_mps"])
        if key not in best or c["rmse_m"] < _rmse(r, key, best[key]):
            best[key] = c["method"]
    return {
        "generated": time.strftime("%Y-%m-%d %H:%M"),
        "machine": machine(),
        "methods": list(methods),
        "cells": r["cells"],
        "lowest_rmse": [
            {"payload_g": p, "speed_mps": s, "method": m} for (p, s), m in best.items()
        ],
        "tuned": r["settings"]["tuned"],
        "tuning": r["tuning"],
        "trials": r["settings"]["trials"],
        "wall_time_s": time.perf_counter() - t0,
    }


def _rmse(r: dict[str, Any], key: tuple[float, float], method: str) -> float:
    for c in r["cells"]:
        if (c["payload_g"], c["speed_mps"]) == key and c["method"] == method:
            return float(c["rmse_m"])
    return float(np.inf)


def table(result: dict[str, Any]) -> str:
    """RMSE / z-RMSE / settling per cell and method, as a markdown table."""
    methods = result["methods"]
    lines = [
        "| payload (g) | speed (m/s) | " + " | ".join(methods) + " |",
        "|---|---|" + "---|" * len(methods),
    ]
    by_cell: dict[tuple[float, float], dict[str, dict]] = {}
    for c in result["cells"]:
        by_cell.setdefault((c["payload_g"], c["speed_mps"]), {})[c["method"]] = c
    for (p, s), row in by_cell.items():
        vals = [
            f"{row[m]['rmse_m']:.4f} / {row[m]['rmse_z_m']:.4f} / {row[m]['settling_s']:.2f}"
            for m in methods
        ]
        lines.append(f"| {p:g} | {s:g} | " + " | ".join(vals) + " |")
    return "\n".join(lines)
