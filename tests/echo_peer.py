"""A second process for bus tests: echoes every Observation on test/ping/* to test/pong/<group>."""

import asyncio
import sys

from ebrl import keys
from ebrl.bus.session import Bus, BusOptions
from ebrl.messages import Observation


async def main(port: int) -> None:
    bus = Bus(BusOptions(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]))
    sub = bus.subscribe("test/ping/*", Observation, capacity=8)

    async def answer(request: bytes) -> bytes:
        return b"pong:" + request

    bus.declare_queryable("test/query", answer)
    bus.declare_token(keys.live("test", "echo", 0))  # last: the token says "ready"
    async for _, msg in sub:
        if msg.seq < 0:
            break
        await bus.put(f"test/pong/{msg.group}", msg)
    await bus.close()


if __name__ == "__main__":
    asyncio.run(main(int(sys.argv[1])))
