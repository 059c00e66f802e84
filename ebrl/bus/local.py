"""Services of one process (``run.processes``, :mod:`ebrl.process`) hand each other messages by reference.

Each service keeps a bus of its own (:class:`LocalBus`) on the process's one Zenoh session, and the buses of the
process share a :class:`LocalHub`: who in the process subscribes to what. A message one of them publishes goes

* to every subscriber in the process, through the hub, *as the object it is*: no encoding, no copy. A typed
  subscription accepts it as it would a decoded one (:func:`ebrl.messages.accept`: the key's size bound, then
  types, shapes and meaning), and receives a new message whose arrays are read-only views of the sender's. A
  subscriber that wants bytes (a recorder, a decoder without a ``local`` form) gets the message encoded, once;
* over Zenoh to other processes and hosts only (``Locality.REMOTE``), and encoded only when one subscribes
  there (Zenoh's matching status): observations, actions and segments between a simulator, generation and
  training of one process are never encoded at all.

Zenoh's own delivery inside the session is turned off both ways (subscribers take remote samples only), so no
sample arrives twice. The run's access rules hold in the process too: a service may publish only what its role
declares (:func:`ebrl.graph.allowed`); anything else is refused before it is delivered or sent, counted in
``bus/refused`` and logged once per key. (Over Zenoh the router checks the process's identity, which may send
what each of its services may.)

A sender hands a message over and does not change it afterwards; the read-only views keep receivers from
changing it. That holds for what EBRL's services publish: each message's arrays are made for it (the audit is
in tests/test_local_bus.py).
"""

from __future__ import annotations

import collections
import logging
import threading
from typing import Any, Callable

import zenoh

from ebrl import graph, messages
from ebrl.bus.session import Bus, BusOptions, Outgoing, Subscription, intersects

log = logging.getLogger("ebrl.bus")


class _Bytes:
    """A subscriber in the process that takes payloads (``subscribe_raw``, a decoder without ``local``)."""

    by_reference = False

    def __init__(self, callback: Callable[[str, Any], None]):
        self.callback = callback

    def offer(self, key: str, payload: bytes) -> None:
        self.callback(key, payload)


class LocalHub:
    """The subscriptions of every bus of one process, by key expression; thread-safe (senders deliver from their
    own threads)."""

    def __init__(self, run: str):
        self.run = run
        self._lock = threading.Lock()
        self._subscribers: list[tuple[str, Any]] = []
        self._by_key: dict[str, list[Any]] = {}  # a key's subscribers, until the next (un)subscription

    def add(self, key: str, target: Any) -> None:
        with self._lock:
            self._subscribers.append((key, target))
            self._by_key.clear()

    def remove(self, target: Any) -> None:
        with self._lock:
            self._subscribers = [(k, t) for k, t in self._subscribers if t is not target]
            self._by_key.clear()

    def subscribers(self, key: str) -> list[Any]:
        with self._lock:
            found = self._by_key.get(key)
            if found is None:
                found = self._by_key[key] = [t for k, t in self._subscribers if intersects(k, key)]
            return found


class _Declared:
    """A subscription of a :class:`LocalBus`: its Zenoh subscriber (other processes) and its place in the hub."""

    def __init__(self, hub: LocalHub, target: Any, remote: zenoh.Subscriber):
        self.hub, self.target, self.remote = hub, target, remote

    def undeclare(self) -> None:
        self.hub.remove(self.target)
        self.remote.undeclare()


class LocalBus(Bus):
    """A service's bus in a process shared with others (module docstring). ``instance``: the service's, for the
    access rules; ``options.role`` its role."""

    _destination = zenoh.Locality.REMOTE

    def __init__(self, options: BusOptions, *, session: zenoh.Session, hub: LocalHub, instance: int):
        super().__init__(options, session=session)
        self.hub, self.instance = hub, instance
        self.local = 0  # messages handed over in the process (by reference, or as bytes to a byte subscriber)
        self.refused: collections.Counter[str] = collections.Counter()  # keys its role may not publish on
        self._may: dict[str, bool] = {}
        self._targets: list[Any] = []  # its subscribers in the hub, withdrawn when it closes

    def may_put(self, key: str) -> bool:
        """Whether this service's role may publish on ``key`` (the service graph); counted and logged if not."""
        allowed = self._may.get(key)
        if allowed is None:
            allowed = self._may[key] = graph.allowed(self.options.role, self.instance, "put", key, self.hub.run)
        if not allowed:
            if not self.refused[key]:
                log.warning("%s/%d may not publish on %s (ebrl.graph): refused; further ones only counted",
                            self.options.role, self.instance, key)
            self.refused[key] += 1
        return allowed

    def _outgoing(self, key: str, msg: Any, express: bool) -> Outgoing:
        if not self.may_put(key):
            return key, None, express, None
        wants_bytes = any(not t.by_reference for t in self.hub.subscribers(key))
        if wants_bytes or self._publisher(key, express).matching_status.matching:
            return key, messages.encode_message(msg), express, msg
        return key, None, express, msg

    def put_bytes_blocking(self, key: str, payload: bytes) -> None:
        if self.may_put(key):
            super().put_bytes_blocking(key, payload)

    async def put_bytes(self, key: str, payload: bytes, *, express: bool = False) -> None:
        if self.may_put(key):
            await super().put_bytes(key, payload, express=express)

    def _put(self, key: str, payload: bytes | None, express: bool, msg: Any = None) -> None:
        for target in self.hub.subscribers(key):
            if msg is not None and target.by_reference:
                target.offer_message(key, msg)
            elif payload is not None:
                target.offer(key, payload)
            else:
                continue
            self.local += 1
        super()._put(key, payload, express, msg)  # to other processes, where one subscribes

    def _feed(self, key: str, callback: Callable[[str, Any], None], subscription: Subscription | None = None
              ) -> _Declared:
        target = subscription if subscription is not None and subscription.by_reference else _Bytes(callback)
        self.hub.add(key, target)
        self._targets.append(target)
        return _Declared(self.hub, target, super()._feed(key, callback))

    def _close_now(self) -> None:
        for target in self._targets:
            self.hub.remove(target)
        super()._close_now()
