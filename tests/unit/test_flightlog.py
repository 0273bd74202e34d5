"""Flight logs (design §5): CSV round trip and clear errors for unusable logs."""

from __future__ import annotations

import io

import numpy as np
import pytest

from arcade_io.flightlog import LogError, columns, from_arrays, read_log, write_log


def _quad_log(n=50, dt=0.01, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, 13))
    X[:, 6:10] /= np.linalg.norm(X[:, 6:10], axis=1, keepdims=True)
    return from_arrays("quadrotor", np.arange(n) * dt, X, rng.normal(size=(n, 4)))


def _csv(header, rows):
    return io.StringIO(",".join(header) + "\n" + "\n".join(",".join(map(str, r)) for r in rows))


def test_round_trip_is_exact(tmp_path):
    log = _quad_log()
    back = read_log(write_log(tmp_path / "log.csv", log), "quadrotor")
    np.testing.assert_array_equal(back.t, log.t)
    np.testing.assert_array_equal(back.X, log.X)
    np.testing.assert_array_equal(back.U, log.U)
    assert back.dt == pytest.approx(0.01)


def test_extra_columns_and_any_order_are_accepted():
    n = 30
    head = ["thetadot", "extra", "u", "t", "x", "xdot", "theta"]
    rows = [[0.1 * k, 99, -k, 0.05 * k, k, 2 * k, 3 * k] for k in range(n)]
    log = read_log(_csv(head, rows), "cartpole")
    np.testing.assert_allclose(log.X[3], [3, 6, 9, 0.3])
    np.testing.assert_allclose(log.U[:, 0], -np.arange(n))
    assert log.dt == pytest.approx(0.05)


def test_missing_columns_are_named():
    head = [c for c in columns("quadrotor") if c not in ("qw", "u2")]
    rows = [[0.01 * k] + [0.0] * (len(head) - 1) for k in range(30)]
    with pytest.raises(LogError, match=r"missing column\(s\) qw, u2"):
        read_log(_csv(head, rows), "quadrotor")


def test_a_file_with_none_of_the_columns_is_not_a_flight_log():
    rows = [[str(k), "x"] for k in range(30)]
    with pytest.raises(LogError, match=r"not a quadrotor flight log \(columns t, px, ") as e:
        read_log(_csv(["name", "value"], rows), "quadrotor")
    assert "missing" not in str(e.value)  # the columns are named once


def test_non_constant_rate_is_rejected():
    t = np.arange(40) * 0.01
    t[20:] += 0.004  # one 14 ms step
    head = list(columns("cartpole"))
    rows = [[tk, 0, 0, 0, 0, 0] for tk in t]
    with pytest.raises(LogError, match="sample rate is not constant"):
        read_log(_csv(head, rows), "cartpole")
    rows[5][0] = rows[4][0]
    with pytest.raises(LogError, match="time does not increase at row 7"):
        read_log(_csv(head, rows), "cartpole")


@pytest.mark.parametrize(("value", "message"), [("nan", "non-finite"), ("abc", "not a number")])
def test_bad_values_are_located(value, message):
    head = list(columns("cartpole"))
    rows = [[0.05 * k, 0, 0, 0, 0, 0] for k in range(30)]
    rows[12][3] = value
    with pytest.raises(LogError, match=rf"{message}.*theta.*row 14|row 14.*theta.*{message}"):
        read_log(_csv(head, rows), "cartpole")


def test_too_short_and_bad_quaternion():
    head = list(columns("cartpole"))
    with pytest.raises(LogError, match="at least"):
        read_log(_csv(head, [[0.05 * k, 0, 0, 0, 0, 0] for k in range(5)]), "cartpole")
    log = _quad_log()
    X = log.X.copy()
    X[7, 6:10] = 0.0
    with pytest.raises(LogError, match="unit quaternion"):
        from_arrays("quadrotor", log.t, X, log.U)
    with pytest.raises(ValueError, match="unknown system"):
        columns("boat")


