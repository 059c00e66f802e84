"""Codec: arrays, nested maps, plain msgpack for array-free messages, malformed input."""

import gc
import struct
import tracemalloc

import msgpack
import numpy as np
import pytest

from ebrl import codec


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


# --- bounded decoding: what a crafted payload may not do --------------------------------------------------------


def raw_frame(header: bytes, data: bytes) -> bytes:
    start = 5 + len(header)
    return struct.pack("<BI", codec.FRAME_MAGIC, len(header)) + header + bytes(-start % 64) + data


def frame(header_obj, data: bytes = b"") -> bytes:
    """A frame around ``header_obj`` (array refs as ExtType) and ``data``, padded as encode pads the header."""
    return raw_frame(msgpack.packb(header_obj, use_bin_type=True), data)


def ref(dtype, shape, offset=0):
    return msgpack.ExtType(codec.ARRAY_EXT, msgpack.packb([dtype, shape, offset]))


def test_the_frame_helper_matches_encode():
    a = np.arange(5, dtype=np.float32)
    assert frame({"a": ref("<f4", [5])}, a.tobytes() + bytes(44)) == codec.encode({"a": a})


@pytest.mark.parametrize(
    "header, data",
    [
        ([ref("<f8", [-1])], bytes(64)),  # a negative dimension (once: the whole buffer)
        ([ref("<f8", [1 << 40, 1 << 40])], bytes(64)),  # a product past int64
        ([ref("<f8", [2.0])], bytes(64)),
        ([ref("<f8", [True])], bytes(64)),
        ([ref("<f8", 8)], bytes(64)),
        ([ref("|u1", [1] * (codec.MAX_NDIM + 1))], bytes(64)),
        ([ref("|O", [1])], bytes(64)),
        ([ref("<U2", [1])], bytes(64)),
        ([ref("|V8", [1])], bytes(64)),
        ([ref("|S8", [1])], bytes(64)),
        ([ref("<M8[s]", [1])], bytes(64)),
        ([ref("i1,i1", [1])], bytes(64)),  # structured
        ([ref("(1073741824,)f8", [1])], bytes(64)),  # a subarray dtype of 8 GB
        ([ref("<f16", [1])], bytes(64)),  # long double: platform-dependent
        ([ref(b"<f8", [1])], bytes(64)),
        ([ref("<f8", [1], -64)], bytes(64)),
        ([ref("<f8", [1], 8)], bytes(64)),  # misaligned
        ([ref("<f8", [1], 64)], bytes(128)),  # a gap before the first array
        ([ref("<f8", [8]), ref("<f8", [8], 0)], bytes(128)),  # overlapping arrays
        ([ref("<f8", [1]), ref("<f8", [1], 128)], bytes(192)),  # a gap between arrays
        ([ref("<f8", [8])], bytes(63)),  # the last array's padding cut short
        ([ref("<f8", [8])], bytes(65)),  # trailing bytes
        ([ref("<f8", [8])], bytes(128)),  # trailing padding
        ([msgpack.ExtType(1, msgpack.packb(["<f8", [1]]))], bytes(64)),  # not [dtype, shape, offset]
        ([msgpack.ExtType(1, msgpack.packb(["<f8", [1], 0, 0]))], bytes(64)),
        ([msgpack.ExtType(1, msgpack.packb({"dtype": "<f8"}))], bytes(64)),
        ([msgpack.ExtType(1, b"\xc1")], bytes(64)),
        ([msgpack.ExtType(1, bytes(300))], bytes(64)),  # a reference longer than any valid one
        ([msgpack.ExtType(2, msgpack.packb(["<f8", [1], 0]))], bytes(64)),  # another extension type
    ],
)
def test_array_references_must_be_exact(header, data):
    with pytest.raises(codec.DecodeError):
        codec.decode(frame(header, data))


def test_arrays_lie_end_to_end_in_header_order():
    arrays = {"a": np.ones(3, np.float64), "e": np.zeros((0, 5), np.int8), "b": np.arange(70, dtype=np.uint8),
              "c": np.ones((2, 2), ">f4"), "d": np.array(True)}
    out = codec.decode(codec.encode(arrays))
    for name, a in arrays.items():
        np.testing.assert_array_equal(out[name], a)
        assert out[name].dtype == a.dtype
    assert codec.decode(frame([ref("<f8", [1]), ref("|b1", [0], 64), ref("|u1", [2], 64)], bytes(128)))[2].shape == (2,)


@pytest.mark.parametrize("payload", [b"\xc1\x00\x01", b"\xc1\x10\x00\x00\x00" + bytes(15), b"\xc1\xff\xff\xff\xff"])
def test_a_frame_header_must_lie_inside_the_payload(payload):
    with pytest.raises(codec.DecodeError):
        codec.decode(payload)


