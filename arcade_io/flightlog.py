"""Flight logs (design §5): CSV, one row per control step, constant rate.

Quadrotor columns ``t, px, py, pz, vx, vy, vz, qw, qx, qy, qz, wx, wy, wz, u0, u1, u2, u3``
(world ENU, body FLU, SI; ``u = [collective thrust N, body-rate setpoints rad/s]``, the
setpoint in effect from ``t`` to the next row). Cartpole columns ``t, x, xdot, theta,
thetadot, u``. Extra columns are allowed and ignored; the order of columns is free.

:func:`read_log` checks what the workflow relies on and says precisely what is wrong:
missing columns, too few rows, non-numeric or non-finite values (with the first bad row),
time not strictly increasing or a rate that is not constant (1 % tolerance on every
step, as logs written with float timestamps jitter in the last digits). Quadrotor
quaternions are made continuous in sign (:func:`continuous_quaternions`).
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from arcade_io import atomicfile

STATE_COLUMNS = {
    "quadrotor": ("px", "py", "pz", "vx", "vy", "vz", "qw", "qx", "qy", "qz", "wx", "wy", "wz"),
    "cartpole": ("x", "xdot", "theta", "thetadot"),
}
INPUT_COLUMNS = {"quadrotor": ("u0", "u1", "u2", "u3"), "cartpole": ("u",)}
#: Relative tolerance on the sample period.
RATE_TOLERANCE = 0.01
MIN_ROWS = 20


class LogError(ValueError):
    """A flight log that the workflow cannot use (the message says why)."""


@dataclass(frozen=True)
class FlightLog:
    """A constant-rate log: times ``t (n,)``, states ``X (n, nx)``, inputs ``U (n, nu)``."""

    system: str
    t: np.ndarray
    X: np.ndarray
    U: np.ndarray

    @property
    def dt(self) -> float:
        """Sample period [s] (mean step)."""
        return float((self.t[-1] - self.t[0]) / (len(self.t) - 1))

    def __len__(self) -> int:
        return len(self.t)

    def slice(self, start: int, stop: int) -> FlightLog:
        """Rows ``start:stop``."""
        return FlightLog(self.system, self.t[start:stop], self.X[start:stop], self.U[start:stop])


def columns(system: str) -> tuple[str, ...]:
    """All required columns of ``system`` in the canonical order."""
    _check_system(system)
    return ("t", *STATE_COLUMNS[system], *INPUT_COLUMNS[system])


def _check_system(system: str) -> None:
    if system not in STATE_COLUMNS:
        raise ValueError(f"unknown system {system!r}; known: {', '.join(STATE_COLUMNS)}")


def write_log(path: str | Path, log: FlightLog) -> Path:
    """Write ``log`` as CSV with the canonical columns (full float precision)."""
    path = Path(path)
    data = np.column_stack([log.t, log.X, log.U])
    with atomicfile.atomic_open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns(log.system))
        for row in data:
            w.writerow([repr(float(v)) for v in row])
    return path


def read_log(source: str | Path | io.TextIOBase, system: str) -> FlightLog:
    """Read and validate a CSV flight log of ``system`` (see the module docstring)."""
    _check_system(system)
    name = str(source) if isinstance(source, str | Path) else "<stream>"
    if isinstance(source, str | Path):
        path = Path(source)
        if not path.is_file():
            raise FileNotFoundError(f"flight log not found: {path}")
        text = path.read_text()
    else:
        text = source.read()
    rows = list(csv.reader(io.StringIO(text)))
    rows = [r for r in rows if r and any(c.strip() for c in r)]
    if not rows:
        raise LogError(f"{name}: empty file")
    header = [h.strip() for h in rows[0]]
    need = columns(system)
    missing = [c for c in need if c not in header]
    if len(missing) == len(need):  # not a flight log at all: say what one looks like
        raise LogError(f"{name}: not a {system} flight log (columns {', '.join(need)})")
    if missing:
        raise LogError(f"{name}: missing column(s) {', '.join(missing)} for a {system} log")
    idx = [header.index(c) for c in need]
    body = rows[1:]
    if len(body) < MIN_ROWS:
        raise LogError(f"{name}: {len(body)} data rows; at least {MIN_ROWS} are needed")
    data = np.empty((len(body), len(need)))
    for i, r in enumerate(body):
        if len(r) < len(header):
            raise LogError(f"{name}: row {i + 2} has {len(r)} fields, the header has {len(header)}")
        for j, k in enumerate(idx):
            try:
                data[i, j] = float(r[k])
            except ValueError:
                raise LogError(
                    f"{name}: row {i + 2}, column {need[j]!r}: not a number: {r[k]!r}"
                ) from None
    bad = ~np.isfinite(data)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise LogError(
            f"{name}: non-finite value (NaN/inf) in column {need[j]!r} at row {i + 2} "
            f"({int(bad.any(axis=1).sum())} rows affected)"
        )
    return _validated(system, data, name)


def from_arrays(system: str, t, X, U) -> FlightLog:
    """A validated :class:`FlightLog` from arrays (same checks as :func:`read_log`)."""
    _check_system(system)
    t = np.asarray(t, dtype=float).reshape(-1)
    X = np.asarray(X, dtype=float)
    U = np.asarray(U, dtype=float).reshape(len(t), -1)
    nx, nu = len(STATE_COLUMNS[system]), len(INPUT_COLUMNS[system])
    if X.shape != (len(t), nx) or U.shape != (len(t), nu):
        raise LogError(f"{system} log needs X ({len(t)}, {nx}) and U ({len(t)}, {nu})")
    data = np.column_stack([t, X, U])
    if not np.isfinite(data).all():
        raise LogError("log contains non-finite values (NaN/inf)")
    return _validated(system, data, "<arrays>")


def _validated(system: str, data: np.ndarray, name: str) -> FlightLog:
    nx = len(STATE_COLUMNS[system])
    t = data[:, 0]
    steps = np.diff(t)
    if np.any(steps <= 0.0):
        i = int(np.argmax(steps <= 0.0))
        raise LogError(f"{name}: time does not increase at row {i + 3} (t = {t[i + 1]!r})")
    dt = (t[-1] - t[0]) / (len(t) - 1)
    dev = np.abs(steps - dt) / dt
    if np.any(dev > RATE_TOLERANCE):
        i = int(np.argmax(dev))
        raise LogError(
            f"{name}: the sample rate is not constant: step {steps[i]:.6g} s at row {i + 3} "
            f"vs mean {dt:.6g} s (resample the log to a constant rate first)"
        )
    X = data[:, 1 : 1 + nx].copy()
    U = data[:, 1 + nx :].copy()
    if system == "quadrotor":
        norm = np.linalg.norm(X[:, 6:10], axis=1)
        if np.any(norm < 0.5):
            i = int(np.argmax(norm < 0.5))
            raise LogError(f"{name}: quaternion at row {i + 2} is not a unit quaternion")
        # Renormalise logs written with few digits; exact unit quaternions stay untouched.
        off = np.abs(norm - 1.0) > 1e-12
        X[off, 6:10] /= norm[off, None]
        X[:, 6:10] = continuous_quaternions(X[:, 6:10])
    return FlightLog(system, t.copy(), X, U)


def continuous_quaternions(q: np.ndarray) -> np.ndarray:
    """``q`` (n, 4) with signs chosen so that neighbouring rows lie in one hemisphere and the
    first has a non-negative scalar part.

    ``q`` and ``-q`` are one attitude and trackers output either (many keep ``w >= 0`` and
    so flip when the attitude crosses it), but the models take ``q`` as a vector: a flip
    between two rows would read as a 360-degree rotation in one step.
    """
    q = np.asarray(q, dtype=float)
    if len(q) == 0:
        return q.copy()
    turns = np.concatenate([[q[0, 0] < 0.0], np.sum(q[1:] * q[:-1], axis=1) < 0.0])
    sign = np.where(np.cumsum(turns) % 2 == 1, -1.0, 1.0)
    return q * sign[:, None]
