"""Quadrotor model with the library's effects: the nominal model plus effect terms (JAX).

What a log is compared against: the rigid-body part of the nominal model
(Appendix D; :func:`~arcade_core.dynamics.quadrotor.quadrotor_deriv` supplies ``pdot,
vdot, qdot``) driven by what the vehicle file says about the motors and the rate loop,
plus the effects of :mod:`arcade_core.discrepancy.catalog` with parameters ``theta``.

Body rates. The nominal model's first-order rate lag ``omegadot = (omega_cmd - omega) /
rate_tau`` is completed with the vehicle file's linear rate loop: with ``G(s)`` the closed
loop from rate setpoint to rate (PID ``p + i/s + d s F(s)`` with the D-term low-pass
``F``, feed-forward, first-order motors, torque authority ``torque_max``, inertia ``J``),

    omegadot = -omega / rate_tau + g(t),   g = (s + 1/rate_tau) G(s) L(s) omega_cmd,

which reproduces ``omega = G L omega_cmd`` exactly while starting every prediction from
the *measured* rate (deviations decay with ``rate_tau``). ``L`` is the ``rate_lag``
effect: a transport delay and a first-order filter on the setpoint. A centre-of-mass
offset ``r`` (``com_offset``) makes the thrust produce the torque ``-r x (0, 0, T)``; the
rate loop (integrator included) turns that disturbance ``d`` into the rate residual
``H(s) d`` with ``H = (s + 1/rate_tau) / (s + M(s) C(s) / J)``, which is added to ``g``.
All of this is linear in the inputs and is solved exactly over each zero-order-hold log
step (matrix exponentials; the delayed setpoint switches inside the step), so motor, filter
and loop time constants far shorter than a log step are fine.

Thrust. The rotors' collective thrust ``T`` lags the command with the vehicle file's motor
time constant (``motor_lag`` replaces it), times ``thrust_scale`` (which also scales the
loop's torque authority), times the mean Cheeseman-Bennett gain ``1 / (1 - R^2 /
(16 h_i^2))`` over the rotor heights ``h_i`` (``ground_effect``, clamped at ``h = R/2``,
parameterised by ``R^2`` so that it is linear at ``R = 0``), times the induced-inflow
factor ``1 - k_c v_b,z - k_h (v_b,x^2 + v_b,y^2)`` (``induced_inflow``, air-relative body
velocity ``v_b``) and the battery factor ``1 - r t / 60`` (``battery_sag``, ``t`` [s] since
the log's first sample).

Forces (world ENU, body FLU, ``m`` the nominal mass): ``a += R F_b / m`` with
``F_b = -m d * n * v_b - c * |v_b| * v_b`` and ``v_b = R^T (v - wind)`` (``rotor_drag``,
``quadratic_drag``, ``wind``). ``n = sqrt(T / (m g))`` is the sum of the rotor speeds
relative to hover (rotor thrust grows with the square of its speed; the collective command
``T`` split evenly over the rotors); the logged position (the geometric centre, not the centre
of mass) accelerates by ``-R (omegadot x r + omega x (omega x r))`` more (``com_offset``).
``p, v, q`` are integrated by classical RK4 (Appendix D) on the exact rate and thrust
signals.

Parameter vector ``theta`` (internal coordinates, :data:`GROUPS`): ``d (3), c (3), R^2,
scale, motor tau, delay, filter tau, r (3), wind (3), k_c, k_h, sag r``. The vertical
centre-of-mass offset ``r_z`` makes no thrust torque, so identification leaves it at the
model file's value (only ``r_x, r_y`` form the ``com_offset`` group).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.scipy.linalg import expm

from arcade_core import frames as quat
from arcade_core.dynamics.params import QuadrotorParams
from arcade_core.dynamics.quadrotor import quadrotor_deriv

#: Effect name -> indices into ``theta`` (fixed layout).
GROUPS: tuple[tuple[str, tuple[int, ...]], ...] = (
    ("rotor_drag", (0, 1, 2)),
    ("quadratic_drag", (3, 4, 5)),
    ("ground_effect", (6,)),
    ("thrust_scale", (7,)),
    ("motor_lag", (8,)),
    ("rate_lag", (9, 10)),
    ("com_offset", (11, 12)),
    ("wind", (14, 15, 16)),
    ("induced_inflow", (17, 18)),
    ("battery_sag", (19,)),
)
N_THETA = 20
#: The effects each effect acts through: wind only moves the air velocity ``v_b``, which
#: enters the drag terms and the inflow loss (the identification looks for it there).
CARRIERS: dict[str, tuple[str, ...]] = {
    "wind": ("rotor_drag", "quadratic_drag", "induced_inflow"),
}
#: Internal bounds of ``theta`` (the library's plausible ranges; ``R^2`` from 0).
THETA_LOW = (
    (0.0,) * 6 + (0.0, 0.5, 0.002, 0.0, 0.0) + (-0.015,) * 3 + (-15.0,) * 3 + (0.0, -0.02, 0.0)
)
THETA_HIGH = (
    (2.0,) * 3 + (0.2,) * 3 + (0.04, 1.5, 0.2, 0.1, 0.3) + (0.015,) * 3 + (15.0,) * 3
    + (0.2, 0.02, 0.1)
)  # fmt: skip
_TINY_TAU = 1e-7
#: Per-axis linear state: front filter (1), loop filter (4), com filter (4), omega (1).
_NF = 9
_NL = _NF + 1


class QuadModel(NamedTuple):
    """What the model needs from a vehicle file (SI, body FLU; per-axis arrays are (3,)).

    ``rotors`` (4, 3) rotor positions (ground-effect heights); the rate loop as the
    simulator's PX4-like PID runs it: gains ``rate_p, rate_i, rate_d, rate_ff``
    (normalised torque), ``torque_max`` [N m] (normalised torque 1), D-term low-pass
    ``d_cutoff_rad_s``.
    """

    params: QuadrotorParams
    motor_tau: float | Array
    rotors: Array
    rate_p: Array
    rate_i: Array
    rate_d: Array
    rate_ff: Array
    torque_max: Array
    d_cutoff_rad_s: float | Array


def theta_off(model: QuadModel) -> Array:
    """``theta`` with every effect switched off: the vehicle file's own model."""
    th = jnp.zeros(N_THETA)
    return th.at[7].set(1.0).at[8].set(model.motor_tau)


