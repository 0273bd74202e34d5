"""PX4 flight logs (ULog, ``.ulg``) as the project's quadrotor :class:`FlightLog`.

:func:`read_ulog` reads a ULog (with ``pyulog``) into a constant-rate quadrotor log (the
columns of :mod:`arcade_io.flightlog`: world ENU, body FLU, SI) and a metadata dict that
says what it did. Topics, newest first (each quantity from the first that is logged):

- position and velocity: ``vehicle_local_position`` ``x, y, z, vx, vy, vz`` (NED; a
  ``*_valid`` flag that is false or a reset counter that changes in the segment is a
  warning);
- attitude: ``vehicle_attitude.q`` (``w`` first, body FRD to NED);
- body rates: ``vehicle_angular_velocity.xyz``, else ``vehicle_attitude``'s
  ``rollspeed, pitchspeed, yawspeed`` (old logs), else ``sensor_combined.gyro_rad`` (the
  raw gyro: a warning);
- collective thrust, normalised: ``-vehicle_thrust_setpoint.xyz[2]`` (FRD: negative is
  up), else ``actuator_controls_0.control[3]`` (old logs), else
  ``-vehicle_rates_setpoint.thrust_body[2]``;
- rate setpoints: ``vehicle_rates_setpoint`` ``roll, pitch, yaw`` (FRD). When they are not
  logged the measured rates stand in for them: the metadata's ``stand_ins`` and
  ``warnings`` say so;
- airborne: ``vehicle_land_detected.landed`` (held from sample to sample).

States are timed by ``timestamp_sample`` where the topic has one, setpoints by
``timestamp``. The log is the longest airborne stretch in which every signal is logged
without a gap over ``max_gap_s``, resampled at ``rate_hz`` (:mod:`arcade_io.resample`:
linear for positions, velocities and rates, nlerp for quaternions, zero-order hold for
setpoints), changed to ENU/FLU with :mod:`arcade_core.frames`. Thrust in newtons: linear
in the normalised thrust, ``m g s / s_hover`` (:func:`collective_thrust`,
:func:`hover_thrust`), since PX4's mixer applies ``THR_MDL_FAC`` at its outputs and the
setpoint it logs is linear in force (``THR_MDL_FAC`` is reported, not used); the mass
comes from the caller or a vehicle file (:func:`import_mass`). docs/discrepancy.md has
the details.

Every problem (unreadable, truncated or corrupted file, missing topic, too short an
airborne segment, no mass) raises :class:`ULogError` with a one-line message.
:func:`arcade_io.ulog_seed.vehicle_seed` collects what a ULog says about the vehicle.
"""

from __future__ import annotations

import contextlib
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from arcade_core.frames import frd_to_flu, ned_to_enu, quat_ned_frd_to_enu_flu
from arcade_io import resample
from arcade_io.flightlog import MIN_ROWS, FlightLog, LogError, continuous_quaternions, from_arrays
from arcade_io.resample import DEFAULT_MAX_GAP_S, DEFAULT_MIN_AIRBORNE_S, DEFAULT_RATE_HZ
from arcade_io.vehicle import DEFAULT_ELECTROMAGNET_MASS_KG, load_vehicle

#: The first bytes of every ULog file.
ULOG_MAGIC = b"ULog\x01\x12\x35"
DEFAULT_GRAVITY = 9.81
MASS_MISSING = (
    "the vehicle's mass is not in a ULog: give it with --mass KG or a vehicle file (--vehicle FILE)"
)


class ULogError(ValueError):
    """A ULog the import cannot use (the one-line message says why)."""


_DEFINITION_KINDS = frozenset(b"BFIMPQ")  # flag bits, format, info, info multiple, parameters
_DATA_KINDS = frozenset(b"ALC")  # subscription, log message, tagged log message

