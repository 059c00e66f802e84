"""The in-memory bus: Zenoh's key matching, back-pressure, liveliness on close and crash, queries, threads.

Behaviour it shares with the Zenoh bus is tested over both in test_bus.py and test_weights.py."""

import asyncio
import threading
import time

import pytest
import zenoh

from ebrl.bus import sender, session, subscription
from ebrl.bus.memory import MemoryBus, MemoryNetwork
from ebrl.messages import Event
from helpers import until


def event(seq: int) -> Event:
    return Event(time=float(seq), service="s", instance=0, kind="k", text="")


def test_keys_match_by_zenoh_rules_and_a_bus_hears_itself():
    async def scenario():
        bus = MemoryBus(MemoryNetwork())
        deep = bus.subscribe("test/**", Event)
        one = bus.subscribe("test/*", Event)
        hidden = bus.subscribe("test/@admin", Event)
        for key in ("test/a", "test/a/b", "test/@admin", "other/a"):
            await bus.put(key, event(0), express=True)
        await bus.flush()
        assert [key for key, _ in deep.drain()] == ["test/a", "test/a/b"]  # no wildcard matches an @ chunk
        assert [key for key, _ in one.drain()] == ["test/a"]
        assert [key for key, _ in hidden.drain()] == ["test/@admin"]
        with pytest.raises(zenoh.ZError):
            bus.subscribe("test//a", Event)
        await bus.close()

    asyncio.run(scenario())


def test_a_full_block_subscription_holds_the_publisher_back_and_loses_nothing(monkeypatch):
    monkeypatch.setattr(sender, "SENDER_QUEUE", 4)

    async def scenario():
        network = MemoryNetwork()
        publisher, consumer = MemoryBus(network), MemoryBus(network)
        sub = consumer.subscribe("test/block", Event, policy="block", capacity=1)

        async def publish() -> None:
            for seq in range(10):
                await publisher.put("test/block", event(seq))

        task = asyncio.create_task(publish())
        # 1 queued at the consumer, 1 held by the publisher's sender, 4 in its sender queue: the rest must wait.
        await until(lambda: len(sub) == 1 and publisher.sender.queue.full(), 10, "the publisher to fill up")
        assert not task.done() and sub.received == 1
        got = []
        while len(got) < 10:
            _, msg = await asyncio.wait_for(sub.next(), 10)
            got.append(int(msg.time))
        await asyncio.wait_for(task, 10)
        assert got == list(range(10)) and sub.dropped == 0
        await publisher.close()
        await consumer.close()

    asyncio.run(scenario())


def test_a_stalled_consumer_costs_a_counted_drop_after_the_block_limit(monkeypatch):
    monkeypatch.setattr(subscription, "BLOCK_LIMIT_S", 0.1)

    async def scenario():
        bus = MemoryBus(MemoryNetwork())
        stalled = bus.subscribe("test/block", Event, policy="block", capacity=1)
        latest = bus.subscribe("test/block", Event, policy="latest", capacity=1)
        for seq in range(3):
            await bus.put("test/block", event(seq))
        await bus.flush(timeout=10)
        assert (stalled.received, stalled.dropped) == (1, 2) and [int(m.time) for _, m in stalled.drain()] == [0]
        assert (latest.dropped, [int(m.time) for _, m in latest.drain()]) == (2, [2])
        await bus.close()

    asyncio.run(scenario())


