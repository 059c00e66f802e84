"""log service: the bus -> tracking sinks (TensorBoard, CSV, W&B). Subscribes to ``ebrl/stats/<run>/**``.

Why a service of its own (``ebrl/tracking.py`` says more): the sinks see only what is on the bus, in a process
that nothing waits for. Its inbox keeps the newest ``INBOX`` samples and drops the oldest when it falls behind
(``log/dropped``); the sinks write on a thread of their own, never on the event loop; the launcher treats it
as optional (it dies: restarted, then the run goes on without it).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import time

from ebrl import tracking
from ebrl.messages import decode_stats_sample
from ebrl.service import Service, service_main

WRITE_S = 0.5  # the inbox is written out this often
INBOX = 20_000
DRAIN_QUIET_S = 0.5  # stopping: the others' last reports are still coming; write until the bus is quiet this long
DRAIN_MAX_S = 3.0  # ... or this long at most


class LogService(Service):
    role = "log"

    async def setup(self) -> None:
        self.pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="log-sinks")
        loop = asyncio.get_running_loop()
        self.tracker = await loop.run_in_executor(self.pool, tracking.open_tracker, self.cfg, self.run_dir)
        names = ", ".join(s.name for s in self.tracker.sinks) or "none"
        self.log.info("sinks: %s (in %s)", names, self.run_dir)
        self.inbox = self.bus.subscribe(self.keys.sub("stats"), decode_stats_sample, policy="latest",
                                        capacity=INBOX)

    async def run(self) -> None:
        while True:
            await asyncio.sleep(WRITE_S)
            await self.write_inbox()

    async def write_inbox(self) -> int:
        items = self.inbox.drain()
        if items:
            await asyncio.get_running_loop().run_in_executor(self.pool, self.tracker.on_messages,
                                                             [msg for _, msg in items])
        return len(items)

    def metrics(self) -> dict[str, float]:
        return {**self.tracker.metrics(), "log/dropped": float(self.inbox.dropped)}

    async def teardown(self) -> None:
        deadline, quiet_since = time.monotonic() + DRAIN_MAX_S, time.monotonic()
        while time.monotonic() < deadline and time.monotonic() - quiet_since < DRAIN_QUIET_S:
            if await self.write_inbox():
                quiet_since = time.monotonic()
            await asyncio.sleep(0.1)
        await asyncio.get_running_loop().run_in_executor(self.pool, self.tracker.close)
        self.pool.shutdown(wait=True)


def main() -> None:
    service_main(LogService)


if __name__ == "__main__":
    main()
