"""Data validated by meaning, not only by type: what each receiver refuses, and that refusing changes nothing.

A segment with a NaN reward used to turn every weight non-finite; a weights message with a huge version made
generation ignore every real update after it; a forged ``train/9`` report ended a run as finished. Each is
a message that decodes and type-checks: only its meaning gives it away."""

import asyncio
import dataclasses
import time

import numpy as np
import pytest

from ebrl import keys
from ebrl.bus.memory import MemoryBus, MemoryNetwork
from ebrl.messages import (ActionChunk, Affinity, MessageError, Observation, OversizedError, Quota, StatsReport,
                           Stop, TrajectorySegment, Weights, WeightsPart, decode_message, encode_message)
from ebrl.runview import RunView
from ebrl.sched.batching import ObservationQueue
from ebrl.sched.modes import resolve
from ebrl.weights import MAX_JUMP, WeightsLayout, WeightsReceiver, plausible
from ebrl import config
from helpers import ROOT

RUN = "v"


def segment(t: int = 4, k: int = 2, a: int = 3, **changes) -> TrajectorySegment:
    seg = TrajectorySegment(
        group=0, env_id=1, episode=0, obs=np.zeros((t, 5), np.float32), actions=np.zeros((t, k, a), np.float32),
        latents=np.zeros((t, 0), np.float32), logprobs=np.zeros(t, np.float32), values=np.zeros(t, np.float32),
        rewards=np.ones(t, np.float32), steps=np.full(t, k, np.int32), versions=np.zeros(t, np.int64), end="cut",
        last_obs=np.zeros(5, np.float32), episode_returns=[], episode_lengths=[])
    return dataclasses.replace(seg, **changes)


def roundtrip(msg):
    return decode_message(type(msg), encode_message(msg))


def test_a_well_formed_segment_passes():
    seg = roundtrip(segment())
    assert len(seg.obs) == 4 and seg.end == "cut"


@pytest.mark.parametrize("changes, error", [
    ({"rewards": np.array([1, np.nan, 1, 1], np.float32)}, "not finite"),
    ({"values": np.array([0, 0, np.inf, 0], np.float32)}, "not finite"),
    ({"obs": np.full((4, 5), np.nan, np.float32)}, "not finite"),
    ({"logprobs": np.zeros(3, np.float32)}, "differ in length"),
    ({"versions": np.zeros(5, np.int64)}, "differ in length"),
    ({"steps": np.full(4, 3, np.int32)}, "steps"),
    ({"versions": np.array([0, -1, 0, 0], np.int64)}, "versions"),
    ({"last_obs": np.zeros(6, np.float32)}, "last_obs"),
    ({"episode_returns": [float("nan")], "episode_lengths": [3]}, "not finite"),
    ({"episode_returns": [1.0], "episode_lengths": []}, "episode returns"),
    ({"env_id": -3}, "env_id"),
])
def test_a_segment_that_would_poison_training_is_refused(changes, error):
    with pytest.raises(MessageError, match=error):
        roundtrip(segment(**changes))


def test_an_action_chunk_with_a_nan_or_ragged_fields_is_refused():
    good = ActionChunk(group=0, seq=3, policy_version=1, actions=np.zeros((2, 4, 3), np.float32),
                       logprobs=np.zeros(2, np.float32), values=np.zeros(2, np.float32), latents=np.zeros((2, 0), np.float32))
    assert roundtrip(good).seq == 3
    with pytest.raises(MessageError, match="not finite"):
        roundtrip(dataclasses.replace(good, actions=np.full((2, 4, 3), np.nan, np.float32)))
    with pytest.raises(MessageError, match="differ in length"):
        roundtrip(dataclasses.replace(good, values=np.zeros(3, np.float32)))
    with pytest.raises(MessageError, match="policy_version"):
        roundtrip(dataclasses.replace(good, policy_version=-2))
    obs = Observation(group=0, seq=0, env_ids=np.arange(3), obs=np.zeros((2, 4), np.float32), sent_at=0.0)
    with pytest.raises(MessageError, match="env ids"):
        roundtrip(obs)


@pytest.mark.parametrize("msg, error", [
    (Quota(version=1, threads=0), "threads"),
    (Quota(version=1, sm_percent=250.0), "sm_percent"),
    (Quota(version=1, mem_bytes=-1), "mem_bytes"),
    (Quota(version=-1), "version"),
    (Affinity(version=1, cores=[]), "cores"),
    (Affinity(version=1, cores=[0, 0]), "cores"),
    (Affinity(version=1, cores=[-1]), "cores"),
    (Stop(reason="x" * 10_000), "reason"),
])
def test_control_values_are_bounded(msg, error):
    with pytest.raises(MessageError, match=error):
        roundtrip(msg)


