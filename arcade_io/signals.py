"""Signal handlers that stop threads safely.

A Python signal handler runs on the main thread between two bytecodes, so it can
interrupt that thread while it holds a lock. ``threading.Event`` guards its flag with a
non-reentrant lock, taken inside ``set()`` and ``wait()``: a handler that calls
``event.set()`` while the main thread is inside ``event.set()`` or ``event.wait()`` waits
for itself forever. That happened when a service ended by itself (its own ``stop.set()``)
just as the launcher's SIGINT came.
"""

from __future__ import annotations

import threading


def set_from_handler(event: threading.Event) -> None:
    """``event.set()`` from a signal handler: done on a short thread, which waits for the
    main thread to release the event's lock. Nothing to do if the event is already set."""
    if not event.is_set():
        threading.Thread(target=event.set, name="signal", daemon=True).start()
