"""Files written whole or not at all.

Every result, weight, checkpoint, log and stats file the tools write goes through
:func:`atomic_open`: the content goes to a temporary file beside the target, is flushed
to disk, and only then renamed over the target (``os.replace``, atomic on POSIX and on
Windows within one file system). A crash, a ``Ctrl-C`` or a full disk mid-write leaves the
previous file as it was and no partial file behind; a reader never sees half a file.

The new file gets the permissions a plain ``open(path, "w")`` would give it (``0o666``
less the process's umask), not the ``0o600`` of :func:`tempfile.mkstemp`.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any


def _umask() -> int:
    # os.umask can only be read by setting it; set it back at once. Read once, at import:
    # the services import this module before they start any thread.
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_FILE_MODE = 0o666 & ~_umask()


@contextlib.contextmanager
def atomic_open(
    path: str | Path, mode: str = "w", *, fsync: bool = True, **kwargs: Any
) -> Iterator[IO[Any]]:
    """Open a temporary file that replaces ``path`` when the ``with`` block ends without
    an exception, and is removed when it raises.

    ``mode`` is ``"w"`` (text; ``kwargs`` go to :func:`open`, e.g. ``newline=""`` for
    CSV) or ``"wb"``. The parent directory is created if it does not exist. ``fsync=False``
    skips flushing to the disk before the rename: the file then survives a crash of the
    process but not necessarily of the machine, and the write does not wait for the disk
    (for a checkpoint written from a control loop).
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"mode must be 'w' or 'wb', not {mode!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, mode, **kwargs) as f:
            yield f
            f.flush()
            if fsync:
                os.fsync(f.fileno())
        os.chmod(tmp, _FILE_MODE)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (:func:`atomic_open`)."""
    with atomic_open(path, "w", encoding="utf-8") as f:
        f.write(text)
    return Path(path)


def write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (:func:`atomic_open`)."""
    with atomic_open(path, "wb") as f:
        f.write(data)
    return Path(path)


def save_figure(fig: Any, path: str | Path, **kwargs: Any) -> Path:
    """``fig.savefig`` to ``path`` atomically, in the format its suffix names (``.png``);
    ``kwargs`` go to ``savefig`` (``dpi``)."""
    path = Path(path)
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format=path.suffix.lstrip(".") or None, **kwargs)
    return path
