"""EBRL: asynchronous embodied reinforcement learning over a Zenoh bus.

A trained policy loads from here (``ebrl.load_policy(path)``, see ``ebrl.policies.portable``), and the
programming API of the allocator is importable from here (``from ebrl import ResourcePool, EmbodiPlacement,
profile``); each is loaded on first use, so ``import ebrl`` stays light for services that do not need it.
"""

__version__ = "0.1.0"

_LAZY = {
    "ResourcePool": "ebrl.resources.pool",
    "EmbodiPlacement": "ebrl.alloc.placement",
    "StageRates": "ebrl.alloc.placement",
    "profile": "ebrl.alloc.profile",
    "load_policy": "ebrl.policies.portable",
    "PortablePolicy": "ebrl.policies.portable",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'ebrl' has no attribute {name!r}")
