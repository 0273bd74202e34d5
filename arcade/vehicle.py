"""Vehicle files (TOML): the parameters the nominal model, simulator and bridge share."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

DEFAULT_VEHICLE = Path(__file__).resolve().parent.parent / "deploy" / "vehicles" / "default.toml"


def load_vehicle(path: str | Path | None = None) -> dict[str, Any]:
    """Read a vehicle file; ``None`` means the shipped default vehicle."""
    path = Path(path) if path is not None else DEFAULT_VEHICLE
    if not path.is_file():
        raise FileNotFoundError(f"vehicle file not found: {path}")
    with path.open("rb") as f:
        data = tomllib.load(f)
    for section in ("body", "rotors", "rate_loop"):
        if section not in data:
            raise ValueError(f"{path}: missing [{section}] table")
    return data


def quadrotor_params(vehicle: dict[str, Any]):
    """Nominal-model parameters from a vehicle file (the electromagnet counts as airframe)."""
    import jax.numpy as jnp

    from arcade_core.dynamics.params import QuadrotorParams

    body = vehicle["body"]
    magnet = vehicle.get("payload", {}).get("electromagnet_mass_kg", 0.0)
    return QuadrotorParams(
        mass=float(body["mass_kg"]) + float(magnet),
        inertia=jnp.asarray(body["inertia_kgm2"], dtype=float),
        gravity=float(vehicle.get("nominal", {}).get("gravity_mps2", 9.81)),
        rate_tau=float(vehicle["rate_loop"]["time_constant_s"]),
    )
