"""A CSV file written row by row during a flight: what a crash or a full disk leaves.

The recorder's flight log and the simulator's ground truth are written while flying, not
at the end: a process that is killed loses at most the rows since the last flush (every
``flush_s`` of row time), and a long flight does not hold its log in memory. A write that
fails (a full disk, a removed drive) stops this file, never the process that writes it:
``on_error`` is called once with the error, and the rows offered after it are counted
(``unwritten``). What was buffered when the write failed is lost with the file.
"""

from __future__ import annotations

import contextlib
import csv
import math
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any


class StreamedCsv:
    """``path`` opened for writing (created or truncated) with its ``header`` row.

    Opening raises ``OSError`` (the caller cannot start without its file); every later
    failure goes to ``on_error`` instead.
    """

    def __init__(
        self,
        path: str | Path,
        header: Iterable[str],
        on_error: Callable[[OSError], None],
        flush_s: float = 1.0,
    ) -> None:
        self.path = Path(path)
        self.rows = 0  # rows written (buffered or on disk)
        self.unwritten = 0  # rows offered after the file stopped
        self.error: OSError | None = None
        self._on_error = on_error
        self._flush_s = flush_s
        self._flushed = -math.inf  # row time of the last flush: the first row goes out at once
        self._file: Any = self.path.open("w", newline="")
        self._csv = csv.writer(self._file)
        self._csv.writerow(list(header))

    @property
    def writing(self) -> bool:
        """False once a write failed or the file was closed."""
        return self._file is not None

    def write(self, t: float, row: Iterable[Any]) -> bool:
        """Write one row of row time ``t`` (flushed when ``flush_s`` passed since the last
        flush); False when the file no longer takes rows."""
        if self._file is None:
            self.unwritten += 1
            return False
        try:
            self._csv.writerow(list(row))
        except OSError as err:
            self.unwritten += 1
            self._stop(err)
            return False
        self.rows += 1
        if t - self._flushed >= self._flush_s:
            self._flushed = t
            try:
                self._file.flush()
            except OSError as err:  # the rows since the last flush are lost with it
                self._stop(err)
        return True

    def close(self) -> None:
        """Flush and close (a failure is reported through ``on_error``); idempotent."""
        if self._file is None:
            return
        file, self._file = self._file, None
        try:
            file.close()
        except OSError as err:
            self.error = err
            self._on_error(err)

    def _stop(self, err: OSError) -> None:
        file, self._file = self._file, None
        self.error = err
        with contextlib.suppress(OSError):  # the buffered bytes cannot go anywhere either
            file.close()
        self._on_error(err)