def test_put_nowait_from_other_threads_arrives_in_order():
    async def scenario():
        bus = MemoryBus(MemoryNetwork())
        wake = asyncio.Event()
        sub = bus.subscribe("test/spans/*", Event, capacity=1000, notify=wake)

        def worker(lane: int) -> None:
            for seq in range(200):
                assert bus.put_nowait(f"test/spans/{lane}", event(seq))

        threads = [threading.Thread(target=worker, args=(lane,)) for lane in range(2)]
        for thread in threads:
            thread.start()
        await asyncio.wait_for(wake.wait(), 10)  # the loop is told, though the put came from elsewhere
        for thread in threads:
            await asyncio.get_running_loop().run_in_executor(None, thread.join)
        await until(lambda: sub.received == 400, 10, "every sample")
        by_lane: dict[str, list[int]] = {}
        for key, msg in sub.drain():
            by_lane.setdefault(key, []).append(int(msg.time))
        assert by_lane == {"test/spans/0": list(range(200)), "test/spans/1": list(range(200))}
        with pytest.raises(RuntimeError):  # it blocks: never on the event loop
            bus.put_bytes_blocking("test/spans/0", b"")
        await bus.close()

    asyncio.run(scenario())


def test_watchers_see_existing_tokens_first_and_tokens_go_on_close_and_on_crash():
    async def scenario():
        network = MemoryNetwork()
        early, watcher = MemoryBus(network), MemoryBus(network)
        early.declare_token("test/live/early")
        changes = []
        watcher.watch_liveliness("test/live/*", lambda key, alive: changes.append((key, alive)))
        late, dying = MemoryBus(network), MemoryBus(network)
        late.declare_token("test/live/late")
        dying.declare_token("test/live/dying")
        await until(lambda: len(changes) == 3, 5, "three tokens")
        assert changes == [("test/live/early", True), ("test/live/late", True), ("test/live/dying", True)]
        await late.close()
        dying.crash()
        await until(lambda: len(changes) == 5, 5, "two tokens to go")
        assert changes[3:] == [("test/live/late", False), ("test/live/dying", False)]
        for bus in (early, watcher):
            await bus.close()

    asyncio.run(scenario())


def test_a_crash_loses_what_was_not_sent_and_leaves_no_answerer():
    async def scenario():
        network = MemoryNetwork()
        doomed, consumer = MemoryBus(network), MemoryBus(network)
        sub = consumer.subscribe("test/data", Event, policy="block", capacity=1)

        async def answer(request: bytes) -> bytes:
            return b"here"

        doomed.declare_queryable("test/who", answer)
        assert await consumer.get("test/who", timeout=5) == [("test/who", b"here")]
        for seq in range(5):
            await doomed.put("test/data", event(seq))
        await until(lambda: len(sub) == 1, 5, "the first sample")
        doomed.crash()  # its sender holds at most one more sample, waiting for room
        got = [int(m.time) for _, m in sub.drain()]
        await until(lambda: not doomed.sender.thread.is_alive(), 10, "the dead bus's sender to stop")
        got += [int(m.time) for _, m in sub.drain()]
        assert got in ([0], [0, 1])
        assert await consumer.get("test/who", timeout=5) == []
        await consumer.close()

    asyncio.run(scenario())


def test_queries_no_answerer_at_once_many_replies_from_a_thread_and_a_timeout():
    async def scenario():
        network = MemoryNetwork()
        asker, server = MemoryBus(network), MemoryBus(network)
        started = time.monotonic()
        assert await asker.get("test/q/**", timeout=30) == []
        assert time.monotonic() - started < 5  # nobody to wait for: no timeout

        def on_query(query: session.Query) -> None:  # answered later, from a thread, like weights parts
            def reply() -> None:
                for index in range(3):
                    query.reply("test/q/parts", bytes([index]))
                with pytest.raises(ValueError):
                    query.reply("test/elsewhere", b"")  # a reply must match the query
                query.finish()

            threading.Thread(target=reply).start()

        server.declare_queryable_raw("test/q/parts", on_query)

        async def slow(request: bytes) -> bytes:
            await asyncio.sleep(60)
            return b"too late"

        server.declare_queryable("test/q/slow", slow)
        started = time.monotonic()
        replies = await asker.get("test/q/**", payload=b"?", timeout=0.5)
        assert replies == [("test/q/parts", b"\x00"), ("test/q/parts", b"\x01"), ("test/q/parts", b"\x02")]
        assert time.monotonic() - started < 30
        for bus in (asker, server):
            await bus.close()

    asyncio.run(scenario())
