"""Fuzz the codec and message validation: round trips, and crafted or mutated payloads fail only as they should."""

import dataclasses
import math

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from ebrl import messages as m
from ebrl import codec

# A bounded number of examples, the same every run (derandomize), no example database left behind.
FUZZ = settings(max_examples=200, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
PER_TYPE = settings(FUZZ, max_examples=60)  # once per message type

# --- values ------------------------------------------------------------------------------------------------

arrays = hnp.arrays(dtype=st.sampled_from(sorted(set(codec.ARRAY_DTYPES.values()), key=str)),
                    shape=hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=4))
scalars = (st.none() | st.booleans() | st.integers(-(1 << 63), (1 << 64) - 1) | st.floats()
           | st.text(max_size=12) | st.binary(max_size=12))
values = st.recursive(scalars | arrays,
                      lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
                      max_leaves=16)


def same(a, b) -> bool:
    """Equal as the codec promises: arrays by dtype, shape and bytes; floats with NaN equal to NaN."""
    if isinstance(a, np.ndarray):
        return (isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape
                and a.tobytes() == b.tobytes())
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    return type(a) is type(b) and a == b


@FUZZ
@given(values)
def test_anything_encodable_round_trips(value):
    payload = codec.encode(value)
    assert same(value, codec.decode(payload))
    assert same(value, codec.decode(bytearray(payload)))


# --- mutations ---------------------------------------------------------------------------------------------


@st.composite
def mutated(draw, payload: bytes) -> bytes:
    """``payload`` with a few bit flips, byte overwrites, cuts, insertions, duplicated slices or a forged frame
    header length."""
    data = bytearray(payload)
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["flip", "byte", "truncate", "insert", "duplicate", "header_len"]))
        at = draw(st.integers(0, max(len(data) - 1, 0)))
        if kind == "flip" and data:
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif kind == "byte" and data:
            data[at] = draw(st.integers(0, 255))
        elif kind == "truncate":
            del data[at:]
        elif kind == "insert":
            data[at:at] = draw(st.binary(min_size=1, max_size=16))
        elif kind == "duplicate":
            data[at:at] = data[at:at + draw(st.integers(1, 64))]
        elif kind == "header_len" and len(data) >= 5:
            data[1:5] = draw(st.integers(0, (1 << 32) - 1)).to_bytes(4, "little")
    return bytes(data)


def decodes_or_refuses(payload: bytes) -> None:
    try:
        codec.decode(payload)
    except codec.DecodeError:
        pass


@FUZZ
@given(st.binary(max_size=512) | st.binary(max_size=512).map(lambda b: b"\xc1" + b))
def test_arbitrary_bytes_decode_or_raise_decode_error(payload):
    decodes_or_refuses(payload)


@FUZZ
@given(st.data())
def test_mutated_payloads_decode_or_raise_decode_error(data):
    payload = codec.encode(data.draw(values))
    decodes_or_refuses(data.draw(mutated(payload)))


@FUZZ
@given(st.lists(st.tuples(st.sampled_from(sorted(codec.ARRAY_DTYPES)) | st.text(max_size=6),
                          st.lists(st.integers(-2, 1 << 40), max_size=3) | st.integers(-(1 << 63), (1 << 64) - 1),
                          st.integers(-128, 256)), min_size=1, max_size=3),
       st.integers(0, 512))
def test_crafted_array_references_decode_or_raise_decode_error(refs, data_len):
    header = msgpack.packb([msgpack.ExtType(codec.ARRAY_EXT, msgpack.packb(list(r))) for r in refs])
    start = 5 + len(header)
    decodes_or_refuses(bytes([codec.FRAME_MAGIC]) + len(header).to_bytes(4, "little") + header
                       + bytes(-start % 64) + bytes(data_len))


# --- messages ----------------------------------------------------------------------------------------------


def f32(*shape):
    return np.arange(math.prod(shape), dtype=np.float32).reshape(shape) / 7