#: quantity -> sources, newest first: (topic, fields, sign, timed by timestamp_sample).
SOURCES: dict[str, list[tuple[str, tuple[str, ...], float, bool]]] = {
    "position": [("vehicle_local_position", ("x", "y", "z", "vx", "vy", "vz"), 1.0, True)],
    "attitude": [("vehicle_attitude", ("q[0]", "q[1]", "q[2]", "q[3]"), 1.0, True)],
    "rates": [
        ("vehicle_angular_velocity", ("xyz[0]", "xyz[1]", "xyz[2]"), 1.0, True),
        ("vehicle_attitude", ("rollspeed", "pitchspeed", "yawspeed"), 1.0, True),
        ("sensor_combined", ("gyro_rad[0]", "gyro_rad[1]", "gyro_rad[2]"), 1.0, False),
    ],
    "thrust": [
        ("vehicle_thrust_setpoint", ("xyz[2]",), -1.0, False),
        ("actuator_controls_0", ("control[3]",), 1.0, False),
        ("vehicle_rates_setpoint", ("thrust_body[2]",), -1.0, False),
    ],
    "rate_setpoints": [("vehicle_rates_setpoint", ("roll", "pitch", "yaw"), 1.0, False)],
    "landed": [("vehicle_land_detected", ("landed",), 1.0, False)],
}
_WHAT = {
    "position": "position",
    "attitude": "attitude",
    "rates": "body rates",
    "thrust": "thrust setpoint",
    "landed": "land detector",
}
TOPICS = sorted({s[0] for sources in SOURCES.values() for s in sources} | {"hover_thrust_estimate"})
#: Estimator flags that :func:`convert` warns about (validity flags, reset counters).
_FLAGS = {
    "vehicle_local_position": ("xy_valid", "z_valid", "v_xy_valid", "v_z_valid",
                               "xy_reset_counter", "z_reset_counter", "vxy_reset_counter",
                               "vz_reset_counter"),
    "vehicle_attitude": ("quat_reset_counter",),
}  # fmt: skip


class Signal(NamedTuple):
    """One quantity as logged: its source (``topic.field``), cleaned times [s since the
    log's start] and values."""

    source: str
    t: np.ndarray
    y: np.ndarray


@dataclass(frozen=True)
class ULogImport:
    """A converted ULog: the flight log and what the conversion did (JSON-friendly)."""

    log: FlightLog
    meta: dict[str, Any]


# --------------------------------------------------------------------------- reading


def looks_like_ulog(path: str | Path) -> bool:
    """Whether ``path`` is a file that starts with the ULog header."""
    try:
        with Path(path).open("rb") as f:
            return f.read(len(ULOG_MAGIC)) == ULOG_MAGIC
    except OSError:
        return False


def scan_messages(data: bytes) -> tuple[int | None, int | None]:
    """Walk a ULog's messages (after the 16-byte file header, each ``uint16 size, uint8
    type, payload``): ``(bad, cut)``, the offset of a message of unknown type in the
    definitions section (before the first ``A``, ``L`` or ``C`` message), and of an
    incomplete last message (a cut-off file); ``None`` for none. pyulog loops forever on
    some damaged definitions, so these are refused before it reads them."""
    pos, n, last = 16, len(data), 16
    definitions = True
    while pos + 3 <= n:
        kind = data[pos + 2]
        if definitions and kind in _DATA_KINDS:
            definitions = False
        elif definitions and kind not in _DEFINITION_KINDS:
            return pos, None
        last, pos = pos, pos + 3 + (data[pos] | (data[pos + 1] << 8))
    return None, (None if pos == n else (last if pos > n else pos))


def _check_path(path: str | Path) -> Path:
    path = Path(path)
    if not path.exists():
        raise ULogError(f"ULog file not found: {path}")
    if path.is_dir():
        raise ULogError(f"{path} is a directory, not a ULog file")
    if not looks_like_ulog(path):
        raise ULogError(f"{path}: not a ULog file (it does not start with the ULog header)")
    return path


