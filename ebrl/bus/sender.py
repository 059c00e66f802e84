"""A bus's one sender thread (:class:`Sender`): what is published, from the event loop or any thread, goes in
order through a bounded queue to the transport's blocking put, so that no publisher waits on the network and
the event loop never blocks in Zenoh."""

from __future__ import annotations

import asyncio
import logging
import queue
import threading
import time
from typing import Any, Callable

log = logging.getLogger("ebrl.bus")

SENDER_QUEUE = 4096  # samples waiting for the sender thread; put waits for room, offer drops (counted)

Outgoing = tuple[str, "bytes | None", bool, Any]
"""One sample on its way: key, payload (None: no one needs the bytes, ``ebrl.bus.local``), express, and the message
itself (None: only its bytes were published)."""


class Sender:
    """A bus's one sender thread: what is published, from the event loop or any thread, goes in order through
    a bounded queue (``SENDER_QUEUE``) to the transport's blocking ``put``, so that no publisher waits on the
    network; ``put`` waits for room, ``offer`` drops (counted) when there is none."""

    def __init__(self, put: Callable[[str, bytes | None, bool, Any], None], closed: Callable[[], bool],
                 settle_s: float):
        self._put, self._closed, self.settle_s = put, closed, settle_s
        self.queue: queue.Queue = queue.Queue(maxsize=SENDER_QUEUE)
        self.dropped = 0
        self.thread = threading.Thread(target=self._loop, name="ebrl-bus-sender", daemon=True)
        self.thread.start()

    def offer(self, item: Outgoing) -> bool:
        try:
            self.queue.put_nowait(item)
            return True
        except queue.Full:
            self.dropped += 1
            return False

    async def put(self, loop: asyncio.AbstractEventLoop, item: Outgoing) -> None:
        try:
            self.queue.put_nowait(item)
        except queue.Full:
            await loop.run_in_executor(None, self.queue.put, item)

    def _loop(self) -> None:
        while True:
            item = self.queue.get()
            if item is None:
                return
            key, payload, express, msg = item
            try:
                self._put(key, payload, express, msg)
            except Exception as exc:  # a closed session at shutdown, mostly
                if not self._closed():
                    log.warning("put on %s failed: %s", key, exc)
            finally:
                self.queue.task_done()

    async def flush(self, timeout: float) -> None:
        """Wait until the queue is empty (best effort, bounded by ``timeout``), then ``settle_s`` for the last
        put to leave the socket."""
        deadline = time.monotonic() + timeout
        while self.queue.unfinished_tasks:
            if time.monotonic() > deadline:
                return
            await asyncio.sleep(0.005)
        await asyncio.sleep(self.settle_s)

    def drop_all(self) -> None:
        """Lose what is still queued and end the thread (a bus that dies like a killed process)."""
        while True:
            try:
                self.queue.get_nowait()
                self.queue.task_done()
            except queue.Empty:
                break
        self.queue.put_nowait(None)

    async def stop(self, loop: asyncio.AbstractEventLoop) -> None:
        """End the thread once it sent what is queued (at most 2 s more)."""
        self.queue.put(None)
        await loop.run_in_executor(None, self.thread.join, 2.0)
