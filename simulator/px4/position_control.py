"""A small PX4-like multicopter position controller for the vehicle's own modes
(hold, take-off, land): position P -> velocity PD -> tilted thrust vector -> attitude P ->
body rates for the simulator's rate loop. World ENU, body FLU, SI units.

It stands in for PX4's ``mc_pos_control`` + ``mc_att_control`` and only has to keep the
vehicle safe and near a point; offboard flight bypasses it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from arcade_core import frames


@dataclass(frozen=True)
class PositionGains:
    """Gains and limits (names after the PX4 parameters they mimic)."""

    pos_p_xy: float = 0.95  # MPC_XY_P [1/s]
    pos_p_z: float = 1.0  # MPC_Z_P
    vel_p_xy: float = 3.0  # velocity error -> acceleration [1/s]
    vel_p_z: float = 4.0
    vel_max_xy: float = 2.0  # MPC_XY_VEL_MAX [m/s]
    vel_max_up: float = 1.0  # MPC_Z_VEL_MAX_UP
    vel_max_down: float = 1.0  # MPC_Z_VEL_MAX_DN
    tilt_max_rad: float = np.deg2rad(35.0)  # MPC_TILTMAX_AIR
    att_p: tuple[float, float, float] = (6.5, 6.5, 2.8)  # MC_ROLL_P, MC_PITCH_P, MC_YAW_P
    thrust_min_frac: float = 0.12  # MPC_THR_MIN, of the hover thrust


def attitude_to_rates(q: np.ndarray, q_sp: np.ndarray, gains=(6.5, 6.5, 2.8)) -> np.ndarray:
    """Body-rate setpoint [rad/s] (body axes) steering attitude ``q`` to ``q_sp``.

    Proportional on the error quaternion ``q^-1 * q_sp`` (PX4's attitude controller without
    its yaw de-prioritisation): ``omega = 2 * k * sign(w_e) * vec(q_e)``.
    """
    qe = frames.multiply_np(frames.conjugate_np(q), np.asarray(q_sp, dtype=float))
    sign = 1.0 if qe[0] >= 0.0 else -1.0
    return 2.0 * sign * np.asarray(gains) * qe[1:]


class PositionController:
    """``control(x, p_sp, yaw_sp, hover_thrust)`` -> ``[collective N, rates FLU rad/s]``."""

    def __init__(self, gains: PositionGains | None = None, gravity: float = 9.81):
        self.g = gains or PositionGains()
        self.gravity = float(gravity)

    def velocity_setpoint(self, p: np.ndarray, p_sp: np.ndarray) -> np.ndarray:
        g = self.g
        v = np.array([g.pos_p_xy, g.pos_p_xy, g.pos_p_z]) * (p_sp - p)
        xy = np.linalg.norm(v[:2])
        if xy > g.vel_max_xy:
            v[:2] *= g.vel_max_xy / xy
        v[2] = np.clip(v[2], -g.vel_max_down, g.vel_max_up)
        return v

    def control(
        self, x: np.ndarray, p_sp, yaw_sp: float, hover_thrust: float, v_sp=None
    ) -> np.ndarray:
        """Thrust and body rates for position ``p_sp`` (or velocity ``v_sp`` if given;
        ``NaN`` entries of ``v_sp`` take the position loop's value)."""
        g = self.g
        p, v, q = x[0:3], x[3:6], x[6:10] / np.linalg.norm(x[6:10])
        v_cmd = self.velocity_setpoint(p, np.asarray(p_sp, dtype=float))
        if v_sp is not None:
            v_sp = np.asarray(v_sp, dtype=float)
            v_cmd = np.where(np.isnan(v_sp), v_cmd, v_sp)
        acc = np.array([g.vel_p_xy, g.vel_p_xy, g.vel_p_z]) * (v_cmd - v)
        # Thrust direction: gravity compensation plus the demanded acceleration, tilt-limited.
        f = np.array([acc[0], acc[1], acc[2] + self.gravity])
        f[2] = max(f[2], g.thrust_min_frac * self.gravity)
        horiz = np.linalg.norm(f[:2])
        max_h = f[2] * np.tan(g.tilt_max_rad)
        if horiz > max_h:
            f[:2] *= max_h / horiz
        b3 = f / np.linalg.norm(f)
        c1 = np.array([np.cos(yaw_sp), np.sin(yaw_sp), 0.0])
        b2 = np.cross(b3, c1)
        b2 /= np.linalg.norm(b2)
        b1 = np.cross(b2, b3)
        q_sp = frames.from_rotation_matrix_np(np.column_stack([b1, b2, b3]))
        # Collective along the current body z (what the rotors can actually deliver).
        body_z = frames.to_rotation_matrix_np(q)[:, 2]
        thrust = hover_thrust / self.gravity * float(f @ body_z)
        thrust = max(thrust, g.thrust_min_frac * hover_thrust)
        return np.array([thrust, *attitude_to_rates(q, q_sp, g.att_p)])
