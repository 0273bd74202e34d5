"""Field types of the wire messages: their limits, validation and the one error they raise.

Each field of a record (:mod:`services.messages`) carries a spec in its dataclass metadata
(:func:`spec_meta`, :func:`array_meta`): :class:`FloatSpec`, :class:`IntSpec`,
:class:`BoolSpec`, :class:`StrSpec`, :class:`ArraySpec` or :class:`ScalarsSpec`. A spec's
``coerce`` checks one value (type, shape, finiteness, range) and returns it in its stored
form; ``to_wire`` gives the value the msgpack map carries. Every defect raises
:class:`MessageError` with a :class:`Reason`.
"""

from __future__ import annotations

import dataclasses
import enum
import re
import types
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = [
    "COMMANDS",
    "COV_TOL",
    "EVENT_KINDS",
    "IDENT",
    "KIND",
    "MAX_ABS_VALUE",
    "MAX_ACCEL_MPS2",
    "MAX_DIMS",
    "MAX_MAP_ITEMS",
    "MAX_MAP_STR",
    "MAX_POSITION_M",
    "MAX_RATE_RADPS",
    "MAX_SOLVE_MS",
    "MAX_SPEED_MPS",
    "MAX_STAMP_S",
    "MAX_THRUST_N",
    "MAX_UINT64",
    "MAX_VARIANCE",
    "MODES",
    "QUAT_NORM_TOL",
    "SERVICE",
    "SEVERITIES",
    "SRC",
    "ArraySpec",
    "BoolSpec",
    "FloatSpec",
    "IntSpec",
    "MessageError",
    "Reason",
    "ScalarsSpec",
    "StrSpec",
    "array_meta",
    "spec_meta",
    "type_name",
]

# ------------------------------------------------------------------------- limits
# Wire sanity limits, not a flight envelope: they catch garbage, unit mistakes and
# diverged estimators, and leave the physics to the services.
# Stamps are seconds; in nanoseconds they must fit the uint64 of MCAP/ROS time (1.8e10 s).
MAX_STAMP_S = 1e10
MAX_POSITION_M = 1e4
MAX_SPEED_MPS = 1e3
MAX_RATE_RADPS = 100.0  # body rates and gyro; MEMS gyros saturate near 35 rad/s
MAX_ACCEL_MPS2 = 1e3  # ~100 g
MAX_THRUST_N = 1e3
QUAT_NORM_TOL = 1e-3  # |‖q‖ - 1|; producers normalise, float32 round-off is ~1e-7
MAX_ABS_VALUE = 1e6  # residuals and decoder weights (normalised units)
MAX_VARIANCE = 1e12
MAX_SOLVE_MS = 1e6
#: Bounds of the dimension symbols of array shapes (``d`` outputs, ``l`` latents). A
#: full-covariance :class:`~services.messages.Model` grows as ``d l^2``; its ``MAX_BYTES``
#: is derived from these, so every legal shape can be sent.
MAX_DIMS: Mapping[str, int] = types.MappingProxyType({"d": 64, "l": 64})
#: Relative round-off tolerated by the covariance checks (float32 producers: ~(l + beam) eps).
COV_TOL = 1e-5
MAX_UINT64 = 2**64 - 1
MAX_MAP_ITEMS = 32
MAX_MAP_STR = 256

# ---------------------------------------------------------------------- vocabularies
#: Controller modes a :class:`~services.messages.Setpoint` may carry.
MODES = ("idle", "takeoff", "hover", "track", "land", "nominal_model")
#: Event kinds the services emit (the field accepts any short identifier).
EVENT_KINDS = (
    "changepoint",
    "failsafe",
    "failsafe_cleared",
    "fault",
    "degraded",
    "restart",
    "ready",
    "deadline_miss",
    "info",
)
SEVERITIES = ("debug", "info", "warning", "error", "critical")
#: Operator commands; anything else is rejected (an unknown command must not act).
COMMANDS = (
    "arm",
    "disarm",
    "takeoff",
    "land",
    "hold",
    "start",
    "stop",
    "release_payload",
    "reset",
    "shutdown",
)

