"""The handover between learners of one run (``RUN_DIR/train-pending.msgpack``): a train stopped to start again (a
new GPU share) writes the segments it had not trained on, fsynced, one checked record per segment; the next one
takes them over once, and a file torn by a kill loses only its torn record."""

from __future__ import annotations

import logging
import struct
import zlib
from pathlib import Path
from typing import BinaryIO, Callable, Iterable

import msgpack

from ebrl import durable
from ebrl.messages import MessageError, TrajectorySegment, decode_message, encode_message

log = logging.getLogger(__name__)

HANDOVER_FILE = "train-pending.msgpack"  # segments a stopping train leaves to the next one (RUN_DIR)
HANDOVER_MAGIC = b"EBRL-HANDOVER/1\n"  # then records: <u32 length><u32 crc32 of the payload><payload>
_RECORD = struct.Struct("<II")


def hand_over(run_dir: str, segments: list[TrajectorySegment]) -> int:
    """Write ``segments`` (received, not yet trained on) for the next learner of this run; how many. Durably
    (:func:`ebrl.durable.writing`), one checked record per segment (:func:`write_records`)."""
    if segments:
        with durable.writing(Path(run_dir) / HANDOVER_FILE) as tmp, open(tmp, "wb") as fh:
            write_records(fh, (encode_message(s) for s in segments))
    return len(segments)


def take_over(run_dir: str, accept: Callable[[TrajectorySegment], int],
              malformed: Callable[[Exception], None]) -> tuple[int, int]:
    """Take over what the learner before handed over, once (the file is removed): each segment goes to
    ``accept``; returns (taken, handed over). A learner killed while handing over left only the temporary
    file (:func:`ebrl.durable.temporaries`): its whole records are taken over too (each is checked; a torn last
    one is lost, logged)."""
    path = Path(run_dir) / HANDOVER_FILE
    left = durable.temporaries(path)
    source = path if path.exists() else left[-1] if left else None
    if source is None:
        return 0, 0
    payloads, torn = read_records(source)
    if torn:
        log.warning("%s: %s; took the %d whole records before it", source, torn, len(payloads))
    for stale in (path, *left):  # before anything is trained on: never taken over twice
        stale.unlink(missing_ok=True)
    durable.fsync_dir(path.parent)
    taken = 0
    for payload in payloads:
        try:
            segment = decode_message(TrajectorySegment, payload)
        except MessageError as exc:  # whole, but no segment of this version (another EBRL wrote it)
            malformed(exc)
            continue
        taken += accept(segment)
    return taken, len(payloads)


def write_records(fh: BinaryIO, payloads: Iterable[bytes]) -> None:
    """The handover file's format: ``HANDOVER_MAGIC``, then one record per payload, each with its length and
    checksum, so that a reader of a file cut short (or with garbage after it) keeps every whole record."""
    fh.write(HANDOVER_MAGIC)
    for payload in payloads:
        fh.write(_RECORD.pack(len(payload), zlib.crc32(payload)))
        fh.write(payload)


def read_records(path: Path) -> tuple[list[bytes], str]:
    """The whole records of a handover file, up to the first torn or garbled one, and what was wrong after them
    ("" for a whole file). A file of the older format (one msgpack list) is read whole or not at all."""
    data = path.read_bytes()
    if not data.startswith(HANDOVER_MAGIC):
        try:
            payloads = msgpack.unpackb(data)
        except (ValueError, msgpack.UnpackException):  # ExtraData and FormatError are ValueErrors
            payloads = None
        if isinstance(payloads, list) and all(isinstance(p, bytes) for p in payloads):
            return payloads, ""
        return [], "not a handover file (no header, not the older format)"
    payloads, at = [], len(HANDOVER_MAGIC)
    while at < len(data):
        if at + _RECORD.size > len(data):
            return payloads, f"record {len(payloads)} is torn (its header is cut short)"
        length, crc = _RECORD.unpack_from(data, at)
        payload = data[at + _RECORD.size:at + _RECORD.size + length]
        if len(payload) < length:
            return payloads, f"record {len(payloads)} is torn ({len(payload)} of {length} bytes)"
        if zlib.crc32(payload) != crc:
            return payloads, f"record {len(payloads)} is garbled (checksum mismatch)"
        payloads.append(payload)
        at += _RECORD.size + length
    return payloads, ""
