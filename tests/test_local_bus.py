"""Services of one process hand each other messages by reference (ebrl.bus.local), over a real Zenoh session.

What a sender hands over must not change afterwards: each message EBRL's services publish is made for it. The
audit, for the messages that go by reference between a simulator, generation and training:

* ``Observation`` (ebrl.sched.group): a process group's observations are a new array per chunk
  (``obs.copy()`` in ``GroupLoop.step``); a vectorized group's are copied out of its worker's buffer per chunk
  (``VectorWorker.chunk``), or made by ``to_host`` per chunk where it steps in the process (``InlineVectorWorker``);
* ``ActionChunk`` (ebrl.services.gen): slices of the forward's output, made per batch;
* ``TrajectorySegment`` / ``SegmentBatch`` (ebrl.sched.segments, ebrl.envs.vector): arrays stacked per segment;
* stats, spans, events, episodes: built per report.
"""

from __future__ import annotations

import asyncio
import contextlib

import numpy as np
import pytest

from ebrl import messages
from ebrl import keys
from ebrl.bus.local import LocalBus, LocalHub
from ebrl.bus.session import Bus, BusOptions, zenoh_config
from ebrl.messages import ActionChunk, Observation, StatsReport
from ebrl.service import bus_metrics
from helpers import free_port, until

import zenoh

RUN = "r"


def observation(seq: int = 0, n: int = 4) -> Observation:
    return Observation(group=0, seq=seq, env_ids=np.arange(n, dtype=np.int64),
                       obs=np.random.default_rng(seq).standard_normal((n, 3)).astype(np.float32), sent_at=1.0)


