"""Faults injected into a motion-capture stream: dropouts, frozen frames, outliers and
clock jumps over mission-time windows (the simulator service's ``--mocap-fault``).

A fault is written ``KIND@START[+DURATION][,key=value...]``: ``dropout@4+0.5`` drops every
frame for 0.5 s from mission time 4 s, ``freeze@...`` repeats the last genuine frame,
``outliers@...,p=0.2,m=0.5`` moves a frame by ``m`` metres with probability ``p``,
``clockjump@...,offset=-0.3`` shifts the frames' stamps.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

_FAULT = re.compile(
    r"(dropout|freeze|outliers|clockjump)@([0-9.]+)(?:\+([0-9.]+))?"
    r"((?:,\w+=[-0-9.e]+)*)"
)


@dataclass(frozen=True)
class MocapFault:
    """One injected mocap fault over the mission-time window ``[start, start + duration)``."""

    kind: str
    start: float
    duration: float = math.inf
    p: float = 1.0  # outliers: probability per frame
    m: float = 0.5  # outliers: jump [m]
    offset: float = 0.0  # clockjump: clock offset [s]

    @classmethod
    def parse(cls, spec: str) -> MocapFault:
        """``KIND@START[+DURATION][,key=value...]`` (see the module docstring)."""
        m = _FAULT.fullmatch(spec.strip())
        if m is None:
            raise ValueError(
                f"bad mocap fault {spec!r}: KIND@START[+DURATION][,key=value...] "
                "with KIND dropout|freeze|outliers|clockjump"
            )
        kw = {k: float(v) for k, v in (item.split("=") for item in m[4].split(",") if item)}
        unknown = set(kw) - {"p", "m", "offset"}
        if unknown:
            raise ValueError(f"bad mocap fault {spec!r}: unknown {sorted(unknown)}")
        start = float(m[2])
        # Stamps count from the clock's origin (lockstep: the mission start): a backward
        # jump larger than the time since then would stamp frames before it.
        if kw.get("offset", 0.0) < -start:
            raise ValueError(
                f"bad mocap fault {spec!r}: offset {kw['offset']:g} s goes back past the "
                f"start of the mission (at least -{start:g} s for a jump at {start:g} s)"
            )
        return cls(m[1], start, float(m[3]) if m[3] else math.inf, **kw)

    def active(self, t: float) -> bool:
        return self.start <= t < self.start + self.duration


class MocapFaults:
    """Applies :class:`MocapFault` s to the frames of one mocap stream (seeded)."""

    def __init__(self, faults: list[MocapFault], seed: int):
        self.faults = faults
        self.rng = np.random.default_rng(np.random.SeedSequence([seed, 0xFA]))
        self.last = None  # last genuine frame (what a frozen tracker repeats)
        self.counts = {k: 0 for k in ("dropout", "freeze", "outliers", "clockjump")}

    def apply(self, frames, t_mission) -> list:
        """The frames to publish; ``t_mission(capture_stamp)`` gives mission time."""
        out = []
        for f in frames:
            t = t_mission(f.stamp)
            active = [x for x in self.faults if x.active(t)]
            kinds = {x.kind for x in active}
            if "dropout" in kinds:
                self.counts["dropout"] += 1
                continue
            if "freeze" in kinds and self.last is not None:
                self.counts["freeze"] += 1
                f = f._replace(position=self.last.position, quaternion=self.last.quaternion)
            else:
                self.last = f
            for x in active:
                if x.kind == "outliers" and self.rng.random() < x.p:
                    self.counts["outliers"] += 1
                    d = self.rng.normal(size=3)
                    f = f._replace(position=f.position + x.m * d / np.linalg.norm(d))
                elif x.kind == "clockjump":
                    self.counts["clockjump"] += 1
                    f = f._replace(stamp=f.stamp + x.offset, arrival=f.arrival + x.offset)
            out.append(f)
        return out
