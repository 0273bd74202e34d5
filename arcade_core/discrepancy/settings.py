"""Settings of the discrepancy workflow and the split of a log they define (design §6).

The log is split in time into blocks of ``heldout_block_s``; a ``heldout`` fraction of them,
spread evenly over the flight, is only evaluated, never fitted (so that the held-out part
sees the same kinds of flight as the fitted part). Fitting uses one-step windows of
``step_s`` (whole log samples) that start in the fitted blocks after ``burn_in_s``
(quadrotor). NumPy only: the command line checks a log with it before any JAX is loaded.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Settings:
    """Workflow settings (:mod:`arcade_core.discrepancy.workflow`); times in seconds."""

    step_s: float = 0.05
    heldout: float = 0.3
    heldout_block_s: float = 2.0
    horizon_s: float = 1.0
    burn_in_s: float = 3.0
    block_s: float = 2.0
    confidence: float = 0.9
    min_explained: float = 0.02
    min_size: float = 0.02
    n_boot: int = 200
    seed: int = 0


#: Valid range of the held-out fraction (``--heldout``).
HELDOUT_RANGE = (0.05, 0.5)
#: Fewest one-step windows the fit needs.
MIN_FIT_WINDOWS = 50


def windows(start: int, stop: int, steps: int, stride: int) -> np.ndarray:
    """Start indices of the windows of ``steps`` samples in ``[start, stop)``, every
    ``stride`` samples."""
    return np.arange(start, max(stop - steps, start), stride, dtype=np.int64)


def split_blocks(n: int, block: int, fraction: float) -> list[tuple[int, int, bool]]:
    """``(start, stop, held_out)`` blocks of ``block`` samples; a ``fraction`` of them,
    spread evenly over the log (the last block of every ``1/fraction``), is held out."""
    out = []
    n_blocks = max(1, -(-n // block))
    for i in range(n_blocks):
        held = math.floor((i + 1) * fraction) > math.floor(i * fraction)
        out.append((i * block, min(n, (i + 1) * block), held))
    return out


def block_windows(blocks, held: bool, start: int, steps: int, stride: int) -> np.ndarray:
    """:func:`windows` in the held-out (``held``) or fitted blocks, from sample ``start``."""
    parts = [windows(max(a, start), b, steps, stride) for a, b, h in blocks if h == held]
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)


def step_samples(settings: Settings, dt: float) -> int:
    """Log samples per model step (``step_s`` rounded, at least one)."""
    return max(1, round(settings.step_s / dt))


def burn_in_samples(settings: Settings, system: str, dt: float) -> int:
    """Samples left out at the start of the log (the quadrotor's ``burn_in_s``)."""
    return round(settings.burn_in_s / dt) if system == "quadrotor" else 0


def log_blocks(settings: Settings, n: int, dt: float) -> list[tuple[int, int, bool]]:
    """:func:`split_blocks` of a log of ``n`` samples at period ``dt``."""
    return split_blocks(n, max(1, round(settings.heldout_block_s / dt)), settings.heldout)


def fit_windows(settings: Settings, system: str, n: int, dt: float) -> np.ndarray:
    """Start indices of the one-step windows the fit uses."""
    H = step_samples(settings, dt)
    burn = burn_in_samples(settings, system, dt)
    return block_windows(log_blocks(settings, n, dt), False, burn, H, H)


class LogTooShort(ValueError):
    """The log holds too few fitting windows for the workflow to tell anything."""


def check_log(system: str, n: int, dt: float, settings: Settings) -> None:
    """``ValueError`` if the workflow cannot run on a log of ``n`` samples at period ``dt``
    with ``settings`` (:class:`LogTooShort` when it has too few fitting windows; cheap: no
    model is built)."""
    lo, hi = HELDOUT_RANGE
    if not lo <= settings.heldout <= hi:
        raise ValueError(f"--heldout must be between {lo:g} and {hi:g}, got {settings.heldout:g}")
    H = step_samples(settings, dt)
    n_windows = len(fit_windows(settings, system, n, dt))
    if n_windows < MIN_FIT_WINDOWS:
        raise LogTooShort(
            f"log too short: {n_windows} fitting windows of {H * dt:.3g} s "
            f"(at least {MIN_FIT_WINDOWS} are needed; {n} samples at {1.0 / dt:.4g} Hz, "
            f"--step {settings.step_s:g})"
        )
