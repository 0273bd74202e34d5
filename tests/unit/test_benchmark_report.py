"""BENCHMARKS.md sections rendered from results: the quadrotor evaluation, the service loop."""

from __future__ import annotations

import json

import pytest

from arcade_io import jsonout
from benchmarks import report_cartpole, report_measurements, report_quadrotor, report_variants


def _cell(pay, speed, method, rmse, settling):
    return {
        "payload_g": pay,
        "speed_mps": speed,
        "method": method,
        "rmse_m": rmse,
        "rmse_z_m": rmse / 2,
        "shift_m": 0.01,
        "settling_s": settling,
    }


@pytest.mark.parametrize("dumps", [jsonout.dumps, json.dumps], ids=["strict", "older-nan"])
def test_quadrotor_section_marks_the_best_method_per_cell(tmp_path, dumps):
    """Results files hold a settling time that never came as null (strict JSON); files
    written before, with `Infinity`, render the same."""
    cells = [
        _cell(75, 0.5, "nominal", 0.3, 1.3),
        _cell(75, 0.5, "l1", 0.02, 0.0),
        _cell(75, 0.5, "ours", 0.03, float("inf")),
        _cell(175, 2.5, "nominal", 0.7, 1.6),
        _cell(175, 2.5, "l1", 0.08, 0.3),
        _cell(175, 2.5, "ours", 0.05, 2.3),
    ]
    path = tmp_path / "results.json"
    path.write_text(
        dumps(
            {
                "cells": cells,
                "settings": {"trials": 10},
                "generated": "2026-01-01 00:00",
                "machine": "test machine",
                "improvement_over_nominal": [{"payload_g": 75, "speed_mps": 0.5, "ours": 90.0}],
                "tuning": {
                    "chosen": {"ours_beta": 0.05, "ours_sigma2": 0.001},
                    "cell": [150.0, 2.0],
                },
            }
        )
    )
    text = "\n".join(report_quadrotor.quadrotor_section(path))
    assert "written 2026-01-01 00:00" in text and "test machine" in text
    assert "| 75 | 0.5 | **0.020** | 0.030 | 0.300 |" in text
    assert "| 175 | 2.5 | 0.080 | **0.050** | 0.700 |" in text
    assert "| 75 | 0.5 | **0.00** | inf | 1.30 |" in text  # a trial that never settled
    assert "ours 90 %" in text
    assert "(150 g, 2 m/s" in text and "ours_sigma2 = 0.001" in text  # the tuned knobs


def test_quadrotor_section_gives_the_median_settling_and_the_trials_off_band(tmp_path):
    """One late excursion in ten trials sets the mean; the median and the count show it."""

    def trial(method, i, settling):
        return {
            "payload_g": 175,
            "speed_mps": 2.5,
            "method": method,
            "trial": i,
            "settling_s": settling,
        }

    trials = [trial("l1", i, 0.3) for i in range(10)] + [
        trial("ours", i, 3.8 if i == 4 else 0.0) for i in range(10)
    ]
    trials += [trial("gp", i, float("inf") if i < 6 else 1.0) for i in range(10)]
    cells = [
        _cell(175, 2.5, "l1", 0.08, 0.3),
        _cell(175, 2.5, "gp", 0.2, float("inf")),
        _cell(175, 2.5, "ours", 0.07, 0.38),
    ]
    path = tmp_path / "results.json"
    path.write_text(jsonout.dumps({"cells": cells, "trials": trials, "settings": {"trials": 10}}))
    text = "\n".join(report_quadrotor.quadrotor_section(path))
    assert "| 175 | 2.5 | **0.30** | 0.38 | inf |" in text  # the mean
    # the median: six of ten GP trials never settled (null in the file, not zero)
    assert "| 175 | 2.5 | 0.30 | **0.00** | inf |" in text
    assert "| 175 | 2.5 | 10 | **1** | 10 |" in text and "(of 10 per cell)" in text


