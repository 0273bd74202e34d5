"""What a PX4 ULog says about the vehicle: the start of a vehicle file (:mod:`arcade_io.vehicle`).

A ULog holds PX4's parameters, not the vehicle's physics. :func:`vehicle_seed` takes what
they give: the motors' thrust model (``THR_MDL_FAC``), the hover thrust, the rate limits
(``MC_*RATE_MAX``) and rate-loop gains (``MC_*RATE_K`` times ``_P``, ``_I``, ``_D``;
``_FF``), the rate-loop rate and derivative cut-off (``IMU_GYRO_RATEMAX``,
``IMU_DGYRO_CUTOFF``), the rotor count (``CA_ROTOR_COUNT``, else ``MAV_TYPE``), the arm
length and the yaw-moment coefficient from the rotor geometry (``CA_ROTORn_PX``, ``_PY``,
``_KM``), and with a mass given, each rotor's maximum thrust (``m g`` over the hover
thrust and the rotor count: PX4's normalised thrust is linear in force, its mixer applies
``THR_MDL_FAC``). It lists what the log does not hold (the mass, the inertia, ...):
:func:`seed_toml` writes both as a TOML file that :func:`arcade_io.vehicle.load_vehicle`
refuses until those are filled in.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from arcade_io.ulog import DEFAULT_GRAVITY, hover_thrust, open_ulog

#: MAVLink MAV_TYPE -> rotors, for the multicopter types.
MAV_TYPE_ROTORS = {2: 4, 13: 6, 14: 8, 15: 3}
#: What a ULog never holds: entry -> how to get it.
NOT_IN_A_ULOG = {
    "body.mass_kg": "weigh the vehicle with its battery (or pass --mass)",
    "body.inertia_kgm2": "a bifilar pendulum or the CAD model",
    "body.size_m": "measure the collision box",
    "rotors.motor_time_constant_s": "a step on a thrust stand",
    "rate_loop.time_constant_s": "fit a first-order lag to rate steps in a flight",
}
_AXES = ("ROLL", "PITCH", "YAW")


def vehicle_seed(
    ulog, mass_kg: float | None = None, *, gravity: float = DEFAULT_GRAVITY, hover=None
) -> dict[str, Any]:
    """``{"vehicle": tables, "missing": [...], "notes": [...]}`` for a vehicle file from a
    ULog (a path or a parsed ``pyulog.ULog``); ``hover``: the ``(hover thrust, source)``
    to use (default :func:`arcade_io.ulog.hover_thrust` over the log)."""
    if isinstance(ulog, str | Path):
        ulog = open_ulog(ulog, allow_damaged=True)[0]
    p = ulog.initial_parameters
    info = ulog.msg_info_dict
    missing = {k: v for k, v in NOT_IN_A_ULOG.items() if not (mass_kg and k == "body.mass_kg")}
    notes: list[str] = []
    body: dict[str, Any] = {}
    rotors: dict[str, Any] = {}
    rate: dict[str, Any] = {}

    fac = float(p.get("THR_MDL_FAC", 0.0))
    h, h_source = hover if hover is not None else hover_thrust(ulog)
    count = p.get("CA_ROTOR_COUNT") or MAV_TYPE_ROTORS.get(int(p.get("MAV_TYPE", -1)))
    if count:
        rotors["count"] = int(count)
        if int(count) == 4:
            rotors["layout"] = "x"
        else:
            notes.append(f"{int(count)} rotors: the model knows only the quad-x layout")
    else:
        missing["rotors.count"] = "no CA_ROTOR_COUNT, and MAV_TYPE is not a multicopter"
    if mass_kg:
        body["mass_kg"] = float(mass_kg)
        if count:
            rotors["max_thrust_n"] = mass_kg * gravity / float(h) / count
            notes.append(
                "max_thrust_n per rotor = m g / (hover thrust x rotors): PX4's normalised "
                "thrust is linear in force, as the ULog import scales it"
            )
    if "max_thrust_n" not in rotors:
        missing["rotors.max_thrust_n"] = "give the mass: m g / (hover thrust x rotors)"

    n = int(count or 0)
    xy = [(p.get(f"CA_ROTOR{i}_PX"), p.get(f"CA_ROTOR{i}_PY")) for i in range(n)]
    if n and all(x is not None and y is not None for x, y in xy):
        dist = [math.hypot(x, y) for x, y in xy]
        arm = sum(dist) / n
        body["arm_length_m"] = arm
        if max(dist) - min(dist) > 0.1 * arm:
            notes.append(
                f"rotors {min(dist):.3f}-{max(dist):.3f} m from the centre (not a "
                "symmetric X): arm_length_m is their mean"
            )
    else:
        missing["body.arm_length_m"] = "no CA_ROTORn_PX/PY: measure motor to centre"
    km = [p.get(f"CA_ROTOR{i}_KM") for i in range(n)]
    if n and all(k is not None for k in km):
        rotors["yaw_moment_coeff_m"] = sum(abs(k) for k in km) / n
    else:
        missing["rotors.yaw_moment_coeff_m"] = "no CA_ROTORn_KM: reaction torque / thrust"

    limits = [p.get(f"MC_{a}RATE_MAX") for a in _AXES]
    if all(v is not None for v in limits):
        rate["max_rate_rad_s"] = [math.radians(v) for v in limits]
    else:
        missing["rate_loop.max_rate_rad_s"] = "no MC_*RATE_MAX"
    gains = {k: [p.get(f"MC_{a}RATE_{k.upper()}") for a in _AXES] for k in ("p", "i", "d", "ff")}
    k_gain = [p.get(f"MC_{a}RATE_K", 1.0) for a in _AXES]
    if all(v is not None for g in gains.values() for v in g):
        for k, g in gains.items():
            rate[k] = [float(v) * (1.0 if k == "ff" else kk) for v, kk in zip(g, k_gain)]
        notes.append(
            "rate_loop p, i, d, ff are PX4's (MC_*RATE_K x P, I, D; FF): in PX4's "
            "normalised torque, which need not be this model's"
        )
    if "IMU_GYRO_RATEMAX" in p:
        rate["rate_hz"] = float(p["IMU_GYRO_RATEMAX"])
    if "IMU_DGYRO_CUTOFF" in p:
        rate["d_cutoff_hz"] = float(p["IMU_DGYRO_CUTOFF"])
    mav_type = p.get("MAV_TYPE")
    if mav_type is not None and int(mav_type) not in MAV_TYPE_ROTORS:
        notes.append(f"MAV_TYPE {int(mav_type)} is not a multicopter (a VTOL?)")

    vehicle = {
        "name": f"px4-{info.get('ver_hw', 'vehicle')}".lower(),
        "body": body,
        "rotors": rotors,
        "thrust_curve": {"thr_mdl_fac": fac},
        "rate_loop": rate,
        # A PX4 vehicle carries no ARCADE electromagnet: without this the model adds 0.02 kg.
        "payload": {"electromagnet_mass_kg": 0.0},
        "nominal": {"gravity_mps2": float(gravity)},
        "px4": {
            "hover_thrust": float(h),
            "hover_thrust_source": h_source,
            **{k.lower(): p[k] for k in ("MPC_THR_HOVER", "MAV_TYPE", "SYS_AUTOSTART") if k in p},
            **{k: str(info[k]) for k in ("ver_hw", "ver_sw") if k in info},
        },
    }
    return {
        "vehicle": vehicle,
        "missing": [f"[{k.split('.')[0]}] {k.split('.')[1]}: {v}" for k, v in missing.items()],
        "notes": notes,
    }


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    return json.dumps(str(v))


def seed_toml(seed: dict[str, Any], source: str = "a PX4 log") -> str:
    """A vehicle file (TOML) of :func:`vehicle_seed`'s result, what is missing on top."""
    lines = [f"# Vehicle file seeded from {source} (`arcade log convert --vehicle-out`)."]
    if seed["missing"]:
        lines.append("# NOT IN THE LOG: add these before use (arcade refuses the file till then):")
        lines += [f"#   {m}" for m in seed["missing"]]
    if seed["notes"]:
        lines.append("# Notes:")
        lines += [f"#   {m}" for m in seed["notes"]]
    lines.append("# [px4] is for reference only: nothing reads it.")
    tables = {k: v for k, v in seed["vehicle"].items() if isinstance(v, dict)}
    lines += [f"{k} = {_value(v)}" for k, v in seed["vehicle"].items() if k not in tables]
    for name, table in tables.items():
        lines += ["", f"[{name}]", *(f"{k} = {_value(v)}" for k, v in table.items())]
    return "\n".join(lines) + "\n"
