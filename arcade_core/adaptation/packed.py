"""The real-time loop's form of Algorithm 1: a beam and its knobs in few arrays, one jitted step.

A :class:`PackedBeam` carries a :class:`~arcade_core.adaptation.state.BeamState` and the
traced hyperparameters in five arrays (and the static ``score``); :func:`packed_step` runs
one iteration of Algorithm 1 (Eqs. 5-10) on it and returns the prediction and diagnostics
in one buffer.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from arcade_core.adaptation.beam import step
from arcade_core.adaptation.config import AdaptationConfig, nu_of, score_of
from arcade_core.adaptation.state import BeamState, Prediction, UpdateInfo


class PackedBeam(NamedTuple):
    """A :class:`BeamState` plus ``pi, beta, tau2, prior_floor`` in five arrays, for the
    real-time loop.

    At this problem size a jitted call costs about as much per argument and result leaf
    as the arithmetic of a whole step, so the loop passes the two large arrays and the
    constant prior mean as they are and everything small in one float and one int buffer:
    ``floats = [log_scores (K), log_offset, sigma2 (d), pi, beta, tau2, prior_floor]``
    (state dtype),
    ``ints = [num_changepoints (K), last_changepoint (K), is_changepoint (K), step]``.
    (Flattening the arrays into the float buffer too would save leaves but makes XLA fuse
    the update into one slow concatenation kernel: with the ``(d, l)`` prior mean in it a
    step took three times as long.) ``score`` and ``nu`` are ``AdaptationConfig``'s:
    static (auxiliary data of the pytree, never leaves), so a jitted step compiles once
    per scoring rule and likelihood. See :func:`make_packed_step`.
    """

    means: Array
    sqrt_covariances: Array
    floats: Array
    ints: Array
    prior_mean: Array
    score: str = "algorithm1"
    nu: float = math.inf


_ARRAYS = PackedBeam._fields[:-2]
_KEYS = tuple(jax.tree_util.GetAttrKey(name) for name in _ARRAYS)
_N = len(_ARRAYS)

# The five arrays are the leaves and ``score`` and ``nu`` the auxiliary data (static); the
# flatten slices the tuple, as cheap per call as a plain named tuple.
jax.tree_util.register_pytree_with_keys(
    PackedBeam,
    lambda p: (tuple(zip(_KEYS, p[:_N])), p[_N:]),
    lambda static, arrays: PackedBeam(*arrays, *static),
    lambda p: (p[:_N], p[_N:]),
)


def pack(state: BeamState, config: AdaptationConfig) -> PackedBeam:
    """``state`` and the traced hyperparameters of ``config`` as a :class:`PackedBeam`.

    ``state`` stays valid after the packed beam has been donated to a step.
    """
    dtype = state.means.dtype
    hyper = jnp.stack(
        [jnp.asarray(v, dtype) for v in (config.pi, config.beta, config.tau2, config.prior_floor)]
    )
    floats = jnp.concatenate([state.log_scores, state.log_offset[None], state.sigma2, hyper])
    ints = jnp.concatenate(
        [
            state.num_changepoints,
            state.last_changepoint,
            state.is_changepoint.astype(jnp.int32),
            state.step[None],
        ]
    )
    # Copies, so that donating the packed beam never invalidates ``state``.
    return PackedBeam(
        jnp.copy(state.means),
        jnp.copy(state.sqrt_covariances),
        floats,
        ints,
        jnp.copy(state.prior_mean),
        score_of(config),
        nu_of(config),
    )


def unpack(packed: PackedBeam) -> tuple[BeamState, AdaptationConfig]:
    """Inverse of :func:`pack` (sizes are read from the array shapes)."""
    K, d, _ = packed.means.shape
    f, n = packed.floats, packed.ints
    sigma2 = f[K + 1 : K + 1 + d]
    pi, beta, tau2, floor = f[K + 1 + d], f[K + 2 + d], f[K + 3 + d], f[K + 4 + d]
    state = BeamState(
        means=packed.means,
        sqrt_covariances=packed.sqrt_covariances,
        log_scores=f[:K],
        log_offset=f[K],
        num_changepoints=n[:K],
        last_changepoint=n[K : 2 * K],
        is_changepoint=n[2 * K : 3 * K] != 0,
        step=n[3 * K],
        sigma2=sigma2,
        prior_mean=packed.prior_mean,
    )
    shared = packed.sqrt_covariances.shape[1] == 1
    noise = sigma2[0] if shared else sigma2  # keeps the shared-covariance contract
    return state, AdaptationConfig(
        K=K,
        pi=pi,
        beta=beta,
        tau2=tau2,
        sigma2=noise,
        prior_floor=floor,
        score=packed.score,
        nu=packed.nu,
    )


def packed_step(packed: PackedBeam, inputs: Array) -> tuple[PackedBeam, Array]:
    """:func:`step` on a :class:`PackedBeam` (Algorithm 1, one iteration).

    Args:
        packed: the beam and hyperparameters.
        inputs: ``[z (l), delta (d), sigma_z2 (l)]`` in the state dtype (zeros for
            ``sigma_z2`` when the encoder variance is not used).

    Returns:
        the new packed beam and ``outputs`` (see :func:`unpack_outputs`).
    """
    state, config = unpack(packed)
    _, d, l = state.means.shape
    z, delta, sigma_z2 = inputs[:l], inputs[l : l + d], inputs[l + d :]
    new_state, pred, info = step(state, z, delta, config, sigma_z2)
    dtype = state.means.dtype
    outputs = jnp.concatenate(
        [
            *pred,
            info.p_change,
            jnp.stack([info.cp_prob, info.cp_mass, info.log_evidence]),
            jnp.stack([info.changepoint, info.map_last_changepoint, info.accepted]).astype(dtype),
        ]
    )
    return pack(new_state, config), outputs


def unpack_outputs(outputs, d: int, K: int) -> tuple[Prediction, UpdateInfo]:
    """Split the ``outputs`` of :func:`packed_step` (NumPy or JAX array) by slicing only.

    ``map_last_changepoint`` comes back in the state dtype (exact below ``2**24`` steps
    in float32; the int32 value is ``ints[K]`` of the returned :class:`PackedBeam`).
    """
    pred = Prediction(*(outputs[i * d : (i + 1) * d] for i in range(7)))
    o = 7 * d
    info = UpdateInfo(
        p_change=outputs[o : o + K],
        cp_prob=outputs[o + K],
        cp_mass=outputs[o + K + 1],
        log_evidence=outputs[o + K + 2],
        changepoint=outputs[o + K + 3] != 0,
        map_last_changepoint=outputs[o + K + 4],
        accepted=outputs[o + K + 5] != 0,
    )
    return pred, info


def make_packed_step():
    """Jitted :func:`packed_step` that donates the packed beam (updated in place).

    Returns ``fn(packed, inputs) -> (packed, outputs)``; the packed beam passed in must not
    be used after the call. Compiles once per beam size, dimensions, dtype and ``score``.
    """
    return jax.jit(packed_step, donate_argnums=0)
