"""Injectable physical effects: the model discrepancies the simulator can switch on.

An effects file is TOML with one table per effect, keyed by the canonical names in
:data:`EFFECTS`, e.g.::

    [rotor_drag]
    d = [0.4, 0.4, 0.05]

    [wind]
    velocity_mps = [2.0, 0.0, 0.0]

A vehicle file may carry the same tables under ``[effects]`` (``[effects.rotor_drag]``);
:func:`load_effects` accepts either layout. Unknown effect names, unknown parameters,
wrong shapes and values outside the plausible range are rejected with a ``ValueError``
that names the offending entry, so a typo never silently turns an effect off.

The parameter table :data:`EFFECTS` is plain data (unit, plausible range, default,
description) taken from the discrepancy library (``arcade_core.discrepancy.catalog``).
Physical forms, world ENU / body FLU, ``v_rel = v - wind`` the air-relative velocity of
the airframe:

``rotor_drag``
    Rotor (blade-flapping / induced) drag, the Faessler et al. form with coefficients
    proportional to the rotor speeds (as RotorPy models it, per rotor ``-k omega_i v``):
    ``F_body = -m * diag(d) * (n_sum / n_hover) @ R^T v_rel``, where ``m`` is the vehicle
    mass (airframe + electromagnet, what the nominal model uses), so ``d`` is the
    acceleration coefficient at the hover rotor speed [1/s], and ``n_sum / n_hover`` the
    sum of the rotor speeds relative to hover: ``mean_i sqrt(f_i / (m g / 4))`` over the
    motors' thrusts ``f_i`` (thrust grows with the square of the rotor speed). Both drag
    terms act at the centre of mass of the rigid vehicle (airframe, electromagnet, rigid
    payload): a pure force, no moment.
``quadratic_drag``
    Bluff-body drag per body axis: ``F_body,i = -c_i * |v_b,i| * v_b,i`` with
    ``v_b = R^T v_rel``; ``c_i = rho * C_d * A_i / 2`` [kg/m].
``ground_effect``
    Cheeseman-Bennett in-ground-effect thrust gain per rotor,
    ``T_IGE / T_OGE = 1 / (1 - (R / (4 h))^2)`` with ``h`` the rotor height above the
    floor, clamped to ``h >= R / 2`` (gain at most 4/3) where the formula stops holding.
``thrust_scale``
    Actual / nominal thrust coefficient: every rotor produces ``scale`` times the thrust
    the mixer asked for (max thrust and yaw reaction torque scale with it).
``motor_lag``
    Replaces the first-order motor (thrust) time constant of the vehicle file.
``rate_lag``
    Extra lag in front of the body-rate controller: the body-rate setpoints pass through a
    pure transport delay ``delay_s`` and then a first-order filter ``time_constant_s``
    (the collective thrust is not delayed).
``com_offset``
    Centre-of-mass offset of the airframe in the body frame. Thrust still acts at the
    rotors, so an offset produces a torque the rate loop's integrator has to cancel. The
    simulator's ground-truth position stays the airframe's geometric centre (the
    motion-capture rigid-body origin).
``wind``
    Constant wind velocity in the world frame. It acts only through the drag terms
    (``rotor_drag`` and/or ``quadratic_drag`` use ``v_rel = v - wind``) and the induced
    inflow; an effects set with wind but no drag term is rejected because the wind would
    do (almost) nothing. The payload feels no aerodynamic force.
``induced_inflow``
    The rotors' thrust changes with their inflow: every rotor makes
    ``1 - climb_loss * v_b,z - airspeed_loss * (v_b,x^2 + v_b,y^2)`` times its thrust,
    ``v_b = R^T v_rel`` (climbing through the air loses thrust; a negative
    ``airspeed_loss`` is translational lift).
``battery_sag``
    The battery voltage sags over the flight: every rotor makes ``1 - loss_per_min * t /
    60`` times its thrust, ``t`` the simulation time [s] since the reset.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from arcade_core.discrepancy.catalog import QUADROTOR_EFFECTS, ParamSpec
from arcade_core.discrepancy.tables import validate_tables

#: Canonical effect names -> parameter name -> :class:`ParamSpec`. Single-sourced from the
#: discrepancy library, so the simulator and the identification share units and ranges.
EFFECTS: dict[str, dict[str, ParamSpec]] = {
    name: dict(spec.params) for name, spec in QUADROTOR_EFFECTS.items()
}


@dataclass(frozen=True)
class Effects:
    """A validated set of active effects: name -> parameter name -> value.

    Scalars are floats, vectors are read-only float arrays of shape (3,). Missing
    optional parameters are filled with their defaults.
    """

    params: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

    def __contains__(self, name: object) -> bool:
        return name in self.params

    def __iter__(self):
        return iter(self.params)

    def get(self, name: str, param: str, default: Any = None) -> Any:
        """The value of ``param`` of effect ``name``, or ``default`` when it is not active."""
        if name not in self.params:
            return default
        return self.params[name][param]

    def to_dict(self) -> dict[str, dict[str, float | list[float]]]:
        """A TOML/JSON-ready copy (vectors as lists)."""
        out: dict[str, dict[str, float | list[float]]] = {}
        for name, ps in self.params.items():
            out[name] = {
                k: (v.tolist() if isinstance(v, np.ndarray) else float(v)) for k, v in ps.items()
            }
        return out

    def merged(self, other: Effects) -> Effects:
        """Effects of ``self`` with the effects named in ``other`` replaced by ``other``'s."""
        combined = {**self.params, **other.params}
        return validate_effects({k: dict(v) for k, v in combined.items()})


