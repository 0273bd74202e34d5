"""Wire messages of the service stack: typed records, msgpack codec and validation.

Every message is a frozen dataclass (:class:`Message` subclass) with a schema name, a
version, a per-publisher sequence number ``seq``, a ``stamp`` in seconds (simulated time
in lockstep mode, ``time.monotonic()``-based otherwise) and the publisher id ``src``.

Wire format
-----------
A payload is one msgpack map with string keys::

    {"schema": "arcade.State", "version": 1, "seq": 42, "stamp": 3.02,
     "src": "estimator/1f2e...", "x": [13 floats], "cov_diag": null, ...}

- every field of the record is present (optional ones as ``nil``); no other keys;
- arrays are (nested) msgpack arrays of numbers, row-major, one nesting level per
  dimension; the encoder writes float64 so a record round-trips bit-exactly; integers are
  accepted where a float is expected (other encoders write ``0`` for ``0.0``), booleans and
  strings are not;
- floats must be finite; every field has a documented range (absurd magnitudes, negative
  thrust or variances, non-unit quaternions are rejected);
- a payload larger than the type's ``MAX_BYTES`` is rejected before it is unpacked.

Everything that is wrong with a payload raises :class:`MessageError` with a
:class:`Reason`; records built in Python are validated by the same code, so a record that
exists is a record that would be accepted on receipt. :class:`StreamChecker` rejects
out-of-order and stale messages per publisher, :class:`RejectCounter` counts and logs
rejects (rate limited), and :func:`safe_handler` turns a decoder and a callback into a
function that never raises.

Units and frames follow the project conventions: world ENU, body FLU, SI units; state
``x = [p(3), v(3), q(4, w first), omega(3)]``; input ``u = [collective thrust N,
body-rate setpoints rad/s (3)]``.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import logging
import re
import threading
import time
import types
from collections import Counter, OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import field
from typing import Any, ClassVar, TypeVar

import msgpack
import numpy as np

__all__ = [
    "COMMANDS",
    "EVENT_KINDS",
    "MESSAGE_TYPES",
    "MODES",
    "SEVERITIES",
    "TOPICS",
    "Command",
    "Event",
    "Imu",
    "Message",
    "MessageError",
    "Mocap",
    "Model",
    "Reason",
    "Receiver",
    "RejectCounter",
    "Residual",
    "Setpoint",
    "State",
    "StreamChecker",
    "decode",
    "encode",
    "field_specs",
    "message_type",
    "safe_handler",
]

log = logging.getLogger("arcade.messages")

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
#: full-covariance :class:`Model` grows as ``d l^2``; its ``MAX_BYTES`` is derived from
#: these, so every legal shape can be sent.
MAX_DIMS: Mapping[str, int] = types.MappingProxyType({"d": 64, "l": 64})
#: Relative round-off tolerated by the covariance checks (float32 producers: ~(l + beam) eps).
COV_TOL = 1e-5
MAX_UINT64 = 2**64 - 1
MAX_MAP_ITEMS = 32
MAX_MAP_STR = 256

#: Controller modes a :class:`Setpoint` may carry.
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

_IDENT = re.compile(r"[A-Za-z0-9_.\-]{1,64}")
_SRC = re.compile(r"[A-Za-z0-9_.:/@\-]{0,128}")
_KIND = re.compile(r"[a-z][a-z0-9_]{0,31}")
_SERVICE = re.compile(r"[A-Za-z0-9_.\-]{0,64}")


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
class _Float:
    lo: float = -np.inf
    hi: float = np.inf
    optional: bool = False

    def coerce(self, name: str, v: Any, dims: dict[str, int]) -> float | None:
        if v is None and self.optional:
            return None
        x = _scalar(v, "f")
        if x is None:
            raise MessageError(Reason.BAD_TYPE, f"expected a number, got {_tname(v)}", field=name)
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
class _Int:
    lo: int = 0
    hi: int = MAX_UINT64
    optional: bool = False

    def coerce(self, name: str, v: Any, dims: dict[str, int]) -> int | None:
        if v is None and self.optional:
            return None
        x = _scalar(v, "i")
        if x is None:
            raise MessageError(Reason.BAD_TYPE, f"expected an integer, got {_tname(v)}", field=name)
        if not self.lo <= x <= self.hi:
            raise MessageError(
                Reason.OUT_OF_RANGE, f"{x} not in [{self.lo}, {self.hi}]", field=name
            )
        return x

    def to_wire(self, v: Any) -> Any:
        return v


@dataclasses.dataclass(frozen=True)
class _Bool:
    def coerce(self, name: str, v: Any, dims: dict[str, int]) -> bool:
        if _is_bool(v) or (getattr(v, "shape", None) == () and np.dtype(v.dtype).kind == "b"):
            return bool(v)
        raise MessageError(Reason.BAD_TYPE, f"expected a bool, got {_tname(v)}", field=name)

    def to_wire(self, v: Any) -> Any:
        return v


@dataclasses.dataclass(frozen=True)
class _Str:
    pattern: re.Pattern[str] | None = None
    choices: tuple[str, ...] | None = None
    max_len: int = 64

    def coerce(self, name: str, v: Any, dims: dict[str, int]) -> str:
        if not isinstance(v, str):
            raise MessageError(Reason.BAD_TYPE, f"expected a string, got {_tname(v)}", field=name)
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
class _Array:
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
            raise MessageError(Reason.BAD_TYPE, f"expected an array, got {_tname(v)}", field=name)
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
class _Scalars:
    """A small map ``name -> None | bool | int | float | str`` (event data, command args)."""

    def coerce(self, name: str, v: Any, dims: dict[str, int]) -> Mapping[str, Any]:
        if not isinstance(v, Mapping):
            raise MessageError(Reason.BAD_TYPE, f"expected a map, got {_tname(v)}", field=name)
        if len(v) > MAX_MAP_ITEMS:
            raise MessageError(Reason.OUT_OF_RANGE, f"more than {MAX_MAP_ITEMS} items", field=name)
        out: dict[str, Any] = {}
        for k, x in v.items():
            if not isinstance(k, str) or not _IDENT.fullmatch(k):
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
                raise MessageError(Reason.BAD_TYPE, f"{k}: {_tname(x)}", field=name)
        return types.MappingProxyType(out)

    def to_wire(self, v: Any) -> Any:
        return dict(v)


def _tname(v: Any) -> str:
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
        raise MessageError(Reason.BAD_TYPE, f"array element is {_tname(x)}", field=name)


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


def _m(spec: Any) -> dict[str, Any]:
    """Field metadata carrying the validation spec."""
    return {"spec": spec}


def _arr(shape: tuple[int | str, ...], lo: Any = -np.inf, hi: Any = np.inf, **kw: Any) -> Any:
    return _m(_Array(shape, lo, hi, **kw))


def _check_quaternion(name: str, q: np.ndarray) -> None:
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise MessageError(Reason.OUT_OF_RANGE, f"quaternion norm {norm}", field=name)


# -------------------------------------------------------------------------- records

M = TypeVar("M", bound="Message")


@dataclasses.dataclass(frozen=True, eq=False, kw_only=True)
class Message:
    """Common header of every wire message.

    Attributes:
        seq: per-publisher sequence number (uint64), assigned by the bus publisher.
        stamp: seconds; simulated time in lockstep mode, ``time.monotonic()``-based otherwise.
        src: publisher id, ``"<service>/<session id>"`` when sent through the bus.
    """

    SCHEMA: ClassVar[str] = ""
    VERSION: ClassVar[int] = 1
    TOPIC: ClassVar[str] = ""
    MAX_BYTES: ClassVar[int] = 4096

    seq: int = field(default=0, metadata=_m(_Int()))
    stamp: float = field(metadata=_m(_Float(0.0, MAX_STAMP_S)))
    src: str = field(default="", metadata=_m(_Str(pattern=_SRC, max_len=128)))

    def __post_init__(self) -> None:
        dims: dict[str, int] = {}
        for name, spec in _specs(type(self)).items():
            object.__setattr__(self, name, spec.coerce(name, getattr(self, name), dims))
        self._check()

    def _check(self) -> None:
        """Cross-field checks of a subclass (after every field is valid on its own)."""

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for name in _specs(type(self)):
            a, b = getattr(self, name), getattr(other, name)
            if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
                if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)):
                    return False
                if a.shape != b.shape or not np.array_equal(a, b):
                    return False
            elif a != b:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]  # arrays inside

    def replace(self: M, **changes: Any) -> M:
        """A copy with ``changes`` applied (validated like any new record)."""
        return dataclasses.replace(self, **changes)

    def to_wire(self) -> dict[str, Any]:
        """The msgpack map of this record (plain Python values, also fine for JSON logs)."""
        out: dict[str, Any] = {"schema": self.SCHEMA, "version": self.VERSION}
        for name, spec in _specs(type(self)).items():
            out[name] = spec.to_wire(getattr(self, name))
        return out

    @classmethod
    def from_wire(cls: type[M], data: Mapping[str, Any]) -> M:
        """Validate an unpacked map (schema and version already checked) into a record."""
        names = _specs(cls)
        keys = set(data) - {"schema", "version"}
        if missing := names.keys() - keys:
            raise MessageError(Reason.MISSING_FIELD, f"missing {sorted(missing)}")
        if extra := keys - names.keys():
            raise MessageError(Reason.EXTRA_FIELD, f"unexpected {sorted(map(repr, extra))}")
        return cls(**{name: data[name] for name in names})

    def encode(self) -> bytes:
        """msgpack bytes of this record (see :func:`encode`)."""
        return encode(self)


@functools.cache
def _specs(cls: type[Message]) -> Mapping[str, Any]:
    return types.MappingProxyType({f.name: f.metadata["spec"] for f in dataclasses.fields(cls)})


def field_specs(cls: type[Message]) -> Mapping[str, Any]:
    """Field name -> validation spec of a record type, in wire order.

    A spec is a frozen dataclass: ``_Float(lo, hi, optional)``, ``_Int(lo, hi, optional)``,
    ``_Bool()``, ``_Str(pattern, choices, max_len)``, ``_Array(shape, lo, hi, optional,
    unit)`` (shape entries are sizes or dimension symbols bounded by :data:`MAX_DIMS`) or
    ``_Scalars()``. Tools that generate or document records (schemas, fuzzers) read these
    instead of duplicating the limits.
    """
    return _specs(message_type(cls))


_R, _V = MAX_RATE_RADPS, MAX_SPEED_MPS
_P, _Q = MAX_POSITION_M, 1.0 + QUAT_NORM_TOL
_X_LO = (-_P,) * 3 + (-_V,) * 3 + (-_Q,) * 4 + (-_R,) * 3
_X_HI = (_P,) * 3 + (_V,) * 3 + (_Q,) * 4 + (_R,) * 3


@dataclasses.dataclass(frozen=True, eq=False, kw_only=True)
class Mocap(Message):
    """One motion-capture sample of a rigid body (world ENU, body FLU, SI).

    Attributes:
        position: ``(3,)`` m.
        quaternion: ``(4,)`` unit, ``w`` first, body-to-world.
        body: rigid-body name in the mocap system.
        frame: world frame id.
        capture_stamp: time the frame was captured (same clock as ``stamp``).
    """

    SCHEMA: ClassVar[str] = "arcade.Mocap"
    TOPIC: ClassVar[str] = "mocap"

    position: np.ndarray = field(metadata=_arr((3,), -_P, _P))
    quaternion: np.ndarray = field(metadata=_arr((4,), -_Q, _Q, unit=(0, 4)))
    body: str = field(default="vehicle", metadata=_m(_Str(pattern=_IDENT)))
    frame: str = field(default="world", metadata=_m(_Str(pattern=_IDENT)))
    capture_stamp: float = field(metadata=_m(_Float(0.0, MAX_STAMP_S)))

    def _check(self) -> None:
        if self.capture_stamp > self.stamp:  # a frame is sent after it is captured
            raise MessageError(
                Reason.OUT_OF_RANGE,
                f"capture_stamp {self.capture_stamp} after stamp {self.stamp}",
                field="capture_stamp",
            )


@dataclasses.dataclass(frozen=True, eq=False, kw_only=True)
class Imu(Message):
    """Inertial sample in body FLU: ``gyro`` ``(3,)`` rad/s, optional ``accel`` ``(3,)`` m/s²."""

    SCHEMA: ClassVar[str] = "arcade.Imu"
    TOPIC: ClassVar[str] = "imu"

    gyro: np.ndarray = field(metadata=_arr((3,), -MAX_RATE_RADPS, MAX_RATE_RADPS))
    accel: np.ndarray | None = field(
        default=None, metadata=_arr((3,), -MAX_ACCEL_MPS2, MAX_ACCEL_MPS2, optional=True)
    )


@dataclasses.dataclass(frozen=True, eq=False, kw_only=True)
class State(Message):
    """Estimated vehicle state ``x = [p, v, q (w first), omega]`` (13,), ENU/FLU, SI.

    Attributes:
        x: ``(13,)`` state.
        cov_diag: optional ``(13,)`` marginal variances of ``x``.
        mocap_stale: no fresh mocap sample was fused in the last period.
        predicted_through_dropout: ``x`` is a model prediction across a mocap dropout.
        meas_stamp: capture stamp of the newest fused measurement (sense-to-actuate latency).
    """

    SCHEMA: ClassVar[str] = "arcade.State"
    TOPIC: ClassVar[str] = "state"

    x: np.ndarray = field(metadata=_arr((13,), _X_LO, _X_HI, unit=(6, 10)))
    cov_diag: np.ndarray | None = field(
        default=None, metadata=_arr((13,), 0.0, MAX_VARIANCE, optional=True)
    )
    mocap_stale: bool = field(default=False, metadata=_m(_Bool()))
    predicted_through_dropout: bool = field(default=False, metadata=_m(_Bool()))
    meas_stamp: float | None = field(
        default=None, metadata=_m(_Float(0.0, MAX_STAMP_S, optional=True))
    )

    def _check(self) -> None:
        # A measurement from the future would make its age negative and pass every
        # staleness check downstream.
        if self.meas_stamp is not None and self.meas_stamp > self.stamp:
            raise MessageError(
                Reason.OUT_OF_RANGE,
                f"meas_stamp {self.meas_stamp} after stamp {self.stamp}",
                field="meas_stamp",
            )

    @classmethod
    def from_parts(cls, *, p: Any, v: Any, q: Any, omega: Any, **kw: Any) -> State:
        """Build from the four components (array-likes: numpy, JAX, lists)."""
        parts = [np.asarray(a, dtype=np.float64).reshape(-1) for a in (p, v, q, omega)]
        return cls(x=np.concatenate(parts), **kw)

    @property
    def p(self) -> np.ndarray:
        """Position ``(3,)`` m, world ENU."""
        return self.x[0:3]

    @property
    def v(self) -> np.ndarray:
        """Velocity ``(3,)`` m/s, world ENU."""
        return self.x[3:6]

    @property
    def q(self) -> np.ndarray:
        """Attitude quaternion ``(4,)``, ``w`` first, body FLU to world ENU."""
        return self.x[6:10]

    @property
    def omega(self) -> np.ndarray:
        """Body rates ``(3,)`` rad/s, body FLU."""
        return self.x[10:13]


@dataclasses.dataclass(frozen=True, eq=False, kw_only=True)
class Setpoint(Message):
    """Controller output ``u = [collective thrust N, body rates rad/s (3)]``.

    Attributes:
        u: ``(4,)`` input; thrust in ``[0, MAX_THRUST_N]``.
        state_seq: ``seq`` of the :class:`State` this setpoint answers (lockstep pairing).
        mode: one of :data:`MODES`.
        solve_ms: controller computation time for this setpoint.
    """

    SCHEMA: ClassVar[str] = "arcade.Setpoint"
    TOPIC: ClassVar[str] = "setpoint"

    u: np.ndarray = field(metadata=_arr((4,), (0.0, -_R, -_R, -_R), (MAX_THRUST_N, _R, _R, _R)))
    state_seq: int = field(metadata=_m(_Int()))
    mode: str = field(default="track", metadata=_m(_Str(choices=MODES)))
    solve_ms: float = field(default=0.0, metadata=_m(_Float(0.0, MAX_SOLVE_MS)))

    @property
    def thrust(self) -> float:
        """Collective thrust, N."""
        return float(self.u[0])

    @property
    def rates(self) -> np.ndarray:
        """Body-rate setpoints ``(3,)`` rad/s, FLU."""
        return self.u[1:4]


_VAR = (0.0, MAX_VARIANCE)


def _model_max_bytes(d: int, l: int) -> int:
    """Encoded size bound of a :class:`Model` of dimensions ``d, l``: every float as a
    msgpack float64 (9 bytes), every (nested) array header at most 5 bytes, and 1 KiB for
    the header fields and names."""
    floats = 2 * d * l + d * l * l + d
    arrays = (1 + d) * 2 + (1 + d + d * l) + 1
    return 9 * floats + 5 * arrays + 1024


@dataclasses.dataclass(frozen=True, eq=False, kw_only=True)
class Residual(Message):
    """One adaptation step: observed residual and its beam-marginal prediction (Eq. 10).

    All arrays are ``(d,)``. The predictive variance splits as in Sec. IV:
    ``var_param + var_between + var_noise + var_encoder``.

    Attributes:
        delta: observed residual ``x_{k+1} - f_nom(x_k, u_k)`` (units of the adapter).
        mean: predicted residual before the update.
        var_param, var_between, var_noise, var_encoder: variance parts.
        cp_prob: beam-weighted changepoint posterior (Eq. 9), in ``[0, 1]``.
        changepoint: the MAP history gained a changepoint at this step (Algorithm 1).
        state_seq: ``seq`` of the newest :class:`State` used, if known.
    """

    SCHEMA: ClassVar[str] = "arcade.Residual"
    TOPIC: ClassVar[str] = "residual"
    MAX_BYTES: ClassVar[int] = 16384

    delta: np.ndarray = field(metadata=_arr(("d",), -MAX_ABS_VALUE, MAX_ABS_VALUE))
    mean: np.ndarray = field(metadata=_arr(("d",), -MAX_ABS_VALUE, MAX_ABS_VALUE))
    var_param: np.ndarray = field(metadata=_arr(("d",), *_VAR))
    var_between: np.ndarray = field(metadata=_arr(("d",), *_VAR))
    var_noise: np.ndarray = field(metadata=_arr(("d",), *_VAR))
    var_encoder: np.ndarray = field(metadata=_arr(("d",), *_VAR))
    cp_prob: float = field(metadata=_m(_Float(0.0, 1.0)))
    changepoint: bool = field(default=False, metadata=_m(_Bool()))
    state_seq: int | None = field(default=None, metadata=_m(_Int(optional=True)))

    @classmethod
    def from_prediction(cls, delta: Any, prediction: Any, **kw: Any) -> Residual:
        """Build from an observed ``delta`` and a prediction with the fields of
        ``arcade_core.adaptation.Prediction`` (``mean, param, between, noise, encoder``)."""
        return cls(
            delta=delta,
            mean=prediction.mean,
            var_param=prediction.param,
            var_between=prediction.between,
            var_noise=prediction.noise,
            var_encoder=prediction.encoder,
            **kw,
        )

    @property
    def sigma_tot2(self) -> np.ndarray:
        """Sec. IV total predictive variance (encoder + parameter + between, no noise)."""
        return self.var_encoder + self.var_param + self.var_between

    @property
    def variance(self) -> np.ndarray:
        """Full predictive variance of the Eq. 10 mixture (``sigma_tot2`` plus noise)."""
        return self.sigma_tot2 + self.var_noise


@dataclasses.dataclass(frozen=True, eq=False, kw_only=True)
class Model(Message):
    """Beam-marginal decoder posterior for the controller (Eq. 10 moment-matched mixture).

    Attributes:
        theta: ``(d, l)`` posterior mean of the decoder.
        theta_var: optional ``(d, l)`` marginal variances (diagonal of ``theta_cov``).
        theta_cov: optional ``(d, l, l)`` per-output-row covariance, for ``z^T Sigma z``.
        sigma_tot2: ``(d,)`` Sec. IV total predictive variance at the latest step.
        step: adapter step count.
        changepoints: number of changepoints detected so far.
        state_seq: ``seq`` of the newest :class:`State` used, if known.
    """

    SCHEMA: ClassVar[str] = "arcade.Model"
    TOPIC: ClassVar[str] = "model"
    MAX_BYTES: ClassVar[int] = _model_max_bytes(MAX_DIMS["d"], MAX_DIMS["l"])

    theta: np.ndarray = field(metadata=_arr(("d", "l"), -MAX_ABS_VALUE, MAX_ABS_VALUE))
    theta_var: np.ndarray | None = field(
        default=None, metadata=_arr(("d", "l"), *_VAR, optional=True)
    )
    theta_cov: np.ndarray | None = field(
        default=None, metadata=_arr(("d", "l", "l"), -MAX_VARIANCE, MAX_VARIANCE, optional=True)
    )
    sigma_tot2: np.ndarray = field(metadata=_arr(("d",), *_VAR))
    step: int = field(default=0, metadata=_m(_Int()))
    changepoints: int = field(default=0, metadata=_m(_Int()))
    state_seq: int | None = field(default=None, metadata=_m(_Int(optional=True)))

    def _check(self) -> None:
        cov = self.theta_cov
        if cov is None:
            return
        diag = np.diagonal(cov, 0, 1, 2)
        if (diag < 0).any():
            raise MessageError(Reason.OUT_OF_RANGE, "negative variance", field="theta_cov")
        # Symmetric, and every 2x2 principal minor non-negative (|C_ij| <= sqrt(C_ii C_jj)):
        # cheap necessary conditions of positive semi-definiteness (a full eigenvalue check
        # costs ~0.1 s at the largest legal shape). Anything else makes the controller's
        # Cholesky factor non-finite.
        root = np.sqrt(diag)
        scale = root[:, :, None] * root[:, None, :]  # no underflow of tiny variances
        tol = COV_TOL * (scale + diag.max(axis=1)[:, None, None]) + 1e-300
        if (np.abs(cov - np.swapaxes(cov, 1, 2)) > tol).any():
            raise MessageError(Reason.OUT_OF_RANGE, "not symmetric", field="theta_cov")
        if (np.abs(cov) > scale + tol).any():
            raise MessageError(Reason.OUT_OF_RANGE, "not positive semi-definite", field="theta_cov")

    @classmethod
    def from_marginal(
        cls, theta: Any, cov: Any, sigma_tot2: Any, *, full_cov: bool = True, **kw: Any
    ) -> Model:
        """Build from ``arcade_core.adaptation.marginal_decoder`` output ``(mean, cov)``.

        ``theta_var`` is the diagonal of ``cov``; ``theta_cov`` is sent when ``full_cov``.
        """
        cov = np.asarray(cov, dtype=np.float64)
        return cls(
            theta=theta,
            theta_var=np.diagonal(cov, 0, 1, 2),
            theta_cov=cov if full_cov else None,
            sigma_tot2=sigma_tot2,
            **kw,
        )


@dataclasses.dataclass(frozen=True, eq=False, kw_only=True)
class Event(Message):
    """Something operators and other services should know (changepoint, failsafe, ...).

    Attributes:
        kind: short identifier, see :data:`EVENT_KINDS`.
        severity: one of :data:`SEVERITIES`.
        text: human-readable description (at most 1024 characters).
        data: up to 32 ``name -> None | bool | int | float | str`` items.
    """

    SCHEMA: ClassVar[str] = "arcade.Event"
    TOPIC: ClassVar[str] = "event"
    MAX_BYTES: ClassVar[int] = 16384

    kind: str = field(metadata=_m(_Str(pattern=_KIND)))
    severity: str = field(default="info", metadata=_m(_Str(choices=SEVERITIES)))
    text: str = field(default="", metadata=_m(_Str(max_len=1024)))
    data: Mapping[str, Any] = field(default_factory=dict, metadata=_m(_Scalars()))


@dataclasses.dataclass(frozen=True, eq=False, kw_only=True)
class Command(Message):
    """Operator command.

    Attributes:
        name: one of :data:`COMMANDS`.
        target: service that should act (``""``: every service that knows the command).
        args: up to 32 ``name -> None | bool | int | float | str`` items.
    """

    SCHEMA: ClassVar[str] = "arcade.Command"
    TOPIC: ClassVar[str] = "command"
    MAX_BYTES: ClassVar[int] = 8192

    name: str = field(metadata=_m(_Str(choices=COMMANDS)))
    target: str = field(default="", metadata=_m(_Str(pattern=_SERVICE)))
    args: Mapping[str, Any] = field(default_factory=dict, metadata=_m(_Scalars()))


_TYPES: tuple[type[Message], ...] = (Mocap, Imu, State, Setpoint, Residual, Model, Event, Command)
#: Topic name -> record type.
MESSAGE_TYPES: Mapping[str, type[Message]] = types.MappingProxyType({t.TOPIC: t for t in _TYPES})
#: Every topic, in data-flow order.
TOPICS: tuple[str, ...] = tuple(MESSAGE_TYPES)
_BY_SCHEMA: Mapping[str, type[Message]] = types.MappingProxyType({t.SCHEMA: t for t in _TYPES})
_MAX_ANY = max(t.MAX_BYTES for t in _TYPES)


# ---------------------------------------------------------------------------- codec


def message_type(topic_or_schema: str | type[Message]) -> type[Message]:
    """Record type for a topic (``"state"``), key expression (``"arcade/v1/state"``),
    schema name (``"arcade.State"``) or the type itself. Raises ``KeyError`` if unknown."""
    if isinstance(topic_or_schema, type) and issubclass(topic_or_schema, Message):
        if topic_or_schema not in _TYPES:
            raise KeyError(topic_or_schema)
        return topic_or_schema
    name = str(topic_or_schema)
    if name in _BY_SCHEMA:
        return _BY_SCHEMA[name]
    return MESSAGE_TYPES[name.rsplit("/", 1)[-1]]


def encode(record: Message) -> bytes:
    """msgpack bytes of ``record``; raises :class:`MessageError` if above ``MAX_BYTES``."""
    payload = msgpack.packb(record.to_wire(), use_bin_type=True)
    if len(payload) > record.MAX_BYTES:
        raise MessageError(Reason.OVERSIZE, f"{len(payload)} > {record.MAX_BYTES} bytes")
    return payload


def decode(topic_or_schema: str | type[Message] | None, payload: Any) -> Message:
    """Validate ``payload`` (bytes) into a record of the expected type.

    ``topic_or_schema`` is anything :func:`message_type` accepts, or ``None`` to accept any
    known schema. Raises :class:`MessageError` for every defect of the payload.
    """
    cls = None if topic_or_schema is None else message_type(topic_or_schema)
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise MessageError(Reason.NOT_MSGPACK, f"payload is {_tname(payload)}, not bytes")
    cap = _MAX_ANY if cls is None else cls.MAX_BYTES
    size = len(payload)
    if size > cap:
        raise MessageError(Reason.OVERSIZE, f"{size} > {cap} bytes")
    if size == 0:
        raise MessageError(Reason.NOT_MSGPACK, "empty payload")
    try:
        data = msgpack.unpackb(payload, raw=False, strict_map_key=True, use_list=True)
    except Exception as e:  # the unpacker's error types vary (ExtraData, StackError, ...)
        raise MessageError(Reason.NOT_MSGPACK, f"{type(e).__name__}: {e}") from e
    if type(data) is not dict:
        raise MessageError(Reason.NOT_MAP, f"top level is {_tname(data)}")
    schema = data.get("schema")
    if cls is None:
        cls = _BY_SCHEMA.get(schema) if isinstance(schema, str) else None
        if cls is None:
            raise MessageError(Reason.BAD_SCHEMA, f"unknown schema {schema!r}")
        if size > cls.MAX_BYTES:
            raise MessageError(Reason.OVERSIZE, f"{size} > {cls.MAX_BYTES} bytes")
    elif schema != cls.SCHEMA:
        raise MessageError(Reason.BAD_SCHEMA, f"schema {schema!r}, want {cls.SCHEMA!r}")
    version = data.get("version")
    if type(version) is not int or version != cls.VERSION:
        raise MessageError(Reason.BAD_VERSION, f"version {version!r}, want {cls.VERSION}")
    try:
        return cls.from_wire(data)
    except MessageError:
        raise
    except Exception as e:  # never let a malformed payload escape as another type
        raise MessageError(Reason.BAD_TYPE, f"{type(e).__name__}: {e}") from e


# ------------------------------------------------------------------- stream checks


class StreamChecker:
    """Rejects out-of-order and stale messages, per publisher (``src``).

    A message is accepted when its ``seq`` is larger than the last accepted ``seq`` of the
    same publisher and its ``stamp`` is not older than the last accepted ``stamp``
    (equal stamps are fine: several messages may share one lockstep instant). With
    ``max_age`` and a ``clock`` on the stamps' time base, messages older than ``max_age``
    seconds are stale too. A restarted publisher has a new ``src`` (the bus appends its
    session id), so it starts a new stream. Thread-safe.

    One message stamped in the future would otherwise make every later one of its
    publisher stale: after ``reanchor_after`` consecutive stale stamps from one publisher
    (its ``seq`` still increasing), the next one is accepted and becomes the reference
    (counted in :attr:`reanchored`, logged). This needs no clock shared with the
    publisher: realtime stamps are ``time.monotonic()`` of the publisher's host, lockstep
    stamps simulated time.
    """

    def __init__(
        self,
        *,
        max_age: float | None = None,
        clock: Callable[[], float] | None = None,
        max_publishers: int = 64,
        reanchor_after: int = 10,
    ):
        if (max_age is None) != (clock is None):
            raise ValueError("max_age and clock go together")
        if reanchor_after < 1:
            raise ValueError(f"reanchor_after must be >= 1, not {reanchor_after}")
        self.max_age, self.clock, self.max_publishers = max_age, clock, max_publishers
        self.reanchor_after = reanchor_after
        self._last: OrderedDict[str, tuple[int, float]] = OrderedDict()
        self._stale_run: dict[str, int] = {}  # consecutive stale stamps per publisher
        self._lock = threading.Lock()
        self.accepted = 0
        #: Sequence numbers skipped by accepted messages (messages lost on the way).
        self.gaps = 0
        #: Streams whose stamp reference was reset after ``reanchor_after`` stale stamps.
        self.reanchored = 0

    def stats(self) -> dict[str, int]:
        """``accepted``, ``gaps`` and ``reanchored`` counts (for the statistics files)."""
        with self._lock:
            return {"accepted": self.accepted, "gaps": self.gaps, "reanchored": self.reanchored}

    def check(self, record: Message) -> None:
        """Accept ``record`` (and remember it) or raise :class:`MessageError`."""
        if self.max_age is not None and self.clock is not None:
            age = self.clock() - record.stamp
            if age > self.max_age:
                raise MessageError(Reason.STALE, f"{age:.3f} s old > {self.max_age} s")
        with self._lock:
            last = self._last.get(record.src)
            if last is not None:
                seq, stamp = last
                if record.seq <= seq:
                    raise MessageError(
                        Reason.OUT_OF_ORDER, f"seq {record.seq} after {seq} from {record.src!r}"
                    )
                if record.stamp < stamp:
                    run = self._stale_run.get(record.src, 0)
                    if run < self.reanchor_after:
                        self._stale_run[record.src] = run + 1
                        raise MessageError(
                            Reason.STALE,
                            f"stamp {record.stamp} after {stamp} from {record.src!r}",
                        )
                    self.reanchored += 1
                    log.warning(
                        "stamps from %r re-anchored at %s after %d stale ones (reference %s "
                        "was from the future or the publisher's clock went back)",
                        record.src,
                        record.stamp,
                        run,
                        stamp,
                    )
                self.gaps += record.seq - seq - 1
            self._stale_run.pop(record.src, None)
            self._last[record.src] = (record.seq, record.stamp)
            self._last.move_to_end(record.src)
            if len(self._last) > self.max_publishers:
                src, _ = self._last.popitem(last=False)
                self._stale_run.pop(src, None)
            self.accepted += 1

    def reset(self, src: str | None = None) -> None:
        """Forget one publisher (or all)."""
        with self._lock:
            if src is None:
                self._last.clear()
                self._stale_run.clear()
            else:
                self._last.pop(src, None)
                self._stale_run.pop(src, None)


class Receiver:
    """``payload -> record`` decoder for one topic with per-publisher order checks.

    ``check_order=False`` skips the :class:`StreamChecker` (e.g. for a recorder that wants
    everything); ``max_age``/``clock`` are passed to it.
    """

    def __init__(
        self,
        topic_or_schema: str | type[Message],
        *,
        check_order: bool = True,
        max_age: float | None = None,
        clock: Callable[[], float] | None = None,
    ):
        self.type = message_type(topic_or_schema)
        self.checker = StreamChecker(max_age=max_age, clock=clock) if check_order else None

    def __call__(self, payload: Any) -> Message:
        record = decode(self.type, payload)
        if self.checker is not None:
            self.checker.check(record)
        return record


# -------------------------------------------------------------------- reject counts


class RejectCounter:
    """Counts rejected messages by reason (and topic) and logs them, rate limited.

    Each ``(topic, reason)`` pair logs at most one line per ``log_interval`` seconds; the
    next line says how many were suppressed meanwhile. Thread-safe; :meth:`wait_total`
    lets a caller block until a number of rejects has been counted.

    A callback that fails on a valid message is the receiving ``service``'s own failure,
    not a rejected input: :meth:`failure` counts it apart (:attr:`failures`, per topic)
    and logs "<service> failed handling a <topic> message", rate limited the same way.
    """

    def __init__(
        self,
        *,
        logger: logging.Logger | None = None,
        log_interval: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
        service: str = "",
    ):
        self.logger = logger or log
        self.log_interval = log_interval
        self.clock = clock
        self.service = service
        self._counts: Counter[tuple[str, Reason]] = Counter()
        self._failures: Counter[str] = Counter()
        self._last_log: dict[tuple[str, Reason | None], float] = {}
        self._suppressed: Counter[tuple[str, Reason | None]] = Counter()
        self._cond = threading.Condition()

    def _due(self, key: tuple[str, Reason | None]) -> tuple[bool, int]:
        """Whether ``key`` logs now, and how many of its lines were suppressed (locked)."""
        now = self.clock()
        last = self._last_log.get(key)
        if last is None or now - last >= self.log_interval:
            self._last_log[key] = now
            return True, self._suppressed.pop(key, 0)
        self._suppressed[key] += 1
        return False, 0

    def reject(
        self, error: MessageError, *, topic: str = "", exc: BaseException | None = None
    ) -> None:
        """Count one reject and log it unless this ``(topic, reason)`` logged recently."""
        key = (topic, error.reason)
        with self._cond:
            self._counts[key] += 1
            emit, suppressed = self._due(key)
            self._cond.notify_all()
        if emit:
            more = f" ({suppressed} more suppressed)" if suppressed else ""
            self.logger.warning(
                "rejected %s message: %s%s", topic or "a", error, more, exc_info=exc
            )

    def failure(self, exc: BaseException, *, topic: str = "") -> None:
        """Count one failure of this service's own callback on a valid ``topic`` message
        and log it with its traceback unless that topic's failures logged recently."""
        with self._cond:
            self._failures[topic] += 1
            emit, suppressed = self._due((topic, None))
            self._cond.notify_all()
        if emit:
            more = f" ({suppressed} more suppressed)" if suppressed else ""
            self.logger.error(
                "%s failed handling a %s message: %r%s",
                self.service or "service",
                topic or "",
                exc,
                more,
                exc_info=exc,
            )

    @property
    def failures(self) -> dict[str, int]:
        """Callback failures by topic (see :meth:`failure`)."""
        with self._cond:
            return dict(self._failures)

    @property
    def counts(self) -> dict[str, int]:
        """Rejects by reason code."""
        with self._cond:
            out: Counter[str] = Counter()
            for (_, reason), n in self._counts.items():
                out[reason.value] += n
            return dict(out)

    @property
    def by_topic(self) -> dict[tuple[str, str], int]:
        """Rejects by ``(topic, reason code)``."""
        with self._cond:
            return {(t, r.value): n for (t, r), n in self._counts.items()}

    @property
    def total(self) -> int:
        with self._cond:
            return sum(self._counts.values())

    def wait_total(self, n: int, timeout: float) -> bool:
        """Block until at least ``n`` rejects were counted; ``False`` on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: sum(self._counts.values()) >= n, timeout)

    def wait_failures(self, n: int, timeout: float) -> bool:
        """Block until at least ``n`` callback failures were counted; ``False`` on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: sum(self._failures.values()) >= n, timeout)


def safe_handler(
    decoder: Callable[[Any], M],
    callback: Callable[[M], Any],
    counter: RejectCounter,
    *,
    topic: str = "",
) -> Callable[[Any], None]:
    """``payload -> None`` that decodes, calls ``callback`` and never raises.

    A :class:`MessageError` from ``decoder`` is counted under its reason and any other
    exception of the decoder as ``internal`` (rejected input); an exception of the
    callback is the service's own failure, counted by :meth:`RejectCounter.failure`
    (logged with its traceback).
    """

    def handle(payload: Any) -> None:
        try:
            record = decoder(payload)
        except MessageError as e:
            counter.reject(e, topic=topic)
            return
        except Exception as e:
            counter.reject(MessageError(Reason.INTERNAL, repr(e)), topic=topic, exc=e)
            return
        try:
            callback(record)
        except Exception as e:
            counter.failure(e, topic=topic)

    return handle
