"""Run folders and the checks commands make before they start work.

Every long command writes its outputs to ``runs/<timestamp>-<name>/`` (or ``--out``).
:func:`check_output_dir` / :func:`check_output_file` tell up front whether an output path
can be used, so that a command does not fail after minutes of work; :func:`number` and
:func:`count` are argparse ``type=`` checks that name the valid range.
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
import time
from pathlib import Path


def runs_root(root: str | Path | None = None) -> Path:
    """Where run folders go: ``root``, else ``$ARCADE_RUNS``, else ``runs``."""
    return Path(root or os.environ.get("ARCADE_RUNS", "runs"))


def new_run_dir(name: str, root: str | Path | None = None) -> Path:
    root = runs_root(root)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    path = root / f"{stamp}-{name}"
    n = 1
    while path.exists():
        n += 1
        path = root / f"{stamp}-{name}-{n}"
    path.mkdir(parents=True)
    return path


class OutputPathError(ValueError):
    """An output path a command cannot write to (the message says why)."""


def _nearest_existing(path: Path) -> Path:
    for parent in (path, *path.parents):
        if parent.exists():
            return parent
    return Path(".")


def _probe_write(folder: Path, what: str, path: Path) -> None:
    """Create and remove a file in ``folder``: permission bits do not tell it all (root
    passes every ``os.access`` check; a read-only mount or ``/proc`` refuses anyway)."""
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise OutputPathError(
            f"{what} {path}: cannot write in {folder} ({exc.strerror or exc})"
        ) from None


def _check_folder_below(path: Path, what: str) -> None:
    """``path`` does not exist: its nearest existing ancestor must be a writable folder."""
    base = _nearest_existing(path.parent if path.parent != path else path)
    if not base.is_dir():
        raise OutputPathError(f"{what} {path}: {base} is a file, not a folder")
    if not os.access(base, os.W_OK | os.X_OK):
        raise OutputPathError(f"{what} {path}: cannot create it, {base} is not writable")
    _probe_write(base, what, path)


def check_output_dir(path: str | Path, what: str = "output folder") -> Path:
    """``path`` as an output folder: an existing writable folder, or one that can be made.

    Raises :class:`OutputPathError` (a ``ValueError``) naming the path otherwise.
    """
    path = Path(path)
    if path.exists():
        if not path.is_dir():
            raise OutputPathError(f"{what} {path} is an existing file, not a folder")
        if not os.access(path, os.W_OK | os.X_OK):
            raise OutputPathError(f"{what} {path} is not writable")
        _probe_write(path, what, path)
        return path
    _check_folder_below(path, what)
    return path


def check_output_file(path: str | Path, what: str = "output file") -> Path:
    """``path`` as a file to (over)write: not a folder, and in a folder that is or can be
    made writable. Raises :class:`OutputPathError` naming the path otherwise."""
    path = Path(path)
    if path.is_dir():
        raise OutputPathError(f"{what} {path} is an existing folder; give a file name")
    if path.exists():
        if not os.access(path, os.W_OK):
            raise OutputPathError(f"{what} {path} is not writable")
        _probe_write(path.parent, what, path)  # files are replaced atomically, in there
        return path
    _check_folder_below(path, what)
    return path


def check_runs_root(root: str | Path | None = None) -> Path:
    """The run-folder root (:func:`runs_root`) as an output folder (:func:`check_output_dir`)."""
    return check_output_dir(runs_root(root), "run folder root")


def _fmt(x: float) -> str:
    return f"{x:g}"


def number(
    low: float | None = None,
    high: float | None = None,
    *,
    low_open: bool = False,
    high_open: bool = False,
):
    """argparse ``type=``: a finite float in ``[low, high]`` (``low_open``/``high_open``
    exclude the bound); the error names the valid range."""
    if low is not None and high is not None:
        rng = f"between {_fmt(low)} and {_fmt(high)}"
        if low_open or high_open:
            rng = (
                f"in {'(' if low_open else '['}{_fmt(low)}, {_fmt(high)}{')' if high_open else ']'}"
            )
    elif low is not None:
        rng = f"a finite number {'>' if low_open else '>='} {_fmt(low)}"
    elif high is not None:
        rng = f"a finite number {'<' if high_open else '<='} {_fmt(high)}"
    else:
        rng = "a finite number"

    def parse(text: str) -> float:
        try:
            x = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        ok = math.isfinite(x)
        if ok and low is not None:
            ok = x > low if low_open else x >= low
        if ok and high is not None:
            ok = x < high if high_open else x <= high
        if not ok:
            raise argparse.ArgumentTypeError(f"must be {rng}, got {text}")
        return x

    return parse


def count(low: int = 0, high: int | None = None):
    """argparse ``type=``: an integer in ``[low, high]``; the error names the valid range."""
    rng = f"between {low} and {high}" if high is not None else f"at least {low}"

    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if n < low or (high is not None and n > high):
            raise argparse.ArgumentTypeError(f"must be {rng}, got {text}")
        return n

    return parse