def test_each_message_type_has_its_own_size_limit_checked_before_decoding():
    report = StatsReport(run=RUN, service="train", instance=0, time=0.0, seq=0, metrics={})
    assert roundtrip(report).service == "train"
    big = encode_message(dataclasses.replace(report, run="x" * (2 << 20)))  # 2 MiB: over a stats report's 1 MiB
    with pytest.raises(OversizedError, match="over its limit"):
        decode_message(StatsReport, big)
    with pytest.raises(OversizedError):
        decode_message(Stop, b"\x00" * (StatsReport.MAX_BYTES + 1))  # garbage is never decoded at that size
    assert decode_message(TrajectorySegment, encode_message(segment())).env_id == 1
    assert Stop.MAX_BYTES < StatsReport.MAX_BYTES < WeightsPart.MAX_BYTES < TrajectorySegment.MAX_BYTES


def test_an_oversized_message_is_counted_as_oversized_and_malformed():
    async def scenario():
        network = MemoryNetwork()
        sender, receiver = MemoryBus(network), MemoryBus(network)
        key = keys.ctl(RUN, "gen", 0, "stop")
        sub = receiver.subscribe(key, Stop, policy="latest")
        await sender.put_bytes(key, encode_message(Stop(reason="ok")))
        await sender.put_bytes(key, b"\x81" + b"\x00" * (Stop.MAX_BYTES + 10))
        _, msg = await asyncio.wait_for(sub.next(), 5)
        assert msg.reason == "ok"
        deadline = time.monotonic() + 5
        while not receiver.oversized and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        assert receiver.oversized[key] == 1 and receiver.malformed[key] == 1
        await sender.close()
        await receiver.close()

    asyncio.run(scenario())


# --- weights ----------------------------------------------------------------------------------------------


def arrays(scale: float = 1.0) -> dict[str, np.ndarray]:
    return {"w": np.full((4, 3), scale, np.float32), "b": np.zeros(3, np.float32)}


class Receiving:
    """A WeightsReceiver fed by hand (``feed``), on an in-memory bus."""

    def __init__(self, floor: int = -1, layout: WeightsLayout | None = WeightsLayout.of(arrays())):
        self.bus = MemoryBus(MemoryNetwork())
        self.receiver = WeightsReceiver(self.bus, RUN, layout=layout, floor=floor)

    def feed(self, version: int, params: dict[str, np.ndarray]) -> Weights | None:
        payload = encode_message(Weights(version=version, params=params, created_at=time.time()))
        self.receiver._on_payload(keys.weights(RUN), payload)
        return self.receiver.take_newer(-1)

    def malformed(self) -> int:
        return sum(self.bus.malformed.values())


def test_weights_of_another_shape_or_with_a_nan_are_refused_and_change_nothing():
    async def scenario():
        r = Receiving()
        assert r.feed(1, arrays()).version == 1
        assert r.feed(2, {"w": np.zeros((4, 4), np.float32), "b": np.zeros(3, np.float32)}) is None
        assert r.feed(2, {"w": np.full((4, 3), np.nan, np.float32), "b": np.zeros(3, np.float32)}) is None
        assert r.feed(2, {"w": np.zeros((4, 3), np.float64), "b": np.zeros(3, np.float32)}) is None
        assert r.feed(2, {**arrays(), "extra": np.zeros(1, np.float32)}) is None
        assert r.malformed() == 4 and r.receiver.version == 1
        assert r.feed(2, arrays(2.0)).version == 2  # the real next version is still taken
        await r.bus.close()

    asyncio.run(scenario())


def test_a_forged_far_future_version_is_refused_and_real_updates_keep_coming():
    async def scenario():
        r = Receiving()
        assert r.feed(0, arrays()).version == 0
        assert r.feed(10**9, arrays(9.0)) is None  # the attack: generation would ignore v1, v2, ... after it
        assert r.receiver.refused == 1 and r.receiver.version == 0
        assert r.feed(1, arrays(1.0)).version == 1
        assert r.feed(1 + MAX_JUMP, arrays(1.0)).version == 1 + MAX_JUMP  # a gen that missed some versions
        await r.bus.close()

    asyncio.run(scenario())


def test_the_first_version_must_be_plausible_from_the_floor():
    async def scenario():
        resumed = Receiving(floor=5000)  # a resumed run: its checkpoint was v5000
        assert resumed.feed(5001, arrays()).version == 5001
        fresh = Receiving()
        assert fresh.feed(10**6, arrays()) is None and fresh.receiver.refused == 1
        await resumed.bus.close()
        await fresh.bus.close()

    asyncio.run(scenario())
    assert plausible(100, 0, 1.0) and not plausible(10**6, 0, 1.0) and plausible(10**6, 0, 10**4)


def test_a_version_the_taker_could_not_load_does_not_count():
    async def scenario():
        r = Receiving(layout=None)  # no layout: the loader finds out
        assert r.feed(3, arrays()).version == 3
        bad = r.feed(4, {"x": np.zeros(1, np.float32)})
        r.receiver.reject(bad, current=3)
        assert r.receiver.version == 3 and r.receiver.refused == 1
        assert r.feed(4, arrays()).version == 4  # the real v4 is not "stale"
        await r.bus.close()

    asyncio.run(scenario())