FACTORY = {
    m.Observation: lambda: m.Observation(group=1, seq=7, env_ids=np.arange(4, dtype=np.int64), obs=f32(4, 3),
                                         sent_at=1.5),
    m.ActionChunk: lambda: m.ActionChunk(group=0, seq=3, policy_version=2, actions=f32(4, 2, 1), logprobs=f32(4),
                                         values=f32(4), latents=f32(4, 0)),
    m.TrajectorySegment: lambda: m.TrajectorySegment(
        group=0, env_id=3, episode=1, obs=f32(2, 3), actions=f32(2, 4, 1), latents=f32(2, 0), logprobs=f32(2),
        values=f32(2), rewards=f32(2), steps=np.array([4, 2], np.int32), versions=np.array([5, 6], np.int64),
        end="terminated", last_obs=f32(3), episode_returns=[1.5], episode_lengths=[6], episode_offset=0),
    m.SegmentBatch: lambda: m.SegmentBatch(
        group=1, env_ids=np.array([3, 4], np.int64), episodes=np.array([1, 0], np.int64),
        lengths=np.array([2, 1], np.int32), ends=np.array([1, 0], np.int8), obs=f32(3, 3), actions=f32(3, 4, 1),
        latents=f32(3, 0), logprobs=f32(3), values=f32(3), rewards=f32(3), steps=np.array([4, 2, 4], np.int32),
        versions=np.array([5, 6, 6], np.int64), last_obs=f32(2, 3), episode_returns=np.array([1.5, 0], np.float32),
        episode_lengths=np.array([6, -1], np.int32), episode_successes=np.array([1, -1], np.int8),
        episode_offsets=np.array([0, 8], np.int64)),
    m.ReplayRequest: lambda: m.ReplayRequest(
        session=9, seq=2, acked=64, batches=2, batch_size=2, obs=f32(3, 3), actions=f32(3, 4), rewards=f32(3),
        steps=np.array([1, 1, 1], np.int32), terminal=np.array([0, 0, 1], np.uint8), next_obs=f32(3, 3) + 1,
        versions=np.array([5, 5, 6], np.int64)),
    m.ReplaySample: lambda: m.ReplaySample(
        session=9, seq=2, size=67, inserted=67, obs=f32(4, 3), actions=f32(4, 4), rewards=f32(4),
        steps=np.ones(4, np.int32), terminal=np.array([0, 1, 0, 0], np.uint8), next_obs=f32(4, 3),
        versions=np.arange(4, dtype=np.int64)),
    m.Weights: lambda: m.Weights(version=3, params={"w": f32(2, 2), "b": f32(2)}, created_at=2.0),
    m.WeightsPart: lambda: m.WeightsPart(version=3, index=0, count=1, part_bytes=128, total_bytes=128, created_at=2.0,
                                         data=np.arange(128, dtype=np.uint8), names=["w", "b"],
                                         dtypes=["<f4", "<f4"], shapes=[[2, 2], [2]], offsets=[0, 64]),
    m.StatsReport: lambda: m.StatsReport(run="r", service="sim", instance=0, time=3.0, seq=1,
                                         metrics={"sim/env_steps": 10.0, "sim/env_steps_per_s": 2.5}),
    m.SpanBatch: lambda: m.SpanBatch(lane="gen", service="gen", instance=0, start=[1.0, 2.0], end=[1.5, 2.5],
                                     label=["forward", "wait"]),
    m.Event: lambda: m.Event(time=1.0, service="sim", instance=0, kind="live", text="sim 0 is up"),
    m.EpisodeBatch: lambda: m.EpisodeBatch(service="sim", instance=0, env_id=[1, 2], episode=[0, 0],
                                           returns=[1.0, -2.0], length=[10, 12], success=[True, None],
                                           policy_version=[1, 1], env_steps=[10, 22], end_time=[1.0, 2.0]),
    m.Stop: lambda: m.Stop(reason="done"),
    m.Affinity: lambda: m.Affinity(version=1, cores=[0, 2]),
    m.Quota: lambda: m.Quota(version=1, threads=2, sm_percent=50.0, mem_bytes=1 << 30, batch=8),
    m.GpuShare: lambda: m.GpuShare(version=1, stage="gen", env={"CUDA_VISIBLE_DEVICES": "0"}),
}
TYPES = pytest.mark.parametrize("cls", m.MESSAGES, ids=lambda c: c.__name__)


def test_every_message_type_has_a_valid_example():
    assert set(FACTORY) == set(m.MESSAGES)
    for cls, make in FACTORY.items():
        msg = make()
        again = m.decode_message(cls, m.encode_message(msg))
        assert same(m.to_wire(again), m.to_wire(msg)), cls.__name__


def decodes_as_or_refuses(cls, payload: bytes) -> None:
    try:
        msg = m.decode_message(cls, payload)
    except m.MessageError:
        return
    assert isinstance(msg, cls)


@TYPES
@PER_TYPE
@given(data=st.data())
def test_mutated_messages_decode_as_their_type_or_raise_message_error(cls, data):
    decodes_as_or_refuses(cls, data.draw(mutated(m.encode_message(FACTORY[cls]()))))


@TYPES
@PER_TYPE
@given(data=st.data())
def test_messages_with_a_field_changed_decode_as_their_type_or_raise_message_error(cls, data):
    wire = m.to_wire(FACTORY[cls]())
    names = sorted(wire)
    for _ in range(data.draw(st.integers(1, 3))):
        action = data.draw(st.sampled_from(["replace", "delete", "add"]))
        if action == "replace":
            wire[data.draw(st.sampled_from(names))] = data.draw(values)
        elif action == "delete":
            wire.pop(data.draw(st.sampled_from(names)), None)
        else:
            wire[data.draw(st.text(max_size=6) | st.binary(max_size=6))] = data.draw(values)
    decodes_as_or_refuses(cls, codec.encode(wire))


@TYPES
@PER_TYPE
@given(data=st.data())
def test_from_wire_on_anything_returns_the_type_or_raises_message_error(cls, data):
    names = [f.name for f in dataclasses.fields(cls)] + ["v"]
    keys = st.sampled_from(names) | st.text(max_size=6) | st.binary(max_size=4)
    raw = data.draw(st.dictionaries(keys, st.just(m.SCHEMA_VERSION) | values, max_size=len(names) + 2) | values)
    try:
        msg = m.from_wire(cls, raw)
    except m.MessageError:
        return
    assert isinstance(msg, cls) and set(raw) <= set(names)


@pytest.mark.parametrize("change", [
    {"v": np.zeros(2)},  # an array's != is elementwise: its truth value raised ValueError
    {"v": np.zeros(0)},
    {"extra": 1, b"extra": 2},  # unknown fields of str and bytes keys: sorting them raised TypeError
], ids=["v-array", "v-empty-array", "str-and-bytes-keys"])
def test_from_wire_regressions(change):
    wire = m.to_wire(FACTORY[m.Stop]())
    wire.update(change)
    with pytest.raises(m.MessageError):
        m.decode_message(m.Stop, codec.encode(wire))
