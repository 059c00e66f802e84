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
over a Zenoh session, :class:`ebrl.bus.memory.MemoryBus` over an in-process network (tests).
"""

from __future__ import annotations

import abc
import asyncio
import atexit
import collections
import contextlib
import functools
import json
import logging
import queue
import threading
import time
import weakref
from dataclasses import dataclass, field
from typing import Any, AsyncIterator, Awaitable, Callable, Generic, Literal, TypeVar

import zenoh

from ebrl import messages  # module import: messages itself imports ebrl.codec
from ebrl.bus import auth
from ebrl.bus.endpoints import config_file_connect, config_file_listen

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
    max_message_bytes: int = 256 << 20  # larger payloads are dropped before decoding (Zenoh's own rx limit too)
    secret_file: str = ""  # the run's secret (ebrl.bus.auth); empty: an open bus that anyone on the host can join
    role: str = ""  # who signs in (with a secret_file): a role of the service graph, or observer (a script watching)
    run: str = "*"  # the run whose keys a router's access rules name (ebrl.graph.access_control)
    # a launcher's host number, or "router" for ebrl router: a router signed in that opens no link of its own
    # takes that host's Zenoh id (ebrl.bus.auth.host_zid), which the hosts that connect to it trust
    host: int | str | None = None
    file_listen_wins: bool = False  # the listen endpoints of config_file, when it has some, replace ``listen``
    local: str = ""  # a loopback endpoint listened on in any case (a launcher's, for its own services)
    # ``user:password`` of this process's own instance identity, handed over by its launcher (ebrl.procenv): a
    # client signs in with it rather than with its role's line of secret_file (ebrl.bus.auth)
    identity: str = ""
    # a client-mode launcher's router: the service instances it starts ((role, n) pairs), each admitted with its
    # own identity and rights, checked against dictionary_file (ebrl.bus.auth.write_router_dictionary); and the
    # groups each simulator has (its data keys are its own groups'); empty: every role's line, any instance
    instances: tuple[tuple[str, int], ...] = ()
    dictionary_file: str = ""
    groups: int = 0
    # ... and every instance of the run on every host (launchers included), where its plan names them: tokens of
    # any other instance then reach this router's own session alone, where the launcher counts them
    planned: tuple[tuple[str, int], ...] | None = None
    # ... and the processes of several services it starts (run.processes): the first service of each, one of
    # ``instances``, signs in for all of them and may send what each may
    shares: tuple[tuple[tuple[str, int], ...], ...] = ()


# Zenoh's default has both peers of a pair connect to each other as soon as gossip tells them of the other.
# The two sessions race; with usrpwd (bus.auth) zenoh 1.10 rejects the second one as a duplicate of a
# different configuration (eclipse-zenoh/zenoh#2577), and a pair of peers could end with no session at all,
# never hearing each other (a run stalled at start). One side connecting ends the race (tests/test_bus.py
# holds the check; the counts are in the commit that made it so).
AUTOCONNECT_STRATEGY = {"peer": {"to_router": "always", "to_peer": "greater-zid"}}


def zenoh_config(options: BusOptions) -> zenoh.Config:
    """A Zenoh config: loopback-only peer unless told otherwise, multicast scouting off; with a
    ``secret_file``, signed in as ``role`` and, as a router or peer, access-controlled (:mod:`ebrl.bus.auth`);
    with an ``identity`` (a service its launcher started), signed in as its own instance.

    Peers learn each other's loopback locators by gossip through the endpoint they
    connect to (the launcher's), so services talk directly, without a relay. Of two peers that learn of each
    other, only the one with the greater Zenoh id connects (:data:`AUTOCONNECT_STRATEGY`).
    """
    conf = zenoh.Config.from_file(options.config_file) if options.config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(options.mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if json.loads(conf.get_json("scouting/gossip/autoconnect_strategy")) is None:  # unless config_file says
        conf.insert_json5("scouting/gossip/autoconnect_strategy", json.dumps(AUTOCONNECT_STRATEGY))
    file_listen = config_file_listen(options.config_file)  # none where the file leaves the default (every address)
    listen = file_listen if options.file_listen_wins and file_listen else options.listen
    listen = [*listen, options.local] if options.local and options.local not in listen else listen
    if listen and options.mode != "client" and listen is not file_listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if options.connect:
        conf.insert_json5("connect/endpoints", json.dumps(options.connect))
    # Zenoh reassembles no message larger than this (it drops it, the link stays): the same bound as ours
    conf.insert_json5("transport/link/rx/max_message_size", json.dumps(options.max_message_bytes))
    if options.identity:
        credentials = auth.parse_line(options.identity)
        own = auth.instance_of(credentials.user)
        if options.mode != "client" or own is None or (options.role and own[0] != options.role):
            raise auth.AuthError(f"{credentials.user!r} is no identity of a {options.role or 'service'} instance "
                                 f"(it signs in as a client of its launcher, not as a {options.mode})")
        conf.insert_json5("transport/auth/usrpwd", json.dumps(auth.zenoh_settings(credentials, "client")
                                                               ["transport/auth/usrpwd"]))
    elif options.secret_file:
        if not options.role:
            raise auth.AuthError("signing in needs a role (BusOptions.role): a role of the service graph or "
                                 "observer")
        credentials = auth.load(options.secret_file, options.role)
        connects = options.mode == "router" and bool(options.connect or config_file_connect(options.config_file))
        for path, value in auth.zenoh_settings(credentials, options.mode, options.run, connects, options.instances,
                                               options.dictionary_file or None, options.groups,
                                               options.planned, options.shares).items():
            conf.insert_json5(path, json.dumps(value))
        if options.mode == "router" and not connects and options.host is not None:
            conf.insert_json5("id", json.dumps(auth.host_zid(options.secret_file, options.host)))
    return conf


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