#: Patterns of string fields: names (bodies, frames, map keys), publisher ids
#: (``"<service>/<session id>"``), event kinds, service names (empty: every service).
IDENT = re.compile(r"[A-Za-z0-9_.\-]{1,64}")
SRC = re.compile(r"[A-Za-z0-9_.:/@\-]{0,128}")
KIND = re.compile(r"[a-z][a-z0-9_]{0,31}")
SERVICE = re.compile(r"[A-Za-z0-9_.\-]{0,64}")


# -------------------------------------------------------------------------- errors


class Reason(enum.StrEnum):
    """Why a payload (or a record under construction) was rejected."""

    OVERSIZE = "oversize"
    NOT_MSGPACK = "not_msgpack"
    NOT_MAP = "not_map"
    BAD_SCHEMA = "bad_schema"
    BAD_VERSION = "bad_version"
    MISSING_FIELD = "missing_field"
    EXTRA_FIELD = "extra_field"
    BAD_TYPE = "bad_type"
    BAD_SHAPE = "bad_shape"
    NON_FINITE = "non_finite"
    OUT_OF_RANGE = "out_of_range"
    OUT_OF_ORDER = "out_of_order"
    STALE = "stale"
    #: A valid message from a bus session other than the one its topic is pinned to.
    FOREIGN_PUBLISHER = "foreign_publisher"
    INTERNAL = "internal"


class MessageError(ValueError):
    """The one exception of the wire layer: a :class:`Reason` code plus a readable detail."""

    def __init__(self, reason: Reason, detail: str, *, field: str | None = None):
        self.reason = Reason(reason)
        self.detail = detail
        self.field = field
        where = f" [{field}]" if field else ""
        super().__init__(f"{self.reason.value}{where}: {detail}")


# ---------------------------------------------------------------------- field specs


def _is_bool(v: Any) -> bool:
    return isinstance(v, bool | np.bool_)


def _scalar(v: Any, kinds: str) -> Any:
    """``v`` as a Python scalar if it is a real number of one of the numpy ``kinds``."""
    if _is_bool(v):
        return None
    if isinstance(v, int | np.integer) and "i" in kinds:
        return int(v)
    if isinstance(v, float | np.floating) and "f" in kinds:
        return float(v)
    if isinstance(v, int | np.integer) and "f" in kinds:
        return float(v)
    shape, dtype = getattr(v, "shape", None), getattr(v, "dtype", None)
    allowed = "fiu" if "f" in kinds else "iu"
    if shape == () and dtype is not None and np.dtype(dtype).kind in allowed:
        return _scalar(np.asarray(v).item(), kinds)  # 0-d numpy/JAX array
    return None


@dataclasses.dataclass(frozen=True)
class FloatSpec:
    """A float in ``[lo, hi]`` (integers accepted), or ``None`` when ``optional``."""

    lo: float = -np.inf
    hi: float = np.inf
    optional: bool = False

    def coerce(self, name: str, v: Any, dims: dict[str, int]) -> float | None:
        if v is None and self.optional:
            return None
        x = _scalar(v, "f")
        if x is None:
            raise MessageError(
                Reason.BAD_TYPE, f"expected a number, got {type_name(v)}", field=name
            )
        if not np.isfinite(x):
            raise MessageError(Reason.NON_FINITE, f"{x}", field=name)
        if not self.lo <= x <= self.hi:
            raise MessageError(
                Reason.OUT_OF_RANGE, f"{x} not in [{self.lo}, {self.hi}]", field=name
            )
        return x

    def to_wire(self, v: Any) -> Any:
        return v


@dataclasses.dataclass(frozen=True)
class IntSpec:
    """An integer in ``[lo, hi]`` (a uint64 by default), or ``None`` when ``optional``."""

    lo: int = 0
    hi: int = MAX_UINT64
    optional: bool = False

    def coerce(self, name: str, v: Any, dims: dict[str, int]) -> int | None:
        if v is None and self.optional:
            return None
        x = _scalar(v, "i")
        if x is None:
            raise MessageError(
                Reason.BAD_TYPE, f"expected an integer, got {type_name(v)}", field=name
            )
        if not self.lo <= x <= self.hi:
            raise MessageError(
                Reason.OUT_OF_RANGE, f"{x} not in [{self.lo}, {self.hi}]", field=name
            )
        return x

    def to_wire(self, v: Any) -> Any:
        return v


