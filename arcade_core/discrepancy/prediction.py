"""One system's model with effects as the discrepancy workflow uses it (design §6, step 1).

:class:`DiscrepancyModel` holds the nominal model (quadrotor: with motors and rate loop;
cartpole: Appendix D) and the effect tables the current model already has, the parameter
layout ``theta`` of the effect library (groups, plausible ranges, the current ``theta``),
and predicts from measured states with the measured inputs over windows of the log: one
model step for the residuals, a short horizon for the CRMSE.
"""

from __future__ import annotations

import hashlib
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from arcade_core.discrepancy import cartpole, quadrotor

QUAD_COMPONENTS = (
    "px", "py", "pz", "vx", "vy", "vz", "att_x", "att_y", "att_z", "wx", "wy", "wz",
)  # fmt: skip
CART_COMPONENTS = ("x", "xdot", "theta", "thetadot")
#: Residual channels used for identification (indices into the state).
QUAD_CHANNELS = (3, 4, 5, 10, 11, 12)
CART_CHANNELS = (1, 3)
#: Predictions are padded to multiples of these (samples, windows), so that logs of
#: similar length share one compilation.
_PAD_SAMPLES = 4096
_PAD_WINDOWS = 512

#: One jitted prediction function per system (compiled once per shape).
_PREDICT = {
    "quadrotor": jax.jit(quadrotor.predict_windows, static_argnames=("steps", "dt")),
    "cartpole": jax.jit(cartpole.predict_windows, static_argnames=("steps", "dt")),
}
#: The quadrotor's prediction in two parts: its input-driven states (a scan over the whole
#: log, about half the cost) are computed once per value of the ``theta`` entries they
#: depend on, and reused by the predictions at the other entries' values (the sensitivities
#: to drag, wind, ground effect, ... step those alone).
_QUAD_FILTERS = jax.jit(quadrotor.filter_states, static_argnames=("dt",))
_QUAD_PREDICT_FROM = jax.jit(quadrotor.predict_windows_from, static_argnames=("steps", "dt"))
#: Input-driven states kept per model (one per value of ``FILTER_THETA``'s entries).
_FILTERS_KEPT = 8


class DiscrepancyModel:
    """One system's model, parameter layout and jitted predictions.

    ``model``: a :class:`~arcade_core.discrepancy.quadrotor.QuadModel` or
    :class:`~arcade_core.discrepancy.cartpole.CartpoleModel`; ``effect_tables``: the
    effects the current model has, checked and completed by
    :func:`arcade_core.discrepancy.tables.validate_tables`.
    """

    def __init__(self, system: str, model, effect_tables: dict[str, dict[str, Any]]):
        self.name = system
        self.model = model
        self.effect_tables = effect_tables
        if system == "quadrotor":
            mod = quadrotor
            self.components = QUAD_COMPONENTS
            self.channels = QUAD_CHANNELS
        else:
            mod = cartpole
            self.components = CART_COMPONENTS
            self.channels = CART_CHANNELS
        self.mod = mod
        self.groups = mod.GROUPS
        names = [name for name, _ in self.groups]
        #: Group index -> indices of the groups it acts through (``mod.CARRIERS``).
        self.carriers = {
            names.index(j): tuple(names.index(k) for k in ks) for j, ks in mod.CARRIERS.items()
        }
        self.low = np.asarray(mod.THETA_LOW, float)
        self.high = np.asarray(mod.THETA_HIGH, float)
        self.theta_base = np.asarray(mod.theta_from_effects(self.model, self.effect_tables))
        self._predict = _PREDICT[system]
        self._filters: dict[bytes, quadrotor.Filters] = {}

    def predict(self, theta, X, U, starts, steps: int, dt: float) -> np.ndarray:
        """Predictions ``(len(starts), steps, nx)`` (padded to shared shapes for jit reuse)."""
        args, Up = self.padded(theta, X, U, starts)
        m = len(starts)
        if self.name != "quadrotor":
            return np.asarray(self._predict(*args, steps=steps, dt=dt))[:m]
        fil = self._input_states(args[1], args[3], Up, dt)
        return np.asarray(_QUAD_PREDICT_FROM(*args, fil, steps=steps, dt=dt))[:m]

    def padded(self, theta, X, U, starts) -> tuple[tuple, np.ndarray]:
        """The arguments of the jitted prediction ``(model, theta, X, U, starts)``, the log
        and the windows padded to shared shapes, and the padded inputs."""
        n, m = X.shape[0], len(starts)
        n_pad = -(-n // _PAD_SAMPLES) * _PAD_SAMPLES
        m_pad = -(-m // _PAD_WINDOWS) * _PAD_WINDOWS
        Xp = np.concatenate([X, np.repeat(X[-1:], n_pad - n, axis=0)])
        Up = np.concatenate([U, np.repeat(U[-1:], n_pad - n, axis=0)])
        sp = np.concatenate([starts, np.full(m_pad - m, starts[0])]).astype(np.int32)
        args = (self.model, jnp.asarray(theta), jnp.asarray(Xp), jnp.asarray(Up), jnp.asarray(sp))
        return args, Up

    def _input_states(self, theta, U, U_host: np.ndarray, dt: float) -> quadrotor.Filters:
        """The quadrotor's input-driven states for ``theta`` and the (padded) inputs ``U``
        (``U_host``: the same on the host, for the key), computed once per value of the
        entries they depend on."""
        sub = np.asarray(theta)[list(quadrotor.FILTER_THETA)]
        key = hashlib.blake2b(
            b"".join([sub.astype(float).tobytes(), np.float64(dt).tobytes(), U_host.tobytes()]),
            digest_size=16,
        ).digest()
        fil = self._filters.get(key)
        if fil is None:
            fil = _QUAD_FILTERS(self.model, theta, U, dt=dt)
            if len(self._filters) >= _FILTERS_KEPT:
                del self._filters[next(iter(self._filters))]
            self._filters[key] = fil
        return fil

    def errors(self, X, pred, starts, steps) -> np.ndarray:
        """Measured minus predicted per reporting component, ``(m, steps, n_comp)``."""
        idx = np.asarray(starts)[:, None] + np.arange(1, steps + 1)[None, :]
        meas = X[idx]
        if self.name == "cartpole":
            return meas - pred
        att = attitude_error(meas[..., 6:10], pred[..., 6:10])
        return np.concatenate(
            [meas[..., 0:6] - pred[..., 0:6], att, meas[..., 10:13] - pred[..., 10:13]],
            axis=-1,
        )

    def effect_params(self, theta, name: str):
        """Physical parameters of effect ``name`` at ``theta`` (library units)."""
        return self.mod.effect_params(theta, name)


def rms(a: np.ndarray, axis=0) -> np.ndarray:
    """Root mean square along ``axis``."""
    return np.sqrt(np.mean(np.square(a), axis=axis))


def attitude_error(q_meas: np.ndarray, q_pred: np.ndarray) -> np.ndarray:
    """Rotation vector (body frame) from the predicted to the measured attitude [rad]."""
    w1, v1 = q_pred[..., :1], q_pred[..., 1:]
    w2, v2 = q_meas[..., :1], q_meas[..., 1:]
    # q_pred^* (x) q_meas
    w = w1 * w2 + np.sum(v1 * v2, axis=-1, keepdims=True)
    v = w1 * v2 - w2 * v1 - np.cross(v1, v2)
    return 2.0 * np.sign(np.where(w == 0, 1.0, w)) * v
