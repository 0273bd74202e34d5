"""Sizes, grids and thresholds of the cartpole evaluation (paper Sec. V-A, Appendix D).

:class:`EvalSettings` sizes one run (data, splits, trials, epochs); the grids are the
values each adaptive method's online knobs are tuned over, and the detection thresholds
say when a changepoint counts as found.
"""

from __future__ import annotations

from dataclasses import dataclass

STATE_NAMES = ("x", "xdot", "theta", "thetadot")
MLP_LR_GRID = (1e-6, 1e-4, 1e-3, 1e-2, 1e-1, 0.3, 1.0)
# Ours' knobs are tuned one after the other (beta, pi, tau^2), each at the others' current
# values, starting from the preset (which every grid holds), in passes until one changes
# nothing (:func:`ours_tuning`).
OURS_BETA_GRID = (0.3, 0.5, 0.7, 0.9, 0.97)
OURS_PI_GRID = (0.01, 0.02, 0.05, 0.1, 0.2, 0.3)
# Wide on purpose: with K = 1 the predictions depend on tau^2 / sigma^2 only, and the
# tuning picks the largest values (an almost flat prior); a grid ending at 1 cut it short.
NO_CP_TAU2_GRID = (0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 100.0)
# Ours gets the same prior-variance grid as Ours w/o CP: the same tuning effort.
OURS_TAU2_GRID = NO_CP_TAU2_GRID
OURS_KNOBS = ("beta", "pi", "tau2")
MAX_TUNING_PASSES = 4
# The known-changepoint reference restarts only at true changes: it may temper harder.
KNOWN_CP_BETA_GRID = (0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 0.9)
#: Latent dimensions of the ablation over l (Appendix D: l = 2 for the cartpole).
LATENT_DIMS = (2, 4, 8)
PAPER_MLP_LR = 1e-6
HIT_WINDOW = 3  # steps after an intervention within which a detection counts
#: Hit rate the detection-tuned row must reach on the tuning trajectories.
DETECTION_MIN_HIT_RATE = 0.9


@dataclass(frozen=True)
class EvalSettings:
    n_traj: int = 100
    T_data: int = 100
    n_splits: int = 10
    n_test: int = 20
    trials: int = 10
    T_online: int = 120
    epochs: int = 50
    gp_points: int = 400
    # 20: with 5 (or 10) Ours' tau^2 scores from 1 to 100 lay within 1.3 % and the pick
    # changed with 20 and 40, which agree (docs/cartpole.md).
    tuning_trials: int = 20
    ablations: bool = True
    seed: int = 0

    @classmethod
    def quick(cls, trials: int = 4) -> EvalSettings:
        """A fast variant for tests: fewer trajectories, splits and epochs."""
        return cls(
            n_traj=30,
            T_data=80,
            n_splits=2,
            n_test=6,
            trials=trials,
            epochs=50,
            gp_points=150,
            tuning_trials=2,
            ablations=False,
        )
