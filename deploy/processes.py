"""The stack's processes from the outside: stopping one, signals around a stop, its output.

:func:`end_process` stops one process (SIGINT, a grace period, a stack dump on SIGUSR1,
SIGTERM, SIGKILL); :func:`interrupts_deferred` holds Ctrl-C and SIGTERM back while every
service is being stopped; :func:`sigterm_interrupts` makes SIGTERM stop a stack as Ctrl-C
does; :func:`last_output` quotes what a process of a run said last.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from arcade_io import signals

__all__ = ["end_process", "interrupts_deferred", "last_output", "sigterm_interrupts"]

#: ANSI colour sequences (MAVSDK colours its console lines).
_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


def last_output(out: Path, name: str, lines: int = 4) -> list[str]:
    """What a process of the run in ``out`` said last (``logs/<name>.out``): after a
    traceback, the log line before it and the exception; otherwise its last ``lines``
    non-blank lines. Empty when there is no output."""
    path = Path(out) / "logs" / f"{name}.out"
    try:
        with path.open("rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - 16384))
            text = f.read().decode(errors="replace")
    except OSError:
        return []
    rows = [_ANSI.sub("", r).rstrip() for r in text.splitlines()]
    rows = [r for r in rows if r.strip()]
    tb = max((i for i, r in enumerate(rows) if r.startswith("Traceback (")), default=None)
    if tb is not None:
        # Frames are indented; the exception (and what chains it) is not. The exception
        # line stays even when more output follows it.
        after = [r for r in rows[tb + 1 :] if not r[:1].isspace()]
        before = rows[max(0, tb - 1) : tb]
        if len(before) + len(after) <= lines:
            rows = before + after
        else:
            rows = after[:1] + after[1:][-(lines - 1) :] if lines > 1 else after[:1]
    else:
        rows = rows[-lines:]
    return [r if len(r) <= 400 else r[:399] + "…" for r in rows]


@contextlib.contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """While inside, SIGTERM raises ``KeyboardInterrupt`` as Ctrl-C does, so the
    :class:`~deploy.launcher.Stack` context manager stops every service (``arcade up``,
    ``arcade demo``); the previous handler is restored on leaving. Only the main thread can
    install handlers: elsewhere, nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def on_term(*_: object) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


def end_process(p: subprocess.Popen, grace: float, hurry: threading.Event) -> None:
    """SIGINT ``p`` and wait up to ``grace`` s (less once ``hurry`` is set), then SIGTERM
    and 5 s, then SIGKILL; returns once it has been reaped. A service still running after
    the grace period first gets SIGUSR1: it writes its threads' stacks to its ``.out`` log
    (``faulthandler``), the record of where it hung."""
    with contextlib.suppress(ProcessLookupError):
        p.send_signal(signal.SIGINT)
    deadline = time.monotonic() + grace
    # Polled, because a process's exit cannot be waited for together with ``hurry``.
    while p.poll() is None and not hurry.is_set() and time.monotonic() < deadline:
        hurry.wait(0.05)
    if p.poll() is None and not hurry.is_set():
        with contextlib.suppress(ProcessLookupError):
            p.send_signal(signal.SIGUSR1)
        with contextlib.suppress(subprocess.TimeoutExpired):
            p.wait(timeout=0.5)
    if p.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            p.terminate()
        try:
            p.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


@contextlib.contextmanager
def interrupts_deferred() -> Any:
    """While inside: SIGINT and SIGTERM set the yielded event instead of acting; on leaving,
    the previous handlers are back and the signals that came are delivered to them.
    Outside the main thread (no signal handlers there): only the event."""
    hurry = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield hurry
        return
    came: list[int] = []

    def defer(sig: int, _frame: object) -> None:
        came.append(sig)
        signals.set_from_handler(hurry)  # the main thread may be inside hurry.wait()

    sigs = (signal.SIGINT, signal.SIGTERM)
    previous = {sig: signal.signal(sig, defer) for sig in sigs}
    try:
        yield hurry
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
        for sig in dict.fromkeys(came):
            signal.raise_signal(sig)
