"""Run folders: every long command writes its outputs to ``runs/<timestamp>-<name>/``."""

from __future__ import annotations

import os
import time
from pathlib import Path


def new_run_dir(name: str, root: str | Path | None = None) -> Path:
    root = Path(root or os.environ.get("ARCADE_RUNS", "runs"))
    stamp = time.strftime("%Y%m%d-%H%M%S")
    path = root / f"{stamp}-{name}"
    n = 1
    while path.exists():
        n += 1
        path = root / f"{stamp}-{name}-{n}"
    path.mkdir(parents=True)
    return path