@dataclasses.dataclass(frozen=True)
class BoolSpec:
    """A bool (numpy's too), never a number."""

    def coerce(self, name: str, v: Any, dims: dict[str, int]) -> bool:
        if _is_bool(v) or (getattr(v, "shape", None) == () and np.dtype(v.dtype).kind == "b"):
            return bool(v)
        raise MessageError(Reason.BAD_TYPE, f"expected a bool, got {type_name(v)}", field=name)

    def to_wire(self, v: Any) -> Any:
        return v


@dataclasses.dataclass(frozen=True)
class StrSpec:
    """A string of at most ``max_len`` characters: one of ``choices``, matching ``pattern``."""

    pattern: re.Pattern[str] | None = None
    choices: tuple[str, ...] | None = None
    max_len: int = 64

    def coerce(self, name: str, v: Any, dims: dict[str, int]) -> str:
        if not isinstance(v, str):
            raise MessageError(
                Reason.BAD_TYPE, f"expected a string, got {type_name(v)}", field=name
            )
        if len(v) > self.max_len:
            raise MessageError(Reason.OUT_OF_RANGE, f"longer than {self.max_len}", field=name)
        if self.choices is not None and v not in self.choices:
            raise MessageError(Reason.OUT_OF_RANGE, f"{v!r} not one of {self.choices}", field=name)
        if self.pattern is not None and not self.pattern.fullmatch(v):
            raise MessageError(Reason.OUT_OF_RANGE, f"{v!r} is not a valid name", field=name)
        return str(v)

    def to_wire(self, v: Any) -> Any:
        return v


@dataclasses.dataclass(frozen=True)
class ArraySpec:
    """A float64 array of a fixed or symbolic shape (symbols bind across a record)."""

    shape: tuple[int | str, ...]
    lo: float | tuple[float, ...] = -np.inf
    hi: float | tuple[float, ...] = np.inf
    optional: bool = False
    #: ``(start, stop)`` of a 1-D array slice that must be a unit quaternion, if any.
    unit: tuple[int, int] | None = None

    def coerce(self, name: str, v: Any, dims: dict[str, int]) -> np.ndarray | None:
        if v is None and self.optional:
            return None
        if isinstance(v, list):
            arr = _from_nested(name, v, len(self.shape))
        elif isinstance(v, int | float | str | bytes | Mapping | np.generic):
            raise MessageError(
                Reason.BAD_TYPE, f"expected an array, got {type_name(v)}", field=name
            )
        else:
            try:
                arr = np.asarray(v)
            except Exception as e:  # e.g. a ragged sequence
                raise MessageError(Reason.BAD_TYPE, f"not an array: {e}", field=name) from e
            if arr.dtype.kind not in "fiu":
                raise MessageError(Reason.BAD_TYPE, f"dtype {arr.dtype} is not real", field=name)
            arr = np.array(arr, dtype=np.float64)  # always a private copy
        if arr.ndim != len(self.shape):
            raise MessageError(
                Reason.BAD_SHAPE, f"shape {arr.shape}, want {self.shape}", field=name
            )
        for n, want in zip(arr.shape, self.shape):
            if isinstance(want, str):
                if not 1 <= n <= MAX_DIMS[want]:
                    raise MessageError(
                        Reason.BAD_SHAPE, f"{want}={n} not in [1, {MAX_DIMS[want]}]", field=name
                    )
                if dims.setdefault(want, n) != n:
                    raise MessageError(
                        Reason.BAD_SHAPE, f"{want}={n} but {dims[want]} elsewhere", field=name
                    )
            elif n != want:
                raise MessageError(
                    Reason.BAD_SHAPE, f"shape {arr.shape}, want {self.shape}", field=name
                )
        if not np.isfinite(arr).all():
            raise MessageError(Reason.NON_FINITE, "non-finite element", field=name)
        if not ((arr >= np.asarray(self.lo)).all() and (arr <= np.asarray(self.hi)).all()):
            raise MessageError(Reason.OUT_OF_RANGE, "element out of range", field=name)
        if self.unit is not None:
            _check_quaternion(name, arr[self.unit[0] : self.unit[1]])
        arr.flags.writeable = False
        return arr

    def to_wire(self, v: Any) -> Any:
        return None if v is None else v.tolist()


