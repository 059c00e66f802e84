"""An in-memory bus with the API of :class:`ebrl.bus.session.Bus`, for tests that run several services in one process.

Like dora-rs's ``MockNode`` or FastStream's in-memory broker, but with the bus's real semantics::

    network = MemoryNetwork()                      # the fabric: one per test
    train_bus = MemoryBus(network)                 # one per service, created inside the running loop
    gen_bus = MemoryBus(network, BusOptions(max_message_bytes=1 << 20))

Code written against the bus API (:class:`~ebrl.bus.session.BusBase`: services, ``ebrl.weights``) runs unchanged
on it; all buses of a network share one event loop in a test, though nothing requires it.

Every bus on a network sees the samples, liveliness tokens and queryables of every bus on it, its own
included, as Zenoh peers do. What stays real: payloads are encoded and decoded by ``ebrl.messages``, so a
malformed or oversized one is counted and dropped exactly as over Zenoh; key expressions match by Zenoh's
own rules (``zenoh.KeyExpr``); publishing goes through the same ordered sender thread as :class:`Bus`, which
delivers into each subscriber's bounded queue, so a full ``block`` subscription stalls the publisher for up
to ``BLOCK_LIMIT_S`` (then drops, counted) and ``put`` awaits once the sender queue is full; ``latest``
drops the oldest; ``put_nowait`` works from any thread; ``express`` is accepted (nothing to bypass here).
After ``await bus.flush()`` everything put before is in the subscribers' queues (or counted as dropped).

``close()`` flushes and withdraws the bus's declarations: watchers see its tokens go (``alive=False``), as
when a process exits. ``crash()`` is a killed process: what is still unsent is lost and everything is
withdrawn at once. A query with no answerer returns ``[]`` at once; answers run on the answerer's loop.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from dataclasses import dataclass
from typing import Any, Callable

import zenoh

from ebrl.bus.session import BusBase, BusOptions, Query, intersects

log = logging.getLogger("ebrl.bus")

KINDS = ("subscriber", "token", "watcher", "queryable")


@dataclass(eq=False)
class Declaration:
    """One subscriber, liveliness token, liveliness watcher or queryable on a network."""

    network: MemoryNetwork
    bus: MemoryBus
    kind: str
    key: str
    callback: Callable[..., Any] | None = None

    def undeclare(self) -> None:
        self.network.withdraw(self)


class MemoryNetwork:
    """The in-process fabric that :class:`MemoryBus` instances share: who subscribes, which liveliness tokens
    live, who watches them, who answers queries. Thread-safe: senders deliver from their own threads."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._declared: dict[str, list[Declaration]] = {kind: [] for kind in KINDS}

    def declare(self, decl: Declaration) -> None:
        zenoh.KeyExpr(decl.key)  # a malformed key expression raises, as on Zenoh
        with self._lock:  # liveliness news is queued under the lock, so it reaches each loop in order
            self._declared[decl.kind].append(decl)
            if decl.kind == "token":
                self._tell_watchers(decl.key, True)
            elif decl.kind == "watcher":
                for token in self._matching("token", decl.key):  # history: the tokens already there
                    decl.bus._call_soon(decl.callback, token.key, True)

    def withdraw(self, decl: Declaration) -> None:
        with self._lock:
            if decl not in self._declared[decl.kind]:
                return
            self._declared[decl.kind].remove(decl)
            if decl.kind == "token":
                self._tell_watchers(decl.key, False)

    def matching(self, kind: str, key: str) -> list[Declaration]:
        with self._lock:
            return self._matching(kind, key)

    def deliver(self, key: str, payload: bytes) -> None:
        """Hand one sample to every matching subscriber, on the caller's thread (a sender's)."""
        for decl in self.matching("subscriber", key):
            decl.callback(key, payload)

    def _matching(self, kind: str, key: str) -> list[Declaration]:  # under self._lock
        return [decl for decl in self._declared[kind] if intersects(decl.key, key)]

    def _tell_watchers(self, key: str, alive: bool) -> None:  # under self._lock
        for watcher in self._matching("watcher", key):
            watcher.bus._call_soon(watcher.callback, key, alive)


