"""Zenoh bus: session and asyncio bridge, codec, key builders, liveliness."""

from ebrl.bus import keys
from ebrl.bus.session import Bus, BusOptions, Subscription, zenoh_config

__all__ = ["Bus", "BusOptions", "Subscription", "keys", "zenoh_config"]
