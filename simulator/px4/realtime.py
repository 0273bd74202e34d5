"""The simulated PX4 vehicle on the wall clock: physics in small chunks paced to
``time.monotonic()``, telemetry after each chunk, MAVLink input applied from the next
chunk on (zero-order hold, like a flight controller sampling its inputs)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from simulator.px4.airframe import Px4Airframe
from simulator.px4.mavlink_vehicle import MavlinkVehicle
from simulator.px4.vehicle import Px4Vehicle

#: Falling behind the wall clock by more than this counts as an overrun [s].
OVERRUN_S = 0.5


class Px4Sim:
    """A MuJoCo quadrotor that any MAVLink client can fly as a PX4 vehicle.

    Args:
        url: MAVLink link, ``udpout://HOST:PORT`` (default PX4 style) or ``udpin://...``.
        vehicle: vehicle file (``None``: the shipped default).
        payload_g: swinging payload [g] (0: none); released with :meth:`release_payload`.
        cable_length: cable length [m] (``None``: the vehicle file's).
        start, yaw, airborne, vision_required, vision_timeout_s, params: see
            :class:`~simulator.px4.vehicle.Px4Vehicle`.
        seed: sensor-noise seed of the simulator.
        substep: physics chunk between input/telemetry handling [s].
        on_text: called with ``(severity, text)`` for each STATUSTEXT.
    """

    def __init__(
        self,
        url: str,
        *,
        vehicle: str | Path | dict[str, Any] | None = None,
        payload_g: float = 0.0,
        cable_length: float | None = None,
        start=(0.0, 0.0, 0.0),
        yaw: float = 0.0,
        airborne: bool = False,
        vision_required: bool = True,
        vision_timeout_s: float = 0.5,
        params: dict[str, Any] | None = None,
        seed: int = 0,
        substep: float = 0.005,
        on_text: Callable[[int, str], None] | None = None,
    ):
        sim = Px4Airframe(
            vehicle, payload_mass=payload_g / 1000.0, cable_length=cable_length, seed=seed
        )
        self.vehicle = Px4Vehicle(
            sim,
            start=start,
            yaw=yaw,
            airborne=airborne,
            vision_required=vision_required,
            vision_timeout_s=vision_timeout_s,
            params=params,
        )
        self.mavlink = MavlinkVehicle(self.vehicle, url, on_text=on_text)
        self.substep = float(substep)
        self.stop = threading.Event()
        self.overruns = 0
        #: ``time.monotonic()`` at simulated time 0 while :meth:`run` runs (moved forward
        #: by an overrun: the vehicle does not race to catch up).
        self.epoch = time.monotonic() - self.vehicle.time
        self._thread: threading.Thread | None = None

    @property
    def lock(self) -> threading.RLock:
        """Held while the vehicle steps or handles input; take it to read a consistent state."""
        return self.mavlink.lock

    def release_payload(self) -> bool:
        with self.lock:
            return self.vehicle.release_payload()

    def run(
        self, duration: float | None = None, on_chunk: Callable[[Px4Sim], bool | None] | None = None
    ) -> None:
        """Fly on the wall clock until :attr:`stop` is set, ``duration`` [s] of simulated
        time passed or ``on_chunk`` (called after each chunk, lock released) returns True."""
        if self.mavlink._thread is None:
            self.mavlink.start()
        v = self.vehicle
        self.epoch = epoch = time.monotonic() - v.time
        while not self.stop.is_set():
            with self.lock:
                v.step(self.substep)
                self.mavlink.send_due()
            delay = epoch + v.time - time.monotonic()
            if delay > 0.0:
                self.stop.wait(delay)  # pacing to the wall clock
            elif delay < -OVERRUN_S:
                self.overruns += 1
                epoch = time.monotonic() - v.time  # re-anchor instead of racing to catch up
                self.epoch = epoch
            # After pacing: the chunk's end is now, so what on_chunk publishes is not
            # ahead of the wall clock.
            if on_chunk is not None and on_chunk(self):
                break
            if duration is not None and v.time >= duration:
                break

    def start(self, **kwargs) -> Px4Sim:
        """Run in a background thread (tests, embedding)."""
        self._thread = threading.Thread(target=self.run, kwargs=kwargs, name="px4-sim", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self.stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self.mavlink.close()

    def __enter__(self) -> Px4Sim:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
