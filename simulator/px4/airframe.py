"""The MuJoCo quadrotor with PX4's motor gating: motors stop when disarmed, and the rate
integrators are held at zero while the vehicle sits on the ground (as PX4's rate controller
does when landed), so that a vehicle waiting on the floor cannot wind up and tip over.
"""

from __future__ import annotations

from simulator.quadrotor import QuadrotorSim


class Px4Airframe(QuadrotorSim):
    """:class:`~simulator.QuadrotorSim` with a ``landed`` flag and a resting start on the floor."""

    @property
    def landed(self) -> bool:
        return self.hold_integrators

    @landed.setter
    def landed(self, value: bool) -> None:
        self.hold_integrators = bool(value)

    def rest_on_ground(self, xy=(0.0, 0.0), yaw: float = 0.0, settle_s: float = 1.0) -> float:
        """Place the vehicle on the floor at ``xy`` with motors off and let it settle.

        Returns the resting height of the airframe centre [m]. Time restarts at 0.
        """
        self.reset(position=(xy[0], xy[1], 0.3), yaw=yaw)
        self.stop_motors()
        self.step(settle_s)
        z = float(self.data.qpos[2])
        pose = self.data.qpos[0:3].copy()
        self.reset(position=pose, yaw=yaw)
        self.stop_motors()
        self.set_setpoint([0.0, 0.0, 0.0, 0.0])
        return z
