"""``--trajectory`` of ``arcade up`` and ``arcade demo``: resolve, check, hand to the stack.

:func:`resolve` turns the option into a :class:`arcade_control.trajectory.Trajectory` (a
built-in spec, or a trajectory or waypoint CSV fitted by :mod:`arcade_control.trajectory`);
:func:`check` samples the whole flight plan's flat reference (take-off and hover included)
every :data:`CHECK_DT` and names the first vehicle limit it breaks
(:func:`arcade_control.trajectory.first_violation`); :func:`stage` writes a fitted path
into the run folder (``trajectory.npz``) and returns what the services are given
(``--trajectory`` and ``--trajectory-sha256``: every process loads the same arrays).

The limits: the vehicle file's ``[limits]`` (speed, acceleration, tilt, the fraction of the
rotors' thrust a reference may use), its rate limits, the carried mass with the payload, and
the geofence box (the bridge's ``--geofence``; its default in the sim profile).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # loaded on first use: ``arcade --help`` does not load JAX
    from arcade_control.trajectory import Limits, Trajectory, Violation

#: Sampling period of the check [s] (a fifth of the control period).
CHECK_DT = 0.01
#: The ``[limits]`` entries of a vehicle file and their values when it has none.
LIMIT_DEFAULTS = {
    "max_speed_mps": 5.0,
    "max_accel_mps2": 10.0,
    "max_tilt_deg": 45.0,
    "thrust_fraction": 0.9,
}


def resolve(spec: str, speed: float) -> Trajectory | None:
    """The trajectory ``spec`` names: a built-in (``NAME[:KEY=VALUE,...]``) around the
    plan's centre at mean ``speed``, or a CSV file; None for the figure-eight.
    ``ValueError`` with one line naming what is wrong."""
    from arcade_control import trajectory as traj
    from arcade_control.scenario import Scenario
    from arcade_io.trajectory_file import read_samples

    if traj.parse_builtin(spec) is not None:
        return traj.builtin(spec, Scenario().center, speed)
    path = Path(spec)
    if not path.is_file():
        raise ValueError(f"{spec}: no such file and no built-in ({', '.join(traj.BUILTINS)})")
    s = read_samples(path)
    if s.waypoints:
        fitted = traj.fit_waypoints(s.p, s.t, speed, what=str(path))
    else:
        fitted = traj.fit_samples(s.t, s.p, s.v, s.a, what=str(path))
    yaw = None if s.yaw is None else traj.fit_yaw(s.t, s.yaw, what=str(path))
    return traj.sampled(path.name, fitted, yaw)


def vehicle_limits(vehicle: dict[str, Any], payload_g: float, geofence: Any) -> Limits:
    """The :class:`Limits` of a vehicle file carrying ``payload_g`` inside ``geofence``
    (:class:`arcade_core.px4_command.Geofence`)."""
    from arcade_control.trajectory import Limits
    from arcade_io.vehicle import DEFAULT_CABLE_MASS_KG, DEFAULT_ELECTROMAGNET_MASS_KG

    own = {**LIMIT_DEFAULTS, **vehicle.get("limits", {})}
    pay = vehicle.get("payload", {})
    mass = (
        float(vehicle["body"]["mass_kg"])
        + float(pay.get("electromagnet_mass_kg", DEFAULT_ELECTROMAGNET_MASS_KG))
        + float(pay.get("cable_mass_kg", DEFAULT_CABLE_MASS_KG))
        + payload_g / 1000.0
    )
    rotors = vehicle["rotors"]
    max_thrust = int(rotors.get("count", 4)) * float(rotors["max_thrust_n"])
    return Limits(
        max_speed_mps=float(own["max_speed_mps"]),
        max_accel_mps2=float(own["max_accel_mps2"]),
        max_tilt_deg=float(own["max_tilt_deg"]),
        max_thrust_n=float(own["thrust_fraction"]) * max_thrust,
        max_rate_rad_s=tuple(float(r) for r in vehicle["rate_loop"]["max_rate_rad_s"]),
        carried_mass_kg=mass,
        fence_lo=tuple(float(v) for v in geofence.lo),
        fence_hi=tuple(float(v) for v in geofence.hi),
    )


def check(scenario: Any, limits: Limits) -> Violation | None:
    """The first limit the flight plan's reference breaks (every :data:`CHECK_DT` from
    take-off to the end), or None."""
    import jax.numpy as jnp
    import numpy as np

    from arcade_control.nominal import nominal_params
    from arcade_control.scenario import flat_reference
    from arcade_control.trajectory import first_violation
    from arcade_io.traced import load_or_trace

    params = nominal_params()
    times = np.arange(0.0, scenario.t_end + CHECK_DT / 2, CHECK_DT)
    ref_args = (scenario.path(), jnp.asarray(times))
    # Traced once per plan and kept on disk (arcade_io.traced), as the services do.
    x, u = load_or_trace("reference", flat_reference, ref_args)(*ref_args)
    return first_violation(limits, times, x, u, float(params.mass), float(params.gravity))


#: ``--trajectory``'s help, the same in ``arcade up`` and ``arcade demo``.
HELP = (
    "fly this after the take-off and hover instead of the figure-eight: a CSV file "
    "(t,px,py,pz[,vx,vy,vz[,ax,ay,az]][,yaw], ENU, header row; a smooth quintic spline "
    "through it) or waypoints (header [t,]x,y,z), or a built-in: figure-eight, "
    "circle[:radius=R,laps=N], lissajous[:ax=,ay=,az=,nx=,ny=,nz=,laps=], "
    "hover[:seconds=S]; checked against the vehicle's limits (speed, acceleration, tilt, "
    "thrust, body rates, geofence) before anything starts (docs/trajectories.md)"
)


def option_problem(
    spec: str,
    *,
    speed: float,
    payload_g: float,
    vehicle_file: str | None = None,
    geofence: str | None = None,
) -> tuple[Trajectory | None, str | None]:
    """:func:`prepare` for the command line: the vehicle file (None: the shipped one) and
    the geofence (None: the bridge's default box) as given on it."""
    from arcade_core.px4_command import Geofence
    from arcade_io.vehicle import load_vehicle
    from services.px4_bridge_options import DEFAULT_GEOFENCE

    return prepare(
        spec,
        speed=speed,
        payload_g=payload_g,
        vehicle=load_vehicle(vehicle_file),
        geofence=Geofence.parse(geofence or DEFAULT_GEOFENCE),
    )


def prepare(
    spec: str,
    *,
    speed: float,
    payload_g: float,
    vehicle: dict[str, Any],
    geofence: Any,
    release: float = 0.95,
    origin: tuple[float, float] = (0.0, 0.0),
) -> tuple[Trajectory | None, str | None]:
    """``--trajectory spec`` resolved and checked against the vehicle: (the trajectory,
    None), or (None, why not: one line naming the file or the limit, the time and the
    value)."""
    from arcade_control.scenario import planned

    try:
        trajectory = resolve(spec, speed)
    except ValueError as err:
        return None, f"--trajectory {err}"
    scen = planned(payload_g, speed, release, origin=origin, trajectory=trajectory)
    print(
        f"checking trajectory {spec} ({scen.t_end:.1f} s of flight) against the vehicle's "
        "limits ...",
        file=sys.stderr,
        flush=True,
    )
    broken = check(scen, vehicle_limits(vehicle, payload_g, geofence))
    if broken is not None:
        return None, f"--trajectory {spec}: {broken.describe(scen.t_figure)}"
    return trajectory, None


def stage(out: Path, spec: str, trajectory: Trajectory | None) -> tuple[str | None, str | None]:
    """What the services get for ``spec``: a built-in's spec as it is, a fitted path
    written to ``out/trajectory.npz`` with its SHA-256; (None, None) for the figure-eight."""
    from arcade_core.trajectories import PiecewisePolynomial
    from arcade_io.trajectory_file import save_fitted

    if trajectory is None:
        return None, None
    if not isinstance(trajectory.path, PiecewisePolynomial):
        return spec, None
    path = Path(out) / "trajectory.npz"
    yaw = trajectory.yaw
    heading = None if yaw is None else (yaw.breaks, yaw.coeffs)
    sha = save_fitted(
        path, trajectory.name, trajectory.path.breaks, trajectory.path.coeffs, heading
    )
    return str(path), sha
