"""Zenoh bus: session and asyncio bridge, codec, key builders, liveliness.

``Bus`` and friends load on first use, so that ``ebrl.messages`` (which the session
module needs) can import ``ebrl.bus.codec`` and ``ebrl.bus.keys`` without a cycle."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ebrl.bus import keys

if TYPE_CHECKING:
    from ebrl.bus.session import Bus, BusOptions, Subscription, zenoh_config

__all__ = ["Bus", "BusOptions", "Subscription", "keys", "zenoh_config"]


def __getattr__(name: str) -> Any:
    if name in ("Bus", "BusOptions", "Subscription", "zenoh_config"):
        from ebrl.bus import session

        return getattr(session, name)
    raise AttributeError(f"module 'ebrl.bus' has no attribute {name!r}")
