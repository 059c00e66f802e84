"""Every message on the EBRL bus, defined once; ``schemas/`` is generated from here.

A message is a dataclass whose fields carry a docstring (``doc``). On receipt :func:`decode_message`
checks, in this order, and raises :class:`MessageError` (services count it and drop the message):

1. the payload's size against the type's ``MAX_BYTES``, before anything is decoded
   (:class:`OversizedError`; a weights part, a segment and a stats report have different limits);
2. the msgpack and array headers (:mod:`ebrl.codec`: bounded lengths, exact byte counts);
3. every field's type (:mod:`ebrl.typecheck`);
4. the message's meaning (its ``check`` method): per-decision fields of one length, finite values, counts
   and versions in range.

What only the receiver knows (the policy's shapes, the weights' layout, which instances exist) it checks
itself. On the wire a message is a msgpack map of its fields plus ``"v"`` (the schema version); arrays
travel through :mod:`ebrl.codec`.

The package holds them by family, and exports every name here (``from ebrl.messages import Observation``):

* :mod:`ebrl.messages.common`: the errors, size limits and field docstrings every type shares;
* :mod:`ebrl.messages.rollout`: observations, action chunks, segments; :mod:`ebrl.messages.replay`;
  :mod:`ebrl.messages.weights`; :mod:`ebrl.messages.stats` (reports, spans, events, episodes);
  :mod:`ebrl.messages.control` (stop, affinity, quota, GPU share);
* :mod:`ebrl.messages.wire`: :data:`MESSAGES`, encoding and the checks on receipt;
  :mod:`ebrl.messages.schema`: the JSON Schemas.
"""

from ebrl.messages.common import (CONTROL_MAX_BYTES, DATA_MAX_BYTES, KIB, MAX_METRICS, MAX_TEXT, MAX_VERSION, MIB,
                                  SCHEMA_VERSION, MessageError, OversizedError, doc)
from ebrl.messages.control import GPU_SHARE_VARIABLES, Affinity, GpuShare, Quota, Stop
from ebrl.messages.replay import TRANSITION_FIELDS, ReplayRequest, ReplaySample
from ebrl.messages.rollout import SEGMENT_ENDS, ActionChunk, Observation, SegmentBatch, TrajectorySegment
from ebrl.messages.stats import EPISODES_MAX, RETURN_WINDOW, EpisodeBatch, Event, Span, SpanBatch, StatsReport
from ebrl.messages.weights import Weights, WeightsPart
from ebrl.messages.wire import (MESSAGES, STATS_FAMILIES, accept, array_bytes, decode_message, decode_stats_sample,
                                encode_message, from_wire, to_wire)
from ebrl.messages.schema import json_schema, write_schemas

__all__ = [
    "CONTROL_MAX_BYTES", "DATA_MAX_BYTES", "KIB", "MAX_METRICS", "MAX_TEXT", "MAX_VERSION", "MIB", "SCHEMA_VERSION",
    "MessageError", "OversizedError", "doc",
    "GPU_SHARE_VARIABLES", "Affinity", "GpuShare", "Quota", "Stop",
    "TRANSITION_FIELDS", "ReplayRequest", "ReplaySample",
    "SEGMENT_ENDS", "ActionChunk", "Observation", "SegmentBatch", "TrajectorySegment",
    "EPISODES_MAX", "RETURN_WINDOW", "EpisodeBatch", "Event", "Span", "SpanBatch", "StatsReport",
    "Weights", "WeightsPart",
    "MESSAGES", "STATS_FAMILIES", "accept", "array_bytes", "decode_message", "decode_stats_sample", "encode_message",
    "from_wire", "to_wire",
    "json_schema", "write_schemas",
]
