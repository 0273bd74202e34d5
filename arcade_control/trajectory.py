"""Reference trajectories the stack flies besides the figure-eight, and their feasibility.

A :class:`Trajectory` is what the flight plan (:class:`arcade_control.scenario.Scenario`)
flies after its take-off and hover: a path of :mod:`arcade_core.trajectories` whose clock
starts at 0 at rest, its lap (the payload is released at a fraction of the first lap) and
number of laps, and the speed ramp of a periodic path. It comes from

- a built-in generator (:func:`builtin`): ``figure-eight`` (the shipped plan: no
  :class:`Trajectory` at all), ``circle``, ``lissajous`` and ``hover``, around the plan's
  centre at the plan's mean speed; a periodic one starts at rest through the same speed
  ramp as the figure-eight (:class:`arcade_control.scenario.RampedPath`);
- samples (:func:`fit_samples`): positions with optional velocities and accelerations at
  increasing times. Positions alone are interpolated by a quintic spline (scipy's
  ``make_interp_spline``, ``k = 5``) with zero velocity and acceleration at the first and
  the last sample, so the vehicle starts from its hover and ends at rest; given
  velocities (and accelerations) are matched exactly by piecewise quintic Hermite
  interpolation (scipy's ``BPoly.from_derivatives``), the accelerations that are not
  given taken from that quintic spline. A sampled trajectory must start at rest; a given
  yaw follows the same clamped quintic spline (:func:`fit_yaw`) and starts at 0;
- waypoints (:func:`fit_waypoints`): the same clamped quintic spline through the points,
  at the given times or, without times, at times spaced by distance at the mean speed.

:func:`first_violation` checks a sampled flat reference (take-off and hover included)
against the vehicle's limits (:class:`Limits`: speed, acceleration, tilt, the thrust the
rotors have for the vehicle and its payload, body rates, the geofence) and names the first
limit broken, when, and by how much. Nothing here reads files (``arcade_io.trajectory_file``
does).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from arcade_core.trajectories import Circle, Hover, Lissajous, Offset, PiecewisePolynomial

#: Built-in generators and the parameters each takes (``NAME:KEY=VALUE,...``).
BUILTINS: dict[str, tuple[str, ...]] = {
    "figure-eight": (),
    "circle": ("radius", "laps"),
    "lissajous": ("ax", "ay", "az", "nx", "ny", "nz", "laps"),
    "hover": ("seconds",),
}
#: Their defaults: circle radius [m]; Lissajous amplitudes [m] and integer frequencies
#: per axis; laps of the periodic ones; hover time [s].
DEFAULTS: dict[str, float] = {
    "radius": 1.5,
    "laps": 2.0,
    "ax": 1.5,
    "ay": 1.0,
    "az": 0.25,
    "nx": 1.0,
    "ny": 2.0,
    "nz": 2.0,
    "seconds": 10.0,
}
#: The speed ramp of a periodic built-in [s] (the figure-eight's).
RAMP_S = 2.0
#: Allowed mismatch of a sampled trajectory's start from rest (velocity m/s, accel m/s^2).
REST_TOL = 1e-6


@dataclass(frozen=True, eq=False)
class Trajectory:
    """What the plan flies after its take-off and hover (module docstring).

    Attributes:
        name: how the user named it (built-in spec or file name).
        path: a path of :mod:`arcade_core.trajectories`, clock 0 at its first point, at
            rest there (a periodic one wrapped in the speed ramp).
        lap_s: one lap [s] of the path's own clock (a sampled trajectory: its duration).
        laps: laps flown.
        ramp_s: the speed ramp of a periodic path [s] (0: none); the path's clock then
            runs ``ramp_s / 2`` behind the flight's.
        yaw: the heading [rad] over the path's clock (a one-axis
            :class:`PiecewisePolynomial`, 0 at its start); None: yaw 0 throughout.
    """

    name: str
    path: Any
    lap_s: float
    laps: float = 1.0
    ramp_s: float = 0.0
    yaw: Any = None

    def t_of_clock(self, s: float) -> float:
        """Time since the trajectory's start at which its own clock reads ``s``
        (``s >= ramp_s / 2``)."""
        return s + 0.5 * self.ramp_s

    @property
    def duration_s(self) -> float:
        return self.t_of_clock(self.laps * self.lap_s)

    def shifted(self, offset: Any) -> Trajectory:
        """The same trajectory moved by ``offset`` (3,) [m]."""
        return dataclasses.replace(self, path=Offset(self.path, tuple(map(float, offset))))

    def start(self) -> np.ndarray:
        """Its first point (world ENU) [m]."""
        return np.asarray(self.path.position(np.float64(0.0)), dtype=float)


# ----------------------------------------------------------------------- built-ins


def parse_builtin(spec: str) -> tuple[str, dict[str, float]] | None:
    """``NAME[:KEY=VALUE,...]`` -> (name, parameters with defaults), None if ``NAME`` is
    no built-in; ``ValueError`` (one line) for an unknown or bad parameter."""
    name, _, rest = spec.partition(":")
    if name not in BUILTINS:
        return None
    params = {k: DEFAULTS[k] for k in BUILTINS[name]}
    for item in filter(None, rest.split(",")):
        key, eq, value = item.partition("=")
        if key not in params or not eq:
            keys = ", ".join(BUILTINS[name]) or "none"
            raise ValueError(f"{name}: no parameter {item!r} (parameters: {keys})")
        try:
            params[key] = float(value)
        except ValueError:
            params[key] = math.nan
        if not (math.isfinite(params[key]) and params[key] >= 0):
            raise ValueError(f"{name}: {key} must be a number >= 0, not {value!r}")
    if name == "lissajous" and any(params[k] != round(params[k]) for k in ("nx", "ny", "nz")):
        raise ValueError("lissajous: the frequencies nx, ny, nz must be whole numbers")
    for key in ("radius", "laps", "seconds"):
        if key in params and params[key] <= 0:
            raise ValueError(f"{name}: {key} must be positive")
    return name, params


def builtin(spec: str, center: Any, speed: float) -> Trajectory | None:
    """The built-in ``spec`` (:func:`parse_builtin`) around ``center`` at mean ``speed``;
    None for ``figure-eight`` (the plan's own); ``ValueError`` if ``spec`` is none."""
    from arcade_control.scenario import RampedPath

    parsed = parse_builtin(spec)
    if parsed is None:
        raise ValueError(f"no built-in trajectory {spec!r} (built-ins: {', '.join(BUILTINS)})")
    name, k = parsed
    c = tuple(float(v) for v in center)
    if name == "figure-eight":
        return None
    if name == "hover":
        return Trajectory(spec, Hover(c), lap_s=k["seconds"])
    if name == "circle":
        # The circle's centre one radius behind, so that it starts at the plan's centre.
        circle = Circle((c[0] - k["radius"], c[1], c[2]), k["radius"], float(speed))
        lap = float(circle.period())
    else:
        amp = (k["ax"], k["ay"], k["az"])
        if not any(amp):
            raise ValueError("lissajous: at least one amplitude must be positive")
        circle = Lissajous(c, amp, (k["nx"], k["ny"], k["nz"]), float(speed))
        lap = float(circle.period())
    return Trajectory(spec, RampedPath(circle, RAMP_S), lap_s=lap, laps=k["laps"], ramp_s=RAMP_S)


# ----------------------------------------------------------------------- fitted paths


def _as_path(pp: Any) -> PiecewisePolynomial:
    """scipy ``PPoly`` (or a B-spline) -> :class:`PiecewisePolynomial`, clock from 0."""
    from scipy.interpolate import BPoly, BSpline, PPoly

    if isinstance(pp, BPoly):
        pp = PPoly.from_bernstein_basis(pp)
    if isinstance(pp, BSpline):  # PPoly.from_spline takes one axis at a time
        axes = [PPoly.from_spline(BSpline(pp.t, pp.c[:, j], pp.k)) for j in range(pp.c.shape[1])]
        x, c = axes[0].x, np.stack([a.c for a in axes], axis=-1)
    else:
        x, c = pp.x, pp.c
    # Drop the zero-length pieces of repeated end knots.
    keep = np.diff(x) > 0
    breaks = np.r_[x[:-1][keep], x[-1]]
    coeffs = np.asarray(c[:, keep], dtype=float)
    return PiecewisePolynomial(breaks - breaks[0], coeffs)


def _check_times(t: np.ndarray, what: str) -> None:
    if t.ndim != 1 or t.size < 2:
        raise ValueError(f"{what}: at least two points are needed")
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        i = int(np.argmax(~(np.diff(t) > 0))) + 1
        raise ValueError(f"{what}: times must increase (row {i + 1}: t = {t[i]:g} s)")


def clamped_spline(t: np.ndarray, p: np.ndarray) -> Any:
    """Quintic interpolating spline through ``p`` (n, d) at ``t`` with zero velocity and
    acceleration at both ends (scipy ``make_interp_spline``, ``k = 5``)."""
    from scipy.interpolate import make_interp_spline

    zero = np.zeros(p.shape[1])
    rest = [(1, zero), (2, zero)]
    if t.size == 2:  # two conditions per end and two points: the quintic itself
        from scipy.interpolate import BPoly

        return BPoly.from_derivatives(t, [[p[0], zero, zero], [p[1], zero, zero]])
    return make_interp_spline(t, p, k=5, bc_type=(rest, rest))


def fit_samples(
    t: Any, p: Any, v: Any = None, a: Any = None, what: str = "trajectory"
) -> PiecewisePolynomial:
    """A smooth path through sampled positions ``p`` (n, 3) at times ``t`` (n,), matching
    the velocities ``v`` and accelerations ``a`` (n, 3) where given (module docstring);
    ``ValueError`` naming ``what`` if the samples do not make one."""
    from scipy.interpolate import BPoly

    t = np.asarray(t, dtype=float)
    p = np.asarray(p, dtype=float)
    _check_times(t, what)
    if a is not None and v is None:
        raise ValueError(f"{what}: accelerations need velocities")
    spline = clamped_spline(t, p)
    if v is None:
        return _as_path(spline)
    v = np.asarray(v, dtype=float)
    a = np.asarray(spline(t, 2), dtype=float) if a is None else np.asarray(a, dtype=float)
    for name, d in (("velocity", v[0]), ("acceleration", a[0])):
        if np.linalg.norm(d) > REST_TOL:
            raise ValueError(
                f"{what}: {name} at the first sample is {np.linalg.norm(d):.3g}, not 0: a "
                "trajectory starts at rest (the vehicle hovers at its first point before it)"
            )
    return _as_path(BPoly.from_derivatives(t, np.stack([p, v, a], axis=1)))


def fit_yaw(t: Any, yaw: Any, what: str = "trajectory") -> PiecewisePolynomial:
    """The heading through ``yaw`` [rad] (n,) at ``t`` (unwrapped): the clamped quintic
    spline of :func:`clamped_spline`; it must start at 0 (the heading at take-off)."""
    t = np.asarray(t, dtype=float)
    yaw = np.unwrap(np.asarray(yaw, dtype=float))
    _check_times(t, what)
    if abs(yaw[0]) > REST_TOL:
        raise ValueError(
            f"{what}: yaw at the first sample is {yaw[0]:g} rad, not 0: the heading starts "
            "as the vehicle takes off"
        )
    return _as_path(clamped_spline(t, yaw[:, None]))


def waypoint_times(points: Any, speed: float) -> np.ndarray:
    """Times of ``points`` (n, 3) spaced by distance at the mean ``speed`` [m/s]."""
    points = np.asarray(points, dtype=float)
    d = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return np.r_[0.0, np.cumsum(d)] / speed


def fit_waypoints(
    points: Any, times: Any = None, speed: float = 1.0, what: str = "waypoints"
) -> PiecewisePolynomial:
    """The clamped quintic spline (:func:`clamped_spline`) through ``points`` (n, 3) at
    ``times``, or at :func:`waypoint_times` for the mean ``speed``."""
    points = np.asarray(points, dtype=float)
    t = waypoint_times(points, speed) if times is None else np.asarray(times, dtype=float)
    return fit_samples(t, points, what=what)


def sampled(
    name: str, path: PiecewisePolynomial, yaw: PiecewisePolynomial | None = None
) -> Trajectory:
    """A fitted path (and heading) as a :class:`Trajectory` (flown once, no ramp)."""
    b = np.asarray(path.breaks)
    return Trajectory(name, path, lap_s=float(b[-1] - b[0]), yaw=yaw)


# ----------------------------------------------------------------------- limits


@dataclass(frozen=True)
class Limits:
    """What a reference may ask of the vehicle (``[limits]`` of the vehicle file, its
    rotors' thrust and rate limits, the geofence box)."""

    max_speed_mps: float
    max_accel_mps2: float
    max_tilt_deg: float
    max_thrust_n: float  # the collective thrust a reference may use
    max_rate_rad_s: tuple[float, float, float]
    carried_mass_kg: float  # airframe, electromagnet, cable and payload
    fence_lo: tuple[float, float, float]
    fence_hi: tuple[float, float, float]


@dataclass(frozen=True)
class Violation:
    """The first limit a reference breaks."""

    limit: str
    t: float
    value: float
    bound: float
    unit: str

    def describe(self, t_start: float = 0.0) -> str:
        """One line: the limit, the value, when (flight time; ``t_start``: the
        trajectory's start, also said relative to it) and the bound."""
        when = f"t = {self.t:.2f} s"
        if self.t >= t_start > 0.0:
            when += f" ({self.t - t_start:.2f} s into the trajectory)"
        elif t_start > 0.0:
            when += " (in the take-off and hover)"
        if self.limit.startswith("geofence"):
            return f"{self.limit} at {when}, {self.value:.3g} m outside the box"
        return (
            f"{self.limit} {self.value:.3g}{self.unit} at {when} exceeds the vehicle's "
            f"limit {self.bound:.3g}{self.unit}"
        )


def first_violation(
    limits: Limits, t: Any, x_ref: Any, u_ref: Any, nominal_mass_kg: float, gravity: float
) -> Violation | None:
    """The earliest limit the flat reference ``x_ref`` (n, 13), ``u_ref`` (n, 4) of the
    nominal model (mass ``nominal_mass_kg``) at times ``t`` (n,) breaks, or None.

    Speed ``|v|``; acceleration ``|a|`` with ``a = T_nom z_b / m_nom - g e3``; tilt of the
    body z axis from the vertical; thrust ``|a + g e3|`` times the carried mass; each body
    rate setpoint against its axis's limit; the position against the geofence box.
    """
    from arcade_core import frames

    t = np.asarray(t, dtype=float)
    x = np.asarray(x_ref, dtype=float)
    u = np.asarray(u_ref, dtype=float)
    speed = np.linalg.norm(x[:, 3:6], axis=1)
    z_b = frames.to_rotation_matrix_np(x[:, 6:10])[:, :, 2]
    f = u[:, :1] / nominal_mass_kg * z_b  # a + g e3
    accel = np.linalg.norm(f - np.array([0.0, 0.0, gravity]), axis=1)
    tilt = np.degrees(np.arccos(np.clip(z_b[:, 2], -1.0, 1.0)))
    thrust = limits.carried_mass_kg * np.linalg.norm(f, axis=1)
    rate = np.abs(u[:, 1:4]) / np.asarray(limits.max_rate_rad_s)
    below = np.asarray(limits.fence_lo) - x[:, :3]
    above = x[:, :3] - np.asarray(limits.fence_hi)
    fence = np.maximum(below, above).max(axis=1)
    checks = [
        ("speed", speed, limits.max_speed_mps, " m/s"),
        ("acceleration", accel, limits.max_accel_mps2, " m/s^2"),
        ("tilt", tilt, limits.max_tilt_deg, " deg"),
        ("thrust (with the payload)", thrust, limits.max_thrust_n, " N"),
    ]
    found: list[Violation] = []
    for name, value, bound, unit in checks:
        bad = np.flatnonzero(value > bound)
        if bad.size:
            i = int(bad[0])
            found.append(Violation(name, float(t[i]), float(value[i]), float(bound), unit))
    bad = np.flatnonzero(rate.max(axis=1) > 1.0)
    if bad.size:
        i = int(bad[0])
        axis = int(np.argmax(rate[i]))
        found.append(
            Violation(
                f"{'xyz'[axis]} body rate",
                float(t[i]),
                float(abs(u[i, 1 + axis])),
                float(limits.max_rate_rad_s[axis]),
                " rad/s",
            )
        )
    bad = np.flatnonzero(fence > 0)
    if bad.size:
        i = int(bad[0])
        axis = int(np.argmax(np.maximum(below[i], above[i])))
        lo, hi = limits.fence_lo[axis], limits.fence_hi[axis]
        found.append(
            Violation(
                f"geofence: {'xyz'[axis]} = {x[i, axis]:.2f} m not in [{lo:g}, {hi:g}] m",
                float(t[i]),
                float(fence[i]),
                0.0,
                " m",
            )
        )
    return min(found, key=lambda v: v.t) if found else None