def open_ulog(path: str | Path, allow_damaged: bool = False) -> tuple[Any, list[str]]:
    """The parsed ULog (a ``pyulog.ULog`` of :data:`TOPICS`) and warnings. A truncated or
    corrupted file is an error, or with ``allow_damaged`` a warning (pyulog keeps what it
    can read)."""
    path = _check_path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ULogError(f"{path}: cannot read it: {exc.strerror or exc}") from None
    bad, cut = scan_messages(data)
    if bad is not None:
        raise ULogError(f"{path}: corrupted ULog: unknown message type in its header at byte {bad}")
    from pyulog import ULog

    try:  # pyulog prints its warnings; they become ours
        with contextlib.redirect_stdout(io.StringIO()):
            ulog = ULog(io.BytesIO(data), TOPICS)
    except Exception as exc:  # pyulog raises many kinds on a damaged file
        raise ULogError(f"{path}: cannot read the ULog: {exc}") from None
    damage = []
    if ulog.file_corruption:  # (then the walk of the messages is no guide to a cut)
        damage.append("pyulog found corrupted data in it")
    elif cut is not None and not ulog.has_data_appended:
        damage.append(f"the file is truncated (its last message, at byte {cut}, is incomplete)")
    if damage and not allow_damaged:
        raise ULogError(f"{path}: {'; '.join(damage)} (--allow-damaged reads what is left)")
    return ulog, [f"damaged log: {d}" for d in damage]


def _topics(ulog) -> dict[str, dict[str, np.ndarray]]:
    """Topic name -> its fields (the lowest multi-instance of each)."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for d in sorted(ulog.data_list, key=lambda d: d.multi_id):
        out.setdefault(d.name, d.data)
    return out


def _seconds(stamps: np.ndarray, t0: int) -> np.ndarray:
    return (np.asarray(stamps).astype(np.int64) - np.int64(t0)) * 1e-6


def _label(topic: str, fields: tuple[str, ...]) -> str:
    """``topic.field``; ``topic.q`` for the fields ``q[0]..q[3]``; ``topic.a,b,c`` else."""
    stems = {f.split("[")[0] for f in fields}
    if len(fields) == 1 or (len(stems) == 1 and "[" in fields[0]):
        return f"{topic}.{fields[0] if len(fields) == 1 else stems.pop()}"
    return f"{topic}.{','.join(fields)}"


def find_signal(topics, quantity: str, t0: int) -> tuple[Signal, resample.Cleaned] | None:
    """The first logged source of ``quantity`` (:data:`SOURCES`), cleaned; ``None``: none."""
    for topic, fields, sign, by_sample in SOURCES[quantity]:
        data = topics.get(topic)
        if data is None or not all(f in data for f in fields) or len(data["timestamp"]) == 0:
            continue
        stamp = data.get("timestamp_sample") if by_sample else None
        stamp = stamp if stamp is not None and np.all(stamp > 0) else data["timestamp"]
        y = sign * np.column_stack([data[f] for f in fields]).astype(np.float64)
        if quantity == "attitude":
            y[np.abs(np.linalg.norm(y, axis=1) - 1.0) > 0.1] = np.nan
        c = resample.clean(_seconds(stamp, t0), y)
        if len(c.t) < (1 if quantity == "landed" else 2):
            continue
        return Signal(_label(topic, fields), c.t, c.y), c
    return None


# --------------------------------------------------------------------------- conversion


def collective_thrust(s, hover: float, mass_kg: float, gravity: float):
    """Collective thrust [N] of normalised thrust commands ``s`` (clipped to ``[0, 1]``):
    ``mass_kg * gravity * s / hover``, linear, so that the hover command ``hover`` gives
    ``mass_kg * gravity``.

    The setpoint PX4 logs is linear in force: its mixer inverts the ``THR_MDL_FAC`` motor
    model at the outputs, so the model does not enter here."""
    if not 0.0 < hover <= 1.0:
        raise ULogError(f"hover thrust {hover:g} is not in (0, 1]")
    return mass_kg * gravity / hover * np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)


def state_enu_flu(pos_vel_ned, q_ned_frd, rates_frd) -> np.ndarray:
    """The (n, 13) quadrotor state ``p, v`` (ENU), ``q`` (``w`` first, body FLU to ENU,
    continuous in sign), ``omega`` (FLU) of PX4's NED/FRD quantities."""
    pv = np.asarray(pos_vel_ned, dtype=np.float64)
    q = continuous_quaternions(quat_ned_frd_to_enu_flu(q_ned_frd))
    return np.column_stack(
        [ned_to_enu(pv[:, :3]), ned_to_enu(pv[:, 3:6]), q, frd_to_flu(rates_frd)]
    )