def test_quadrotor_section_tables_the_diagnostics_when_the_results_have_them(tmp_path):
    def cell(method, dT, drate, cp):
        return {
            **_cell(175, 2.5, method, 0.08, 0.3),
            "thrust_increment_rms_n": dT,
            "rate_increment_rms_rad_s": drate,
            "changepoint_rate": cp,
        }

    cells = [
        cell("l1", 0.13, 0.03, float("nan")),
        cell("ours_no_cp", 0.3, 0.2, 0.0),
        cell("ours", 0.55, 0.41, 0.54),
    ]
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"cells": cells, "settings": {"trials": 10}}))
    text = "\n".join(report_quadrotor.quadrotor_section(path))
    assert "| 175 | 2.5 | **0.13** | 0.55 | 0.30 |" in text  # thrust increments
    assert "| 175 | 2.5 | **0.03** | 0.41 | 0.20 |" in text  # rate increments
    assert "| payload (g) | speed (m/s) | ours |" in text and "| 175 | 2.5 | 0.54 |" in text
    # Result files written before the diagnostics existed still give a report without them.
    path.write_text(json.dumps({"cells": [_cell(175, 2.5, "l1", 0.08, 0.3)]}))
    assert "thrust command" not in "\n".join(report_quadrotor.quadrotor_section(path))


def test_quadrotor_section_says_how_to_produce_missing_results(tmp_path):
    text = "\n".join(report_quadrotor.quadrotor_section(tmp_path / "results.json"))
    assert "No results yet" in text and report_quadrotor.QUADROTOR_COMMAND in text


def test_loop_section_states_the_realtime_conditions_of_its_numbers():
    """A service that ran without the realtime privileges shows in the report: its tails are
    not comparable with those taken under SCHED_FIFO and polling idle CPUs."""
    r = {
        "hop_p50_ms": 0.2,
        "hop_p99_ms": 0.4,
        "sense_to_actuate_p99_ms": 9.5,
        "mpc_p50_ms": 5.4,
        "mpc_p99_ms": 7.0,
        "rate_hz": 50.0,
        "missed_deadlines": 0,
        "duration_s": 120.0,
        "stages_ms": {"hop_imu": [0.2, 0.4]},
        "realtime": {
            "sim": {"policy": "fifo", "cpu_wakeup_latency_us": 0},
            "controller": {"policy": "normal", "cpu_wakeup_latency_us": None},
        },
    }
    text = "\n".join(report_measurements.loop_section(r))
    assert "sim fifo + CPU wake-up latency 0 µs" in text
    assert "controller normal (idle CPUs may sleep)" in text
    assert "| 0.20 | 0.40 | 9.50 | 50.00 | 0 | 120 |" in text
    assert "MPC solve p50/p99 5.40/7.00 ms, inside the controller's stage" in text
    # The advanced step: the solve after the setpoint, the stage's answer from the plan.
    r |= {"advanced_step": True, "answer_p50_ms": 1.5, "answer_p99_ms": 3.25}
    text = "\n".join(
        report_measurements.loop_section(r | {"planned_steps": 5990, "control_steps": 6001})
    )
    assert "MPC solve p50/p99 5.40/7.00 ms for the next instant after each setpoint" in text
    assert "(step p50/p99 1.50/3.25 ms; 5990 of 6001 states)" in text


