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
exists is a record that would be accepted on receipt. The base class is in
:mod:`services.message_record`; the field types, the limits and the error are in
:mod:`services.message_fields`; what a receiving service does with a stream
of records (order and staleness checks per publisher, reject counts, handlers that never
raise) is :mod:`services.reception`.

Units and frames follow the project conventions: world ENU, body FLU, SI units; state
``x = [p(3), v(3), q(4, w first), omega(3)]``; input ``u = [collective thrust N,
body-rate setpoints rad/s (3)]``.
"""

from __future__ import annotations

import dataclasses
import types
from collections.abc import Mapping
from dataclasses import field
from typing import Any, ClassVar

import msgpack
import numpy as np

# Rigid bodies on the ``mocap`` topic (the vehicle's frames are the only ones its estimator
# and the PX4 bridge take), defined with the vehicle files.
from arcade_io.vehicle import PAYLOAD_BODY, VEHICLE_BODY
from services.message_fields import (
    COMMANDS,
    COV_TOL,
    EVENT_KINDS,
    IDENT,
    KIND,
    MAX_ABS_VALUE,
    MAX_ACCEL_MPS2,
    MAX_DIMS,
    MAX_POSITION_M,
    MAX_RATE_RADPS,
    MAX_SOLVE_MS,
    MAX_SPEED_MPS,
    MAX_STAMP_S,
    MAX_THRUST_N,
    MAX_VARIANCE,
    MODES,
    QUAT_NORM_TOL,
    SERVICE,
    SEVERITIES,
    BoolSpec,
    FloatSpec,
    IntSpec,
    MessageError,
    Reason,
    ScalarsSpec,
    StrSpec,
    array_meta,
    spec_meta,
    type_name,
)
from services.message_record import Message, _specs

__all__ = [
    "COMMANDS",
    "EVENT_KINDS",
    "MAX_ABS_VALUE",
    "MAX_ACCEL_MPS2",
    "MAX_DIMS",
    "MAX_POSITION_M",
    "MAX_RATE_RADPS",
    "MAX_SOLVE_MS",
    "MAX_SPEED_MPS",
    "MAX_STAMP_S",
    "MAX_THRUST_N",
    "MAX_VARIANCE",
    "MESSAGE_TYPES",
    "MODES",
    "PAYLOAD_BODY",
    "QUAT_NORM_TOL",
    "SEVERITIES",
    "TOPICS",
    "VEHICLE_BODY",
    "Command",
    "Event",
    "Imu",
    "Message",
    "MessageError",
    "Mocap",
    "Model",
    "Reason",
    "Reference",
    "Residual",
    "Setpoint",
    "State",
    "decode",
    "encode",
    "field_specs",
    "message_type",
]

# -------------------------------------------------------------------------- records


def field_specs(cls: type[Message]) -> Mapping[str, Any]:
    """Field name -> validation spec of a record type, in wire order.

    A spec is a frozen dataclass of :mod:`services.message_fields`: ``FloatSpec(lo, hi,
    optional)``, ``IntSpec(lo, hi, optional)``, ``BoolSpec()``, ``StrSpec(pattern, choices,
    max_len)``, ``ArraySpec(shape, lo, hi, optional, unit)`` (shape entries are sizes or
    dimension symbols bounded by :data:`MAX_DIMS`) or ``ScalarsSpec()``. Tools that generate
    or document records (schemas, fuzzers) read these instead of duplicating the limits.
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
        body: rigid-body name in the mocap system (one stream may carry several bodies:
            :meth:`of_vehicle` says which is the vehicle's).
        frame: world frame id.
        capture_stamp: time the frame was captured (same clock as ``stamp``).
    """

    SCHEMA: ClassVar[str] = "arcade.Mocap"
    TOPIC: ClassVar[str] = "mocap"

    position: np.ndarray = field(metadata=array_meta((3,), -_P, _P))
    quaternion: np.ndarray = field(metadata=array_meta((4,), -_Q, _Q, unit=(0, 4)))
    body: str = field(default=VEHICLE_BODY, metadata=spec_meta(StrSpec(pattern=IDENT)))
    frame: str = field(default="world", metadata=spec_meta(StrSpec(pattern=IDENT)))
    capture_stamp: float = field(metadata=spec_meta(FloatSpec(0.0, MAX_STAMP_S)))

    def _check(self) -> None:
        if self.capture_stamp > self.stamp:  # a frame is sent after it is captured
            raise MessageError(
                Reason.OUT_OF_RANGE,
                f"capture_stamp {self.capture_stamp} after stamp {self.stamp}",
                field="capture_stamp",
            )

    def of_vehicle(self, vehicle_body: str) -> bool:
        """Whether this frame is the vehicle's, whose rigid body is named ``vehicle_body``
        (the services' ``--mocap-body``, default :data:`VEHICLE_BODY`)."""
        return self.body == vehicle_body


@dataclasses.dataclass(frozen=True, eq=False, kw_only=True)
class Imu(Message):
    """Inertial sample in body FLU: ``gyro`` ``(3,)`` rad/s, optional ``accel`` ``(3,)`` m/s²."""

    SCHEMA: ClassVar[str] = "arcade.Imu"
    TOPIC: ClassVar[str] = "imu"

    gyro: np.ndarray = field(metadata=array_meta((3,), -MAX_RATE_RADPS, MAX_RATE_RADPS))
    accel: np.ndarray | None = field(
        default=None, metadata=array_meta((3,), -MAX_ACCEL_MPS2, MAX_ACCEL_MPS2, optional=True)
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

    x: np.ndarray = field(metadata=array_meta((13,), _X_LO, _X_HI, unit=(6, 10)))
    cov_diag: np.ndarray | None = field(
        default=None, metadata=array_meta((13,), 0.0, MAX_VARIANCE, optional=True)
    )
    mocap_stale: bool = field(default=False, metadata=spec_meta(BoolSpec()))
    predicted_through_dropout: bool = field(default=False, metadata=spec_meta(BoolSpec()))
    meas_stamp: float | None = field(
        default=None, metadata=spec_meta(FloatSpec(0.0, MAX_STAMP_S, optional=True))
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
        failsafe: the reason of the controller's ``failsafe`` event raised at this instant
            ("" when none). The event stays the vehicle link's trigger in real time; a
            lockstep simulator acts on this field, which arrives with the answer it waits
            for (an event travels at a lower priority and may arrive steps later).
    """

    SCHEMA: ClassVar[str] = "arcade.Setpoint"
    TOPIC: ClassVar[str] = "setpoint"

    u: np.ndarray = field(
        metadata=array_meta((4,), (0.0, -_R, -_R, -_R), (MAX_THRUST_N, _R, _R, _R))
    )
    state_seq: int = field(metadata=spec_meta(IntSpec()))
    mode: str = field(default="track", metadata=spec_meta(StrSpec(choices=MODES)))
    solve_ms: float = field(default=0.0, metadata=spec_meta(FloatSpec(0.0, MAX_SOLVE_MS)))
    failsafe: str = field(default="", metadata=spec_meta(StrSpec()))

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

    delta: np.ndarray = field(metadata=array_meta(("d",), -MAX_ABS_VALUE, MAX_ABS_VALUE))
    mean: np.ndarray = field(metadata=array_meta(("d",), -MAX_ABS_VALUE, MAX_ABS_VALUE))
    var_param: np.ndarray = field(metadata=array_meta(("d",), *_VAR))
    var_between: np.ndarray = field(metadata=array_meta(("d",), *_VAR))
    var_noise: np.ndarray = field(metadata=array_meta(("d",), *_VAR))
    var_encoder: np.ndarray = field(metadata=array_meta(("d",), *_VAR))
    cp_prob: float = field(metadata=spec_meta(FloatSpec(0.0, 1.0)))
    changepoint: bool = field(default=False, metadata=spec_meta(BoolSpec()))
    state_seq: int | None = field(default=None, metadata=spec_meta(IntSpec(optional=True)))

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

    theta: np.ndarray = field(metadata=array_meta(("d", "l"), -MAX_ABS_VALUE, MAX_ABS_VALUE))
    theta_var: np.ndarray | None = field(
        default=None, metadata=array_meta(("d", "l"), *_VAR, optional=True)
    )
    theta_cov: np.ndarray | None = field(
        default=None,
        metadata=array_meta(("d", "l", "l"), -MAX_VARIANCE, MAX_VARIANCE, optional=True),
    )
    sigma_tot2: np.ndarray = field(metadata=array_meta(("d",), *_VAR))
    step: int = field(default=0, metadata=spec_meta(IntSpec()))
    changepoints: int = field(default=0, metadata=spec_meta(IntSpec()))
    state_seq: int | None = field(default=None, metadata=spec_meta(IntSpec(optional=True)))

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
class Reference(Message):
    """The flight plan's reference the controller tracks at one control instant.

    Attributes:
        x: ``(13,)`` reference state ``[p, v, q (w first), omega]`` (flat, nominal model).
        u: ``(4,)`` reference input ``[collective thrust N, body rates rad/s]`` of the
            nominal model.
        t: mission time of the reference [s] (with a link delay: that much after the
            state's instant).
    """

    SCHEMA: ClassVar[str] = "arcade.Reference"
    TOPIC: ClassVar[str] = "reference"

    x: np.ndarray = field(metadata=array_meta((13,), _X_LO, _X_HI, unit=(6, 10)))
    u: np.ndarray = field(
        metadata=array_meta((4,), (0.0, -_R, -_R, -_R), (MAX_THRUST_N, _R, _R, _R))
    )
    t: float = field(metadata=spec_meta(FloatSpec(0.0, MAX_STAMP_S)))


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

    kind: str = field(metadata=spec_meta(StrSpec(pattern=KIND)))
    severity: str = field(default="info", metadata=spec_meta(StrSpec(choices=SEVERITIES)))
    text: str = field(default="", metadata=spec_meta(StrSpec(max_len=1024)))
    data: Mapping[str, Any] = field(default_factory=dict, metadata=spec_meta(ScalarsSpec()))


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

    name: str = field(metadata=spec_meta(StrSpec(choices=COMMANDS)))
    target: str = field(default="", metadata=spec_meta(StrSpec(pattern=SERVICE)))
    args: Mapping[str, Any] = field(default_factory=dict, metadata=spec_meta(ScalarsSpec()))


_TYPES: tuple[type[Message], ...] = (
    Mocap,
    Imu,
    State,
    Setpoint,
    Reference,
    Residual,
    Model,
    Event,
    Command,
)
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
    return record.encode()


def decode(topic_or_schema: str | type[Message] | None, payload: Any) -> Message:
    """Validate ``payload`` (bytes) into a record of the expected type.

    ``topic_or_schema`` is anything :func:`message_type` accepts, or ``None`` to accept any
    known schema. Raises :class:`MessageError` for every defect of the payload.
    """
    cls = None if topic_or_schema is None else message_type(topic_or_schema)
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise MessageError(Reason.NOT_MSGPACK, f"payload is {type_name(payload)}, not bytes")
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
        raise MessageError(Reason.NOT_MAP, f"top level is {type_name(data)}")
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
