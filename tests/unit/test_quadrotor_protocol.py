"""The closed-loop evaluation's conditions and its paired comparison with L1."""

from types import SimpleNamespace

import numpy as np
import pytest
from fake_runner import SequentialTrials

from benchmarks import quadrotor_closedloop as qc
from benchmarks.quadrotor_protocol import (
    CONDITIONS,
    LINK_DELAY_S,
    condition,
    format_paired,
    paired_ci,
    paired_differences,
)


def _trials(method, rmse, payload=175.0, speed=2.5):
    return [
        {"payload_g": payload, "speed_mps": speed, "method": method, "trial": k, "rmse_m": v}
        for k, v in enumerate(rmse)
    ]


def test_paired_differences_follow_the_trials_not_the_means():
    rng = np.random.default_rng(0)
    base = 0.03 + 0.01 * rng.standard_normal(10)  # trial-to-trial spread 10 mm
    better = base - 0.001 + 1e-4 * rng.standard_normal(10)  # 1 mm better in every trial
    same = base + 1e-4 * rng.standard_normal(10)
    rows = _trials("l1", base) + _trials("arcade", better) + _trials("ours", same)
    paired = {p["method"]: p for p in paired_differences(rows, vs="l1")}
    assert set(paired) == {"arcade", "ours"}  # L1 is not compared with itself
    a = paired["arcade"]
    assert a["vs"] == "l1" and a["n"] == 10
    assert a["diff_mean_m"] == pytest.approx(float(np.mean(better - base)))
    lo, hi = a["ci95_m"]
    assert lo < a["diff_mean_m"] < hi < 0.0 and a["better"]
    # The spread between trials is ten times the difference: unpaired, it would not show.
    assert np.std(base) > 5 * abs(a["diff_mean_m"])
    lo, hi = paired["ours"]["ci95_m"]
    assert lo < 0.0 < hi and not paired["ours"]["better"]
    text = "\n".join(format_paired(list(paired.values())))
    assert "better" in text and "tie" in text


def test_a_crash_is_an_infinite_difference_and_cells_stay_apart():
    rows = (
        _trials("l1", [0.03, 0.03, 0.03])
        + _trials("arcade", [0.02, float("inf"), 0.02])
        + _trials("l1", [0.01, 0.01], payload=75.0, speed=0.5)
        + _trials("arcade", [0.02, 0.03], payload=75.0, speed=0.5)
    )
    paired = {(p["payload_g"], p["speed_mps"]): p for p in paired_differences(rows)}
    crashed = paired[(175.0, 2.5)]
    assert crashed["diff_mean_m"] == float("inf") and not crashed["better"]
    worse = paired[(75.0, 0.5)]
    assert worse["n"] == 2 and worse["diff_mean_m"] == pytest.approx(0.015)
    assert worse["ci95_m"][0] > 0.0 and not worse["better"]


def test_paired_ci_of_a_constant_difference_is_the_value():
    assert paired_ci([0.002, 0.002, 0.002]) == (0.002, 0.002)
    assert paired_ci([-0.001]) == (-0.001, -0.001)


def test_conditions():
    assert condition("ideal") == (0.0, False, False, ())
    # The stack condition flies the flagship's thrust smoothness the stack flies (by hand).
    assert condition("stack") == (LINK_DELAY_S, True, True, (("arcade_thrust_smooth", 10.0),))
    with pytest.raises(ValueError, match="one of ideal, stack"):
        condition("px4")
    assert set(CONDITIONS) == {"ideal", "stack"}


def test_the_evaluation_flies_and_tunes_in_its_condition(monkeypatch):
    """Every flight of the stack condition is on the estimate, with the link's delay in the
    scenario and compensated; the result pairs each method with L1."""
    flown = []

    class FakeRunner(SequentialTrials):
        dtype = np.float32

        def __init__(self, models):
            pass

        def fly(self, name, scenario, seed=0, estimated=False, compensate_delay=False):
            flown.append((name, scenario.command_delay_s, estimated, compensate_delay))
            rmse = 0.02 if name == "arcade" else 0.03
            metrics = {k: 0.0 for k in (*qc.KEYS, *qc.DIAGNOSTIC_KEYS)}
            metrics.update(rmse_m=rmse + 1e-3 * seed, crashed=False)
            return SimpleNamespace(metrics=metrics, step_ms=np.zeros(3))

    monkeypatch.setattr(qc, "Runner", FakeRunner)
    models = SimpleNamespace(closedloop={})
    r = qc.run_closedloop(
        trials=3,
        methods=("l1", "arcade"),
        cells=[(175.0, 2.5)],
        models=models,
        tuning=False,
        condition_name="stack",
    )
    assert set(flown) == {(m, LINK_DELAY_S, True, True) for m in ("l1", "arcade")}
    assert r["settings"]["condition"] == "stack"
    assert r["settings"]["tuned"]["arcade_thrust_smooth"] == 10.0  # not the ideal's 25
    (p,) = r["paired"]
    assert p["method"] == "arcade" and p["diff_mean_m"] == pytest.approx(-0.01) and p["better"]
    assert "Paired RMSE difference to L1" in qc.format_table(r)


def test_stored_knobs_of_the_stack_condition_are_the_stacks():
    from arcade_control.knobs import TUNED_DEFAULTS
    from arcade_control.stack import STACK_ARCADE_KNOBS, STACK_L1_KNOBS
    from benchmarks.quadrotor_protocol import stored_knobs

    assert stored_knobs("ideal") == TUNED_DEFAULTS
    stack = stored_knobs("stack")
    assert {k: stack[k] for k in STACK_ARCADE_KNOBS} == STACK_ARCADE_KNOBS
    assert {k: stack[k] for k in STACK_L1_KNOBS} == STACK_L1_KNOBS
    assert stack["ours_sigma2"] == 0.1 and stack["mlp_lr"] == TUNED_DEFAULTS["mlp_lr"]
    with pytest.raises(ValueError, match="unknown condition"):
        stored_knobs("px4")
