"""The service life cycle (``Service.run``) and its statistics, on an in-process session:
warm-up interrupted by a stop, a failing teardown, per-topic stream and reject counts,
sequence numbers of records that are not sent, the launcher's parent watch and the
``--help`` of ``python -m services``."""

from __future__ import annotations

import argparse
import gc
import json
import logging
import os
import select
import signal
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from loopback import LoopbackSession

from services import options, runtime
from services.bus import Bus
from services.messages import Command, MessageError, Mocap, Reason, State, encode

#: Environment of child interpreters that import the project (from any working directory).
CHILD_ENV = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))


def args(out: Path | None) -> argparse.Namespace:
    return options.common_parser("probe", "test").parse_args(
        ["--vehicle", "test"] + ([] if out is None else ["--out", str(out)])
    )


class Probe(runtime.Service):
    """A service on an in-process session that records its life cycle."""

    name = "probe"

    def __init__(self, a: argparse.Namespace, **hooks: Callable[[Probe], None]):
        super().__init__(a)
        self.session = LoopbackSession()
        self.calls: list[str] = []
        self.hooks = hooks

    def _open_bus(self) -> Bus:
        return Bus("test", self.name).open(session=self.session)

    def _hook(self, name: str) -> None:
        self.calls.append(name)
        if name in self.hooks:
            self.hooks[name](self)

    def setup(self, bus: Bus) -> None:
        self._hook("setup")

    def warmup(self) -> None:
        self._hook("warmup")

    def ready(self) -> None:
        self._hook("ready")

    def main(self) -> None:
        self._hook("main")

    def teardown(self) -> None:
        self._hook("teardown")


@pytest.fixture(autouse=True)
def _restore_signals():
    """``Service.run`` installs SIGINT/SIGTERM handlers: give pytest its own back."""
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    yield
    for s, h in saved.items():
        signal.signal(s, h)


def test_a_stop_during_warm_up_never_announces_ready(tmp_path):
    probe = Probe(args(tmp_path), warmup=lambda p: p.stop.set())  # e.g. SIGTERM meanwhile
    assert probe.run() == 0
    assert probe.calls == ["setup", "warmup"]  # no ready(), main() or teardown()
    # No liveliness token either: only the one naming the bus session (declared at open).
    assert probe.session.tokens == ["arcade/test/alive/probe/f0220000"]
    assert (tmp_path / "stats" / "probe.json").is_file()


def test_a_failing_teardown_still_writes_the_statistics(tmp_path):
    def fail(p: Probe) -> None:
        p.stats["teardown_started"] = True
        raise OSError("disk full")

    probe = Probe(args(tmp_path), teardown=fail)
    before = list(gc.callbacks)
    assert probe.run() == 1  # the failure is the exit code, after the rest of the shutdown
    assert probe.calls == ["setup", "warmup", "ready", "main", "teardown"]
    assert probe.session.tokens == ["arcade/test/alive/probe/f0220000", "arcade/test/alive/probe"]
    stats = json.loads((tmp_path / "stats" / "probe.json").read_text())
    assert stats["teardown_started"] is True and "gc_pauses" in stats
    assert gc.callbacks == before  # the pause hook was removed too


def test_statistics_that_cannot_be_written_are_one_error_line_and_the_exit_code(tmp_path, caplog):
    (tmp_path / "stats").write_text("")  # a file where the folder goes: no file in it
    probe = Probe(args(tmp_path))
    with caplog.at_level(logging.ERROR, logger="arcade.probe"):
        assert probe.run() == 1
    assert probe.calls == ["setup", "warmup", "ready", "main", "teardown"]
    (line,) = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert line.getMessage().startswith(f"cannot write {tmp_path / 'stats' / 'probe.json'}: ")
    assert line.getMessage().endswith("this run's statistics of probe are lost")
    assert line.exc_info is None  # no traceback: the reason is the line


def test_statistics_that_cannot_be_written_do_not_hide_a_failing_teardown(tmp_path, caplog):
    def fail(p: Probe) -> None:
        raise ValueError("teardown broke")

    (tmp_path / "stats").write_text("")
    probe = Probe(args(tmp_path), teardown=fail)
    with caplog.at_level(logging.ERROR, logger="arcade.probe"):
        assert probe.run() == 1
    stats_line, failed = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert "statistics of probe are lost" in stats_line.getMessage()
    assert failed.getMessage() == "probe failed" and failed.exc_info[0] is ValueError


