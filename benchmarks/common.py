"""Shared by the benchmarks: machine description, latency statistics, the results folder."""

from __future__ import annotations

import os
import platform
from pathlib import Path

import numpy as np

#: Where the benchmarks and evaluations write their results and figures (repository-relative).
RESULTS = Path("benchmarks") / "results"


def machine() -> str:
    """A one-line description of the machine the numbers were taken on."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    import jax

    return (
        f"{cpu}, {os.cpu_count()} logical CPUs, {platform.system()} {platform.release()}, "
        f"Python {platform.python_version()}, jax {jax.__version__} ({jax.default_backend()})"
    )


def percentiles(samples_s, scale: float) -> tuple[float, float]:
    """Median and 99th percentile of timing samples (seconds), multiplied by ``scale``."""
    a = np.asarray(samples_s, dtype=float) * scale
    return float(np.median(a)), float(np.percentile(a, 99))
