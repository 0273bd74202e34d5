"""Files are written whole or not at all (arcade_io.atomicfile)."""

from __future__ import annotations

import dataclasses
import os
import stat

import numpy as np
import pytest

from arcade_io import atomicfile, flightlog


def _leftovers(directory):
    return sorted(p.name for p in directory.iterdir() if p.name.endswith(".tmp"))


def test_text_and_bytes_round_trip_and_create_the_parent(tmp_path):
    text = tmp_path / "a" / "b" / "result.json"
    assert atomicfile.write_text(text, '{"x": 1}\n') == text
    assert text.read_text() == '{"x": 1}\n'
    data = tmp_path / "w.bin"
    atomicfile.write_bytes(data, b"\x00\x01")
    assert data.read_bytes() == b"\x00\x01"
    assert _leftovers(tmp_path) == [] and _leftovers(text.parent) == []


def test_a_failure_mid_write_leaves_the_previous_file_and_no_temporary(tmp_path):
    path = tmp_path / "metrics.json"
    path.write_text("previous")
    with pytest.raises(RuntimeError, match="disk full"), atomicfile.atomic_open(path) as f:
        f.write("half of the new")
        raise RuntimeError("disk full")
    assert path.read_text() == "previous"
    assert _leftovers(tmp_path) == []


def test_the_target_is_not_touched_until_the_block_ends(tmp_path):
    path = tmp_path / "stats.json"
    path.write_text("old")
    with atomicfile.atomic_open(path) as f:
        f.write("new")
        f.flush()
        assert path.read_text() == "old"  # a reader meanwhile sees the old file whole
        assert len(_leftovers(tmp_path)) == 1
    assert path.read_text() == "new"
    assert _leftovers(tmp_path) == []


def test_the_new_file_gets_the_permissions_of_a_plain_open(tmp_path):
    plain = tmp_path / "plain"
    plain.write_text("x")
    written = atomicfile.write_text(tmp_path / "atomic", "x")
    assert stat.S_IMODE(os.stat(written).st_mode) == stat.S_IMODE(os.stat(plain).st_mode)


def test_binary_writers_such_as_numpy_can_stream_into_it(tmp_path):
    path = tmp_path / "beam.npz"
    with atomicfile.atomic_open(path, "wb") as f:
        np.savez(f, a=np.arange(3.0))
    with np.load(path) as z:
        np.testing.assert_array_equal(z["a"], [0.0, 1.0, 2.0])


def test_only_write_modes_are_accepted(tmp_path):
    with pytest.raises(ValueError, match="mode"), atomicfile.atomic_open(tmp_path / "x", "a"):
        pass


def test_a_bad_open_argument_closes_the_descriptor_and_removes_the_temporary(tmp_path):
    opened = len(os.listdir("/proc/self/fd"))
    with pytest.raises(LookupError), atomicfile.atomic_open(tmp_path / "x", encoding="nope"):
        pass
    assert len(os.listdir("/proc/self/fd")) == opened
    assert _leftovers(tmp_path) == []


def test_a_flight_log_that_fails_mid_write_keeps_the_previous_log(tmp_path, monkeypatch):
    path = tmp_path / "flight.csv"
    log = flightlog.FlightLog(
        system="cartpole", t=np.arange(3) * 0.02, X=np.zeros((3, 4)), U=np.zeros((3, 1))
    )
    flightlog.write_log(path, log)
    before = path.read_text()
    bad = dataclasses.replace(log, X=np.ones((3, 4)))

    def boom(*_):
        raise OSError("No space left on device")

    monkeypatch.setattr(flightlog.csv, "writer", lambda f: type("W", (), {"writerow": boom})())
    with pytest.raises(OSError, match="No space"):
        flightlog.write_log(path, bad)
    assert path.read_text() == before
    assert _leftovers(tmp_path) == []


def test_a_figure_is_saved_in_the_format_its_suffix_names(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    path = atomicfile.save_figure(fig, tmp_path / "plot.png", dpi=50)
    plt.close(fig)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert _leftovers(tmp_path) == []


def test_fsync_is_skipped_on_request_only(tmp_path, monkeypatch):
    synced = []
    monkeypatch.setattr(atomicfile.os, "fsync", lambda fd: synced.append(fd))
    atomicfile.write_text(tmp_path / "a", "x")
    assert len(synced) == 1
    with atomicfile.atomic_open(tmp_path / "b", "wb", fsync=False) as f:
        f.write(b"y")
    assert len(synced) == 1 and (tmp_path / "b").read_bytes() == b"y"
