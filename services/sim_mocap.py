"""The simulated motion-capture system on the bus: the simulator services' ``mocap`` records.

One capture of :class:`simulator.mocap.MocapEmulator` becomes one record of the vehicle
(body ``--mocap-body``, default :data:`~services.messages.VEHICLE_BODY`) and, while the
simulator has a swinging payload, one of the payload (body
:data:`~services.messages.PAYLOAD_BODY`) with the same ``capture_stamp`` and ``stamp``,
published right after it: a lab's mocap system streams every rigid body of a capture in
one packet. The payload stays tracked after its release, as a mocap system keeps seeing a
marked object that fell to the floor.

Injected faults (``--mocap-fault``, :mod:`simulator.mocap_faults`) act on captures: a
dropout loses both bodies and a clock jump moves the stamps of both (the stream's fault);
a freeze or outliers act on the vehicle's pose only (the tracking under test). Their counts
are per capture, as without a payload.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

from services.messages import PAYLOAD_BODY, VEHICLE_BODY, Mocap
from simulator.mocap_faults import MocapFault, MocapFaults


class MocapStream:
    """The ``mocap`` publisher of a simulator service, with its injected faults.

    ``faults``: :class:`MocapFault` s or their specs; ``seed`` seeds the outliers;
    ``vehicle_body``: the vehicle's rigid-body name.
    """

    def __init__(
        self,
        bus,
        faults: Iterable[MocapFault | str],
        seed: int,
        vehicle_body: str = VEHICLE_BODY,
    ):
        self.faults = MocapFaults(
            [f if isinstance(f, MocapFault) else MocapFault.parse(f) for f in faults], seed
        )
        self.vehicle_body = vehicle_body
        self.pub = bus.publisher("mocap")

    @property
    def fault_counts(self) -> dict[str, int]:
        """Captures hit per fault kind (the ``mocap_faults`` statistics)."""
        return self.faults.counts

    def publish(
        self,
        frames: list,
        to_stamp: Callable[[float], float],
        mission_time: Callable[[float], float],
    ) -> None:
        """Put ``frames`` (:class:`~simulator.mocap.MocapSample` s) on the bus, stamps
        through ``to_stamp`` (simulated time -> bus clock); ``mission_time`` (simulated
        time -> mission time) places the faults."""
        if self.faults.faults:
            frames = self.faults.apply(frames, mission_time)
        for f in frames:
            capture, arrival = to_stamp(f.stamp), to_stamp(f.arrival)
            self.pub.put(
                Mocap(
                    position=f.position,
                    quaternion=f.quaternion,
                    body=self.vehicle_body,
                    capture_stamp=capture,
                    stamp=arrival,
                )
            )
            if f.payload is not None:
                p, q = f.payload
                self.pub.put(
                    Mocap(
                        position=p,
                        quaternion=q,
                        body=PAYLOAD_BODY,
                        capture_stamp=capture,
                        stamp=arrival,
                    )
                )


__all__ = ["MocapStream"]