def test_cartpole_section_renders_the_reference_rows_and_the_latent_ablation(tmp_path):
    stat = {"mean": 4.0, "std": 0.2}
    choice = lambda v: {"chosen": v, "tuning_crmse": {}}  # noqa: E731
    cp = {"hit_rate": 0.77, "false_alarms_per_100_steps": 8.4, "mean_delay_steps": 0.7}
    r = {
        "settings": {"trials": 10, "n_splits": 10},
        "online": {"ours": stat, "ours_known_changepoints": {"mean": 5.25, "std": 0.48}},
        "offline": {"ours": stat},
        "ratios": {"ours/ours_no_cp": 0.7},
        "tuning": {
            "ours": choice(0.7),
            "ours_pi": choice(0.2),
            "ours_tau2": choice(3.0),
            "ours_passes": 2,
            "ours_no_cp": choice(100.0),
            "mlp_last_layer": choice(0.1),
            "ours_known_changepoints": {**choice(0.2), "tau2": choice(10.0)},
        },
        "changepoints": cp,
        "changepoints_paper_config": cp,
        "latent_ablation": [
            {
                "l": 4,
                "beta": 0.7,
                "pi": 0.1,
                "ours_tau2": 3.0,
                "tau2": 100.0,
                "ours": {"mean": 3.981, "std": 0.3},
                "hit_rate": 0.9,
                "false_alarms_per_100_steps": 9.0,
                "ours_no_cp": {"mean": 5.871, "std": 0.8},
                "offline_only": {"mean": 7.141, "std": 0.1},
                "ratio_ours_no_cp": 0.678,
            }
        ],
    }
    text = "\n".join(report_cartpole.cartpole_section(r, tmp_path))
    assert "| ours_known_changepoints | 5.250 ± 0.480 | — | — |" in text
    assert "`ours_known_changepoints` is Ours with one hypothesis" in text
    assert "beta = 0.2, tau^2 = 10 tuned the same way" in text
    assert "Ours beta = 0.7 (paper 0.9), pi = 0.2 (paper 0.05), tau^2 = 3 (paper 0.1; " in text
    row = "| 4 | 3.981 ± 0.300 | 90% | 9.00 | 5.871 ± 0.800 | 7.141 | 0.68 | 0.7, 0.1, 3; 100 |"
    assert row in text
    assert "Testbed" not in text and "Sensitivity" not in text
    del r["latent_ablation"], r["tuning"]["ours_known_changepoints"]
    text = "\n".join(report_cartpole.cartpole_section(r, tmp_path))
    assert "latent dimension" not in text and "shows the noise floor." in text


def test_cartpole_section_renders_the_testbed_both_crmse_readings_and_the_sensitivity(tmp_path):
    stat = {"mean": 4.0, "std": 0.2}
    choice = lambda v: {"chosen": v, "tuning_crmse": {}}  # noqa: E731
    ratio = {
        "ours/ours_no_cp": 0.9,
        "ours/gp": 0.8,
        "ours/mlp_last_layer": 0.7,
        "ours/offline_only": 0.6,
    }
    cp = {
        "hit_rate": 0.5,
        "precision": 0.25,
        "false_alarms_per_100_eligible_steps": 3.0,
        "false_alarms_per_100_steps": 3.1,
        "mean_delay_steps": 1.0,
        "hit_rate_per_intervention": {"0": 0.0, "40": 0.5, "80": 1.0},
        "random_baseline": {"flag_rate": 0.05, "hit_rate": 0.19, "precision": 0.09},
    }
    row = {
        "online": {"ours": stat},
        "ratios": ratio,
        "ratios_horizon_1": ratio,
        "ratios_horizon_25": {**ratio, "ours/gp": 0.55},
        "changepoints": cp,
    }
    r = {
        "testbed": {
            "pulse_steps": 1,
            "impulse_Ns": 0.1,
            "mass_factor_per_intervention": 0.9,
            "disturbance_mean_N": -0.5,
            "disturbance_std_N": 0.5,
            "dt_s": 0.05,
            "x0_bounds": [1.0, 1.0, 0.6, 1.0],
            "horizon_steps": 25,
        },
        "settings": {"trials": 10, "n_splits": 10},
        "online": {"ours": stat, "ours_tuned": {"mean": 3.5, "std": 0.1}},
        "online_horizon": {"ours": {"mean": 30.0, "std": 2.0}},
        "offline": {"ours": stat},
        "ratios": ratio,
        "ratios_horizon": {**ratio, "ours/gp": 0.45},
        "tuning": {
            "ours": choice(0.7),
            "ours_no_cp": choice(100.0),
            "mlp_last_layer": choice(0.1),
        },
        "changepoints": cp,
        "changepoints_tuned": cp,
        "sensitivity": {
            "horizons": [1, 25],
            "pulse_steps": {"1": row, "held": row},
            "noise": {"std": row},
        },
    }
    text = "\n".join(report_cartpole.cartpole_section(r, tmp_path))
    assert "2 N impulse as a 1-step pulse (0.1 N s)" in text
    assert "| ours | 4.000 ± 0.200 | 30.000 ± 2.000 | 5.83 |" in text
    assert "| ours_tuned | 3.500 ± 0.100 | — | — |" in text
    assert "| ratio | ratios | ratios_horizon |" in text
    assert "| ours/gp | 0.80 | 0.45 |" in text
    assert "Changepoint detection (paper settings): hit rate within 3 steps 50% " in text
    assert "precision 25%" in text and "random detector at the same flag rate" in text
    assert "| pulse_steps = held | 4.00 | 0.90 (0.90/0.90) | 0.80 (0.80/0.55) |" in text


