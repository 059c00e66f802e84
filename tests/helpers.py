"""Test helpers: free loopback ports, a bus on loopback, a connected pair of buses, waiting for conditions."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import time

from ebrl.bus import Bus, BusOptions, MemoryBus, MemoryNetwork


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


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


ROOT = __import__("pathlib").Path(__file__).resolve().parent.parent


def ebrl_up(out_dir, config: str, *overrides: str, port: int | None = None):
    """Start a real `ebrl up` on a free loopback port; return (Popen with text stdout, port)."""
    import json
    import subprocess
    import sys

    port = port or free_port()
    cmd = [sys.executable, "-m", "ebrl.cli", "up", str(ROOT / config), "--set", f"run.output_dir={json.dumps(str(out_dir))}",
           "--set", f'bus.listen=["tcp/127.0.0.1:{port}"]', "--set", "run.stats_interval=0.5"]
    for item in overrides:
        cmd += ["--set", item]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    return proc, port


def run_collecting_stats(out_dir, config: str, *overrides: str, run: str, timeout: float = 180):
    """Run `ebrl up` to the end while collecting every stats report; return (returncode, output, stats)
    with stats as {"<service>/<instance>": [metrics, ...]} in arrival order."""
    import msgpack
    import zenoh

    proc, port = ebrl_up(out_dir, config, f"run.name={run}", *overrides)
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    seen: dict[str, list[dict]] = {}

    def on_sample(sample) -> None:
        key = str(sample.key_expr).split("/", 3)[3]
        if not key.startswith(("spans/", "events/")):
            seen.setdefault(key, []).append(msgpack.unpackb(sample.payload.to_bytes())["metrics"])

    with zenoh.open(conf) as session:
        session.declare_subscriber(f"ebrl/stats/{run}/**", on_sample)
        try:
            out, _ = proc.communicate(timeout=timeout)
        except Exception:
            proc.kill()
            raise
    return proc.returncode, out, seen