def test_a_weights_part_larger_than_the_policy_is_refused_before_any_buffer():
    async def scenario():
        r = Receiving()
        layout = r.receiver.layout
        part = WeightsPart(version=1, index=0, count=1024, part_bytes=1 << 20, total_bytes=1 << 30, created_at=1.0,
                           data=np.zeros(1 << 20, np.uint8))
        r.receiver._on_payload(keys.weights_parts(RUN), encode_message(part))
        assert r.malformed() == 1 and r.receiver._assembly is None and r.receiver._spare is None
        assert layout.total_bytes == 128  # 48 and 12 bytes, each at a 64-byte boundary
        await r.bus.close()

    asyncio.run(scenario())


# --- the launcher's view ------------------------------------------------------------------------------------


def report(service: str, instance: int, **metrics: float) -> tuple[str, StatsReport]:
    return keys.stats(RUN, service, instance), StatsReport(run=RUN, service=service, instance=instance,
                                                          time=time.time(), seq=0, metrics=metrics)


def test_the_launcher_reads_stats_only_from_the_run_s_instances_and_only_finite_values():
    view = RunView(RUN, iterations=10, instances=lambda role, instance: instance < (2 if role == "train" else 1))
    view.on_report(*report("train", 0, **{"train/policy_version": 3.0}))
    view.on_report(*report("train", 9, **{"train/policy_version": 1e6}))  # forged: the run has ranks 0 and 1
    key, forged = report("train", 0, **{"train/policy_version": 1e6})
    view.on_report(keys.stats(RUN, "train", 1), forged)  # a report on another instance's key
    view.on_report(*report("sim", 0, **{"sim/episode_return_mean": float("nan"), "sim/env_steps": 5.0}))
    assert view.version() == 3 and not view.iterations_done()
    assert view.mean_return() is None and view.metric("sim/env_steps") == 5.0
    assert view.refused == 3


# --- generation's waiting observations ------------------------------------------------------------------------


def test_generation_s_waiting_observations_stay_bounded():
    cfg = config.load(ROOT / "configs/quickstart.toml", [])
    queue = ObservationQueue(resolve(cfg), capacity=8)

    def obs(group: int, seq: int) -> Observation:
        return Observation(group=group, seq=seq, env_ids=np.arange(1), obs=np.zeros((1, 4), np.float32), sent_at=0.0)

    queue.extend([obs(0, 0), obs(0, 0), obs(1, 0)])  # group 0 sent again (a timeout): one waits
    assert len(queue) == 2 and queue.replaced == 1
    queue.extend([obs(g, 0) for g in range(100, 1100)])  # a flood of made-up groups
    assert len(queue) == 8 and queue.dropped == 994
    batch = queue.take(version=0, sim_hosts=1, max_groups=100)
    assert [m.group for m in batch] == list(range(1092, 1100)) and len(queue) == 0


def test_generation_drops_an_observation_that_does_not_fit_its_policy_and_counts_it():
    cfg = config.load(ROOT / "configs/quickstart.toml", [])
    queue = ObservationQueue(resolve(cfg), obs_shape=(4,))

    def obs(group: int, rows: np.ndarray) -> Observation:
        return Observation(group=group, seq=0, env_ids=np.arange(len(rows)), obs=rows.astype(np.float32), sent_at=0.0)

    queue.extend([obs(0, np.zeros((2, 4))), obs(1, np.zeros((2, 5))), obs(2, np.zeros((2, 4, 1))),
                  obs(3, np.array([[0.0, np.nan, 0.0, 0.0]]))])  # a wrong width, a wrong rank, a NaN
    assert [m.group for m in queue.take(version=0, sim_hosts=1, max_groups=10)] == [0]
    assert queue.counters() == {"obs_waiting_for_policy": 0, "obs_waiting_dropped": 0, "obs_dropped": 3}


def test_generation_that_went_back_from_a_forged_version_keeps_the_bound_from_where_the_sims_are():
    cfg = config.load(ROOT / "configs/quickstart.toml", [])
    schedule = resolve(cfg)
    queue = ObservationQueue(schedule, obs_shape=(4,))
    ahead = Observation(group=0, seq=70 * schedule.length(), env_ids=np.arange(1), obs=np.zeros((1, 4), np.float32),
                        sent_at=0.0)  # iteration 70: the sims ran ahead while generation acted with a forged v70
    queue.extend([ahead])
    assert queue.take(version=9, sim_hosts=1, max_groups=10) == []  # train's v9 can never reach iteration 69
    queue.went_back(70, 9)
    assert queue.take(version=9, sim_hosts=1, max_groups=10) == [ahead]
