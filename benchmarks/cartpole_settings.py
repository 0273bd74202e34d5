"""Sizes, grids and thresholds of the cartpole evaluation (paper Sec. V-A, Appendix D).

:class:`EvalSettings` sizes one run (data, splits, trials, epochs); the grids are the
values each adaptive method's online knobs are tuned over, and the detection thresholds
say when a changepoint counts as found.
"""

from __future__ import annotations

from dataclasses import dataclass

from arcade_control import cartpole as cd

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
PAPER_MLP_LR = 1e-6  # Appendix E (MLP-MPC); Ours' settings are adaptation.cartpole_config()
HIT_WINDOW = 3  # steps after an intervention within which a detection counts
#: Hit rate the detection-tuned row must reach on the tuning trajectories.
DETECTION_MIN_HIT_RATE = 0.9


#: Readings the paper leaves open, each varied alone in the sensitivity study
#: (``cartpole_eval.sensitivity``): impulse length in control periods (None: held until the
#: next intervention, alternating), the noise reading, the horizon of the horizon CRMSE.
SENSITIVITY = {
    "pulse_steps": (1, 2, 5, None),
    "noise": ("std", "variance"),
    "horizon": (1, 5, 10, 25),
}


@dataclass(frozen=True)
class EvalSettings:
    """One run's sizes and the testbed's reading (``arcade_control.cartpole``): impulse
    length ``pulse_steps`` (None: the held variant), ``noise`` (``"std"``: the paper's 0.5 is
    the standard deviation; ``"variance"``), and the ``horizon`` of the open-loop CRMSE
    (the MPC's 25 steps; 0 leaves it out)."""

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
    sensitivity: bool = True
    pulse_steps: int | None = cd.PULSE_STEPS
    noise: str = "std"
    horizon: int = 25
    seed: int = 0

    def true_params(self):
        """The true cartpole of this reading (``noise``)."""
        if self.noise not in cd.NOISE_READINGS:
            raise ValueError(f"noise reading must be one of {sorted(cd.NOISE_READINGS)}")
        return cd.TRUE_PARAMS._replace(dist_std=cd.NOISE_READINGS[self.noise])

    def push_snr(self) -> float | None:
        """The one-period push in standard deviations of this reading's disturbance force
        (``None`` for a longer or held push, for which no bound is given)."""
        if self.pulse_steps != 1:
            return None
        return cd.PUSH_N / float(self.true_params().dist_std)

    def schedule(self) -> cd.Schedule:
        """The online scenario's interventions of this reading (``pulse_steps``)."""
        return cd.intervention_schedule(self.T_online, pulse_steps=self.pulse_steps)

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
            sensitivity=False,
        )
