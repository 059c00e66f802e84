"""The one codec for bus payloads: msgpack, with numpy arrays as an extension type.

Two wire forms, told apart by the first byte:

* A message without arrays is plain msgpack, so any script decodes stats and
  spans with ``msgpack.unpackb(payload)``.
* A message with arrays is a frame: ``0xC1`` (the one byte msgpack never
  uses), a little-endian uint32 header length, a msgpack header in which each
  array is an ``ExtType(1, msgpack([dtype, shape, offset]))``, then the raw
  array buffers, each aligned to 64 bytes. Decoding returns read-only
  ``np.frombuffer`` views into the received buffer: no copy.
"""

from __future__ import annotations

import struct
from typing import Any

import msgpack
import numpy as np

FRAME_MAGIC = 0xC1
ARRAY_EXT = 1
_ALIGN = 64
_HEAD = struct.Struct("<BI")


class DecodeError(ValueError):
    """A payload that is not a valid EBRL message."""


def encode(obj: Any) -> bytes:
    """Encode ``obj`` (dicts, lists, scalars, strings, bytes, numpy arrays) to bytes."""
    arrays: list[np.ndarray] = []
    offset = 0

    def default(value: Any) -> Any:
        nonlocal offset
        if isinstance(value, np.ndarray):
            if value.dtype.hasobject:
                raise TypeError("object arrays cannot be encoded")
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


def decode(payload: bytes | bytearray | memoryview) -> Any:
    """Decode bytes produced by :func:`encode`. Raises :class:`DecodeError` on malformed input."""
    buf = memoryview(payload)
    try:
        if len(buf) and buf[0] == FRAME_MAGIC:
            if len(buf) < _HEAD.size:
                raise DecodeError("truncated frame header")
            _, header_len = _HEAD.unpack_from(buf)
            start = _HEAD.size
            if start + header_len > len(buf):
                raise DecodeError("frame header longer than payload")
            data = buf[_padded(start + header_len) :]

            def ext_hook(code: int, ref: bytes) -> Any:
                if code != ARRAY_EXT:
                    raise DecodeError(f"unknown extension type {code}")
                dtype_str, shape, off = msgpack.unpackb(ref)
                dtype = np.dtype(dtype_str)
                if dtype.hasobject:
                    raise DecodeError("object arrays are not allowed")
                count = int(np.prod(shape, dtype=np.int64))
                if off < 0 or off + count * dtype.itemsize > len(data):
                    raise DecodeError("array buffer out of range")
                return np.frombuffer(data, dtype=dtype, count=count, offset=off).reshape(shape)

            return msgpack.unpackb(buf[start : start + header_len], ext_hook=ext_hook, raw=False)
        return msgpack.unpackb(buf, raw=False, ext_hook=_no_ext)
    except DecodeError:
        raise
    except Exception as exc:  # msgpack raises several unrelated types on garbage
        raise DecodeError(f"{type(exc).__name__}: {exc}") from None


def _no_ext(code: int, data: bytes) -> Any:
    raise DecodeError("array extension outside a frame")


def _padded(n: int) -> int:
    return (n + _ALIGN - 1) // _ALIGN * _ALIGN
