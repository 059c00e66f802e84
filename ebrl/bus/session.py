"""The one asyncio bridge to the bus: publishing, bounded subscriptions, liveliness, queries; over Zenoh here.

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

:class:`BusBase` holds all of that except the transport, and so is the bus API; :class:`Bus` carries it
over a Zenoh session, :class:`ebrl.bus.memory.MemoryBus` over an in-process network (tests). The pieces a bus
holds have modules of their own: its options and Zenoh config (:mod:`ebrl.bus.options`), its sender thread
(:mod:`ebrl.bus.sender`) and its subscriptions (:mod:`ebrl.bus.subscription`); ``BusOptions``,
``zenoh_config`` and ``Subscription`` are importable from here too.
"""

from __future__ import annotations

import abc
import asyncio
import atexit
import collections
import contextlib
import functools
import logging
import threading
import weakref
from dataclasses import dataclass
from typing import Any, Awaitable, Callable, Literal, TypeVar

import zenoh

from ebrl import messages  # module import: a test counts the encodings by patching it (tests/test_local_bus.py)
from ebrl.bus.options import BusOptions, zenoh_config
from ebrl.bus.sender import Outgoing, Sender
from ebrl.bus.subscription import Subscription

__all__ = ["Bus", "BusBase", "BusOptions", "Outgoing", "Query", "Subscription", "intersects", "zenoh_config"]

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


@functools.lru_cache(maxsize=4096)
def intersects(a: str, b: str) -> bool:
    """Whether two key expressions share a key, by Zenoh's own rules (``*``, ``**``, ``@`` chunks)."""
    return zenoh.KeyExpr(a).intersects(zenoh.KeyExpr(b))


@dataclass(eq=False)
class Query:
    """A query being answered (:meth:`BusBase.declare_queryable_raw`): reply from any thread, any number of
    times, with a key that :meth:`matches` the query's; then :meth:`finish`."""

    key: str  # the query's key expression: may hold wildcards, so not the key to reply on
    payload: bytes
    _reply: Callable[[str, bytes], None]
    _finish: Callable[[], None]

    def matches(self, key: str) -> bool:
        return intersects(self.key, key)

    def reply(self, key: str, payload: bytes) -> None:
        self._reply(key, payload)

    def finish(self) -> None:
        """No more replies: the asker's ``get`` returns once every answerer finished (or at its timeout)."""
        self._finish()


