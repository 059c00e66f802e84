"""Bus: a round trip between two processes, liveliness, request-reply, queue policies, malformed input.

The behaviour tests run over both buses with the same API: two Zenoh peers on loopback, and two MemoryBus
on one network (``kind``)."""

import asyncio
import os
import pathlib
import signal
import subprocess
import sys

import numpy as np
import pytest

from ebrl import keys
from ebrl.messages import Event, Observation, StatsReport
from ebrl.bus.session import BusOptions
from helpers import BUS_KINDS, bus_pair, free_port, loopback_bus, until

HERE = pathlib.Path(__file__).resolve().parent


@pytest.fixture(params=BUS_KINDS)
def kind(request):
    return request.param


def observation(seq: int, group: int = 0, n: int = 4) -> Observation:
    return Observation(group=group, seq=seq, env_ids=np.arange(n, dtype=np.int64),
                       obs=np.full((n, 3, 32, 32), seq, dtype=np.float32), sent_at=0.0)


@pytest.fixture
def echo_process():
    port = free_port()
    env = dict(os.environ, PYTHONPATH=f"{HERE.parent}{os.pathsep}{HERE}")
    procs = []

    def start():
        proc = subprocess.Popen([sys.executable, str(HERE / "echo_peer.py"), str(port)], env=env)
        procs.append(proc)
        return proc

    yield port, start
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
        proc.wait(5)


def test_round_trip_between_two_processes_with_liveliness_and_query(echo_process):
    port, start = echo_process

    async def scenario():
        bus = loopback_bus(port)
        live = {}
        bus.watch_liveliness(keys.live("test", "echo", "*"), lambda k, alive: live.__setitem__(k, alive))
        pongs = bus.subscribe("test/pong/*", Observation, capacity=64)
        proc = start()
        await until(lambda: live.get(keys.live("test", "echo", 0)), 30, "the echo peer's liveliness token")
        replies = await bus.get("test/query", payload=b"hi", timeout=5.0)
        assert replies == [("test/query", b"pong:hi")]
        for seq in range(20):
            await bus.put(f"test/ping/{seq % 3}", observation(seq, group=seq % 3))
        got = [await asyncio.wait_for(pongs.next(), 10) for _ in range(20)]
        assert sorted(m.seq for _, m in got) == list(range(20))
        key, msg = got[-1]
        assert key == f"test/pong/{msg.group}"
        np.testing.assert_array_equal(msg.obs, np.full((4, 3, 32, 32), msg.seq, np.float32))
        proc.send_signal(signal.SIGKILL)
        await until(lambda: live.get(keys.live("test", "echo", 0)) is False, 10, "the token to vanish")
        assert await bus.get("test/query", timeout=0.5) == []
        await bus.close()

    asyncio.run(scenario())


def test_a_round_trip_with_liveliness_and_query_in_one_process(kind):
    async def scenario():
        async with bus_pair(kind) as pair:
            bus, echo = pair.sender, pair.receiver
            live = {}
            bus.watch_liveliness(keys.live("test", "echo", "*"), lambda k, alive: live.__setitem__(k, alive))
            pings = echo.subscribe("test/ping/*", Observation, capacity=8)
            pongs = bus.subscribe("test/pong/*", Observation, capacity=64)

            async def answer(request: bytes) -> bytes:
                return b"pong:" + request

            async def echo_pings() -> None:
                async for _, msg in pings:
                    await echo.put(f"test/pong/{msg.group}", msg)

            echo.declare_queryable("test/query", answer)
            echo.declare_token(keys.live("test", "echo", 0))
            task = asyncio.create_task(echo_pings())
            await until(lambda: live.get(keys.live("test", "echo", 0)), 10, "the echo's liveliness token")
            await pair.settled()
            assert await bus.get("test/query", payload=b"hi", timeout=5.0) == [("test/query", b"pong:hi")]
            for seq in range(20):
                await bus.put(f"test/ping/{seq % 3}", observation(seq, group=seq % 3))
            got = [await asyncio.wait_for(pongs.next(), 10) for _ in range(20)]
            assert sorted(m.seq for _, m in got) == list(range(20))
            assert all(key == f"test/pong/{msg.group}" for key, msg in got)
            task.cancel()
            await echo.close()
            await until(lambda: live.get(keys.live("test", "echo", 0)) is False, 10, "the token to vanish")
            assert await bus.get("test/query", timeout=0.5) == []

    asyncio.run(scenario())


