"""Strict JSON for every file and ``--json`` output the tools write.

Python's ``json`` writes ``NaN`` and ``Infinity``, which are not JSON (RFC 8259): a
JavaScript or Go reader refuses the file, and ``jq`` turns ``Infinity`` into
``1.797e308``. Results do hold numbers that are not defined (the settling time of a flight
that never settled, the changepoint rate of a method without changepoints, the tuning score
of a setting whose flights crashed); they are written as ``null``, and the file's other
fields say why (``settled_fraction``, ``crashed``).
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np


def finite(obj: Any) -> Any:
    """``obj`` with every float that is not finite (NaN, +-inf; numpy scalars included)
    replaced by ``None``, in nested dicts, lists and tuples; numpy scalars become Python
    numbers."""
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def dumps(obj: Any, **kwargs: Any) -> str:
    """``json.dumps`` of :func:`finite` ``(obj)``, refusing anything that would still not be
    JSON (``allow_nan=False``)."""
    return json.dumps(finite(obj), allow_nan=False, **kwargs)


def number(value: Any, missing: float = math.nan) -> Any:
    """A number read back from such a file: ``missing`` where it was written as ``null``
    (``math.inf`` for a settling time: the flight never settled), else ``value``."""
    return missing if value is None else value