# --------------------------------------------------------------------------- linear part


def _companion(num: Array, den: Array) -> tuple[Array, Array, Array]:
    """Controllable canonical form of a strictly proper ``num/den`` (highest power first)."""
    n = den.shape[0] - 1
    lead = den[0]
    den = den / lead
    num = jnp.concatenate([jnp.zeros(n + 1 - num.shape[0]), num]) / lead
    A = jnp.zeros((n, n)).at[:-1, 1:].set(jnp.eye(n - 1)).at[-1].set(-den[1:][::-1])
    B = jnp.zeros(n).at[-1].set(1.0)
    C = num[1:][::-1]
    return A, B, C


def _axis_system(model: QuadModel, theta: Array, axis: int):
    """Continuous ``(A, B)`` of one axis: states ``[front, loop (4), com (4), omega]``,
    inputs ``[rate setpoint (delayed), thrust command]``."""
    par = model.params
    tau_r = par.rate_tau
    J = par.inertia[axis]
    k = theta[7]
    tmax = model.torque_max[axis] * k
    p, i, d, ff = (model.rate_p[axis], model.rate_i[axis], model.rate_d[axis], model.rate_ff[axis])
    tau_m = jnp.maximum(theta[8], _TINY_TAU)
    wc = model.d_cutoff_rad_s
    fd = jnp.array([1.0 / wc, 1.0])  # D-term low-pass denominator s/wc + 1
    # Closed loop G = N / D with N = tmax ((p + ff) s + i)(s/wc + 1),
    # D = J s^2 (tau_m s + 1)(s/wc + 1) + tmax ((p s + i)(s/wc + 1) + d s^2).
    s2m = jnp.polymul(jnp.array([J, 0.0, 0.0]), jnp.array([tau_m, 1.0]))
    den = jnp.polymul(s2m, fd)
    den = jnp.polyadd(
        den, tmax * jnp.polyadd(jnp.polymul(jnp.array([p, i]), fd), jnp.array([d, 0.0, 0.0]))
    )
    lead = jnp.array([1.0, 1.0 / tau_r])
    num_g = jnp.polymul(lead, tmax * jnp.polymul(jnp.array([p + ff, i]), fd))
    a_g, b_g, c_g = _companion(num_g, den)
    # com: H M = (s + 1/tau_r) J s (s/wc + 1) / D, scaled by k * lever / J below.
    num_c = jnp.polymul(lead, jnp.polymul(jnp.array([J, 0.0]), fd))
    a_c, b_c, c_c = _companion(num_c, den)
    lever = jnp.stack([-theta[12], theta[11], jnp.zeros_like(theta[11])])[axis]
    gain_c = k * lever / J
    tau_f = jnp.maximum(theta[10], _TINY_TAU)
    A = jnp.zeros((_NL, _NL))
    A = A.at[0, 0].set(-1.0 / tau_f)
    A = A.at[1:5, 1:5].set(a_g).at[1:5, 0].set(b_g)
    A = A.at[5:9, 5:9].set(a_c)
    A = A.at[9, 1:5].set(c_g).at[9, 5:9].set(gain_c * c_c).at[9, 9].set(-1.0 / tau_r)
    B = jnp.zeros((_NL, 2)).at[0, 0].set(1.0 / tau_f).at[5:9, 1].set(b_c)
    return A, B


