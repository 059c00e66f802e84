"""A bounded, typed subscription (:class:`Subscription`): each sample is checked against its size bound, decoded
and validated on the transport's thread, then queued for the event loop under an explicit overflow policy:
``block`` (Zenoh's thread waits, which back-pressures the publisher, at most ``BLOCK_LIMIT_S``) or ``latest``
(the oldest item is dropped). A malformed sample is counted by its bus and dropped."""

from __future__ import annotations

import asyncio
import collections
import logging
import threading
import time
from typing import TYPE_CHECKING, Any, AsyncIterator, Callable, Generic, TypeVar

from ebrl import messages

if TYPE_CHECKING:
    from ebrl.bus.session import BusBase

log = logging.getLogger("ebrl.bus")
T = TypeVar("T")

# Zenoh closes a link whose blocking put waits longer than 5 s; a consumer that
# is full for this long drops the sample (counted) so the link survives.
BLOCK_LIMIT_S = 3.0


class Subscription(Generic[T]):
    """Bounded bridge from a bus's transport thread to the event loop (see module docstring)."""

    def __init__(self, bus: BusBase, key: str, cls: type[T] | Callable[[str, bytes], T], policy: str, capacity: int,
                 notify: asyncio.Event | None = None, max_bytes: int | None = None):
        if policy not in ("block", "latest"):
            raise ValueError(f"unknown queue policy {policy!r}")
        self.bus, self.key, self.policy, self.capacity = bus, key, policy, capacity
        self.max_bytes = max_bytes  # the key's bound in this run (ebrl.sizes); None: the bus's alone
        if isinstance(cls, type):
            self._decode: Callable[[str, bytes], T] = lambda _key, payload: messages.decode_message(cls, payload)
            self._accept: Callable[[str, Any], T] | None = lambda _key, msg: messages.accept(cls, msg)
        else:
            self._decode = cls
            self._accept = getattr(cls, "local", None)  # a decoder that takes messages handed over in the process
        self.received = 0
        self.dropped = 0
        self._items: collections.deque[tuple[str, T]] = collections.deque()
        self._cond = threading.Condition()
        self._ready = asyncio.Event()
        self._notify = notify
        self._closed = False
        self._source: Any = None  # the transport's declaration feeding offer(); undeclared on close

    def __len__(self) -> int:
        return len(self._items)

    @property
    def by_reference(self) -> bool:
        """Whether it takes a message handed over in the process as it is (else the message's bytes)."""
        return self._accept is not None

    def offer(self, key: str, payload: Any) -> None:  # a transport thread; payload: bytes-like
        """Check, decode and queue one sample; for a full ``block`` queue, wait for room (back-pressure)."""
        if self._closed or not self.bus.fits(key, len(payload), self.max_bytes):  # len: no copy yet
            return
        try:
            msg = self._decode(key, bytes(payload))
        except Exception as exc:  # MessageError mostly; never let an exception escape into the transport
            self.bus.count_malformed(key, exc)
            return
        self._queue(key, msg)

    def offer_message(self, key: str, msg: Any) -> None:  # a sender thread of this process
        """Check and queue a message handed over by reference in the process (``ebrl.bus.local``): bounded and
        validated as one decoded from the bus, its arrays shared read-only, not copied."""
        assert self._accept is not None
        if self._closed or not self.bus.fits(key, messages.array_bytes(msg), self.max_bytes):
            return
        try:
            accepted = self._accept(key, msg)
        except Exception as exc:
            self.bus.count_malformed(key, exc)
            return
        self._queue(key, accepted)

    def _queue(self, key: str, msg: T) -> None:
        with self._cond:
            if len(self._items) >= self.capacity:
                if self.policy == "latest":
                    self._items.popleft()
                    self.dropped += 1
                else:
                    deadline = time.monotonic() + BLOCK_LIMIT_S
                    while len(self._items) >= self.capacity and not self._closed:
                        left = deadline - time.monotonic()
                        if left <= 0:
                            self.dropped += 1
                            log.warning("%s: consumer stalled %.0f s, dropped a sample", self.key, BLOCK_LIMIT_S)
                            return
                        self._cond.wait(left)
            if self._closed:
                return
            self._items.append((key, msg))
            self.received += 1
            was_empty = len(self._items) == 1
        if was_empty:
            self.bus._call_soon(self._signal)

    def _signal(self) -> None:
        self._ready.set()
        if self._notify is not None:
            self._notify.set()

    def drain(self, limit: int | None = None) -> list[tuple[str, T]]:
        """Take up to ``limit`` items that are already here, without waiting."""
        out = []
        with self._cond:
            while self._items and (limit is None or len(out) < limit):
                out.append(self._items.popleft())
            if out:
                self._cond.notify_all()
        return out

    async def next(self) -> tuple[str, T]:
        while True:
            with self._cond:
                if self._items:
                    item = self._items.popleft()
                    self._cond.notify_all()
                    return item
                self._ready.clear()
            await self._ready.wait()

    def __aiter__(self) -> AsyncIterator[tuple[str, T]]:
        return self

    async def __anext__(self) -> tuple[str, T]:
        return await self.next()

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        try:
            if self._source is not None:
                self._source.undeclare()
        except Exception:
            pass
