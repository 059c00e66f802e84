"""The one codec for bus payloads: msgpack, with numpy arrays as an extension type.

Two wire forms, told apart by the first byte:

* A message without arrays is plain msgpack, so any script decodes stats and
  spans with ``msgpack.unpackb(payload)``.
* A message with arrays is a frame: ``0xC1`` (the one byte msgpack never
  uses), a little-endian uint32 header length, a msgpack header in which each
  array is an ``ExtType(1, msgpack([dtype, shape, offset]))``, then the raw
  array buffers, each aligned to 64 bytes. Decoding returns read-only numpy
  views into the received buffer: no copy.

Decoding is bounded, because any process on the bus can send anything. Array
data is never copied; only msgpack becomes Python objects, at up to ~40 bytes
of memory per byte (small negative ints), so :func:`decode` checks, before or
while unpacking, and raises :class:`DecodeError` (and nothing else) past:

* ``max_bytes`` for the whole payload (per message type; None: none here) and
  ``max_header_bytes`` for its msgpack: a plain payload, or a frame's header,
  which must lie inside the payload;
* ``max_len`` entries in any list or map: msgpack preallocates a declared
  length, so a lying prefix costs at most 8 bytes x ``max_len`` per level of
  nesting, which msgpack stops at 1024; strings and binaries are bounded by
  the header, array references to a few hundred bytes;
* ``max_objects`` lists, maps and arrays in all;
* an array reference other than exactly ``[dtype, shape, offset]``: a dtype of
  :data:`ARRAY_DTYPES` (bool, integers, floats, complex; no object, string,
  structured, subarray or datetime dtype), at most :data:`MAX_NDIM`
  non-negative dimensions, and the offset :func:`encode` gives: arrays lie end
  to end in header order, each padded to 64 bytes, so none overlaps another,
  and the payload ends with the last one's padding (no trailing bytes).

With the defaults the worst 8 MB payload found costs ~70 MB and ~40 ms to
refuse (tests/test_codec.py). A msgpack timestamp (never written by
:func:`encode`) decodes as integer nanoseconds.
"""

from __future__ import annotations

import struct
from typing import Any, Callable

import msgpack
import numpy as np

FRAME_MAGIC = 0xC1
ARRAY_EXT = 1
_ALIGN = 64
_HEAD = struct.Struct("<BI")

MAX_HEADER_BYTES = 1 << 20
"""Default most bytes of msgpack (a plain payload, a frame's header): a report of 4096 metrics is ~200 KB."""
MAX_LEN = 4096
"""Default most entries in one list or map: the longest a service sends (a span batch, a report's metrics, a
weights manifest's one per tensor); lists preallocated by a lying prefix then cost at most 1023 x 32 KiB."""
MAX_OBJECTS = 8192
"""Default most lists, maps and arrays in one payload, together (weights of 4096 tensors take 4098)."""
MAX_NDIM = 16
"""Most dimensions of an array on the wire (numpy allows 64)."""
ARRAY_DTYPES: dict[str, np.dtype] = {
    np.dtype(name).newbyteorder(order).str: np.dtype(name).newbyteorder(order)
    for name in ("bool", "int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64",
                 "float16", "float32", "float64", "complex64", "complex128")
    for order in "<>"
}
"""The dtype strings an array may carry on the wire (either byte order), with their dtypes."""
_MAX_REF = 256  # an array reference is at most ~160 bytes of msgpack (MAX_NDIM uint64 dimensions)


class DecodeError(ValueError):
    """A payload that is not a valid EBRL message."""


def encode(obj: Any) -> bytes:
    """Encode ``obj`` (dicts, lists, scalars, strings, bytes, numpy arrays) to bytes."""
    arrays: list[np.ndarray] = []
    offset = 0

    def default(value: Any) -> Any:
        nonlocal offset
        if isinstance(value, np.ndarray):
            if value.dtype.str not in ARRAY_DTYPES:
                raise TypeError(f"arrays of dtype {value.dtype} cannot be encoded (see codec.ARRAY_DTYPES)")
            if value.ndim > MAX_NDIM:
                raise TypeError(f"arrays of {value.ndim} dimensions cannot be encoded (at most {MAX_NDIM})")
            array = np.asarray(value, order="C")  # ascontiguousarray would make a 0-d array 1-d
            ref = msgpack.packb([array.dtype.str, list(array.shape), offset])
            arrays.append(array)
            offset += _padded(array.nbytes)
            return msgpack.ExtType(ARRAY_EXT, ref)
        if isinstance(value, np.generic):
            return value.item()
        if isinstance(value, tuple):
            return list(value)
        raise TypeError(f"cannot encode {type(value).__name__}")

    header = msgpack.packb(obj, default=default, use_bin_type=True)
    if not arrays:
        return header
    start = _HEAD.size + len(header)
    pieces: list[bytes | memoryview] = [_HEAD.pack(FRAME_MAGIC, len(header)), header, bytes(_padded(start) - start)]
    for array in arrays:
        if array.nbytes:
            pieces.append(memoryview(array).cast("B"))
        pieces.append(bytes(_padded(array.nbytes) - array.nbytes))
    return b"".join(pieces)  # one copy of the array data (a bytearray and bytes() of it would be two)


