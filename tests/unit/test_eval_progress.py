"""An interrupted quadrotor evaluation continues where it stopped, with the same results."""

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
from fake_runner import SequentialTrials

from benchmarks import quadrotor_closedloop as qc
from benchmarks.eval_progress import FILE, Progress, ProgressMismatch, discard

KEY = {"condition": "ideal", "trials": 2}


def test_parts_come_back_as_they_were_kept(tmp_path):
    done = Progress(tmp_path, KEY)
    value = {"rmse": np.float64(0.25), "settling_s": math.inf, "z": [math.nan, 1], "ok": True}
    done.put("a", value)
    again = Progress(tmp_path, KEY)
    assert len(again) == 1
    back = again.get("a")
    assert back["rmse"] == 0.25 and back["settling_s"] == math.inf and back["ok"] is True
    assert math.isnan(back["z"][0]) and back["z"][1] == 1
    assert again.get("b") is None
    # Every line of the file is strict JSON (no NaN, no Infinity).
    for line in (tmp_path / FILE).read_text().splitlines():
        json.loads(line, parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))


def test_a_line_cut_short_by_a_kill_is_flown_again(tmp_path):
    done = Progress(tmp_path, KEY)
    done.put("a", 1.0)
    done.put("b", 2.0)
    path = tmp_path / FILE
    path.write_text(path.read_text()[:-5])  # the last line cut short
    again = Progress(tmp_path, KEY)
    assert again.get("a") == 1.0 and again.get("b") is None
    again.put("b", 3.0)  # on a line of its own: a third run reads both
    third = Progress(tmp_path, KEY)
    assert third.get("a") == 1.0 and third.get("b") == 3.0 and third.read_back == 2


def test_another_setting_is_refused_and_nothing_is_overwritten(tmp_path):
    Progress(tmp_path, KEY).put("a", 1.0)
    before = (tmp_path / FILE).read_text()
    with pytest.raises(ProgressMismatch, match="another --out"):
        Progress(tmp_path, {**KEY, "trials": 3})
    assert (tmp_path / FILE).read_text() == before
    assert len(Progress(None, KEY)) == 0  # no folder: nothing kept, nothing read
    discard(tmp_path)  # a finished run: the next one flies afresh, with any settings
    assert not (tmp_path / FILE).exists() and len(Progress(tmp_path, {**KEY, "trials": 3})) == 0


class _Killed(Exception):
    pass


def _fake_runner(flown: list, kill_after: int | None = None):
    class FakeRunner(SequentialTrials):
        """Flights whose RMSE depends on the method, the seed and the knobs flown (so that
        the tuning chooses), and whose settling is infinite for L1 (a non-finite number
        kept and read back)."""

        dtype = np.float32

        def __init__(self, models):
            self.models = models

        def fly(self, name, scenario, seed=0, estimated=False, compensate_delay=False):
            if kill_after is not None and len(flown) >= kill_after:
                raise _Killed
            flown.append((name, scenario.payload_g, scenario.speed_mps, seed))
            knobs = sum(abs(math.log(v)) for v in self.models.closedloop.values() if v > 0)
            metrics = {k: 0.0 for k in (*qc.KEYS, *qc.DIAGNOSTIC_KEYS)}
            metrics.update(
                rmse_m=(0.02 if name == "arcade" else 0.03) + 1e-3 * seed + 1e-5 * knobs,
                settling_s=math.inf if name == "l1" else 0.5,
                crashed=False,
            )
            return SimpleNamespace(metrics=metrics, step_ms=np.zeros(3))

    return FakeRunner


def _run(monkeypatch, keep, flown, kill_after=None, progress=lambda msg: None):
    monkeypatch.setattr(qc, "Runner", _fake_runner(flown, kill_after))
    return qc.run_closedloop(
        trials=2,
        methods=("l1", "arcade"),
        cells=[(75.0, 0.5), (175.0, 1.5)],
        models=SimpleNamespace(closedloop={}),
        tuning=True,
        keep=keep,
        progress=progress,
    )


def test_an_interrupted_run_continues_to_the_results_of_one_run(monkeypatch, tmp_path):
    whole: list = []
    expected = _run(monkeypatch, None, whole)
    tuning_flights = len(whole) - 2 * 2 * 2  # 2 cells x 2 methods x 2 trials after them
    # Killed in the second cell, after its first method's flights: the tuning and three
    # cell x method parts are kept.
    first: list = []
    with pytest.raises(_Killed):
        _run(monkeypatch, tmp_path, first, kill_after=tuning_flights + 6)
    second: list = []
    messages = []
    result = _run(monkeypatch, tmp_path, second, progress=messages.append)
    # Only the part cut short is flown again, and the results are those of one run.
    assert second == [("arcade", 175.0, 1.5, s) for s in (0, 1)]
    assert any("continuing the run kept in" in m for m in messages)
    for key in ("cells", "trials", "paired", "tuning", "settings"):
        assert result[key] == expected[key], key
    assert result["cells"][0]["settling_s"] == math.inf
    # The run's time counts the parts read back as they took when flown.
    assert result["continued"]["parts_read_back"] > 3
    assert result["wall_time_s"] >= result["continued"]["their_time_s"] > 0.0
    assert "continued" not in expected
