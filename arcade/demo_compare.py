"""`arcade demo --compare`: the stack's controllers flown one after the other on one seed.

Each method flies the demo's flight (:func:`arcade.demo_stack.run_demo`) through the whole
service stack into its own folder of the run folder; the ground truth of each gives the
same metrics, and one figure puts their x, y and z tracking errors side by side around
the release. Same seed, plan and vehicle: the flights differ only by the controller.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from arcade_control.knobs import STACK_METHODS
from arcade_io import atomicfile, jsonout

#: What ``--compare`` flies, baseline first: L1, the paper's method, the flagship.
COMPARED = ("l1", "ours", "arcade")
#: The window of the error figure around the release [s] (before, after).
WINDOW_S = (2.0, 6.0)
#: The metrics of the table: summary key, column title, format.
COLUMNS = (
    ("rmse_m", "RMSE (m)", "{:.4f}"),
    ("rmse_z_m", "z RMSE (m)", "{:.4f}"),
    ("shift_m", "shift (m)", "{:.3f}"),
    ("settling_s", "settling (s)", "{:.2f}"),
    ("thrust_increment_rms_n", "dT RMS (N)", "{:.3f}"),
    ("detection_delay_s", "cp delay (s)", "{:.2f}"),
)


def run_compare(
    out: Path,
    *,
    methods: Sequence[str] = COMPARED,
    progress: Callable[[str], None] | None = None,
    **demo: Any,
) -> dict[str, Any]:
    """Fly ``methods`` (each one of ``STACK_METHODS``) through the stack with the same
    ``demo`` arguments (:func:`arcade.demo_stack.run_demo`'s), each into ``out/<method>``;
    writes ``compare.png`` and ``compare.json`` in ``out`` and returns
    ``{"methods": {name: summary}, "settings": ...}``."""
    from arcade.demo_stack import read_truth, run_demo

    unknown = [m for m in methods if m not in STACK_METHODS]
    if unknown:
        raise ValueError(f"the stack flies {', '.join(STACK_METHODS)}, not {', '.join(unknown)}")
    summaries: dict[str, dict[str, Any]] = {}
    truths: dict[str, dict[str, np.ndarray]] = {}
    for i, method in enumerate(methods):
        if progress is not None:
            progress(f"[{i + 1}/{len(methods)}] flying {method}")
        summaries[method] = run_demo(out / method, method=method, **demo)
        truths[method] = read_truth(out / method / "truth.csv")
    first = summaries[methods[0]]
    settings = {k: v for k, v in first["settings"].items() if k != "method"}
    result = {"settings": settings, "methods": summaries}
    plot_errors(out / "compare.png", truths, first.get("t_release_s"))
    atomicfile.write_text(out / "compare.json", jsonout.dumps(result, indent=2))
    return result


def plot_errors(
    path: Path, truths: dict[str, dict[str, np.ndarray]], t_release: float | None
) -> None:
    """x, y and z tracking error of each flight (ground truth), one panel per axis, over
    :data:`WINDOW_S` around the release (the whole flight without one)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(9, 7.5), sharex=True)
    for name, truth in truths.items():
        t = truth["t"]
        sel = np.ones_like(t, bool)
        if t_release is not None:
            sel = (t >= t_release - WINDOW_S[0]) & (t <= t_release + WINDOW_S[1])
        for ax, axis in zip(axes, ("x", "y", "z"), strict=True):
            err = truth[f"p{axis}"] - truth[f"ref_p{axis}"]
            ax.plot(t[sel], err[sel], lw=1.2, label=name)
    for ax, axis in zip(axes, ("x", "y", "z"), strict=True):
        ax.set_ylabel(f"{axis} - {axis}_ref [m]")
        ax.axhline(0.0, color="k", lw=0.5)
        if t_release is not None:
            ax.axvline(t_release, color="r", lw=1, ls="--")
    axes[0].legend(fontsize=8, ncol=len(truths))
    axes[-1].set_xlabel("t [s] (red: payload released)" if t_release is not None else "t [s]")
    fig.suptitle("The stack's controllers on one seed: tracking error (ground truth)")
    fig.tight_layout()
    atomicfile.save_figure(fig, path, dpi=120)
    plt.close(fig)


def format_compare(result: dict[str, Any]) -> str:
    """The metrics table, one row per method ("-" where a metric does not apply)."""
    head = f"{'method':8s}" + "".join(f" {title:>13s}" for _, title, _ in COLUMNS)
    lines = [head]
    for name, s in result["methods"].items():
        cells = []
        for key, _, fmt in COLUMNS:
            v = s.get(key)
            cells.append("-" if v is None or not np.isfinite(v) else fmt.format(v))
        note = "  CRASHED" if s.get("crashed") else ""
        lines.append(f"{name:8s}" + "".join(f" {c:>13s}" for c in cells) + note)
    return "\n".join(lines)
