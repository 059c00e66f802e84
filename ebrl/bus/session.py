"""The one asyncio bridge to Zenoh: sessions, publishing, bounded subscriptions, liveliness, queries.

zenoh-python has no asyncio API. Its callbacks run on Zenoh-owned threads, and
a put with blocking congestion control can block its thread. So:

* every put goes through one sender thread per session (ordered, never on the
  event loop), fed by a bounded queue;
* every subscription decodes and validates on Zenoh's thread, then hands the
  typed message to a bounded deque that the event loop drains. Its overflow
  policy is explicit: ``block`` (data that must not be lost: Zenoh's thread
  waits, which back-pressures the publisher) or ``latest`` (weights, stats:
  the oldest item is dropped);
* a malformed payload is counted per key, logged once per key, and dropped.
"""

from __future__ import annotations

import asyncio
import atexit
import collections
import json
import logging
import queue
import threading
import time
import weakref
from dataclasses import dataclass, field
from typing import Any, AsyncIterator, Awaitable, Callable, Generic, Literal, TypeVar

import zenoh

from ebrl import messages  # module import: messages itself imports ebrl.bus.codec

log = logging.getLogger("ebrl.bus")
T = TypeVar("T")
_open_buses: weakref.WeakSet[Bus] = weakref.WeakSet()


def _close_forgotten_buses() -> None:
    # zenoh-python runs Python callbacks on non-daemon threads that live until
    # the subscriber is undeclared, so a session left open (a test that failed
    # before bus.close(), a service that crashed) would hang interpreter exit.
    # threading's exit hooks run before it joins those threads.
    for bus in list(_open_buses):
        bus._close_now()


_register_exit = getattr(threading, "_register_atexit", atexit.register)
_register_exit(_close_forgotten_buses)

# Zenoh closes a link whose blocking put waits longer than 5 s; a consumer that
# is full for this long drops the sample (counted) so the link survives.
BLOCK_LIMIT_S = 3.0
SENDER_QUEUE = 4096


@dataclass
class BusOptions:
    """How to join the bus. Built from the ``[bus]`` config section."""

    mode: Literal["peer", "client", "router"] = "peer"  # router: a launcher joining hosts
    connect: list[str] = field(default_factory=list)
    listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:0"])
    config_file: str = ""
    max_message_bytes: int = 1 << 30  # larger payloads are dropped (counted) before decoding