def test_quaternion_sign_flips_are_removed():
    # A tracker that keeps w >= 0 flips the sign when a yaw turn passes 180 degrees; another
    # sends -q at random. Both must read as the continuous attitude the models expect.
    n = 200
    yaw = np.linspace(0.0, 1.5 * 2 * np.pi, n)
    q = np.stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)], axis=1)
    canonical = q * np.where(q[:, :1] < 0, -1.0, 1.0)
    rng = np.random.default_rng(1)
    scrambled = q * rng.choice([-1.0, 1.0], size=(n, 1))
    X = np.zeros((n, 13))
    U = np.zeros((n, 4))
    for source in (canonical, scrambled):
        X[:, 6:10] = source
        log = from_arrays("quadrotor", np.arange(n) * 0.01, X, U)
        np.testing.assert_allclose(log.X[:, 6:10], q, atol=1e-15)
        assert np.all(np.sum(log.X[1:, 6:10] * log.X[:-1, 6:10], axis=1) > 0)


# ------------------------------------------------------------- the recorder service


class _RecorderBus:
    """What the recorder needs of a bus (its subscriptions are called directly)."""

    def key(self, topic):
        return f"arcade/test/{topic}"

    def subscribe(self, topic, callback, check_order=True):
        return None


def _recorder(tmp_path):
    import argparse

    from services.recorder import Recorder

    rec = Recorder(argparse.Namespace(out=tmp_path, incarnation=0))
    rec.setup(_RecorderBus())
    return rec


def _pair(stamp):
    from services.messages import Setpoint, State

    x = np.r_[0.0, 0.0, 1.0 + stamp, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    return State(x=x, stamp=stamp), Setpoint(u=[5.0, 0, 0, 0], state_seq=0, stamp=stamp)


def test_recorder_writes_the_flight_log_while_flying(tmp_path):
    """Rows reach the file during the flight (a crash keeps them), in stamp order, and the
    finished log reads back whole."""
    rec = _recorder(tmp_path)
    stamps = 100.0 + np.arange(60) * 0.05
    for k, t in enumerate(stamps):
        s, sp = _pair(float(t))
        if k == 10:  # a setpoint before its state: paired when the state comes
            rec.record("setpoint", sp)
            rec.record("state", s)
        else:
            rec.record("state", s)
            rec.record("setpoint", sp)
    written = read_log(tmp_path / "flight_log.csv", "quadrotor")  # before any teardown
    assert len(written.t) >= 20 and written.t[0] == 0.0  # flushed once a second (stamps)
    rec.teardown()
    log = read_log(tmp_path / "flight_log.csv", "quadrotor")
    np.testing.assert_allclose(log.t, stamps - stamps[0], atol=1e-9)
    np.testing.assert_allclose(log.X[:, 2], 1.0 + stamps)
    assert rec.stats["rows"] == 60 and rec.stats["late_rows"] == 0


def test_recorder_keeps_the_newest_unpaired_setpoints_and_counts_the_rest(tmp_path):
    from services.recorder import MAX_UNPAIRED

    rec = _recorder(tmp_path)
    stamps = 100.0 + np.arange(MAX_UNPAIRED + 20) * 0.05
    for t in stamps:  # setpoints whose states are not (yet) there
        rec.record("setpoint", _pair(float(t))[1])
    assert rec.stats["unpaired_setpoints"] == 20
    for t in stamps[-30:]:  # the newest states come after all
        rec.record("state", _pair(float(t))[0])
    rec.teardown()
    assert rec.stats["rows"] == 30  # their setpoints were still waiting
    assert len(read_log(tmp_path / "flight_log.csv", "quadrotor").t) == 30


def _messages_on_disk(path) -> int:
    """Messages a linear scan reads from an MCAP file as it is on the disk now (no summary
    yet: what a killed recorder leaves), up to where it ends."""
    from mcap.exceptions import McapError
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    n, foxglove = 0, set()  # the bus's own messages, not their Foxglove forms
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f, emit_chunks=False).records:
                if isinstance(record, Channel) and "/foxglove/" in record.topic:
                    foxglove.add(record.id)
                n += isinstance(record, Message) and record.channel_id not in foxglove
        except (McapError, EOFError):  # the end of what was written
            pass
    return n


