"""EBRL: asynchronous embodied reinforcement learning over a Zenoh bus.

From Python: ``ebrl.train("quickstart", run={"iterations": 20})`` runs a config as ``ebrl up`` does and returns
the run (``ebrl.api``); ``for report in ebrl.watch(run_dir)`` follows a run's stats (``ebrl.stats.stream``); a
trained policy loads with ``ebrl.load_policy(path)`` (``ebrl.policies.portable``); the programming API of the
allocator is here too (``from ebrl import ResourcePool, EmbodiPlacement, profile``). Each is loaded on first
use, so ``import ebrl`` stays light for services that do not need it.
"""

__version__ = "0.2.0"

_LAZY = {
    "train": "ebrl.api",
    "TrainedRun": "ebrl.api",
    "RunNotStarted": "ebrl.api",
    "watch": ("ebrl.stats", "stream"),
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

        module, attribute = _LAZY[name] if isinstance(_LAZY[name], tuple) else (_LAZY[name], name)
        return getattr(importlib.import_module(module), attribute)
    raise AttributeError(f"module 'ebrl' has no attribute {name!r}")