def hover_thrust(ulog, interval: tuple[float, float] | None = None) -> tuple[float, str]:
    """The hover thrust (normalised) and where it came from: the median of the valid
    ``hover_thrust_estimate`` samples in ``interval`` [s], else in the whole log, else the
    parameter ``MPC_THR_HOVER``."""
    hte = _topics(ulog).get("hover_thrust_estimate")
    if hte is not None and "hover_thrust" in hte:
        t = _seconds(hte["timestamp"], ulog.start_timestamp)
        h = np.asarray(hte["hover_thrust"], dtype=np.float64)
        ok = np.isfinite(h) & (h > 0.0) & (h <= 1.0)
        if "valid" in hte:
            ok &= np.asarray(hte["valid"]) != 0
        spans = [("segment", interval)] if interval is not None else []
        for where, (a, b) in [*spans, ("log", (-math.inf, math.inf))]:
            sel = ok & (t >= a) & (t <= b)
            if sel.any():
                return float(np.median(h[sel])), f"hover_thrust_estimate (median over the {where})"
    value = ulog.initial_parameters.get("MPC_THR_HOVER")
    if value is None:
        raise ULogError("no hover thrust: neither hover_thrust_estimate nor MPC_THR_HOVER")
    return float(value), "parameter MPC_THR_HOVER"


def import_mass(mass_kg: float | None, vehicle: str | Path | None) -> tuple[float, float, str]:
    """``(mass kg, gravity m/s^2, where from)``: ``mass_kg`` if given, else the vehicle
    file's model mass (airframe plus electromagnet); neither: :data:`MASS_MISSING`."""
    gravity, veh = DEFAULT_GRAVITY, None
    if vehicle is not None:
        try:
            veh = load_vehicle(vehicle)
        except (ValueError, FileNotFoundError) as exc:
            raise ULogError(str(exc)) from None
        gravity = float(veh.get("nominal", {}).get("gravity_mps2", DEFAULT_GRAVITY))
    if mass_kg is not None:
        if not (math.isfinite(mass_kg) and mass_kg > 0.0):
            raise ULogError(f"the mass must be a positive number of kg, got {mass_kg:g}")
        return float(mass_kg), gravity, "--mass"
    if veh is None:
        raise ULogError(MASS_MISSING)
    magnet = veh.get("payload", {}).get("electromagnet_mass_kg", DEFAULT_ELECTROMAGNET_MASS_KG)
    return float(veh["body"]["mass_kg"]) + float(magnet), gravity, f"vehicle file {vehicle}"


def read_ulog(
    path: str | Path,
    *,
    mass_kg: float | None = None,
    vehicle: str | Path | None = None,
    rate_hz: float = DEFAULT_RATE_HZ,
    min_airborne_s: float = DEFAULT_MIN_AIRBORNE_S,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    allow_damaged: bool = False,
) -> ULogImport:
    """The ULog at ``path`` as a quadrotor :class:`FlightLog` (see the module docstring);
    the mass from ``mass_kg`` or else the vehicle file ``vehicle`` (:func:`import_mass`)."""
    for name, v in (("rate", rate_hz), ("max gap", max_gap_s)):
        if not (math.isfinite(v) and v > 0.0):
            raise ULogError(f"the {name} must be a positive number, got {v:g}")
    if not (math.isfinite(min_airborne_s) and min_airborne_s >= 0.0):
        raise ULogError(f"the minimum airborne time must be >= 0 s, got {min_airborne_s:g}")
    _check_path(path)  # before the mass: the file is the first thing to get right
    mass, gravity, mass_source = import_mass(mass_kg, vehicle)
    ulog, warnings = open_ulog(path, allow_damaged)
    imp = convert(
        ulog,
        mass,
        gravity=gravity,
        rate_hz=rate_hz,
        min_airborne_s=min_airborne_s,
        max_gap_s=max_gap_s,
        name=str(path),
    )
    imp.meta["source"] = str(path)
    imp.meta["thrust_conversion"]["mass_source"] = mass_source
    imp.meta["warnings"][:0] = warnings
    return imp


