"""The failsafe position hold of the simulated vehicle (:mod:`services.sim_node`): engaging
it when setpoints stop or on the controller's failsafe, the answers that end it, and the
hold's own setpoint (the role of PX4's position controller)."""

from __future__ import annotations

import numpy as np

from arcade_control.hover import hold_setpoint
from services.messages import Event, Setpoint


class FailsafeHold:
    """The failsafe half of :class:`~services.sim_node.SimNode` (a base class of it).

    Works on the simulator service's state: ``sim``, ``stats``, ``event``, ``log``, the
    condition ``_cond``, the hold position ``_hold`` (None: not holding), the run of
    answered control instants ``_answered_run``, the controller's failsafe event received
    ``_controller_failsafe`` and the mission start ``_mission0``, all made by its set-up.
    """

    _hold_by_controller = False  # the position hold answers the controller's failsafe

    def _engage_failsafe(self, stamp: float, since: float, controller: str | None = None) -> None:
        """Hold position: no setpoint for ``since`` s, or the controller's failsafe (its
        reason: ``controller``)."""
        x = self.sim.state()
        self._hold = x[:3].copy()
        self._hold_by_controller = controller is not None
        self._answered_run = 0
        rec = {"t": self.sim.time - self._mission0, "since_last_setpoint_s": since}
        text, data = f"no setpoint for {since:.3f} s: holding position", {}
        if controller is not None:
            rec["controller_reason"] = controller
            text = f"controller failsafe: {controller}: holding position"
            data = {"reason": "controller_failsafe", "controller_reason": controller}
            self.stats["controller_failsafes"] += 1
        self.stats["failsafes"].append(rec)
        self.event(
            "failsafe",
            text,
            "error",
            stamp=stamp,
            mode="hold",
            since_last_setpoint_s=float(since),
            sim_time=float(rec["t"]),
            px=float(x[0]),
            py=float(x[1]),
            pz=float(x[2]),
            **data,
        )

    def _take_controller_failsafe(self) -> Event | None:
        """The controller's failsafe event received (realtime), if any."""
        with self._cond:
            e, self._controller_failsafe = self._controller_failsafe, None
            return e

    def _on_controller_failsafe(
        self, reason: str, stamp: float, since: float, flying: bool
    ) -> None:
        """Act on the controller's failsafe (its ``reason``) at the control instant or
        chunk ``stamp``."""
        if not flying:
            self.stats["controller_failsafes_ignored"] += 1
            self.log.warning("controller failsafe before the mission started: ignored")
        elif self._hold is None:
            self._engage_failsafe(stamp, since, controller=reason)
        elif not self._hold_by_controller:
            # Holding already (no setpoints for a while): that hold now also waits for
            # answers out of hover, or it would hand the vehicle to open-loop hover.
            self._hold_by_controller = True
            self._answered_run = 0
            self.stats["controller_failsafes"] += 1
            self.stats["failsafes"][-1]["controller_reason"] = reason
            self.log.warning("controller failsafe while holding: resume waits for tracking")

    def _resumes(self, sp: Setpoint | None) -> bool:
        """Whether the answer ``sp`` (None: none) counts towards ending the hold: a hold
        for the controller's failsafe ignores its (open-loop) hover answers."""
        return sp is not None and not (self._hold_by_controller and sp.mode == "hover")

    def _clear_failsafe(self, stamp: float) -> None:
        self._hold = None
        self._hold_by_controller = False
        self.stats["failsafes"][-1]["cleared_t"] = self.sim.time - self._mission0
        self.event(
            "failsafe_cleared",
            "setpoints resumed: failsafe cleared",
            stamp=stamp,
            sim_time=float(self.sim.time - self._mission0),
        )

    def _hold_u(self) -> np.ndarray:
        sim = self.sim
        return self.sim.set_setpoint(
            hold_setpoint(
                sim.state(),
                self._hold,
                sim.hover_thrust(),
                sim.carried_mass(),
                4.0 * sim.max_thrust,
            )
        )
