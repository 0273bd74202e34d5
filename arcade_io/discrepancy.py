"""The discrepancy workflow on files: a flight log, the vehicle file (quadrotor) or cartpole
model file that describes the current model, and the updated file with the identified
effects (design §6).

:func:`run_workflow` reads the model from a file (or a dict of one), runs
:func:`arcade_core.discrepancy.workflow.find_discrepancy` on a
:class:`~arcade_io.flightlog.FlightLog` in float64, and :func:`write_model_file` writes the
updated vehicle/model file: the original plus the identified effects in its ``[effects]``
table, loadable by :func:`arcade_io.vehicle.load_vehicle` (or :func:`load_cartpole_file`),
the simulator and the JAX model.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax.numpy as jnp

from arcade_core.discrepancy.cartpole import CartpoleModel
from arcade_core.discrepancy.prediction import DiscrepancyModel
from arcade_core.discrepancy.quadrotor import QuadModel
from arcade_core.discrepancy.settings import Settings, check_log
from arcade_core.discrepancy.tables import validate_tables
from arcade_core.discrepancy.workflow import Outcome, find_discrepancy
from arcade_core.dynamics.params import CARTPOLE_NOMINAL
from arcade_io import atomicfile, jaxsetup
from arcade_io.flightlog import FlightLog
from arcade_io.vehicle import DEFAULT_VEHICLE, load_vehicle, quadrotor_params, read_toml

# --------------------------------------------------------------------------- models


def quad_model_from_vehicle(vehicle: dict[str, Any]) -> QuadModel:
    """:class:`~arcade_core.discrepancy.quadrotor.QuadModel` of a vehicle file."""
    rotors, rl = vehicle["rotors"], vehicle["rate_loop"]
    if rotors.get("layout", "x") != "x":
        raise ValueError("only quad-x vehicles are supported")
    b = float(vehicle["body"]["arm_length_m"]) / math.sqrt(2.0)
    h = float(rotors.get("rotor_height_m", 0.015))
    tmax = float(rotors["max_thrust_n"])
    pos = jnp.array([[b, -b, h], [-b, b, h], [b, b, h], [-b, -b, h]])
    # Largest torque per axis (what normalised torque 1 means), as the mixer defines it.
    torque_max = jnp.array(
        [2.0 * b * tmax, 2.0 * b * tmax, 2.0 * float(rotors["yaw_moment_coeff_m"]) * tmax]
    )

    def vec(key: str, default: float):
        return jnp.asarray(rl.get(key, [default] * 3), dtype=float).reshape(3)

    return QuadModel(
        params=quadrotor_params(vehicle),
        motor_tau=float(rotors["motor_time_constant_s"]),
        rotors=pos,
        rate_p=vec("p", 0.0),
        rate_i=vec("i", 0.0),
        rate_d=vec("d", 0.0),
        rate_ff=vec("ff", 0.0),
        torque_max=torque_max,
        d_cutoff_rad_s=2.0 * math.pi * float(rl.get("d_cutoff_hz", 30.0)),
    )


def load_cartpole_file(path: str | Path | None) -> dict[str, Any]:
    """A cartpole model file (TOML ``[cartpole] M, m, L, g`` + ``[effects]``); ``None``:
    the Appendix D nominal model."""
    N = CARTPOLE_NOMINAL
    data: dict[str, Any] = {"cartpole": {"M": N.M, "m": N.m, "L": N.L, "g": N.g}}
    if path is not None:
        loaded = read_toml(path, "cartpole model file")
        if not isinstance(loaded.get("cartpole"), dict):
            raise ValueError(f"{path}: missing [cartpole] table (M, m, L)")
        data = {**loaded, "cartpole": {**data["cartpole"], **loaded["cartpole"]}}
        for k in ("M", "m", "L", "g"):
            v = data["cartpole"][k]
            if isinstance(v, bool) or not isinstance(v, int | float) or not 0 < v < math.inf:
                raise ValueError(f"{path}: [cartpole] {k} must be a positive number, got {v!r}")
    return data


def load_model_file(system: str, vehicle: str | Path | dict[str, Any] | None) -> dict[str, Any]:
    """The vehicle file (quadrotor) or cartpole model file ``vehicle`` as a dict (a dict is
    taken as it is; ``None``: the shipped vehicle, the nominal cartpole)."""
    if isinstance(vehicle, dict):
        return vehicle
    return load_vehicle(vehicle) if system == "quadrotor" else load_cartpole_file(vehicle)


def check_model_file(system: str, path: Path | None) -> None:
    """Read the vehicle/model file and check its effects (``ValueError``,
    ``FileNotFoundError``); cheap: no model is built."""
    veh = load_model_file(system, path)
    if system == "quadrotor" and veh["rotors"].get("layout", "x") != "x":
        raise ValueError(f"{path}: only quad-x vehicles are supported")
    try:
        validate_tables(system, dict(veh.get("effects", {})))
    except ValueError as exc:
        raise ValueError(f"{path or 'default model'}: {exc}") from None


def discrepancy_model(system: str, vehicle: dict[str, Any]) -> DiscrepancyModel:
    """The workflow's model of a vehicle/model file (as a dict), with its ``[effects]``."""
    tables = validate_tables(system, dict(vehicle.get("effects", {})))
    if system == "quadrotor":
        model = quad_model_from_vehicle(vehicle)
    else:
        c = vehicle["cartpole"]
        model = CartpoleModel(float(c["M"]), float(c["m"]), float(c["L"]), float(c.get("g", 9.81)))
    return DiscrepancyModel(system, model, tables)


