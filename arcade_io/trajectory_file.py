"""Trajectory files: the CSV a lab writes, and the fitted path every process of a stack loads.

**Trajectory CSV** (``arcade up --trajectory FILE``): a header row, then one row per
sample; world ENU, SI units, ``#`` lines are comments::

    t,px,py,pz[,vx,vy,vz[,ax,ay,az]][,yaw]

``t`` in seconds, increasing (the first row is the trajectory's start, whatever its
value); velocities and accelerations are optional (all three axes together, accelerations
only with velocities); ``yaw`` [rad, ENU: 0 along x, counter-clockwise] is optional and
starts at 0.

**Waypoint CSV**: a header row ``x,y,z`` (or ``t,x,y,z``), one waypoint per row; without
``t`` the times follow from the distances at the plan's mean speed.

How the samples become a smooth path is :mod:`arcade_control.trajectory`.

**Fitted path** (``<run>/trajectory.npz``): the piecewise polynomial that was checked, as
every process of the stack loads it (:func:`save_fitted`, :func:`load_fitted`), with the
SHA-256 of the file checked on load so that no process flies another path.
"""

from __future__ import annotations

import csv
import hashlib
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from arcade_io.atomicfile import write_bytes

TRAJECTORY_COLUMNS = ("t", "px", "py", "pz", "vx", "vy", "vz", "ax", "ay", "az", "yaw")
WAYPOINT_COLUMNS = ("t", "x", "y", "z")


@dataclass(frozen=True)
class Samples:
    """What a trajectory or waypoint file holds (``t`` None: waypoints without times)."""

    t: np.ndarray | None
    p: np.ndarray
    v: np.ndarray | None = None
    a: np.ndarray | None = None
    yaw: np.ndarray | None = None
    waypoints: bool = False


def _rows(path: Path) -> tuple[list[str], list[list[str]]]:
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: cannot read: {getattr(err, 'strerror', None) or err}") from None
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    table = list(csv.reader(io.StringIO("\n".join(lines))))
    if not table:
        raise ValueError(f"{path}: empty (want a header row, e.g. t,px,py,pz)")
    return [h.strip() for h in table[0]], table[1:]


def read_samples(path: str | Path) -> Samples:
    """A trajectory or waypoint CSV (module docstring); ``ValueError`` naming the file, and
    the row or column, for anything else."""
    path = Path(path)
    header, rows = _rows(path)
    waypoints = "x" in header
    allowed = WAYPOINT_COLUMNS if waypoints else TRAJECTORY_COLUMNS
    unknown = [h for h in header if h not in allowed]
    if unknown or len(set(header)) != len(header):
        what = f"unknown column {unknown[0]!r}" if unknown else "a repeated column"
        raise ValueError(
            f"{path}: {what} (a trajectory: t,px,py,pz[,vx,vy,vz[,ax,ay,az]][,yaw]; "
            "waypoints: [t,]x,y,z)"
        )
    need = ("x", "y", "z") if waypoints else ("t", "px", "py", "pz")
    missing = [h for h in need if h not in header]
    if missing:
        raise ValueError(f"{path}: missing column {', '.join(missing)}")
    for group in (("vx", "vy", "vz"), ("ax", "ay", "az")):
        given = [h for h in group if h in header]
        if given and len(given) != 3:
            raise ValueError(f"{path}: columns {','.join(group)} go together")
    if "ax" in header and "vx" not in header:
        raise ValueError(f"{path}: accelerations need velocities (vx,vy,vz)")
    data = np.empty((len(rows), len(header)))
    for i, row in enumerate(rows):
        if len(row) != len(header):
            raise ValueError(f"{path}: row {i + 2} has {len(row)} values, want {len(header)}")
        for j, cell in enumerate(row):
            try:
                data[i, j] = float(cell)
            except ValueError:
                data[i, j] = math.nan
            if not math.isfinite(data[i, j]):
                raise ValueError(f"{path}: row {i + 2}, column {header[j]}: not a number: {cell!r}")
    if len(rows) < 2:
        raise ValueError(f"{path}: at least two rows are needed")
    col = {h: data[:, j] for j, h in enumerate(header)}

    def block(*names: str) -> np.ndarray | None:
        return np.stack([col[n] for n in names], axis=1) if names[0] in col else None

    if waypoints:
        return Samples(col.get("t"), block("x", "y", "z"), waypoints=True)
    return Samples(
        col["t"],
        block("px", "py", "pz"),
        block("vx", "vy", "vz"),
        block("ax", "ay", "az"),
        col.get("yaw"),
    )


def save_fitted(
    path: str | Path,
    name: str,
    breaks: np.ndarray,
    coeffs: np.ndarray,
    yaw: tuple[np.ndarray, np.ndarray] | None = None,
) -> str:
    """Write a fitted path (:class:`arcade_core.trajectories.PiecewisePolynomial` arrays)
    and its heading's (``yaw``: breaks, coefficients) atomically; returns the file's
    SHA-256 (hex)."""
    buf = io.BytesIO()
    heading = {} if yaw is None else {"yaw_breaks": yaw[0], "yaw_coeffs": yaw[1]}
    np.savez(buf, name=np.array(name), breaks=breaks, coeffs=coeffs, **heading)
    data = buf.getvalue()
    write_bytes(Path(path), data)
    return hashlib.sha256(data).hexdigest()


def load_fitted(path: str | Path, sha256: str) -> tuple[str, np.ndarray, np.ndarray, Any]:
    """``(name, breaks, coeffs, yaw)`` of a file :func:`save_fitted` wrote (``yaw``: its
    breaks and coefficients, or None); ``ValueError`` if it cannot be read or its SHA-256
    is not ``sha256``."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise ValueError(f"{path}: cannot read the trajectory: {err.strerror or err}") from None
    digest = hashlib.sha256(data).hexdigest()
    if digest != sha256:
        raise ValueError(
            f"{path}: SHA-256 {digest[:12]}... is not the checked one {sha256[:12]}..."
        )
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        yaw = (z["yaw_breaks"], z["yaw_coeffs"]) if "yaw_breaks" in z else None
        return str(z["name"]), z["breaks"], z["coeffs"], yaw