#: Most squarings of the matrix exponential: a fast motor (2 ms) in the companion form
#: of the rate loop gives ``|A t|`` near 1e6 over a 20 ms log step, which needs about 18
#: (JAX's default, 16, returns NaN beyond it).
_MAX_SQUARINGS = 48


def _discretise(A: Array, B: Array, t) -> tuple[Array, Array]:
    """Exact zero-order-hold transition ``(Phi, Gamma)`` over ``t >= 0``."""
    n, m = B.shape
    M = jnp.zeros((n + m, n + m)).at[:n, :n].set(A).at[:n, n:].set(B)
    E = expm(M * jnp.maximum(t, 0.0), max_squarings=_MAX_SQUARINGS)
    return E[:n, :n], E[:n, n:]


class _Transitions(NamedTuple):
    """Per-axis transitions needed for one log step with an in-step input switch."""

    A: Array  # (3, NL, NL)
    sw: tuple[Array, Array]  # over [0, s_sw]
    half: tuple[Array, Array]  # over [0, dt/2]
    half_rest: tuple[Array, Array]  # over [s_sw, dt/2]
    full: tuple[Array, Array]  # over [0, dt]
    full_rest: tuple[Array, Array]  # over [s_sw, dt]
    s_sw: Array
    lag: Array  # steps of whole-sample delay
    dt: float


def _transitions(model: QuadModel, theta: Array, dt: float) -> _Transitions:
    delay = theta[9]
    m = jnp.floor(delay / dt)
    s_sw = (delay / dt - m) * dt
    systems = [_axis_system(model, theta, a) for a in range(3)]
    A = jnp.stack([s[0] for s in systems])
    B = jnp.stack([s[1] for s in systems])
    disc = jax.vmap(_discretise, in_axes=(0, 0, None))
    return _Transitions(
        A,
        disc(A, B, s_sw),
        disc(A, B, 0.5 * dt),
        disc(A, B, 0.5 * dt - s_sw),
        disc(A, B, dt),
        disc(A, B, dt - s_sw),
        s_sw,
        m.astype(jnp.int32),
        dt,
    )


def _at(tr: _Transitions, z0: Array, u_a: Array, u_b: Array, u0, half: bool) -> Array:
    """Linear states (3, NL) at ``dt/2`` (``half``) or ``dt`` into the step from ``z0``.

    The delayed setpoint is ``u_a`` before ``s_sw`` and ``u_b`` after it (``s_sw = 0``: no
    switch, ``u_b`` throughout). Exact for the zero-order-hold inputs.
    """
    pw, gw = tr.sw
    (pt, gt), (pr, gr) = (tr.half, tr.half_rest) if half else (tr.full, tr.full_rest)
    ua = jnp.stack([u_a, jnp.full(3, u0)], axis=1)  # (3, 2)
    ub = jnp.stack([u_b, jnp.full(3, u0)], axis=1)
    z_sw = jnp.einsum("aij,aj->ai", pw, z0) + jnp.einsum("aij,aj->ai", gw, ua)
    switched = jnp.einsum("aij,aj->ai", pr, z_sw) + jnp.einsum("aij,aj->ai", gr, ub)
    if not half:  # s_sw < dt always: the switch has happened by the end of the step
        return switched
    before = jnp.einsum("aij,aj->ai", pt, z0) + jnp.einsum("aij,aj->ai", gt, ua)
    return jnp.where(tr.s_sw <= 0.5 * tr.dt, switched, before)


def _delayed(U: Array, k, lag) -> tuple[Array, Array]:
    n = U.shape[0]
    return U[jnp.clip(k - lag - 1, 0, n - 1), 1:4], U[jnp.clip(k - lag, 0, n - 1), 1:4]


# --------------------------------------------------------------------------- filter states


class Filters(NamedTuple):
    """Input-driven states at every log sample: motor thrust ``T (n,)`` and the linear
    filters ``F (n, 3, 9)`` of the rate channel (everything but ``omega`` itself)."""

    T: Array
    F: Array


