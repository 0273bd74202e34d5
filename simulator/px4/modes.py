"""PX4 flight modes as MAVLink carries them.

PX4 puts its mode in HEARTBEAT ``custom_mode`` as ``main_mode << 16 | sub_mode << 24``
(``px4_custom_mode.h``) and takes it back in ``MAV_CMD_DO_SET_MODE`` as param2 (main) and
param3 (sub) with ``MAV_MODE_FLAG_CUSTOM_MODE_ENABLED`` in param1.
"""

from __future__ import annotations

from enum import Enum

# Main modes.
MAIN_MANUAL, MAIN_ALTCTL, MAIN_POSCTL, MAIN_AUTO, MAIN_ACRO, MAIN_OFFBOARD = 1, 2, 3, 4, 5, 6
MAIN_STABILIZED = 7
# AUTO sub-modes.
AUTO_READY, AUTO_TAKEOFF, AUTO_LOITER, AUTO_MISSION, AUTO_RTL, AUTO_LAND = 1, 2, 3, 4, 5, 6


class FlightMode(Enum):
    """The modes this vehicle flies, with their ``(main, sub)`` PX4 encoding."""

    POSITION = (MAIN_POSCTL, 0)
    OFFBOARD = (MAIN_OFFBOARD, 0)
    HOLD = (MAIN_AUTO, AUTO_LOITER)
    TAKEOFF = (MAIN_AUTO, AUTO_TAKEOFF)
    LAND = (MAIN_AUTO, AUTO_LAND)

    @property
    def custom_mode(self) -> int:
        main, sub = self.value
        return (main << 16) | (sub << 24)

    @property
    def is_auto(self) -> bool:
        return self.value[0] == MAIN_AUTO

    @classmethod
    def from_px4(cls, main: int, sub: int = 0) -> FlightMode | None:
        """The mode of a DO_SET_MODE request, or ``None`` if this vehicle does not fly it."""
        for mode in cls:
            m, s = mode.value
            if m == main and (s == sub or (m != MAIN_AUTO and sub == 0)):
                return mode
        return None

    @classmethod
    def from_custom_mode(cls, custom_mode: int) -> FlightMode | None:
        return cls.from_px4((custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF)
