"""`arcade demo --compare`: the table and the figure from the flights' ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from arcade.demo_compare import COLUMNS, COMPARED, format_compare, plot_errors, run_compare
from arcade.demo_stack import truth_metrics
from arcade_control.knobs import STACK_METHODS


def _truth(offset: float) -> dict[str, np.ndarray]:
    t = np.arange(0.0, 20.0, 0.05)
    ref = {f"ref_p{a}": np.sin(t + i) for i, a in enumerate("xyz")}
    truth = {"t": t, **ref}
    for a in "xyz":
        truth[f"p{a}"] = ref[f"ref_p{a}"] + offset
    thrust = 7.0 + offset * np.where(np.arange(t.size) % 2 == 0, 1.0, -1.0)
    truth.update(u0=thrust, u1=np.zeros_like(t), u2=np.zeros_like(t), u3=np.zeros_like(t))
    return truth


def test_the_compared_methods_are_what_the_stack_flies():
    assert set(COMPARED) == set(STACK_METHODS) and COMPARED[0] == "l1"


def test_metrics_from_the_truth_include_the_thrust_increments():
    m = truth_metrics(_truth(0.01), t_figure=5.0, t_release=None)
    assert m["rmse_m"] == pytest.approx(0.01 * np.sqrt(3))
    assert m["rmse_z_m"] == pytest.approx(0.01)
    assert m["thrust_increment_rms_n"] == pytest.approx(0.02)  # +-0.01 every step


def test_the_table_has_a_row_per_method_and_dashes_where_nothing_applies():
    flights = {
        "l1": {"rmse_m": 0.043, "rmse_z_m": 0.021, "shift_m": 0.07, "settling_s": 0.65,
               "thrust_increment_rms_n": 0.33, "detection_delay_s": None, "crashed": False},
        "arcade": {"rmse_m": 0.040, "rmse_z_m": 0.022, "shift_m": float("nan"),
                   "settling_s": 0.0, "thrust_increment_rms_n": 0.92,
                   "detection_delay_s": 0.1, "crashed": True},
    }  # fmt: skip
    lines = format_compare({"methods": flights}).splitlines()
    assert len(lines) == 3 and all(title in lines[0] for _, title, _ in COLUMNS)
    l1 = lines[1].split()
    assert l1[0] == "l1" and l1[1] == "0.0430" and l1[-1] == "-"
    arcade = lines[2].split()
    assert arcade[3] == "-" and arcade[-1] == "CRASHED" and arcade[-2] == "0.10"


def test_the_figure_is_written_with_and_without_a_release(tmp_path):
    truths = {"l1": _truth(0.02), "arcade": _truth(0.01)}
    plot_errors(tmp_path / "a.png", truths, t_release=10.0)
    plot_errors(tmp_path / "b.png", truths, t_release=None)
    assert (tmp_path / "a.png").stat().st_size > 0 and (tmp_path / "b.png").stat().st_size > 0


def test_compare_flies_each_method_on_the_same_arguments(tmp_path, monkeypatch):
    """Without a stack: ``run_demo`` replaced by one that writes a truth file."""
    import arcade.demo_stack as demo_stack

    flown = []

    def fake_run_demo(out, *, method, **kw):
        flown.append((method, kw))
        out.mkdir(parents=True)
        truth = _truth({"l1": 0.02, "ours": 0.05, "arcade": 0.01}[method])
        names = list(truth)
        np.savetxt(out / "truth.csv", np.column_stack([truth[n] for n in names]),
                   delimiter=",", header=",".join(names), comments="")  # fmt: skip
        settings = {"seed": kw["seed"], "method": method}
        rmse = float(np.mean(truth["px"] - truth["ref_px"]))
        return {"rmse_m": rmse, "crashed": False, "t_release_s": 10.0, "settings": settings}

    monkeypatch.setattr(demo_stack, "run_demo", fake_run_demo)
    result = run_compare(tmp_path, seed=3, payload_g=175.0)
    assert [m for m, _ in flown] == list(COMPARED)
    assert all(kw == {"seed": 3, "payload_g": 175.0} for _, kw in flown)
    assert result["settings"] == {"seed": 3}
    assert list(result["methods"]) == list(COMPARED)
    stored = json.loads((tmp_path / "compare.json").read_text())
    assert stored["methods"]["arcade"]["rmse_m"] == pytest.approx(0.01)
    assert (tmp_path / "compare.png").is_file()
    with pytest.raises(ValueError, match="not gp"):
        run_compare(tmp_path, methods=("l1", "gp"))
