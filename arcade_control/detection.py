"""The changepoint detector's configuration, shared by the adapter and the flagship.

The adapter runs it beside the learner and reports what it declares
(``services.adapter``); the flagship restarts its learner when it declares
(:func:`arcade_control.methods.restart_at_change`). Its knobs are chosen by detection
quality, apart from the learner's (``arcade eval changepoints``, docs/changepoints.md).
"""

from __future__ import annotations

import math
from typing import Any

import jax.numpy as jnp
import numpy as np

from arcade_control.knobs import (
    DETECTION_DEFAULTS,
    DETECTION_ENERGY_OUTPUTS,
    DETECTION_OUTPUTS,
    DETECTION_TRUE_STATE,
)
from arcade_core import adaptation


def detector_noise(sigma2: Any) -> Any:
    """The detector's observation noise beside a learner's per-output ``sigma2``: the
    calibrated one (Appendix D), whatever the learner's tuned one (the flagship's is
    smaller)."""
    return jnp.full(
        jnp.shape(sigma2), adaptation.quadrotor_config().sigma2, jnp.result_type(sigma2)
    )


def detection_config(
    knobs: dict[str, Any] | None = None,
    dtype: Any = None,
    score: str = "joint",
    *,
    estimated: bool,
):
    """The adapter's changepoint detector (:class:`arcade_core.adaptation.DetectionConfig`)
    from :data:`arcade_control.knobs.DETECTION_DEFAULTS` (``estimated``: the state is an
    estimate) or :data:`arcade_control.knobs.DETECTION_TRUE_STATE` (the ground truth)
    updated with ``knobs``: a beam of
    ``K = 15`` scored as the exact joint, at the quadrotor preset's ``tau^2`` and offline
    prior floor, watching the outputs the knob names with the learner's noise. ``score``:
    the hypothesis score (``"algorithm1"`` only to compare, see ``docs/changepoints.md``).
    A knob ``nu`` gives the scores Student-t tails (``AdaptationConfig.nu``, static; default
    ``inf``, the Gaussian of Eq. 8). ``noise`` scales the noise of the watched outputs
    (``DetectionConfig.noise_scale``); ``block`` and ``whiten`` are
    ``DetectionConfig.block`` and ``DetectionConfig.whiten``; ``energy`` and
    ``energy_rate`` are ``DetectionConfig.energy_gain`` and ``energy_rate``, on the
    horizontal velocities (:data:`arcade_control.knobs.DETECTION_ENERGY_OUTPUTS`)."""
    k = {**(DETECTION_DEFAULTS if estimated else DETECTION_TRUE_STATE), **(knobs or {})}
    if k["outputs"] not in DETECTION_OUTPUTS:
        raise ValueError(f"unknown detector outputs {k['outputs']!r}")
    dtype = dtype or jnp.result_type(float)
    scale = np.full(13, np.inf)
    scale[list(DETECTION_OUTPUTS[k["outputs"]])] = k["noise"]
    energy = np.zeros(13)
    energy[list(DETECTION_ENERGY_OUTPUTS)] = 1.0
    beam = adaptation.quadrotor_config()._replace(pi=k["pi"], beta=k["beta"], score="joint")
    f = lambda v: jnp.asarray(v, dtype)  # noqa: E731
    return adaptation.DetectionConfig(
        beam=adaptation.AdaptationConfig(
            K=beam.K,
            pi=f(beam.pi),
            beta=f(beam.beta),
            tau2=f(beam.tau2),
            sigma2=f(1.0),
            prior_floor=f(beam.prior_floor),
            score=score,
            nu=float(k.get("nu", math.inf)),
        ),
        noise_scale=f(scale),
        tracking=f(k["tracking"]),
        window=jnp.asarray(k["window"], jnp.int32),
        threshold=f(k["threshold"]),
        refractory_steps=jnp.asarray(k["refractory_steps"], jnp.int32),
        block=jnp.asarray(k["block"], jnp.int32),
        whiten=f(k["whiten"]),
        energy_outputs=f(energy),
        energy_gain=f(k["energy"]),
        energy_rate=f(k["energy_rate"]),
    )
