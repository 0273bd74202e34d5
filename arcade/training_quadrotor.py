"""`arcade train --system quadrotor`: the quadrotor VLD of Sec. III-A / Appendix D.

Data: the expert flights of :mod:`simulator.expert_flights` (rigid payloads of 10, 100
and 200 g, 3 min each, 100 Hz logs; residuals at the 0.05 s control period). Model: the
Appendix D preset (MLP [64, 128, 64], ELU, l = 8, KL weight 0.1, Adam 1e-3, batch 256,
100 epochs). After training, the residual scale is calibrated so that the online
regression's noise variance ``sigma_j^2`` of the Appendix D quadrotor table is the
offline one-step error level (:func:`arcade_core.encoder.calibrate_residual_scale`).
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax

from arcade.training import WEIGHTS_DIR, load_or_train, progress_callback
from arcade_io.weights import save_model

QUADROTOR_WEIGHTS = WEIGHTS_DIR / "quadrotor_vld.eqx"
#: How the shipped quadrotor weights are regenerated.
QUADROTOR_COMMAND = "arcade train --system quadrotor"


def train_quadrotor(
    out: Path | None = None,
    epochs: int | None = None,
    seed: int = 0,
    progress: bool = True,
    minutes_per_payload: float = 3.0,
) -> Path:
    """Fly the training dataset (cached after the first run), fit the VLD, write the file.

    Returns the path written (default ``deploy/weights/quadrotor_vld.eqx``).
    """
    from arcade_control.guard import compute_guard, guard_to_metadata
    from arcade_control.nominal import CONTROL_DT
    from arcade_core import adaptation, encoder
    from simulator.expert_flights import TRAIN_PAYLOADS_G, make_dataset

    def say(msg: str) -> None:
        if progress:
            print(msg, file=sys.stderr)

    data = make_dataset(
        seed=seed, minutes_per_payload=minutes_per_payload, progress=say if progress else None
    )
    x, u, delta = data["x"], data["u"], data["delta"]
    cfg = encoder.quadrotor_config()
    if epochs is not None:
        cfg = cfg._replace(epochs=int(epochs))
    say(
        f"training on {x.shape[0]} transitions at {CONTROL_DT} s "
        f"(payloads {', '.join(f'{p:g}' for p in TRAIN_PAYLOADS_G)} g)"
    )
    callback = progress_callback(cfg.epochs, "train quadrotor VLD") if progress else None
    key = jax.random.fold_in(jax.random.PRNGKey(seed), 1)
    model, history = encoder.train(key, cfg, x, u, delta, callback=callback)
    model = encoder.calibrate_residual_scale(
        model, x, u, delta, adaptation.quadrotor_config().sigma2
    )
    path = Path(out) if out is not None else QUADROTOR_WEIGHTS
    path.parent.mkdir(parents=True, exist_ok=True)
    save_model(
        path,
        model,
        cfg,
        extra={
            "system": "quadrotor",
            "data": (
                f"expert flights with rigid payloads {list(TRAIN_PAYLOADS_G)} g, "
                f"{minutes_per_payload:g} min each, MuJoCo simulator, seed {seed}; "
                f"{x.shape[0]} transitions at the {CONTROL_DT} s control period"
            ),
            "control_dt": CONTROL_DT,
            "residual": "x(t + control_dt) - f_nom(x(t), u(t)), nominal RK4 over control_dt",
            "final_train_loss": float(history.train_loss[-1]),
            "command": QUADROTOR_COMMAND,
            # Trust region of the model inside the MPC rollout, from the training data,
            # so services need not fly the training flights again to rebuild it.
            "guard": guard_to_metadata(compute_guard(model, x, u, delta)),
        },
    )
    say(f"wrote {path}")
    return path


def load_quadrotor(path: Path | None = None):
    """The quadrotor VLD in ``path``. Only the shipped file (``path`` None) is trained and
    written first when it is missing; a given ``path`` must exist."""
    return load_or_train(
        QUADROTOR_WEIGHTS if path is None else Path(path),
        QUADROTOR_COMMAND,
        train_quadrotor,
        system="quadrotor",
        train_if_missing=path is None,
    )
