"""Service runtime in-process on loopback: liveliness, stats, spans, versioned control, status query, stop."""

import asyncio
import os

from ebrl import config
from ebrl import keys
from ebrl.bus.session import BusOptions
from ebrl.messages import Affinity, SpanBatch, StatsReport, Stop, decode_message
from ebrl.service import Service
from helpers import free_port, loopback_bus, until

WAIT_S = 60.0  # deadline of each wait below: generous, for a loaded machine (a pass takes well under a second)


class Ticker(Service):
    role = "ticker"

    async def run(self) -> None:
        while True:
            with self.span("tick", lane="ticker"):
                self.count("ticker/ticks")
                await asyncio.sleep(0.01)


def test_lifecycle_stats_spans_control_and_stop():
    cfg = config.from_dict({"run": {"name": "svc", "stats_interval": 0.2}})
    port = free_port()

    async def scenario():
        bus = loopback_bus(port)
        live = {}
        bus.watch_liveliness(keys.live_all("svc"), lambda k, a: live.__setitem__(k, a))
        stats = bus.subscribe(keys.stats("svc", "ticker", 0), StatsReport, policy="latest", capacity=4)
        spans = bus.subscribe(keys.spans("svc", "ticker"), SpanBatch, capacity=1000)
        service = Ticker(cfg, 0, BusOptions(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]))
        task = asyncio.create_task(service.main())
        await until(lambda: live.get(keys.live("svc", "ticker", 0)), WAIT_S, "the service token")
        _, report = await asyncio.wait_for(stats.next(), WAIT_S)
        _, batch = await asyncio.wait_for(spans.next(), WAIT_S)
        span = batch.spans()[0]
        assert span.label == "tick" and span.end >= span.start and span.service == "ticker"

        cores = sorted(os.sched_getaffinity(0))
        for version in (1, 1, 0):  # a repeated or older version is ignored
            await bus.put(keys.ctl("svc", "ticker", 0, "affinity"), Affinity(version=version, cores=cores[:1]))
        await until(lambda: service.meter.total("ctl/affinity_ignored") == 2, WAIT_S, "control messages")
        assert service.meter.total("ctl/affinity_applied") == 1
        replies = await bus.get(keys.ctl("svc", "ticker", 0, "status"), timeout=WAIT_S)
        status = decode_message(StatsReport, replies[0][1])
        assert status.metrics["ticker/ticks"] > 0 and status.metrics["ctl/affinity_applied"] == 1

        await bus.put(keys.ctl("svc", "ticker", 0, "stop"), Stop(reason="test"))
        assert await asyncio.wait_for(task, WAIT_S) == 0
        await until(lambda: live.get(keys.live("svc", "ticker", 0)) is False, WAIT_S, "the token to vanish")
        await bus.close()
        os.sched_setaffinity(0, cores)  # the service pinned this (shared) process

    asyncio.run(scenario())