class BusBase(abc.ABC):
    """The bus API, bridged to one asyncio loop: everything but the transport. Create it inside the running
    loop; ``loop`` is that loop. Declarations return a handle with ``undeclare()``."""

    _FLUSH_SETTLE_S = 0.05  # after the queue is empty, for the last put to leave the socket

    def __init__(self, options: BusOptions | None):
        self.options = options or BusOptions()
        self.loop = asyncio.get_running_loop()
        self.malformed: collections.Counter[str] = collections.Counter()
        self.oversized: collections.Counter[str] = collections.Counter()
        self._loop_thread = threading.get_ident()
        self._logged_keys: set[str] = set()
        self._closed = False
        self._subscriptions: list[Subscription] = []
        self._tasks: set[asyncio.Future] = set()
        self.sender = Sender(self._put, lambda: self._closed, self._FLUSH_SETTLE_S)

    @property
    def sender_dropped(self) -> int:
        """Messages published without waiting (``put_nowait``) and dropped because the sender queue was full."""
        return self.sender.dropped

    # --- the transport --------------------------------------------------------------------

    @abc.abstractmethod
    def _put(self, key: str, payload: bytes | None, express: bool, msg: Any = None) -> None:
        """Hand one sample to the transport, blocking while a subscriber applies back-pressure. ``msg``: the
        message encoded as ``payload``, where it was published as one (a transport may hand it over as it is)."""

    @abc.abstractmethod
    def _feed(self, key: str, callback: Callable[[str, Any], None], subscription: Subscription | None = None) -> Any:
        """Call ``callback(key, payload)`` on a transport thread per sample on ``key`` (payload: bytes-like).
        ``subscription``: the typed subscription ``callback`` feeds, if it is one."""

    def _outgoing(self, key: str, msg: Any, express: bool) -> Outgoing:
        """What :meth:`put` hands the sender for ``msg``: encoded here, on the publisher's thread, so that the
        message may change once published."""
        return key, messages.encode_message(msg), express, None

    @abc.abstractmethod
    def declare_token(self, key: str) -> Any:
        """A liveliness token on ``key``: present until undeclared, or until this bus closes or dies."""

    @abc.abstractmethod
    def watch_liveliness(self, key: str, on_change: Callable[[str, bool], None]) -> Any:
        """Call ``on_change(key, alive)`` on the event loop for every token matching ``key``
        (tokens already present are reported first)."""

    @abc.abstractmethod
    def declare_queryable_raw(self, key: str, on_query: Callable[[Query], None]) -> Any:
        """Call ``on_query(query)`` on a transport thread for every query on ``key``; it must return at
        once, and the query be answered from elsewhere (a worker thread, a task): see :class:`Query`."""

    @abc.abstractmethod
    async def get_raw(self, selector: str, on_reply: Callable[[str, bytes], None], payload: bytes | None = None,
                      timeout: float = 1.0) -> None:
        """Query ``selector``: call ``on_reply(key, payload)`` on a transport thread as every reply arrives (none
        merged, each sent with blocking congestion control); return when all answerers finished or at
        ``timeout`` seconds, at once if nobody answers."""

    @abc.abstractmethod
    def _close_now(self) -> None:
        """Close without flushing: the synchronous tail of :meth:`close`."""

    # --- publishing -------------------------------------------------------------------------

    async def put(self, key: str, msg: Any, *, express: bool = False) -> None:
        """Publish ``msg`` (a message dataclass) on ``key``; waits only if the sender queue is full."""
        await self.sender.put(self.loop, self._outgoing(key, msg, express))

    async def put_bytes(self, key: str, payload: bytes, *, express: bool = False) -> None:
        """Publish an already encoded payload (encode once, send and serve many times)."""
        await self.sender.put(self.loop, (key, payload, express, None))

    def put_nowait(self, key: str, msg: Any, *, express: bool = False) -> bool:
        """Publish from any thread without waiting; a full sender queue drops it (counted)."""
        return self.sender.offer(self._outgoing(key, msg, express))

    def put_bytes_blocking(self, key: str, payload: bytes) -> None:
        """Publish from a worker thread, past the sender queue (so unordered with ``put``): returns once the
        transport has the sample, blocking while a subscriber applies back-pressure. Large, many-part
        sends (weights) use it to know when each part has left."""
        if threading.get_ident() == self._loop_thread:
            raise RuntimeError("put_bytes_blocking blocks its thread: call it from a worker thread")
        self._put(key, payload, False, None)

    async def flush(self, timeout: float = 2.0) -> None:
        """Wait until the sender queue is empty (best effort, bounded by ``timeout``)."""
        await self.sender.flush(timeout)

    # --- subscribing ------------------------------------------------------------------------

    def subscribe(self, key: str, cls: type[T] | Callable[[str, bytes], T], *,
                  policy: Literal["block", "latest"] = "block", capacity: int = 64,
                  notify: asyncio.Event | None = None, max_bytes: int | None = None) -> Subscription[T]:
        """A bounded, typed async iterator of ``(key, message)`` for samples on ``key``.

        ``cls`` is a message class, or a function ``(key, payload) -> message`` for keys that
        carry several types (``messages.decode_stats_sample``); either raises ``MessageError``
        on a malformed payload. ``notify`` is set too when a sample arrives, so one task can
        wait on several subscriptions. ``max_bytes``: the key's bound in this run (``ebrl.sizes``), below the
        bus's; a larger payload is counted and dropped before it is copied or decoded (:meth:`fits`)."""
        sub = Subscription(self, key, cls, policy, capacity, notify, max_bytes)
        sub._source = self._feed(key, sub.offer, sub)
        self._subscriptions.append(sub)
        return sub

    def subscribe_raw(self, key: str, callback: Callable[[str, bytes], None], max_bytes: int | None = None) -> Any:
        """Call ``callback(key, payload)`` on a transport thread for every sample: no decoding, no queue.
        For recorders that must stay cheap; the callback must be fast and never raise. ``max_bytes``: as
        :meth:`subscribe`'s."""

        def on_sample(sample_key: str, payload: Any) -> None:
            if not self.fits(sample_key, len(payload), max_bytes):  # before the copy
                return
            try:
                callback(sample_key, bytes(payload))
            except Exception as exc:  # never let an exception escape into the transport
                log.warning("raw subscriber on %s: %s", key, exc)

        return self._feed(key, on_sample)

    def fits(self, key: str, size: int, max_bytes: int | None = None) -> bool:
        """False, counted as oversized and malformed, for a payload over ``options.max_message_bytes`` or over
        ``max_bytes`` (its key's bound in this run, ``ebrl.sizes``). Asked with the length Zenoh reports before
        the payload is copied out of it, so a refused payload costs no copy."""
        limit = self.options.max_message_bytes if max_bytes is None else min(max_bytes,
                                                                             self.options.max_message_bytes)
        if size <= limit:
            return True
        self.oversized[key] += 1
        self.count_malformed(key, ValueError(f"{size} bytes, over its limit of {limit} (the key's bound in this run, "
                                             "or bus.max_message_bytes)"))
        return False

    def count_malformed(self, key: str, error: Exception) -> None:
        if isinstance(error, messages.OversizedError):
            self.oversized[key] += 1
        self.malformed[key] += 1
        if key not in self._logged_keys:
            self._logged_keys.add(key)
            log.warning("dropped malformed message on %s: %s (further ones on this key are only counted)", key, error)

    # --- request / reply --------------------------------------------------------------------

    def declare_queryable(self, key: str, answer: Callable[[bytes], Awaitable[bytes | None]]) -> Any:
        """Answer queries on ``key`` with ``await answer(request_payload)`` (None: no reply)."""

        def on_query(query: Query) -> None:
            async def respond() -> None:
                try:
                    payload = await answer(query.payload)
                    if payload is not None:
                        query.reply(query.key if "*" not in query.key else key, payload)
                except Exception as exc:
                    log.warning("query on %s failed: %s", key, exc)
                finally:
                    query.finish()

            self._call_soon(self._start_task, respond())

        return self.declare_queryable_raw(key, on_query)

    async def get(self, selector: str, payload: bytes | None = None, timeout: float = 1.0) -> list[tuple[str, bytes]]:
        """Query ``selector``; return ``(key, payload)`` of every reply (none merged) within ``timeout`` seconds."""
        replies: list[tuple[str, bytes]] = []
        await self.get_raw(selector, lambda key, data: replies.append((key, data)), payload, timeout)
        return replies

    # --- lifecycle --------------------------------------------------------------------------

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
        """Flush, then withdraw everything this bus declared (watchers see its tokens go)."""
        if self._closed:
            return
        await self.flush()
        self._closed = True
        for sub in self._subscriptions:
            sub.close()
        await self.sender.stop(self.loop)
        self._close_now()