def test_malformed_messages_are_counted_and_dropped(kind):
    async def scenario():
        async with bus_pair(kind) as pair:
            bus, receiver = pair.sender, pair.receiver
            sub = receiver.subscribe("test/spans/*", Event, capacity=16)
            await pair.settled()
            good = Event(time=1.0, service="gen", instance=0, kind="forward", text="a forward pass")
            await bus.put_bytes("test/spans/a", b"\xc1garbage")
            await bus.put("test/spans/a", StatsReport(run="r", service="s", instance=0, time=0.0, seq=0, metrics={}))
            await bus.put_bytes("test/spans/b", os.urandom(64))
            await bus.put("test/spans/a", good)
            key, msg = await asyncio.wait_for(sub.next(), 5)
            assert (key, msg) == ("test/spans/a", good)
            assert receiver.malformed["test/spans/a"] == 2 and receiver.malformed["test/spans/b"] == 1
            assert not bus.malformed  # counted where it is received

    asyncio.run(scenario())


def test_latest_policy_keeps_the_newest_and_block_policy_loses_nothing(kind):
    async def scenario():
        async with bus_pair(kind) as pair:
            bus = pair.sender
            latest = pair.receiver.subscribe("test/latest", Event, policy="latest", capacity=2)
            blocking = pair.receiver.subscribe("test/block", Observation, policy="block", capacity=2)
            await pair.settled()
            for i in range(10):
                await bus.put("test/latest", Event(time=float(i), service="s", instance=0, kind="k", text=""))
            await until(lambda: latest.received >= 2 and latest.dropped + latest.received >= 10, 5, "latest samples")
            assert [m.time for _, m in latest.drain()] == [8.0, 9.0]
            for seq in range(50):
                await bus.put("test/block", observation(seq))
            seen = []
            while len(seen) < 50:
                _, msg = await asyncio.wait_for(blocking.next(), 5)
                seen.append(msg.seq)
                assert len(blocking) <= 2  # never more than its capacity
            assert seen == list(range(50)) and blocking.dropped == 0

    asyncio.run(scenario())


def test_keys_put_the_run_in_every_key():
    assert keys.obs("r1", 3) == "ebrl/data/r1/obs/3"
    assert keys.act("r1", 3) == "ebrl/data/r1/act/3"
    assert keys.traj("r1") == "ebrl/data/r1/traj/*"
    assert keys.weights("r1") == "ebrl/data/r1/weights"
    assert keys.ctl("r1", "gen", 0, "quota") == "ebrl/ctl/r1/gen/0/quota"
    assert keys.stats("r1", "sim", 0) == "ebrl/stats/r1/sim/0"
    assert keys.spans("r1", "sim.g0") == "ebrl/stats/r1/spans/sim.g0"
    assert keys.live("r1", "train", 0) == "ebrl/live/r1/train/0"
    assert keys.stats() == "ebrl/stats/**"
    with pytest.raises(ValueError):
        keys.ctl("r1", "gen", 0, "reboot")
    with pytest.raises(ValueError):
        keys.check_chunk("Bad Name", "run.name")


