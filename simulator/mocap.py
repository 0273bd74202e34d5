"""Motion-capture and gyro emulation: noisy, late, sometimes missing samples.

Every sample carries its *capture* stamp (the simulation time of the ground truth it was
taken from) and its *arrival* time (capture + latency); a consumer only sees samples whose
arrival time has passed. Frames are due every ``1 / rate_hz`` from the reset (t = 0 is the
first frame) and are captured at the first physics step at or after that time, so stamps
are exact but lie on the physics-step grid.

Noise, latency and drops come from a seeded NumPy generator, so a run is reproducible;
mocap and gyro use independent streams, so changing one's settings does not change the
other's noise.

Pose noise: position ``N(0, position_noise_m^2)`` per world axis; attitude
``q_meas = q_true (x) exp(delta / 2)`` with ``delta ~ N(0, attitude_noise_rad^2)`` per body
axis. Latency ``latency_s + N(0, latency_jitter_s^2)`` (clipped at 0; arrivals are kept
in order, as on one network link). Each frame is dropped independently with
``drop_probability``. A capture may also hold a second rigid body, the payload (one packet
of a lab's mocap stream carries every rigid body of a capture): it shares the frame's
stamps and drop, with its own pose noise from a stream of its own (so tracking it does not
change the vehicle's noise). Gyro: ``omega + bias + N(0, noise^2)`` per axis with a constant bias
drawn once per run from ``N(0, bias_std^2)``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from arcade_core import frames


@dataclass(frozen=True)
class MocapConfig:
    """Motion-capture emulation settings (defaults: a 120 Hz OptiTrack-like system)."""

    rate_hz: float = 120.0
    position_noise_m: float = 3e-4
    attitude_noise_rad: float = float(np.deg2rad(0.2))
    latency_s: float = 0.007
    latency_jitter_s: float = 0.001
    drop_probability: float = 0.01

    def __post_init__(self):
        _check_rate(self.rate_hz)
        _check_nonneg(
            self, "position_noise_m", "attitude_noise_rad", "latency_s", "latency_jitter_s"
        )
        if not 0.0 <= self.drop_probability < 1.0:
            raise ValueError(f"drop_probability must be in [0, 1), got {self.drop_probability}")


@dataclass(frozen=True)
class GyroConfig:
    """Gyro stream settings (body FLU rates as the flight controller reports them)."""

    rate_hz: float = 500.0
    noise_rad_s: float = 0.005
    bias_std_rad_s: float = 0.002
    latency_s: float = 0.004

    def __post_init__(self):
        _check_rate(self.rate_hz)
        _check_nonneg(self, "noise_rad_s", "bias_std_rad_s", "latency_s")


def _check_rate(rate: float) -> None:
    if not 0.0 < rate <= 2000.0:
        raise ValueError(f"sample rate must be in (0, 2000] Hz, got {rate}")


def _check_nonneg(cfg, *names: str) -> None:
    for n in names:
        v = getattr(cfg, n)
        if not (v >= 0.0 and np.isfinite(v)):
            raise ValueError(f"{type(cfg).__name__}.{n} must be finite and >= 0, got {v}")


class MocapSample(NamedTuple):
    """One motion-capture frame: airframe origin position (ENU) and attitude (w, x, y, z),
    and ``payload``: the payload's ``(position, quaternion)`` in the same capture (``None``:
    no payload tracked)."""

    stamp: float
    arrival: float
    position: np.ndarray
    quaternion: np.ndarray
    payload: tuple[np.ndarray, np.ndarray] | None = None


class GyroSample(NamedTuple):
    """One gyro sample: body rates (FLU) [rad/s]."""

    stamp: float
    arrival: float
    omega: np.ndarray


_MAX_PENDING = 8192


class _Stream:
    """Periodic capture on the physics clock plus a FIFO of samples not yet read."""

    def __init__(self, rate_hz: float):
        self.period = 1.0 / rate_hz
        self.reset(0.0)

    def reset(self, t0: float) -> None:
        self._next = t0
        self._last_arrival = -np.inf
        # Bounded like a socket buffer: a consumer that never reads loses the oldest.
        self.pending: deque = deque(maxlen=_MAX_PENDING)

    def due(self, t: float) -> bool:
        # Half a microsecond of slack absorbs float error in the stamp grid.
        if t + 5e-7 < self._next:
            return False
        self._next += self.period
        if self._next <= t:  # physics step longer than the sample period: skip ahead
            self._next = t + self.period
        return True

    def arrival(self, stamp: float, latency: float) -> float:
        arr = max(stamp + latency, self._last_arrival)
        self._last_arrival = arr
        return arr

    def pop_arrived(self, now: float) -> list:
        out = []
        while self.pending and self.pending[0].arrival <= now + 1e-9:
            out.append(self.pending.popleft())
        return out


class MocapEmulator:
    """Turns ground-truth poses on the physics clock into motion-capture samples."""

    def __init__(self, config: MocapConfig, rng: np.random.Generator):
        self.config = config
        self.rng = rng
        self._payload_rng = rng.spawn(1)[0]  # its own stream: the vehicle's noise is unchanged
        self._stream = _Stream(config.rate_hz)
        self.n_captured = 0
        self.n_dropped = 0

    def reset(self, t0: float = 0.0) -> None:
        self._stream.reset(t0)
        self.n_captured = 0
        self.n_dropped = 0

    def observe(
        self,
        t: float,
        position: np.ndarray,
        quaternion: np.ndarray,
        payload: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None,
    ) -> None:
        """Offer the true pose at time ``t``; captures it when a frame is due. ``payload``
        gives the payload's true ``(position, quaternion)`` (asked only for a frame kept)."""
        if not self._stream.due(t):
            return
        c = self.config
        self.n_captured += 1
        noise = self.rng.standard_normal(7)  # always draw: drops do not shift the noise
        latency = max(0.0, c.latency_s + c.latency_jitter_s * noise[6])
        if self.rng.random() < c.drop_probability:
            self.n_dropped += 1
            return
        pos, q = self._noisy(position, quaternion, noise)
        carried = None
        if payload is not None:
            carried = self._noisy(*payload(), self._payload_rng.standard_normal(6))
        arrival = self._stream.arrival(t, latency)
        self._stream.pending.append(MocapSample(t, arrival, pos, q, carried))

    def _noisy(
        self, position: np.ndarray, quaternion: np.ndarray, noise: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The pose measured with the standard normal draws ``noise[:6]`` (module docstring)."""
        c = self.config
        pos = position + c.position_noise_m * noise[:3]
        q = frames.multiply_np(
            quaternion, frames.from_rotation_vector_np(c.attitude_noise_rad * noise[3:6])
        )
        return pos, q / np.linalg.norm(q)

    def read(self, now: float) -> list[MocapSample]:
        """Samples that have arrived by ``now`` and were not read before, oldest first."""
        return self._stream.pop_arrived(now)


class GyroEmulator:
    """Turns true body rates into a biased, noisy, delayed gyro stream."""

    def __init__(self, config: GyroConfig, rng: np.random.Generator):
        self.config = config
        self.rng = rng
        self._stream = _Stream(config.rate_hz)
        self.bias = np.zeros(3)
        self.reset()

    def reset(self, t0: float = 0.0) -> None:
        self._stream.reset(t0)
        self.bias = self.config.bias_std_rad_s * self.rng.standard_normal(3)

    def measure(self, omega: np.ndarray) -> np.ndarray:
        """One noisy, biased measurement of ``omega`` (also what the rate loop uses)."""
        return omega + self.bias + self.config.noise_rad_s * self.rng.standard_normal(3)

    def observe(self, t: float, omega: np.ndarray) -> None:
        """Offer the true body rates at time ``t``; samples them when a reading is due."""
        if not self._stream.due(t):
            return
        self._stream.pending.append(
            GyroSample(t, self._stream.arrival(t, self.config.latency_s), self.measure(omega))
        )

    def read(self, now: float) -> list[GyroSample]:
        """Samples that have arrived by ``now`` and were not read before, oldest first."""
        return self._stream.pop_arrived(now)
