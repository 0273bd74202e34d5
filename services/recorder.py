"""Recorder service: every bus message to a replayable MCAP log, plus the CSV flight log.

``<out>/bus.mcap``: one channel per topic (``arcade/<vehicle>/<topic>``), messages as JSON
(the wire map of :mod:`services.messages`: schema name, version, ``seq``, ``stamp``, fields)
with a JSON Schema per record type, so Foxglove Studio opens it directly. ``log_time`` is
the receive time (``time.time_ns()``), ``publish_time`` the message ``stamp`` in ns.

The same file also holds the flight in Foxglove's well-known schemas (protobuf): per
state the vehicle's ``foxglove.FrameTransform`` (world -> ``<vehicle>/body``),
``foxglove.PoseInFrame`` and ``foxglove.SceneUpdate``, per payload ``mocap`` frame the
payload (its transform, a sphere and the cable until the release), and every second the
reference path and the geofence, on ``arcade/<vehicle>/foxglove/<name>``
(:mod:`arcade_io.foxglove_scene`, the conversion the live ``foxglove`` service serves too),
so that Foxglove's 3D panel shows the flight without set-up. The reference path is the
controller's ``reference`` records so far.

``<out>/flight_log.csv``: the design §5 flight log, one row per setpoint: the estimated
state it answers and the setpoint (``t, px, ..., wz, u0..u3``; ``t`` relative to the first
state), plus the setpoint's ``mode``. Rows are written while flying, in stamp order, once
:data:`REORDER_S` of newer pairs exist (flushed every second of stamps), so a crash loses
only the last moments; a pair that completes later than that is dropped and counted
(``late_rows``), as are setpoints whose state never arrived (``unpaired_setpoints``,
the oldest go first once :data:`MAX_UNPAIRED` wait).

Messages are recorded as received (no order check: a recorder wants everything, including
what a consumer would reject as stale); invalid payloads are still rejected and counted.

A file that cannot be written (a full disk, a removed drive) stops being written, never the
recorder nor the flight: a ``fault`` event names the file and the error, the other file
goes on, and what is not recorded from then on is counted (``unrecorded`` messages,
``unwritten_rows``); ``recording_errors`` in the statistics keeps each file's error. What
was buffered when the write failed is lost with the file: the MCAP writer's open chunk (at
most :data:`MCAP_FLUSH_S` of messages), the flight log's rows since its last flush (a second
of stamps). A killed recorder loses the same: both files are flushed while flying, and what
reached the disk reads back (the MCAP file without its summary index: by a linear scan,
e.g. ``mcap.stream_reader.StreamReader`` or the ``mcap`` command line's ``recover``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import heapq
import json
import threading
import time
from pathlib import Path
from typing import Any

from arcade_io import flightlog
from services import runtime
from services.csvlog import StreamedCsv
from services.messages import MESSAGE_TYPES, Message, Setpoint, State

#: A state-setpoint pair is written once a pair this much newer [s] exists (they complete
#: out of order only by a few periods).
REORDER_S = 1.0
#: Setpoints kept while waiting for their state.
MAX_UNPAIRED = 256
#: The MCAP writer's open chunk is written out at least this often [s of receive time]
#: (else it waits for 1 MiB of messages, uncompressed: about 2 s of a realtime flight, lost
#: if the recorder dies).
MCAP_FLUSH_S = 1.0

_JSON_TYPES = {"float": "number", "int": "integer", "bool": "boolean", "str": "string"}


def json_schema(cls: type[Message]) -> dict[str, Any]:
    """A JSON Schema of the wire map of ``cls`` (arrays as nested number arrays)."""
    props: dict[str, Any] = {"schema": {"type": "string"}, "version": {"type": "integer"}}
    for f in dataclasses.fields(cls):
        spec = f.metadata["spec"]
        kind = type(spec).__name__.removesuffix("Spec")
        if kind == "Array":
            item: dict[str, Any] = {"type": "number"}
            for _ in spec.shape:
                item = {"type": "array", "items": item}
            props[f.name] = item
        elif kind == "Scalars":
            props[f.name] = {"type": "object"}
        else:
            props[f.name] = {"type": _JSON_TYPES.get(kind.lower(), "string")}
        if getattr(spec, "optional", False):
            props[f.name] = {"anyOf": [props[f.name], {"type": "null"}]}
    return {"title": cls.SCHEMA, "type": "object", "properties": props}


class Recorder(runtime.Service):
    """Recorder: MCAP log of the bus and the CSV flight log."""

    name = "recorder"
    uses_jax = False

    def setup(self, bus) -> None:
        from mcap.writer import Writer

        out = Path(self.args.out or ".")
        out.mkdir(parents=True, exist_ok=True)
        # A restarted recorder must not overwrite what the crashed one wrote.
        n = self.args.incarnation
        suffix = f".{n}" if n else ""
        self._lock = threading.Lock()
        self._file = (out / f"bus{suffix}.mcap").open("wb")
        self.writer = Writer(self._file)
        self.writer.start(profile="", library="arcade")
        self._clock = time.monotonic  # of the chunk flushes
        self._flushed = self._clock()
        self._channels: dict[str, int] = {}
        for topic, cls in MESSAGE_TYPES.items():
            schema = self.writer.register_schema(
                name=cls.SCHEMA, encoding="jsonschema", data=json.dumps(json_schema(cls)).encode()
            )
            self._channels[topic] = self.writer.register_channel(
                topic=bus.key(topic), message_encoding="json", schema_id=schema
            )
        self.flight_log = StreamedCsv(
            out / f"flight_log{suffix}.csv",
            [*flightlog.columns("quadrotor"), "mode"],
            on_error=lambda err: self._lost(self.flight_log.path, err),
        )
        self._states: dict[int, State] = {}
        self._unpaired: dict[float, Setpoint] = {}
        self._rows: list[tuple[float, int, list[Any]]] = []  # heap by stamp, not yet written
        self._n_rows = 0
        self._newest = -float("inf")  # stamp of the newest pair
        self._written = -float("inf")  # stamp of the newest row written
        self._t0: float | None = None
        self._foxglove_channels(bus)
        self.stats["messages"] = dict.fromkeys(MESSAGE_TYPES, 0)
        self.stats.update(rows=0, late_rows=0, unpaired_setpoints=0, unrecorded=0, unwritten_rows=0)
        self.stats["recording_errors"] = {}
        self._mcap_name = self._file.name
        self._closed = False
        for topic in MESSAGE_TYPES:
            bus.subscribe(topic, lambda m, topic=topic: self.record(topic, m), check_order=False)

    def _foxglove_channels(self, bus) -> None:
        """The Foxglove channels (:mod:`arcade_io.foxglove_scene`) in the MCAP file."""
        from arcade_io.foxglove_scene import CHANNELS
        from services.foxglove_live import scene_for

        self.scene = scene_for(self.args)
        self._fg_channels: dict[str, int] = {}
        for name, cls in CHANNELS.items():
            schema = cls.get_schema()
            schema_id = self.writer.register_schema(
                name=schema.name, encoding=schema.encoding, data=schema.data
            )
            self._fg_channels[name] = self.writer.register_channel(
                topic=self.scene.topic(name), message_encoding="protobuf", schema_id=schema_id
            )
        self.stats["foxglove_messages"] = 0

    def record(self, topic: str, m: Message) -> None:
        wire = m.to_wire()
        data = json.dumps(wire).encode()
        with self._lock:
            if self._closed:
                return
            if self.writer is not None:
                try:
                    now_ns = time.time_ns()
                    publish_ns = min(int(m.stamp * 1e9), 2**64 - 1)
                    self.writer.add_message(
                        self._channels[topic],
                        log_time=now_ns,
                        data=data,
                        publish_time=publish_ns,
                        sequence=m.seq % 2**32,
                    )
                    for name, msg in self.scene.messages(topic, wire):
                        self.writer.add_message(
                            self._fg_channels[name],
                            log_time=now_ns,
                            data=msg.encode(),
                            publish_time=publish_ns,
                        )
                        self.stats["foxglove_messages"] += 1
                    now = self._clock()
                    if now - self._flushed >= MCAP_FLUSH_S:
                        self._flushed = now
                        self.writer.flush()  # the open chunk, to the disk
                except OSError as err:
                    self._stop_mcap(err)
            if self.writer is None:
                self.stats["unrecorded"] += 1
            else:
                self.stats["messages"][topic] += 1
            # State and setpoint come from different publishers: pair whichever is second.
            # By stamp (a setpoint carries the stamp of the state it answers), not by
            # ``seq``: a restarted estimator counts ``seq`` from 1 again.
            if isinstance(m, State):
                if self._t0 is None:
                    self._t0 = m.stamp
                self._states[m.stamp] = m
                sp = self._unpaired.pop(m.stamp, None)
                if sp is not None:
                    self._row(m, sp)
                if len(self._states) > 256:
                    for k in sorted(self._states)[:-128]:
                        del self._states[k]
            elif isinstance(m, Setpoint):
                s = self._states.pop(m.stamp, None)
                if s is not None:
                    self._row(s, m)
                else:
                    if len(self._unpaired) >= MAX_UNPAIRED:  # their states never came
                        del self._unpaired[min(self._unpaired)]
                        self.stats["unpaired_setpoints"] += 1
                    self._unpaired[m.stamp] = m

    def _row(self, s: State, sp: Setpoint) -> None:
        """Queue the row of a pair; write the rows that no later pair can precede."""
        self._n_rows += 1  # tie-breaker: rows of equal stamps keep their order
        heapq.heappush(self._rows, (s.stamp, self._n_rows, [*s.x, *sp.u, sp.mode]))
        self._newest = max(self._newest, s.stamp)
        self._write_rows(self._newest - REORDER_S)

    def _write_rows(self, until: float) -> None:
        t0 = self._t0 or 0.0
        while self._rows and self._rows[0][0] <= until:
            stamp, _, row = heapq.heappop(self._rows)
            if stamp < self._written:  # its rows are out already: time must increase
                self.stats["late_rows"] += 1
                if self.stats["late_rows"] == 1:
                    self.log.warning("a state-setpoint pair completed too late for the log")
                continue
            self._written = stamp
            if self.flight_log.write(stamp, [stamp - t0, *row]):
                self.stats["rows"] += 1
            else:
                self.stats["unwritten_rows"] += 1

    # -- a file that cannot be written
    def _stop_mcap(self, err: OSError) -> None:
        self.writer = None
        with contextlib.suppress(OSError):  # the buffered bytes cannot go anywhere either
            self._file.close()
        self._lost(self._mcap_name, err)

    def _lost(self, name: str | Path, err: OSError) -> None:
        """Report once that ``name`` is no longer written."""
        name = str(name)
        if name in self.stats["recording_errors"]:
            return
        self.stats["recording_errors"][name] = str(err)
        self.event(
            "fault",
            f"cannot write {name}: {err.strerror or err}; not recorded from here on",
            "error",
            file=str(name),
            errno=err.errno if err.errno is not None else -1,
        )

    def teardown(self) -> None:
        with self._lock:
            self._closed = True
            try:
                if self.writer is not None:
                    self.writer.finish()
                    self._file.close()
            except OSError as err:
                self._stop_mcap(err)
            finally:  # the flight log even when the MCAP file cannot be finished
                self.writer = None
                if not self._file.closed:
                    with contextlib.suppress(OSError):  # reported above
                        self._file.close()
                self._write_rows(float("inf"))
                self.flight_log.close()


def _extra(p) -> None:
    from services.foxglove_live import add_scene_arguments

    add_scene_arguments(p)


def main(argv: list[str] | None = None) -> int:
    return runtime.main_for(Recorder, argv, _extra)