class MemoryBus(BusBase):
    """A bus on a :class:`MemoryNetwork`, with :class:`~ebrl.bus.session.Bus`'s API. Create it inside the running loop."""

    _FLUSH_SETTLE_S = 0.0  # no socket: once the sender queue is empty, every sample is delivered

    def __init__(self, network: MemoryNetwork, options: BusOptions | None = None):
        super().__init__(options)
        self.network = network
        self._crashed = False
        self._declarations: list[Declaration] = []

    def _declare(self, kind: str, key: str, callback: Callable[..., Any] | None = None) -> Declaration:
        if self._closed:
            raise RuntimeError(f"declaring {key} on a closed bus")
        decl = Declaration(self.network, self, kind, key, callback)
        self.network.declare(decl)
        self._declarations.append(decl)
        return decl

    def _put(self, key: str, payload: bytes | None, express: bool, msg: Any = None) -> None:
        if not self._crashed and payload is not None:
            self.network.deliver(key, payload)

    def _feed(self, key: str, callback: Callable[[str, Any], None], subscription: Any = None) -> Declaration:
        return self._declare("subscriber", key, callback)

    def declare_token(self, key: str) -> Declaration:
        return self._declare("token", key)

    def watch_liveliness(self, key: str, on_change: Callable[[str, bool], None]) -> Declaration:
        return self._declare("watcher", key, on_change)

    def declare_queryable_raw(self, key: str, on_query: Callable[[Query], None]) -> Declaration:
        return self._declare("queryable", key, on_query)

    async def get_raw(self, selector: str, on_reply: Callable[[str, bytes], None], payload: bytes | None = None,
                      timeout: float = 1.0) -> None:
        key = selector.split("?", 1)[0]
        zenoh.KeyExpr(key)
        answerers = self.network.matching("queryable", key)
        if not answerers:
            return
        gathering = _Gathering(self, key, on_reply, len(answerers))
        for decl in answerers:
            query = Query(key, payload or b"", gathering.reply, gathering.finisher())
            try:
                decl.callback(query)
            except Exception as exc:
                log.warning("query on %s failed: %s", decl.key, exc)
                query.finish()
        try:
            await asyncio.wait_for(gathering.done.wait(), timeout)
        except asyncio.TimeoutError:
            pass
        gathering.close()

    def crash(self) -> None:
        """Die like a killed process: what is still unsent is lost (a sample being delivered may still
        arrive), subscriptions stop, and tokens and queryables vanish at once (watchers see ``alive=False``)."""
        self._crashed = True
        self.sender.drop_all()
        self._close_now()

    def _close_now(self) -> None:
        self._closed = True
        for sub in self._subscriptions:
            sub.close()
        for decl in self._declarations:
            decl.undeclare()


class _Gathering:
    """The replies to one ``get``: handed to ``on_reply`` one at a time until the asker stops listening."""

    def __init__(self, bus: MemoryBus, key: str, on_reply: Callable[[str, bytes], None], answerers: int):
        self.bus, self.key, self.on_reply = bus, key, on_reply
        self.done = asyncio.Event()
        self._lock = threading.Lock()  # replies come from any thread; one at a time, as from Zenoh's
        self._listening = True
        self._left = answerers

    def reply(self, key: str, payload: bytes) -> None:
        if not intersects(key, self.key):
            raise ValueError(f"reply on {key} does not match the query {self.key}")
        with self._lock:
            if self._listening:
                self.on_reply(key, bytes(payload))

    def finisher(self) -> Callable[[], None]:
        finished = False

        def finish() -> None:
            nonlocal finished
            with self._lock:
                if finished:
                    return
                finished = True
                self._left -= 1
                if self._left == 0:
                    self.bus._call_soon(self.done.set)

        return finish

    def close(self) -> None:
        with self._lock:
            self._listening = False
