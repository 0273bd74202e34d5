"""The fallback laws (NumPy only): the controller's level hover without position feedback,
and the vehicle's position hold when it fails safe."""

from __future__ import annotations

import numpy as np

from arcade_core import frames

#: Tracking steps the level hover's thrust is averaged over (50: 2.5 s at 20 Hz).
HOVER_THRUST_STEPS = 50
#: Gain of the level-hover attitude law [rad/s per unit tilt].
LEVEL_GAIN = 2.0


def level_hover(q: np.ndarray, thrust_hover: float, gain: float = LEVEL_GAIN) -> np.ndarray:
    """``[collective N, body rates FLU]`` that level the vehicle of attitude ``q``
    (scalar first, body FLU to world ENU) and hold its height while level.

    ``g_b`` is the world's up axis in body coordinates (the third row of ``R(q)``); the
    body sees it move as ``dg_b/dt = -omega x g_b``, so ``omega = gain [-g_b,y, g_b,x, 0]``
    makes ``1 - g_b,z`` (the tilt) decrease: ``d/dt (1 - g_b,z) = -gain (g_b,x^2 +
    g_b,y^2)``. Yaw rate zero. The thrust is divided by the tilt's cosine (at most 2x).
    """
    g_b = frames.world_up_in_body_np(q)
    rates = gain * np.array([-g_b[1], g_b[0], 0.0])
    return np.r_[thrust_hover / max(g_b[2], 0.5), rates]


#: Failsafe position hold: PD gains [1/s^2, 1/s], horizontal acceleration limit [m/s^2],
#: attitude gain [1/s] (tilt error -> body rates).
HOLD_KP, HOLD_KD, HOLD_MAX_ACC, HOLD_K_ATT = 4.0, 3.0, 4.0, 6.0


def hold_setpoint(
    x: np.ndarray, p_hold: np.ndarray, hover_thrust: float, mass: float, max_thrust: float
) -> np.ndarray:
    """Position hold at ``p_hold`` on state ``x``: ``[thrust N, body rates rad/s]``.

    Desired acceleration ``kp (p_hold - p) - kd v`` (horizontal part limited) plus
    gravity; thrust is its projection on the body z axis; body rates turn the body z
    axis towards the desired direction (small-angle attitude loop), yaw rate zero.
    """
    p, v, q = x[0:3], x[3:6], x[6:10] / np.linalg.norm(x[6:10])
    g = hover_thrust / mass
    acc = HOLD_KP * (p_hold - p) - HOLD_KD * v
    n = np.linalg.norm(acc[:2])
    if n > HOLD_MAX_ACC:
        acc[:2] *= HOLD_MAX_ACC / n
    acc[2] = np.clip(acc[2], -0.5 * g, g)
    f_world = mass * (acc + np.array([0.0, 0.0, g]))
    R = frames.to_rotation_matrix_np(q)
    f_body = R.T @ f_world
    thrust = float(np.clip(f_body[2], 0.0, max_thrust))
    d = f_body / max(np.linalg.norm(f_body), 1e-6)  # desired thrust axis, body frame
    # z_b x d = (-d_y, d_x, 0): rotate about body x by -d_y, about body y by d_x.
    rates = HOLD_K_ATT * np.array([-d[1], d[0], 0.0])
    return np.r_[thrust, rates]
