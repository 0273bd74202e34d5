"""Full fuzz run: 10^4 payloads per message type and per service handler.

``make test`` runs the decoder fuzzing at 10^4 payloads per type and the handler fuzzing
at 2 000 per service; ``arcade bench fuzz`` runs both test modules at ``cases`` (10^4) each
(``ARCADE_FUZZ_CASES`` / ``ARCADE_FUZZ_HANDLER_CASES``) in a pytest subprocess and reports
the outcome and the time it took. Needs the source tree (the tests are not installed).

    python -m benchmarks.fuzz [--quick] [--cases N]
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from arcade_io import jsonout
from benchmarks.common import machine

TESTS = ("tests/property/test_fuzz_messages.py", "tests/property/test_fuzz_handlers.py")


def run(
    quick: bool = False,
    cases: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run the fuzz tests with ``cases`` payloads per type/handler (``quick``: 1 000);
    ``progress`` gets a start line and pytest's output line by line as it runs."""
    n = cases if cases is not None else (1_000 if quick else 10_000)
    root = Path(__file__).resolve().parents[1]
    missing = [t for t in TESTS if not (root / t).is_file()]
    if missing:
        raise FileNotFoundError(f"fuzz tests not found (source tree needed): {missing}")
    env = dict(os.environ, ARCADE_FUZZ_CASES=str(n), ARCADE_FUZZ_HANDLER_CASES=str(n))
    if progress is not None:
        progress(f"[fuzz] pytest {' '.join(TESTS)}, {n} cases per type and handler")
    t0 = time.perf_counter()
    # -v: a line per test as it ends (the progress); pytest's errors (e.g. no hypothesis
    # installed) go into the output too, so that the summary names them.
    with subprocess.Popen(
        [sys.executable, "-m", "pytest", "-v", "-p", "no:cacheprovider", *TESTS],
        cwd=root,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    ) as proc:
        assert proc.stdout is not None
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if progress is not None and line.strip():
                progress(f"[fuzz] {line.rstrip()}")
    wall = time.perf_counter() - t0
    stdout = "".join(lines)
    summary = stdout.strip().splitlines()[-1].strip("= ") if stdout.strip() else ""
    counts = {k: int(v) for v, k in re.findall(r"(\d+) (passed|failed|error)", summary)}
    failed = re.findall(r"^FAILED (\S+)", stdout, flags=re.M)
    return {
        "machine": machine(),
        "cases_per_type_and_handler": n,
        "wall_s": wall,
        "passed": counts.get("passed", 0),
        "failed": counts.get("failed", 0) + counts.get("error", 0),
        "failures": failed,
        "ok": proc.returncode == 0,
        "summary": summary,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--cases", type=int, default=None)
    a = p.parse_args(argv)
    r = run(quick=a.quick, cases=a.cases)
    print(jsonout.dumps(r, indent=2))
    return 0 if r["ok"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
