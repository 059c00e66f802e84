"""Codec: arrays, nested maps, plain msgpack for array-free messages, malformed input."""

import msgpack
import numpy as np
import pytest

from ebrl.bus import codec


def test_arrays_in_nested_maps_round_trip():
    obj = {
        "images": np.arange(8 * 3 * 16 * 16, dtype=np.uint8).reshape(8, 3, 16, 16),
        "inner": {"state": np.linspace(0, 1, 64, dtype=np.float32).reshape(8, 8), "ids": [1, 2, 3]},
        "scalar": np.float32(1.5),
        "empty": np.zeros((0, 4), dtype=np.float64),
        "zero_d": np.array(7, dtype=np.int64),  # e.g. BatchNorm's num_batches_tracked
        "text": "ok",
        "tuple": (1, 2),
    }
    out = codec.decode(codec.encode(obj))
    np.testing.assert_array_equal(out["images"], obj["images"])
    np.testing.assert_array_equal(out["inner"]["state"], obj["inner"]["state"])
    assert out["inner"]["state"].dtype == np.float32
    assert out["empty"].shape == (0, 4) and out["zero_d"].shape == () and out["zero_d"] == 7
    assert out["scalar"] == 1.5 and out["text"] == "ok" and out["tuple"] == [1, 2]


def test_decode_does_not_copy_array_buffers():
    payload = codec.encode({"a": np.arange(1000, dtype=np.float64)})
    out = codec.decode(payload)
    assert not out["a"].flags.writeable  # a view into the payload, not a copy
    assert out["a"].ctypes.data % 8 == 0  # aligned in the frame


def test_non_contiguous_arrays_are_encoded_by_value():
    a = np.arange(20, dtype=np.int32).reshape(4, 5)[:, ::2]
    np.testing.assert_array_equal(codec.decode(codec.encode({"a": a}))["a"], a)


def test_messages_without_arrays_are_plain_msgpack():
    payload = codec.encode({"metrics": {"sim/env_steps_per_s": 12.5}, "seq": 3})
    assert msgpack.unpackb(payload) == {"metrics": {"sim/env_steps_per_s": 12.5}, "seq": 3}


@pytest.mark.parametrize(
    "payload",
    [
        b"",
        b"\xc1",  # frame magic, truncated header
        b"\xc1\xff\xff\xff\x7f",  # header longer than payload
        b"\x92\x01",  # truncated msgpack list
        bytes(range(256)),
        msgpack.packb(msgpack.ExtType(1, msgpack.packb(["<f4", [2], 0]))),  # array outside a frame
    ],
)
def test_malformed_payloads_raise_decode_error(payload):
    with pytest.raises(codec.DecodeError):
        codec.decode(payload)


def test_array_reference_out_of_range_is_rejected():
    good = bytearray(codec.encode({"a": np.zeros(4, dtype=np.float32)}))
    bad = bytes(good[:-64])  # drop the array buffer
    with pytest.raises(codec.DecodeError):
        codec.decode(bad)


def test_object_arrays_are_refused():
    with pytest.raises(TypeError):
        codec.encode({"a": np.array([object()])})
