"""The expert pilot of the training flights and its random reference paths (Appendix D).

The "expert pilot" is :class:`ExpertPilot`, a cascaded position/attitude controller that
produces what the vehicle's offboard interface takes (collective thrust + body-rate
setpoints) while tracking :class:`RandomPath`, a smooth random cubic Hermite spline through
random waypoints (mean segment speeds 0.5-3.0 m/s, peak speed capped at 3.5 m/s, peak
acceleration at 8 m/s^2, a slowly varying yaw). Like a human pilot it knows the payload
only through the hover throttle it trimmed after take-off. The flights themselves are
flown by :mod:`simulator.expert_flights`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from arcade_core import frames

if TYPE_CHECKING:
    from scipy.interpolate import CubicHermiteSpline

#: Flight envelope of the random trajectories (world ENU, m).
BOX_LOW = np.array([-2.5, -2.5, 1.3])
BOX_HIGH = np.array([2.5, 2.5, 3.3])
START = np.array([0.0, 0.0, 2.0])
MAX_SPEED = 3.5  # m/s
MAX_ACCEL = 8.0  # m/s^2
SEGMENT_SPEED = (0.5, 3.0)  # mean speed between waypoints, m/s
HOVER_LEAD_S = 3.0  # hover at the start so the pilot's trim settles


# ------------------------------------------------------------------------ trajectories


class RandomPath:
    """Smooth random reference: C1 cubic Hermite spline through random waypoints.

    Segment durations follow random mean speeds in :data:`SEGMENT_SPEED`; the whole
    time axis is then stretched until the peak speed is at most :data:`MAX_SPEED` and the
    peak acceleration at most :data:`MAX_ACCEL`. The path starts with a hover of
    :data:`HOVER_LEAD_S` at :data:`START`. Yaw is a slow random sinusoid (+-0.4 rad).
    """

    def __init__(self, rng: np.random.Generator, duration: float):
        pts, times = [START, START], [0.0, HOVER_LEAD_S]
        while times[-1] < duration + 5.0:
            nxt = rng.uniform(BOX_LOW, BOX_HIGH)
            dist = float(np.linalg.norm(nxt - pts[-1]))
            times.append(times[-1] + max(dist / rng.uniform(*SEGMENT_SPEED), 1.0))
            pts.append(nxt)
        spline = self._fit(np.asarray(times), np.asarray(pts))
        grid = np.arange(HOVER_LEAD_S, times[-1], 0.01)
        vmax = np.max(np.linalg.norm(spline(grid, 1), axis=1))
        amax = np.max(np.linalg.norm(spline(grid, 2), axis=1))
        # Stretching time by s divides speeds by s and accelerations by s^2.
        stretch = max(1.0, vmax / MAX_SPEED, np.sqrt(amax / MAX_ACCEL))
        t = np.asarray(times)
        t = np.where(t > HOVER_LEAD_S, HOVER_LEAD_S + (t - HOVER_LEAD_S) * stretch, t)
        self.spline = self._fit(t, np.asarray(pts))
        self.yaw_amp = rng.uniform(0.1, 0.4)
        self.yaw_freq = rng.uniform(0.02, 0.08)
        self.yaw_phase = rng.uniform(0.0, 2.0 * np.pi)

    @staticmethod
    def _fit(times: np.ndarray, pts: np.ndarray) -> CubicHermiteSpline:
        # Imported here: SciPy's interpolate costs ~0.7 s of import in every process that
        # imports this module (each service of the stack), and only the data needs it.
        from scipy.interpolate import CubicHermiteSpline

        # Catmull-Rom velocities (central differences, rest at both ends): unlike a global
        # C2 spline this cannot overshoot far between unevenly spaced waypoints.
        vel = np.zeros_like(pts)
        vel[1:-1] = (pts[2:] - pts[:-2]) / (times[2:] - times[:-2])[:, None]
        return CubicHermiteSpline(times, pts, vel)

    def __call__(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Position, velocity, acceleration and yaw at time ``t``."""
        s = self.spline
        ramp = min(1.0, t / HOVER_LEAD_S)
        yaw = ramp * self.yaw_amp * np.sin(2 * np.pi * self.yaw_freq * t + self.yaw_phase)
        yaw -= ramp * self.yaw_amp * np.sin(self.yaw_phase)  # start at yaw 0
        return s(t), s(t, 1), s(t, 2), float(yaw)


# ------------------------------------------------------------------------ the pilot


class ExpertPilot:
    """Cascaded position (PID) / attitude (P) controller emitting thrust + body rates.

    Position loop: ``a = a_ref + Kp e_p + Kd e_v + Ki int(e_p)`` with the tilt limited to
    ``max_tilt``; thrust vector ``F = m (a + g e3)``, collective thrust ``F . z_body``,
    where ``m`` is the mass implied by the hover throttle the pilot trimmed after take-off
    (:meth:`trim`), as a pilot knows how heavy the vehicle feels. Attitude
    loop (geometric, Lee et al. 2010): ``omega_cmd = -K_R vee(R_d^T R - R^T R_d) / 2``.
    """

    def __init__(
        self,
        mass: float,
        gravity: float = 9.81,
        kp: float = 6.0,
        kd: float = 4.0,
        ki: float = 2.0,
        k_att: float = 6.0,
        max_tilt: float = np.deg2rad(50.0),
        integral_limit: float = 3.0,
    ):
        self.mass, self.gravity = float(mass), float(gravity)
        self.kp, self.kd, self.ki, self.k_att = kp, kd, ki, k_att
        self.max_tilt, self.integral_limit = max_tilt, integral_limit
        self.integral = np.zeros(3)

    def trim(self, hover_thrust: float) -> None:
        """Learn the hover thrust [N] (after take-off): feedback is scaled by the mass it
        implies, the integrator only removes what is left."""
        self.mass = hover_thrust / self.gravity
        self.integral[:] = 0.0

    def __call__(self, x: np.ndarray, ref, dt: float) -> np.ndarray:
        p_ref, v_ref, a_ref, yaw = ref
        p, v, q = x[0:3], x[3:6], x[6:10]
        e_p = p_ref - p
        self.integral = np.clip(self.integral + e_p * dt, -self.integral_limit, self.integral_limit)
        a = a_ref + self.kp * e_p + self.kd * (v_ref - v) + self.ki * self.integral
        a_z = max(a[2] + self.gravity, 0.3 * self.gravity)
        horiz = a[:2]
        lim = np.tan(self.max_tilt) * a_z
        norm = np.linalg.norm(horiz)
        if norm > lim:
            horiz = horiz * (lim / norm)
        f = self.mass * np.array([horiz[0], horiz[1], a_z])
        r = frames.to_rotation_matrix_np(q / np.linalg.norm(q))
        thrust = float(f @ r[:, 2])
        z_d = f / np.linalg.norm(f)
        x_c = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        y_d = np.cross(z_d, x_c)
        y_d /= np.linalg.norm(y_d)
        r_d = np.stack([np.cross(y_d, z_d), y_d, z_d], axis=1)
        e = r_d.T @ r - r.T @ r_d
        e_r = 0.5 * np.array([e[2, 1], e[0, 2], e[1, 0]])
        return np.concatenate([[thrust], -self.k_att * e_r])
