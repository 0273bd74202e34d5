"""Irregular logged signals onto one uniform time grid (the ULog import, :mod:`arcade_io.ulog`).

Pure functions of NumPy arrays (times in seconds, one row per sample), so that each step is
tested on its own:

- :func:`clean`: sort by time (stable), drop rows with a non-finite time or value, and keep
  the last of the rows that share a timestamp (a repeated stamp is a re-publication);
- :func:`coverage`: the time intervals a signal covers, split where two samples are more
  than ``max_gap`` apart; :func:`intersect` and :func:`longest` combine such interval lists;
  :func:`airborne_intervals` turns a landed flag into intervals, and :func:`usable_segment`
  picks the longest airborne piece that every signal covers;
- :func:`grid`: the uniform sample times of an interval;
- interpolation: :func:`linear` (positions, velocities, measured rates), :func:`hold`
  (zero-order hold: setpoints, each in effect until the next one) and
  :func:`quaternions` (normalised linear interpolation after making the samples continuous
  in sign, then continuous again).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from arcade_io.flightlog import continuous_quaternions

Interval = tuple[float, float]

#: The ULog import's defaults (here, so that the command line reads them without JAX).
DEFAULT_RATE_HZ = 100.0  # the output rate
DEFAULT_MAX_GAP_S = 0.25  # a longer silence of a signal splits the segment
DEFAULT_MIN_AIRBORNE_S = 30.0  # a shorter airborne segment is refused


class Cleaned(NamedTuple):
    """A signal after :func:`clean`, and how many rows each repair touched."""

    t: np.ndarray  # (n,) strictly increasing
    y: np.ndarray  # (n, k)
    out_of_order: int  # samples whose time was below the one before
    duplicates: int  # rows dropped because another row has the same time
    non_finite: int  # rows dropped for a NaN/inf time or value


def clean(t, y) -> Cleaned:
    """``t`` strictly increasing and ``y`` reordered alike (see the module docstring)."""
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    y = np.asarray(y, dtype=np.float64).reshape(len(t), -1)
    finite = np.isfinite(t) & np.isfinite(y).all(axis=1)
    t, y = t[finite], y[finite]
    out_of_order = int(np.sum(np.diff(t) < 0.0))
    order = np.argsort(t, kind="stable")
    t, y = t[order], y[order]
    # Of a run of equal stamps keep the last row (the stable sort kept their logged order).
    keep = np.ones(len(t), dtype=bool)
    keep[:-1] = t[1:] != t[:-1]
    return Cleaned(t[keep], y[keep], out_of_order, int(np.sum(~keep)), int(np.sum(~finite)))


def coverage(t, max_gap: float) -> list[Interval]:
    """The intervals between the first and last sample of ``t`` (increasing) without a gap
    longer than ``max_gap`` [s] between two samples (a gap splits an interval)."""
    t = np.asarray(t, dtype=np.float64)
    if len(t) < 2:
        return []
    cut = np.flatnonzero(np.diff(t) > max_gap)
    starts = np.concatenate([[t[0]], t[cut + 1]])
    stops = np.concatenate([t[cut], [t[-1]]])
    return [(float(a), float(b)) for a, b in zip(starts, stops) if b > a]


def intersect(a: list[Interval], b: list[Interval]) -> list[Interval]:
    """The intervals where both lists (each sorted and disjoint) cover the time."""
    out, i, j = [], 0, 0
    while i < len(a) and j < len(b):
        lo, hi = max(a[i][0], b[j][0]), min(a[i][1], b[j][1])
        if hi > lo:
            out.append((lo, hi))
        if a[i][1] < b[j][1]:
            i += 1
        else:
            j += 1
    return out


def longest(intervals: list[Interval]) -> Interval | None:
    """The longest interval (the first of equals); ``None`` for none."""
    return max(intervals, key=lambda iv: iv[1] - iv[0]) if intervals else None


def usable_segment(
    airborne: list[Interval], times: list[np.ndarray], max_gap: float
) -> tuple[Interval | None, Interval | None]:
    """The longest piece of the ``airborne`` intervals that every signal (its sample
    times, increasing) covers without a gap over ``max_gap``, and the airborne interval it
    lies in (``None, None``: no such piece)."""
    best, flight = None, None
    for iv in airborne:
        pieces = [iv]
        for t in times:
            pieces = intersect(pieces, coverage(t, max_gap))
        piece = longest(pieces)
        if piece is not None and (best is None or piece[1] - piece[0] > best[1] - best[0]):
            best, flight = piece, iv
    return best, flight


def airborne_intervals(t, landed, t_end: float) -> list[Interval]:
    """Where the landed flag (``t`` increasing, ``landed`` 0/1 held from each sample to the
    next) is 0: from a sample that says airborne to the next that says landed, or to
    ``t_end`` for a log that ends in the air."""
    t = np.asarray(t, dtype=np.float64)
    air = np.asarray(landed).reshape(-1) == 0
    out = []
    start = None
    for ti, a in zip(t, air):
        if a and start is None:
            start = float(ti)
        elif not a and start is not None:
            out.append((start, float(ti)))
            start = None
    if start is not None and t_end > start:
        out.append((start, float(t_end)))
    return out


def grid(interval: Interval, rate_hz: float) -> np.ndarray:
    """Times ``a + k / rate_hz`` for ``k = 0, 1, ...`` up to ``b`` (inclusive)."""
    a, b = interval
    n = int(np.floor((b - a) * rate_hz + 1e-9)) + 1
    return a + np.arange(n) / rate_hz


def linear(t, y, t_out) -> np.ndarray:
    """Linear interpolation of the columns of ``y`` (rows at ``t``, increasing) at ``t_out``
    (inside ``[t[0], t[-1]]``; outside it the end values are held)."""
    y = np.asarray(y, dtype=np.float64).reshape(len(t), -1)
    return np.column_stack([np.interp(t_out, t, y[:, k]) for k in range(y.shape[1])])


def hold(t, y, t_out) -> np.ndarray:
    """Zero-order hold: at each ``t_out`` the last row of ``y`` logged at or before it (the
    first row before ``t[0]``)."""
    y = np.asarray(y, dtype=np.float64).reshape(len(t), -1)
    idx = np.searchsorted(np.asarray(t), np.asarray(t_out), side="right") - 1
    return y[np.clip(idx, 0, len(y) - 1)]


def quaternions(t, q, t_out) -> np.ndarray:
    """Unit quaternions (``w`` first) at ``t_out``: the samples normalised and made
    continuous in sign (:func:`~arcade_io.flightlog.continuous_quaternions`), interpolated
    linearly per component, normalised again (nlerp: slerp's path, off its timing by less
    than 3e-5 rad between samples 10 degrees apart), continuous in sign."""
    q = np.asarray(q, dtype=np.float64).reshape(len(t), 4)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = continuous_quaternions(q / np.where(norm > 0.0, norm, 1.0))
    out = linear(t, q, t_out)
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    return continuous_quaternions(out)