def decode(payload: bytes | bytearray | memoryview, *, max_bytes: int | None = None,
           max_header_bytes: int = MAX_HEADER_BYTES, max_len: int = MAX_LEN, max_objects: int = MAX_OBJECTS) -> Any:
    """Decode bytes produced by :func:`encode`, within the limits in the module docstring.

    ``max_bytes`` bounds the whole payload (None: unbounded here; the bus has its own
    ``max_message_bytes``), ``max_header_bytes`` its msgpack part, ``max_len`` each list and map,
    ``max_objects`` the lists, maps and arrays together. Raises :class:`DecodeError`, and only that,
    on malformed or oversized input. Arrays are views into ``payload`` (read-only when it is ``bytes``)."""
    try:
        buf = memoryview(payload).cast("B")
        size = len(buf)
        if max_bytes is not None and size > max_bytes:
            raise DecodeError(f"{size} bytes, over max_bytes = {max_bytes}")
        objects = 0

        def counted(obj: Any) -> Any:  # msgpack's hook for every list and map, when complete
            nonlocal objects
            objects += 1
            if objects > max_objects:
                raise DecodeError(f"more than max_objects = {max_objects} lists, maps and arrays")
            return obj

        def unpack(header: memoryview, ext_hook: Any) -> Any:
            return msgpack.unpackb(header, raw=False, strict_map_key=True, use_list=True, ext_hook=ext_hook,
                                   list_hook=counted, object_hook=counted, timestamp=2,
                                   max_str_len=len(header), max_bin_len=len(header), max_ext_len=_MAX_REF,
                                   max_array_len=max_len, max_map_len=max_len)

        if not size or buf[0] != FRAME_MAGIC:
            if size > max_header_bytes:
                raise DecodeError(f"{size} bytes of msgpack, over max_header_bytes = {max_header_bytes}")
            return unpack(buf, _no_ext)
        return _decode_frame(buf, max_header_bytes, unpack, counted)
    except DecodeError:
        raise
    except Exception as exc:  # msgpack raises several unrelated types on garbage; numpy on impossible shapes
        raise DecodeError(f"{type(exc).__name__}: {exc}") from None


def _decode_frame(buf: memoryview, max_header_bytes: int, unpack: Callable[[memoryview, Any], Any],
                  counted: Callable[[Any], Any]) -> Any:
    """The object in a frame (a payload whose first byte is ``FRAME_MAGIC``): its msgpack header unpacked by
    ``unpack`` (:func:`decode`'s, with its limits), each array reference in it a view into the array data after
    the header, counted by ``counted`` with the lists and maps. Runs inside :func:`decode`'s ``try``, which turns
    any other error into a :class:`DecodeError`."""
    size = len(buf)
    if size < _HEAD.size:
        raise DecodeError("truncated frame header")
    _, header_len = _HEAD.unpack_from(buf)
    header_end = _HEAD.size + header_len
    if header_len > max_header_bytes:
        raise DecodeError(f"frame header of {header_len} bytes, over max_header_bytes = {max_header_bytes}")
    if header_end > size:
        raise DecodeError("frame header longer than payload")
    data = buf[_padded(header_end):]
    end = 0  # where the next array starts in data: arrays lie end to end, in header order

    def ext_hook(code: int, ref: bytes) -> np.ndarray:
        nonlocal end
        if code != ARRAY_EXT:
            raise DecodeError(f"unknown extension type {code}")
        counted(None)
        dtype, shape, nbytes = _array_ref(ref, end)
        if end + nbytes > len(data):
            raise DecodeError("array buffer out of range")
        array = np.ndarray(shape, dtype, buffer=data, offset=end)
        end += _padded(nbytes)
        return array

    obj = unpack(buf[_HEAD.size:header_end], ext_hook)
    if _padded(header_end) + end != size:
        raise DecodeError(f"frame of {size} bytes, its header and arrays take {_padded(header_end) + end}")
    return obj


def _array_ref(ref: bytes, offset: int) -> tuple[np.dtype, tuple[int, ...], int]:
    """The dtype, shape and byte count of an array reference that must sit at ``offset``."""
    fields = msgpack.unpackb(ref, raw=False, use_list=True, max_str_len=len(ref), max_bin_len=0,
                             max_array_len=MAX_NDIM, max_map_len=0, max_ext_len=0)
    if type(fields) is not list or len(fields) != 3:
        raise DecodeError("an array reference is not [dtype, shape, offset]")
    dtype_str, shape, off = fields
    dtype = ARRAY_DTYPES.get(dtype_str) if type(dtype_str) is str else None
    if dtype is None:
        raise DecodeError(f"array dtype {str(dtype_str)[:20]!r} is not allowed")
    if type(off) is not int or off != offset:
        raise DecodeError(f"array at offset {str(off)[:24]}, expected {offset} (arrays lie end to end)")
    if type(shape) is not list:
        raise DecodeError("an array shape is not a list")
    nbytes = dtype.itemsize
    for d in shape:
        if type(d) is not int or d < 0:
            raise DecodeError("an array dimension is not a non-negative integer")
        nbytes *= d  # Python ints: no overflow
    return dtype, tuple(shape), nbytes


def _no_ext(code: int, data: bytes) -> Any:
    raise DecodeError("array extension outside a frame")


def _padded(n: int) -> int:
    return (n + _ALIGN - 1) // _ALIGN * _ALIGN