def convert(
    ulog,
    mass_kg: float,
    *,
    gravity: float = DEFAULT_GRAVITY,
    rate_hz: float = DEFAULT_RATE_HZ,
    min_airborne_s: float = DEFAULT_MIN_AIRBORNE_S,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    name: str = "ULog",
) -> ULogImport:
    """:func:`read_ulog` on a parsed ``pyulog.ULog`` (``name`` names it in errors)."""
    t0 = int(ulog.start_timestamp)
    topics = _topics(ulog)
    warnings: list[str] = []
    stand_ins: list[str] = []
    found: dict[str, Signal] = {}
    for quantity in ("position", "attitude", "rates", "thrust", "rate_setpoints", "landed"):
        hit = find_signal(topics, quantity, t0)
        if hit is None:
            if quantity == "rate_setpoints":
                continue
            topics_ = " or ".join(s[0] for s in SOURCES[quantity])
            raise ULogError(f"{name}: no {_WHAT[quantity]} in the log ({topics_})")
        sig, c = hit
        found[quantity] = sig
        for n, what in (
            (c.out_of_order, "out-of-order samples sorted"),
            (c.duplicates, "samples with a repeated timestamp dropped"),
            (c.non_finite, "invalid or non-finite samples dropped"),
        ):
            if n:
                warnings.append(f"{sig.source}: {n} {what}")
    if found["rates"].source.startswith("sensor_combined"):
        warnings.append("body rates from sensor_combined (the raw gyro, bias not removed)")
    if "rate_setpoints" not in found:
        stand_ins.append(
            "rate setpoints: the measured body rates (vehicle_rates_setpoint "
            f"is not logged; {found['rates'].source})"
        )
        warnings.append(
            "no vehicle_rates_setpoint: the measured body rates stand in for "
            "the rate setpoints (u1-u3), so the rate loop's lag is not in the log"
        )
    mav_type = ulog.initial_parameters.get("MAV_TYPE")
    if mav_type is not None and int(mav_type) != 2:
        warnings.append(f"MAV_TYPE {int(mav_type)} is not a quadrotor (2): read as one")

    # Where to cut: the longest airborne stretch that every signal covers without a gap.
    landed = found.pop("landed")
    t_end = max(float(s.t[-1]) for s in found.values())
    airborne = resample.airborne_intervals(landed.t, landed.y[:, 0], t_end)
    if not airborne:
        raise ULogError(f"{name}: the vehicle is never airborne (vehicle_land_detected.landed)")
    segment, flight = resample.usable_segment(airborne, [s.t for s in found.values()], max_gap_s)
    if segment is None:
        raise ULogError(f"{name}: no airborne stretch in which every signal is logged")
    duration = segment[1] - segment[0]
    if duration < min_airborne_s:
        raise ULogError(
            f"{name}: the longest airborne stretch with every signal logged is {duration:.1f} s "
            f"({segment[0]:.1f}-{segment[1]:.1f} s into the log), less than the "
            f"{min_airborne_s:g} s asked for (--min-airborne-s)"
        )
    if duration < DEFAULT_MIN_AIRBORNE_S:
        warnings.append(
            f"{duration:.1f} s airborne: the discrepancy workflow needs "
            f"{DEFAULT_MIN_AIRBORNE_S:g} s to tell effects apart"
        )
    if len(airborne) > 1:
        warnings.append(f"{len(airborne)} airborne segments: kept the longest usable one")
    if (flight[1] - flight[0]) - duration > 2.0 / rate_hz:
        warnings.append(
            f"the airborne segment {flight[0]:.2f}-{flight[1]:.2f} s is cut to "
            f"{segment[0]:.2f}-{segment[1]:.2f} s: a gap over {max_gap_s:g} s or a signal "
            "that starts late or ends early"
        )

    # Resample and convert.
    t = resample.grid(segment, rate_hz)
    if len(t) < MIN_ROWS:
        raise ULogError(f"{name}: {len(t)} samples at {rate_hz:g} Hz; at least {MIN_ROWS}")
    pos = found["position"]
    att = found["attitude"]
    rates = found["rates"]
    thr = found["thrust"]
    pv = resample.linear(pos.t, pos.y, t)
    q = resample.quaternions(att.t, att.y, t)
    w = resample.linear(rates.t, rates.y, t)
    rsp = found.get("rate_setpoints")
    w_sp = w if rsp is None else resample.hold(rsp.t, rsp.y, t)
    X = state_enu_flu(pv, q, w)
    hover, hover_source = hover_thrust(ulog, segment)
    fac = float(ulog.initial_parameters.get("THR_MDL_FAC", 0.0))
    s = resample.hold(thr.t, thr.y, t)[:, 0]
    U = np.column_stack([collective_thrust(s, hover, mass_kg, gravity), frd_to_flu(w_sp)])
    try:
        log = from_arrays("quadrotor", t, X, U)
    except LogError as exc:
        raise ULogError(f"{name}: {exc}") from None

    for p, _v, _n in ulog.changed_parameters:
        if p == "MPC_THR_HOVER":
            warnings.append(f"parameter {p} changes during the log: its first value is used")
        elif p == "THR_MDL_FAC":
            warnings.append(
                f"parameter {p} changes during the log: its first value is reported "
                "(the thrust conversion does not use it)"
            )
    rates_hz = _quality(topics, found, segment, rate_hz, t0, warnings)
    meta = {
        "source": name,
        "px4": {k: ulog.msg_info_dict.get(k) for k in ("sys_name", "ver_hw", "ver_sw")},
        "rate_hz": float(rate_hz),
        "samples": len(log),
        "duration_s": float(log.t[-1] - log.t[0]),
        "segment_s": [float(segment[0]), float(segment[1])],
        "airborne_segments_s": [[float(a), float(b)] for a, b in airborne],
        "signals": {k: v.source for k, v in found.items()},
        "logged_rates_hz": rates_hz,
        "interpolation": {
            "position, velocity, body rates": "linear",
            "attitude": "normalised linear (nlerp), continuous in sign",
            "thrust and rate setpoints": "zero-order hold"
            if rsp is not None
            else "thrust: zero-order hold; rate setpoints (measured rates): linear",
        },
        "thrust_conversion": {
            "thrust_source": thr.source,
            "hover_thrust": hover,
            "hover_thrust_source": hover_source,
            "thr_mdl_fac": fac,
            "mass_kg": float(mass_kg),
            "gravity_mps2": float(gravity),
            "hover_force_n": float(mass_kg * gravity),
        },
        "stand_ins": stand_ins,
        "warnings": warnings,
    }
    return ULogImport(log, meta)


