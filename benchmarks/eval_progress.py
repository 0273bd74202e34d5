"""Finished parts of a long evaluation kept in its output folder, so that the same command
run again with the same ``--out`` continues where it stopped.

`arcade eval quadrotor` flies for hours on 2 cores (README, "Benchmarks"); an interrupted
run must not lose what it had flown. Each finished part (the tuning, each cell x method's
flights) is appended to ``<out>/progress.jsonl`` as one line, flushed and synced. The
first line holds the run's key: the settings that decide the flights and a digest of the
code and data they depend on (:data:`SOURCES`). Run again with the same key, the finished
parts are read back instead of flown and the results are the same as those of one
uninterrupted run; with another key the run stops with one error line and the file is
left as it is (nothing is overwritten). A line cut short by a kill is ignored: its part is
flown again. Once the run's results are written the file is removed: the same command run
again flies afresh.

The file is a checkpoint read only by this module: numbers that are not finite (a flight
that never settled) are kept as ``{"$float": "inf"}``, not as JSON's ``null``, so that a
continued run computes with exactly what the interrupted one flew.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from arcade_io.atomicfile import write_text
from arcade_io.traced import source_digest

#: What the flights depend on besides the settings: the code, the vehicle files and the
#: shipped weights (not the stored results under ``benchmarks/``: no ``.json``).
SOURCES = (
    "arcade_core",
    "arcade_control",
    "arcade_io",
    "simulator",
    "benchmarks",
    "deploy/vehicles",
    "deploy/weights",
)
_SUFFIXES = (".py", ".toml", ".eqx")
FILE = "progress.jsonl"


def discard(folder: Path | str) -> None:
    """Remove the kept parts of a run that has finished (its results are written): the
    same command run again then flies afresh."""
    (Path(folder) / FILE).unlink(missing_ok=True)


class ProgressMismatch(ValueError):
    """The output folder holds a partial run of other settings or code."""


def _encode(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _encode(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_encode(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _encode(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return {"$float": repr(obj)}
    return obj


def _decode(obj: Any) -> Any:
    if isinstance(obj, dict):
        if set(obj) == {"$float"}:
            return float(obj["$float"])
        return {k: _decode(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_decode(v) for v in obj]
    return obj


class Progress:
    """The finished parts of one run (``folder``: its output folder; ``None``: keep
    nothing) with the settings ``key`` (JSON-able)."""

    def __init__(self, folder: Path | str | None, key: dict[str, Any]):
        self.path = Path(folder) / FILE if folder is not None else None
        self._parts: dict[str, Any] = {}
        #: How many parts were read back, and the seconds they took to compute in the runs
        #: that kept them.
        self.read_back = 0
        self.kept_s = 0.0
        self._since = time.perf_counter()
        self.key = hashlib.sha256(
            json.dumps(
                {"settings": _encode(key), "sources": source_digest(SOURCES, _SUFFIXES)},
                sort_keys=True,
            ).encode()
        ).hexdigest()
        if self.path is None:
            return
        if self.path.is_file() and self.path.stat().st_size > 0:
            text = self.path.read_text()
            lines = text.splitlines()
            try:
                head = json.loads(lines[0])["key"]
            except (json.JSONDecodeError, KeyError, TypeError):
                head = None
            if head != self.key:
                raise ProgressMismatch(
                    f"{self.path} holds a partial run of other settings or other code: run "
                    "with another --out, or remove the file to start afresh"
                )
            good = lines[:1]
            for line in lines[1:]:
                try:
                    rec = json.loads(line)
                except json.JSONDecodeError:  # cut short by a kill: flown again
                    break
                good.append(line)
                self._parts[rec["part"]] = _decode(rec["value"])
                self.kept_s += float(rec.get("elapsed_s", 0.0))
                self.read_back += 1
            if len(good) < len(lines) or not text.endswith("\n"):
                # Drop the line cut short, so that the next parts start on a line of their own.
                write_text(self.path, "".join(f"{line}\n" for line in good))
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._append({"key": self.key, "settings": _encode(key)})

    def __len__(self) -> int:
        return len(self._parts)

    def get(self, part: str) -> Any:
        """The value stored for ``part`` by an earlier run, else ``None``."""
        return self._parts.get(part)

    def put(self, part: str, value: Any) -> None:
        """Keep ``value`` (JSON-able, numpy and non-finite floats allowed) as finished, with
        the time since the last part was kept (or since this run started)."""
        now = time.perf_counter()
        elapsed, self._since = now - self._since, now
        self._parts[part] = _decode(_encode(value))
        if self.path is not None:
            self._append({"part": part, "value": _encode(value), "elapsed_s": elapsed})

    def _append(self, record: dict[str, Any]) -> None:
        assert self.path is not None
        with self.path.open("a") as f:
            f.write(json.dumps(record, allow_nan=False) + "\n")
            f.flush()
            os.fsync(f.fileno())
