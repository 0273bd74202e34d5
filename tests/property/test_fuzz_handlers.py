"""Fuzzing of every service's message handlers, on the path the services register.

Each service (estimator, adapter, controller, simulator, recorder) is built in-process as
its process builds it (``Service.run``: the command subscription, ``setup``, ``warmup``)
on a :class:`~services.bus.Bus` whose session is an in-process stand-in: ``put`` calls are
captured and the subscription callbacks -- the ``safe_handler``-wrapped decoders the bus
registers -- are called directly with fuzz payloads (``fuzz_payloads.make_payloads``).
The controller's loop body (``Controller.handle``) runs on every state it queued, as its
``main`` would.

Per service ``HANDLER_CASES`` payloads (2 000 by default so that the suite stays fast;
``ARCADE_FUZZ_HANDLER_CASES=10000``, as ``arcade bench fuzz`` sets it, for the full run):
no exception escapes a handler, no callback fails and no ``internal`` reject is
counted, every payload the decoder refuses is counted once per subscription
under the decoder's reason (a valid one is delivered or refused by the subscription's
order check), and everything the service publishes decodes as a valid record -- in
particular every setpoint is finite and within the MPC input bounds. Handlers that run a
JAX step per valid message get fewer valid messages (every n-th batch of that topic has
one) so that the cases stay fast. Edge cases the random search finds only rarely (extreme
but valid commands, states and dropouts) have their own deterministic tests at the end.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from fuzz_payloads import BATCH, fuzz_settings, make_payloads, recipes
from hypothesis import given
from loopback import LoopbackSession

from services import messages as wm
from services import options, runtime
from services.bus import Bus
from services.messages import MessageError, Reason, decode

VEHICLE = "fuzz"
#: Fuzz payloads per service.
HANDLER_CASES = int(os.environ.get("ARCADE_FUZZ_HANDLER_CASES", "2000"))


def build(
    module: Any, cls: type[runtime.Service], out: Path, *argv: str
) -> tuple[runtime.Service, LoopbackSession]:
    """A service wired exactly as ``Service.run`` wires it, on a loopback session."""
    parser = options.common_parser(cls.name, "fuzz")
    extra = getattr(module, "_extra", None)
    if extra is not None:
        extra(parser)
    args = parser.parse_args(["--vehicle", VEHICLE, "--out", str(out), "--x64", *argv])
    service = cls(args)
    session = LoopbackSession(VEHICLE)
    bus = Bus(VEHICLE, cls.name).open(session=session)
    service.bus = bus
    bus.subscribe("command", service._on_command)
    bus.publisher("event")
    service.setup(bus)
    service.warmup()
    return service, session


class Fuzzer:
    """Feeds fuzz payloads to a service and checks, payload by payload, that every one the
    decoder refuses is counted once per subscription under the decoder's reason, and that a
    valid one is either delivered or refused by the subscription's order check -- never
    fails in a callback (the order policy is the service's: it may differ per topic)."""

    def __init__(
        self,
        service: runtime.Service,
        session: LoopbackSession,
        topics: dict[str, int],
        *,
        dims: dict[str, dict[str, int]] | None = None,
        valid_every: dict[str, int] | None = None,
        after_batch: Callable[[], None] | None = None,
    ):
        self.service, self.session = service, session
        self.topics = [t for t, w in topics.items() for _ in range(w)]
        self.decoded: Counter[str] = Counter()  # valid payloads by topic
        self.delivered: Counter[str] = Counter()  # valid and accepted by every subscription
        self.dims = dims or {}
        self.valid_every = valid_every or {}  # topic -> only every n-th batch has a valid one
        self.after_batch = after_batch
        self.cases = 0
        self.batches = 0

    def _counts(self, topic: str) -> Counter[str]:
        return Counter(
            {r: n for (t, r), n in self.service.bus.rejects.by_topic.items() if t == topic}
        )

    def feed(self, recipe: tuple[int, int, int]) -> None:
        topic = self.topics[recipe[2] % len(self.topics)]
        cls = wm.message_type(topic)
        subs = len(self.session.handlers[f"arcade/{VEHICLE}/{topic}"])
        assert subs >= 1, topic
        self.batches += 1
        with_valid = self.batches % self.valid_every.get(topic, 1) == 0
        for payload in make_payloads(cls, recipe, self.dims.get(topic), with_valid):
            try:
                decode(cls, payload)
                reason = None
            except MessageError as e:
                reason = e.reason.value
            before = self._counts(topic)
            self.session.deliver(topic, payload)  # an escaping exception fails the test
            delta = self._counts(topic) - before
            if reason is not None:
                assert delta == Counter({reason: subs}), (topic, reason, delta)
            else:
                assert set(delta) <= {Reason.OUT_OF_ORDER.value, Reason.STALE.value}, (
                    topic,
                    delta,
                    self.service.bus.rejects.by_topic,
                )
                assert sum(delta.values()) <= subs
                self.decoded[topic] += 1
                self.delivered[topic] += not delta
            self.cases += 1
        if self.after_batch is not None:
            self.after_batch()

    def run(self, cases: int = HANDLER_CASES) -> None:
        @fuzz_settings(-(-cases // BATCH))
        @given(recipes)
        def go(recipe: tuple[int, int, int]) -> None:
            self.feed(recipe)

        go()
        assert self.cases >= cases
        by_reason = self.service.bus.rejects.counts
        assert self.service.bus.rejects.failures == {}
        assert Reason.INTERNAL.value not in by_reason, by_reason
        for topic in set(self.topics):
            assert self.delivered[topic] > 0, topic  # the core was reached


def assert_setpoints_safe(
    setpoints: list[wm.Setpoint], u_min: np.ndarray, u_max: np.ndarray
) -> None:
    for sp in setpoints:
        assert np.all(np.isfinite(sp.u)), sp
        assert np.all(sp.u >= u_min) and np.all(sp.u <= u_max), sp.u


# ----------------------------------------------------------------------- services


def test_controller_handlers(tmp_path):
    from services import controller as mod

    svc, session = build(mod, mod.Controller, tmp_path)
    assert svc.learner0 is not None  # the shipped weights: models of this shape are used
    d, l = svc._theta0.shape
    answered: list[wm.State] = []

    def loop_body() -> None:  # Controller.main without the blocking wait
        while not svc._queue.empty():
            s, _arrival = svc._queue.get_nowait()
            svc.handle(s)  # main would turn an exception into a hover setpoint: none here
            answered.append(s)

    fuzz = Fuzzer(
        svc,
        session,
        {"state": 2, "model": 1, "command": 3},
        dims={"model": {"d": d, "l": l}},
        valid_every={"state": 8},
        after_batch=loop_body,
    )
    fuzz.run()
    setpoints = session.outputs("setpoint")
    assert len(setpoints) == len(answered) == fuzz.delivered["state"] > 0
    assert_setpoints_safe(setpoints, svc.u_min, svc.u_max)
    modes = Counter(sp.mode for sp in setpoints)
    assert modes["hover"] > 0 and modes["hover"] < len(setpoints), modes  # both paths ran
    session.outputs("event")  # valid events only


def adapter_loop_body(svc) -> None:
    """The realtime adapter's queue, every state handled in order (its loop,
    :meth:`~services.adapter.Adapter.handle_newest`, would keep only the newest; here each
    one is fuzzed)."""
    while not svc._states.empty():
        svc.on_state(svc._states.get_nowait())


def test_adapter_handlers(tmp_path):
    from services import adapter as mod

    svc, session = build(mod, mod.Adapter, tmp_path)
    assert svc.learner is not None
    fuzz = Fuzzer(
        svc,
        session,
        {"state": 2, "setpoint": 1, "command": 1},
        valid_every={"state": 8},
        after_batch=lambda: adapter_loop_body(svc),
    )
    fuzz.run()
    models = session.outputs("model")
    assert 0 < len(models) <= fuzz.delivered["state"]
    for m in models:
        assert np.all(np.isfinite(m.theta)) and np.all(m.sigma_tot2 >= 0)
    session.outputs("residual")
    session.outputs("event")
    assert svc.stats["steps"] >= 1


def test_estimator_handlers(tmp_path):
    from services import estimator as mod

    svc, session = build(mod, mod.Estimator, tmp_path)
    fuzz = Fuzzer(svc, session, {"mocap": 2, "imu": 1, "command": 1}, valid_every={"imu": 4})
    fuzz.run()
    states = session.outputs("state")
    assert len(states) == svc.stats["states"] > 0
    for s in states:
        assert np.all(np.isfinite(s.x)) and abs(np.linalg.norm(s.q) - 1.0) < 1e-6
    session.outputs("event")


def test_sim_node_handlers(tmp_path):
    from services import sim_node as mod

    svc, session = build(mod, mod.SimNode, tmp_path, "--wait-for", "")
    fuzz = Fuzzer(svc, session, {"setpoint": 3, "command": 1})
    fuzz.run()
    latest = svc._latest
    assert latest is not None
    applied = svc.sim.set_setpoint(latest.u)  # what the next physics step would follow
    assert np.all(np.isfinite(applied))


def test_recorder_handlers(tmp_path):
    from services import recorder as mod

    svc, session = build(mod, mod.Recorder, tmp_path)
    fuzz = Fuzzer(svc, session, dict.fromkeys(wm.TOPICS, 1))
    fuzz.run()
    # The recorder wants everything valid (no order check), out of order or not.
    recorded = {t: fuzz.decoded[t] for t in wm.TOPICS}
    assert svc.stats["messages"] == recorded
    svc.teardown()
    from mcap.reader import make_reader

    with (tmp_path / "bus.mcap").open("rb") as f:
        in_file = Counter(
            ch.topic.rsplit("/", 1)[-1]
            for _, ch, _ in make_reader(f).iter_messages()
            if "/foxglove/" not in ch.topic  # the states drawn for Foxglove besides
        )
    assert in_file == +Counter(recorded)


def test_controller_extreme_but_valid_inputs(tmp_path):
    # Edge values the wire allows, in the order a hostile or broken publisher could send
    # them: a start command with an extreme t0, then states at the limits of every range.
    import time

    from services import controller as mod

    svc, session = build(mod, mod.Controller, tmp_path)
    q_flip = [0.0, 1.0, 0.0, 0.0]  # upside down
    states = [
        np.r_[0, 0, 1.0, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0],
        np.r_[
            wm.MAX_POSITION_M,
            -wm.MAX_POSITION_M,
            0.0,
            [wm.MAX_SPEED_MPS] * 3,
            q_flip,
            [wm.MAX_RATE_RADPS] * 3,
        ],
        np.r_[[0.0] * 6, 0.5, 0.5, 0.5, 0.5, [-wm.MAX_RATE_RADPS] * 3],
    ]
    seq = 0
    for t0 in (1e308, -1e308, 0.0, wm.MAX_STAMP_S, 2**64 - 1):
        seq += 1
        session.deliver(
            "command",
            wm.encode(
                wm.Command(
                    name="start", args={"t0": t0}, stamp=float(seq), seq=seq, src="operator/1"
                )
            ),
        )
        for x in states:
            seq += 1
            now = time.monotonic()
            session.deliver(
                "state",
                wm.encode(wm.State(x=x, stamp=now, meas_stamp=now, seq=seq, src="estimator/1")),
            )
            svc.handle(svc._queue.get_nowait()[0])  # must not raise
    setpoints = session.outputs("setpoint")
    assert len(setpoints) == 5 * len(states)
    assert_setpoints_safe(setpoints, svc.u_min, svc.u_max)
    assert svc.bus.rejects.total == 0


def test_adapter_extreme_but_valid_states(tmp_path):
    # State estimates at the limits of the wire ranges, with the largest variances the wire
    # allows (an estimator predicting through a long dropout): the adapter must keep
    # publishing valid models, never fail in its callback.
    from services import adapter as mod

    svc, session = build(mod, mod.Adapter, tmp_path)
    hover = np.r_[0, 0, 1.0, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0]
    far = np.r_[
        wm.MAX_POSITION_M,
        0.0,
        0.0,
        [wm.MAX_SPEED_MPS] * 3,
        0.0,
        1.0,
        0.0,
        0.0,
        [wm.MAX_RATE_RADPS] * 3,
    ]
    seq = 0
    for x, var in (
        (hover, None),
        (hover, 1e10),
        (hover, wm.MAX_VARIANCE),
        (far, None),
        (far, wm.MAX_VARIANCE),
        (hover, None),
    ):
        seq += 1
        stamp = 0.05 * seq
        cov = None if var is None else np.full(13, var)
        session.deliver(
            "state", wm.encode(wm.State(x=x, cov_diag=cov, stamp=stamp, seq=seq, src="estimator/1"))
        )
        adapter_loop_body(svc)
        session.deliver(
            "setpoint",
            wm.encode(
                wm.Setpoint(
                    u=[5.6, 0.0, 0.0, 0.0], state_seq=seq, stamp=stamp, seq=seq, src="controller/1"
                )
            ),
        )
    assert svc.bus.rejects.counts == {}
    models = session.outputs("model")
    assert len(models) == seq
    session.outputs("residual")


def test_estimator_long_dropout_and_clock_jumps(tmp_path):
    # One mocap frame, then control instants far apart (a long dropout, or a sensor clock
    # that jumped): the prediction's variance grows without bound, yet every state the
    # estimator publishes must be valid and its callback must not fail.
    from services import estimator as mod

    svc, session = build(mod, mod.Estimator, tmp_path)
    session.deliver(
        "mocap",
        wm.encode(
            wm.Mocap(
                position=[0.0, 0.0, 1.0],
                quaternion=[1.0, 0.0, 0.0, 0.0],
                capture_stamp=0.0,
                stamp=0.0,
                seq=1,
                src="sim/1",
            )
        ),
    )
    for seq, stamp in enumerate((0.0, 1.0, 10.0, 100.0, 1e3, 1e4, 1e6, wm.MAX_STAMP_S), 1):
        session.deliver(
            "imu", wm.encode(wm.Imu(gyro=[0.0, 0.0, 0.0], stamp=stamp, seq=seq, src="sim/1"))
        )
    assert svc.bus.rejects.counts == {}
    states = session.outputs("state")  # decoding re-validates every published state
    assert len(states) >= 1 and states[0].stamp == 0.0