def _quality(topics, found, segment, rate_hz, t0, warnings: list[str]) -> dict[str, float]:
    """Warnings on the segment ``[a, b]`` [s]: signals logged below a quarter of the
    output rate, estimator validity flags that are false, estimator resets. Returns each
    signal's logged rate [Hz] in the segment."""
    a, b = segment
    rates_hz = {}
    for quantity, sig in found.items():
        hz = (int(np.sum((sig.t >= a) & (sig.t <= b))) - 1) / (b - a)
        rates_hz[sig.source] = round(hz, 1)
        if hz < rate_hz / 4.0:
            how = "held" if quantity in ("thrust", "rate_setpoints") else "interpolated"
            warnings.append(f"{sig.source} is logged at ~{hz:.0f} Hz: {how} between samples")
    for topic, fields in _FLAGS.items():
        data = topics.get(topic, {})
        if "timestamp" not in data:
            continue
        ts = _seconds(data["timestamp"], t0)
        inside = (ts >= a) & (ts <= b)
        for f in fields:
            if f not in data or not inside.any():
                continue
            v = np.asarray(data[f])[inside].astype(np.int64)
            if f.endswith("_valid") and np.any(v == 0):
                warnings.append(
                    f"{topic}.{f} is false in {np.mean(v == 0):.0%} of the segment: "
                    "those values are not estimates"
                )
            elif f.endswith("_counter") and np.any(np.diff(v) != 0):
                at = ts[inside][1:][np.diff(v) != 0]
                warnings.append(
                    f"{topic}.{f} changes at {', '.join(f'{x:.2f}' for x in at)} s: "
                    "an estimator reset (a jump in the state)"
                )
    return rates_hz
