"""What the host did with the machine's CPUs: steal, and intervals of slow execution."""

import pytest

from arcade_io import hostcpu


def test_steal_is_read_from_the_cpu_line(tmp_path):
    stat = tmp_path / "stat"
    stat.write_text("cpu  10 0 5 100 0 0 0 250 0 0\ncpu0 5 0 2 50 0 0 0 125 0 0\n")
    assert hostcpu.steal_s(str(stat)) == pytest.approx(250 / hostcpu.os.sysconf("SC_CLK_TCK"))
    stat.write_text("intr 1 2 3\n")
    assert hostcpu.steal_s(str(stat)) is None
    assert hostcpu.steal_s(str(tmp_path / "missing")) is None


def test_slow_units_are_runs_of_consecutive_slow_units_only():
    starts = [float(i) for i in range(12)]
    durations = [0.1] * 12
    durations[2] = 1.0  # one interrupted unit: not a slowdown
    durations[5:8] = [0.5, 2.0, 0.4]  # a sustained one
    durations[10] = 0.31  # slow by a hair, alone
    assert hostcpu.slow_units(starts, durations, factor=3.0) == [[5.0, 7.4]]
    assert hostcpu.slow_units(starts, durations, factor=3.0, min_units=1) == [
        [2.0, 3.0],
        [5.0, 7.4],
        [10.0, 10.31],
    ]
    assert hostcpu.slow_units([], [], factor=3.0) == []


def test_intervals_merge_and_overlap():
    merged = hostcpu.merge_intervals([[5.0, 6.0], [1.0, 2.0], [1.5, 3.0], [6.0, 7.0]])
    assert merged == [[1.0, 3.0], [5.0, 7.0]]
    assert hostcpu.overlaps(merged, 2.5, 2.6)
    assert hostcpu.overlaps(merged, 3.5, 5.0)  # touches the second one's start
    assert not hostcpu.overlaps(merged, 3.1, 4.9)
    assert not hostcpu.overlaps(merged, 7.1, 8.0)
    assert not hostcpu.overlaps([], 0.0, 1.0)


def test_the_probe_runs_on_every_cpu_and_reports_what_it_saw(tmp_path):
    with hostcpu.SlowdownProbe(tmp_path, period_s=0.005) as probe:
        pass
    assert probe.summary["cpus"] == len(hostcpu.os.sched_getaffinity(0))
    assert all(ms > 0.0 for ms in probe.summary["unit_ms"])
    assert probe.episodes == sorted(probe.episodes)
    assert all(a <= b for a, b in probe.episodes)


def test_what_the_watched_block_raises_goes_on(tmp_path):
    with pytest.raises(KeyError, match="flight"), hostcpu.SlowdownProbe(tmp_path):
        raise KeyError("flight")
    assert hostcpu.usual_duration([]) == 0.0
    assert hostcpu.usual_duration([5.0, 1.0, 2.0, 3.0, 4.0]) == 2.0