def test_variants_section_keeps_the_run_s_method_order_and_marks_the_best(tmp_path):
    cells = [
        _cell(75, 0.5, "l1", 0.004, 0.0),
        _cell(75, 0.5, "ours", 0.006, 0.0),
        _cell(75, 0.5, "ours_matched", 0.002, 0.5),
    ]
    path = tmp_path / "results.json"
    path.write_text(
        json.dumps(
            {
                "cells": cells,
                "methods": ["l1", "ours", "ours_matched"],
                "trials": 10,
                "tuning": {"chosen": {"ours_matched_beta": 0.2}},
                "generated": "2026-01-01 00:00",
                "machine": "test machine",
                "wall_time_s": 660.0,
            }
        )
    )
    text = "\n".join(report_variants.variants_section(path))
    assert "| payload (g) | speed (m/s) | l1 | ours | ours_matched |" in text
    assert "| 75 | 0.5 | 0.0040 | 0.0060 | **0.0020** |" in text
    assert "| 75 | 0.5 | **0.00** | **0.00** | 0.50 |" in text  # settling: lowest in bold
    assert "not the paper's method" in text and "ours_matched_beta = 0.2" in text
    assert "in 11 min" in text and "test machine" in text
    missing = "\n".join(report_variants.variants_section(tmp_path / "none.json"))
    assert "No results yet" in missing and "arcade bench variants" in missing


def test_estimated_state_section_compares_the_rows_flown_on_the_estimate(tmp_path):
    def m(rmse):
        return {"rmse_m": rmse, "rmse_z_m": rmse / 2, "settling_s": 0.0, "changepoint_rate": 0.1}

    row = {"payload_g": 75.0, "speed_mps": 0.5, "l1": m(0.001), "ours": m(0.002)}
    row |= {"l1_estimated": m(0.009), "ours_estimated": m(0.04), "ours_stack_estimated": m(0.03)}
    path = tmp_path / "estimated.json"
    path.write_text(
        json.dumps(
            {
                "generated": "2026-01-01 00:00",
                "machine": "test machine",
                "trials": 3,
                "rows": [row],
                "wall_time_s": 300.0,
            }
        )
    )
    text = "\n".join(report_variants.estimated_section(path))
    # The truth rows are the evaluation's: not in these tables, nor in the bold.
    head = "| payload (g) | speed (m/s) | l1_estimated | ours_estimated | ours_stack_estimated |"
    assert head in text
    assert "| 75 | 0.5 | **0.0090** | 0.0400 | 0.0300 |" in text
    assert "Seeds 0 to 2" in text and "in 5 min" in text and "test machine" in text
    missing = "\n".join(report_variants.estimated_section(tmp_path / "none.json"))
    assert "No results yet" in missing and "quadrotor_variants estimated" in missing