NO_EFFECTS = Effects()


def _frozen(value: float | list[float]) -> float | np.ndarray:
    """A checked parameter as the simulator holds it: a float, or a read-only array."""
    if isinstance(value, float):
        return value
    arr = np.asarray(value, dtype=float)
    arr.setflags(write=False)
    return arr


def validate_effects(tables: Mapping[str, Any]) -> Effects:
    """Check effect tables against the library (:func:`arcade_core.discrepancy.tables.
    validate_tables`) and fill defaults."""
    checked = validate_tables("quadrotor", tables)
    return Effects({n: {p: _frozen(v) for p, v in t.items()} for n, t in checked.items()})


def load_effects(source: str | Path | Mapping[str, Any] | Effects | None) -> Effects:
    """Effects from a TOML file, a mapping of tables, an :class:`Effects`, or ``None``.

    A file (or mapping) with an ``effects`` table, such as a vehicle file, uses that
    table; otherwise every top-level table is an effect.
    """
    if source is None:
        return NO_EFFECTS
    if isinstance(source, Effects):
        return source
    if isinstance(source, str | Path):
        path = Path(source)
        if not path.is_file():
            raise FileNotFoundError(f"effects file not found: {path}")
        with path.open("rb") as f:
            tables: Mapping[str, Any] = tomllib.load(f)
        if "effects" in tables:
            tables = tables["effects"]
        return validate_effects(tables)
    if "effects" in source and isinstance(source["effects"], Mapping):
        source = source["effects"]
    return validate_effects(source)


# --- force / gain terms used by the simulator (numpy, body FLU, world ENU) ---


def rotor_speed_ratio(thrusts, hover_thrust_per_rotor: float) -> float:
    """Sum of the rotor speeds relative to hover, ``mean_i sqrt(f_i / f_hover)`` (thrust
    grows with the square of the rotor speed)."""
    return sum(math.sqrt(max(f, 0.0) / hover_thrust_per_rotor) for f in thrusts) / len(thrusts)


def drag_force_body(
    effects: Effects, v_rel_body: np.ndarray, vehicle_mass: float, speed_ratio: float = 1.0
) -> np.ndarray:
    """Total drag force in the body frame [N] from ``rotor_drag`` (at ``speed_ratio``
    times the hover rotor speeds, :func:`rotor_speed_ratio`) and ``quadratic_drag``."""
    f = np.zeros(3)
    d = effects.get("rotor_drag", "d")
    if d is not None:
        f -= vehicle_mass * speed_ratio * d * v_rel_body
    c = effects.get("quadratic_drag", "c")
    if c is not None:
        f -= c * np.abs(v_rel_body) * v_rel_body
    return f


def inflow_gain(effects: Effects, v_rel_body: np.ndarray) -> float:
    """Thrust ratio of ``induced_inflow`` at the air-relative body velocity (1 without it)."""
    if "induced_inflow" not in effects:
        return 1.0
    k_c = effects.get("induced_inflow", "climb_loss")
    k_h = effects.get("induced_inflow", "airspeed_loss")
    vx, vy, vz = (float(x) for x in v_rel_body)
    return 1.0 - k_c * vz - k_h * (vx * vx + vy * vy)


def battery_gain(effects: Effects, t: float) -> float:
    """Thrust ratio of ``battery_sag`` at ``t`` [s] since the reset (1 without it)."""
    return 1.0 - effects.get("battery_sag", "loss_per_min", 0.0) * t / 60.0


def ground_effect_gain(height_m: np.ndarray, rotor_radius_m: float) -> np.ndarray:
    """Cheeseman-Bennett thrust ratio T_IGE / T_OGE for rotor heights above the floor."""
    h = np.maximum(np.asarray(height_m, dtype=float), 0.5 * rotor_radius_m)
    return 1.0 / (1.0 - (rotor_radius_m / (4.0 * h)) ** 2)