def zenoh_config(options: BusOptions) -> zenoh.Config:
    """A Zenoh config: loopback-only peer unless told otherwise, multicast scouting off.

    Peers learn each other's loopback locators by gossip through the endpoint they
    connect to (the launcher's), so services talk directly, without a relay.
    """
    conf = zenoh.Config.from_file(options.config_file) if options.config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(options.mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if options.listen and options.mode != "client":
        conf.insert_json5("listen/endpoints", json.dumps(options.listen))
    if options.connect:
        conf.insert_json5("connect/endpoints", json.dumps(options.connect))
    return conf


class Bus:
    """One Zenoh session bridged to one asyncio loop. Create it inside the running loop."""

    def __init__(self, options: BusOptions | None = None, *, session: zenoh.Session | None = None):
        self.options = options or BusOptions()
        self.session = session or zenoh.open(zenoh_config(self.options))
        self.loop = asyncio.get_running_loop()
        self.malformed: collections.Counter[str] = collections.Counter()
        self.oversized: collections.Counter[str] = collections.Counter()
        self.sender_dropped = 0
        self._logged_keys: set[str] = set()
        self._publishers: dict[tuple[str, bool], zenoh.Publisher] = {}
        self._outbox: queue.Queue = queue.Queue(maxsize=SENDER_QUEUE)
        self._sender = threading.Thread(target=self._send_loop, name="ebrl-bus-sender", daemon=True)
        self._sender.start()
        self._closed = False
        self._declared: list[Any] = []
        self._tasks: set[asyncio.Future] = set()
        _open_buses.add(self)

    # --- publishing -------------------------------------------------------------

    async def put(self, key: str, msg: Any, *, express: bool = False) -> None:
        """Publish ``msg`` (a message dataclass) on ``key``; waits only if the sender queue is full."""
        await self.put_bytes(key, messages.encode_message(msg), express=express)

    async def put_bytes(self, key: str, payload: bytes, *, express: bool = False) -> None:
        """Publish an already encoded payload (encode once, send and serve many times)."""
        item = (key, payload, express)
        try:
            self._outbox.put_nowait(item)
        except queue.Full:
            await self.loop.run_in_executor(None, self._outbox.put, item)

    def put_nowait(self, key: str, msg: Any, *, express: bool = False) -> bool:
        """Publish from any thread without waiting; a full sender queue drops it (counted)."""
        try:
            self._outbox.put_nowait((key, messages.encode_message(msg), express))
            return True
        except queue.Full:
            self.sender_dropped += 1
            return False

    def _send_loop(self) -> None:
        while True:
            item = self._outbox.get()
            if item is None:
                return
            key, payload, express = item
            try:
                self._put(key, payload, express)
            finally:
                self._outbox.task_done()

    def _put(self, key: str, payload: bytes, express: bool) -> None:
        try:
            pub = self._publishers.get((key, express))
            if pub is None:
                pub = self.session.declare_publisher(
                    key, congestion_control=zenoh.CongestionControl.BLOCK, express=express
                )
                self._publishers[(key, express)] = pub
            pub.put(payload)
        except Exception as exc:  # a closed session at shutdown, mostly
            if not self._closed:
                log.warning("put on %s failed: %s", key, exc)

    async def flush(self, timeout: float = 2.0) -> None:
        """Wait until the sender queue is empty (best effort, bounded by ``timeout``)."""
        deadline = time.monotonic() + timeout
        while self._outbox.unfinished_tasks:
            if time.monotonic() > deadline:
                return
            await asyncio.sleep(0.005)
        await asyncio.sleep(0.05)  # let the last put leave the socket before close

    # --- subscribing ------------------------------------------------------------

    def subscribe(
        self,
        key: str,
        cls: type[T] | Callable[[str, bytes], T],
        *,
        policy: Literal["block", "latest"] = "block",
        capacity: int = 64,
        notify: asyncio.Event | None = None,
    ) -> "Subscription[T]":
        """A bounded, typed async iterator of ``(key, message)`` for samples on ``key``.

        ``cls`` is a message class, or a function ``(key, payload) -> message`` for keys that
        carry several types (``messages.decode_stats_sample``); either raises ``MessageError``
        on a malformed payload. ``notify`` is set too when a sample arrives, so one task can
        wait on several subscriptions."""
        sub = Subscription(self, key, cls, policy, capacity, notify)
        self._declared.append(sub)
        return sub

    def subscribe_raw(self, key: str, callback: Callable[[str, bytes], None]) -> None:
        """Call ``callback(key, payload)`` on a Zenoh thread for every sample: no decoding, no
        queue. For recorders that must stay cheap; the callback must be fast and never raise."""

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                callback(str(sample.key_expr), sample.payload.to_bytes())
            except Exception as exc:  # never let an exception escape into Zenoh
                log.warning("raw subscriber on %s: %s", key, exc)

        self._declared.append(self.session.declare_subscriber(key, on_sample))

    def count_malformed(self, key: str, error: Exception) -> None:
        self.malformed[key] += 1
        if key not in self._logged_keys:
            self._logged_keys.add(key)
            log.warning("dropped malformed message on %s: %s (further ones on this key are only counted)", key, error)

    # --- liveliness -------------------------------------------------------------

    def declare_token(self, key: str) -> zenoh.LivelinessToken:
        token = self.session.liveliness().declare_token(key)
        self._declared.append(token)
        return token

    def watch_liveliness(self, key: str, on_change: Callable[[str, bool], None]) -> None:
        """Call ``on_change(key, alive)`` on the event loop for every token matching ``key``
        (tokens already present are reported first)."""

        def callback(sample: zenoh.Sample) -> None:
            alive = sample.kind == zenoh.SampleKind.PUT
            self._call_soon(on_change, str(sample.key_expr), alive)

        sub = self.session.liveliness().declare_subscriber(key, callback, history=True)
        self._declared.append(sub)

    # --- request / reply --------------------------------------------------------

    def declare_queryable(self, key: str, answer: Callable[[bytes], Awaitable[bytes | None]]) -> None:
        """Answer queries on ``key`` with ``await answer(request_payload)`` (None: no reply)."""

        def callback(query: zenoh.Query) -> None:
            request = query.payload.to_bytes() if query.payload is not None else b""
            reply_key = str(query.key_expr) if "*" not in str(query.key_expr) else key

            async def respond() -> None:
                try:
                    payload = await answer(request)
                    if payload is not None:
                        query.reply(reply_key, payload)
                except Exception as exc:
                    log.warning("query on %s failed: %s", key, exc)
                finally:
                    query.drop()

            self._call_soon(self._start_task, respond())

        queryable = self.session.declare_queryable(key, callback)
        self._declared.append(queryable)

    async def get(self, selector: str, payload: bytes | None = None, timeout: float = 1.0) -> list[tuple[str, bytes]]:
        """Query ``selector``; return ``(key, payload)`` of every reply within ``timeout`` seconds."""

        def run() -> list[tuple[str, bytes]]:
            replies = self.session.get(selector, payload=payload, timeout=timeout)
            out = []
            for reply in replies:
                if reply.ok is not None:
                    out.append((str(reply.ok.key_expr), reply.ok.payload.to_bytes()))
            return out

        return await self.loop.run_in_executor(None, run)

    # --- lifecycle --------------------------------------------------------------

    def _start_task(self, coro: Awaitable[None]) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)  # the loop holds tasks weakly
        task.add_done_callback(self._tasks.discard)

    def _call_soon(self, fn: Callable[..., Any], *args: Any) -> None:
        try:
            self.loop.call_soon_threadsafe(fn, *args)
        except RuntimeError:  # loop closed during shutdown
            pass

    async def close(self) -> None:
        if self._closed:
            return
        await self.flush()
        self._closed = True
        for obj in self._declared:
            if isinstance(obj, Subscription):
                obj.close()
        self._outbox.put(None)
        await self.loop.run_in_executor(None, self._sender.join, 2.0)
        self._close_now()

    def _close_now(self) -> None:
        """Close without flushing (the synchronous tail of close; also run at interpreter exit)."""
        self._closed = True
        _open_buses.discard(self)
        for obj in self._declared:
            if isinstance(obj, Subscription):
                obj.close()
        try:
            self.session.close()
        except Exception as exc:
            log.debug("session close: %s", exc)


