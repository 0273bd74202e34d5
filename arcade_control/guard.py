"""The trust region of a learned residual inside the MPC rollout, and array casting."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from arcade_core import encoder


class Guard(NamedTuple):
    """Trust region of a learned residual inside the MPC rollout (design decision).

    A learned model is only trusted on the data it was trained on: the predicted residual
    is clipped to the largest magnitude seen per state component in the training flights
    (``residual_max``, physical units), and the VLD's latent features to their training
    range ``mean +- 4 std`` (``feature_lo``/``feature_hi``). Without this, the optimiser
    finds inputs where a network extrapolates, and an adapted decoder can make the 20-step
    rollout diverge (the feature map grows linearly, the residual feeds back into the
    state) until it overflows. Applied to every learned-model method (GP, MLP, ours).
    """

    residual_max: Array  # (13,)
    feature_lo: Array  # (l,)
    feature_hi: Array  # (l,)


def compute_guard(vld: encoder.VLD, x, u, delta) -> Guard:
    """:class:`Guard` of a VLD from its training transitions (``x``, ``u``, ``delta``)."""
    x, u = jnp.asarray(x), jnp.asarray(u)
    z = jax.vmap(vld.features)(x, u)
    mu, sd = jnp.mean(z, axis=0), jnp.std(z, axis=0)
    return Guard(jnp.max(jnp.abs(jnp.asarray(delta)), axis=0), mu - 4 * sd, mu + 4 * sd)


def guard_to_metadata(g: Guard) -> dict[str, list[float]]:
    """JSON-ready form stored in the weights file header (``extra["guard"]``)."""
    return {k: [float(v) for v in np.asarray(a)] for k, a in g._asdict().items()}


def guard_from_metadata(extra: dict[str, Any] | None) -> Guard | None:
    """The guard a weights file carries, or ``None`` for files written without one."""
    meta = (extra or {}).get("guard")
    if meta is None:
        return None
    # Through NumPy (cast on the host) and device_put: a list into jnp.asarray compiles a
    # conversion, and so does jnp.asarray of an array (tens of milliseconds each at start-up).
    return Guard(
        *(
            jax.device_put(np.asarray(meta[k], dtype=jax.dtypes.canonicalize_dtype(np.float64)))
            for k in Guard._fields
        )
    )


def make_guard(models, dtype) -> Guard:
    """:class:`Guard` of ``models.vld`` (``models.guard``: the one its weights file carries,
    or :func:`compute_guard` of the training flights), its arrays in ``dtype``."""
    g = getattr(models, "guard", None)
    if g is None:
        raise ValueError(
            "the learned model carries no guard: its weights file was written without one "
            "(retrain with `arcade train --system quadrotor`) and none was computed"
        )
    return cast(g, dtype)


def clip_residual(delta: Array, guard: Guard) -> Array:
    return jnp.clip(delta, -guard.residual_max, guard.residual_max)


def cast(tree, dtype):
    """Floating-point array leaves of ``tree`` converted to ``dtype`` (others untouched)."""

    def one(a):
        if isinstance(a, jax.Array | np.ndarray) and jnp.issubdtype(a.dtype, jnp.floating):
            return jnp.asarray(a, dtype)
        return a

    return jax.tree.map(one, tree)