@contextlib.asynccontextmanager
async def process(*services: tuple[str, int], remote: bool = False):
    """The buses of one process's services (``LocalBus`` on one Zenoh session and hub), and with ``remote`` a bus
    in another process's session connected to it (``None`` without)."""
    port = free_port()
    session = zenoh.open(zenoh_config(BusOptions(listen=[f"tcp/127.0.0.1:{port}"])))
    hub = LocalHub(RUN)
    buses = [LocalBus(BusOptions(role=role), session=session, hub=hub, instance=n) for role, n in services]
    other = Bus(BusOptions(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"])) if remote else None
    try:
        yield buses, other
    finally:
        for bus in buses + ([other] if other else []):
            await bus.close()
        session.close()


@pytest.fixture
def encodes(monkeypatch):
    """How many messages were encoded (a copy into a payload)."""
    count = [0]
    real = messages.encode_message

    def counting(msg):
        count[0] += 1
        return real(msg)

    monkeypatch.setattr(messages, "encode_message", counting)
    return count


def test_a_message_reaches_a_service_of_the_same_process_by_reference_never_encoded(encodes):
    async def main():
        async with process(("sim", 0), ("gen", 0)) as ((sim, gen), _):
            sub = gen.subscribe(keys.obs(RUN), Observation)
            sent = observation()
            await sim.put(keys.obs(RUN, 0), sent)
            await until(lambda: len(sub) == 1, 10, "the observation")
            (key, got), = sub.drain()
            assert key == keys.obs(RUN, 0) and got is not sent
            assert np.shares_memory(got.obs, sent.obs) and np.shares_memory(got.env_ids, sent.env_ids)  # no copy
            assert not got.obs.flags.writeable and sent.obs.flags.writeable  # neither changes the other's
            assert encodes[0] == 0, "encoded though nobody outside the process subscribes"
            assert sim.local == 1 and bus_metrics(sim)["bus/local"] == 1.0

    asyncio.run(main())


def test_another_process_gets_its_own_copy_and_the_process_gets_each_message_once(encodes):
    async def main():
        async with process(("sim", 0), ("gen", 0), remote=True) as ((sim, gen), other):
            here = gen.subscribe(keys.obs(RUN), Observation, capacity=2048)  # every probe below
            there = other.subscribe(keys.obs(RUN), Observation, capacity=2048)
            probe = 0
            while not len(there):  # until the other process's subscription has reached the session
                await sim.put(keys.obs(RUN, 0), observation(probe))
                probe += 1
                await asyncio.sleep(0.05)
                assert probe < 1200, "the other process never received an observation"  # 60 s: a hang, not a window
            sent = observation(1000)
            await sim.put(keys.obs(RUN, 0), sent)
            await until(lambda: any(m.seq == 1000 for _, m in list(there._items)), 60, "the copy")
            await sim.flush()
            mine = [m for _, m in here.drain()]
            assert [m.seq for m in mine] == list(range(probe)) + [1000]  # each once: Zenoh's own local delivery off
            copy = next(m for _, m in there.drain() if m.seq == 1000)
            assert np.array_equal(copy.obs, sent.obs) and not np.shares_memory(copy.obs, sent.obs)
            assert np.shares_memory(mine[-1].obs, sent.obs)
            assert encodes[0] >= 1

    asyncio.run(main())


def test_a_bad_message_in_the_process_is_counted_and_dropped_as_from_the_bus():
    async def main():
        async with process(("sim", 0), ("gen", 0)) as ((sim, gen), _):
            acts = sim.subscribe(keys.act(RUN, 0), ActionChunk)
            small = gen.subscribe(keys.obs(RUN), Observation, max_bytes=1000)
            nan = ActionChunk(group=0, seq=0, policy_version=0, actions=np.full((2, 1, 1), np.nan, np.float32),
                              logprobs=np.zeros(2, np.float32), values=np.zeros(2, np.float32),
                              latents=np.zeros((2, 0), np.float32))
            await gen.put(keys.act(RUN, 0), nan)
            await sim.put(keys.obs(RUN, 0), observation(n=200))  # 2.4 KB of observations, over the 1000 bound
            await until(lambda: sim.malformed[keys.act(RUN, 0)] == 1 and gen.oversized[keys.obs(RUN, 0)] == 1, 10,
                        "both counted")
            assert not len(acts) and not len(small)

    asyncio.run(main())


def test_a_service_may_not_publish_in_the_process_what_its_role_may_not_send(encodes):
    async def main():
        async with process(("sim", 0), ("gen", 0), ("train", 0), remote=True) as ((sim, gen, train), other):
            local = train.subscribe(keys.traj(RUN), StatsReport)
            remote = other.subscribe(keys.weights(RUN), StatsReport)
            report = StatsReport(run=RUN, service="gen", instance=0, time=1.0, seq=0, metrics={"x": 1.0})
            for _ in range(3):
                await gen.put(keys.traj(RUN, 0), report)  # only the simulator sends segments
                await gen.put(keys.weights(RUN), report)  # only training sends weights
            await gen.flush()
            assert gen.refused == {keys.traj(RUN, 0): 3, keys.weights(RUN): 3}
            assert bus_metrics(gen)["bus/refused"] == 6.0 and gen.local == 0 and encodes[0] == 0
            assert not len(local) and not len(remote)

    asyncio.run(main())


def test_a_byte_subscriber_in_the_process_gets_the_payload():
    async def main():
        async with process(("sim", 0), ("log", 0)) as ((sim, log), _):
            got: list[bytes] = []
            log.subscribe_raw(keys.stats_all(RUN), lambda key, payload: got.append(payload))
            typed = log.subscribe(keys.stats_all(RUN), messages.decode_stats_sample)
            report = StatsReport(run=RUN, service="sim", instance=0, time=1.0, seq=3, metrics={"sim/env_steps": 5.0})
            await sim.put(keys.stats(RUN, "sim", 0), report)
            await until(lambda: got and len(typed), 10, "the report")
            assert messages.decode_message(StatsReport, got[0]) == report
            (_, same), = typed.drain()
            assert same == report and same is not report

    asyncio.run(main())