def filter_states(model: QuadModel, theta: Array, U: Array, dt: float) -> Filters:
    """Reconstruct the input-driven states from the input log alone (steady start)."""
    tr = _transitions(model, theta, dt)
    n = U.shape[0]
    tau_m = jnp.maximum(theta[8], _TINY_TAU)
    a_m = jnp.exp(-dt / tau_m)
    # Steady state of the filter block for the first input (A_ff x + B_f u = 0).
    Aff = tr.A[:, :_NF, :_NF]
    u_first = jnp.stack([U[0, 1:4], jnp.full(3, U[0, 0])], axis=1)
    Bf = jnp.stack([_axis_system(model, theta, a)[1][:_NF] for a in range(3)])
    eye = 1e-9 * jnp.eye(_NF)
    rhs = jnp.einsum("aij,aj->ai", Bf, u_first)[..., None]
    x0 = -jnp.linalg.solve(Aff - eye, rhs)[..., 0]

    def body(carry, k):
        T, x = carry
        u_a, u_b = _delayed(U, k, tr.lag)
        z = jnp.concatenate([x, jnp.zeros((3, 1))], axis=1)
        z1 = _at(tr, z, u_a, u_b, U[k, 0], half=False)
        T1 = U[k, 0] + (T - U[k, 0]) * a_m
        return (T1, z1[:, :_NF]), (T, x)

    _, (T, F) = jax.lax.scan(body, (U[0, 0], x0), jnp.arange(n))
    return Filters(T, F)


# --------------------------------------------------------------------------- dynamics


def rotor_speed_ratio(T, mass, gravity):
    """Sum of the rotor speeds relative to hover for the collective thrust ``T`` split
    evenly over the rotors (thrust grows with the square of the rotor speed)."""
    return jnp.sqrt(jnp.maximum(T, 1e-9) / (mass * gravity))


def _accel(model: QuadModel, theta: Array, p, v, q, w, wdot, T, t) -> tuple[Array, Array]:
    """Thrust the rotors make and the effect accelerations (world) at one instant ``t``
    [s since the log's first sample]."""
    m = model.params.mass
    R = quat.to_rotation_matrix(q)
    h = p[2] + (model.rotors @ R.T)[:, 2]
    ratio = jnp.minimum(theta[6] / (16.0 * jnp.maximum(h, 1e-3) ** 2), 0.25)
    vb = R.T @ (v - theta[14:17])
    inflow = 1.0 - theta[17] * vb[2] - theta[18] * (vb[0] ** 2 + vb[1] ** 2)
    sag = 1.0 - theta[19] * t / 60.0
    thrust = theta[7] * jnp.mean(1.0 / (1.0 - ratio)) * inflow * sag * T
    n = rotor_speed_ratio(T, m, model.params.gravity)
    f_b = -m * theta[0:3] * n * vb - theta[3:6] * jnp.abs(vb) * vb
    r = theta[11:14]
    a_com = -R @ (jnp.cross(wdot, r) + jnp.cross(w, jnp.cross(w, r)))
    return thrust, R @ f_b / m + a_com


