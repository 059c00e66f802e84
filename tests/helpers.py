"""Test helpers: a bus on loopback, a connected pair of buses, waiting for conditions, and real `ebrl up` runs
(from ebrl.testing)."""

from __future__ import annotations

import asyncio
import contextlib
import time
from pathlib import Path
from types import SimpleNamespace

from ebrl.bus.memory import MemoryBus, MemoryNetwork
from ebrl.bus.session import Bus, BusOptions
from ebrl.testing import Run, StatsWatcher, free_port

__all__ = ["BUS_KINDS", "Counts", "ROOT", "Run", "StatsWatcher", "bus_pair", "free_port", "loopback_bus",
           "run_collecting_stats", "until", "up"]

ROOT = Path(__file__).resolve().parent.parent


class Counts(SimpleNamespace):
    """A learner's telemetry that keeps what was counted (``counts``) and drops spans."""

    def __init__(self):
        super().__init__(counts={})

    def count(self, name, n=1):
        self.counts[name] = self.counts.get(name, 0) + n

    def publish_span(self, *args):
        pass


def loopback_bus(port: int, *, listen: bool = True) -> Bus:
    """A bus peer on loopback: listening on ``port`` (the first peer) or connecting to it."""
    if listen:
        return Bus(BusOptions(listen=[f"tcp/127.0.0.1:{port}"]))
    return Bus(BusOptions(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]))


BUS_KINDS = ("zenoh", "memory")


class BusPair:
    """Two connected buses on one loop: ``sender`` and ``receiver`` (either can do both)."""

    def __init__(self, sender, receiver):
        self.sender, self.receiver = sender, receiver
        self._seen: set[str] = set()
        self._tokens = 0
        sender.watch_liveliness("test/settled/*", lambda key, alive: self._seen.add(key) if alive else None)

    async def settled(self) -> None:
        """Return once the sender knows every declaration the receiver made so far: over Zenoh they travel
        in order on one link, so the receiver's newest liveliness token comes after them."""
        self._tokens += 1
        key = f"test/settled/{self._tokens}"
        self.receiver.declare_token(key)
        await until(lambda: key in self._seen, 10, "the receiver's declarations")


@contextlib.asynccontextmanager
async def bus_pair(kind: str, receiver_options: BusOptions | None = None):
    """A :class:`BusPair`: two Zenoh peers on loopback, or two ``MemoryBus`` on one network; closed after."""
    if kind == "zenoh":
        port = free_port()
        sender = loopback_bus(port)
        options = receiver_options or BusOptions()
        receiver = Bus(BusOptions(**{**vars(options), "listen": ["tcp/127.0.0.1:0"],
                                     "connect": [f"tcp/127.0.0.1:{port}"]}))
    else:
        network = MemoryNetwork()
        sender, receiver = MemoryBus(network), MemoryBus(network, receiver_options)
    try:
        yield BusPair(sender, receiver)
    finally:
        await receiver.close()
        await sender.close()


async def until(predicate, timeout: float = 10.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        await asyncio.sleep(0.02)


# Each service in a process of its own, for the tests of what one role's own credential can do: on a CPU host
# "auto" puts sim and gen in one process, whose one identity may send what both may (that identity's rights are
# tests/test_shared_process.py's), so a simulator's credential of its own exists only with processes apart.
OWN_PROCESSES = "run.processes=[]"


def up(out_dir, config: str, *overrides: str, name: str, args=(), port: int | None = None) -> Run:
    """A real `ebrl up` of ``config`` (relative to the repository) as run ``name``, writing into ``out_dir``."""
    return Run(ROOT / config, *overrides, name=name, out_dir=out_dir, args=args, port=port, cwd=ROOT)


def run_collecting_stats(out_dir, config: str, *overrides: str, run: str, timeout: float = 300):
    """Run `ebrl up` to the end while collecting every stats report; return (returncode, output, stats)
    with stats as {"<service>/<instance>": [metrics, ...]} in arrival order."""
    with up(out_dir, config, *overrides, name=run) as started, StatsWatcher(started) as stats:
        code = started.wait(timeout)
    return code, started.output, stats.by_source()


def store_profile(path: Path, cfg, gen_batches: tuple[int, ...], train_batch: int) -> None:
    """A stage profile at ``path`` for this machine and ``cfg`` (its "auto" settings settled), as the launcher
    would find one: the simulator scales with cores, the small models do not and look cheap, so Algorithm 1
    predicts that every stage shares every core."""
    from ebrl.alloc.algorithm import Profiles
    from ebrl.alloc.profile import fingerprint, save
    from ebrl.resources.pool import ResourcePool

    pool = ResourcePool(gpu_pool="none")
    n = len(pool.cores)
    save(path, Profiles(sim={(1, e, e): 1000.0 * 1.6 ** (e - 1) for e in range(1, n + 1)},
                        gen={(c, b): 50_000.0 for c in range(1, n + 1) for b in gen_batches},
                        train={(c, train_batch): 50_000.0 for c in range(1, n + 1)}), fingerprint(pool, cfg))

