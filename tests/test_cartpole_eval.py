"""Fast variant of the cartpole evaluation (paper Sec. V-A): a regression guard.

Runs the whole pipeline — data under nominal MPC, offline training of every model, online
adaptation through the interventions with per-method tuning — at reduced size, and checks
the ordering the paper's Table I shows: Ours < Ours w/o CP < offline only, with the
changepoint detector firing at the interventions.
"""

import math

import pytest

from benchmarks import cartpole_eval as ce


@pytest.fixture(scope="module")
def result():
    return ce.evaluate(ce.EvalSettings.quick())


def test_online_ordering_matches_table_1(result):
    o = {k: v["mean"] for k, v in result["online"].items()}
    assert o["ours"] < o["ours_no_cp"] < o["offline_only"], o
    # No learner may beat the oracle that knows the true dynamics (noise floor).
    for name in ("ours", "ours_no_cp", "gp", "mlp_last_layer", "offline_only"):
        assert o[name] > o["oracle_true_model"], name


def test_changepoints_found_at_interventions(result):
    cp = result["changepoints"]
    assert cp["hit_rate"] >= 0.75, cp
    assert 0.0 <= cp["mean_delay_steps"] <= ce.HIT_WINDOW


def test_result_has_the_documented_shape(result):
    for method in ("ours", "ours_no_cp", "gp", "mlp_last_layer", "offline_only"):
        stats = result["online"][method]
        assert set(stats) >= {"mean", "std"} and math.isfinite(stats["mean"])
    for method in ("ours", "deterministic", "mlp", "gp", "sysid"):
        assert math.isfinite(result["offline"][method]["mean"])
    assert set(result["changepoints"]) == {
        "hit_rate",
        "false_alarms_per_100_steps",
        "mean_delay_steps",
    }


def test_changepoint_quality_counts_hits_and_false_alarms():
    import numpy as np

    flags = np.zeros((2, 120), bool)
    flags[0, [1, 41, 82]] = True  # three hits, delays 1, 1, 2
    flags[1, [10, 60]] = True  # two false alarms, no hit
    q = ce.changepoint_quality(flags)
    assert q["hit_rate"] == 3 / 6
    assert q["false_alarms_per_100_steps"] == 100 * 2 / 240
    assert q["mean_delay_steps"] == (1 + 1 + 2) / 3
    assert ce.hits_per_intervention(flags) == {"0": 0.5, "40": 0.5, "80": 0.5}
    flags[1, 40] = True
    assert ce.hits_per_intervention(flags)["40"] == 1.0


def test_tuned_pi_is_the_one_evaluated(result):
    """pi is tuned at the tuned beta, by the lowest tuning CRMSE, and the online row runs
    that configuration."""
    t = result["tuning"]
    assert set(t) == {"ours", "ours_pi", "ours_no_cp", "mlp_last_layer"}
    scores = t["ours_pi"]["tuning_crmse"]
    assert set(scores) == {str(p) for p in ce.OURS_PI_GRID}
    assert str(t["ours_pi"]["chosen"]) == min(scores, key=scores.get)
    # The pi grid's row at the tuned beta is the beta grid's row at the preset pi.
    preset_pi = ce.adaptation.cartpole_config().pi
    assert scores[str(preset_pi)] == t["ours"]["tuning_crmse"][str(t["ours"]["chosen"])]
    cfg = result["ours_config"]
    assert (cfg["beta"], cfg["pi"]) == (t["ours"]["chosen"], t["ours_pi"]["chosen"])


def test_detection_tuned_row_is_the_most_accurate_pair_that_detects(result):
    """beta and pi are read off the same beta x pi grid as the detection-tuned pair, which
    is the lowest tuning CRMSE among the pairs that reach the hit rate."""
    d = result["detection_tuning"]
    grid = {(g["beta"], g["pi"]): g for g in d["grid"]}
    assert len(grid) == len(ce.OURS_BETA_GRID) * len(ce.OURS_PI_GRID)
    preset_pi = ce.adaptation.cartpole_config().pi
    for beta, crmse in result["tuning"]["ours"]["tuning_crmse"].items():
        assert grid[(float(beta), preset_pi)]["tuning_crmse"] == crmse
    ok = [g for g in d["grid"] if g["tuning_hit_rate"] >= d["min_hit_rate"]]
    if ok:
        best = min(ok, key=lambda g: g["tuning_crmse"])
        assert d["chosen"] == {"beta": best["beta"], "pi": best["pi"]}
        assert math.isfinite(result["online"]["ours_detection_tuned"]["mean"])
        assert 0.0 <= d["changepoints"]["hit_rate"] <= 1.0
    else:
        assert d["chosen"] is None and "ours_detection_tuned" not in result["online"]


def test_tuning_grid_with_traced_knobs_matches_separately_compiled_runs():
    """The grid runs every (beta, pi) pair in one program with the knobs traced; each row
    must be what a run compiled for that pair alone gives (CRMSE, hit rate)."""
    import jax

    key = jax.random.PRNGKey(3)
    model = ce.encoder.VLD(key, ce.encoder.cartpole_config())
    data = ce.cd.simulate(key, ce.cd.sample_initial_states(key, 3),
                          ce.cd.intervention_schedule(60))
    cfg = ce.adaptation.cartpole_config()
    betas, pis = (0.3, 0.9), (0.05, 0.3)
    grid = ce.beam_tuning_grid(model, cfg, data.X, data.U, data.X, betas, pis)
    assert [(g["beta"], g["pi"]) for g in grid] == [(b, p) for b in betas for p in pis]
    for g in grid:
        xhat, _, flags, _ = ce.beam_batch(model, cfg._replace(beta=g["beta"], pi=g["pi"]),
                                          data.X, data.U)
        assert g["tuning_crmse"] == pytest.approx(
            float(ce._crmse_batch(xhat, data.X).mean()), rel=1e-4)
        assert g["tuning_hit_rate"] == ce.changepoint_quality(flags)["hit_rate"]


def test_detection_summary_says_when_no_pair_detects_enough():
    text = ce.detection_summary({"min_hit_rate": 0.9, "grid": [], "chosen": None})
    assert "no (beta, pi) pair" in text and "90%" in text
    text = ce.detection_summary({
        "min_hit_rate": 0.9, "chosen": {"beta": 0.5, "pi": 0.3},
        "changepoints": {"hit_rate": 0.97, "false_alarms_per_100_steps": 19.7,
                         "mean_delay_steps": 0.7},
        "hit_rate_per_intervention": {"0": 0.9, "40": 1.0}})
    assert "beta = 0.5, pi = 0.3" in text and "hit rate 97% (step 0 90%, step 40 100%)" in text