# --------------------------------------------------------------------------- workflow


def check_settings(log: FlightLog, system: str, settings: Settings) -> None:
    """``ValueError`` if the workflow cannot run on ``log`` with ``settings`` (cheap: no
    model is built)."""
    if system != log.system:
        raise ValueError(f"log is a {log.system} log, not {system}")
    check_log(system, len(log), log.dt, settings)


def run_workflow(
    log: FlightLog,
    system: str,
    vehicle: str | Path | dict[str, Any] | None = None,
    settings: Settings | None = None,
    progress: Callable[[str], None] | None = None,
) -> Outcome:
    """The discrepancy workflow (:mod:`arcade_core.discrepancy.workflow`) on ``log`` against
    the model of the vehicle/model file ``vehicle`` (:func:`load_model_file`).

    Runs in float64 whatever the caller's JAX setting, as the command line does (the
    setting is restored after it), so that its numbers do not depend on the caller: in
    float32 they differ in the third or fourth digit, and the secants' scoring overflows.
    The result's ``model_file`` is ``None`` (:func:`write_model_file` writes one); the
    details hold the log's times ``t``.
    """
    settings = Settings() if settings is None else settings
    with jaxsetup.x64():
        check_settings(log, system, settings)
        model = discrepancy_model(system, load_model_file(system, vehicle))
        outcome = find_discrepancy(model, log.X, log.U, log.dt, settings, progress)
    outcome.result["model_file"] = None
    outcome.details["t"] = log.t
    return outcome


# --------------------------------------------------------------------------- model file


def write_model_file(
    out: Path,
    system: str,
    vehicle: str | Path | dict[str, Any] | None,
    effects: dict[str, dict[str, Any]],
) -> Path:
    """The updated vehicle/model file in the folder ``out``: the original ``vehicle`` (the
    shipped vehicle file for a quadrotor given as a dict) with ``effects`` (an
    :class:`~arcade_core.discrepancy.workflow.Outcome`'s ``model_effects``) as its
    ``[effects]``."""
    if system == "quadrotor":
        vehicle_path = None if isinstance(vehicle, dict) else vehicle
        src = Path(vehicle_path) if vehicle_path is not None else DEFAULT_VEHICLE
        base = _strip_effects(src.read_text()) if src.is_file() else ""
        path = out / "vehicle.toml"
        header = "# Vehicle file updated by `arcade discrepancy`: identified effects below.\n"
    else:
        c = load_model_file(system, vehicle)["cartpole"]
        base = "[cartpole]\n" + "".join(
            f"{k} = {_toml_value(float(c[k]))}\n" for k in ("M", "m", "L", "g") if k in c
        )
        path = out / "cartpole_model.toml"
        header = "# Cartpole model file updated by `arcade discrepancy`.\n"
    atomicfile.write_text(path, header + base + _effects_toml(effects))
    return path


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(float(v))
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} to TOML")


def _effects_toml(effects: dict[str, dict[str, Any]]) -> str:
    lines = []
    for name, params in effects.items():
        lines.append(f"\n[effects.{name}]")
        for k, v in params.items():
            lines.append(f"{k} = {_toml_value(v)}")
    return "\n".join(lines) + "\n"


def _strip_effects(text: str) -> str:
    """Remove ``[effects]`` / ``[effects.*]`` tables from TOML text (other tables kept)."""
    out, skip = [], False
    for line in text.splitlines():
        s = line.strip()
        if s.startswith("[") and not s.startswith("[["):
            skip = s == "[effects]" or s.startswith("[effects.")
        if not skip:
            out.append(line)
    return "\n".join(out).rstrip() + "\n"