def test_size_limits():
    payload = codec.encode({"a": np.zeros(100, np.float32), "names": ["x"] * 10})
    assert codec.decode(payload, max_bytes=len(payload))["names"] == ["x"] * 10
    with pytest.raises(codec.DecodeError, match="max_bytes"):
        codec.decode(payload, max_bytes=len(payload) - 1)
    with pytest.raises(codec.DecodeError, match="max_header_bytes"):
        codec.decode(payload, max_header_bytes=16)
    with pytest.raises(codec.DecodeError, match="max_array_len"):
        codec.decode(payload, max_len=9)
    with pytest.raises(codec.DecodeError, match="max_objects"):
        codec.decode(payload, max_objects=2)  # the map, the list, the array
    plain = msgpack.packb({"k": list(range(100))})
    with pytest.raises(codec.DecodeError, match="max_header_bytes"):
        codec.decode(plain, max_header_bytes=len(plain) - 1)
    with pytest.raises(codec.DecodeError, match="max_map_len"):
        codec.decode(msgpack.packb({str(i): i for i in range(20)}), max_len=19)


@pytest.mark.parametrize(
    "payload",
    [
        b"\xdd\xff\xff\xff\xff" + bytes(64),  # a list claiming 2**32 - 1 items
        b"\xdf\xff\xff\xff\xff",  # a map claiming as many
        b"\x91" * 2000 + b"\xc0",  # nested deeper than msgpack's stack (1024)
        b"\x91" * 1000 + b"\x81\xc0\xc0",  # a map key that is not a string
        b"\x81\xa1k\xd6\xff\x00",  # a broken msgpack timestamp
    ],
)
def test_crafted_msgpack_is_a_decode_error(payload):
    with pytest.raises(codec.DecodeError):
        codec.decode(payload)


def test_encode_refuses_what_decode_would_refuse():
    for bad in (np.array(["ab"]), np.zeros(2, "M8[s]"), np.zeros(2, "i1,i1"), np.zeros((1,) * (codec.MAX_NDIM + 1))):
        with pytest.raises(TypeError):
            codec.encode({"a": bad})
    for dtype in codec.ARRAY_DTYPES.values():
        a = np.arange(6).astype(dtype).reshape(2, 3)
        np.testing.assert_array_equal(codec.decode(codec.encode([a]))[0], a)


def lists_of(item: bytes, size: int) -> bytes:
    """A list of lists of ``MAX_LEN`` copies of ``item``, at most ``size`` bytes of msgpack."""
    per = codec.MAX_LEN
    inner = b"\xdd" + struct.pack(">I", per) + item * per
    count = (size - 5) // len(inner)
    return b"\xdd" + struct.pack(">I", count) + inner * count


def crafted_8mb_payload(name: str) -> bytes:
    """The worst 8 MB payloads found: most are the largest header allowed, crafted, before 7 MiB of array data."""
    mib = 1 << 20
    header = codec.MAX_HEADER_BYTES
    ints = lists_of(b"\xe0", header - (8 << 10))  # -32: one byte, a 32-byte int object and an 8-byte slot
    array = msgpack.packb([ref("|u1", [7 * mib])])[1:]  # one array, without its list header
    make = {
        "8M-empty-lists": lambda: b"\xdd" + struct.pack(">I", 8 * mib - 5) + b"\x90" * (8 * mib - 5),
        "small-ints": lambda: raw_frame(b"\x92" + ints + array, bytes(7 * mib)),
        "short-strings": lambda: raw_frame(b"\x92" + lists_of(b"\xa2\xc4\x80", header - 64) + array, bytes(7 * mib)),
        # lists claiming MAX_LEN items, nested as deep as msgpack allows, are all preallocated; then small ints
        "preallocated": lambda: raw_frame((b"\xdd" + struct.pack(">I", codec.MAX_LEN)) * 1000 + ints, bytes(7 * mib)),
        "empty-maps": lambda: raw_frame(lists_of(b"\x80", header), bytes(7 * mib)),
        "empty-arrays": lambda: raw_frame(lists_of(msgpack.packb(ref("|u1", [0])), header), bytes(7 * mib)),
    }
    return make[name]()


@pytest.mark.parametrize("name", ["8M-empty-lists", "small-ints", "short-strings", "preallocated", "empty-maps",
                                  "empty-arrays"])
def test_a_crafted_8mb_payload_costs_less_than_100mb(name):
    payload = crafted_8mb_payload(name)
    assert len(payload) <= 8 << 20
    gc.collect()
    tracemalloc.start()
    try:
        out = codec.decode(payload)
    except codec.DecodeError:
        out = None
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peak < 100 << 20, f"{name}: {peak / 2**20:.0f} MB"
    if name in ("small-ints", "short-strings"):  # valid: the largest header decodes
        assert len(out[0]) > 40 and out[1].nbytes == 7 << 20
