"""Vehicle files (TOML): the parameters the nominal model, simulator and bridge share."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any

DEFAULT_VEHICLE = Path(__file__).resolve().parent.parent / "deploy" / "vehicles" / "default.toml"

#: Entries every vehicle file must have: table -> key -> number of values (1: a scalar).
#: Each value must be a positive, finite number.
REQUIRED = {
    "body": {"mass_kg": 1, "inertia_kgm2": 3, "arm_length_m": 1, "size_m": 3},
    "rotors": {"max_thrust_n": 1, "motor_time_constant_s": 1, "yaw_moment_coeff_m": 1},
    "rate_loop": {"time_constant_s": 1, "max_rate_rad_s": 3},
}
#: Cable and electromagnet masses [kg] when the vehicle file gives none (the simulator's
#: defaults: it always carries the electromagnet, and the nominal model counts it).
DEFAULT_CABLE_MASS_KG = 0.002
DEFAULT_ELECTROMAGNET_MASS_KG = 0.02
#: Rigid bodies on the ``mocap`` topic: the vehicle's by default (a lab names it with
#: ``--mocap-body``) and the simulator's swinging payload.
VEHICLE_BODY, PAYLOAD_BODY = "vehicle", "payload"
#: The ``payload`` entry of the simulator's event data at the release (the cable goes).
PAYLOAD_RELEASED = "released"
#: Radius of the payload sphere [m] (the simulator's, and the one Foxglove draws).
PAYLOAD_RADIUS_M = 0.02
#: Cable length [m] when the vehicle file gives none.
DEFAULT_CABLE_LENGTH_M = 0.5


def cable_length_m(vehicle: dict[str, Any]) -> float:
    """The payload's cable [m], electromagnet to payload: ``[payload] cable_length_m`` of
    a vehicle file, else :data:`DEFAULT_CABLE_LENGTH_M`."""
    return float(vehicle.get("payload", {}).get("cable_length_m", DEFAULT_CABLE_LENGTH_M))


def read_toml(path: str | Path, what: str = "file") -> dict[str, Any]:
    """Parse a TOML file; errors name the file (``what`` says what kind of file it is)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {path}")
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not a valid TOML {what}: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read the {what}: {exc}") from None


def load_vehicle(path: str | Path | None = None) -> dict[str, Any]:
    """Read a vehicle file; ``None`` means the shipped default vehicle.

    Raises ``FileNotFoundError`` for a missing file and ``ValueError`` (naming the file)
    for invalid TOML or a missing, non-numeric or non-positive required entry.
    """
    path = Path(path) if path is not None else DEFAULT_VEHICLE
    data = read_toml(path, "vehicle file")
    for section, keys in REQUIRED.items():
        table = data.get(section)
        if not isinstance(table, dict):
            raise ValueError(f"{path}: missing [{section}] table")
        for key, n in keys.items():
            if not _positive_numbers(table.get(key), n):
                want = "a positive number" if n == 1 else f"{n} positive numbers"
                raise ValueError(f"{path}: [{section}] {key} must be {want}")
    return data


def _positive_numbers(value: Any, n: int) -> bool:
    values = [value] if n == 1 else value
    if not isinstance(values, list) or len(values) != n:
        return False
    return all(
        isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v > 0
        for v in values
    )


def max_payload_g(vehicle: dict[str, Any]) -> float:
    """Heaviest payload [g] the rotors can carry at full thrust (hover at 100 % throttle).

    The carried mass is the airframe, the electromagnet, the cable and the payload; a
    ``thrust_scale`` effect in the file's ``[effects]`` scales the thrust. A heavier
    payload cannot leave the floor.
    """
    body, rotors = vehicle["body"], vehicle["rotors"]
    pay = vehicle.get("payload", {})
    gravity = float(vehicle.get("nominal", {}).get("gravity_mps2", 9.81))
    scale = float(vehicle.get("effects", {}).get("thrust_scale", {}).get("scale", 1.0))
    lift_kg = 4.0 * float(rotors["max_thrust_n"]) * scale / gravity
    carried_kg = (
        float(body["mass_kg"])
        + float(pay.get("electromagnet_mass_kg", DEFAULT_ELECTROMAGNET_MASS_KG))
        + float(pay.get("cable_mass_kg", DEFAULT_CABLE_MASS_KG))
    )
    return max(0.0, 1000.0 * (lift_kg - carried_kg))


def quadrotor_params(vehicle: dict[str, Any]):
    """Nominal-model parameters from a vehicle file (the electromagnet counts as airframe)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from arcade_core.dynamics.params import QuadrotorParams

    body = vehicle["body"]
    magnet = vehicle.get("payload", {}).get("electromagnet_mass_kg", DEFAULT_ELECTROMAGNET_MASS_KG)
    # Cast on the host (the same rounding), not by a conversion compiled in every process.
    inertia = np.asarray(body["inertia_kgm2"], dtype=jnp.result_type(float))
    return QuadrotorParams(
        mass=float(body["mass_kg"]) + float(magnet),
        inertia=jax.device_put(inertia),
        gravity=float(vehicle.get("nominal", {}).get("gravity_mps2", 9.81)),
        rate_tau=float(vehicle["rate_loop"]["time_constant_s"]),
    )
