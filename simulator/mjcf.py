"""MJCF model of the quadrotor, its electromagnet and an optional payload, from a vehicle file.

Bodies (world ENU, body FLU, SI):

- ``airframe``: free body with the vehicle file's mass and principal inertia; its frame
  origin is the geometric centre (the motion-capture rigid-body origin) and its centre of
  mass sits there unless a ``com_offset`` is given. A box collides with the floor.
- four rotor sites in the PX4 quad-x layout (1 front-right, 2 rear-left, 3 front-left,
  4 rear-right) at ``arm_length`` from the centre, ``rotor_height`` above it. Each carries a
  ``motor`` actuator whose control is the rotor's *actual* thrust [N]: the gear applies the
  force along body z and the yaw reaction torque ``yaw_moment_coeff * thrust`` about body z
  with the PX4 spin directions (rotors 1, 2 spin CCW seen from above, so their reaction
  torque on the airframe is clockwise, i.e. negative about FLU z; rotors 3, 4 the
  opposite). Motor lag, saturation and thrust effects are computed by the simulator before
  the control is written, so the actuators themselves are plain force sources.
- ``electromagnet``: a rigid child body under the airframe (20 g by default).
- swinging payload (``payload_mass > 0``): a free ``hook`` body (the lumped cable mass) held
  at the electromagnet by a ``connect`` equality named :data:`RELEASE_EQUALITY`, and a free
  ``payload`` sphere hanging from it by a length-limited spatial tendon (a light cable: it
  can go slack but not stretch beyond ``cable_length``). Releasing deactivates the equality
  through ``MjData.eq_active``; hook and payload then fall together.
- rigid payload (``rigid_payload=True``): the payload sphere is a child body of the
  electromagnet (the "rigidly attached payloads" of the paper's offline dataset); it cannot
  be released.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from arcade_io.vehicle import DEFAULT_ELECTROMAGNET_MASS_KG
from arcade_io.vehicle import PAYLOAD_RADIUS_M as PAYLOAD_RADIUS
from arcade_io.vehicle import cable_length_m as vehicle_cable_length

#: Name of the equality constraint that holds the cable at the electromagnet.
RELEASE_EQUALITY = "magnet_lock"
#: Rotor site names in PX4 quad-x order.
ROTOR_SITES = ("rotor1", "rotor2", "rotor3", "rotor4")

# Geometry that the vehicle file does not describe (metres).
MAGNET_RADIUS = 0.012
MAGNET_HALF_HEIGHT = 0.006
HOOK_RADIUS = 0.004
# Defaults for vehicle-file keys that older files may lack.
DEFAULT_ROTOR_HEIGHT = 0.015
DEFAULT_ROTOR_RADIUS = 0.0381
DEFAULT_CABLE_MASS = 0.002
# Model placement used for constraint set-up; `QuadrotorSim.reset` moves everything.
_BUILD_POSITION = (0.0, 0.0, 1.0)
# Constraint softness (MuJoCo solref time constant, s): stiff but >= 2 physics steps.
_CABLE_SOLREF = 0.004


class RotorGeometry(NamedTuple):
    """Rotor positions in the body frame [m], (4, 3), and yaw reaction signs, (4,)."""

    positions: np.ndarray
    yaw_signs: np.ndarray


def rotor_geometry(vehicle: dict[str, Any]) -> RotorGeometry:
    """PX4 quad-x rotor layout of a vehicle (only ``layout = "x"`` is supported)."""
    rotors = vehicle["rotors"]
    layout = rotors.get("layout", "x")
    if layout != "x":
        raise ValueError(f"rotor layout {layout!r} not supported (only quad 'x')")
    b = float(vehicle["body"]["arm_length_m"]) / math.sqrt(2.0)
    h = float(rotors.get("rotor_height_m", DEFAULT_ROTOR_HEIGHT))
    positions = np.array([[b, -b, h], [-b, b, h], [b, b, h], [-b, -b, h]])
    return RotorGeometry(positions, np.array([-1.0, -1.0, 1.0, 1.0]))


def magnet_offset(vehicle: dict[str, Any]) -> float:
    """Body-frame z of the electromagnet's centre (negative: below the airframe)."""
    return -(0.5 * float(vehicle["body"]["size_m"][2]) + MAGNET_HALF_HEIGHT)


def _vec(v) -> str:
    return " ".join(f"{float(x):.9g}" for x in v)


