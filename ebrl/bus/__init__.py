"""The bus: session and asyncio bridge, in-memory bus for tests, codec, key builders, liveliness.

``Bus`` (Zenoh) and ``MemoryBus`` (one process, for tests) share one API, :class:`BusBase`. They load on
first use, so that ``ebrl.messages`` (which the session module needs) can import ``ebrl.bus.codec`` and
``ebrl.bus.keys`` without a cycle."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ebrl.bus import keys

if TYPE_CHECKING:
    from ebrl.bus.memory import MemoryBus, MemoryNetwork
    from ebrl.bus.session import Bus, BusBase, BusOptions, Query, Subscription, zenoh_config

__all__ = ["Bus", "BusBase", "BusOptions", "MemoryBus", "MemoryNetwork", "Query", "Subscription", "keys",
           "zenoh_config"]
_SESSION = ("Bus", "BusBase", "BusOptions", "Query", "Subscription", "zenoh_config")
_MEMORY = ("MemoryBus", "MemoryNetwork")


def __getattr__(name: str) -> Any:
    if name in _SESSION:
        from ebrl.bus import session

        return getattr(session, name)
    if name in _MEMORY:
        from ebrl.bus import memory

        return getattr(memory, name)
    raise AttributeError(f"module 'ebrl.bus' has no attribute {name!r}")
