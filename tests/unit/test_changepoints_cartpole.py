"""Scoring of declared changepoints (``benchmarks.cartpole_detection``, shared by the cartpole
evaluation and ``benchmarks.changepoints_cartpole``) on hand-made flags.

Interventions at steps 0, 40, 80 of 120-step trajectories and a hit window of 3 steps: a
declaration at step ``k`` is a hit for intervention ``t`` if ``t <= k <= t + 3``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmarks.cartpole_detection import declaration_quality

T = 120
STEPS = (0, 40, 80)


def _flags(*per_trajectory):
    flags = np.zeros((len(per_trajectory), T), bool)
    for i, steps in enumerate(per_trajectory):
        flags[i, list(steps)] = True
    return flags


def test_hits_false_alarms_precision_delay():
    flags = _flags(
        # 40 and 81 hit (delays 0 and 1); 45 is outside the window of 40: a false alarm.
        (40, 45, 81),
        # 2 and 3 are both in the window of 0: one hit (delay 2), one false alarm; 83 hits
        # (delay 3), 84 is one step past the window: a false alarm.
        (2, 3, 83, 84),
        # Nothing declared: three misses.
        (),
    )
    q = declaration_quality(flags, STEPS, 3)
    hits, declared, interventions = 4, 7, 9
    assert q["hit_rate"] == pytest.approx(hits / interventions)
    assert q["false_alarms_per_100_steps"] == pytest.approx(100 * (declared - hits) / (3 * T))
    assert q["precision"] == pytest.approx(hits / declared)
    assert q["mean_delay_steps"] == pytest.approx((0 + 1 + 2 + 3) / 4)
    assert q["f1"] == pytest.approx(2 * hits / (declared + interventions))
    np.testing.assert_allclose(q["hit_rate_per_intervention"], [1 / 3, 1 / 3, 2 / 3])


def test_no_declarations():
    q = declaration_quality(_flags((), ()), STEPS, 3)
    assert q["hit_rate"] == 0.0
    assert q["false_alarms_per_100_steps"] == 0.0
    assert q["f1"] == 0.0
    assert math.isnan(q["precision"]) and math.isnan(q["mean_delay_steps"])


def test_only_false_alarms_and_leading_axes():
    one = _flags((10, 50, 100))
    perfect = _flags((0, 41, 82))
    q = declaration_quality(np.stack([one, perfect]), STEPS, 3)
    np.testing.assert_allclose(q["hit_rate"], [0.0, 1.0])
    np.testing.assert_allclose(q["false_alarms_per_100_steps"], [2.5, 0.0])
    np.testing.assert_allclose(q["precision"], [0.0, 1.0])
    assert math.isnan(q["mean_delay_steps"][0]) and q["mean_delay_steps"][1] == 1.0


def test_overlapping_windows_rejected():
    with pytest.raises(ValueError):
        declaration_quality(_flags(()), (0, 3), 3)


def test_a_grid_edge_is_extended_one_value_at_a_time_until_its_values_run_out():
    from benchmarks.changepoints_cartpole import EXTENSIONS, extension

    grid = {"beta": (0.3, 0.9), "refractory": (3, 5), "m": (1, 4)}
    assert extension(grid, [("beta", 0), ("refractory", 1)]) == {
        "beta": [EXTENSIONS["beta"][0][0]],
        "refractory": [EXTENSIONS["refractory"][1][0]],
    }
    # Past values already in the grid: the next one out.
    grid = {"beta": (0.03, 0.1, 0.3), "refractory": (3, 5, 8, 12)}
    assert extension(grid, [("beta", 0), ("refractory", 1)]) == {
        "beta": [0.01],
        "refractory": [20],
    }
    # Nothing past the last value (refractory stops at 20 steps), none below m = 1.
    grid = {"refractory": (3, 20), "m": (1, 4)}
    assert extension(grid, [("refractory", 1), ("m", 0)]) == {}