def build_mjcf(
    vehicle: dict[str, Any],
    *,
    payload_mass: float = 0.0,
    cable_length: float | None = None,
    rigid_payload: bool = False,
    com_offset: np.ndarray | None = None,
    timestep: float = 0.001,
) -> str:
    """MJCF XML for the vehicle (see the module docstring for the bodies it contains)."""
    body = vehicle["body"]
    rotors = vehicle["rotors"]
    pay = vehicle.get("payload", {})
    mass = float(body["mass_kg"])
    inertia = [float(x) for x in body["inertia_kgm2"]]
    size = [float(x) for x in body["size_m"]]
    gravity = float(vehicle.get("nominal", {}).get("gravity_mps2", 9.81))
    magnet_mass = float(pay.get("electromagnet_mass_kg", DEFAULT_ELECTROMAGNET_MASS_KG))
    cable_mass = float(pay.get("cable_mass_kg", DEFAULT_CABLE_MASS))
    if cable_length is None:
        cable_length = vehicle_cable_length(vehicle)
    if payload_mass < 0.0:
        raise ValueError(f"payload_mass must be >= 0, got {payload_mass}")
    if payload_mass > 0.0 and not rigid_payload and (cable_length <= 0.0 or cable_mass <= 0.0):
        raise ValueError("a swinging payload needs cable_length > 0 and cable_mass_kg > 0")
    if magnet_mass <= 0.0:
        raise ValueError("electromagnet_mass_kg must be > 0")
    com = np.zeros(3) if com_offset is None else np.asarray(com_offset, dtype=float)
    geo = rotor_geometry(vehicle)
    k_yaw = float(rotors["yaw_moment_coeff_m"])
    r_rotor = float(rotors.get("rotor_radius_m", DEFAULT_ROTOR_RADIUS))
    z_mag = magnet_offset(vehicle)

    rotor_xml = []
    for name, pos in zip(ROTOR_SITES, geo.positions):
        rotor_xml.append(f'<site name="{name}" pos="{_vec(pos)}" size="0.004"/>')
        rotor_xml.append(
            f'<geom class="visual" type="cylinder" pos="{_vec(pos)}" size="{r_rotor:.6g} 0.002"'
            ' rgba="0.6 0.6 0.6 0.3"/>'
        )
        rotor_xml.append(
            f'<geom class="visual" type="capsule" fromto="0 0 0 {_vec(pos)}" size="0.004"/>'
        )
    actuators = [
        f'<motor name="{name}" site="{name}" gear="0 0 1 0 0 {s * k_yaw:.9g}"/>'
        for name, s in zip(ROTOR_SITES, geo.yaw_signs)
    ]

    payload_child = ""
    free_bodies = ""
    tendon = ""
    equality = ""
    if payload_mass > 0.0 and rigid_payload:
        payload_child = (
            f'<body name="payload" pos="0 0 {-MAGNET_HALF_HEIGHT - PAYLOAD_RADIUS:.9g}">'
            f'<geom class="payload" type="sphere" size="{PAYLOAD_RADIUS}"'
            f' mass="{payload_mass:.9g}"/></body>'
        )
    elif payload_mass > 0.0:
        x0, y0, z0 = _BUILD_POSITION
        hook_z = z0 + z_mag - MAGNET_HALF_HEIGHT
        pay_z = hook_z - cable_length - PAYLOAD_RADIUS
        free_bodies = (
            f'<body name="hook" pos="{x0} {y0} {hook_z:.9g}"><freejoint name="hook_root"/>'
            f'<geom class="payload" type="sphere" size="{HOOK_RADIUS}" mass="{cable_mass:.9g}"/>'
            '<site name="hook_site" size="0.002"/></body>'
            f'<body name="payload" pos="{x0} {y0} {pay_z:.9g}"><freejoint name="payload_root"/>'
            f'<geom class="payload" type="sphere" size="{PAYLOAD_RADIUS}"'
            f' mass="{payload_mass:.9g}"/>'
            f'<site name="payload_site" pos="0 0 {PAYLOAD_RADIUS}" size="0.002"/></body>'
        )
        tendon = (
            f'<tendon><spatial name="cable" limited="true" range="0 {cable_length:.9g}"'
            f' solreflimit="{_CABLE_SOLREF} 1" width="0.001">'
            '<site site="hook_site"/><site site="payload_site"/></spatial></tendon>'
        )
        equality = (
            f'<equality><connect name="{RELEASE_EQUALITY}" site1="magnet_anchor"'
            f' site2="hook_site" solref="{_CABLE_SOLREF} 1"/></equality>'
        )

    return f"""<mujoco model="{vehicle.get("name", "quadrotor")}">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{timestep:.9g}" gravity="0 0 {-gravity:.9g}" integrator="implicitfast"/>
  <default>
    <geom contype="0" conaffinity="1" mass="0"/>
    <default class="visual"><geom contype="0" conaffinity="0" group="1"/></default>
    <default class="payload"><geom rgba="0.8 0.3 0.1 1"/></default>
  </default>
  <worldbody>
    <geom name="floor" type="plane" size="0 0 0.1" contype="1" conaffinity="0"/>
    <body name="airframe" pos="{_vec(_BUILD_POSITION)}">
      <freejoint name="airframe_root"/>
      <inertial pos="{_vec(com)}" mass="{mass:.9g}" diaginertia="{_vec(inertia)}"/>
      <geom name="frame" type="box" size="{_vec(0.5 * np.asarray(size))}" rgba="0.2 0.2 0.2 1"/>
      {"".join(rotor_xml)}
      <body name="electromagnet" pos="0 0 {z_mag:.9g}">
        <geom type="cylinder" size="{MAGNET_RADIUS} {MAGNET_HALF_HEIGHT}" mass="{magnet_mass:.9g}"
              rgba="0.5 0.5 0.7 1"/>
        <site name="magnet_anchor" pos="0 0 {-MAGNET_HALF_HEIGHT}" size="0.002"/>
        {payload_child}
      </body>
    </body>
    {free_bodies}
  </worldbody>
  {tendon}
  {equality}
  <actuator>{"".join(actuators)}</actuator>
</mujoco>
"""
