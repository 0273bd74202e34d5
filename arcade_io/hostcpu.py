"""What the host did with this machine's CPUs: time stolen by the hypervisor.

On a virtual machine the host can take a vCPU away (``steal`` in ``/proc/stat``); no
scheduling policy inside the guest protects a deadline from that. A realtime flight records
how much was stolen while it flew, so that a missed deadline can be told from a slow step.
"""

from __future__ import annotations

import os

__all__ = ["steal_s"]


def steal_s(path: str = "/proc/stat") -> float | None:
    """CPU time stolen from this machine so far, summed over its CPUs, in seconds (``None``
    where the kernel does not report it)."""
    try:
        with open(path) as f:
            fields = f.readline().split()
    except OSError:
        return None
    if len(fields) < 9 or fields[0] != "cpu":
        return None
    return int(fields[8]) / os.sysconf("SC_CLK_TCK")
