"""The MuJoCo quadrotor impersonating a PX4 autopilot over MAVLink.

:class:`Px4Sim` runs the simulator on the wall clock behind a MAVLink UDP link, so that a
MAVSDK (or any ground-station) client flies it as it would fly a PX4 vehicle in offboard
attitude-rate mode. The pieces: :mod:`~simulator.px4.vehicle` (commander: arming, modes,
offboard loss failsafe), :mod:`~simulator.px4.position_control` (hold / take-off / land),
:mod:`~simulator.px4.mavlink_vehicle` (the MAVLink protocol side). Frame and thrust
conversions are the bridge's own (:mod:`arcade_core.frames`,
:mod:`arcade_core.px4_command`): the vehicle inverts exactly what an offboard client
computes. Its normalised thrust is linear in force, as a PX4 whose ``THR_MDL_FAC`` matches
its motors delivers it.
"""

from simulator.px4.mavlink_vehicle import MavlinkVehicle
from simulator.px4.modes import FlightMode
from simulator.px4.realtime import Px4Sim
from simulator.px4.vehicle import PARAM_DEFAULTS, Px4Vehicle

__all__ = ["PARAM_DEFAULTS", "FlightMode", "MavlinkVehicle", "Px4Sim", "Px4Vehicle"]
