"""What a service measures between two stats reports: counters, busy time per lane, timeline spans.

Library code (the group loop, the learner) records through the small :class:`Telemetry`
protocol, so it never needs a service or a bus; :class:`Meter` is the implementation
every service owns, safe to call from any thread (forward passes and updates run on
worker threads).
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Callable, Protocol

SPAN_BATCH_MAX = 4096  # a lane with this many unpublished spans is flushed at once


class Telemetry(Protocol):
    """What library code may record: counters, spans and events (a service, or a test's stand-in)."""

    def count(self, name: str, n: float = 1) -> None: ...

    def publish_span(self, lane: str, label: str, start: float, end: float, busy: bool = True) -> None: ...

    def event(self, kind: str, text: str) -> None: ...


class Meter:
    """Counters (reported as total and per-second rate), busy seconds per lane and pending spans.

    ``spans=False`` keeps only the busy seconds (``viz.spans = false``). ``slowdown = (factor, after_s)``
    stretches busy spans by busy-waiting in the caller's thread (``run.slowdown``: an injected,
    CPU-real slowdown for the allocator's adaptation benchmark); ``on_slowdown`` is called once when
    it starts."""

    def __init__(self, *, spans: bool = True, slowdown: tuple[float, float] | None = None,
                 on_slowdown: Callable[[float], None] | None = None, on_full: Callable[[], None] | None = None):
        self.spans_enabled = spans
        self.slowdown = slowdown
        self._on_slowdown = on_slowdown
        self._on_full = on_full
        self._lock = threading.Lock()
        self._counts: collections.Counter[str] = collections.Counter()
        self._busy: collections.Counter[str] = collections.Counter()
        self._spans: collections.defaultdict[str, list[tuple[float, float, str]]] = collections.defaultdict(list)
        self._last: tuple[float, dict[str, float], dict[str, float]] | None = None
        self.started_at = time.time()

    def count(self, name: str, n: float = 1) -> None:
        with self._lock:
            self._counts[name] += n

    def total(self, name: str) -> float:
        with self._lock:
            return self._counts[name]

    def publish_span(self, lane: str, label: str, start: float, end: float, busy: bool = True) -> None:
        """Record a span; ``busy=False`` marks waiting (shown on the timeline, not counted in busy/<lane>)."""
        if busy and self.slowdown is not None:
            end = self._stretch(start, end)
        with self._lock:
            if busy:
                self._busy[lane] += end - start
            if not self.spans_enabled:
                return
            rows = self._spans[lane]
            rows.append((start, end, label))
            full = len(rows) >= SPAN_BATCH_MAX
        if full and self._on_full is not None:
            self._on_full()

    def _stretch(self, start: float, end: float) -> float:
        factor, after_s = self.slowdown  # type: ignore[misc]
        if time.time() - self.started_at < after_s:
            return end
        if self._on_slowdown is not None:
            self._on_slowdown(factor)
            self._on_slowdown = None
        extra = (factor - 1.0) * (end - start)
        until = time.perf_counter() + extra
        while time.perf_counter() < until:  # CPU time, like real work
            pass
        self.count("slowdown/injected_s", extra)
        return end + extra

    def take_spans(self) -> dict[str, list[tuple[float, float, str]]]:
        """The spans recorded since the last call, per lane."""
        with self._lock:
            pending, self._spans = self._spans, collections.defaultdict(list)
        return {lane: rows for lane, rows in pending.items() if rows}

    def metrics(self) -> dict[str, float]:
        """Counters as ``name`` (total) and ``name_per_s``, and ``busy/<lane>`` (share of the interval), since
        the previous call."""
        now = time.monotonic()
        with self._lock:
            counts, busy = dict(self._counts), dict(self._busy)
        last_t, last_counts, last_busy = self._last or (now, {}, {})
        dt = max(now - last_t, 1e-9)
        out: dict[str, float] = {}
        for name, total in counts.items():
            out[name] = float(total)
            out[f"{name}_per_s"] = (total - last_counts.get(name, 0)) / dt if now > last_t else 0.0
        for lane, seconds in busy.items():
            out[f"busy/{lane}"] = min(1.0, (seconds - last_busy.get(lane, 0.0)) / dt) if now > last_t else 0.0
        if now > last_t:
            self._last = (now, counts, busy)
        return out

    def start_interval(self) -> None:
        """Begin the first rate interval now (rates of the first report are over the time since)."""
        with self._lock:
            self._last = (time.monotonic(), dict(self._counts), dict(self._busy))