def test_a_killed_recorder_loses_at_most_the_last_second_of_the_bus_log(tmp_path):
    from services.recorder import MCAP_FLUSH_S

    assert MCAP_FLUSH_S == 1.0
    rec = _recorder(tmp_path)
    clock = [0.0]
    rec._clock, rec._flushed = (lambda: clock[0]), 0.0
    for k in range(60):  # 3.5 s of messages, far less than the writer's 1 MiB chunk
        clock[0] = k * 0.06
        s, sp = _pair(100.0 + k * 0.05)
        rec.record("state", s)
        rec.record("setpoint", sp)
    # Not torn down (a kill): the flushed chunks are on the disk, the open one is not.
    # Flushes at 1.02, 2.04 and 3.06 s: up to the state of pair 51.
    assert _messages_on_disk(tmp_path / "bus.mcap") == 2 * 51 + 1
    rec.teardown()
    assert _messages_on_disk(tmp_path / "bus.mcap") == 120


class _EventBus:
    """The bus a service publishes its events on: every record kept."""

    def __init__(self):
        self.sent = []

    def put(self, record):
        self.sent.append(record)


def _full_disk_recorder(tmp_path, full: str):
    """A recorder whose ``full`` file is /dev/full: every write to it fails with ENOSPC,
    as on a full disk (the kernel's own device, no mocking)."""
    (tmp_path / full).symlink_to("/dev/full")
    rec = _recorder(tmp_path)
    rec.bus = _EventBus()
    return rec


def _fly(rec, n: int, t0: float = 100.0) -> None:
    for k in range(n):
        s, sp = _pair(t0 + k * 0.05)
        rec.record("state", s)
        rec.record("setpoint", sp)


def test_a_full_disk_stops_the_bus_log_not_the_recorder_nor_the_flight_log(tmp_path):
    import errno

    rec = _full_disk_recorder(tmp_path, "bus.mcap")
    _fly(rec, 3000)  # the MCAP writer writes its first chunk (1 MiB) before this ends
    rec.teardown()  # never raises
    (fault,) = [e for e in rec.bus.sent if e.kind == "fault"]  # said once
    assert fault.severity == "error" and fault.data["errno"] == errno.ENOSPC
    assert "bus.mcap" in fault.text and "No space left on device" in fault.text
    assert rec.stats["unrecorded"] > 0 and "bus.mcap" in next(iter(rec.stats["recording_errors"]))
    assert sum(rec.stats["messages"].values()) + rec.stats["unrecorded"] == 6000
    # The flight log, on a disk with space, is whole.
    log = read_log(tmp_path / "flight_log.csv", "quadrotor")
    assert len(log.t) == 3000 and rec.stats["unwritten_rows"] == 0


def test_a_full_disk_stops_the_flight_log_not_the_bus_log(tmp_path):
    from mcap.reader import make_reader

    rec = _full_disk_recorder(tmp_path, "flight_log.csv")
    _fly(rec, 400)  # rows are flushed once a second of stamps: the first flush fails
    rec.teardown()
    (fault,) = [e for e in rec.bus.sent if e.kind == "fault"]
    assert "flight_log.csv" in fault.text
    assert rec.stats["rows"] + rec.stats["unwritten_rows"] == 400
    assert rec.stats["unwritten_rows"] > 0 and rec.stats["unrecorded"] == 0
    with open(tmp_path / "bus.mcap", "rb") as f:  # finished and readable, every message in it
        bus = make_reader(f).iter_messages()
        assert sum(1 for _, c, _ in bus if "/foxglove/" not in c.topic) == 800
