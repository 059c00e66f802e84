"""Test helpers: free loopback ports, a bus on loopback, waiting for conditions."""

from __future__ import annotations

import asyncio
import socket
import time

from ebrl.bus import Bus, BusOptions


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def loopback_bus(port: int, *, listen: bool = True) -> Bus:
    """A bus peer on loopback: listening on ``port`` (the first peer) or connecting to it."""
    if listen:
        return Bus(BusOptions(listen=[f"tcp/127.0.0.1:{port}"]))
    return Bus(BusOptions(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]))


async def until(predicate, timeout: float = 10.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        await asyncio.sleep(0.02)