@dataclasses.dataclass(frozen=True)
class ScalarsSpec:
    """A small map ``name -> None | bool | int | float | str`` (event data, command args)."""

    def coerce(self, name: str, v: Any, dims: dict[str, int]) -> Mapping[str, Any]:
        if not isinstance(v, Mapping):
            raise MessageError(Reason.BAD_TYPE, f"expected a map, got {type_name(v)}", field=name)
        if len(v) > MAX_MAP_ITEMS:
            raise MessageError(Reason.OUT_OF_RANGE, f"more than {MAX_MAP_ITEMS} items", field=name)
        out: dict[str, Any] = {}
        for k, x in v.items():
            if not isinstance(k, str) or not IDENT.fullmatch(k):
                raise MessageError(Reason.BAD_TYPE, f"bad key {k!r}", field=name)
            if x is None or isinstance(x, str):
                if isinstance(x, str) and len(x) > MAX_MAP_STR:
                    raise MessageError(Reason.OUT_OF_RANGE, f"{k}: string too long", field=name)
                out[k] = x
            elif _is_bool(x):
                out[k] = bool(x)
            elif (i := _scalar(x, "i")) is not None:
                if not -(2**63) <= i <= MAX_UINT64:
                    raise MessageError(Reason.OUT_OF_RANGE, f"{k}: {i}", field=name)
                out[k] = i
            elif (f := _scalar(x, "f")) is not None:
                if not np.isfinite(f):
                    raise MessageError(Reason.NON_FINITE, f"{k}: {f}", field=name)
                out[k] = f
            else:
                raise MessageError(Reason.BAD_TYPE, f"{k}: {type_name(x)}", field=name)
        return types.MappingProxyType(out)

    def to_wire(self, v: Any) -> Any:
        return dict(v)


def type_name(v: Any) -> str:
    """The type of ``v``, as error details name it."""
    return type(v).__name__


_NUMBER = (float, int, np.floating, np.integer)


def _check_leaves(name: str, v: list) -> None:
    if all(type(x) is float for x in v):  # the wire case, fast
        return
    for x in v:
        if isinstance(x, _NUMBER) and not isinstance(x, bool | np.bool_):
            continue
        if isinstance(x, list):
            raise MessageError(Reason.BAD_SHAPE, "too many nesting levels", field=name)
        raise MessageError(Reason.BAD_TYPE, f"array element is {type_name(x)}", field=name)


def _check_nesting(name: str, v: list, ndim: int) -> None:
    if ndim == 1:
        _check_leaves(name, v)
        return
    for row in v:
        if type(row) is not list:
            raise MessageError(Reason.BAD_SHAPE, f"want {ndim} nesting levels", field=name)
        _check_nesting(name, row, ndim - 1)


def _from_nested(name: str, v: list, ndim: int) -> np.ndarray:
    """Strictly parse nested lists of real numbers (no bools, strings or ragged rows)."""
    _check_nesting(name, v, ndim)
    try:
        arr = np.array(v, dtype=np.float64)
    except OverflowError as e:
        raise MessageError(Reason.OUT_OF_RANGE, "integer too large", field=name) from e
    except ValueError as e:  # inhomogeneous nesting
        raise MessageError(Reason.BAD_SHAPE, "ragged array", field=name) from e
    if arr.ndim != ndim:  # e.g. empty rows
        raise MessageError(Reason.BAD_SHAPE, f"shape {arr.shape}", field=name)
    return arr


def spec_meta(spec: Any) -> dict[str, Any]:
    """Field metadata carrying the validation spec."""
    return {"spec": spec}


def array_meta(shape: tuple[int | str, ...], lo: Any = -np.inf, hi: Any = np.inf, **kw: Any) -> Any:
    """Field metadata carrying an :class:`ArraySpec`."""
    return spec_meta(ArraySpec(shape, lo, hi, **kw))


def _check_quaternion(name: str, q: np.ndarray) -> None:
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise MessageError(Reason.OUT_OF_RANGE, f"quaternion norm {norm}", field=name)
