"""Strict JSON out: numbers that are not defined become null, nothing else changes."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from arcade_io import jsonout


def _strict_loads(text: str):
    """A reader that, like JavaScript's or Go's, refuses NaN and Infinity."""

    def refuse(token: str):
        raise ValueError(f"not JSON: {token}")

    return json.loads(text, parse_constant=refuse)


def test_numbers_that_are_not_finite_become_null_anywhere_in_the_tree():
    result = {
        "cells": [{"settling_s": math.inf, "rmse_m": 0.02, "rate": np.float32("nan")}],
        "tuning": {"scores": (0.1, -math.inf, np.float64(0.3))},
        "count": np.int64(3),
        "name": "ours",
        "flag": True,
        "none": None,
    }
    back = _strict_loads(jsonout.dumps(result, indent=2))
    assert back == {
        "cells": [{"settling_s": None, "rmse_m": 0.02, "rate": None}],
        "tuning": {"scores": [0.1, None, 0.3]},
        "count": 3,
        "name": "ours",
        "flag": True,
        "none": None,
    }
    with pytest.raises(ValueError, match="not JSON"):
        _strict_loads(json.dumps(result["cells"][0] | {"rate": 0.0}))


def test_a_number_read_back_takes_the_meaning_the_caller_gives_null():
    assert jsonout.number(None, math.inf) == math.inf
    assert math.isnan(jsonout.number(None))
    assert jsonout.number(2) == 2 and jsonout.number(0.5, math.inf) == 0.5
