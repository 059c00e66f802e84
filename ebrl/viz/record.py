"""The run recording: every sample under ``ebrl/stats/<run>/**`` appended to ``RUN_DIR/stats.msgpack``.

The launcher records while the run goes on (:class:`Recorder`); reports and
scripts read it back (:func:`read`). The file is a plain stream of msgpack
arrays ``[received_at, key, payload]`` where ``payload`` is the message exactly
as it travelled on the bus, so the recording costs the launcher one append per
sample and no decoding; messages are validated when read back, and malformed
ones are counted and skipped there.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from pathlib import Path

import msgpack

from ebrl.messages import EpisodeBatch, Event, MessageError, Span, SpanBatch, StatsReport, decode_stats_sample
from ebrl.viz.timeline import lane_order

FILENAME = "stats.msgpack"
FLUSH_S = 1.0


class Recorder:
    """Appends raw samples to a file from any thread (Zenoh's callback threads)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._fh = open(self.path, "ab", buffering=1 << 20)
        self._lock = threading.Lock()
        self._packer = msgpack.Packer()
        self._last_flush = time.monotonic()
        self.samples = 0

    def write(self, key: str, payload: bytes) -> None:
        record = self._packer.pack([time.time(), key, payload])
        with self._lock:
            if self._fh.closed:
                return
            self._fh.write(record)
            self.samples += 1
            if time.monotonic() - self._last_flush > FLUSH_S:  # a crash loses at most ~a second
                self._fh.flush()
                self._last_flush = time.monotonic()

    def close(self) -> None:
        with self._lock:
            if not self._fh.closed:
                self._fh.close()


@dataclasses.dataclass
class Recording:
    """A run's recording, decoded: spans sorted by start; stats, events and episode batches in arrival order."""

    spans: list[Span] = dataclasses.field(default_factory=list)
    stats: list[StatsReport] = dataclasses.field(default_factory=list)
    events: list[Event] = dataclasses.field(default_factory=list)
    episodes: list[EpisodeBatch] = dataclasses.field(default_factory=list)
    malformed: int = 0

    @property
    def lanes(self) -> list[str]:
        return sorted({s.lane for s in self.spans}, key=lane_order)

    def bounds(self) -> tuple[float, float]:
        """(first, last) epoch second covered by spans, stats or events."""
        times = ([s.start for s in self.spans] + [s.end for s in self.spans] + [r.time for r in self.stats]
                 + [e.time for e in self.events])
        return (min(times), max(times)) if times else (0.0, 0.0)


def read(path: str | Path) -> Recording:
    """Decode a recording file (or a run directory holding ``stats.msgpack``)."""
    path = Path(path)
    if path.is_dir():
        path = path / FILENAME
    out = Recording()
    with open(path, "rb") as fh:
        unpacker = msgpack.Unpacker(fh, raw=False)
        while True:
            try:
                record = unpacker.unpack()
            except msgpack.OutOfData:  # end of file, or a record cut short by a crash
                break
            except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError):
                out.malformed += 1
                break
            try:
                _, key, payload = record
                msg = decode_stats_sample(key, payload)
            except (MessageError, TypeError, ValueError):
                out.malformed += 1
                continue
            if isinstance(msg, SpanBatch):
                out.spans.extend(msg.spans())
            elif isinstance(msg, Event):
                out.events.append(msg)
            elif isinstance(msg, EpisodeBatch):
                out.episodes.append(msg)
            else:
                out.stats.append(msg)
    out.spans.sort(key=lambda s: s.start)
    return out