def _step(model, theta, tr: _Transitions, a_m, x, T0, F0, U, k, dt):
    par = model.params
    u_a, u_b = _delayed(U, k, tr.lag)
    u0 = U[k, 0]
    z0 = jnp.concatenate([F0, x[10:13, None]], axis=1)  # (3, NL)
    zh = _at(tr, z0, u_a, u_b, u0, half=True)
    z1 = _at(tr, z0, u_a, u_b, u0, half=False)
    a_half = jnp.exp(-0.5 * dt / jnp.maximum(theta[8], _TINY_TAU))

    def omega(z):
        return z[:, -1], jnp.einsum("aj,aj->a", tr.A[:, -1, :], z)

    sig = (
        (omega(z0), T0),
        (omega(zh), u0 + (T0 - u0) * a_half),
        (omega(z1), u0 + (T0 - u0) * a_m),
    )

    def deriv(y, i):
        (w, wdot), T = sig[i]
        p, v, q = y[0:3], y[3:6], y[6:10]
        thrust, a_eff = _accel(model, theta, p, v, q, w, wdot, T, (k + 0.5 * i) * dt)
        xd = quadrotor_deriv(jnp.concatenate([p, v, q, w]), jnp.concatenate([thrust[None], w]), par)
        return jnp.concatenate([xd[0:3], xd[3:6] + a_eff, xd[6:10]])

    y0 = x[0:10]
    k1 = deriv(y0, 0)
    k2 = deriv(y0 + 0.5 * dt * k1, 1)
    k3 = deriv(y0 + 0.5 * dt * k2, 1)
    k4 = deriv(y0 + dt * k3, 2)
    y1 = y0 + (dt / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
    x1 = jnp.concatenate([y1[0:6], quat.normalize(y1[6:10]), z1[:, -1]])
    return x1, sig[2][1], z1[:, :_NF]


#: The entries of ``theta`` that the input-driven states (:func:`filter_states`) depend on:
#: thrust scale, motor lag, rate lag (delay and filter) and the horizontal CoM offset.
FILTER_THETA = (7, 8, 9, 10, 11, 12)


def predict_windows(
    model: QuadModel, theta: Array, X: Array, U: Array, starts: Array, steps: int, dt: float
) -> Array:
    """Predictions ``(len(starts), steps, 13)`` after 1..``steps`` log steps from every
    measured ``X[start]``, with the logged inputs (zero-order hold) and the input-driven
    states reconstructed from the whole input history (module docstring)."""
    fil = filter_states(model, theta, U, dt)
    return predict_windows_from(model, theta, X, U, starts, fil, steps, dt)


def predict_windows_from(
    model: QuadModel,
    theta: Array,
    X: Array,
    U: Array,
    starts: Array,
    fil: Filters,
    steps: int,
    dt: float,
) -> Array:
    """:func:`predict_windows` from the input-driven states ``fil`` of
    ``filter_states(model, theta', U, dt)`` for any ``theta'`` equal to ``theta`` in
    :data:`FILTER_THETA` (the same results, bit for bit)."""
    tr = _transitions(model, theta, dt)
    a_m = jnp.exp(-dt / jnp.maximum(theta[8], _TINY_TAU))

    def one(k0):
        def body(carry, j):
            x, T, F = carry
            x, T, F = _step(model, theta, tr, a_m, x, T, F, U, k0 + j, dt)
            return (x, T, F), x

        _, xs = jax.lax.scan(body, (X[k0], fil.T[k0], fil.F[k0]), jnp.arange(steps))
        return xs

    return jax.vmap(one)(starts)


# --------------------------------------------------------------------------- effect tables


def theta_from_effects(model: QuadModel, tables) -> Array:
    """``theta`` of effect tables (canonical names, physical parameters as in the library);
    effects not named are off."""
    th = theta_off(model)
    for name, t in tables.items():
        if name == "rotor_drag":
            th = th.at[0:3].set(jnp.asarray(t["d"], float))
        elif name == "quadratic_drag":
            th = th.at[3:6].set(jnp.asarray(t["c"], float))
        elif name == "ground_effect":
            th = th.at[6].set(float(t["rotor_radius_m"]) ** 2)
        elif name == "thrust_scale":
            th = th.at[7].set(float(t["scale"]))
        elif name == "motor_lag":
            th = th.at[8].set(float(t["time_constant_s"]))
        elif name == "rate_lag":
            th = th.at[9].set(float(t.get("delay_s", 0.0)))
            th = th.at[10].set(float(t.get("time_constant_s", 0.0)))
        elif name == "com_offset":
            th = th.at[11:14].set(jnp.asarray(t["offset_m"], float))
        elif name == "wind":
            th = th.at[14:17].set(jnp.asarray(t["velocity_mps"], float))
        elif name == "induced_inflow":
            th = th.at[17].set(float(t.get("climb_loss", 0.0)))
            th = th.at[18].set(float(t.get("airspeed_loss", 0.0)))
        elif name == "battery_sag":
            th = th.at[19].set(float(t["loss_per_min"]))
        else:
            raise ValueError(f"unknown quadrotor effect {name!r}")
    return th


def effect_params(theta, name: str) -> dict[str, float | list[float]]:
    """Physical parameters of effect ``name`` from ``theta`` (library units)."""
    th = [float(v) for v in theta]
    if name == "rotor_drag":
        return {"d": th[0:3]}
    if name == "quadratic_drag":
        return {"c": th[3:6]}
    if name == "ground_effect":
        return {"rotor_radius_m": max(th[6], 0.0) ** 0.5}
    if name == "thrust_scale":
        return {"scale": th[7]}
    if name == "motor_lag":
        return {"time_constant_s": th[8]}
    if name == "rate_lag":
        return {"delay_s": th[9], "time_constant_s": th[10]}
    if name == "com_offset":
        return {"offset_m": th[11:14]}
    if name == "wind":
        return {"velocity_mps": th[14:17]}
    if name == "induced_inflow":
        return {"climb_loss": th[17], "airspeed_loss": th[18]}
    if name == "battery_sag":
        return {"loss_per_min": th[19]}
    raise ValueError(f"unknown quadrotor effect {name!r}")