def test_estimator_section_tables_the_tuning_and_the_cells_side_by_side(tmp_path):
    def m(rmse):
        return {"rmse_m": rmse, "rmse_z_m": rmse / 2, "settling_s": 0.0, "changepoint_rate": 0.1}

    names = ("l1@100", "l1@20", "ours_stack@100", "ours_stack@20")
    row = {"payload_g": 75.0, "speed_mps": 0.5}
    row |= {n: m(v) for n, v in zip(names, (0.0087, 0.0067, 0.0462, 0.0343), strict=True)}
    result = {
        "generated": "2026-01-01 00:00",
        "machine": "test machine",
        "trials": 3,
        "tuning": {
            "cell": [150.0, 2.0],
            "seeds": [999, 998],
            "grid": [100.0, 20.0, 5.0],
            "rmse_m": {"l1": [0.0191, 0.0187, 0.1212], "ours_stack": [0.0631, 0.053, 0.0516]},
            "chosen": 20.0,
            "hand_set": 100.0,
            "default": 20.0,
        },
        "rows_flown": [{"name": n} for n in names],
        "rows": [row],
        "wall_time_s": 480.0,
    }
    path = tmp_path / "estimator.json"
    path.write_text(json.dumps(result))
    text = "\n".join(report_variants.estimator_section(path))
    assert "| jerk density | l1 | ours_stack |" in text
    assert "| 20 (picked) | 0.0187 | 0.0530 |" in text and "| 5 | 0.1212 | 0.0516 |" in text
    assert "(150, 2: payload g, speed m/s; seeds 999, 998)" in text
    assert "| payload (g) | speed (m/s) | " + " | ".join(names) + " |" in text
    assert "| 75 | 0.5 | 0.0087 | **0.0067** | 0.0462 | 0.0343 |" in text
    assert "hand-set 100" in text and "in 8 min" in text and "test machine" in text
    missing = "\n".join(report_variants.estimator_section(tmp_path / "none.json"))
    assert "No results yet" in missing and "quadrotor_variants estimator" in missing


def test_delay_section_tables_the_sensitivity_the_retuning_and_the_cells(tmp_path):
    def m(rmse):
        return {"rmse_m": rmse, "rmse_z_m": rmse / 2, "settling_s": 0.0, "changepoint_rate": 0.1}

    names = ("l1@0ms", "ours@0ms", "l1@20ms", "ours@20ms", "ours_retuned@20ms")
    row = {"payload_g": 75.0, "speed_mps": 0.5}
    row |= {n: m(v) for n, v in zip(names, (0.004, 0.003, 0.0045, 0.08, 0.017), strict=True)}
    result = {
        "generated": "2026-01-01 00:00",
        "machine": "test machine",
        "trials": 3,
        "sensitivity": {
            "cell": [150.0, 2.0],
            "seeds": [999, 998],
            "delays_s": [0.0, 0.01, 0.02],
            "knobs": {"l1": {"l1_a_s": -0.1}, "ours": {"ours_sigma2": 0.0001}},
            "rmse_m": {"l1": [0.0175, 0.02, 0.0258], "ours": [0.0411, 0.09, 0.1039]},
        },
        "tuning": {"command_delay_s": 0.02, "chosen": {"ours_sigma2": 0.1, "l1_a_s": -0.1}},
        "tuning_compensated": {"chosen": {"ours_sigma2": 0.001, "l1_a_s": -0.1}},
        "rows_flown": [{"name": n} for n in names],
        "rows": [row],
        "wall_time_s": 900.0,
    }
    path = tmp_path / "delay.json"
    path.write_text(json.dumps(result))
    text = "\n".join(report_variants.delay_section(path))
    assert "| delay (ms) | l1 | ours |" in text
    assert "| 0 | 0.0175 | 0.0411 |" in text and "| 20 | 0.0258 | 0.1039 |" in text
    assert "l1: l1_a_s = -0.1; ours: ours_sigma2 = 0.0001" in text
    assert (
        "with 20 ms: ours_sigma2 = 0.1, l1_a_s = -0.1; compensating it: ours_sigma2 = 0.001" in text
    )
    assert "| payload (g) | speed (m/s) | " + " | ".join(names) + " |" in text
    assert "| 75 | 0.5 | 0.0040 | **0.0030** | 0.0045 | 0.0800 | 0.0170 |" in text
    assert "in 15 min" in text and "test machine" in text
    missing = "\n".join(report_variants.delay_section(tmp_path / "none.json"))
    assert "No results yet" in missing and "quadrotor_variants delay" in missing


