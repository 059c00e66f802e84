"""Messages on and off the wire: every type (:data:`MESSAGES`), encoding, and the checks on receipt (size, codec,
field types, the type's own ``check``) that raise :class:`MessageError`; the in-process counterpart
(:func:`accept`) and the stats families of ``ebrl/stats/<run>/**``."""

from __future__ import annotations

import dataclasses
import typing
from typing import Any, TypeVar

import numpy as np

from ebrl import codec, keys, typecheck
from ebrl.messages.common import SCHEMA_VERSION, MessageError, OversizedError
from ebrl.messages.control import Affinity, GpuShare, Quota, Stop
from ebrl.messages.replay import ReplayRequest, ReplaySample
from ebrl.messages.rollout import ActionChunk, Observation, SegmentBatch, TrajectorySegment
from ebrl.messages.stats import EpisodeBatch, Event, SpanBatch, StatsReport
from ebrl.messages.weights import Weights, WeightsPart

T = TypeVar("T")

MESSAGES: tuple[type, ...] = (
    Observation,
    ActionChunk,
    TrajectorySegment,
    SegmentBatch,
    ReplayRequest,
    ReplaySample,
    Weights,
    WeightsPart,
    StatsReport,
    SpanBatch,
    Event,
    EpisodeBatch,
    Stop,
    Affinity,
    Quota,
    GpuShare,
)


def to_wire(msg: Any) -> dict[str, Any]:
    """The msgpack-able map of a message (shallow: arrays stay arrays)."""
    out = {f.name: getattr(msg, f.name) for f in dataclasses.fields(msg)}
    out["v"] = SCHEMA_VERSION
    return out


def encode_message(msg: Any) -> bytes:
    return codec.encode(to_wire(msg))


def decode_message(cls: type[T], payload: bytes | memoryview) -> T:
    """Decode and validate ``payload`` as ``cls``; raise :class:`MessageError` if it is not one (an
    :class:`OversizedError` before decoding anything when it is over ``cls.MAX_BYTES``)."""
    limit = getattr(cls, "MAX_BYTES", None)
    if limit is not None and len(payload) > limit:
        raise OversizedError(f"{cls.__name__}: {len(payload)} bytes, over its limit of {limit}")
    try:
        raw = codec.decode(payload)
    except codec.DecodeError as exc:
        raise MessageError(f"undecodable payload: {exc}") from None
    return from_wire(cls, raw)


def accept(cls: type[T], msg: Any) -> T:
    """The in-process counterpart of :func:`decode_message`, for a message handed over by reference between
    services of one process (``ebrl.bus.local``): ``msg`` must be a ``cls``; it is checked exactly as a decoded
    one (types, shapes, meaning) and comes back as a new ``cls`` whose arrays are read-only views of the
    sender's: nothing is copied, and neither side can change what the other holds through it."""
    if type(msg) is not cls:
        raise MessageError(f"{cls.__name__}: got a {type(msg).__name__} in the process")
    raw = {f.name: _read_only(getattr(msg, f.name)) for f in dataclasses.fields(cls)}
    raw["v"] = SCHEMA_VERSION
    return from_wire(cls, raw)


def _read_only(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        value = value.view()
        value.flags.writeable = False
    return value


def array_bytes(msg: Any) -> int:
    """The bytes of a message's arrays: what its payload would be, less the small header (a bound on a message
    passed by reference is checked on it before it is accepted)."""
    return sum(v.nbytes for v in vars(msg).values() if isinstance(v, np.ndarray))


def from_wire(cls: type[T], raw: Any) -> T:
    if not isinstance(raw, dict):
        raise MessageError(f"{cls.__name__}: expected a map, got {type(raw).__name__}")
    version = raw.get("v")
    if type(version) is not int or version != SCHEMA_VERSION:  # an array's != is elementwise; True == 1
        shown = version if type(version) is int else typecheck.describe(version)
        raise MessageError(f"{cls.__name__}: schema version {shown}, expected {SCHEMA_VERSION}")
    hints = type_hints(cls)
    values = {}
    for f in dataclasses.fields(cls):
        if f.name in raw:
            values[f.name] = typecheck.check(raw[f.name], hints[f.name], f"{cls.__name__}.{f.name}", MessageError)
        elif f.default is dataclasses.MISSING:
            raise MessageError(f"{cls.__name__}: missing field {f.name!r}")
    unknown = set(raw) - set(hints) - {"v"}
    if unknown:
        raise MessageError(f"{cls.__name__}: unknown fields {sorted(unknown, key=repr)}")  # str and bytes keys
    msg = cls(**values)
    check = getattr(msg, "check", None)
    if check is not None:
        try:
            check()
        except MessageError:
            raise
        except Exception as exc:  # a check that trips over a value it did not expect: still a bad message
            raise MessageError(f"{cls.__name__}: {type(exc).__name__}: {exc}") from None
    return msg


_HINTS: dict[type, dict[str, Any]] = {}


def type_hints(cls: type) -> dict[str, Any]:
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls, include_extras=True)
    return _HINTS[cls]


STATS_FAMILIES: dict[str, type] = {"spans": SpanBatch, "events": Event, "episodes": EpisodeBatch}


def decode_stats_sample(key: str, payload: bytes | memoryview) -> "StatsReport | SpanBatch | Event | EpisodeBatch":
    """Decode a sample from ``ebrl/stats/<run>/**``: a ``SpanBatch`` on ``spans/<lane>``, an ``Event``
    on ``events/<service>``, an ``EpisodeBatch`` on ``episodes/<service>``, else a ``StatsReport``; raise
    :class:`MessageError` if it is none. Its ``local`` accepts one handed over in the process
    (``ebrl.bus.local``)."""
    return decode_message(_stats_class(key), payload)  # type: ignore[return-value]


def _stats_class(key: str) -> type:
    try:
        family = keys.parse(key).family
    except ValueError:
        family = "report"
    return STATS_FAMILIES.get(family, StatsReport)


decode_stats_sample.local = lambda key, msg: accept(_stats_class(key), msg)  # type: ignore[attr-defined]