def _state(seq: int, stamp: float, src: str = "estimator/1") -> bytes:
    x = np.r_[0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    return encode(State(x=x, stamp=stamp, seq=seq, src=src))


def _mocap(seq: int, stamp: float, src: str = "sim/1") -> bytes:
    q = [1.0, 0.0, 0.0, 0.0]
    return encode(
        Mocap(position=[0, 0, 1], quaternion=q, capture_stamp=stamp, stamp=stamp, seq=seq, src=src)
    )


def test_statistics_report_streams_rejects_by_topic_and_callback_failures(tmp_path):
    def fail_on_third(s: Any) -> None:
        if s.seq == 3:
            raise RuntimeError("bug")

    def setup(p: Probe) -> None:
        p.bus.subscribe("state", fail_on_third)
        runtime.subscribe_ordered(p.bus, {"mocap": lambda m: None}, seq_only=("mocap",))

    def traffic(p: Probe) -> None:
        for seq in (1, 3, 6):  # 2, 4 and 5 lost on the way
            p.session.deliver("state", _state(seq, float(seq)))
        p.session.deliver("state", b"\xc1")
        for seq in (1, 2, 5, 4):  # 3 and 4 lost (a late 4 is out of order)
            p.session.deliver("mocap", _mocap(seq, 1.0))

    probe = Probe(args(tmp_path), setup=setup, main=traffic)
    assert probe.run() == 0
    stats = json.loads((tmp_path / "stats" / "probe.json").read_text())
    assert stats["streams"]["state"] == {"accepted": 3, "gaps": 3, "reanchored": 0}
    assert stats["streams"]["mocap"] == {"accepted": 3, "gaps": 2}
    assert stats["rejects"] == {"not_msgpack": 1, "out_of_order": 1}
    assert stats["rejects_by_topic"] == {
        "mocap": {"out_of_order": 1},
        "state": {"not_msgpack": 1},
    }
    assert stats["callback_failures"] == {"state": 1}


def test_a_record_that_is_not_sent_keeps_its_sequence_number_free():
    session = LoopbackSession()
    bus = Bus("test", "probe").open(session=session)
    pub = bus.publisher("command")
    assert pub.put(Command(name="arm", stamp=1.0)) == 1
    huge = Command(name="arm", args={f"k{i}": "x" * 256 for i in range(32)}, stamp=2.0)
    with pytest.raises(MessageError) as info:
        pub.put(huge)
    assert info.value.reason is Reason.OVERSIZE
    assert pub.put(Command(name="disarm", stamp=3.0)) == 2 and pub.seq == 2
    assert len(session.published["arcade/test/command"]) == 2


def test_services_help_lists_every_service(capsys):
    from services import __main__ as cli

    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in cli.SERVICES:
        assert any(line.split()[:1] == [name] for line in out.splitlines()), name
    assert cli.main([]) == 2


def test_service_help_shows_every_default():
    from services import estimator, px4_bridge

    for module, sample in ((estimator, "(default: 0.25)"), (px4_bridge, "(default: 0.3)")):
        parser = options.common_parser("x", "test")
        module._extra(parser)  # the service's own options, on the same parser
        formatter = parser._get_formatter()
        for action in parser._actions:
            if action.help is argparse.SUPPRESS or action.default is argparse.SUPPRESS:
                continue  # hidden options; -h
            assert "default" in formatter._get_help_string(action), action.option_strings
        text = " ".join(parser.format_help().split())
        assert sample in text and "(default: INFO)" in text and "(default: 20.0)" in text


def test_a_service_stops_when_its_launcher_dies():
    """The parent watch of ``Service.run``: a service whose launcher was killed (no
    shutdown reached it; its own session hides the terminal's Ctrl-C) stops by itself."""
    child = textwrap.dedent(
        """
        import sys, threading
        from services import runtime
        stop = threading.Event()
        runtime.watch_parent(stop, interval=0.05)
        print("watching", flush=True)
        sys.exit(0 if stop.wait(30.0) else 3)
        """
    )
    launcher = textwrap.dedent(
        f"""
        import subprocess, sys
        p = subprocess.Popen([sys.executable, "-c", {child!r}], start_new_session=True,
                             stdout=subprocess.PIPE, text=True)
        assert p.stdout.readline().strip() == "watching"
        print(p.pid, flush=True)
        input()  # until killed
        """
    )
    parent = subprocess.Popen(
        [sys.executable, "-c", launcher],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=CHILD_ENV,
    )
    pid = int(parent.stdout.readline())
    service = os.pidfd_open(pid)  # not our child: its exit is waited for on a pidfd
    try:
        parent.kill()
        parent.wait()
        exited, _, _ = select.select([service], [], [], 10.0)
        if not exited:
            os.kill(pid, signal.SIGKILL)
        assert exited, "the service outlived its launcher"
    finally:
        os.close(service)


# ------------------------------------------------------------- the simulator service


def test_a_backward_clock_jump_past_the_mission_start_is_refused_when_parsed(capsys):
    from services import sim_node
    from simulator.mocap_faults import MocapFault

    with pytest.raises(ValueError, match="offset -2 s goes back past the start"):
        MocapFault.parse("clockjump@1+1,offset=-2")
    assert MocapFault.parse("clockjump@2+1,offset=-1.5").offset == -1.5
    parser = options.common_parser("sim", "test")
    sim_node._extra(parser)
    with pytest.raises(SystemExit):
        parser.parse_args(["--mocap-fault", "clockjump@1,offset=-2"])
    assert "offset -2 s goes back past the start" in capsys.readouterr().err
    (fault,) = parser.parse_args(["--mocap-fault", "dropout@1+0.5"]).mocap_fault
    assert fault == MocapFault("dropout", 1.0, 0.5)


class DivergingSim:
    """A simulator whose physics turns non-finite in its first step."""

    setpoint = np.zeros(4)
    payload_attached = False
    time = 0.0

    def __init__(self) -> None:
        self.x = np.r_[0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        self.mocap = self
        self.gyro = SimpleNamespace(read=lambda _until: [])

    def state(self) -> np.ndarray:
        return self.x.copy()

    def read(self, _until: float) -> list:
        return self.read_mocap()

    def read_mocap(self) -> list:
        from simulator.mocap import MocapSample

        return [MocapSample(self.time, self.time, self.x[:3], self.x[6:10])]

    def read_gyro(self) -> list:
        return []

    def set_setpoint(self, u: np.ndarray) -> np.ndarray:
        return np.asarray(u)

    def step(self, dt: float) -> None:
        self.time += dt
        self.x[:] = np.nan


def test_non_finite_physics_is_reported_as_a_crash_not_an_exception(tmp_path):
    """Lockstep: the step that diverges ends the flight with the crash event; no Mocap or
    Imu is built from the non-finite state (that raised out of the loop)."""
    import threading

    from services import sim_node
    from services.messages import Setpoint
    from services.sim_mocap import MocapStream
    from services.sim_node import SimNode

    parser = options.common_parser("sim", "test")
    sim_node._extra(parser)
    node = SimNode(parser.parse_args(["--lockstep", "--vehicle", "test"]))
    session = LoopbackSession()
    node.bus = Bus("test", "sim").open(session=session)
    node.sim = DivergingSim()
    node.n_steps, node.period, node.k_release = 5, 0.05, -1
    node._release_at, node._mission0, node._gyro = np.inf, 0.0, np.zeros(3)
    node._ref_t, node._ref_p = np.array([0.0, 10.0]), np.array([[0.0, 0.0, 1.0]] * 2)
    node._cond, node._tick_wall, node._answered = threading.Condition(), {}, set()
    node._hold, node._answered_run, node._t_last_sp, node.truth = None, 0, 0.0, None
    node._setpoints = {
        k * 0.05: Setpoint(u=[1.0, 0, 0, 0], state_seq=0, stamp=k * 0.05) for k in range(5)
    }
    node.stats = {"steps": 0, "timeouts": 0, "crashed": False}
    node.mocap_out, node.pub_imu = MocapStream(node.bus, [], 0), node.bus.publisher("imu")
    node._lockstep()  # raised MessageError (non-finite position) before
    assert node.stats["crashed"] is True and node.stats["steps"] == 1
    events = session.published["arcade/test/event"]
    assert len(events) == 1 and b"vehicle crashed" in events[0]


# ----------------------------------------------------------------------- the launcher

#: A service that answers SIGINT by interrupting its launcher (a second Ctrl-C arriving
#: during the stop, deterministically) and otherwise runs on.
_INTERRUPTS_BACK = (
    "import os, signal, sys\n"
    "signal.signal(signal.SIGINT, lambda *_: os.kill(os.getppid(), signal.SIGINT))\n"
    "print('up', flush=True)\n"
    "sys.stdin.read()\n"
)
#: A service that ignores SIGINT (a stuck one).
_STUCK = (
    "import signal, sys\n"
    "signal.signal(signal.SIGINT, signal.SIG_IGN)\n"
    "print('up', flush=True)\n"
    "sys.stdin.read()\n"
)


def test_a_second_interrupt_during_stop_still_stops_every_service():
    import threading

    from deploy.launcher import Stack

    procs = {
        name: subprocess.Popen(
            [sys.executable, "-c", code],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        for name, code in (("first", _INTERRUPTS_BACK), ("second", _STUCK))
    }
    # Ctrl-C raises KeyboardInterrupt, as in a terminal (a shell running the tests in
    # the background starts them with SIGINT ignored).
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        for p in procs.values():
            assert p.stdout.readline().strip() == "up"
        stack = Stack.__new__(Stack)
        stack._stopping, stack._bus, stack.procs = threading.Event(), None, procs
        stack.config = SimpleNamespace(stop_order=("first", "second"))
        with pytest.raises(KeyboardInterrupt):  # delivered once everything is stopped
            stack.stop(grace=30.0)  # the interrupt cuts the 30 s grace short
        assert all(p.poll() is not None for p in procs.values())
        assert procs["first"].returncode == procs["second"].returncode == -signal.SIGTERM
    finally:
        signal.signal(signal.SIGINT, previous)
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()


def test_the_demo_turns_sigterm_into_an_interrupt_while_it_flies():
    from deploy.launcher import sigterm_interrupts

    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt), sigterm_interrupts():  # the stack's exit stops all
        signal.raise_signal(signal.SIGTERM)
    assert signal.getsignal(signal.SIGTERM) is before


def test_a_service_that_has_shut_down_ignores_late_stop_signals():
    """The launcher's SIGINT may race a vehicle process that ends its flight by itself:
    once the service has shut down, the signal must not kill it (the interpreter resets a
    Python-handled signal to its default action as it exits), so its exit code stands."""
    code = textwrap.dedent(
        """
        import signal, sys
        from services import runtime

        class Stub:
            "a service that has run"
            name = "stub"

            def __init__(self, args):
                pass

            def run(self):
                signal.signal(signal.SIGINT, lambda *_: None)  # as Service.run installs
                return 3

        code = runtime.main_for(Stub, [])
        print(signal.getsignal(signal.SIGINT) is signal.SIG_IGN,
              signal.getsignal(signal.SIGTERM) is signal.SIG_IGN)
        sys.exit(code)
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )
    assert done.stdout.split() == ["True", "True"], done.stderr
    assert done.returncode == 3


def test_a_service_hung_while_stopping_dumps_its_stacks_before_it_is_terminated():
    import threading

    from deploy.processes import end_process

    code = textwrap.dedent(
        """
        import signal, sys, time
        from services import runtime

        class Stub:
            "a service that ignores its stop request"
            name = "stub"

            def __init__(self, args):
                pass

            def run(self):
                signal.signal(signal.SIGINT, lambda *_: None)
                print("up", flush=True)
                while True:
                    time.sleep(0.01)

        sys.exit(runtime.main_for(Stub, []))
        """
    )
    p = subprocess.Popen(
        [sys.executable, "-c", code],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=CHILD_ENV,
        start_new_session=True,
    )
    try:
        assert p.stdout.readline().strip() == "up"
        end_process(p, grace=0.2, hurry=threading.Event())
        assert p.returncode == -signal.SIGTERM
        err = p.stderr.read()
        assert "most recent call first" in err and "in run" in err, err
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


def test_a_stop_signal_while_the_main_thread_holds_the_event_lock_does_not_deadlock():
    # The launcher's SIGINT can land while a service's main thread is inside its own
    # stop.set() (a flight that ended by itself) or stop.wait(): the handler must not
    # take the event's lock on that same thread. In a child process: the old handler
    # hung there for good.
    code = textwrap.dedent(
        """
        import signal, threading
        from arcade_io import signals
        stop = threading.Event()
        signal.signal(signal.SIGINT, lambda *_: signals.set_from_handler(stop))
        with stop._cond:  # where stop.set() and stop.wait() hold it
            signal.raise_signal(signal.SIGINT)  # the handler runs here
        print(stop.wait(5.0), flush=True)
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=CHILD_ENV, timeout=30
    )
    assert out.returncode == 0 and out.stdout.strip() == "True", out