class Bus(BusBase):
    """One Zenoh session bridged to one asyncio loop. Create it inside the running loop. ``session``: an open one
    to use (services sharing a process share theirs: ``ebrl.process``), which this bus then does not close; it
    withdraws only what it declared itself."""

    def __init__(self, options: BusOptions | None = None, *, session: zenoh.Session | None = None):
        options = options or BusOptions()
        self._owns_session = session is None
        self.session = session or zenoh.open(zenoh_config(options))
        super().__init__(options)
        self._publishers: dict[tuple[str, bool], zenoh.Publisher] = {}
        self._publishers_lock = threading.Lock()  # the sender thread and put_bytes_blocking's callers
        self._declared: list[Any] = []  # zenoh-python undeclares what is no longer referenced
        _open_buses.add(self)

    def _put(self, key: str, payload: bytes | None, express: bool, msg: Any = None) -> None:
        if payload is not None:
            self._publisher(key, express).put(payload)

    def routers_linked(self) -> int:
        """Zenoh routers this session has a link to: for a launcher that connects to another host, that host's
        launcher or the ``ebrl router`` (its own services are clients, not counted)."""
        return len(list(self.session.info.routers_zid()))

    def _publisher(self, key: str, express: bool) -> zenoh.Publisher:
        with self._publishers_lock:
            pub = self._publishers.get((key, express))
            if pub is None:
                pub = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                                     express=express, allowed_destination=self._destination)
                self._publishers[(key, express)] = pub
        return pub

    _destination = zenoh.Locality.ANY  # where this bus's samples go (ebrl.bus.local: other processes only)

    def _feed(self, key: str, callback: Callable[[str, Any], None], subscription: Subscription | None = None
              ) -> zenoh.Subscriber:
        sub = self.session.declare_subscriber(key, lambda sample: callback(str(sample.key_expr), sample.payload),
                                              allowed_origin=self._destination)
        self._declared.append(sub)
        return sub

    def declare_token(self, key: str) -> zenoh.LivelinessToken:
        token = self.session.liveliness().declare_token(key)
        self._declared.append(token)
        return token

    def watch_liveliness(self, key: str, on_change: Callable[[str, bool], None]) -> zenoh.Subscriber:
        def callback(sample: zenoh.Sample) -> None:
            alive = sample.kind == zenoh.SampleKind.PUT
            self._call_soon(on_change, str(sample.key_expr), alive)

        sub = self.session.liveliness().declare_subscriber(key, callback, history=True)
        self._declared.append(sub)
        return sub

    def declare_queryable_raw(self, key: str, on_query: Callable[[Query], None]) -> zenoh.Queryable:
        def callback(query: zenoh.Query) -> None:
            request = query.payload.to_bytes() if query.payload is not None else b""
            try:
                on_query(Query(str(query.key_expr), request, query.reply, query.drop))
            except Exception as exc:  # never let an exception escape into Zenoh
                log.warning("query on %s failed: %s", key, exc)
                query.drop()

        queryable = self.session.declare_queryable(key, callback)
        self._declared.append(queryable)
        return queryable

    async def get_raw(self, selector: str, on_reply: Callable[[str, bytes], None], payload: bytes | None = None,
                      timeout: float = 1.0) -> None:
        def run() -> None:
            # Replies travel with the query's congestion control: blocking, so no reply is dropped.
            replies = self.session.get(selector, payload=payload, timeout=timeout,
                                       consolidation=zenoh.ConsolidationMode.NONE,
                                       congestion_control=zenoh.CongestionControl.BLOCK)
            for reply in replies:
                if reply.ok is not None:
                    on_reply(str(reply.ok.key_expr), reply.ok.payload.to_bytes())

        await self.loop.run_in_executor(None, run)

    def _close_now(self) -> None:
        """Close without flushing (the synchronous tail of close; also run at interpreter exit)."""
        self._closed = True
        _open_buses.discard(self)
        for sub in self._subscriptions:
            sub.close()
        if not self._owns_session:  # a shared session: withdraw this bus's own declarations alone
            for declared in self._declared:
                with contextlib.suppress(Exception):
                    declared.undeclare()
            for pub in self._publishers.values():
                with contextlib.suppress(Exception):
                    pub.undeclare()
            return
        try:
            self.session.close()
        except Exception as exc:
            log.debug("session close: %s", exc)
