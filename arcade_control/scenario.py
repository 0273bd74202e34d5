"""The closed-loop flight plan (Sec. V-B) and its flat reference.

Every flight climbs from 1.5 m to the centre of the figure-eight at 2.0 m (2.5 s), hovers
(1.5 s), then flies two laps of the figure-eight
(:class:`arcade_core.trajectories.FigureEight`, 4 m x 2 m) at the mean speed of the cell.
The first 2 s of the figure-eight ramp the speed up smoothly (:class:`RampedPath`) so the
reference starts at rest. The payload is released just before the second lap (at 95 % of
the first lap).

With a ``trajectory`` (:class:`arcade_control.trajectory.Trajectory`: a built-in circle,
Lissajous curve or hover, or one fitted to a file) the flight climbs from the start to the
trajectory's first point instead (2.5 s, or at 0.5 m/s mean when that is farther), hovers
there, then flies the trajectory; the payload is released at the same fraction of its
first lap. Without one the plan is the figure-eight above, unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from arcade_control.nominal import CONTROL_DT as DT
from arcade_control.nominal import nominal_params
from arcade_core.trajectories import Chain, FigureEight, Headed, Hover, Takeoff, flat_state

#: Mean speed of a take-off to a trajectory's first point farther than ``takeoff_s`` allows
#: at it [m/s] (the degree-7 smoothstep peaks at 2.19 times the mean).
CLIMB_SPEED_MPS = 0.5


class RampedPath(NamedTuple):
    """A path flown on a warped clock ``s(t)`` whose rate ramps smoothly from 0 to 1.

    ``ds/dt = smoothstep5(t / ramp)``: velocity, acceleration and jerk of the reference are
    continuous and zero at ``t = 0``, so it chains with a hover (thrust and body rates of
    the flat reference stay continuous). ``s(t) = ramp (2.5 r^4 - 3 r^5 + r^6)`` for
    ``r = t / ramp <= 1``, then ``ramp / 2 + (t - ramp)``.
    """

    path: Any  # a periodic path (figure-eight, circle, Lissajous)
    ramp: Array | float

    def clock(self, t: Array) -> Array:
        r = jnp.clip(t / self.ramp, 0.0, 1.0)
        s_ramp = self.ramp * r**4 * (2.5 - 3.0 * r + r**2)
        return jnp.where(t < self.ramp, s_ramp, 0.5 * self.ramp + (t - self.ramp))

    def position(self, t: Array) -> Array:
        return self.path.position(self.clock(t))


@dataclass(frozen=True)
class Scenario:
    """One cell of Table III plus the fixed flight plan (module docstring)."""

    payload_g: float = 175.0
    speed_mps: float = 2.5
    start: tuple[float, float, float] = (0.0, 0.0, 1.5)
    center: tuple[float, float, float] = (0.0, 0.0, 2.0)
    takeoff_s: float = 2.5
    hover_s: float = 1.5
    ramp_s: float = 2.0
    half_length_m: float = 2.0
    half_width_m: float = 1.0
    laps: float = 2.0
    release_fraction: float = 0.95  # of the first lap; a negative value: no release
    cable_length_m: float | None = None
    #: The payload fixed under the vehicle (no swing) instead of on its cable.
    rigid_payload: bool = False
    #: Transport delay of every setpoint to the rate loop (``QuadrotorSim``'s
    #: ``command_delay_s``); the evaluation's cells fly without one.
    command_delay_s: float = 0.0
    #: What is flown after the hover instead of the figure-eight (None: the figure-eight).
    trajectory: Any = None

    @property
    def figure_eight(self) -> FigureEight:
        return FigureEight(
            center=self.center,
            half_length=self.half_length_m,
            half_width=self.half_width_m,
            speed=self.speed_mps,
        )

    @property
    def lap_s(self) -> float:
        if self.trajectory is not None:
            return float(self.trajectory.lap_s)
        return float(self.figure_eight.period())

    @property
    def first_point(self) -> tuple[float, float, float]:
        """Where the take-off ends and the hover holds: the figure-eight's centre or the
        trajectory's first point."""
        if self.trajectory is None:
            return self.center
        return tuple(float(v) for v in self.trajectory.start())

    @property
    def climb_s(self) -> float:
        """Duration of the take-off [s]: ``takeoff_s``, longer to a trajectory's first
        point farther than ``takeoff_s * 0.5 m/s`` (module docstring)."""
        if self.trajectory is None:
            return self.takeoff_s
        distance = float(np.linalg.norm(np.subtract(self.first_point, self.start)))
        return max(self.takeoff_s, distance / CLIMB_SPEED_MPS)

    @property
    def t_figure(self) -> float:
        """Start of the figure-eight (or of the trajectory) [s]."""
        return self.climb_s + self.hover_s

    def t_of_clock(self, s: float) -> float:
        """Flight time at which the figure-eight (trajectory) clock reads ``s`` (s >= ramp / 2)."""
        if self.trajectory is not None:
            return self.t_figure + self.trajectory.t_of_clock(s)
        return self.t_figure + self.ramp_s + (s - 0.5 * self.ramp_s)

    @property
    def t_release(self) -> float:
        return self.t_of_clock(self.release_fraction * self.lap_s)

    @property
    def t_end(self) -> float:
        if self.trajectory is not None:
            return self.t_figure + self.trajectory.duration_s
        return self.t_of_clock(self.laps * self.lap_s)

    def path(self):
        """The reference as one pytree path (all numbers as arrays: no recompilation)."""
        f = jnp.asarray
        if self.trajectory is not None:
            to = jax.tree.map(f, self.trajectory.path)
            plan = Chain(
                Takeoff(f(self.start), f(self.first_point), f(self.climb_s)),
                Chain(Hover(f(self.first_point)), to, f(self.hover_s)),
                f(self.climb_s),
            )
            if self.trajectory.yaw is None:
                return plan
            return Headed(plan, jax.tree.map(f, self.trajectory.yaw), f(self.t_figure))
        fig = FigureEight(
            center=f(self.center),
            half_length=f(self.half_length_m),
            half_width=f(self.half_width_m),
            speed=f(self.speed_mps),
        )
        hover_then_fig = Chain(
            Hover(f(self.center)), RampedPath(fig, f(self.ramp_s)), f(self.hover_s)
        )
        return Chain(
            Takeoff(f(self.start), f(self.center), f(self.takeoff_s)),
            hover_then_fig,
            f(self.takeoff_s),
        )


