"""Effect tables checked against the effect library (design §6).

An effect table is what an effects file or a vehicle/model file's ``[effects]`` holds: a
canonical effect name and its parameters in library units, e.g. ``{"rotor_drag": {"d":
[0.4, 0.4, 0.05]}}``. :func:`validate_tables` rejects unknown names, unknown or missing
parameters, wrong shapes and values outside the plausible range with a ``ValueError`` that
names the offending entry (a typo never silently turns an effect off), and fills defaults.
NumPy only, no JAX.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from arcade_core.discrepancy.catalog import CARTPOLE_EFFECTS, QUADROTOR_EFFECTS, ParamSpec


def validate_tables(system: str, tables: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Check effect tables of ``system`` against the library; fill defaults.

    Returns plain tables: scalars as floats, vectors as lists of floats. Quadrotor tables
    follow the simulator's rules (``simulator.effects.validate_effects``: shapes, and wind
    only together with a drag term, through which it acts); cartpole parameters are
    scalars.
    """
    if system == "quadrotor":
        return _quadrotor_tables(tables)
    out: dict[str, dict[str, Any]] = {}
    for name, table in tables.items():
        if name not in CARTPOLE_EFFECTS:
            known = ", ".join(sorted(CARTPOLE_EFFECTS))
            raise ValueError(f"unknown cartpole effect {name!r}; known effects: {known}")
        specs = CARTPOLE_EFFECTS[name].params
        unknown = set(table) - set(specs)
        if unknown:
            raise ValueError(f"effect [{name}]: unknown parameter(s) {sorted(unknown)}")
        vals: dict[str, Any] = {}
        for pname, spec in specs.items():
            if pname not in table and spec.default is None:
                raise ValueError(f"effect [{name}]: missing required parameter {pname!r}")
            v = float(table.get(pname, spec.default))
            if not (np.isfinite(v) and spec.low <= v <= spec.high):
                raise ValueError(
                    f"effect [{name}] parameter {pname!r}: {v!r} outside the plausible range "
                    f"[{spec.low}, {spec.high}] {spec.unit}"
                )
            vals[pname] = v
        out[name] = vals
    return out


def _quadrotor_tables(tables: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for name, table in tables.items():
        if name not in QUADROTOR_EFFECTS:
            known = ", ".join(sorted(QUADROTOR_EFFECTS))
            raise ValueError(f"unknown effect {name!r}; known effects: {known}")
        if not isinstance(table, Mapping):
            raise ValueError(f"effect [{name}] must be a table of parameters, got {table!r}")
        specs = QUADROTOR_EFFECTS[name].params
        unknown = set(table) - set(specs)
        if unknown:
            raise ValueError(
                f"effect [{name}]: unknown parameter(s) {sorted(unknown)}; known: {sorted(specs)}"
            )
        values: dict[str, Any] = {}
        for pname, spec in specs.items():
            if pname in table:
                values[pname] = _check_value(name, pname, spec, table[pname])
            elif spec.default is None:
                raise ValueError(f"effect [{name}]: missing required parameter {pname!r}")
            else:
                values[pname] = _check_value(name, pname, spec, spec.default)
        out[name] = values
    if "wind" in out and not ({"rotor_drag", "quadratic_drag"} & set(out)):
        raise ValueError(
            "effect [wind] acts through the drag terms: add [rotor_drag] and/or "
            "[quadratic_drag] as well"
        )
    return out


def _check_value(name: str, pname: str, spec: ParamSpec, value: Any) -> float | list[float]:
    where = f"effect [{name}] parameter {pname!r}"
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: expected a number or list of numbers, got {value!r}") from exc
    if arr.shape != spec.shape:
        want = "a scalar" if spec.shape == () else f"a list of {spec.shape[0]} numbers"
        raise ValueError(f"{where}: expected {want}, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{where}: non-finite value {value!r}")
    if np.any(arr < spec.low) or np.any(arr > spec.high):
        raise ValueError(
            f"{where}: {value!r} outside the plausible range [{spec.low}, {spec.high}] {spec.unit}"
        )
    return float(arr) if spec.shape == () else arr.tolist()
