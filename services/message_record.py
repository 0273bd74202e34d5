"""The record base class every wire message of :mod:`services.messages` derives from.

:class:`Message` is the common header (``seq``, ``stamp``, ``src``) and what every record
does with its fields: validation on construction (each field by its spec, then the
record's cross-field checks), equality over arrays, ``replace``, and the msgpack map and
bytes of the wire format. The record types themselves, the topic table and the codec are
in :mod:`services.messages`; the field specs and :class:`MessageError` in
:mod:`services.message_fields`.
"""

from __future__ import annotations

import dataclasses
import functools
import types
from collections.abc import Mapping
from dataclasses import field
from typing import Any, ClassVar, TypeVar

import msgpack
import numpy as np

from services.message_fields import (
    MAX_STAMP_S,
    SRC,
    FloatSpec,
    IntSpec,
    MessageError,
    Reason,
    StrSpec,
    spec_meta,
)

__all__ = ["Message"]

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

    seq: int = field(default=0, metadata=spec_meta(IntSpec()))
    stamp: float = field(metadata=spec_meta(FloatSpec(0.0, MAX_STAMP_S)))
    src: str = field(default="", metadata=spec_meta(StrSpec(pattern=SRC, max_len=128)))

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
        """msgpack bytes of this record; raises :class:`MessageError` if above
        ``MAX_BYTES`` (what :func:`services.messages.encode` returns)."""
        payload = msgpack.packb(self.to_wire(), use_bin_type=True)
        if len(payload) > self.MAX_BYTES:
            raise MessageError(Reason.OVERSIZE, f"{len(payload)} > {self.MAX_BYTES} bytes")
        return payload


@functools.cache
def _specs(cls: type[Message]) -> Mapping[str, Any]:
    return types.MappingProxyType({f.name: f.metadata["spec"] for f in dataclasses.fields(cls)})