def test_link_section_tables_each_delay_with_and_without_compensation(tmp_path):
    def m(rmse):
        return {"rmse_m": rmse, "rmse_z_m": rmse / 2, "settling_s": 0.0, "changepoint_rate": 0.1}

    names = ("ours_stack_compensated@20ms", "l1_compensated@20ms", "l1_retuned_compensated@20ms")
    row = {"payload_g": 175.0, "speed_mps": 2.5}
    row |= {n: m(v) for n, v in zip(names, (0.06, 0.2, 0.05), strict=True)}
    result = {
        "generated": "2026-01-01 00:00",
        "machine": "test machine",
        "trials": 3,
        "sensitivity": {
            "cell": [150.0, 2.0],
            "seeds": [999, 998, 997, 996],
            "delays_s": [0.0, 0.02],
            "knobs": {"ours_stack": {"ours_sigma2": 0.1}, "l1": {"l1_a_s": -0.1}},
            "rows": {
                "ours_stack": {"rmse_m": [0.053, 0.081], "rmse_z_m": [0.022, 0.04]},
                "ours_stack_compensated": {"rmse_m": [0.053, 0.057], "rmse_z_m": [0.022, 0.025]},
            },
        },
        "tuning": {"command_delay_s": 0.02, "chosen": {"l1_a_s": -2.0, "ours_sigma2": 0.1}},
        "rows_flown": [{"name": n} for n in names],
        "rows": [row],
        "wall_time_s": 2700.0,
    }
    path = tmp_path / "link.json"
    path.write_text(json.dumps(result))
    text = "\n".join(report_variants.link_section(path))
    assert "| delay (ms) | ours_stack | ours_stack_compensated |" in text
    assert "| 0 | 0.0530 | 0.0530 |" in text and "| 20 | 0.0810 | 0.0570 |" in text
    assert "| 20 | 0.0400 | 0.0250 |" in text  # the z-RMSE table
    assert "ours_stack: ours_sigma2 = 0.1; l1: l1_a_s = -0.1" in text
    assert "(150, 2: payload g, speed m/s; seeds 999, 998, 997, 996)" in text
    assert "(the estimate, 20 ms, compensated): l1_a_s = -2, ours_sigma2 = 0.1" in text
    assert "| payload (g) | speed (m/s) | " + " | ".join(names) + " |" in text
    assert "| 175 | 2.5 | 0.0600 | 0.2000 | **0.0500** |" in text
    assert "in 45 min" in text and "test machine" in text
    missing = "\n".join(report_variants.link_section(tmp_path / "none.json"))
    assert "No results yet" in missing and "quadrotor_variants link" in missing


def test_discrepancy_section_names_what_was_found_and_what_was_not():
    result = {
        "minutes_of_data": 10.0,
        "samples": 60001,
        "cold_s": 20.4,
        "warm_s": 14.2,
        "target_s": 60.0,
        "within_target": True,
        "named": ["rotor_drag"],
        "confidence": {"rotor_drag": 0.97},
        "parameter_rel_error": {"rotor_drag": 0.012},
        "heldout_rmse_before": 0.04,
        "heldout_rmse_after": 0.01,
        "heldout_components": ["vx", "vy"],
    }
    text = "\n".join(report_measurements.discrepancy_section(result))
    assert "| 20.4 | 14.2 | True | rotor_drag | 0.0400 | 0.0100 | 75 % |" in text
    assert "| rotor_drag | 0.97 | 1.2 % |" in text
    assert "| motor_lag | — | not found |" in text  # hidden but not identified
    assert "time_constant_s = 0.06" in text


def _paired_trials() -> list[dict]:
    """Three paired seeds in one cell (175 g, 2.5 m/s): arcade 5 mm better than L1 on
    each, ours 10 mm worse; horizontally L1 8 mm, arcade 4 mm, ours 12 mm."""
    return [
        {
            "payload_g": 175,
            "speed_mps": 2.5,
            "method": method,
            "trial": k,
            "rmse_m": r + 1e-4 * k,
            "rmse_z_m": z,
            "settling_s": 0.0,
        }
        for k in range(3)
        for method, r, z in (("l1", 0.010, 0.006), ("arcade", 0.005, 0.003), ("ours", 0.02, 0.016))
    ]


def _write_paired(tmp_path, cells: list[dict], **fields):
    """A results file with :func:`_paired_trials`, their paired differences to L1,
    ``cells`` and ``fields``; its path."""
    from benchmarks.quadrotor_protocol import paired_differences

    trials = _paired_trials()
    path = tmp_path / "results.json"
    paired = paired_differences(trials, vs="l1")
    path.write_text(jsonout.dumps({"cells": cells, "trials": trials, "paired": paired, **fields}))
    return path


