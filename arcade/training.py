"""Offline training jobs behind `arcade train` (data, progress bar, weight files)."""

from __future__ import annotations

import sys
from pathlib import Path

import jax
from tqdm import tqdm

from arcade_io.weights import save_model

WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "deploy" / "weights"
CARTPOLE_WEIGHTS = WEIGHTS_DIR / "cartpole_vld.eqx"
#: How the shipped cartpole weights are regenerated.
CARTPOLE_COMMAND = "arcade train --system cartpole"


def progress_callback(total: int, desc: str):
    bar = tqdm(total=total, desc=desc, unit="epoch", file=sys.stderr, leave=True)

    def callback(epoch: int, train_loss: float, val_loss: float) -> None:
        bar.set_postfix(loss=f"{train_loss:.4f}")
        bar.update(1)
        if epoch == total:
            bar.close()

    return callback


def train_cartpole(
    out: Path | None = None,
    epochs: int | None = None,
    variational: bool = True,
    seed: int = 0,
    n_traj: int = 100,
    T: int = 100,
) -> Path:
    """Simulate the paper's offline dataset (Appendix D) and fit the VLD on all of it."""
    from arcade_control import cartpole as cd
    from arcade_core import adaptation, encoder

    key = jax.random.PRNGKey(seed)
    k_data, k_train = jax.random.split(key)
    print(f"simulating {n_traj} cartpole trajectories under nominal MPC ...", file=sys.stderr)
    data = cd.simulate(k_data, cd.sample_initial_states(k_data, n_traj), cd.stationary_schedule(T))
    x, u, xn = cd.transitions(data)
    delta = xn - cd.nominal_next(x, u)
    cfg = encoder.cartpole_config(variational=variational)
    if epochs is not None:
        cfg = cfg._replace(epochs=epochs)
    model, history = encoder.train(
        k_train, cfg, x, u, delta, callback=progress_callback(cfg.epochs, "train cartpole VLD")
    )
    model = encoder.calibrate_residual_scale(
        model, x, u, delta, adaptation.cartpole_config().sigma2
    )
    path = Path(out) if out is not None else CARTPOLE_WEIGHTS
    path.parent.mkdir(parents=True, exist_ok=True)
    save_model(
        path,
        model,
        cfg,
        extra={
            "system": "cartpole",
            "data": f"{n_traj} x {T}-step true-cartpole trajectories, nominal MPC, seed {seed}",
            "final_train_loss": float(history.train_loss[-1]),
            "command": CARTPOLE_COMMAND,
        },
    )
    return path


def load_or_train(
    path: Path,
    command: str,
    train,
    *,
    system: str | None = None,
    train_if_missing: bool = True,
) -> object:
    """The VLD in ``path`` (``system``'s, when given: see ``arcade_io.weights.load_model``).

    A missing file is trained and written by ``train(out=path)`` (saying so) when
    ``train_if_missing``, else ``FileNotFoundError``. A corrupt or foreign file raises
    ``WeightFileError``.
    """
    from arcade_io.weights import load_model

    if not path.is_file():
        if not train_if_missing:
            raise FileNotFoundError(f"{path}: no such file")
        print(f"{path} not found: training it now ({command})", file=sys.stderr)
        train(out=path)
    model, _, _ = load_model(path, system=system)
    return model


def load_cartpole(path: Path | None = None):
    """The cartpole VLD in ``path``. Only the shipped file (``path`` None) is trained and
    written first when it is missing; a given ``path`` must exist."""
    return load_or_train(
        CARTPOLE_WEIGHTS if path is None else Path(path),
        CARTPOLE_COMMAND,
        train_cartpole,
        system="cartpole",
        train_if_missing=path is None,
    )