def test_keys_parse_into_named_fields_for_every_family():
    assert keys.parse(keys.obs("r1", 3)) == keys.Key("data", "r1", kind="obs", group=3)
    assert keys.parse(keys.weights("r1")).kind == "weights" and keys.parse(keys.weights("r1")).group is None
    ctl = keys.parse(keys.ctl("r1", "gen", 0, "quota"))
    assert (ctl.category, ctl.service, ctl.instance, ctl.kind) == ("ctl", "gen", "0", "quota")
    report = keys.parse(keys.stats("r1", "sim", 2))
    assert (report.service, report.instance, report.family) == ("sim", "2", "report")
    span = keys.parse(keys.spans("r1", "sim.g0"))
    assert (span.family, span.lane) == ("spans", "sim.g0")
    assert keys.parse(keys.events("r1", "train")).family == "events"
    assert keys.role_of(keys.live("r1", "train", 0)) == "train"
    assert keys.role_of("not/an/ebrl/key") == ""
    for bad in ("ebrl/data", "other/data/r1/obs/0", "ebrl/nosuch/r1/x/0", "ebrl/live/r1/sim"):
        with pytest.raises(ValueError):
            keys.parse(bad)


def test_a_bus_left_open_does_not_hang_interpreter_exit(tmp_path):
    # zenoh-python's callback threads are non-daemon: before the exit hook, a
    # failure before bus.close() hung the process (and once, a CI run) forever.
    script = tmp_path / "forgets_to_close.py"
    script.write_text(
        "import asyncio, sys\n"
        "from ebrl import keys\n"
        "from ebrl.messages import Observation\n"
        "from helpers import free_port, loopback_bus\n"
        "async def main():\n"
        "    bus = loopback_bus(free_port())\n"
        "    bus.watch_liveliness(keys.live('t', 'x', '*'), lambda k, alive: None)\n"
        "    bus.subscribe('t/x/*', Observation)\n"
        "    await bus.get('t/q', timeout=0.2)\n"
        "    raise SystemExit(3)\n"
        "asyncio.run(main())\n"
    )
    env = dict(os.environ, PYTHONPATH=f"{HERE.parent}{os.pathsep}{HERE}")
    proc = subprocess.run([sys.executable, str(script)], env=env, timeout=60, capture_output=True)
    assert proc.returncode == 3, proc.stderr.decode()


def test_messages_over_the_size_limit_are_dropped_before_decoding(kind):
    async def scenario():
        async with bus_pair(kind, receiver_options=BusOptions(max_message_bytes=4096)) as pair:
            small = pair.receiver
            sub = small.subscribe("test/obs", Observation, capacity=8)
            await pair.settled()
            await pair.sender.put("test/obs", observation(1, n=1))  # 12 KB of pixels
            await pair.sender.put("test/obs", Observation(group=0, seq=2, env_ids=np.zeros(1, np.int64),
                                                          obs=np.zeros((1, 4), np.float32), sent_at=0.0))
            _, msg = await asyncio.wait_for(sub.next(), 10)
            assert msg.seq == 2 and small.oversized["test/obs"] == 1 and small.malformed["test/obs"] == 1

    asyncio.run(scenario())


def test_bulk_payloads_between_processes_of_a_host_go_through_shared_memory(tmp_path):
    """Zenoh puts a payload over 3 KB into shared memory on its own (one reference crosses the router's sockets:
    benchmarks/bus_shm.py measured 6.6x at 64 KB, 11.5x at 1 MB); every session a run opens keeps that on."""
    import json

    from ebrl.bus import auth
    from ebrl.bus.session import BusOptions, zenoh_config

    secret = auth.create(tmp_path / "bus.secret")
    dictionary = auth.write_router_dictionary(secret, tmp_path / "bus.router-0.secret", (("sim", 0),))
    for options in (BusOptions(), BusOptions(mode="client", connect=["tcp/127.0.0.1:7447"], listen=[], role="sim",
                                             identity=auth.instance_line(secret, "sim", 0)),
                    BusOptions(mode="router", secret_file=str(secret), role="launcher", run="r",
                               instances=(("sim", 0),), dictionary_file=str(dictionary), groups=1)):
        shm = json.loads(zenoh_config(options).get_json("transport/shared_memory"))
        assert shm["enabled"] and shm["transport_optimization"]["enabled"], (options.mode, shm)
        assert shm["transport_optimization"]["message_size_threshold"] <= 4096, shm