class Subscription(Generic[T]):
    """Bounded bridge from a Zenoh subscriber to the event loop (see module docstring)."""

    def __init__(self, bus: Bus, key: str, cls: type[T] | Callable[[str, bytes], T], policy: str, capacity: int,
                 notify: asyncio.Event | None = None):
        if policy not in ("block", "latest"):
            raise ValueError(f"unknown queue policy {policy!r}")
        self.bus, self.key, self.policy, self.capacity = bus, key, policy, capacity
        if isinstance(cls, type):
            self._decode: Callable[[str, bytes], T] = lambda _key, payload: messages.decode_message(cls, payload)
        else:
            self._decode = cls
        self.received = 0
        self.dropped = 0
        self._items: collections.deque[tuple[str, T]] = collections.deque()
        self._cond = threading.Condition()
        self._ready = asyncio.Event()
        self._notify = notify
        self._closed = False
        self._sub = bus.session.declare_subscriber(key, self._on_sample)

    def __len__(self) -> int:
        return len(self._items)

    def _on_sample(self, sample: zenoh.Sample) -> None:  # runs on a Zenoh thread
        key = str(sample.key_expr)
        if len(sample.payload) > self.bus.options.max_message_bytes:
            self.bus.oversized[key] += 1
            self.bus.count_malformed(key, ValueError(f"{len(sample.payload)} bytes, over bus.max_message_bytes = "
                                                     f"{self.bus.options.max_message_bytes}"))
            return
        try:
            msg = self._decode(key, sample.payload.to_bytes())
        except messages.MessageError as exc:
            self.bus.count_malformed(key, exc)
            return
        except Exception as exc:  # never let an exception escape into Zenoh
            self.bus.count_malformed(key, exc)
            return
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
            self._sub.undeclare()
        except Exception:
            pass
