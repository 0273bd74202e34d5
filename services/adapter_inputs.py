"""The inputs the adapter (:mod:`services.adapter`) learns from: whether the vehicle flies
the controller's setpoints (the mission ``start`` command, the vehicle link's ``failsafe``
and ``failsafe_cleared`` events) and which setpoint was the input of a transition (the one
answering its first state; in realtime, when that one is missing, the newest one the
vehicle's zero-order hold applied). The module docstring of :mod:`services.adapter` says
when and why."""

from __future__ import annotations

from services.messages import Event, Setpoint, State

#: Realtime: the newest earlier setpoint stands in for a missing one up to this many
#: control periods before the transition's first state (one period, with jitter margin).
FALLBACK_PERIODS = 1.5


class AppliedInputs:
    """The input half of :class:`~services.adapter.Adapter` (a base class of it).

    Works on the adapter's state: ``args``, ``stats``, ``event``, ``bus``, ``stop``, the
    condition ``_cond``, the setpoints received ``_setpoints`` (stamp -> setpoint), the
    stamp of the first one ``_first_setpoint``, the newest mission's ``_mission_t0`` and
    whether the vehicle flies the setpoints ``_applied``, all made by its set-up.
    """

    #: Whether the controller has been seen (:meth:`_controller_gone`).
    _controller_seen = False

    def on_command(self, cmd) -> None:
        if cmd.name != "start":
            return
        t0 = cmd.args.get("t0", cmd.stamp)
        if t0 == self._mission_t0:
            return  # the mission clock re-sent to a (re)joining service: no new mission
        self._mission_t0 = t0
        # ``flying``: the link's answer to a service that (re)joins a running mission (this
        # adapter, restarted) -- whether the vehicle flies the setpoints right now.
        flying = cmd.args.get("flying", True)
        if flying is False:
            why = f"joined the mission under a failsafe ({cmd.src})"
            self._set_applied(False, why, announce=True)
        else:
            self._set_applied(True, f"mission started ({cmd.src})")

    def on_event(self, e: Event) -> None:
        if e.kind == "failsafe" and not e.src.startswith("controller/"):
            self._set_applied(False, f"{e.src}: {e.text}")
        elif e.kind == "failsafe_cleared":
            self._set_applied(True, f"{e.src}: {e.text}")

    def _set_applied(self, applied: bool, why: str, announce: bool = False) -> None:
        """Learn (or not) from the steps to come; announced when it changes (or
        ``announce``)."""
        if applied == self._applied and not announce:
            return
        self._applied = applied
        if applied:
            self.event("info", f"learning from the applied setpoints: {why}", learning=True)
        else:
            self.event(
                "info",
                f"vehicle not flying the setpoints, learning paused: {why}",
                learning=False,
            )

    def on_setpoint(self, sp: Setpoint) -> None:
        with self._cond:
            if self._first_setpoint is None:
                self._first_setpoint = sp.stamp
            self._setpoints[sp.stamp] = sp
            if len(self._setpoints) > 64:
                for s in sorted(self._setpoints)[:-32]:
                    del self._setpoints[s]
            self._cond.notify_all()

    def _controller_alive(self) -> bool:
        return self.bus is None or "controller" in self.bus.alive

    def _controller_gone(self) -> bool:
        """The controller's liveliness token was seen and is gone now. A controller not
        seen yet is not gone: its token can reach this process after the first states of a
        lockstep flight do (on a loaded host)."""
        alive = self._controller_alive()
        self._controller_seen = self._controller_seen or alive
        return self._controller_seen and not alive

    def _input_for(self, prev: State) -> Setpoint | None:
        with self._cond:
            if self.args.lockstep:
                # The simulator steps once the controller answered a state, so the answer
                # to ``prev`` is on its way unless the controller is gone (asked first: it
                # notes a controller seen alive).
                self._cond.wait_for(
                    lambda: (
                        self._controller_gone()
                        or prev.stamp in self._setpoints
                        or self.stop.is_set()
                    ),
                    self.args.step_timeout,
                )
                return self._setpoints.get(prev.stamp)
            sp = self._setpoints.get(prev.stamp)
            if sp is not None:
                return sp
            # The controller skipped that state (or the bus dropped its answer): the vehicle
            # held the newest setpoint sent before it, if that one is recent enough.
            held = [t for t in self._setpoints if t <= prev.stamp]
            if held and prev.stamp - max(held) <= FALLBACK_PERIODS / self.args.rate:
                self.stats["input_fallback"] += 1
                return self._setpoints[max(held)]
            if self._first_setpoint is None or prev.stamp < self._first_setpoint:
                # The controller was not answering yet (warming up, or joining): no loss.
                self.stats["before_first_setpoint"] += 1
            else:
                self.stats["input_missing"] += 1
            return None
