"""Messages: round trips, validation on receipt, and schemas/ kept in sync with ebrl/messages/."""

import json
import pathlib

import jsonschema
import msgpack
import numpy as np
import pytest

from ebrl import messages as m
from ebrl import codec

ROOT = pathlib.Path(__file__).resolve().parent.parent


def observation(**kw):
    base = dict(group=1, seq=7, env_ids=np.arange(4, dtype=np.int64), obs=np.ones((4, 3), np.float32), sent_at=1.0)
    base.update(kw)
    return m.Observation(**base)


def test_round_trip_with_arrays():
    msg = m.decode_message(m.Observation, m.encode_message(observation()))
    assert msg.group == 1 and msg.seq == 7
    np.testing.assert_array_equal(msg.obs, np.ones((4, 3), np.float32))


def test_stats_decode_with_plain_msgpack():
    report = m.StatsReport(run="r", service="sim", instance=0, time=2.0, seq=0, metrics={"sim/env_steps": 3.0})
    raw = msgpack.unpackb(m.encode_message(report))
    assert raw["metrics"] == {"sim/env_steps": 3.0} and raw["v"] == m.SCHEMA_VERSION
    jsonschema.validate(raw, m.json_schema(m.StatsReport))


@pytest.mark.parametrize(
    "mutate, error",
    [
        (lambda w: w.update(obs=np.ones((4, 3), np.float64)), "dtype float64"),
        (lambda w: w.pop("seq"), "missing field 'seq'"),
        (lambda w: w.update(extra=1), "unknown fields"),
        (lambda w: w.update(v=99), "schema version 99"),
        (lambda w: w.update(group="one"), "expected an integer"),
        (lambda w: w.update(env_ids=[0, 1]), "expected an array"),
        (lambda w: w.update(sent_at=True), "expected a number"),
    ],
)
def test_invalid_messages_are_rejected_with_the_field(mutate, error):
    wire = m.to_wire(observation())
    mutate(wire)
    with pytest.raises(m.MessageError, match=error):
        m.decode_message(m.Observation, codec.encode(wire))


def test_garbage_is_a_message_error():
    with pytest.raises(m.MessageError):
        m.decode_message(m.Event, b"\x00\x01garbage")


def test_span_batch_columns_must_agree():
    batch = m.SpanBatch(lane="gen", service="gen", instance=0, start=[1.0, 2.0], end=[1.5, 2.5], label=["forward"] * 2)
    again = m.decode_message(m.SpanBatch, m.encode_message(batch))
    assert again == batch and again.spans()[1] == m.Span("gen", 2.0, 2.5, "forward", "gen", 0)
    wire = m.to_wire(batch)
    wire["end"] = [1.5]
    with pytest.raises(m.MessageError, match="differ in length"):
        m.decode_message(m.SpanBatch, codec.encode(wire))


def test_literal_and_optional_fields():
    seg_end = m.Quota(version=1, threads=None)
    assert m.decode_message(m.Quota, m.encode_message(seg_end)).threads is None
    wire = m.to_wire(m.Stop(reason="x"))
    wire["reason"] = 5
    with pytest.raises(m.MessageError):
        m.from_wire(m.Stop, wire)


def test_a_gpu_share_sets_a_shares_variables_only():
    share = m.GpuShare(version=2, stage="train", env={"CUDA_VISIBLE_DEVICES": "0",
                                                      "CUDA_MPS_ACTIVE_THREAD_PERCENTAGE": "33.3333",
                                                      "CUDA_MPS_PINNED_DEVICE_MEM_LIMIT": "0=2048M"})
    assert m.decode_message(m.GpuShare, m.encode_message(share)) == share
    assert m.GpuShare(version=1, stage="gen", env={"CUDA_VISIBLE_DEVICES": "MIG-4f1a2b3c-1111-2222-3333-444455556666"})
    # a library for CUDA to load into the owner's process (issue 40), or any other variable: refused
    for env in ({"LD_PRELOAD": "/tmp/x.so"}, {"CUDA_INJECTION64_PATH": "/tmp/x.so"}, {"CUDA_MPS_LOG_DIRECTORY": "/"}):
        wire = m.to_wire(share)
        wire["env"] = env
        with pytest.raises(m.MessageError, match="may only set CUDA_VISIBLE_DEVICES"):
            m.from_wire(m.GpuShare, wire)
    for name, value in (("CUDA_VISIBLE_DEVICES", "0;touch /tmp/x"), ("CUDA_MPS_ACTIVE_THREAD_PERCENTAGE", "1000"),
                        ("CUDA_MPS_PINNED_DEVICE_MEM_LIMIT", "0=1T")):
        wire = m.to_wire(share)
        wire["env"] = {name: value}
        with pytest.raises(m.MessageError, match="is not a share's value"):
            m.from_wire(m.GpuShare, wire)
    wire = m.to_wire(share)
    wire["stage"] = "sim"
    with pytest.raises(m.MessageError):
        m.from_wire(m.GpuShare, wire)


def test_schemas_directory_is_up_to_date(tmp_path):
    m.write_schemas(str(tmp_path))
    for cls in m.MESSAGES:
        fresh = json.loads((tmp_path / f"{cls.__name__}.json").read_text())
        committed_path = ROOT / "schemas" / f"{cls.__name__}.json"
        assert committed_path.exists(), f"schemas/{cls.__name__}.json missing: run `make schemas`"
        assert json.loads(committed_path.read_text()) == fresh, f"schemas/{cls.__name__}.json is stale: run `make schemas`"
    extra = {p.stem for p in (ROOT / "schemas").glob("*.json")} - {c.__name__ for c in m.MESSAGES}
    assert not extra, f"schemas/ has files for no message: {extra}"