def planned(
    payload_g: float = 175.0,
    speed_mps: float = 2.5,
    release_fraction: float = 0.95,
    hover_s: float | None = None,
    origin: tuple[float, float] = (0.0, 0.0),
    trajectory: Any = None,
) -> Scenario:
    """The flight plan of the stack's plan options: the scenario moved horizontally by
    ``origin`` (a ``trajectory`` with it), ``hover_s`` None: the scenario's hover."""
    ox, oy = origin
    base = Scenario()
    if trajectory is not None and (ox, oy) != (0.0, 0.0):
        trajectory = trajectory.shifted((ox, oy, 0.0))
    return Scenario(
        payload_g=float(payload_g),
        speed_mps=float(speed_mps),
        release_fraction=float(release_fraction),
        hover_s=float(base.hover_s if hover_s is None else hover_s),
        start=(base.start[0] + ox, base.start[1] + oy, base.start[2]),
        center=(base.center[0] + ox, base.center[1] + oy, base.center[2]),
        trajectory=trajectory,
    )


def flat_reference(path, times) -> tuple[Array, Array]:
    """Flat reference states and inputs of ``path`` at ``times`` (not jitted)."""
    params = nominal_params()
    return jax.vmap(lambda t: flat_state(path, t, params))(times)


_reference = jax.jit(flat_reference)


def reference_arguments(
    scenario: Scenario, n_steps: int, N: int, offset_s: float = 0.0
) -> tuple[Any, Array]:
    """The arguments of :func:`flat_reference` that :func:`reference` evaluates."""
    dtype = jnp.result_type(float)
    # On the host, then placed (the same IEEE float operations): eager, the arange, multiply
    # and add would each compile in every process that builds a reference.
    times = jax.device_put(
        np.arange(n_steps + N + 1, dtype=dtype) * dtype.type(DT) + dtype.type(offset_s)
    )
    path = jax.tree.map(lambda a: jnp.asarray(a, dtype), scenario.path())
    return path, times


def reference(
    scenario: Scenario, n_steps: int, N: int, offset_s: float = 0.0
) -> tuple[Array, Array]:
    """Flat reference states (n_steps + N + 1, 13) and inputs at every control instant
    (``offset_s`` later: the instants a delayed setpoint starts to act at)."""
    return _reference(*reference_arguments(scenario, n_steps, N, offset_s))


class Trial(NamedTuple):
    """Per-trial randomness, derived from the seed exactly as the in-process evaluation
    (:meth:`benchmarks.quadrotor_flights.Runner.fly`) and the simulator service derive it:
    the simulator's noise seed, the start offset (2 cm std in x and y) and the release
    jitter (up to two control periods)."""

    sim_seed: int
    start_offset: np.ndarray
    release_jitter: int


def trial(seed: int) -> Trial:
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x51]))
    sim_seed = int(rng.integers(2**31))
    offset = np.array([*rng.normal(0.0, 0.02, 2), 0.0])
    return Trial(sim_seed, offset, int(rng.integers(-2, 3)))