def test_stack_section_leads_with_paired_differences_to_l1(tmp_path):
    # Three paired seeds in one cell: arcade 5 mm better than L1 each time, ours worse; the
    # section gives the paired intervals in total, horizontally and vertically.
    from benchmarks import report_stack

    cells = []
    for method in ("l1", "arcade", "ours"):
        c = _cell(175, 2.5, method, 0.01, 0.0)
        c.update(thrust_increment_rms_n=0.5, converged_fraction=0.99)
        cells.append(c)
    path = _write_paired(
        tmp_path, cells, settings={"trials": 3, "condition": "stack"}, machine="test machine"
    )
    text = "\n".join(report_stack.stack_section(path))
    assert "test machine" in text and "3 paired seeds per cell" in text
    assert "`arcade` better in 1, worse in 0, no difference in 0" in text
    assert "`ours` better in 0, worse in 1, no difference in 0" in text
    assert "| 175 | 2.5 | **-5.0 [-5.0, -5.0]** | +10.0 [+10.0, +10.0] |" in text
    # Horizontal, sqrt(r^2 - z^2) per seed: L1 8 mm, arcade 4 mm, ours 12 mm; z: 6, 3, 16.
    assert "| 175 | 2.5 | **-4.0 [-4.0, -4.0]** | **-3.0 [-3.0, -3.0]** | +4.0 [" in text
    assert "| +10.0 [+10.0, +10.0] |\n\nTracking RMSE" in text
    assert "| 175 | 2.5 | **0.004** | 0.008 | 0.012 |" in text  # horizontal RMSE
    assert report_stack.ORDER[:4] == ("arcade", "l1", "ours", "ours_paper")


def test_stack_section_says_how_to_produce_missing_results(tmp_path):
    from benchmarks import report_stack

    text = "\n".join(report_stack.stack_section(tmp_path / "results.json"))
    assert "No results yet: run `arcade eval quadrotor --condition stack --out" in text


def test_quadrotor_section_gives_the_paired_differences_to_l1_when_the_flagship_flew(tmp_path):
    # The paper's condition renders the same verdicts and paired tables as the stack's:
    # arcade 5 mm better than L1 on each of three seeds, ours 10 mm worse.

    cells = [
        _cell(175, 2.5, m, rmse, 0.0)
        for m, rmse in (("l1", 0.0101), ("arcade", 0.0051), ("ours", 0.0201))
    ]
    path = _write_paired(
        tmp_path,
        cells,
        settings={"trials": 3},
        tuning={"chosen": {"arcade_lambda": 0.9}, "cell": [150.0, 2.0]},
    )
    text = "\n".join(report_quadrotor.quadrotor_section(path))
    assert "`arcade` better in 1, worse in 0, no difference in 0" in text
    assert "`ours` better in 0, worse in 1, no difference in 0" in text
    assert "| 175 | 2.5 | **-5.0 [-5.0, -5.0]** | +10.0 [+10.0, +10.0] |" in text
    assert "| payload (g) | speed (m/s) | arcade | l1 | ours |" in text  # the flagship first
    assert "`ours_paper` keeps Appendix D's values" in text
    # Without the flagship (results stored before it), no paired section and no such words.
    path.write_text(jsonout.dumps({"cells": cells[:1] + cells[2:], "settings": {"trials": 3}}))
    text = "\n".join(report_quadrotor.quadrotor_section(path))
    assert "Against L1" not in text and "`arcade` is the product's controller" not in text


def test_tuning_line_names_the_extended_grids_and_the_knobs_still_on_an_edge():
    tuning = {"extended": {"l1_cutoff": [160.0, 320.0]}, "still_on_edge": ["ours_sigma2"]}
    line = report_quadrotor.grid_edges(tuning)
    assert "l1_cutoff 160, 320" in line and "exhausted): ours_sigma2." in line
    assert "lay on: none; still on an edge (the knob's range exhausted): none." in (
        report_quadrotor.grid_edges({"extended": {}, "still_on_edge": []})
    )
    assert report_quadrotor.grid_edges({"chosen": {}}) == ""  # stored before the extension
